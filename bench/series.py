"""A series over 30 minutes of a robot's odometry, every record checked (issue 35; no paper
figure): the one check path for N records against today's per-record path, measured in the
same run on the same records, for each variant of robot: `unsigned` (added by hand), `signed`
(paired, provenance v1: one SM2 signature per record, as the demo robot signed until v2) and
`v2` (paired, one signature per upload batch of 500, each header carrying its `topic_seq`,
counted per topic from 0).

- one fresh `make run` stack (bench/stack.py: granian as make run serves it, anvil with
  automine, ANCHOR_MODE=root, the chain worker and the verify-queue worker), one owner
  registered on chain with one robot per variant (the paired ones' keys confirmed on chain).
- the demo robot's odometry, for each robot: R records 0.1 s apart (10 Hz, the simulated
  robot's rate), the agent's Fig. 4 JSON of nav_msgs/Odometry (position on a circle,
  orientation, velocities, covariances: about 1 KB of plaintext), sealed under the owner's key
  (and signed as the variant signs) and stored 500 at a time through the upload service
  (record_create_batch: what the REST upload runs); then every record is awaited on chain
  (records of one batch share a Merkle tree).
- series (the figure): `GET /api/v1/records/series/?fields=position.x,position.y&points=1000`
  over the whole range with the owner's read token, S rounds one after another, each round one
  read of each variant's robot (the order turning by round); every record is checked
  (sharing.verification.opening.records_open: batches of VERIFY_BATCH sent at once to the
  workers, one rootOf per tree, each distinct robot signature verified once, the verdicts in
  bulk INSERTs), then read and downsampled. p50 and p95 of the answer time, and the CPU of the
  web processes and of the workers (the chain worker's pool and the verify worker, both of
  which take verify tasks) per record checked.
- per record (the baseline path, today's for every record that is not in a batch): P records
  of each robot spread evenly over the range, each read once through
  `GET /api/v1/records/{id}/content/`, one after another: one task, one verdict, one chain read
  per record. Its time for the whole range is P's median times R (the sample keeps the run
  short; every view is the same work), and its CPU per record is measured over the sample.

- baseline (issue 45): today's code, the commit this branch starts from on main (`--baseline`,
  by default `git merge-base HEAD main`), measured by its own bench/series.py in a worktree of
  that commit, in the same run just before, with the same records, rounds and variants: each
  series row gets its p50 and CPU over the baseline's.

Ratios: series over per record of the same variant, each variant over unsigned on the same
path, and series over the baseline's series. The goals (issue 45): p50 at most 1 s for 18,000
records (30 minutes), at most 8 s for 216,000 (6 hours), on the 2-core machine. Figures, not
assertions: other work on the machine shows in the load averages and in `others_cpu_share`.

Run: `python -m bench series [--records 18000] [--variants unsigned,signed,v2] [--baseline REF]
[--quick]`.
Writes bench/results/series.json, series.csv and series.png.
"""

import argparse
import json
import math
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, replace
from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import Any

import psutil
import requests

from bench import MAKE_RUN_ANCHOR_MAX_WAIT, RESULTS_DIR, now_iso, run_in_child, summarize
from bench.common import print_table, seal_batch, write_results
from bench.plotting import machine_line, plt, save_figure
from bench.rest import BENCH_REDIS_URL, report_header
from bench.roots import view_times, viewer_token
from bench.stack import BenchStack, StackOptions, owners_register, robot_paired, run_finished

NAME = "series"
VARIANTS = ("unsigned", "signed", "v2")  # the first is the baseline of the variants' ratios
# Issue 45: 30 minutes (18,000 records at 10 Hz) in a second, 6 hours (216,000) in 8 s.
GOALS_P50_S = ((18_000, 1.0), (216_000, 8.0))
PER_POST = 500
RATE_HZ = 10.0  # the simulated robot's odometry rate
TOPIC = "/odom"
FIELDS = (
    "variant",
    "path",
    "records",
    "p50_s",
    "p95_s",
    "mean_s",
    "web_cpu_ms_per_record",
    "workers_cpu_ms_per_record",
    "others_cpu_share",
    "p50_ratio_vs_per_record",
    "web_cpu_ratio_vs_per_record",
    "workers_cpu_ratio_vs_per_record",
    "p50_ratio_vs_unsigned",
    "web_cpu_ratio_vs_unsigned",
    "workers_cpu_ratio_vs_unsigned",
    "p50_ratio_vs_baseline",
    "web_cpu_ratio_vs_baseline",
    "workers_cpu_ratio_vs_baseline",
)
COLUMNS = (
    ("variant", "variant", ""),
    ("path", "path", ""),
    ("records", "records", "d"),
    ("p50 s", "p50_s", ".2f"),
    ("p95 s", "p95_s", ".2f"),
    ("web ms/rec", "web_cpu_ms_per_record", ".3f"),
    ("workers ms/rec", "workers_cpu_ms_per_record", ".3f"),
    ("others", "others_cpu_share", ".2f"),
    ("x p50", "p50_ratio_vs_per_record", ".3f"),
    ("x unsigned", "p50_ratio_vs_unsigned", ".2f"),
    ("x baseline", "p50_ratio_vs_baseline", ".3f"),
)


@dataclass(frozen=True)
class SeriesRun:
    records: int
    series_rounds: int
    per_record_sample: int
    workers: int
    web_workers: int
    redis_url: str
    keep_logs: bool
    block_time: float | None = None
    batch_max: int = 100
    max_wait: float = MAKE_RUN_ANCHOR_MAX_WAIT
    variants: tuple[str, ...] = VARIANTS
    scale: tuple[int, ...] = ()  # series reads over the first N records too (how cost grows)
    first_plots: bool = False  # the record and robot pages' first plot, in Chromium

    def describe(self) -> str:
        return (
            f"series of {self.records} odometry records of each of {', '.join(self.variants)} "
            f"({self.series_rounds} reads each) against {self.per_record_sample} reads one "
            "record at a time"
        )


def odometry_plaintext(owner: str, index: int, at: datetime) -> bytes:
    """The agent's Fig. 4 record of nav_msgs/Odometry, on a circle of 5 m, 1 KB or so."""
    angle = index / (RATE_HZ * 60) * 2 * math.pi  # one lap a minute
    record = {
        "K": {
            "header": {
                "seq": index,
                "stamp": {"secs": int(at.timestamp()), "nsecs": at.microsecond * 1000},
                "frame_id": "odom",
            },
            "child_frame_id": "base_link",
            "position": {"x": 5 * math.cos(angle), "y": 5 * math.sin(angle), "z": 0.0},
            "orientation": {
                "x": 0.0,
                "y": 0.0,
                "z": math.sin((angle + math.pi / 2) / 2),
                "w": math.cos((angle + math.pi / 2) / 2),
            },
            "linear_velocity": {"x": 0.52, "y": 0.0, "z": 0.0},
            "angular_velocity": {"x": 0.0, "y": 0.0, "z": 0.105},
            "pose_covariance": [0.001] * 36,
            "twist_covariance": [0.001] * 36,
        },
        "Owner": owner,
        "Time": at.isoformat().replace("+00:00", "Z"),
        "Type": "nav_msgs/Odometry",
        "Topic": TOPIC,
    }
    return json.dumps(record, separators=(",", ":")).encode()


def _series_start(run: SeriesRun) -> datetime:
    """The first capture time: R records 0.1 s apart end a minute ago."""
    return datetime.now(tz=UTC).replace(microsecond=0) - timedelta(
        seconds=run.records / RATE_HZ + 60
    )


def _odometry_batches(
    run: SeriesRun, robot: Any, start: datetime
) -> Iterator[list[tuple[dict[str, Any], bytes]]]:
    """R odometry records 0.1 s apart from `start`, PER_POST at a time: (header, plaintext)."""
    owner = robot.owner.username
    for first in range(0, run.records, PER_POST):
        batch = []
        for index in range(first, min(first + PER_POST, run.records)):
            at = start + timedelta(seconds=index / RATE_HZ)
            header = {
                "owner": owner,
                "robot": str(robot.pk),
                "topic": TOPIC,
                "type": "nav_msgs/Odometry",
                "seq": index + 1,
                "time": at.isoformat().replace("+00:00", "Z"),
            }
            batch.append((header, odometry_plaintext(owner, index, at)))
        yield batch


def _await_anchored(stack: BenchStack, run: SeriesRun, robot: Any) -> None:
    from sharing.models import Record

    def anchored() -> bool:
        return (
            Record.objects.filter(robot=robot, status=Record.Status.ANCHORED).count() == run.records
        )

    stack.wait_for(anchored, "records not anchored", timeout=900)


def _store(
    run: SeriesRun, robot: Any, key: bytes, signing_key: Any, variant: str, start: datetime
) -> None:
    """R odometry records 0.1 s apart from `start`, sealed as the variant's agent seals them
    (unsigned, signed one by one, or signed once per batch with topic_seq from 0) and stored
    PER_POST at a time through the upload service (record_create_batch: what the REST upload
    runs)."""
    from ros_agent import sealing
    from sharing.services.uploads import record_create_batch

    topic_seq = 0
    for batch in _odometry_batches(run, robot, start):
        if variant == "v2":
            envelopes = seal_batch(key, batch, signing_key, first_topic_seq=topic_seq)
            topic_seq += len(batch)
        else:
            envelopes = [
                sealing.seal_record(key, header, plaintext, signing_key)
                for header, plaintext in batch
            ]
        record_create_batch(robot=robot, envelopes=envelopes)


class _Cpu:
    """CPU seconds of the stack's web and workers, and of the whole machine, over a phase."""

    def __init__(self, stack: BenchStack) -> None:
        self.stack = stack
        self.mine = psutil.Process()

    def take(self) -> dict[str, float]:
        used = self.stack.cpu_seconds()
        machine = psutil.cpu_times()
        own = self.mine.cpu_times()
        return {
            "web": used.get("web", 0.0),
            "workers": used.get("workers", 0.0),
            "stack": sum(used.values()),
            "bench": own.user + own.system,
            "machine": machine.user + machine.system + getattr(machine, "nice", 0.0),
            "wall": time.monotonic(),
        }

    @staticmethod
    def spent(before: dict[str, float], after: dict[str, float]) -> dict[str, float]:
        delta = {key: after[key] - before[key] for key in before}
        others = delta["machine"] - delta["stack"] - delta["bench"]
        delta["others_share"] = max(others, 0.0) / (delta["wall"] * psutil.cpu_count())
        return delta


def measure(run: SeriesRun) -> dict[str, Any]:
    """One stack: each variant's robot and records, then the series reads (the variants in
    turn each round) and each variant's per-record reads."""
    stack = BenchStack(
        StackOptions(
            block_time=None,
            batch_max=run.batch_max,
            workers=run.workers,
            max_wait=run.max_wait,
            redis_url=run.redis_url,
            web_workers=run.web_workers,
            anchor_mode="root",
        ),
        Path(tempfile.mkdtemp(prefix="authros-bench-series-")),
    )
    found: dict[str, Any] = {}
    try:
        stack.start()
        from accounts.services.robots import robot_create
        from sharing.models import Record

        ((hand_robot, key),) = owners_register(stack, 1)
        owner = hand_robot.owner
        robots: dict[str, Any] = {}
        start = _series_start(run)
        for variant in run.variants:
            print(f"== {run.records} records, {variant}", file=sys.stderr, flush=True)
            stored = time.perf_counter()
            if variant == "unsigned":
                robot, _token = robot_create(owner=owner, name="odometry-unsigned")
                signing_key = None
            else:
                robot, signing_key = robot_paired(stack, owner, f"odometry-{variant}")
            _store(run, robot, key, signing_key, variant, start)
            _await_anchored(stack, run, robot)
            robots[variant] = robot
            found[variant] = {"upload_and_anchor_s": time.perf_counter() - stored}
        until = start + timedelta(seconds=run.records / RATE_HZ)
        token = viewer_token(owner)
        cpu = _Cpu(stack)
        series = _series_reads(stack, run, cpu, robots, token, start, until)
        scale = {
            count: _series_reads(
                stack, run, cpu, robots, token, start, start + timedelta(seconds=count / RATE_HZ)
            )
            for count in run.scale
        }
        plots = _first_plots(stack, run, owner, key) if run.first_plots else {}
        for variant, robot in robots.items():
            ids = list(
                Record.objects.filter(robot=robot)
                .order_by("captured_at")
                .values_list("pk", flat=True)
            )
            step = max(len(ids) // run.per_record_sample, 1)
            sample = [str(pk) for pk in ids[::step][: run.per_record_sample]]
            found[variant] |= {
                "series": series[variant],
                "scale": {str(count): reads[variant] for count, reads in scale.items()},
                "first_plots": plots.get(variant, {}),
                "per_record": _per_record_reads(stack, run, cpu, token, sample),
                "trees": Record.objects.filter(robot=robot)
                .values("anchor_root")
                .distinct()
                .count(),
            }
    finally:
        stack.stop()
    return run_finished({"variants": found}, stack, keep_logs=run.keep_logs)


def series_orders(rounds: int, variants: Sequence[str]) -> Iterator[tuple[str, ...]]:
    """The variants' order in each round of series reads, turned by one each round, so that
    none always reads first (on a cooler machine) or last."""
    for number in range(rounds):
        turn = number % len(variants)
        yield (*variants[turn:], *variants[:turn])


def _series_reads(
    stack: BenchStack,
    run: SeriesRun,
    cpu: _Cpu,
    robots: dict[str, Any],
    token: str,
    since: datetime,
    until: datetime,
) -> dict[str, dict[str, Any]]:
    """run.series_rounds rounds of one series read of each robot, one after another: per
    variant the answer times, what each answer counted, and the CPU per record checked over
    its own reads."""
    session = requests.Session()
    session.headers["Authorization"] = f"Token {token}"
    times: dict[str, list[float]] = {variant: [] for variant in robots}
    answers: dict[str, list[dict[str, Any]]] = {variant: [] for variant in robots}
    spent: dict[str, dict[str, float]] = {}
    for order in series_orders(run.series_rounds, list(robots)):
        for variant in order:
            query = {
                "robot": str(robots[variant].pk),
                "topic": TOPIC,
                "fields": "position.x,position.y",
                "since": since.isoformat(),
                "until": until.isoformat(),
                "points": "1000",
            }
            before = cpu.take()
            sent = time.perf_counter()
            answer = session.get(
                f"{stack.web_url}/api/v1/records/series/", params=query, timeout=600
            )
            times[variant].append(time.perf_counter() - sent)
            delta = cpu.spent(before, cpu.take())
            total = spent.setdefault(variant, dict.fromkeys(delta, 0.0))
            for name, value in delta.items():
                total[name] += value
            answer.raise_for_status()
            body = answer.json()
            answers[variant].append(
                {key: body[key] for key in ("source_records", "verified", "refused")}
                | {"points": len(body["points"])}
            )
    session.close()
    found = {}
    for variant in robots:
        checked = sum(answer["source_records"] for answer in answers[variant])
        used = spent[variant]
        found[variant] = {
            "seconds": times[variant],
            "answers": answers[variant],
            "records_checked": checked,
            "web_cpu_ms_per_record": used["web"] * 1000 / checked,
            "workers_cpu_ms_per_record": used["workers"] * 1000 / checked,
            # the machine's cores over the reads' wall time, less the stack's and ours
            "others_cpu_share": max(used["machine"] - used["stack"] - used["bench"], 0.0)
            / (used["wall"] * psutil.cpu_count()),
        }
    return found


# Debian's Chromium, as the browser tests run it; nothing leaves the machine.
CHROMIUM = "/usr/bin/chromium"
CHROMIUM_ARGS = [
    "--no-sandbox",
    "--disable-gpu",
    "--no-first-run",
    "--disable-background-networking",
]
FIRST_PLOTS = (
    # (path, the page's plot): the robot page plots its last 10 minutes, the record page the
    # 5 minutes either side of a record in the middle of the range.
    ("first plot, robot page", "robot-plot"),
    ("first plot, record page", "trajectory-plot"),
)


# Where a first plot's time went, from the browser's own timings (ms from asking for the
# page): the page's HTML in, its scripts run (DOMContentLoaded), and the series answer asked
# for and in (the plot is drawn after it).
_PAGE_TIMINGS = """() => {
  const page = performance.getEntriesByType("navigation")[0];
  const series = performance.getEntriesByType("resource")
    .filter((entry) => entry.name.includes("/records/series/"));
  return {
    html: page.responseEnd,
    scripts_run: page.domContentLoadedEventEnd,
    series_asked: series.length ? series[0].startTime : null,
    series_in: series.length ? series[0].responseEnd : null,
    drawn: window.__plotReadyAt || null,
  };
}"""
# When the plot's data-state first became "ready", kept by the page itself (a locator's wait
# in Playwright only sees it some milliseconds later).
_PLOT_READY_AT = """new MutationObserver((changes, observer) => {
  for (const change of changes) {
    if (change.target.dataset && change.target.dataset.state === "ready") {
      window.__plotReadyAt = performance.now();
      observer.disconnect();
      return;
    }
  }
}).observe(document, { attributes: true, attributeFilter: ["data-state"], subtree: true });"""
PLOT_RECORDS = 6_000  # the pages' windows at 10 Hz: the robot page's last 10 minutes


def _first_plots(
    stack: BenchStack, run: SeriesRun, owner: Any, key: bytes
) -> dict[str, dict[str, Any]]:
    """Each page's first plot as an owner sees it, run.series_rounds times: logged in, in a
    fresh browser context (no cache), from asking for the page to its plot drawn
    (`data-state` "ready": every record of its window checked); what it checked. The pages'
    robot is one more v2 robot whose PLOT_RECORDS end as they are stored, so that the robot
    page's window of the last 10 minutes is full when it is drawn (the series robots' records
    are minutes older by then)."""
    import secrets

    from playwright.sync_api import sync_playwright

    from sharing.models import Record

    plots = replace(run, records=PLOT_RECORDS)
    robot, signing_key = robot_paired(stack, owner, "odometry-pages")
    start = datetime.now(tz=UTC).replace(microsecond=0) - timedelta(seconds=PLOT_RECORDS / RATE_HZ)
    _store(plots, robot, key, signing_key, "v2", start)
    _await_anchored(stack, plots, robot)

    password = secrets.token_urlsafe(18)
    owner.user.set_password(password)
    owner.user.save(update_fields=["password"])
    # The ORM's reads before Playwright's loop runs in this thread.
    ids = list(
        Record.objects.filter(robot=robot).order_by("captured_at").values_list("pk", flat=True)
    )
    pages = {
        "robot-plot": f"{stack.web_url}/robots/{robot.pk}/",
        "trajectory-plot": f"{stack.web_url}/records/{ids[len(ids) // 2]}/",
    }
    found: dict[str, Any] = {}
    with sync_playwright() as playwright:
        browser = playwright.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
        try:
            for path, plot in FIRST_PLOTS:
                seconds, verified, parts = [], [], []
                for _ in range(run.series_rounds):
                    context = browser.new_context(viewport={"width": 1280, "height": 900})
                    context.add_init_script(_PLOT_READY_AT)
                    page = context.new_page()
                    page.goto(f"{stack.web_url}/login/")
                    page.fill("#id_username", owner.user.username)
                    page.fill("#id_password", password)
                    page.click("#login-submit")
                    page.wait_for_url("**/dashboard/")
                    sent = time.perf_counter()
                    page.goto(pages[plot])
                    ready = page.locator(f"[data-testid={plot}][data-state=ready]")
                    ready.wait_for(timeout=600_000)
                    seconds.append(time.perf_counter() - sent)
                    verified.append(int(ready.get_attribute("data-verified") or 0))
                    parts.append(page.evaluate(_PAGE_TIMINGS))
                    context.close()
                found[path] = {"seconds": seconds, "verified": verified, "timings_ms": parts}
        finally:
            browser.close()
    return {"v2": found}  # the pages' robot is a v2 robot: its rows go with v2's


def _per_record_reads(
    stack: BenchStack, run: SeriesRun, cpu: _Cpu, token: str, sample: list[str]
) -> dict[str, Any]:
    before = cpu.take()
    times_ms, failed = view_times(stack.web_url, token, sample)
    spent = cpu.spent(before, cpu.take())
    return {
        "seconds": [ms / 1000 for ms in times_ms],
        "failed": len(failed),
        "records_checked": len(sample),
        "web_cpu_ms_per_record": spent["web"] * 1000 / len(sample),
        "workers_cpu_ms_per_record": spent["workers"] * 1000 / len(sample),
        "others_cpu_share": spent["others_share"],
    }


def _rows(measured: dict[str, Any], run: SeriesRun) -> list[dict[str, Any]]:
    """Per variant a per-record row and a series row, with their ratios: series over per
    record of the variant, and each row over unsigned's row of the same path."""
    rows = []
    for variant, found in measured["variants"].items():
        series, single = found["series"], found["per_record"]
        stats = summarize(series["seconds"])  # seconds in, the same unit out
        baseline = {
            "variant": variant,
            "path": "per record",
            "records": run.records,
            # Every view is the same work: the whole range at the sample's p50 per record.
            "p50_s": statistics.median(single["seconds"]) * run.records,
            "p95_s": None,
            "mean_s": statistics.mean(single["seconds"]) * run.records,
            "web_cpu_ms_per_record": single["web_cpu_ms_per_record"],
            "workers_cpu_ms_per_record": single["workers_cpu_ms_per_record"],
            "others_cpu_share": single["others_cpu_share"],
            "sample": single["records_checked"],
            "sample_p50_ms": statistics.median(single["seconds"]) * 1000,
            "failed": single["failed"],
        }
        row = {
            "variant": variant,
            "path": "series",
            "records": run.records,
            "p50_s": stats["median_ms"],
            "p95_s": stats["p95_ms"],
            "mean_s": stats["mean_ms"],
            "web_cpu_ms_per_record": series["web_cpu_ms_per_record"],
            "workers_cpu_ms_per_record": series["workers_cpu_ms_per_record"],
            "others_cpu_share": series["others_cpu_share"],
            "answers": series["answers"],
            "rounds": len(series["seconds"]),
            "trees": found["trees"],
            "upload_and_anchor_s": found["upload_and_anchor_s"],
        }
        for key, source in RATIO_SOURCES.items():
            row[f"{key}_ratio_vs_per_record"] = _ratio(row[source], baseline[source])
            baseline[f"{key}_ratio_vs_per_record"] = 1.0
        rows += [baseline, row]
        for count, reads in found.get("scale", {}).items():
            part = summarize(reads["seconds"])
            rows.append(
                {
                    "variant": variant,
                    "path": "series, first records",
                    "records": int(count),
                    "p50_s": part["median_ms"],
                    "p95_s": part["p95_ms"],
                    "mean_s": part["mean_ms"],
                    "web_cpu_ms_per_record": reads["web_cpu_ms_per_record"],
                    "workers_cpu_ms_per_record": reads["workers_cpu_ms_per_record"],
                    "others_cpu_share": reads["others_cpu_share"],
                    "answers": reads["answers"],
                }
            )
        for path, plots in found.get("first_plots", {}).items():
            drawn = summarize(plots["seconds"])
            rows.append(
                {
                    "variant": variant,
                    "path": path,
                    "records": max(plots["verified"]),
                    "p50_s": drawn["median_ms"],
                    "p95_s": drawn["p95_ms"],
                    "mean_s": drawn["mean_ms"],
                    "verified": plots["verified"],
                    "rounds": len(plots["seconds"]),
                    # the median of each of the browser's timings, ms from asking for the page
                    "timings_ms": {
                        name: statistics.median(
                            [part[name] for part in plots.get("timings_ms", []) if part.get(name)]
                            or [0.0]
                        )
                        for name in ("html", "scripts_run", "series_asked", "series_in", "drawn")
                    },
                }
            )
    ratios_vs_unsigned(rows)
    return rows


RATIO_SOURCES = {
    "p50": "p50_s",
    "web_cpu": "web_cpu_ms_per_record",
    "workers_cpu": "workers_cpu_ms_per_record",
}


def ratios_vs_unsigned(rows: list[dict[str, Any]]) -> None:
    """Each row's figures over the unsigned row of its path, as "<key>_ratio_vs_unsigned"
    (None without an unsigned row)."""
    unsigned = {row["path"]: row for row in rows if row["variant"] == "unsigned"}
    for row in rows:
        base = unsigned.get(row["path"])
        for key, source in RATIO_SOURCES.items():
            row[f"{key}_ratio_vs_unsigned"] = (
                _ratio(row.get(source), base.get(source)) if base is not None else None
            )


def ratios_vs_baseline(rows: list[dict[str, Any]], baseline: list[dict[str, Any]]) -> None:
    """Each row's figures over the baseline's row of the same variant and path, as
    "<key>_ratio_vs_baseline" (None where the baseline has no such row)."""
    base = {(row["variant"], row["path"], row["records"]): row for row in baseline}
    for row in rows:
        other = base.get((row["variant"], row["path"], row["records"]))
        for key, source in RATIO_SOURCES.items():
            row[f"{key}_ratio_vs_baseline"] = (
                _ratio(row.get(source), other.get(source)) if other is not None else None
            )


def goal_p50_s(records: int) -> float:
    """Issue 45's goal for a series of this many records: the first of GOALS_P50_S that
    covers it (the last beyond)."""
    return next((goal for most, goal in GOALS_P50_S if records <= most), GOALS_P50_S[-1][1])


REPO = Path(__file__).resolve().parents[1]


def baseline_measure(ref: str, run: SeriesRun, workers: int) -> dict[str, Any]:
    """The same run measured by the bench/series.py of commit `ref` ("merge-base": where this
    branch left main) in a worktree of it, its stack started from that tree: its series.json,
    with the commit."""
    if ref == "merge-base":
        ref = _git("merge-base", "HEAD", "main")
    commit = _git("rev-parse", "--verify", f"{ref}^{{commit}}")
    place = Path(tempfile.mkdtemp(prefix="authros-bench-baseline-"))
    tree, results = place / "tree", place / "results"
    _git("worktree", "add", "--detach", str(tree), commit)
    for shared in (".venv", "node_modules"):  # not in git: the stack needs both (anvil)
        if (REPO / shared).exists():
            (tree / shared).symlink_to((REPO / shared).resolve())
    try:
        subprocess.run(
            [
                sys.executable, "-m", "bench", "series",
                "--records", str(run.records),
                "--rounds", str(run.series_rounds),
                "--sample", str(run.per_record_sample),
                "--variants", ",".join(run.variants),
                "--workers", str(workers),
                "--web-workers", str(run.web_workers),
                "--redis-url", run.redis_url,
                "--results-dir", str(results),
                "--baseline", "",  # its own default is its merge base: it would recurse
            ],
            cwd=tree,
            check=True,
        )  # fmt: skip
        found = json.loads((results / f"{NAME}.json").read_text())
    finally:
        _git("worktree", "remove", "--force", str(tree))
        shutil.rmtree(place, ignore_errors=True)
    return found | {"commit": commit}


def _git(*args: str) -> str:
    return subprocess.run(
        ["git", "-C", str(REPO), *args], check=True, capture_output=True, text=True
    ).stdout.strip()


def _ratio(value: float | None, baseline: float | None) -> float | None:
    return value / baseline if value is not None and baseline else None


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench series", description=__doc__)
    parser.add_argument("--records", type=int, default=18_000, help="30 min at 10 Hz (18,000)")
    parser.add_argument("--rounds", type=int, default=5, help="series reads of each (default 5)")
    parser.add_argument(
        "--sample", type=int, default=300, help="records read one at a time, each (default 300)"
    )
    parser.add_argument(
        "--variants",
        default=",".join(VARIANTS),
        help=f"robots to measure, comma-separated, of {', '.join(VARIANTS)} (all)",
    )
    parser.add_argument(
        "--baseline",
        default="merge-base",
        help="commit measured first by its own bench, the same way (default: the branch's "
        "merge base with main; '' for none)",
    )
    parser.add_argument(
        "--scale",
        default="",
        help="series reads over the first N records too, comma-separated counts below "
        "--records (how the cost grows; default none)",
    )
    parser.add_argument(
        "--first-plots",
        action="store_true",
        help="also time the record and robot pages' first plot in Chromium",
    )
    parser.add_argument("--workers", type=int, default=2, help="chain worker pool processes")
    parser.add_argument("--web-workers", type=int, default=0, help="0: as make run sizes it")
    parser.add_argument("--redis-url", default=BENCH_REDIS_URL)
    parser.add_argument("--results-dir", type=Path, default=RESULTS_DIR)
    parser.add_argument("--keep-logs", action="store_true")
    parser.add_argument("--quick", action="store_true", help="smoke run with small numbers")
    args = parser.parse_args(argv)
    variants = tuple(dict.fromkeys(name.strip() for name in args.variants.split(",") if name))
    if not variants or set(variants) - set(VARIANTS):
        parser.error(f"--variants takes names of {', '.join(VARIANTS)}")
    if args.quick:
        args.records, args.rounds, args.sample = 1_000, 2, 30
    if min(args.records, args.rounds, args.sample) < 1:
        parser.error("--records, --rounds and --sample must be at least 1")
    try:
        scale = tuple(sorted({int(count) for count in args.scale.split(",") if count.strip()}))
    except ValueError:
        parser.error("--scale takes record counts, comma-separated")
    if args.first_plots and "v2" not in variants:
        parser.error("--first-plots draws a v2 robot's pages: --variants must hold v2")
    if any(not 0 < count < args.records for count in scale):
        parser.error("--scale's counts must be between 0 and --records")
    run = SeriesRun(
        records=args.records,
        series_rounds=args.rounds,
        per_record_sample=args.sample,
        workers=args.workers,
        web_workers=args.web_workers,
        redis_url=args.redis_url,
        keep_logs=args.keep_logs,
        variants=tuple(variant for variant in VARIANTS if variant in variants),
        scale=scale,
        first_plots=args.first_plots,
    )
    started = now_iso()
    report = report_header(
        NAME,
        argparse.Namespace(
            owners=1,
            workers=args.workers,
            web_workers=args.web_workers,
            verifiers=1,
            max_wait=MAKE_RUN_ANCHOR_MAX_WAIT,
            timeout=900.0,
            quick=args.quick,
        ),
        started,
    )
    baseline = None
    if args.baseline:
        print(f"== baseline: {args.baseline} ({run.describe()})", file=sys.stderr, flush=True)
        baseline = baseline_measure(args.baseline, run, args.workers)
    print(f"== {run.describe()}", file=sys.stderr, flush=True)
    measured = run_in_child(measure, run)
    from smcrypto import sm2

    report["settings"] |= {
        "records": run.records,
        "rate_hz": RATE_HZ,
        "series_rounds": run.series_rounds,
        "per_record_sample": run.per_record_sample,
        "fields": "position.x,position.y",
        "points": 1000,
        "per_post": PER_POST,
        "anchor_mode": "root",
        "chain": "anvil, automine",
        "variants": list(run.variants),
        "scale": list(run.scale),
        "first_plots": run.first_plots,
        "sm2_backend": sm2.BACKEND,
    }
    report["goal_p50_s"] = goal_p50_s(run.records)
    report["measured"] = measured
    report["results"] = _rows(measured, run)
    if baseline is not None:
        report["baseline"] = {
            key: baseline.get(key)
            for key in ("commit", "date", "load_average_at_start", "load_average_at_end")
        } | {"results": baseline["results"]}
        ratios_vs_baseline(report["results"], baseline["results"])
    report["load_average_at_end"] = [round(load, 2) for load in psutil.getloadavg()]
    report["goal_met"] = {
        row["variant"]: row["p50_s"] <= report["goal_p50_s"]
        for row in report["results"]
        if row["path"] == "series"
    }
    print_table(report, COLUMNS)
    write_results(NAME, report, FIELDS, args.results_dir, plot=_plot)
    return 0


_BARS = ("per record", "series")  # the paths of the bar charts, in their order


def _plot(report: dict[str, Any], path: Path) -> None:
    rows = report["results"]
    variants = list(dict.fromkeys(row["variant"] for row in rows))
    by = {(row["variant"], row["path"]): row for row in rows if row["path"] in _BARS}
    grows = [row for row in rows if row["path"] in ("series", "series, first records")]
    plots = [row for row in rows if row["path"].startswith("first plot")]
    panels = 2 + bool(len(grows) > len(variants) or plots)
    figure, axes = plt.subplots(1, panels, figsize=(5.5 * panels, 3.8))
    left, right = axes[0], axes[1]
    if panels == 3:
        _plot_growth(axes[2], report, grows, plots)
    width = 0.38
    for offset, path_name, color in (
        (-width / 2, "per record", "#8c959f"),
        (width / 2, "series", "#0969da"),
    ):
        left.bar(
            [x + offset for x in range(len(variants))],
            [by[(variant, path_name)]["p50_s"] for variant in variants],
            width=width,
            color=color,
            label="per record (sample x N)" if path_name == "per record" else "series",
        )
    base = {
        row["variant"]: row
        for row in report.get("baseline", {}).get("results", [])
        if row["path"] == "series"
    }
    left.scatter(
        [x + width / 2 for x, variant in enumerate(variants) if variant in base],
        [base[variant]["p50_s"] for variant in variants if variant in base],
        marker="_", s=400, color="#cf222e", zorder=3, label="series, baseline (main)",
    )  # fmt: skip
    goal = report["goal_p50_s"]
    left.axhline(goal, color="#cf222e", linestyle="--", linewidth=1)
    left.text(
        len(variants) - 0.5, goal, f" goal {goal:g} s", va="bottom", fontsize=8, color="#cf222e",
    )  # fmt: skip
    left.set_xticks(range(len(variants)), variants)
    left.set_yscale("log")
    left.set_ylim(top=max(row["p50_s"] for row in by.values()) * 10)  # room for the legend
    left.set_ylabel(f"p50 seconds for {report['settings']['records']:,} records (log)")
    left.legend(fontsize=7, loc="upper left")
    bars = [(variant, path_name) for variant in variants for path_name in _BARS]
    labels = [f"{variant}\n{path_name}" for variant, path_name in bars]
    for offset, key, label in (
        (-width / 2, "web_cpu_ms_per_record", "web"),
        (width / 2, "workers_cpu_ms_per_record", "workers"),
    ):
        right.bar(
            [x + offset for x in range(len(bars))],
            [by[bar][key] for bar in bars],
            width=width,
            label=label,
        )
    right.set_xticks(range(len(bars)), labels, fontsize=7)
    right.set_yscale("log")
    right.set_ylabel("CPU ms per record checked (log)")
    right.legend(fontsize=8)
    backend = report.get("settings", {}).get("sm2_backend")
    save_figure(
        figure,
        path,
        f"A series of {report['settings']['records']:,} odometry records of each robot, every "
        "one checked, against one check per record"
        + (f" (SM2: {backend})" if backend else "")
        + f"\n{machine_line(report)}",
    )


def _plot_growth(
    axis: Any, report: dict[str, Any], grows: list[dict[str, Any]], plots: list[dict[str, Any]]
) -> None:
    """A series' p50 against the records it checks, per variant (the baseline's, and the
    goals, marked), and the pages' first plots at the records they checked."""
    for variant in dict.fromkeys(row["variant"] for row in grows):
        points = sorted(
            (row["records"], row["p50_s"]) for row in grows if row["variant"] == variant
        )
        axis.plot(*zip(*points, strict=True), marker="o", label=f"series, {variant}")
    for row in report.get("baseline", {}).get("results", []):
        if row["path"] == "series":
            axis.scatter(row["records"], row["p50_s"], marker="_", s=300, color="#cf222e")
    for records, goal in GOALS_P50_S:
        axis.scatter(records, goal, marker="*", s=80, color="#cf222e")
    for row in plots:
        axis.scatter(
            row["records"], row["p50_s"], marker="s", label=f"{row['path']}, {row['variant']}"
        )
    axis.set_xscale("log")
    axis.set_yscale("log")
    axis.set_xlabel("records checked (log)")
    axis.set_ylabel("p50 seconds (log); red: baseline, stars: goals")
    axis.legend(fontsize=7, loc="upper left")

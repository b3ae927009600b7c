"""A series over 30 minutes of a robot's odometry, every record checked (issue 35; no paper
figure): the one check path for N records against today's per-record path, measured in the
same run on the same records.

- one fresh `make run` stack (bench/stack.py: granian as make run serves it, anvil with
  automine, ANCHOR_MODE=root, the chain worker and the verify-queue worker), one owner
  registered on chain with one robot added by hand.
- the demo robot's odometry: R records 0.1 s apart (10 Hz, the simulated robot's rate), the
  agent's Fig. 4 JSON of nav_msgs/Odometry (position on a circle, orientation, velocities,
  covariances: about 1 KB of plaintext), sealed under the owner's key and POSTed 500 at a time;
  then every record is awaited on chain (records of one batch share a Merkle tree).
- series (the figure): `GET /api/v1/records/series/?fields=position.x,position.y&points=1000`
  over the whole range with the owner's read token, S times one after another; every record is
  checked (sharing.verification.opening.records_open: batches of VERIFY_BATCH sent at once to the
  workers, one rootOf per tree, the verdicts in bulk INSERTs), then read and downsampled. p50
  and p95 of the answer time, and the CPU of the web processes and of the workers (the chain
  worker's pool and the verify worker, both of which take verify tasks) per record checked.
- per record (the baseline, today's path for every record that is not in a batch): P records
  spread evenly over the range, each read once through `GET /api/v1/records/{id}/content/`, one
  after another: one task, one verdict, one chain read per record. Its time for the whole
  range is P's mean times R (the sample keeps the run short; every view is the same work), and
  its CPU per record is measured over the sample.

Ratios are series over per record. The goal (issue 35): p50 at most 2 s for 18,000 records on
the 2-core machine. Figures, not assertions: other work on the machine shows in the load
averages and in `others_cpu_share`.

Run: `python -m bench series [--records 18000] [--quick]`. Writes bench/results/series.json,
series.csv and series.png.
"""

import argparse
import base64
import json
import math
import statistics
import sys
import tempfile
import time
from collections.abc import Iterator
from dataclasses import dataclass
from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import Any

import psutil
import requests

from bench import MAKE_RUN_ANCHOR_MAX_WAIT, RESULTS_DIR, now_iso, run_in_child, summarize
from bench.common import print_table, write_results
from bench.plotting import machine_line, plt, save_figure
from bench.rest import BENCH_REDIS_URL, report_header
from bench.roots import view_times, viewer_token
from bench.stack import BenchStack, StackOptions, owners_register, run_finished

NAME = "series"
GOAL_P50_S = 2.0
PER_POST = 500
RATE_HZ = 10.0  # the simulated robot's odometry rate
TOPIC = "/odom"
FIELDS = (
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
)
COLUMNS = (
    ("path", "path", ""),
    ("records", "records", "d"),
    ("p50 s", "p50_s", ".2f"),
    ("p95 s", "p95_s", ".2f"),
    ("web ms/rec", "web_cpu_ms_per_record", ".3f"),
    ("workers ms/rec", "workers_cpu_ms_per_record", ".3f"),
    ("others", "others_cpu_share", ".2f"),
    ("x p50", "p50_ratio_vs_per_record", ".3f"),
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
    signed: bool = True  # a paired robot's records, as the demo robot's (else added by hand)

    def describe(self) -> str:
        signed = "signed by a paired robot" if self.signed else "of a robot added by hand"
        return (
            f"series of {self.records} odometry records {signed} ({self.series_rounds} reads) "
            f"against {self.per_record_sample} reads one record at a time"
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


def _store_signed(
    stack: BenchStack, run: SeriesRun, robot: Any, key: bytes, signing_key: Any
) -> datetime:
    """R odometry records 0.1 s apart, sealed and signed as the paired robot's agent does and
    stored PER_POST at a time through the upload service (record_create_batch: what the REST
    upload runs), every one awaited on chain. The capture time of the first."""
    from ros_agent import sealing
    from sharing.services.uploads import record_create_batch

    start = _series_start(run)
    for batch in _odometry_batches(run, robot, start):
        envelopes = [
            sealing.seal_record(key, header, plaintext, signing_key) for header, plaintext in batch
        ]
        record_create_batch(robot=robot, envelopes=envelopes)
    _await_anchored(stack, run, robot)
    return start


def _upload(stack: BenchStack, run: SeriesRun, robot: Any, key: bytes, token: str) -> datetime:
    """R odometry records 0.1 s apart, ending now, POSTed PER_POST at a time; every one awaited
    on chain. The capture time of the first."""
    from smcrypto import envelope

    start = _series_start(run)
    session = requests.Session()
    session.headers["Authorization"] = f"Token {token}"
    for batch in _odometry_batches(run, robot, start):
        envelopes = [
            base64.b64encode(envelope.seal(key, header, plaintext)).decode()
            for header, plaintext in batch
        ]
        answer = session.post(
            f"{stack.web_url}/api/v1/records/", json={"envelopes": envelopes}, timeout=120
        )
        answer.raise_for_status()
    session.close()
    _await_anchored(stack, run, robot)
    return start


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
    """One stack: the records, then the series reads and the per-record reads."""
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
    row: dict[str, Any] = {}
    try:
        stack.start()
        from accounts.services.robots import robot_create
        from sharing.models import Record

        uploaded = time.perf_counter()
        if run.signed:
            from bench.exports import _paired_robot

            odometry_robot, key, signing_key = _paired_robot(stack)
            robot = odometry_robot
            start = _store_signed(stack, run, odometry_robot, key, signing_key)
        else:
            ((robot, key),) = owners_register(stack, 1)
            odometry_robot, robot_token = robot_create(owner=robot.owner, name="odometry")
            start = _upload(stack, run, odometry_robot, key, robot_token)
        row["upload_and_anchor_s"] = time.perf_counter() - uploaded
        until = start + timedelta(seconds=run.records / RATE_HZ)
        token = viewer_token(robot.owner)
        cpu = _Cpu(stack)
        row["series"] = _series_reads(stack, run, cpu, odometry_robot, token, start, until)
        ids = list(
            Record.objects.filter(robot=odometry_robot)
            .order_by("captured_at")
            .values_list("pk", flat=True)
        )
        step = max(len(ids) // run.per_record_sample, 1)
        sample = [str(pk) for pk in ids[::step][: run.per_record_sample]]
        row["per_record"] = _per_record_reads(stack, run, cpu, token, sample)
        row["trees"] = (
            Record.objects.filter(robot=odometry_robot).values("anchor_root").distinct().count()
        )
    finally:
        stack.stop()
    return run_finished(row, stack, keep_logs=run.keep_logs)


def _series_reads(
    stack: BenchStack,
    run: SeriesRun,
    cpu: _Cpu,
    robot: Any,
    token: str,
    since: datetime,
    until: datetime,
) -> dict[str, Any]:
    session = requests.Session()
    session.headers["Authorization"] = f"Token {token}"
    query = {
        "robot": str(robot.pk),
        "topic": TOPIC,
        "fields": "position.x,position.y",
        "since": since.isoformat(),
        "until": until.isoformat(),
        "points": "1000",
    }
    times, answers = [], []
    before = cpu.take()
    for _ in range(run.series_rounds):
        sent = time.perf_counter()
        answer = session.get(f"{stack.web_url}/api/v1/records/series/", params=query, timeout=600)
        times.append(time.perf_counter() - sent)
        answer.raise_for_status()
        body = answer.json()
        answers.append(
            {key: body[key] for key in ("source_records", "verified", "refused")}
            | {"points": len(body["points"])}
        )
    spent = cpu.spent(before, cpu.take())
    session.close()
    checked = sum(answer["source_records"] for answer in answers)
    return {
        "seconds": times,
        "answers": answers,
        "records_checked": checked,
        "web_cpu_ms_per_record": spent["web"] * 1000 / checked,
        "workers_cpu_ms_per_record": spent["workers"] * 1000 / checked,
        "others_cpu_share": spent["others_share"],
    }


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
    series, single = measured["series"], measured["per_record"]
    stats = summarize(series["seconds"])  # seconds in, the same unit out
    one = statistics.mean(single["seconds"])
    baseline = {
        "path": "per record",
        "records": run.records,
        # Every view is the same work: the whole range at the sample's mean per record.
        "p50_s": statistics.median(single["seconds"]) * run.records,
        "p95_s": None,
        "mean_s": one * run.records,
        "web_cpu_ms_per_record": single["web_cpu_ms_per_record"],
        "workers_cpu_ms_per_record": single["workers_cpu_ms_per_record"],
        "others_cpu_share": single["others_cpu_share"],
        "sample": single["records_checked"],
        "sample_p50_ms": statistics.median(single["seconds"]) * 1000,
        "failed": single["failed"],
    }
    row = {
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
    }
    for key in ("p50", "web_cpu", "workers_cpu"):
        source = {"p50": "p50_s", "web_cpu": "web_cpu_ms_per_record"}.get(
            key, "workers_cpu_ms_per_record"
        )
        row[f"{key}_ratio_vs_per_record"] = row[source] / baseline[source]
        baseline[f"{key}_ratio_vs_per_record"] = 1.0
    return [baseline, row]


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench series", description=__doc__)
    parser.add_argument("--records", type=int, default=18_000, help="30 min at 10 Hz (18,000)")
    parser.add_argument("--rounds", type=int, default=5, help="series reads (default 5)")
    parser.add_argument(
        "--sample", type=int, default=300, help="records read one at a time (default 300)"
    )
    parser.add_argument("--workers", type=int, default=2, help="chain worker pool processes")
    parser.add_argument("--web-workers", type=int, default=0, help="0: as make run sizes it")
    parser.add_argument("--redis-url", default=BENCH_REDIS_URL)
    parser.add_argument("--results-dir", type=Path, default=RESULTS_DIR)
    parser.add_argument("--keep-logs", action="store_true")
    parser.add_argument("--quick", action="store_true", help="smoke run with small numbers")
    parser.add_argument(
        "--unsigned",
        action="store_true",
        help="a robot added by hand (no robot signatures to check), instead of a paired one",
    )
    args = parser.parse_args(argv)
    if args.quick:
        args.records, args.rounds, args.sample = 1_000, 2, 30
    run = SeriesRun(
        records=args.records,
        series_rounds=args.rounds,
        per_record_sample=args.sample,
        workers=args.workers,
        web_workers=args.web_workers,
        redis_url=args.redis_url,
        keep_logs=args.keep_logs,
        signed=not args.unsigned,
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
    print(f"== {run.describe()}", file=sys.stderr, flush=True)
    measured = run_in_child(measure, run)
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
        "signed": run.signed,
    }
    report["goal_p50_s"] = GOAL_P50_S
    report["measured"] = measured
    report["results"] = _rows(measured, run)
    report["load_average_at_end"] = [round(load, 2) for load in psutil.getloadavg()]
    report["goal_met"] = report["results"][1]["p50_s"] <= GOAL_P50_S
    print_table(report, COLUMNS)
    # The unsigned run is a comparison: it does not take the place of the demo robot's.
    name = NAME if run.signed else f"{NAME}-unsigned"
    write_results(name, report, FIELDS, args.results_dir, plot=_plot)
    return 0


def _plot(report: dict[str, Any], path: Path) -> None:
    baseline, series = report["results"]
    figure, (left, right) = plt.subplots(1, 2, figsize=(9, 3.6))
    names = ["per record\n(sample x N)", "series\n(one check path)"]
    left.bar(names, [baseline["p50_s"], series["p50_s"]], color=["#8c959f", "#0969da"])
    left.axhline(report["goal_p50_s"], color="#cf222e", linestyle="--", linewidth=1)
    left.text(1.4, report["goal_p50_s"], " goal 2 s", va="bottom", fontsize=8, color="#cf222e")
    left.set_yscale("log")
    left.set_ylabel(f"p50 seconds for {series['records']:,} records (log)")
    width = 0.35
    for offset, key, label in (
        (-width / 2, "web_cpu_ms_per_record", "web"),
        (width / 2, "workers_cpu_ms_per_record", "workers"),
    ):
        right.bar(
            [x + offset for x in range(2)],
            [baseline[key], series[key]],
            width=width,
            label=label,
        )
    right.set_xticks(range(2), names)
    right.set_ylabel("CPU ms per record checked")
    right.legend(fontsize=8)
    save_figure(
        figure,
        path,
        f"A series of {series['records']:,} odometry records, every one checked, against one "
        f"check per record\n{machine_line(report)}",
    )

"""Soak (issue 12): the `make run` stack, simulated robot included, sampled for an hour.

The stack is `python -m stack run` WITH the ROS side (bench/stack.py, `ros=True`): roscore on a
free port, `python -m ros_agent.sim` publishing at its real rates (odometry 10 Hz, a 58 KB image
1 Hz) and the demo owner's agent uploading them, with make run's chain worker (2 processes),
verify worker, beat, gunicorn and anvil (automine, zero gas), ANCHOR_BATCH_MAX and
ANCHOR_MAX_WAIT at the portal's defaults. Nothing else uploads. Every `--interval` seconds for
`--minutes` it samples:
- the records anchored, pending and failed (the stack's database, through this process's Django
  pointed at it by <workdir>/stack.json), and how many were uploaded in the minute before;
- the anchoring latency p95 (nearest rank) of the records anchored since the previous sample
  (anchored_at - created_at);
- the resident memory of every process of the stack (each with its children: gunicorn's and
  Celery's pool workers);
- the time of the demo owner's audit page and of the page of its latest anchored record (an
  integrity check against the chain), with a logged-in requests session.

Goals (issue 12), each reported as met or not with its measured value, never asserted: no
failed record; pending under a minute of uploads at every sample; flat memory (every process's
last-quarter median RSS at most RSS_GROWTH_GOAL above its first-quarter median); both pages
under PAGE_GOAL_S at the last sample.

Run: `python -m bench soak [--minutes 60] [--interval 30]` or `make soak` (not part of
`make bench`). Writes bench/results/soak.json, soak.csv and soak.png; `python -m bench report`
then writes its section of bench/REPORT.md.
"""

import argparse
import os
import statistics
import sys
import tempfile
import time
from dataclasses import dataclass, replace
from datetime import datetime, timedelta
from pathlib import Path
from typing import Any

import psutil
import requests

from bench import (
    MAKE_RUN_ANCHOR_MAX_WAIT,
    RESULTS_DIR,
    machine_info,
    now_iso,
    progress_bar,
)
from bench.common import check_redis_url, run_configurations, write_results
from bench.plotting import machine_line, plt, save_figure
from bench.stack import BENCH_REDIS_URL, BenchStack, StackOptions, run_finished, web_description
from bench.sustained import _percentiles
from stack.anvil import anvil_version, free_port

NAME = "soak"
# Processes of stack.json, in the order of the plot's legend; "stack" is `python -m stack run`.
PROCESSES = ("web", "worker", "verify", "beat", "anvil", "agent", "sim", "roscore", "stack")
PAGES = ("audit", "record")
PAGE_GOAL_S = 0.3
RSS_GROWTH_GOAL = 0.10  # last-quarter median over first-quarter median, minus one
# Shown but not judged for flat memory: the development chain keeps every block in memory.
RSS_NOT_JUDGED = ("anvil",)
PAGE_TIMEOUT = 60.0
MAKE_RUN_WORKERS = 2  # STACK_WORKERS' default
MAKE_RUN_BATCH_MAX = 100  # ANCHOR_BATCH_MAX's default (portal/settings.py)
NOTES = (
    "counts are the stack's Record rows by status at each sample; uploads a minute = "
    "records created in the 60 s before the sample (scaled to a minute while the first "
    "upload is less than a minute old); pending meets its goal below that.",
    "latency p95 = nearest-rank 95th percentile of anchored_at - created_at over the "
    "records anchored since the previous sample (none: no record anchored in it).",
    "RSS is summed over a process and its children (shared pages count once per "
    "process). anvil's is shown but not judged for flat memory: the development node "
    "keeps the chain in memory, so it grows with every block (the table says by how much).",
    "page times are one GET each per sample with the demo owner's logged-in session: "
    "/audit/ and /records/<id>/ of the owner's latest anchored record (its integrity "
    "check asks the verify worker and the chain).",
    "every process of the stack and this benchmark share this machine, and other work "
    "may run on it: see load_average_at_start.",
)
FIELDS = (
    "t_s",
    "at",
    "anchored",
    "pending",
    "failed",
    "uploads_per_minute",
    "anchored_in_interval",
    "latency_p95_s",
    *(f"{page}_s" for page in PAGES),
    *(f"{page}_status" for page in PAGES),
    *(f"rss_{name}_mib" for name in PROCESSES),
)


@dataclass(frozen=True)
class SoakRun:
    """The one configuration: make run's stack for a while, sampled."""

    minutes: float
    interval: float
    redis_url: str
    keep_logs: bool
    block_time: float | None = None  # make run: automine
    batch_max: int = MAKE_RUN_BATCH_MAX
    workers: int = MAKE_RUN_WORKERS
    max_wait: float = MAKE_RUN_ANCHOR_MAX_WAIT

    def describe(self) -> str:
        return (
            f"make run's stack with the simulated robot, {self.minutes:g} min, "
            f"sampled every {self.interval:g} s"
        )

    def stack_options(self) -> StackOptions:
        return replace(StackOptions.for_run(self), ros=True)


def main(argv: list[str]) -> int:
    """Run the soak, write JSON, CSV and PNG; 0 when every goal was met, else 1."""
    parser = argparse.ArgumentParser(prog="python -m bench soak", description=__doc__)
    parser.add_argument("--minutes", type=float, default=60.0, help="how long (default 60)")
    parser.add_argument(
        "--interval", type=float, default=30.0, help="seconds between samples (default 30)"
    )
    parser.add_argument(
        "--redis-url",
        default=BENCH_REDIS_URL,
        help="Redis database for the run, FLUSHED first",
    )
    parser.add_argument("--keep-logs", action="store_true", help="keep the run's directory")
    parser.add_argument("--results-dir", type=Path, default=RESULTS_DIR)
    args = parser.parse_args(argv)
    if args.minutes <= 0 or args.interval <= 0 or args.interval > args.minutes * 60:
        parser.error("--minutes and --interval must be positive, the interval within the run")
    check_redis_url(parser, args.redis_url)
    run = SoakRun(
        minutes=args.minutes,
        interval=args.interval,
        redis_url=args.redis_url,
        keep_logs=args.keep_logs,
    )
    report: dict[str, Any] = {
        "benchmark": NAME,
        "date": now_iso(),
        "machine": machine_info(("celery", "django", "gunicorn", "requests", "web3", "redis")),
        "anvil": anvil_version(),
        "load_average_at_start": [round(load, 2) for load in psutil.getloadavg()],
        "settings": {
            "minutes": run.minutes,
            "interval_s": run.interval,
            "stack": "`python -m stack run --ros` (what `make run` execs): roscore, "
            "ros_agent.sim at its real rates and the demo owner's agent; anvil automine with "
            f"zero gas; chain worker -c {run.workers}, verify worker, beat",
            "web_command": web_description(),
            "anchor_batch_max": run.batch_max,
            "anchor_max_wait_s": run.max_wait,
            "page_goal_s": PAGE_GOAL_S,
            "rss_growth_goal": RSS_GROWTH_GOAL,
        },
    }
    (row,) = run_configurations([run], _measure)
    samples = row.pop("samples")
    report["run"] = row
    report["goals"] = goals_evaluate(samples)
    report["rss_growth"] = rss_growth(samples)
    report["notes"] = list(NOTES)
    report["results"] = samples
    for goal in report["goals"]:
        verdict = {True: "met", False: "NOT met", None: "not measured"}[goal["met"]]
        print(f"{goal['goal']}: {verdict} ({goal['measured']})")
    write_results(
        NAME, report, FIELDS, args.results_dir, plot=_plot, csv_rows=map(_csv_row, samples)
    )
    return 0 if all(goal["met"] for goal in report["goals"]) else 1


# --- what the samples say (pure) --------------------------------------------------------------


def latency_p95(latencies: list[float]) -> float | None:
    """Nearest-rank 95th percentile in seconds, as the sustained benchmark's; None if empty."""
    if not latencies:
        return None
    return _percentiles(latencies, "latency")["latency_p95_s"]


def rss_growth(samples: list[dict[str, Any]]) -> dict[str, dict[str, float | None]]:
    """Per process: median RSS of the first and the last quarter of the samples, and the growth
    from one to the other (a fraction); None where a process has too few samples."""
    growth = {}
    for name in PROCESSES:
        values = [s["rss_mib"][name] for s in samples if s["rss_mib"].get(name) is not None]
        if len(values) < 2:
            if values or any(name in s["rss_mib"] for s in samples):
                growth[name] = {"first_mib": None, "last_mib": None, "growth": None}
            continue
        quarter = max(len(values) // 4, 1)
        first = statistics.median(values[:quarter])
        last = statistics.median(values[-quarter:])
        growth[name] = {
            "first_mib": first,
            "last_mib": last,
            "growth": last / first - 1 if first else None,
        }
    return growth


def goals_evaluate(
    samples: list[dict[str, Any]],
    *,
    page_goal_s: float = PAGE_GOAL_S,
    rss_growth_goal: float = RSS_GROWTH_GOAL,
) -> list[dict[str, Any]]:
    """Issue 12's four goals, each {goal, met (True, False or None: not measured), measured}."""
    if not samples:
        return [
            {"goal": goal, "met": None, "measured": "no sample"}
            for goal in ("0 failed", "pending under a minute of uploads", "flat memory", "pages")
        ]
    last = samples[-1]
    most_failed = max(s["failed"] for s in samples)
    goals = [
        {
            "goal": "0 failed records",
            "met": most_failed == 0,
            "measured": f"{last['failed']} failed at the end, at most {most_failed} at a sample",
        }
    ]
    late = [s for s in samples if s["pending"] and s["pending"] >= s["uploads_per_minute"]]
    worst = max(samples, key=lambda s: s["pending"] / max(s["uploads_per_minute"], 1))
    goals.append(
        {
            "goal": "pending under a minute of uploads at every sample",
            "met": not late,
            "measured": f"{len(late)} of {len(samples)} samples over; worst {worst['pending']} "
            f"pending against {worst['uploads_per_minute']:.0f} uploads a minute "
            f"(at {worst['t_s'] / 60:.1f} min)",
        }
    )
    growth = {
        name: value
        for name, value in rss_growth(samples).items()
        if value["growth"] is not None and name not in RSS_NOT_JUDGED
    }
    if growth:
        name, most = max(growth.items(), key=lambda item: item[1]["growth"])
        goals.append(
            {
                "goal": f"flat memory (every process's RSS grows at most "
                f"{rss_growth_goal:.0%}, last quarter against first; "
                f"{', '.join(RSS_NOT_JUDGED)} not judged)",
                "met": most["growth"] <= rss_growth_goal,
                "measured": f"largest growth {name}: {most['first_mib']:.0f} -> "
                f"{most['last_mib']:.0f} MiB ({most['growth']:+.1%})",
            }
        )
    else:
        goals.append({"goal": "flat memory", "met": None, "measured": "too few samples"})
    pages = last["pages"]
    goals.append(
        {
            "goal": f"every page under {page_goal_s * 1000:.0f} ms at the end",
            "met": all(
                pages[page]["status"] == "200"
                and pages[page]["s"] is not None
                and pages[page]["s"] < page_goal_s
                for page in PAGES
            ),
            "measured": ", ".join(
                f"{page} {_ms(pages[page]['s'])} ({pages[page]['status']})" for page in PAGES
            ),
        }
    )
    return goals


def _ms(seconds: float | None) -> str:
    return "-" if seconds is None else f"{seconds * 1000:.0f} ms"


def _csv_row(sample: dict[str, Any]) -> dict[str, Any]:
    row = {key: value for key, value in sample.items() if key not in ("pages", "rss_mib")}
    for page in PAGES:
        row[f"{page}_s"] = sample["pages"][page]["s"]
        row[f"{page}_status"] = sample["pages"][page]["status"]
    for name in PROCESSES:
        row[f"rss_{name}_mib"] = sample["rss_mib"].get(name)
    return row


# --- the run, in a child process ----------------------------------------------------------------


def _measure(run: SoakRun) -> dict[str, Any]:
    workdir = Path(tempfile.mkdtemp(prefix="authros-bench-soak-"))
    os.environ["ROS_MASTER_URI"] = f"http://127.0.0.1:{free_port()}/"  # a roscore of its own
    stack = BenchStack(run.stack_options(), workdir)
    samples: list[dict[str, Any]] = []
    row: dict[str, Any] = {"samples": samples, "stopped_early": None}
    try:
        stack.start()
        row["stack_started_at"] = now_iso()
        try:
            _sample_for(run, stack, samples)
        except (RuntimeError, requests.RequestException) as exc:  # the samples so far stand
            row["stopped_early"] = f"{type(exc).__name__}: {str(exc)[:2000]}"
            print(f"soak stopped early: {exc}", file=sys.stderr)
    finally:
        stack.stop()
    row["ran_s"] = samples[-1]["t_s"] if samples else 0.0
    return run_finished(row, stack, keep_logs=run.keep_logs)


def _sample_for(run: SoakRun, stack: BenchStack, samples: list[dict[str, Any]]) -> None:
    """A sample at once, then every run.interval seconds until run.minutes have passed."""
    from django.utils import timezone

    from accounts.selectors import owner_by_username

    owner = owner_by_username(stack.state["demo"]["username"])
    password = Path(stack.state["demo"]["password_file"]).read_text().strip()
    pages = _Pages(stack.web_url, owner.user.username, password)
    started = time.monotonic()
    since: datetime | None = None
    count = int(run.minutes * 60 // run.interval) + 1
    with progress_bar(count, "soak samples", unit="sample") as progress:
        for number in range(count):
            time.sleep(max(started + number * run.interval - time.monotonic(), 0))
            stack.check_alive()
            now = timezone.now()
            sample = {"t_s": time.monotonic() - started, "at": now.isoformat(timespec="seconds")}
            sample |= _records(owner, since, now)
            sample["rss_mib"] = _rss(stack)
            sample["pages"] = pages.measure(sample.pop("latest_record"))
            samples.append(sample)
            since = now
            progress.update(1)


def _records(owner: Any, since: datetime | None, now: datetime) -> dict[str, Any]:
    """Counts by status, the last minute's uploads, the latency p95 since the last sample."""
    from django.db.models import Count

    from sharing.models import Record

    counts = dict(Record.objects.values_list("status").annotate(n=Count("pk")))
    anchored = Record.objects.filter(status=Record.Status.ANCHORED, anchored_at__lte=now)
    if since is not None:
        anchored = anchored.filter(anchored_at__gt=since)
    latencies = [
        (anchored_at - created_at).total_seconds()
        for created_at, anchored_at in anchored.values_list("created_at", "anchored_at")
    ]
    latest = (
        Record.objects.filter(owner=owner, status=Record.Status.ANCHORED)
        .order_by("-anchored_at")
        .values_list("pk", flat=True)
        .first()
    )
    return {
        "anchored": counts.get(Record.Status.ANCHORED, 0),
        "pending": counts.get(Record.Status.PENDING, 0),
        "failed": counts.get(Record.Status.FAILED, 0),
        "uploads_per_minute": _uploads_per_minute(now),
        "anchored_in_interval": len(latencies),
        "latency_p95_s": latency_p95(latencies),
        "latest_record": None if latest is None else str(latest),
    }


def _uploads_per_minute(now: datetime) -> float:
    """Records created in the minute before now, scaled up to a minute when the first upload
    came less than a minute ago (right after the start)."""
    from django.db.models import Min

    from sharing.models import Record

    recent = Record.objects.filter(created_at__gt=now - timedelta(minutes=1), created_at__lte=now)
    first = Record.objects.aggregate(first=Min("created_at"))["first"]
    if first is None:
        return 0.0
    window = min(max((now - first).total_seconds(), 1.0), 60.0)
    return recent.count() * 60 / window


def _rss(stack: BenchStack) -> dict[str, float | None]:
    """MiB per process of stack.json (with its children); None for one that is gone."""
    pids = {**stack.state["processes"], "stack": stack.state["pid"]}
    rss: dict[str, float | None] = {}
    for name, pid in pids.items():
        try:
            root = psutil.Process(pid)
            members = [root] if name == "stack" else [root, *root.children(recursive=True)]
            total = 0
            for process in members:
                try:
                    total += process.memory_info().rss
                except psutil.NoSuchProcess:  # a pool worker replaced meanwhile
                    continue
            rss[name] = total / 2**20
        except psutil.NoSuchProcess:
            rss[name] = None
    return rss


class _Pages:
    """The demo owner's pages through a logged-in session, as a browser asks for them."""

    def __init__(self, base: str, username: str, password: str) -> None:
        self.base = base
        self.username = username
        self.password = password
        self.session = requests.Session()
        self._log_in()

    def _log_in(self) -> None:
        url = f"{self.base}/login/"
        self.session.get(url, timeout=PAGE_TIMEOUT).raise_for_status()
        answer = self.session.post(
            url,
            data={
                "username": self.username,
                "password": self.password,
                "csrfmiddlewaretoken": self.session.cookies["csrftoken"],
            },
            timeout=PAGE_TIMEOUT,
        )
        if "sessionid" not in self.session.cookies:
            raise RuntimeError(f"the demo owner could not log in ({answer.status_code})")

    def measure(self, record_id: str | None) -> dict[str, dict[str, Any]]:
        """Seconds and HTTP status of each page (a record page only once one is anchored)."""
        paths = {"audit": "/audit/", "record": record_id and f"/records/{record_id}/"}
        times: dict[str, dict[str, Any]] = {}
        for page in PAGES:
            path = paths[page]
            times[page] = {"s": None, "status": "no anchored record"}
            if path:
                times[page] = self._get(path)
                if times[page]["status"] == "302":  # the session ended: once more, logged in
                    self._log_in()
                    times[page] = self._get(path)
        return times

    def _get(self, path: str) -> dict[str, Any]:
        started = time.perf_counter()
        try:
            answer = self.session.get(
                f"{self.base}{path}", timeout=PAGE_TIMEOUT, allow_redirects=False
            )
        except requests.RequestException as exc:
            return {"s": None, "status": type(exc).__name__}
        return {"s": time.perf_counter() - started, "status": str(answer.status_code)}


# --- the figure -------------------------------------------------------------------------------


def _plot(report: dict[str, Any], path: Path) -> None:
    samples = report["results"]
    minutes = [s["t_s"] / 60 for s in samples]
    figure, axes = plt.subplots(2, 2, figsize=(12, 8))
    (records_axis, latency_axis), (memory_axis, pages_axis) = axes
    records_axis.plot(minutes, [s["anchored"] for s in samples], label="anchored (left)")
    backlog_axis = records_axis.twinx()
    for key, style in (("pending", "--"), ("failed", ":"), ("uploads_per_minute", "-.")):
        backlog_axis.plot(
            minutes, [s[key] for s in samples], style, label=f"{key.replace('_', ' ')} (right)"
        )
    backlog_axis.legend(fontsize=6, loc="center right")
    records_axis.set_title("records (left: anchored; right: pending, failed, uploads a minute)")
    latency_axis.plot(minutes, [s["latency_p95_s"] for s in samples], "o-", markersize=3)
    latency_axis.set_title("anchoring latency p95 over each interval (s)")
    for name in PROCESSES:
        values = [s["rss_mib"].get(name) for s in samples]
        if any(value is not None for value in values):
            memory_axis.plot(minutes, values, label=name)
    memory_axis.set_title("resident memory per process, with its children (MiB)")
    memory_axis.set_yscale("log")
    for page in PAGES:
        times = [s["pages"][page]["s"] for s in samples]
        pages_axis.plot(
            minutes,
            [None if t is None else t * 1000 for t in times],
            "o-",
            markersize=3,
            label=page,
        )
    pages_axis.axhline(PAGE_GOAL_S * 1000, color="grey", linestyle=":", label="goal")
    pages_axis.set_title("page time, demo owner logged in (ms)")
    for axis in (records_axis, latency_axis, memory_axis, pages_axis):
        axis.set_xlabel("minutes since the stack was up")
        axis.grid(True, alpha=0.3)
        if axis is not latency_axis:
            axis.legend(fontsize=6, loc="upper left")
    ran = report["run"]["ran_s"] / 60
    title = (
        f"soak: make run's stack with the simulated robot, {ran:.1f} min; {machine_line(report)}"
    )
    save_figure(figure, path, title, fontsize=8)

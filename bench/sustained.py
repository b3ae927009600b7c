"""Whole pipeline (issue 6, experiment 5): 50 agents upload through REST for 60 s.

Each agent is one robot of its own. It records `--rate` 1 KB records per second and every
`--flush-interval` seconds POSTs what it recorded since its last upload as one batch
(`{"envelopes": [...]}` to `/api/v1/records/`), as ros_agent's uploader does. The robots do
not wait for the portal: a slow answer only makes the next batch bigger (an open loop, like a
robot whose spool grows). After `--duration` seconds they stop and the benchmark waits (at most
`--drain` seconds) until every accepted record is anchored.

Measured per configuration (anvil automine and `--block-time 1`, each with ANCHOR_BATCH_MAX 1,
the paper's one transaction per record and the baseline, and 100, batching):
- sustained anchored records per second: records whose anchored_at falls in the steady part of
  the run (after `--warmup` seconds, until the robots stop) divided by its length;
- p50/p95/p99 latency from the POST that carried a record to Record.anchored_at, over every
  accepted record (one not anchored by the end of the drain counts as slower than all);
- p50/p95/p99 latency to a verified view: every `--view-every`-th accepted record is fetched
  with `GET /api/v1/records/{id}/content/` as soon as it is anchored, by viewer threads using
  its owner's API token (scope `read`: a robot token only uploads); the portal has a worker
  hash the stored ciphertext and compare it with the chain before it answers 200
  `{"verified": true}`;
- CPU (percent of one core) and resident memory of the web (gunicorn master and workers), the
  Celery workers (with their pool children), beat and anvil, sampled every second.

Every configuration runs on each of `--engines` (default both): sqlite-disk, make run's SQLite
file and envelopes on the local disk, and postgres-s3, a fresh database on the PostgreSQL server
at BENCH_PG_URL (default postgres://postgres@127.0.0.1:5432/postgres, dropped after the run) and
envelopes in a SeaweedFS bucket (a `weed server -s3` of the run's own, stopped after it).
postgres-s3 rows get ratios against sqlite-disk of the same configuration in the same run.

Run: `python -m bench sustained [--agents 50] [--duration 60] [--rate 2] [--quick]
[--engines sqlite-disk postgres-s3]`.
Writes bench/results/sustained.json, sustained.csv and sustained.png.
"""

import argparse
import base64
import math
import queue
import sys
import tempfile
import threading
import time
from collections import Counter
from dataclasses import dataclass, field
from datetime import timedelta
from pathlib import Path
from typing import Any

import psutil
import requests

from bench import now_iso, progress_bar
from bench.common import (
    PLAINTEXT_BYTES,
    add_engine_ratios,
    add_ratios,
    print_table,
    run_configurations,
    seal_record,
    write_results,
)
from bench.plotting import ENGINE_STYLES, engine_label, machine_line, plt, save_figure
from bench.rest import (
    REQUEST_TIMEOUT,
    add_arguments,
    add_engines_argument,
    check_arguments,
    engines_chosen,
    engines_prefix,
    engines_settings,
    report_header,
)
from bench.stack import (
    POLL_INTERVAL,
    BenchStack,
    StackOptions,
    block_mode,
    owners_register,
    run_finished,
)

NAME = "sustained"
BLOCK_TIMES: tuple[float | None, ...] = (None, 1.0)  # None: automine
BATCH_SIZES = (1, 100)
QUICK = {"agents": 10, "duration": 15.0, "warmup": 3.0, "drain": 60.0}
SAMPLE_INTERVAL = 1.0
PERCENTILES = (50, 95, 99)
GROUPS = ("web", "workers", "beat", "anvil")
RATIO_KEYS = ("anchored_per_s", "to_anchored_p50_s", "to_anchored_p99_s", "to_verified_p50_s")
# postgres-s3 against sqlite-disk of the same configuration in the same run
ENGINE_RATIO_KEYS = (
    "anchored_per_s",
    "to_anchored_p50_s",
    "to_verified_p50_s",
    "response_p95_s",
    "web_cpu_mean_pct",
    "workers_cpu_mean_pct",
)
FIELDS = (
    "engines",
    "mode",
    "batch_max",
    "agents",
    "duration_s",
    "offered_per_s",
    "accepted",
    "accepted_per_s",
    "anchored",
    "anchored_per_s",
    "anchored_overall_per_s",
    "transactions",
    *(f"response_p{p}_s" for p in PERCENTILES),
    *(f"to_anchored_p{p}_s" for p in PERCENTILES),
    "views",
    "verified_views",
    *(f"to_verified_p{p}_s" for p in PERCENTILES),
    *(f"{group}_cpu_mean_pct" for group in GROUPS),
    *(f"{group}_rss_peak_mib" for group in GROUPS),
    *(f"{key}_ratio_vs_batch1" for key in RATIO_KEYS),
    *(f"{key}_ratio_vs_sqlite" for key in ENGINE_RATIO_KEYS),
)
COLUMNS = (
    ("engines", "engines", ""),
    ("mode", "mode", ""),
    ("batch", "batch_max", "d"),
    ("offered/s", "offered_per_s", ".1f"),
    ("accepted/s", "accepted_per_s", ".1f"),
    ("anchored/s", "anchored_per_s", ".1f"),
    ("anch p50", "to_anchored_p50_s", ".2f"),
    ("anch p99", "to_anchored_p99_s", ".2f"),
    ("view p50", "to_verified_p50_s", ".2f"),
    ("view p99", "to_verified_p99_s", ".2f"),
    ("web cpu%", "web_cpu_mean_pct", ".0f"),
    ("wrk cpu%", "workers_cpu_mean_pct", ".0f"),
    ("web MiB", "web_rss_peak_mib", ".0f"),
    ("wrk MiB", "workers_rss_peak_mib", ".0f"),
    ("anch/s x b1", "anchored_per_s_ratio_vs_batch1", ".2f"),
    ("anch/s x sqlite", "anchored_per_s_ratio_vs_sqlite", ".2f"),
    ("view p50 x sqlite", "to_verified_p50_s_ratio_vs_sqlite", ".2f"),
)


@dataclass(frozen=True)
class SustainedRun:
    """One measured configuration: A robots uploading for a while, then a drain."""

    block_time: float | None
    batch_max: int
    agents: int
    rate: float  # records per second per agent
    flush_interval: float
    duration: float
    warmup: float
    drain: float
    view_every: int
    owners: int
    workers: int
    web_workers: int
    viewers: int
    max_wait: float
    redis_url: str
    keep_logs: bool
    engines: str = "sqlite-disk"  # or "postgres-s3" (bench.stack.ENGINES)

    @property
    def mode(self) -> str:
        return block_mode(self.block_time)

    def describe(self) -> str:
        return engines_prefix(self.engines) + (
            f"{self.mode}, ANCHOR_BATCH_MAX={self.batch_max}, "
            f"{self.agents} robots x {self.rate:g} rec/s for {self.duration:g}s"
        )

    def stack_options(self) -> StackOptions:
        return StackOptions.for_run(self, web_workers=self.web_workers, engines=self.engines)


def main(argv: list[str]) -> int:
    """Run every configuration, print the table and write JSON, CSV and PNG results."""
    parser = argparse.ArgumentParser(prog="python -m bench sustained", description=__doc__)
    parser.add_argument("--agents", type=int, help="robots uploading at once (default 50)")
    parser.add_argument("--duration", type=float, help="seconds the robots upload (default 60)")
    parser.add_argument(
        "--rate", type=float, default=2.0, help="records per second per robot (default 2)"
    )
    parser.add_argument(
        "--flush-interval", type=float, default=1.0, help="seconds between a robot's uploads"
    )
    parser.add_argument("--warmup", type=float, help="seconds left out of the sustained rate")
    parser.add_argument("--drain", type=float, help="seconds to wait for anchoring afterwards")
    parser.add_argument(
        "--view-every", type=int, default=5, help="view every Nth accepted record (default 5)"
    )
    parser.add_argument(
        "--block-times",
        type=float,
        nargs="+",
        help="block times in seconds, 0 = automine (default: automine, 1)",
    )
    add_engines_argument(parser)
    add_arguments(parser)
    args = parser.parse_args(argv)
    check_arguments(parser, args)
    defaults = QUICK if args.quick else {"agents": 50, "duration": 60.0, "warmup": 10.0}
    defaults = {"drain": 300.0} | defaults
    for name, value in defaults.items():
        if getattr(args, name) is None:
            setattr(args, name, value)
    if min(args.agents, args.view_every) < 1 or min(args.rate, args.flush_interval) <= 0:
        parser.error("--agents, --view-every, --rate and --flush-interval must be positive")
    if not 0 <= args.warmup < args.duration:
        parser.error("--warmup must be shorter than --duration")
    block_times = tuple(b or None for b in args.block_times) if args.block_times else BLOCK_TIMES
    engines = engines_chosen(args)
    report = report_header(NAME, args, now_iso())
    report["settings"] |= engines_settings(parser, engines)
    runs = [
        SustainedRun(
            block_time=block_time,
            batch_max=batch_max,
            agents=args.agents,
            rate=args.rate,
            flush_interval=args.flush_interval,
            duration=args.duration,
            warmup=args.warmup,
            drain=args.drain,
            view_every=args.view_every,
            owners=args.owners,
            workers=args.workers,
            web_workers=args.web_workers,
            viewers=args.verifiers,
            max_wait=args.max_wait,
            redis_url=args.redis_url,
            keep_logs=args.keep_logs,
            engines=engine,
        )
        for engine in engines
        for block_time in block_times
        for batch_max in BATCH_SIZES
    ]
    rows = run_configurations(runs, _measure)
    rows_ratios(rows)
    del report["settings"]["timeout_s"]  # --drain bounds the wait here
    report["settings"] |= {
        "agents": f"{args.agents} robots, one thread and requests.Session each, each with its "
        f"own robot token; {args.rate:g} records/s per robot, one batch POST every "
        f"{args.flush_interval:g}s (open loop)",
        "duration_s": args.duration,
        "warmup_s": args.warmup,
        "drain_s": args.drain,
        "view_every": args.view_every,
        "viewers": args.verifiers,
        "block_times": ["automine" if b is None else b for b in block_times],
        "batch_sizes": list(BATCH_SIZES),
        "plaintext_bytes": PLAINTEXT_BYTES,
    }
    report["notes"] = [
        "sustained anchored/s = records with anchored_at in [warmup, duration] after the "
        "robots started, over that many seconds; overall = all anchored over first POST to "
        "last anchored_at (includes the drain).",
        "latency to anchored = the POST carrying the record sent to Record.anchored_at, over "
        "every accepted record; a record still pending after the drain counts as slower "
        "than all, and a percentile that falls on one is shown as '-'.",
        "latency to a verified view = the same POST to a 200 {verified: true} from "
        "GET /api/v1/records/{id}/content/ with the owner's API token (scope read), for "
        "every view_every-th accepted record, asked "
        "for as soon as the benchmark sees the record anchored (polling every "
        f"{POLL_INTERVAL:g}s).",
        "CPU is percent of one core, averaged over the upload window; memory is the peak "
        "resident set size summed over a group's processes (shared pages count once per "
        "process). The benchmark's own robots and viewers run in the benchmark process.",
        "x batch 1 columns divide by ANCHOR_BATCH_MAX=1 (one transaction per record) of the "
        "same block mode and engines in this run.",
        *(
            [
                "x sqlite columns divide postgres-s3 (PostgreSQL + SeaweedFS S3) by sqlite-disk "
                "(SQLite + local disk) of the same block mode and batch size, measured in this "
                "run on this machine.",
            ]
            if len(engines) > 1
            else []
        ),
        "every process shares this machine, and other work may run on it: see "
        "load_average_at_start.",
    ]
    report["results"] = rows
    print_table(report, COLUMNS)
    write_results(NAME, report, FIELDS, args.results_dir, plot=_plot)
    return 0 if all(row["failed_records"] == 0 for row in rows) else 1


def rows_ratios(rows: list[dict[str, Any]]) -> None:
    """Batching against batch size 1, and postgres-s3 against sqlite-disk (same run)."""
    add_ratios(rows, ("engines", "mode"), RATIO_KEYS)
    add_engine_ratios(rows, ("mode", "batch_max"), ENGINE_RATIO_KEYS)


# --- one run, in a child process ---------------------------------------------------------------


@dataclass
class _Upload:
    """One batch POST: when it left, what came back, and its records."""

    sent_at: float
    count: int
    answered_at: float | None = None
    status: str = "not answered"
    record_ids: list[str] = field(default_factory=list)


@dataclass
class _Robot:
    robot: Any
    key: bytes
    token: str
    # The owner's API token (scope read) the viewers read this robot's records with.
    viewer_token: str
    seq: int = 0
    uploads: list[_Upload] = field(default_factory=list)


class _Sampler(threading.Thread):
    """CPU and RSS of each process group, every SAMPLE_INTERVAL seconds, until stopped."""

    def __init__(self, roots: dict[str, list[int]], started: float) -> None:
        super().__init__(daemon=True)
        self.roots = roots
        self.started = started
        self.samples: list[dict[str, Any]] = []
        self._processes: dict[int, psutil.Process] = {}
        self._done = threading.Event()

    def run(self) -> None:
        while not self._done.wait(SAMPLE_INTERVAL):
            sample: dict[str, Any] = {"t": time.time() - self.started}
            for group, pids in self.roots.items():
                cpu = rss = 0.0
                for process in self._members(pids):
                    try:
                        cpu += process.cpu_percent(interval=None)
                        rss += process.memory_info().rss
                    except psutil.Error:
                        continue
                sample[group] = {"cpu_pct": cpu, "rss_mib": rss / 2**20}
            self.samples.append(sample)

    def stop(self) -> None:
        self._done.set()
        self.join()

    def _members(self, pids: list[int]) -> list[psutil.Process]:
        members = []
        for pid in pids:
            try:
                root = self._process(pid)
                members.append(root)
                members.extend(self._process(child.pid) for child in root.children(True))
            except psutil.Error:
                continue
        return members

    def _process(self, pid: int) -> psutil.Process:
        """The same Process object each time, so cpu_percent measures since the last sample."""
        if pid not in self._processes:
            self._processes[pid] = psutil.Process(pid)
            self._processes[pid].cpu_percent(interval=None)
        return self._processes[pid]


def _measure(run: SustainedRun) -> dict[str, Any]:
    workdir = Path(tempfile.mkdtemp(prefix="authros-bench-sustained-"))
    stack = BenchStack(run.stack_options(), workdir)
    try:
        stack.start()
        base = stack.web_url
        robots = _robots_create(run, stack)
        roots = stack.pids()
        started = time.time()
        sampler = _Sampler(roots, started)
        sampler.start()
        try:
            watcher = _Watcher(run, base, robots, started)
            watcher.start()
            _upload_for(run, base, robots, started)
            uploaded = time.time()
            watcher.finish(stack)
        finally:
            sampler.stop()
        row = _statistics(run, robots, watcher, sampler.samples, started, uploaded)
    finally:
        stack.stop()
    return run_finished(row, stack, keep_logs=run.keep_logs)


def _robots_create(run: SustainedRun, stack: BenchStack) -> list[_Robot]:
    """K owners registered on chain, each with an API token to read with, then one robot per
    agent, round-robin over the owners."""
    from accounts.services.api_tokens import owner_token_create
    from accounts.services.robots import robot_create

    owners = owners_register(stack, run.owners)
    viewer_tokens = [
        owner_token_create(
            owner=owner_robot.owner,
            name="bench-viewer",
            scopes=["read"],
            expires_in=timedelta(days=1),
        )[1]
        for owner_robot, _ in owners
    ]
    robots = []
    for number in range(run.agents):
        owner_robot, key = owners[number % len(owners)]
        robot, token = robot_create(owner=owner_robot.owner, name=f"robot-{number}")
        robots.append(_Robot(robot, key, token, viewer_tokens[number % len(owners)]))
    return robots


def _upload_for(run: SustainedRun, base: str, robots: list[_Robot], started: float) -> None:
    """Every robot in its own thread for run.duration seconds, starts spread over one interval."""
    url = f"{base}/api/v1/records/"
    offsets = [run.flush_interval * number / run.agents for number in range(run.agents)]
    offered = sum(math.floor((run.duration - offset) * run.rate) for offset in offsets)
    progress = progress_bar(offered, "records sent", unit="rec")
    lock = threading.Lock()

    def robot_loop(number: int, robot: _Robot) -> None:
        session = requests.Session()
        session.headers["Authorization"] = f"Token {robot.token}"
        offset = offsets[number]
        recorded = 0
        tick = 1
        try:
            while True:
                due = started + offset + tick * run.flush_interval
                time.sleep(max(due - time.time(), 0))
                elapsed = min(time.time(), started + run.duration) - started - offset
                count = math.floor(max(elapsed, 0) * run.rate) - recorded
                if count > 0:
                    _post(session, url, robot, count)
                    recorded += count
                    with lock:
                        progress.update(count)
                if time.time() >= started + run.duration:
                    return
                tick += 1
        finally:
            session.close()

    threading.stack_size(512 * 1024)
    threads = [
        threading.Thread(target=robot_loop, args=(number, robot), name=f"robot-{number}")
        for number, robot in enumerate(robots)
    ]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    progress.close()


def _post(session: requests.Session, url: str, robot: _Robot, count: int) -> None:
    envelopes = []
    for _ in range(count):
        robot.seq += 1
        data = seal_record(robot.robot, robot.key, seq=robot.seq, plaintext_bytes=PLAINTEXT_BYTES)
        envelopes.append(base64.b64encode(data).decode())
    upload = _Upload(sent_at=time.time(), count=count)
    robot.uploads.append(upload)
    try:
        response = session.post(url, json={"envelopes": envelopes}, timeout=REQUEST_TIMEOUT)
        upload.status = str(response.status_code)
        if response.status_code == 201:
            upload.record_ids = [item["id"] for item in response.json()]
    except requests.RequestException as exc:
        upload.status = type(exc).__name__
    upload.answered_at = time.time()


class _Watcher:
    """Sees records anchored (from the database) and has viewers fetch every Nth one."""

    def __init__(self, run: SustainedRun, base: str, robots: list[_Robot], started: float) -> None:
        self.run = run
        self.base = base
        self.robots = robots
        self.started = started
        self.anchored: dict[str, float] = {}
        self.failed: set[str] = set()
        self.viewed: dict[str, float] = {}
        self.view_statuses: Counter[str] = Counter()
        self._views: queue.Queue[tuple[str, str] | None] = queue.Queue()
        self._stop = threading.Event()
        self._threads = [
            threading.Thread(target=self._view_loop, daemon=True, name=f"viewer-{n}")
            for n in range(run.viewers)
        ]
        self._poller = threading.Thread(target=self._poll_loop, daemon=True, name="poller")
        self.error: BaseException | None = None

    def start(self) -> None:
        for thread in (*self._threads, self._poller):
            thread.start()

    def accepted(self) -> dict[str, tuple[float, str]]:
        """Record id -> (POST sent at, the owner's viewer token), for every record answered
        with 201."""
        return {
            record_id: (upload.sent_at, robot.viewer_token)
            for robot in self.robots
            for upload in list(robot.uploads)
            for record_id in upload.record_ids
        }

    def finish(self, stack: BenchStack) -> None:
        """Wait (at most run.drain s) until every accepted record is settled and viewed."""
        accepted = self.accepted()
        deadline = time.monotonic() + self.run.drain
        with progress_bar(len(accepted), "anchored", unit="rec") as progress:
            while time.monotonic() < deadline and self.error is None:
                settled = len(self.anchored) + len(self.failed)
                progress.update(settled - progress.n)
                viewing = self._views.unfinished_tasks
                if settled >= len(accepted) and not viewing:
                    break
                stack.check_alive()
                time.sleep(POLL_INTERVAL)
            else:
                if self.error is None:
                    print(f"drain timed out after {self.run.drain:.0f}s", file=sys.stderr)
        self._stop.set()
        for _ in self._threads:
            self._views.put(None)
        for thread in (*self._threads, self._poller):
            thread.join(timeout=REQUEST_TIMEOUT)
        if self.error is not None:
            raise self.error

    def _poll_loop(self) -> None:
        from django.db import connections

        from sharing.models import Record

        try:
            while not self._stop.wait(POLL_INTERVAL):
                accepted = self.accepted()
                waiting = [rid for rid in accepted if rid not in self.anchored]
                for start in range(0, len(waiting), 900):
                    chunk = waiting[start : start + 900]
                    rows = Record.objects.filter(pk__in=chunk).exclude(status=Record.Status.PENDING)
                    for pk, status, anchored_at in rows.values_list("pk", "status", "anchored_at"):
                        record_id = str(pk)
                        if status == Record.Status.FAILED:
                            self.failed.add(record_id)
                        elif status == Record.Status.ANCHORED:
                            if _sampled(record_id, self.run.view_every):  # queued first: see
                                self._views.put((record_id, accepted[record_id][1]))  # finish()
                            self.anchored[record_id] = anchored_at.timestamp()
        except BaseException as exc:  # the main thread raises it from finish()
            self.error = exc
        finally:
            connections.close_all()

    def _view_loop(self) -> None:
        session = requests.Session()
        try:
            while (item := self._views.get()) is not None:
                record_id, token = item
                try:
                    if self._stop.is_set():  # the drain is over: not asked
                        self.view_statuses["not asked (drain over)"] += 1
                    else:
                        self._view(session, record_id, token)
                finally:
                    self._views.task_done()
            self._views.task_done()
        finally:
            session.close()

    def _view(self, session: requests.Session, record_id: str, token: str) -> None:
        url = f"{self.base}/api/v1/records/{record_id}/content/"
        try:
            response = session.get(
                url, headers={"Authorization": f"Token {token}"}, timeout=REQUEST_TIMEOUT
            )
            status = str(response.status_code)
            if response.status_code == 200 and response.json().get("verified") is True:
                self.viewed[record_id] = time.time()
                status = "200 verified"
        except requests.RequestException as exc:
            status = type(exc).__name__
        self.view_statuses[status] += 1


def _sampled(record_id: str, every: int) -> bool:
    """Every `every`-th record in effect: ids are random UUIDs, so this is a fair sample."""
    return int(record_id.replace("-", ""), 16) % every == 0


def _percentiles(samples: list[float], prefix: str) -> dict[str, float | None]:
    """Nearest-rank p50/p95/p99 of samples in seconds; None where the rank is infinite."""
    ordered = sorted(samples)
    result: dict[str, float | None] = {}
    for p in PERCENTILES:
        value = ordered[max(math.ceil(p / 100 * len(ordered)) - 1, 0)] if ordered else math.inf
        result[f"{prefix}_p{p}_s"] = None if math.isinf(value) else value
    return result


def _statistics(
    run: SustainedRun,
    robots: list[_Robot],
    watcher: _Watcher,
    samples: list[dict[str, Any]],
    started: float,
    uploaded: float,
) -> dict[str, Any]:
    from sharing.models import Record

    uploads = [upload for robot in robots for upload in robot.uploads]
    accepted = watcher.accepted()
    sent = sum(upload.count for upload in uploads)
    window = (started + run.warmup, started + run.duration)
    in_window = [t for t in watcher.anchored.values() if window[0] <= t <= window[1]]
    transactions = set()
    ids = list(watcher.anchored)
    for start in range(0, len(ids), 900):
        transactions |= set(
            Record.objects.filter(pk__in=ids[start : start + 900]).values_list("tx_hash", flat=True)
        )
    viewed = [rid for rid in accepted if _sampled(rid, run.view_every)]
    row: dict[str, Any] = {
        "engines": run.engines,
        "mode": run.mode,
        "block_time_s": run.block_time,
        "batch_max": run.batch_max,
        "agents": run.agents,
        "rate_per_agent": run.rate,
        "flush_interval_s": run.flush_interval,
        "duration_s": run.duration,
        "upload_window_s": uploaded - started,
        "offered_per_s": run.agents * run.rate,
        "posts": len(uploads),
        "post_statuses": dict(Counter(upload.status for upload in uploads)),
        "sent": sent,
        "accepted": len(accepted),
        "accepted_per_s": len(accepted) / run.duration,
        "anchored": len(watcher.anchored),
        "failed_records": len(watcher.failed),
        "pending_after_drain": len(accepted) - len(watcher.anchored) - len(watcher.failed),
        "anchored_per_s": len(in_window) / (window[1] - window[0]),
        "anchored_overall_per_s": (
            len(watcher.anchored) / (max(watcher.anchored.values()) - started)
            if watcher.anchored
            else None
        ),
        "transactions": len(transactions),
        "records_per_transaction": len(watcher.anchored) / len(transactions)
        if transactions
        else None,
        "views": len(viewed),
        "verified_views": sum(rid in watcher.viewed for rid in viewed),
        "view_statuses": dict(watcher.view_statuses),
    }
    answered = [u for u in uploads if u.answered_at is not None]
    row |= _percentiles([u.answered_at - u.sent_at for u in answered], "response")
    row |= _percentiles(
        [watcher.anchored.get(rid, math.inf) - sent_at for rid, (sent_at, _) in accepted.items()],
        "to_anchored",
    )
    row |= _percentiles(
        [watcher.viewed.get(rid, math.inf) - accepted[rid][0] for rid in viewed], "to_verified"
    )
    steady = [s for s in samples if s["t"] <= run.duration]
    for group in GROUPS:
        cpu = [s[group]["cpu_pct"] for s in steady]
        rss = [s[group]["rss_mib"] for s in samples]
        row[f"{group}_cpu_mean_pct"] = sum(cpu) / len(cpu) if cpu else None
        row[f"{group}_cpu_max_pct"] = max(cpu, default=None)
        row[f"{group}_rss_peak_mib"] = max(rss, default=None)
    row["timeline"] = _timeline(run, uploads, watcher, samples, started)
    return row


def _timeline(
    run: SustainedRun,
    uploads: list[_Upload],
    watcher: _Watcher,
    samples: list[dict[str, Any]],
    started: float,
) -> dict[str, Any]:
    """Per-second counts of accepted and anchored records, and the resource samples."""
    end = max([*watcher.anchored.values(), started + run.duration]) - started
    seconds = int(end) + 1
    accepted = [0] * seconds
    anchored = [0] * seconds
    for upload in uploads:
        if upload.record_ids and upload.answered_at is not None:
            accepted[min(int(upload.answered_at - started), seconds - 1)] += len(upload.record_ids)
    for anchored_at in watcher.anchored.values():
        anchored[min(max(int(anchored_at - started), 0), seconds - 1)] += 1
    return {"accepted_per_s": accepted, "anchored_per_s": anchored, "resources": samples}


def _plot(report: dict[str, Any], path: Path) -> None:
    rows = report["results"]
    figure, axes = plt.subplots(2, 2, figsize=(12, 8))
    (rate_axis, latency_axis), (cpu_axis, memory_axis) = axes
    colours = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    engines = list(dict.fromkeys(row.get("engines", "sqlite-disk") for row in rows))
    for row, colour in zip(rows, colours * 4, strict=False):
        engine = row.get("engines", "sqlite-disk")
        label = f"{engine_label(engine, engines)}{row['mode']}, batch {row['batch_max']}"
        width = ENGINE_STYLES.get(engine, {}).get("linewidth", 1.2)
        timeline = row["timeline"]
        rate_axis.plot(
            timeline["anchored_per_s"], color=colour, linewidth=width, label=f"{label}: anchored"
        )
        rate_axis.plot(
            timeline["accepted_per_s"], color=colour, linestyle=":", alpha=0.6, label=None
        )
        quantiles = [row.get(f"to_anchored_p{p}_s") for p in PERCENTILES]
        views = [row.get(f"to_verified_p{p}_s") for p in PERCENTILES]
        latency_axis.plot(
            PERCENTILES, quantiles, "o-", color=colour, lw=width, label=f"{label}: anchored"
        )
        latency_axis.plot(
            PERCENTILES, views, "s--", color=colour, lw=width, label=f"{label}: viewed"
        )
        t = [sample["t"] for sample in timeline["resources"]]
        for group, style in (("web", "-"), ("workers", "--")):
            cpu_axis.plot(
                t,
                [sample[group]["cpu_pct"] for sample in timeline["resources"]],
                style,
                color=colour,
                linewidth=width,
                label=f"{label}: {group}",
            )
            memory_axis.plot(
                t,
                [sample[group]["rss_mib"] for sample in timeline["resources"]],
                style,
                color=colour,
                linewidth=width,
                label=f"{label}: {group}",
            )
    rate_axis.set_title("records per second (solid: anchored, dotted: accepted)")
    rate_axis.set_xlabel("seconds since the robots started")
    latency_axis.set_title("latency from the POST (s), by percentile")
    latency_axis.set_xlabel("percentile")
    latency_axis.set_yscale("log")
    cpu_axis.set_title("CPU, % of one core (solid: web, dashed: workers)")
    cpu_axis.set_xlabel("seconds since the robots started")
    memory_axis.set_title("resident memory, MiB (solid: web, dashed: workers)")
    memory_axis.set_xlabel("seconds since the robots started")
    for axis in (rate_axis, latency_axis, cpu_axis, memory_axis):
        axis.grid(True, alpha=0.3)
        axis.legend(fontsize=6)
    title = f"whole pipeline: {report['settings']['agents']}; {machine_line(report)}"
    save_figure(figure, path, title, fontsize=8)

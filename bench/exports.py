"""Exports of a day (issue 35; no paper figure): the streaming, sealed export against the
in-memory builder it replaced, measured in the same run on the same records.

- one fresh `make run` stack (bench/stack.py: anvil with automine, ANCHOR_MODE=root, the
  workers as make run starts them; no web server, no ROS), one owner registered on chain and
  one robot paired through the pairing services (its key confirmed on chain), as the demo
  robot is: every record is signed, and the export checks every signature and robotKeyOf.
- N records of nav_msgs/Odometry (the demo robot's shape, about 900 bytes of Fig. 4 JSON each,
  capture times 10 ms apart: a 100 Hz odometry) sealed and signed as its agent does
  (ros_agent.sealing), stored with record_create_batch 1,000 at a time in this process, and
  awaited until the workers anchored every one.
- each export in a fresh interpreter of its own (bench.run_in_child), which stands for the
  worker: it loads the Export row and runs the export task's service, then reports its wall
  time, its CPU time and its peak RSS (getrusage ru_maxrss: the whole process, Django and the
  libraries included), and how much of the time went to the integrity check every view runs
  (`_verified`: sharing.verification.check.records_verify, the part issue 35 asks to make one check
  path for N records; `own rec/s` is the rate without it). Variants:
  - `in-memory` (the baseline): sharing/exports.py as it was before issue 35
    (BASELINE_COMMIT, read with `git show`): every record of the selection in one list, the
    MCAP file built in a temporary file then read whole, the bundle built as one dict and
    serialised whole, both stored as plaintext. At B records (5,000: its cap).
  - `streaming` at B records and at N records (100,000): today's, batches of EXPORT_BATCH,
    both files sealed segment by segment, the bundle's entries spooled to disk.
- while each export runs, the share of the machine's CPU used by processes outside this
  benchmark's process tree (`others_cpu`: colleagues' test suites, the development stack) is
  sampled, so that a busy machine is on record beside the numbers.

Goals (issue 35): the export of N = 100,000 records at 1,000 records/s or more, with the
worker's peak RSS under 400 MiB. Ratios are streaming over in-memory at B. Figures, not
assertions.

Run: `python -m bench exports [--records N] [--baseline B] [--quick]`. Writes
bench/results/exports.json, exports.csv and exports.png.
"""

import argparse
import contextlib
import importlib.util
import json
import math
import os
import resource
import secrets
import subprocess
import sys
import tempfile
import threading
import time
import types
from dataclasses import dataclass
from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import Any

import psutil

from bench import MAKE_RUN_ANCHOR_MAX_WAIT, now_iso, run_in_child
from bench.common import check_redis_url, print_table, write_results
from bench.rest import report_header
from bench.stack import (
    BENCH_REDIS_URL,
    BenchStack,
    StackOptions,
    owners_register,
    robot_paired,
    run_finished,
)

NAME = "exports"
# The commit whose sharing/exports.py built exports in memory (before issue 35).
BASELINE_COMMIT = "03acc0e"
GOALS = {"records_per_s_at_least": 1000, "peak_rss_mib_below": 400}
UPLOAD_CHUNK = 1000
CAPTURE_STEP = timedelta(milliseconds=10)
T0 = datetime(2026, 5, 1, 0, 0, tzinfo=UTC)
FIELDS = (
    "variant",
    "records",
    "exported",
    "seconds",
    "records_per_s",
    "cpu_seconds",
    "peak_rss_mib",
    "rss_before_mib",
    "check_seconds",
    "own_records_per_s",
    "mcap_bytes",
    "bundle_bytes",
    "others_cpu",
    "rate_ratio",
    "rss_ratio",
)
COLUMNS = (
    ("variant", "variant", ""),
    ("records", "records", ""),
    ("rec/s", "records_per_s", ".0f"),
    ("peak MiB", "peak_rss_mib", ".0f"),
    ("idle MiB", "rss_before_mib", ".0f"),
    ("check s", "check_seconds", ".1f"),
    ("own rec/s", "own_records_per_s", ".0f"),
    ("cpu s", "cpu_seconds", ".1f"),
    ("others", "others_cpu", ".0%"),
    ("rate x", "rate_ratio", ".2f"),
    ("rss x", "rss_ratio", ".2f"),
)


@dataclass(frozen=True)
class ExportsRun:
    records: int
    baseline: int
    redis_url: str
    keep_logs: bool
    timeout: float
    workers: int = 2
    block_time: float | None = None
    batch_max: int = 500
    max_wait: float = MAKE_RUN_ANCHOR_MAX_WAIT


@dataclass(frozen=True)
class OneExport:
    """One export to run in a fresh interpreter against the stack's environment."""

    variant: str
    export_id: str
    environment: dict[str, str]


def odometry_plaintext(owner: str, seq: int, moment: datetime) -> bytes:
    """A Fig. 4 record of the demo robot's odometry, as the agent's extractor shapes it."""
    stamp = {"secs": int(moment.timestamp()), "nsecs": moment.microsecond * 1000}
    angle = seq / 1000
    data = {
        "header": {"seq": seq, "stamp": stamp, "frame_id": "odom"},
        "child_frame_id": "base_link",
        "position": {"x": math.cos(angle) * 5, "y": math.sin(angle) * 5, "z": 0.0},
        "orientation": {"x": 0.0, "y": 0.0, "z": math.sin(angle / 2), "w": math.cos(angle / 2)},
        "linear_velocity": {"x": 0.5, "y": 0.0, "z": 0.0},
        "angular_velocity": {"x": 0.0, "y": 0.0, "z": 0.1},
        "pose_covariance": [0.0] * 36,
        "twist_covariance": [0.0] * 36,
    }
    time_text = moment.isoformat().replace("+00:00", "Z")
    record = {"K": data, "Owner": owner, "Time": time_text, "Type": "nav_msgs/Odometry"}
    return json.dumps({**record, "Topic": "/odom"}, separators=(",", ":")).encode()


def baseline_module() -> types.ModuleType:
    """sharing/exports.py as of BASELINE_COMMIT, loaded as a module of its own."""
    source = subprocess.run(
        ["git", "show", f"{BASELINE_COMMIT}:sharing/exports.py"],
        capture_output=True,
        check=True,
        text=True,
        cwd=Path(__file__).resolve().parent.parent,
    ).stdout
    path = Path(tempfile.mkdtemp(prefix="bench-exports-baseline-")) / "in_memory_exports.py"
    path.write_text(source)
    spec = importlib.util.spec_from_file_location("bench_exports_in_memory", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def export_once(job: OneExport) -> dict[str, Any]:
    """In a fresh interpreter: run one export as the worker would, and measure it."""
    os.environ.update(job.environment)
    import django

    django.setup()
    from sharing.exports import run
    from sharing.models import Export

    runner = baseline_module() if job.variant == "in-memory" else run
    checking = CheckTime(runner)
    me = psutil.Process()
    rss_before = me.memory_info().rss
    watch = OthersCpu(me.pid)
    watch.start()
    cpu = me.cpu_times()
    started = time.perf_counter()
    runner.export_run(export_id=job.export_id)
    seconds = time.perf_counter() - started
    cpu_after = me.cpu_times()
    others = watch.stop()
    export = Export.objects.get(pk=job.export_id)
    return {
        "status": export.status,
        "error": export.error,
        "exported": export.exported,
        "seconds": seconds,
        "cpu_seconds": (cpu_after.user - cpu.user) + (cpu_after.system - cpu.system),
        "peak_rss_mib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
        "rss_before_mib": rss_before / 2**20,
        "mcap_bytes": export.mcap_size,
        "bundle_bytes": export.bundle_size,
        "others_cpu": others,
        "check_seconds": checking.seconds,
    }


class CheckTime:
    """The time an export spends in its integrity check (`_verified`: records_verify, the
    check every view runs, sharing/verification/check.py), apart from its own work."""

    def __init__(self, module: types.ModuleType) -> None:
        self.seconds = 0.0
        checked = module._verified

        def timed(*args: Any, **kwargs: Any) -> Any:
            started = time.perf_counter()
            try:
                return checked(*args, **kwargs)
            finally:
                self.seconds += time.perf_counter() - started

        module._verified = timed


class OthersCpu:
    """The share of the machine's CPU used by processes outside `pid`'s family (its parents
    and their children: this benchmark and its stack), sampled every second."""

    def __init__(self, pid: int) -> None:
        self._pid = pid
        self._samples: list[float] = []
        self._known: dict[int, psutil.Process] = {}
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def start(self) -> None:
        self._thread.start()

    def stop(self) -> float | None:
        self._stop.set()
        self._thread.join()
        return sum(self._samples) / len(self._samples) if self._samples else None

    def _ours(self) -> list[psutil.Process]:
        root = psutil.Process(self._pid)
        for parent in root.parents():
            if parent.name().startswith("python"):
                root = parent
        family = [root, *root.children(recursive=True)]
        # The same Process objects from one sample to the next: cpu_percent is since the last.
        for process in family:
            self._known.setdefault(process.pid, process)
        return [self._known[process.pid] for process in family]

    def _run(self) -> None:
        cores = psutil.cpu_count() or 1
        psutil.cpu_percent()
        for process in self._ours():
            with contextlib.suppress(psutil.Error):
                process.cpu_percent()
        while not self._stop.wait(1.0):
            total = psutil.cpu_percent() / 100
            ours = 0.0
            for process in self._ours():
                with contextlib.suppress(psutil.Error):
                    ours += process.cpu_percent() / 100 / cores
            self._samples.append(max(total - ours, 0.0))


def measure(run: ExportsRun) -> dict[str, Any]:
    """The stack, the records, then each export in a child of its own."""
    workdir = Path(tempfile.mkdtemp(prefix="bench-exports-"))
    stack = BenchStack(StackOptions.for_run(run, web=False, anchor_mode="root"), workdir)
    try:
        stack.start()
        robot, key, signing_key = _paired_robot(stack)
        _records_stored(stack, robot, key, signing_key, run.records, run.timeout)
        from django.conf import settings

        environment = dict(os.environ)
        rows = []
        for variant, count in (
            ("in-memory", run.baseline),
            ("streaming", run.baseline),
            ("streaming", run.records),
        ):
            export_id = _export_row(robot.owner, count)
            print(f"== {variant}, {count} records", flush=True)
            row = run_in_child(export_once, OneExport(variant, export_id, environment))
            row |= {"variant": variant, "records": count}
            row["records_per_s"] = row["exported"] / row["seconds"] if row["seconds"] else None
            own = row["seconds"] - row["check_seconds"]
            row["own_records_per_s"] = row["exported"] / own if own > 0 else None
            rows.append(row)
        result = {"results": rows, "export_batch": settings.EXPORT_BATCH}
    finally:
        stack.stop()
    return run_finished(result, stack, keep_logs=run.keep_logs)


def _paired_robot(stack: BenchStack) -> tuple[Any, bytes, Any]:
    """One owner on chain with one robot paired as the agent pairs (its key confirmed)."""
    ((hand_robot, key),) = owners_register(stack, 1)
    robot, signing_key = robot_paired(stack, hand_robot.owner, "demo-odometry")
    return robot, key, signing_key


def _records_stored(
    stack: BenchStack, robot: Any, key: bytes, signing_key: Any, count: int, timeout: float
) -> None:
    from ros_agent import sealing
    from sharing.models import Record
    from sharing.services.uploads import record_create_batch

    owner = robot.owner.username
    for start in range(1, count + 1, UPLOAD_CHUNK):
        envelopes = []
        for seq in range(start, min(start + UPLOAD_CHUNK, count + 1)):
            moment = T0 + CAPTURE_STEP * seq
            header = {
                "owner": owner,
                "robot": str(robot.id),
                "topic": "/odom",
                "type": "nav_msgs/Odometry",
                "seq": seq,
                "time": moment.isoformat().replace("+00:00", "Z"),
            }
            plaintext = odometry_plaintext(owner, seq, moment)
            envelopes.append(sealing.seal_record(key, header, plaintext, signing_key))
        record_create_batch(robot=robot, envelopes=envelopes)
        print(f"   stored {min(start + UPLOAD_CHUNK - 1, count)} of {count}", flush=True)

    def anchored() -> bool:
        return Record.objects.filter(robot=robot, status="anchored").count() == count

    stack.wait_for(anchored, "records not anchored", timeout=timeout)


def _export_row(owner: Any, count: int) -> str:
    """An Export of the first `count` records (by capture time), queued for no worker: the
    measured child runs it."""
    from django.utils import timezone

    from sharing.models import Export
    from sharing.selection import RecordSelection

    selection = RecordSelection(until=T0 + CAPTURE_STEP * (count + 1))
    export = Export.objects.create(
        requester=owner,
        selection=selection.as_json(),
        total=count,
        status=Export.Status.RUNNING,  # not queued: the sweep leaves it to us
        expires_at=timezone.now() + timedelta(hours=2),
    )
    return str(export.pk)


def ratios(rows: list[dict[str, Any]]) -> None:
    """Each streaming row against the in-memory row of the same size, where there is one."""
    baseline = {row["records"]: row for row in rows if row["variant"] == "in-memory"}
    for row in rows:
        base = baseline.get(row["records"])
        if base is None or row["variant"] == "in-memory":
            row["rate_ratio"] = row["rss_ratio"] = None
            continue
        row["rate_ratio"] = row["records_per_s"] / base["records_per_s"]
        row["rss_ratio"] = row["peak_rss_mib"] / base["peak_rss_mib"]


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench exports", description=__doc__)
    parser.add_argument("--records", type=int, default=100_000, help="the large export (100000)")
    parser.add_argument("--baseline", type=int, default=5_000, help="the in-memory one (5000)")
    parser.add_argument("--quick", action="store_true", help="10,000 and 2,000 records")
    parser.add_argument("--timeout", type=float, default=1800.0, help="to wait for anchoring")
    parser.add_argument("--redis-url", default=BENCH_REDIS_URL)
    parser.add_argument("--keep-logs", action="store_true")
    parser.add_argument("--results-dir", type=Path, default=Path(__file__).parent / "results")
    args = parser.parse_args(argv)
    check_redis_url(parser, args.redis_url)
    if args.quick:
        args.records, args.baseline = 10_000, 2_000
    if not 0 < args.baseline <= args.records:
        parser.error("--baseline must be between 1 and --records")
    started = now_iso()
    args.owners, args.workers, args.web_workers, args.verifiers = 1, 2, 0, 1
    args.max_wait = MAKE_RUN_ANCHOR_MAX_WAIT
    report = report_header(NAME, args, started)
    run = ExportsRun(
        records=args.records,
        baseline=args.baseline,
        redis_url=args.redis_url,
        keep_logs=args.keep_logs,
        timeout=args.timeout,
    )
    portal = run_in_child(measure, run)
    rows = portal["results"]
    ratios(rows)
    report["load_average_at_end"] = [round(load, 2) for load in psutil.getloadavg()]
    report["settings"] |= {
        "records": args.records,
        "baseline_records": args.baseline,
        "baseline_commit": BASELINE_COMMIT,
        "export_batch": portal.get("export_batch"),
        "record": "nav_msgs/Odometry, signed by a paired robot, 100 Hz capture times",
        "anchor_mode": "root",
        "chain": "anvil, automine",
        "run_id": secrets.token_hex(4),
    }
    report["goals"] = GOALS
    large = rows[-1]
    report["goals_met"] = {
        "records_per_s": (large["records_per_s"] or 0) >= GOALS["records_per_s_at_least"],
        "peak_rss": large["peak_rss_mib"] < GOALS["peak_rss_mib_below"],
    }
    report["results"] = rows
    print_table(report, COLUMNS)
    write_results(NAME, report, FIELDS, args.results_dir, plot=_plot)
    return 0 if all(row["status"] == "done" for row in rows) else 1


def _plot(report: dict[str, Any], path: Path) -> None:
    from bench.plotting import machine_line, plt, save_figure

    rows = report["results"]
    labels = [f"{row['variant']}\n{row['records']:,}" for row in rows]
    colours = ["#8c959f" if row["variant"] == "in-memory" else "#0969da" for row in rows]
    figure, (rate, memory) = plt.subplots(1, 2, figsize=(9, 3.6))
    rate.bar(labels, [row["records_per_s"] or 0 for row in rows], color=colours)
    rate.axhline(GOALS["records_per_s_at_least"], color="#cf222e", linestyle="--", linewidth=1)
    rate.set_ylabel("records exported per second")
    memory.bar(labels, [row["peak_rss_mib"] for row in rows], color=colours)
    memory.axhline(GOALS["peak_rss_mib_below"], color="#cf222e", linestyle="--", linewidth=1)
    memory.set_ylabel("export process peak RSS (MiB)")
    for axis in (rate, memory):
        axis.tick_params(axis="x", labelsize=8)
    save_figure(figure, path, f"Exports: in-memory vs streaming + sealed. {machine_line(report)}")


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))

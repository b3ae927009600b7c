"""Anchoring pipeline: anchored records per second and upload-to-anchored latency.

Issue 3, section 7. For ANCHOR_BATCH_MAX 1 (one record per transaction, the paper's way and
the baseline), 10 and 100, on anvil with automine and with `--block-time 1`. Every
configuration gets a fresh stack, `make run`'s without the portal (bench/stack.py): SQLite
database, anvil, contract, a chain worker with W pool processes, a verify worker and beat, all
sharing Redis DB 13 (flushed first). K owners are registered on chain by the workers,
then N envelopes of about 1 KB are uploaded through `sharing.services.uploads.record_create`,
round-robin over the owners' robots, as fast as one process can (or at `--rate`), and the
benchmark waits until every record is anchored.

Latency = Record.anchored_at - Record.created_at (upload committed to receipt seen by the
worker). Throughput = anchored records / (last anchored_at - first created_at). Batch sizes
10 and 100 are reported as ratios against batch size 1 measured in the same run.

Each configuration runs in its own spawned Python process: Django reads its settings from the
environment once, and the workers need new environment variables per batch size anyway.

Run: `python -m bench pipeline [--records N] [--owners K] [--workers W] [--quick]`.
Writes bench/results/pipeline.json, pipeline.csv and pipeline.png.
"""

import argparse
import sys
import tempfile
import time
from collections import Counter
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path
from typing import Any

import psutil

from bench import RESULTS_DIR, machine_info, now_iso, progress_bar, summarize
from bench.common import (
    PLAINTEXT_BYTES,
    add_ratios,
    check_redis_url,
    run_configurations,
    seal_record,
    write_results,
)
from bench.plotting import machine_line, plt, save_figure
from bench.stack import (
    BENCH_REDIS_URL,
    POLL_INTERVAL,
    BenchStack,
    StackOptions,
    block_mode,
    owners_register,
    run_finished,
)
from stack.anvil import anvil_version

BATCH_SIZES = (1, 10, 100)
BLOCK_TIMES: tuple[float | None, ...] = (None, 1.0)  # None: automine
QUICK = {"records": 20, "owners": 2, "workers": 2}
RATIO_NAMES = {
    "throughput_rps": "throughput_ratio_vs_batch1",
    "latency_p50_s": "latency_p50_ratio_vs_batch1",
    "latency_p95_s": "latency_p95_ratio_vs_batch1",
}


@dataclass(frozen=True)
class Configuration:
    """One measured configuration; the same for every batch size except batch_max/block_time."""

    block_time: float | None
    batch_max: int
    records: int
    owners: int
    workers: int
    max_wait: float
    rate: float  # uploads per second; 0 = as fast as one process can
    timeout: float
    redis_url: str
    keep_logs: bool

    @property
    def mode(self) -> str:
        return block_mode(self.block_time)

    def describe(self) -> str:
        return f"{self.mode}, ANCHOR_BATCH_MAX={self.batch_max}"

    def stack_options(self) -> StackOptions:
        """No portal: records are created through the service, in the benchmark's process."""
        return StackOptions.for_run(self, web=False)


def main(argv: list[str]) -> int:
    """Run every configuration, print the table and write JSON, CSV and PNG results."""
    parser = argparse.ArgumentParser(prog="python -m bench pipeline", description=__doc__)
    parser.add_argument("--records", type=int, default=300, help="uploads per configuration")
    parser.add_argument("--owners", type=int, default=3, help="owners (one robot each)")
    parser.add_argument(
        "--workers", type=int, default=2, help="pool processes of the chain worker (default 2)"
    )
    parser.add_argument(
        "--max-wait", type=float, default=0.2, help="ANCHOR_MAX_WAIT in seconds (default 0.2)"
    )
    parser.add_argument(
        "--rate", type=float, default=0.0, help="uploads per second; 0 = as fast as possible"
    )
    parser.add_argument(
        "--timeout", type=float, default=600.0, help="seconds to wait for anchoring per run"
    )
    parser.add_argument(
        "--quick",
        action="store_true",
        help=f"smoke run: {QUICK['records']} records, {QUICK['owners']} owners",
    )
    parser.add_argument(
        "--redis-url",
        default=BENCH_REDIS_URL,
        help="Redis database for the benchmark, FLUSHED before every configuration",
    )
    parser.add_argument(
        "--keep-logs", action="store_true", help="keep each configuration's directory and logs"
    )
    parser.add_argument("--results-dir", type=Path, default=RESULTS_DIR)
    args = parser.parse_args(argv)
    if args.quick:
        args.records, args.owners = QUICK["records"], QUICK["owners"]
    if min(args.records, args.owners, args.workers) < 1:
        parser.error("--records, --owners and --workers must be at least 1")
    check_redis_url(parser, args.redis_url)

    started = now_iso()
    load_at_start = [round(load, 2) for load in psutil.getloadavg()]  # other work on the host
    configurations = [
        Configuration(
            block_time=block_time,
            batch_max=batch_max,
            records=args.records,
            owners=args.owners,
            workers=args.workers,
            max_wait=args.max_wait,
            rate=args.rate,
            timeout=args.timeout,
            redis_url=args.redis_url,
            keep_logs=args.keep_logs,
        )
        for block_time in BLOCK_TIMES
        for batch_max in BATCH_SIZES
    ]
    rows = run_configurations(configurations, _measure)
    add_ratios(rows, ("mode",), RATIO_NAMES)
    portal_settings = rows[0]["portal_settings"]
    for row in rows:
        del row["portal_settings"]
    report = {
        "benchmark": "pipeline",
        "date": started,
        "machine": machine_info(("celery", "django", "web3", "redis", "matplotlib")),
        "anvil": anvil_version(),
        "load_average_at_start": load_at_start,
        "settings": {
            "records": args.records,
            "owners": args.owners,
            "workers": args.workers,
            "stack": "`python -m stack run --no-ros --no-web` (what `make run` execs, without "
            "the portal), a fresh one for each configuration",
            "worker_command": f"celery -A portal worker -c {args.workers} --pool prefork, "
            "one more -c 1 for the verify queue alone, and one beat, as make run starts them",
            "batch_sizes": list(BATCH_SIZES),
            "block_times": ["automine" if b is None else b for b in BLOCK_TIMES],
            "anchor_max_wait_s": args.max_wait,
            "upload_rate_per_s": args.rate or "as fast as possible",
            "plaintext_bytes": PLAINTEXT_BYTES,
            "timeout_s": args.timeout,
            "quick": args.quick,
            **portal_settings,
        },
        "notes": _notes(args),
        "results": rows,
    }
    _print_table(report)
    write_results("pipeline", report, CSV_FIELDS, args.results_dir, plot=_plot)
    incomplete = [row for row in rows if row["pending"] or row["failed"]]
    return 1 if incomplete else 0


def _notes(args: argparse.Namespace) -> list[str]:
    upload = (
        f"uploads paced at {args.rate:g}/s"
        if args.rate
        else "uploads as fast as one process can (record_create, one envelope per call)"
    )
    return [
        f"{upload}, round-robin over {args.owners} owners (one robot each).",
        "latency = anchored_at - created_at: upload committed to the worker seeing the receipt.",
        "throughput = anchored records / (last anchored_at - first created_at); upl/s is the "
        "upload rate: where throughput comes close to it, the single uploader was the limit.",
        "batch size = ANCHOR_BATCH_MAX; ratio columns divide by batch size 1 of the same "
        "block mode in this run (throughput: higher is better; latency: lower is better).",
        "every process (anvil, workers, beat, the uploading bench process) shares this machine.",
    ]


# --- one configuration, in a child process --------------------------------------------------


def _measure(configuration: Configuration) -> dict[str, Any]:
    """Start the stack, register owners, upload, wait for anchoring, stop; the row of results."""
    workdir = Path(tempfile.mkdtemp(prefix="authros-bench-pipeline-"))
    stack = BenchStack(configuration.stack_options(), workdir)
    try:
        stack.start()
        robots = owners_register(stack, configuration.owners)
        _upload(configuration, robots)
        _await_anchoring(configuration, stack)
        row = _statistics(configuration)
    finally:
        stack.stop()
    row["portal_settings"] = stack.portal_settings
    return run_finished(row, stack, keep_logs=configuration.keep_logs)


def _upload(configuration: Configuration, robots: list[tuple[Any, bytes]]) -> None:
    """Upload the records round-robin over the robots, paced if --rate is given."""
    from sharing.services.uploads import record_create

    started = time.monotonic()
    with progress_bar(configuration.records, "uploaded", unit="rec") as progress:
        for number in range(configuration.records):
            if configuration.rate:
                time.sleep(max(started + number / configuration.rate - time.monotonic(), 0))
            robot, key = robots[number % len(robots)]
            seq = number // len(robots) + 1
            record_create(robot=robot, data=seal_record(robot, key, seq=seq))
            progress.update(1)


def _await_anchoring(configuration: Configuration, stack: BenchStack) -> None:
    """Until every record is anchored or failed, or the timeout."""
    from sharing.models import Record

    deadline = time.monotonic() + configuration.timeout
    with progress_bar(configuration.records, "anchored", unit="rec") as progress:
        while True:
            settled = Record.objects.exclude(status=Record.Status.PENDING).count()
            progress.update(settled - progress.n)
            if settled >= configuration.records:
                return
            stack.check_alive()
            if time.monotonic() > deadline:
                print(
                    f"timed out after {configuration.timeout:.0f}s with "
                    f"{configuration.records - settled} records pending",
                    file=sys.stderr,
                )
                return
            time.sleep(POLL_INTERVAL)


def _statistics(configuration: Configuration) -> dict[str, Any]:
    from sharing.models import Record

    rows = list(Record.objects.values("owner_id", "created_at", "anchored_at", "tx_hash", "status"))
    anchored = [row for row in rows if row["status"] == Record.Status.ANCHORED]
    statuses = Counter(row["status"] for row in rows)
    first_upload = min(row["created_at"] for row in rows)
    last_upload = max(row["created_at"] for row in rows)
    result: dict[str, Any] = {
        "mode": configuration.mode,
        "block_time_s": configuration.block_time,
        "batch_max": configuration.batch_max,
        "records": len(rows),
        "owners": configuration.owners,
        "workers": configuration.workers,
        "anchored": len(anchored),
        "pending": statuses.get(Record.Status.PENDING, 0),
        "failed": statuses.get(Record.Status.FAILED, 0),
        "upload_seconds": (last_upload - first_upload).total_seconds(),
        "upload_rps": (len(rows) - 1) / (last_upload - first_upload).total_seconds()
        if last_upload > first_upload
        else None,
    }
    if not anchored:
        return {**result, "throughput_rps": 0.0, "transactions": 0}
    last_anchored = max(row["anchored_at"] for row in anchored)
    latencies_ms = [
        (row["anchored_at"] - row["created_at"]).total_seconds() * 1000 for row in anchored
    ]
    latency = summarize(latencies_ms)
    per_transaction = Counter(row["tx_hash"] for row in anchored)
    return {
        **result,
        "elapsed_seconds": (last_anchored - first_upload).total_seconds(),
        "throughput_rps": len(anchored) / (last_anchored - first_upload).total_seconds(),
        "latency_p50_s": latency["median_ms"] / 1000,
        "latency_p95_s": latency["p95_ms"] / 1000,
        "latency_mean_s": latency["mean_ms"] / 1000,
        "latency_max_s": latency["max_ms"] / 1000,
        "transactions": len(per_transaction),
        "records_per_transaction_mean": len(anchored) / len(per_transaction),
        "records_per_transaction_max": max(per_transaction.values()),
        "per_owner": _per_owner(anchored, first_upload),
    }


def _per_owner(anchored: list[dict[str, Any]], start: datetime) -> list[dict[str, Any]]:
    """When each owner's records were anchored, in seconds after the first upload."""
    owners = sorted({row["owner_id"] for row in anchored})
    summary = []
    for owner_id in owners:
        own = [row for row in anchored if row["owner_id"] == owner_id]
        times = [(row["anchored_at"] - start).total_seconds() for row in own]
        summary.append(
            {
                "records": len(own),
                "transactions": len({row["tx_hash"] for row in own}),
                "first_anchored_s": min(times),
                "last_anchored_s": max(times),
            }
        )
    return summary


# --- reporting ---------------------------------------------------------------------------------


def _ratio(value: float | None) -> str:
    return f"{value:.2f}x" if value is not None else "-"


def _print_table(report: dict[str, Any]) -> None:
    machine, settings = report["machine"], report["settings"]
    print(
        f"pipeline benchmark, {report['date']}: {machine['cpu_model']}, "
        f"{machine['logical_cores']} cores, {machine['memory_bytes'] / 2**30:.1f} GiB, "
        f"{machine['python']}, {report['anvil']}"
    )
    print(
        f"  {settings['records']} records, {settings['owners']} owners, "
        f"{settings['workers']} workers, ANCHOR_MAX_WAIT {settings['anchor_max_wait_s']:g}s; "
        f"load average at start {report['load_average_at_start']}"
    )
    for note in report["notes"]:
        print(f"  note: {note}")
    header = (
        f"{'mode':<15} {'batch':>5} {'anchored':>8} {'txs':>5} {'rec/tx':>6} {'upl/s':>6} "
        f"{'rec/s':>7} {'x b1':>7} {'p50 s':>7} {'p95 s':>7} {'p50 x b1':>8} {'p95 x b1':>8}"
    )
    print(header)
    print("-" * len(header))
    for row in report["results"]:
        if not row["anchored"]:
            print(f"{row['mode']:<15} {row['batch_max']:>5} {0:>8}  nothing anchored")
            continue
        print(
            f"{row['mode']:<15} {row['batch_max']:>5} {row['anchored']:>5}/{row['records']:<3}"
            f"{row['transactions']:>5} {row['records_per_transaction_mean']:>6.1f} "
            f"{row['upload_rps'] or 0:>6.1f} {row['throughput_rps']:>7.1f} "
            f"{_ratio(row['throughput_ratio_vs_batch1']):>7} {row['latency_p50_s']:>7.2f} "
            f"{row['latency_p95_s']:>7.2f} {_ratio(row['latency_p50_ratio_vs_batch1']):>8} "
            f"{_ratio(row['latency_p95_ratio_vs_batch1']):>8}"
        )


CSV_FIELDS = (
    "mode",
    "block_time_s",
    "batch_max",
    "records",
    "owners",
    "workers",
    "anchored",
    "pending",
    "failed",
    "transactions",
    "records_per_transaction_mean",
    "records_per_transaction_max",
    "upload_seconds",
    "upload_rps",
    "elapsed_seconds",
    "throughput_rps",
    "throughput_ratio_vs_batch1",
    "latency_p50_s",
    "latency_p95_s",
    "latency_mean_s",
    "latency_max_s",
    "latency_p50_ratio_vs_batch1",
    "latency_p95_ratio_vs_batch1",
)


def _plot(report: dict[str, Any], path: Path) -> None:
    rows = [row for row in report["results"] if row["anchored"]]
    figure, (left, right) = plt.subplots(1, 2, figsize=(12, 5))
    colours = {"automine": "tab:blue"}
    for mode in dict.fromkeys(row["mode"] for row in rows):
        measured = [row for row in rows if row["mode"] == mode]
        batches = [row["batch_max"] for row in measured]
        colour = colours.get(mode, "tab:red")
        throughput = [row["throughput_rps"] for row in measured]
        left.plot(batches, throughput, "o-", color=colour, label=f"{mode}: anchored")
        left.plot(
            batches,
            [row["upload_rps"] for row in measured],
            "x:",
            color=colour,
            alpha=0.6,
            label=f"{mode}: upload rate (ceiling)",
        )
        for row, value in zip(measured, throughput, strict=True):
            ratio = row["throughput_ratio_vs_batch1"]
            left.annotate(
                f"{value:.1f}/s" + (f" ({ratio:.1f}x)" if ratio and row["batch_max"] != 1 else ""),
                (row["batch_max"], value),
                textcoords="offset points",
                xytext=(4, 6),
                fontsize=8,
                color=colour,
            )
        right.plot(
            batches,
            [row["latency_p50_s"] for row in measured],
            "o-",
            color=colour,
            label=f"{mode} p50",
        )
        right.plot(
            batches,
            [row["latency_p95_s"] for row in measured],
            "s--",
            color=colour,
            label=f"{mode} p95",
        )
    for axis in (left, right):
        axis.set_xscale("log")
        axis.set_xticks(list(BATCH_SIZES), [str(size) for size in BATCH_SIZES])
        axis.set_xlim(BATCH_SIZES[0] / 1.5, BATCH_SIZES[-1] * 2.5)
        axis.set_xlabel("ANCHOR_BATCH_MAX (records per dataUploadBatch)")
        axis.grid(True, which="both", alpha=0.3)
        axis.legend(fontsize=8)
    left.set_yscale("log")
    left.set_ylabel("anchored records per second (log)")
    left.set_title("throughput")
    right.set_yscale("log")
    right.set_ylabel("upload-to-anchored latency, s (log)")
    right.set_title("latency p50 / p95")
    settings = report["settings"]
    save_figure(
        figure,
        path,
        f"anchoring pipeline: {settings['records']} records, {settings['owners']} owners, "
        f"{settings['workers']} workers, ANCHOR_MAX_WAIT {settings['anchor_max_wait_s']:g}s; "
        f"{machine_line(report)}",
    )

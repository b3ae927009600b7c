"""Exports of a day and their check without the portal (issues 35, 45; no paper figure): the
export of N records and `authros-verify` on it, today's code against a baseline measured in the
same run on the same records (a git worktree of the baseline commit, by default main's).

- one fresh `make run` stack (bench/stack.py: anvil with automine, ANCHOR_MODE=root, the
  workers as make run starts them; no web server, no ROS), one owner registered on chain and
  one robot paired through the pairing services (its key confirmed on chain), as the demo
  robot is: every record is signed as its agent signs them today, one SM2 signature per upload
  batch of SIGN_BATCH (provenance v2), and every export checks every record.
- the largest count of records of nav_msgs/Odometry (the demo robot's shape, about 900 bytes
  of Fig. 4 JSON each, capture times 10 ms apart: a 100 Hz odometry) stored with
  record_create_batch 1,000 at a time in this process, and awaited until the workers
  anchored every one. Each count (10,000, 30,000 and 100,000 by default) exports the first
  records of that many.
- each export in a fresh interpreter of its own (bench/exports_child.py with PYTHONPATH the
  tree: today's, or the baseline's worktree), which stands for the worker: it loads the
  Export row and runs the export task's service, then reports its wall time, its CPU time,
  its peak RSS (getrusage ru_maxrss: the whole process, Django and the libraries included)
  and how much of the time went to the integrity check every view runs (`_verified`:
  sharing.verification.check.records_verify; `own rec/s` is the rate without it).
- today's export's two files, downloaded as its requester would, checked by each verifier as
  an auditor runs it: `python -m authros_verify BUNDLE --mcap FILE --rpc anvil --contract ..`
  in a process of its own (the baseline's tree, today's, and today's with `--jobs J`), its
  wall time, CPU time (its forked processes included), peak RSS (wait4's ru_maxrss: the
  largest process) and the peak of its processes' memory summed (PSS: the pages they share
  counted once), sampled every 0.2 s.
- while each export or check runs, the share of the machine's CPU used by processes outside
  this benchmark's process tree (`others_cpu`: colleagues' test suites, the development
  stack) is sampled, so that a busy machine is on record beside the numbers.

Goals (issue 45): the export of 100,000 records at 3,000 records/s or more with the worker's
peak RSS at most 400 MiB; `authros-verify` on it at 5,000 records/s or more with at most
300 MiB. Ratios are today's over the baseline's at the same count. Figures, not assertions.

Run: `python -m bench exports [--counts 10000,30000,100000] [--baseline-ref main] [--jobs 2]
[--quick]`. Writes bench/results/exports.json, exports.csv and exports.png, and each row
as it is measured to exports.rows.jsonl.
"""

import argparse
import contextlib
import json
import math
import os
import secrets
import subprocess
import sys
import tempfile
import threading
import time
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
REPO = Path(__file__).resolve().parent.parent
CHILD = Path(__file__).resolve().parent / "exports_child.py"
GOALS = {
    "export_records_per_s_at_least": 3000,
    "export_peak_rss_mib_at_most": 400,
    "verify_records_per_s_at_least": 5000,
    "verify_peak_rss_mib_at_most": 300,
}
COUNTS = (10_000, 30_000, 100_000)
UPLOAD_CHUNK = 1000
SIGN_BATCH = 50  # the agent's upload batch (ros_agent/config.py batch_size), signed once
CAPTURE_STEP = timedelta(milliseconds=10)
T0 = datetime(2026, 5, 1, 0, 0, tzinfo=UTC)
FIELDS = (
    "step",
    "variant",
    "records",
    "exported",
    "seconds",
    "records_per_s",
    "cpu_seconds",
    "peak_rss_mib",
    "peak_memory_total_mib",
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
    ("step", "step", ""),
    ("variant", "variant", ""),
    ("records", "records", ""),
    ("rec/s", "records_per_s", ".0f"),
    ("peak MiB", "peak_rss_mib", ".0f"),
    ("all MiB", "peak_memory_total_mib", ".0f"),
    ("check s", "check_seconds", ".1f"),
    ("cpu s", "cpu_seconds", ".1f"),
    ("others", "others_cpu", ".0%"),
    ("rate x", "rate_ratio", ".2f"),
    ("rss x", "rss_ratio", ".2f"),
)


@dataclass(frozen=True)
class ExportsRun:
    counts: tuple[int, ...]
    baseline_commit: str
    jobs: int
    redis_url: str
    keep_logs: bool
    timeout: float
    workers: int = 2
    block_time: float | None = None
    batch_max: int = 500
    max_wait: float = MAKE_RUN_ANCHOR_MAX_WAIT
    # Each row also appended here as soon as it is measured (JSON lines), so that a run cut
    # short on a busy machine still leaves the figures it made.
    rows_file: Path | None = None


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
    """The stack, the records, then at each count the baseline's export and today's, each in
    an interpreter of its own, and today's files checked by each verifier."""
    workdir = Path(tempfile.mkdtemp(prefix="bench-exports-"))
    stack = BenchStack(StackOptions.for_run(run, web=False, anchor_mode="root"), workdir)
    baseline = workdir / "baseline"
    _worktree_add(baseline, run.baseline_commit)
    try:
        stack.start()
        robot, key, signing_key = _paired_robot(stack)
        _records_stored(stack, robot, key, signing_key, max(run.counts), run.timeout)
        from django.conf import settings

        from chainworker.services import chain_client

        client = chain_client()
        chain = {
            "rpc": os.environ["CHAIN_RPC_URL"],
            "contract": client.address,
            "chain_id": client.chain_id,
        }
        rows = []
        for count in run.counts:
            files = None
            for variant, tree in (("baseline", baseline), ("today", REPO)):
                export_id = _export_row(robot.owner, count)
                print(f"== export, {variant}, {count} records", flush=True)
                row = _export_measured(export_id, tree)
                rows.append({"step": "export", "variant": variant, "records": count, **row})
                _row_kept(run, rows[-1])
                if variant == "today":
                    files = _export_files(robot.owner, export_id, workdir)
            verifiers = [("baseline", baseline, 1), ("today --jobs 1", REPO, 1)]
            if run.jobs > 1:
                verifiers.append((f"today --jobs {run.jobs}", REPO, run.jobs))
            for variant, tree, jobs in verifiers:
                print(f"== authros-verify, {variant}, {count} records", flush=True)
                row = _verify_measured(files, chain, tree, jobs)
                rows.append({"step": "verify", "variant": variant, "records": count, **row})
                _row_kept(run, rows[-1])
            for path in files:
                path.unlink()
        result = {"results": rows, "export_batch": settings.EXPORT_BATCH}
    finally:
        stack.stop()
        _worktree_remove(baseline)
    return run_finished(result, stack, keep_logs=run.keep_logs)


def _row_kept(run: ExportsRun, row: dict[str, Any]) -> None:
    if run.rows_file is not None:
        with run.rows_file.open("a") as rows:
            rows.write(json.dumps({"at": now_iso(), **row}) + "\n")


def _worktree_add(path: Path, commit: str) -> None:
    """The baseline's code: a detached worktree of `commit` (removed at the end)."""
    subprocess.run(
        ["git", "worktree", "add", "--detach", str(path), commit],
        cwd=REPO,
        check=True,
        capture_output=True,
    )


def _worktree_remove(path: Path) -> None:
    subprocess.run(
        ["git", "worktree", "remove", "--force", str(path)], cwd=REPO, capture_output=True
    )


def _environment(tree: Path) -> dict[str, str]:
    return {**os.environ, "PYTHONPATH": str(tree)}


def _export_measured(export_id: str, tree: Path) -> dict[str, Any]:
    """One export in bench/exports_child.py, the portal's code from `tree`."""
    watch = OthersCpu(os.getpid())
    watch.start()
    try:
        done = subprocess.run(
            [sys.executable, str(CHILD), export_id],
            cwd=tree,
            env=_environment(tree),
            capture_output=True,
            text=True,
            check=False,
        )
    finally:
        others = watch.stop()
    if done.returncode != 0:
        raise RuntimeError(f"the export child failed: {done.stderr[-2000:]}")
    row = json.loads(done.stdout.strip().splitlines()[-1])
    row["others_cpu"] = others
    row["records_per_s"] = row["exported"] / row["seconds"] if row["seconds"] else None
    own = row["seconds"] - row["check_seconds"]
    row["own_records_per_s"] = row["exported"] / own if own > 0 else None
    return row


def _export_files(owner: Any, export_id: str, workdir: Path) -> tuple[Path, Path]:
    """(bundle, MCAP file) of a ready export, downloaded as its requester would."""
    from sharing.exports.download import export_download

    paths = (workdir / f"{export_id}.proofs.json", workdir / f"{export_id}.mcap")
    for path, part in zip(paths, ("bundle", "mcap"), strict=True):
        with path.open("wb") as target:
            for chunk in export_download(requester=owner, export_id=export_id, part=part).chunks():
                target.write(chunk)
    return paths


def _verify_measured(
    files: tuple[Path, Path], chain: dict[str, Any], tree: Path, jobs: int
) -> dict[str, Any]:
    """`python -m authros_verify` of `tree` on the files, as an auditor runs it."""
    bundle, mcap = files
    command = [
        *(sys.executable, "-m", "authros_verify", str(bundle), "--mcap", str(mcap)),
        *("--rpc", chain["rpc"], "--contract", chain["contract"]),
        *("--chain-id", str(chain["chain_id"])),
        # Always named: the command's default is one process per core.
        *("--jobs", str(jobs)),
    ]
    watch = OthersCpu(os.getpid())
    watch.start()
    started = time.perf_counter()
    with open(os.devnull, "w") as quiet:
        process = subprocess.Popen(
            command, cwd=tree, env=_environment(tree), stdout=subprocess.PIPE, stderr=quiet
        )
    total = TreeRss(process.pid)
    total.start()
    tail = process.stdout.read().decode(errors="replace").strip().splitlines()[-3:]
    _pid, status, usage = os.wait4(process.pid, 0)
    process.returncode = os.waitstatus_to_exitcode(status)
    seconds = time.perf_counter() - started
    others = watch.stop()
    peak_total = total.stop()
    records = sum(1 for _ in _record_lines(bundle))
    return {
        "exit": process.returncode,
        "last_lines": tail,
        "exported": records,
        "jobs": jobs,
        "seconds": seconds,
        "records_per_s": records / seconds,
        "cpu_seconds": usage.ru_utime + usage.ru_stime,
        "peak_rss_mib": usage.ru_maxrss / 1024,
        "peak_memory_total_mib": peak_total,
        "others_cpu": others,
    }


def _record_lines(bundle: Path) -> Any:
    """The bundle's record lines (one a record, after the head and before the closing)."""
    with bundle.open("rb") as lines:
        for number, line in enumerate(lines):
            if number >= 2 and line != b"]}\n":
                yield line


class TreeRss:
    """The peak of the memory of a process and its children, sampled every 0.2 s: their PSS
    summed (the pages forked processes share counted once, not in each one's RSS)."""

    def __init__(self, pid: int) -> None:
        self._pid = pid
        self.peak = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def start(self) -> None:
        self._thread.start()

    def stop(self) -> float:
        self._stop.set()
        self._thread.join()
        return self.peak / 2**20

    def _run(self) -> None:
        while not self._stop.is_set():
            with contextlib.suppress(psutil.Error):
                root = psutil.Process(self._pid)
                total = 0
                for process in (root, *root.children(recursive=True)):
                    with contextlib.suppress(psutil.Error):
                        total += process.memory_full_info().pss
                self.peak = max(self.peak, total)
            self._stop.wait(0.2)


def _paired_robot(stack: BenchStack) -> tuple[Any, bytes, Any]:
    """One owner on chain with one robot paired as the agent pairs (its key confirmed)."""
    ((hand_robot, key),) = owners_register(stack, 1)
    robot, signing_key = robot_paired(stack, hand_robot.owner, "demo-odometry")
    return robot, key, signing_key


def _records_stored(
    stack: BenchStack, robot: Any, key: bytes, signing_key: Any, count: int, timeout: float
) -> None:
    """`count` odometry records, signed SIGN_BATCH at a time as the agent signs its upload
    batches (provenance v2, each record's topic_seq its number on /odom), stored 1,000 at a
    time and awaited until anchored."""
    from sharing.models import Record
    from sharing.services.uploads import record_create_batch
    from smcrypto import envelope, provenance

    owner = robot.owner.username
    for start in range(1, count + 1, UPLOAD_CHUNK):
        envelopes = []
        seqs = range(start, min(start + UPLOAD_CHUNK, count + 1))
        for first in range(0, len(seqs), SIGN_BATCH):
            records = []
            for seq in seqs[first : first + SIGN_BATCH]:
                moment = T0 + CAPTURE_STEP * seq
                header = {
                    "owner": owner,
                    "robot": str(robot.id),
                    "topic": "/odom",
                    "type": "nav_msgs/Odometry",
                    "seq": seq,
                    "time": moment.isoformat().replace("+00:00", "Z"),
                    "topic_seq": seq - 1,
                }
                records.append((header, odometry_plaintext(owner, seq, moment)))
            headers = provenance.sign_batch(
                signing_key.private_key, signing_key.public_key, records
            )
            envelopes += [
                envelope.seal(key, header, plaintext)
                for header, (_, plaintext) in zip(headers, records, strict=True)
            ]
        record_create_batch(robot=robot, envelopes=envelopes)
        print(f"   stored {seqs[-1]} of {count}", flush=True)

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
    """Each of today's rows against the baseline's of the same step and count."""
    baseline = {(row["step"], row["records"]): row for row in rows if row["variant"] == "baseline"}
    for row in rows:
        base = baseline.get((row["step"], row["records"]))
        if base is None or row is base or not base["records_per_s"]:
            row["rate_ratio"] = row["rss_ratio"] = None
            continue
        row["rate_ratio"] = row["records_per_s"] / base["records_per_s"]
        row["rss_ratio"] = row["peak_rss_mib"] / base["peak_rss_mib"]


def goals_met(rows: list[dict[str, Any]]) -> dict[str, bool]:
    """The goals judged on today's rows at the largest count (the best of today's verifiers)."""
    largest = max(row["records"] for row in rows)
    today = [row for row in rows if row["records"] == largest and row["variant"] != "baseline"]
    export = next(row for row in today if row["step"] == "export")
    checks = [row for row in today if row["step"] == "verify"]
    return {
        "export_records_per_s": export["records_per_s"] >= GOALS["export_records_per_s_at_least"],
        "export_peak_rss": export["peak_rss_mib"] <= GOALS["export_peak_rss_mib_at_most"],
        "verify_records_per_s": max(row["records_per_s"] for row in checks)
        >= GOALS["verify_records_per_s_at_least"],
        "verify_peak_rss": min(_verify_rss(row) for row in checks)
        <= GOALS["verify_peak_rss_mib_at_most"],
    }


def _verify_rss(row: dict[str, Any]) -> float:
    """A check's memory: its largest process's peak, or its processes' summed, if larger."""
    return max(row["peak_rss_mib"], row["peak_memory_total_mib"])


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench exports", description=__doc__)
    parser.add_argument(
        "--counts",
        default=",".join(str(count) for count in COUNTS),
        help="the export sizes, comma separated (10000,30000,100000)",
    )
    parser.add_argument("--baseline-ref", default="main", help="the baseline's commit (main)")
    parser.add_argument("--jobs", type=int, default=2, help="today's verifier also with --jobs")
    parser.add_argument("--quick", action="store_true", help="2,000 and 10,000 records")
    parser.add_argument("--timeout", type=float, default=1800.0, help="to wait for anchoring")
    parser.add_argument("--redis-url", default=BENCH_REDIS_URL)
    parser.add_argument("--keep-logs", action="store_true")
    parser.add_argument("--results-dir", type=Path, default=Path(__file__).parent / "results")
    args = parser.parse_args(argv)
    check_redis_url(parser, args.redis_url)
    counts = (2_000, 10_000) if args.quick else tuple(int(c) for c in args.counts.split(","))
    if not counts or min(counts) < 1:
        parser.error("--counts are whole numbers above 0")
    commit = subprocess.run(
        ["git", "rev-parse", "--short", args.baseline_ref],
        cwd=REPO,
        capture_output=True,
        text=True,
        check=True,
    ).stdout.strip()
    started = now_iso()
    args.owners, args.workers, args.web_workers, args.verifiers = 1, 2, 0, 1
    args.max_wait = MAKE_RUN_ANCHOR_MAX_WAIT
    report = report_header(NAME, args, started)
    run = ExportsRun(
        counts=tuple(sorted(counts)),
        baseline_commit=commit,
        jobs=args.jobs,
        redis_url=args.redis_url,
        keep_logs=args.keep_logs,
        timeout=args.timeout,
        rows_file=args.results_dir / f"{NAME}.rows.jsonl",
    )
    args.results_dir.mkdir(parents=True, exist_ok=True)
    portal = run_in_child(measure, run)
    rows = portal["results"]
    ratios(rows)
    report["load_average_at_end"] = [round(load, 2) for load in psutil.getloadavg()]
    report["settings"] |= {
        "counts": list(run.counts),
        "baseline_ref": args.baseline_ref,
        "baseline_commit": commit,
        "verify_jobs": args.jobs,
        "export_batch": portal.get("export_batch"),
        "sign_batch": SIGN_BATCH,
        "record": "nav_msgs/Odometry, signed by a paired robot in batches (provenance v2), "
        "100 Hz capture times",
        "anchor_mode": "root",
        "chain": "anvil, automine",
        "run_id": secrets.token_hex(4),
    }
    report["goals"] = GOALS
    report["goals_met"] = goals_met(rows)
    report["results"] = rows
    print_table(report, COLUMNS)
    write_results(NAME, report, FIELDS, args.results_dir, plot=_plot)
    exports_done = all(row.get("status", "done") == "done" for row in rows)
    return 0 if exports_done and all(row.get("exit", 0) == 0 for row in rows) else 1


def _plot(report: dict[str, Any], path: Path) -> None:
    from bench.plotting import machine_line, plt, save_figure

    rows = report["results"]
    figure, axes = plt.subplots(2, 2, figsize=(10, 6.4))
    targets = {
        "export": ("export_records_per_s_at_least", "export_peak_rss_mib_at_most"),
        "verify": ("verify_records_per_s_at_least", "verify_peak_rss_mib_at_most"),
    }
    for column, step in enumerate(("export", "verify")):
        rate, memory = axes[0][column], axes[1][column]
        variants = dict.fromkeys(row["variant"] for row in rows if row["step"] == step)
        for variant in variants:
            mine = [row for row in rows if row["step"] == step and row["variant"] == variant]
            counts = [row["records"] for row in mine]
            style = {"color": "#8c959f"} if variant == "baseline" else {}
            rate.plot(counts, [row["records_per_s"] for row in mine], "o-", label=variant, **style)
            rss = "peak_memory_total_mib" if step == "verify" else "peak_rss_mib"
            memory.plot(counts, [row[rss] for row in mine], "o-", label=variant, **style)
        rate_goal, rss_goal = targets[step]
        rate.axhline(report["goals"][rate_goal], color="#cf222e", linestyle="--", linewidth=1)
        memory.axhline(report["goals"][rss_goal], color="#cf222e", linestyle="--", linewidth=1)
        name = "export" if step == "export" else "authros-verify"
        rate.set_title(f"{name}: records per second")
        memory.set_title(f"{name}: peak RSS (MiB)")
        memory.set_xlabel("records")
        for axis in (rate, memory):
            axis.legend(fontsize=7)
            axis.set_xscale("log")
    save_figure(figure, path, f"Exports and their check, today vs baseline. {machine_line(report)}")


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))

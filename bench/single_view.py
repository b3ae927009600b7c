"""A single record's verified view: the check asked of a verify worker through Redis
(sharing/verification/direct.py) against the same check sent as the Celery task
(VERIFY_DIRECT off), in alternation on one stack, so that both see the same machine.

One fresh `make run` stack (bench/stack.py: root mode, anvil automine, make run's workers and
web server), one owner registered on chain with one robot added by hand (unsigned) and one
paired robot signing each upload batch once (v2); R records of each uploaded through the upload
service, 100 per batch, and awaited on chain. Then:

- in-process: `sharing.verification.opening.record_open`, the web's own code for a record page
  and a content answer, called from this process (pointed at the stack's database, Redis and
  chain), V times per way, direct and task alternating view by view over random records of
  both robots; the verify worker of the stack checks every one (the chain worker's pool takes
  the verify queue too, and serves direct checks as well).
- HTTP: `GET /api/v1/records/{id}/content/` with the owner's read token against the stack's
  web server (which has VERIFY_DIRECT on, make run's default), V times one after another
  (bench/roots.py view_times), idle; then the same while one robot uploads 100 records/s
  (10 per POST every 0.1 s, bench/roots.py views_under_load) for L seconds.

p50 and p95 of each, and direct over task (in-process, same run). Every process shares this
machine with whatever else runs on it: load averages at start and end, and the CPU share of
processes outside the stack and this benchmark (bench/signing.py CpuWatch) during each phase.

Run: `python -m bench single_view [--views 200] [--records 200] [--load-seconds 20]`; writes
<results-dir>/single_view.json.
"""

import argparse
import base64
import dataclasses
import json
import random
import shutil
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import psutil

from bench import RESULTS_DIR, machine_info, now_iso, run_in_child, summarize
from bench.common import check_redis_url, seal_record
from bench.roots import view_times, viewer_token, views_under_load
from bench.signing import BATCH, BatchClient, CpuWatch, _paired_clients
from bench.stack import BENCH_REDIS_URL, BenchStack, StackOptions, owners_register

NAME = "single_view"


@dataclasses.dataclass(frozen=True)
class SingleViewRun:
    records: int
    views: int
    load_seconds: float
    redis_url: str
    workers: int = 2
    block_time: float | None = None
    batch_max: int = 100
    max_wait: float = 1.0
    timeout: float = 600.0


def measure(run: SingleViewRun) -> dict[str, Any]:
    """Every phase on one fresh stack."""
    workdir = Path(tempfile.mkdtemp(prefix="authros-bench-single-view-"))
    stack = BenchStack(
        StackOptions(
            block_time=run.block_time,
            batch_max=run.batch_max,
            workers=run.workers,
            max_wait=run.max_wait,
            redis_url=run.redis_url,
            anchor_mode="root",
        ),
        workdir,
    )
    found: dict[str, Any] = {}
    try:
        stack.start()  # Django is set up from here on
        from django.conf import settings

        from sharing.models import Record
        from sharing.services.uploads import record_create_batch
        from sharing.verification.opening import record_open

        ((robot, key),) = owners_register(stack, 1)
        owner = robot.owner
        for first in range(1, run.records + 1, BATCH):
            seqs = range(first, min(first + BATCH, run.records + 1))
            record_create_batch(
                robot=robot, envelopes=[seal_record(robot, key, seq=seq) for seq in seqs]
            )
        (paired,) = _paired_clients(stack, [(robot, key)], 1, batched=True)
        assert isinstance(paired, BatchClient)
        for body in paired.bodies(max(1, run.records // BATCH), BATCH):
            record_create_batch(
                robot=paired.robot,
                envelopes=[base64.b64decode(data) for data in body["envelopes"]],
            )
        total = Record.objects.filter(owner=owner).count()
        stack.wait_for(
            lambda: (
                Record.objects.filter(owner=owner, status=Record.Status.ANCHORED).count() == total
            ),
            "records not anchored",
            timeout=run.timeout,
        )
        ids = [str(pk) for pk in Record.objects.filter(owner=owner).values_list("pk", flat=True)]
        random.shuffle(ids)
        for record_id in ids[:4]:  # warm: connections, the chain client, the keys
            record_open(record_id=record_id, viewer=owner)
        times: dict[str, list[float]] = {"direct": [], "task": []}
        failures = {"direct": 0, "task": 0}
        watch = CpuWatch(stack)
        for number in range(2 * run.views):
            way = ("direct", "task")[number % 2]
            settings.VERIFY_DIRECT = way == "direct"
            started = time.perf_counter()
            try:
                record_open(record_id=ids[number % len(ids)], viewer=owner)
            except Exception as exc:  # counted, not raised
                failures[way] += 1
                print(f"{way}: {type(exc).__name__}: {exc}", file=sys.stderr)
                continue
            times[way].append((time.perf_counter() - started) * 1000)
        settings.VERIFY_DIRECT = True
        found["in_process_others_share"] = watch.stop()["others_share"]
        for way, samples in times.items():
            stats = summarize(samples)
            found[f"in_process_{way}"] = {
                "views": len(samples),
                "failed": failures[way],
                "p50_ms": stats["median_ms"],
                "p95_ms": stats["p95_ms"],
                "mean_ms": stats["mean_ms"],
            }
        found["in_process_direct_over_task_p50"] = (
            found["in_process_direct"]["p50_ms"] / found["in_process_task"]["p50_ms"]
        )
        token = viewer_token(owner)
        watch = CpuWatch(stack)
        idle, failed = view_times(stack.web_url, token, ids[: run.views])
        stats = summarize(idle)
        found["http_idle"] = {
            "views": len(idle),
            "not_200": len(failed),
            "p50_ms": stats["median_ms"],
            "p95_ms": stats["p95_ms"],
            "others_share": watch.stop()["others_share"],
        }
        watch = CpuWatch(stack)
        loaded, failed, phase = views_under_load(
            stack, paired, token, ids, seconds=run.load_seconds, timeout=run.timeout
        )
        stats = summarize(loaded)
        found["http_at_100_records_s"] = {
            "views": len(loaded),
            "not_200": len(failed),
            "p50_ms": stats["median_ms"],
            "p95_ms": stats["p95_ms"],
            "others_share": watch.stop()["others_share"],
            "uploads": {k: v for k, v in phase.items() if isinstance(v, int | float)},
        }
    finally:
        stack.stop()
    shutil.rmtree(workdir, ignore_errors=True)
    return found


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench single_view", description=__doc__)
    parser.add_argument("--records", type=int, default=200, help="records per robot (200)")
    parser.add_argument("--views", type=int, default=200, help="views per way and phase (200)")
    parser.add_argument("--load-seconds", type=float, default=20.0, help="views at 100 rec/s")
    parser.add_argument("--redis-url", default=BENCH_REDIS_URL, help="FLUSHED before the run")
    parser.add_argument("--results-dir", type=Path, default=RESULTS_DIR)
    args = parser.parse_args(argv)
    check_redis_url(parser, args.redis_url)
    report: dict[str, Any] = {
        "benchmark": NAME,
        "date": now_iso(),
        "machine": machine_info(("celery", "django", "redis")),
        "load_average_at_start": [round(load, 2) for load in psutil.getloadavg()],
        "settings": vars(args) | {"results_dir": str(args.results_dir)},
    }
    run = SingleViewRun(
        records=args.records,
        views=args.views,
        load_seconds=args.load_seconds,
        redis_url=args.redis_url,
    )
    report["results"] = run_in_child(measure, run)
    report["load_average_at_end"] = [round(load, 2) for load in psutil.getloadavg()]
    print(json.dumps(report["results"], indent=2))
    args.results_dir.mkdir(parents=True, exist_ok=True)
    (args.results_dir / f"{NAME}.json").write_text(json.dumps(report, indent=2) + "\n")
    return 0

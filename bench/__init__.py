"""Benchmarks, never part of the test suite: `python -m bench [NAME [args]]` from the
repository root.

Each benchmark is a module `bench/<name>.py` with `main(argv: list[str]) -> int`, listed in
BENCHMARKS. What they share: this package (where results go, timing, a description of the
machine), bench/common.py (the loop over configurations, ratios, tables, JSON/CSV/PNG files),
bench/plotting.py (matplotlib, set up once), bench/stack.py (a measured run's stack: what
`make run` starts) and bench/rest.py (agents uploading through the REST API).
"""

import importlib.metadata
import multiprocessing
import os
import platform
import signal
import statistics
import sys
import time
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor
from datetime import UTC, datetime
from pathlib import Path
from typing import Any, TypeVar

import psutil
from tqdm import tqdm

RESULTS_DIR = Path(__file__).resolve().parent / "results"
# portal/settings.py's ANCHOR_MAX_WAIT default, which make run keeps (a test holds them equal).
MAKE_RUN_ANCHOR_MAX_WAIT = 1.0
# The modules with a main(argv); the others in this package are what they share.
BENCHMARKS = (
    "block_interval",
    "concurrency",
    "crypto",
    "exports",
    "message_size",
    "pipeline",
    "report",
    "roots",
    "series",
    "signing",
    "sustained",
)
T = TypeVar("T")
R = TypeVar("R")


def available() -> list[str]:
    """Names of the benchmarks, as `python -m bench NAME` takes them."""
    return list(BENCHMARKS)


def run_in_child(function: Callable[[T], R], argument: T) -> R:
    """`function(argument)` in a fresh interpreter, so Django there reads a fresh environment.

    `function` must be importable (module level). A SIGTERM in the child exits it cleanly, so
    the `finally` blocks of a benchmark run still stop the stack it started.
    """
    context = multiprocessing.get_context("spawn")
    with ProcessPoolExecutor(max_workers=1, mp_context=context) as pool:
        return pool.submit(_in_child, function, argument).result()


def _in_child(function: Callable[[T], R], argument: T) -> R:
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(128 + signal.SIGTERM))
    return function(argument)


def measure(
    operation: Callable[[], object], repeat: int, progress: tqdm, warmup: int = 3
) -> list[float]:
    """Run operation warmup + repeat times; return the timed runs in milliseconds."""
    for _ in range(warmup):
        operation()
    samples = []
    for _ in range(repeat):
        start = time.perf_counter_ns()
        operation()
        samples.append((time.perf_counter_ns() - start) / 1e6)
        progress.update(1)
    return samples


def summarize(samples: list[float]) -> dict[str, float]:
    """Median, mean, 5th/95th percentile, min and max of samples in milliseconds."""
    ordered = sorted(samples)
    if len(ordered) > 1:
        cuts = statistics.quantiles(ordered, n=20, method="inclusive")
        p5, p95 = cuts[0], cuts[-1]
    else:
        p5 = p95 = ordered[0]
    return {
        "median_ms": statistics.median(ordered),
        "mean_ms": statistics.fmean(ordered),
        "p5_ms": p5,
        "p95_ms": p95,
        "min_ms": ordered[0],
        "max_ms": ordered[-1],
    }


def progress_bar(total: int, description: str, unit: str = "op") -> tqdm:
    """A progress bar on stderr."""
    return tqdm(total=total, desc=description, file=sys.stderr, unit=unit, mininterval=0.5)


def now_iso() -> str:
    """The current UTC time, ISO 8601."""
    return datetime.now(UTC).isoformat(timespec="seconds").replace("+00:00", "Z")


def machine_info(packages: tuple[str, ...] = ()) -> dict[str, Any]:
    """CPU, cores, memory, OS, Python and the versions of the given packages."""
    info: dict[str, Any] = {
        "cpu_model": _cpu_model(),
        "cpu_flags": _cpu_flags({"aes", "avx2", "avx512f", "pclmulqdq", "sha_ni", "sm3", "sm4"}),
        "logical_cores": os.cpu_count(),
        "physical_cores": psutil.cpu_count(logical=False),
        "memory_bytes": psutil.virtual_memory().total,
        "os": platform.platform(),
        "machine": platform.machine(),
        "python": f"{platform.python_implementation()} {platform.python_version()}",
    }
    frequency = psutil.cpu_freq()
    if frequency is not None:
        info["cpu_mhz"] = round(frequency.current)
    for package in packages:
        try:
            info[f"{package}_version"] = importlib.metadata.version(package)
        except importlib.metadata.PackageNotFoundError:
            info[f"{package}_version"] = None
    return info


def _cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown"


def _cpu_flags(interesting: set[str]) -> list[str]:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("flags"):
                return sorted(interesting & set(line.split(":", 1)[1].split()))
    except OSError:
        pass
    return []

"""What every benchmark does the same way: run its configurations one after another, each in a
fresh interpreter; divide by the batch-size-1 baseline; print a table; write JSON, CSV and PNG;
seal a record as a robot's agent does (ros_agent.sealing: signed for a paired robot), or a
batch signed once (provenance v2).
"""

import argparse
import csv
import json
import secrets
import sys
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from datetime import UTC, datetime
from pathlib import Path
from typing import Any, Protocol, TypeVar

import redis

from bench import run_in_child
from core.redis_url import redis_target
from ros_agent import sealing
from ros_agent.sealing import RobotSigningKey
from smcrypto import envelope, provenance

PLAINTEXT_BYTES = 1024
# Redis databases a benchmark never flushes: the development one and the test suite's.
PROTECTED_REDIS_DBS = (0, 14)


class Run(Protocol):
    """One measured configuration of a benchmark."""

    def describe(self) -> str: ...


RunT = TypeVar("RunT", bound=Run)


def run_configurations(
    runs: Sequence[RunT], measure: Callable[[RunT], dict[str, Any]]
) -> list[dict[str, Any]]:
    """measure(run) for each run, in order, each in its own child process, with a header line
    per run; each row gets run_wall_s, the seconds the run took from start to stop."""
    rows = []
    for number, run in enumerate(runs, 1):
        print(f"== [{number}/{len(runs)}] {run.describe()}", file=sys.stderr)
        started = time.monotonic()
        row = run_in_child(measure, run)
        row["run_wall_s"] = time.monotonic() - started
        rows.append(row)
    return rows


def check_redis_url(parser: argparse.ArgumentParser, url: str) -> None:
    """Refuse a Redis database a benchmark must not flush."""
    target = redis_target(url)
    database = (
        redis.Redis.from_url(url).connection_pool.connection_kwargs.get("db", 0)
        if target.kind == "plain"
        else target.db
    )
    if database in PROTECTED_REDIS_DBS:
        parser.error("refusing to flush Redis DB 0 (development) or 14 (tests)")


def add_ratios(
    rows: list[dict[str, Any]],
    same: Sequence[str],
    keys: Iterable[str] | Mapping[str, str],
    *,
    baseline: Callable[[dict[str, Any]], bool] | None = None,
) -> None:
    """Each row's keys divided by those of the baseline row agreeing on `same` (same run).

    baseline: which rows are baselines; by default the batch-size-1 rows.
    keys: the keys, each ratio named "<key>_ratio_vs_batch1"; or a map key -> ratio name.
    A field missing from a row (older results) agrees with the same field missing elsewhere.
    """
    names = dict(keys) if isinstance(keys, Mapping) else {k: f"{k}_ratio_vs_batch1" for k in keys}
    is_baseline = baseline or (lambda row: row["batch_max"] == 1)
    for row in rows:
        base = next(
            (
                other
                for other in rows
                if is_baseline(other) and all(other.get(f) == row.get(f) for f in same)
            ),
            None,
        )
        for key, name in names.items():
            ours, theirs = row.get(key), base.get(key) if base else None
            row[name] = ours / theirs if ours is not None and theirs else None


def add_engine_ratios(rows: list[dict[str, Any]], same: Sequence[str], keys: Iterable[str]) -> None:
    """Each row's keys divided by those of the sqlite-disk row of the same configuration
    (agreeing on `same`) in this run, as "<key>_ratio_vs_sqlite"; None without such a row."""
    add_ratios(
        rows,
        same,
        {key: f"{key}_ratio_vs_sqlite" for key in keys},
        baseline=lambda row: row.get("engines", "sqlite-disk") == "sqlite-disk",
    )


def print_table(report: dict[str, Any], columns: tuple[tuple[str, str, str], ...]) -> None:
    """The results as a table of (header, key, format) columns, under a line on the machine."""
    machine = report["machine"]
    print(
        f"{report['benchmark']} benchmark, {report['date']}: {machine['cpu_model']}, "
        f"{machine['logical_cores']} cores, {machine['memory_bytes'] / 2**30:.1f} GiB; "
        f"load average at start {report.get('load_average_at_start', '-')}"
    )
    table = [
        ["-" if row.get(key) is None else format(row[key], spec) for _, key, spec in columns]
        for row in report["results"]
    ]
    headers = [header for header, _, _ in columns]
    widths = [max(len(cell) for cell in column) for column in zip(headers, *table, strict=True)]
    for cells in (headers, *table):
        print(" ".join(f"{cell:>{width}}" for cell, width in zip(cells, widths, strict=True)))


def write_results(
    name: str,
    report: dict[str, Any],
    fields: Sequence[str],
    results_dir: Path,
    *,
    plot: Callable[[dict[str, Any], Path], None],
    csv_rows: Iterable[dict[str, Any]] | None = None,
) -> None:
    """results_dir/NAME.json (the whole report), NAME.csv (fields of each result row, or of
    csv_rows) and NAME.png (drawn by plot); then says where they are."""
    results_dir.mkdir(parents=True, exist_ok=True)
    (results_dir / f"{name}.json").write_text(json.dumps(report, indent=2) + "\n")
    with (results_dir / f"{name}.csv").open("w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(fields)
        for row in report["results"] if csv_rows is None else csv_rows:
            writer.writerow(
                [
                    f"{value:.6f}" if isinstance(value, float) else value
                    for value in (row.get(field) for field in fields)
                ]
            )
    plot(report, results_dir / f"{name}.png")
    print(f"results: {results_dir}/{name}.json, {name}.csv, {name}.png")


def record_plaintext(
    robot: Any, *, seq: int, plaintext_bytes: int = PLAINTEXT_BYTES
) -> tuple[dict[str, Any], bytes]:
    """Fig. 4's JSON record padded to plaintext_bytes, captured now: (header, plaintext)."""
    now = datetime.now(tz=UTC).isoformat().replace("+00:00", "Z")
    header = {
        "owner": robot.owner.username,
        "robot": str(robot.id),
        "topic": "/robot/odom",
        "type": "nav_msgs/Odometry",
        "seq": seq,
        "time": now,
    }
    record = {"K": {"seq": seq, "pad": ""}, "Owner": robot.owner.username, "Time": now}
    record.update(Type=header["type"], Topic=header["topic"])
    filler = max(plaintext_bytes - len(json.dumps(record).encode()), 0)
    record["K"]["pad"] = secrets.token_hex(filler // 2 + 1)[:filler]
    return header, json.dumps(record).encode()


def seal_record(
    robot: Any,
    key: bytes,
    *,
    seq: int,
    plaintext_bytes: int = PLAINTEXT_BYTES,
    signing_key: RobotSigningKey | None = None,
) -> bytes:
    """Fig. 4's JSON record padded to plaintext_bytes, sealed as the robot's agent seals it:
    signed with `signing_key` (a paired robot's), unsigned without (a robot added by hand)."""
    header, plaintext = record_plaintext(robot, seq=seq, plaintext_bytes=plaintext_bytes)
    return sealing.seal_record(key, header, plaintext, signing_key)


def seal_batch(
    key: bytes,
    records: Sequence[tuple[Mapping[str, Any], bytes]],
    signing_key: RobotSigningKey,
    *,
    first_topic_seq: int,
) -> list[bytes]:
    """The envelopes of one upload batch signed once (provenance v2, smcrypto.provenance
    .sign_batch): each record's header gains its `topic_seq` (first_topic_seq, then on by one:
    the caller counts per topic from 0) and the batch's signature and its place in it."""
    numbered = [
        ({**header, "topic_seq": first_topic_seq + number}, plaintext)
        for number, (header, plaintext) in enumerate(records)
    ]
    headers = provenance.sign_batch(signing_key.private_key, signing_key.public_key, numbered)
    return [
        envelope.seal(key, header, plaintext)
        for header, (_, plaintext) in zip(headers, numbered, strict=True)
    ]

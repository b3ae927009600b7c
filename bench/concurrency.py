"""Concurrency (paper Fig. 14): N agents upload one 1 KB envelope each through REST at once.

For N in 300, 500 and 700 (`--quick`: 30 and 50), on anvil with automine, `--block-time 1` and
`--block-time 2`, each with ANCHOR_BATCH_MAX 1 (one transaction per record, the paper's way and
the baseline) and 100 (batching), every configuration in its own process with a fresh stack:
the one `make run` starts, web server settings included (bench/stack.py, bench/rest.py).
Measures total response time (first POST to last 201), time until anchored and until
verified, and success rate = verified / sent. Batching is reported as a ratio against batch
size 1 of the same block mode and N, measured in the same run.

Every configuration runs on each of `--engines` (default both): sqlite-disk, make run's SQLite
file and envelopes on the local disk, and postgres-s3, a fresh database on the PostgreSQL server
at BENCH_PG_URL (default postgres://postgres@127.0.0.1:5432/postgres, dropped after the run) and
envelopes in a SeaweedFS bucket (a `weed server -s3` of the run's own). postgres-s3 rows get a
ratio against sqlite-disk of the same configuration, measured in the same run.

Run: `python -m bench concurrency [--agents 300 500 700] [--engines postgres-s3] [--quick]`.
Writes bench/results/concurrency.json, concurrency.csv and concurrency.png.
"""

import argparse
from pathlib import Path
from typing import Any

from bench import now_iso
from bench.common import (
    add_engine_ratios,
    add_ratios,
    print_table,
    run_configurations,
    write_results,
)
from bench.plotting import ENGINE_STYLES, engine_label, machine_line, plt, save_figure
from bench.rest import (
    add_arguments,
    add_engines_argument,
    check_arguments,
    engines_chosen,
    engines_settings,
    measure,
    report_header,
    upload_run,
)

NAME = "concurrency"
AGENTS = (300, 500, 700)
QUICK_AGENTS = (30, 50)
BLOCK_TIMES: tuple[float | None, ...] = (None, 1.0, 2.0)  # None: automine
BATCH_SIZES = (1, 100)
PLAINTEXT_BYTES = 1024
RATIO_KEYS = ("total_response_s", "total_to_anchored_s", "total_to_verified_s", "to_anchored_p50_s")
# postgres-s3 against sqlite-disk of the same configuration in the same run
ENGINE_RATIO_KEYS = ("total_response_s", "total_to_anchored_s", "total_to_verified_s")
FIELDS = (
    "engines",
    "mode",
    "block_time_s",
    "batch_max",
    "agents",
    "plaintext_bytes",
    "envelope_bytes_mean",
    "sent",
    "http_201",
    "anchored",
    "verified",
    "success_rate",
    "transactions",
    "response_mean_s",
    "response_p50_s",
    "response_p95_s",
    "total_response_s",
    "uploads_per_s",
    "to_anchored_p50_s",
    "to_anchored_p95_s",
    "total_to_anchored_s",
    "anchored_per_s",
    "to_verified_p50_s",
    "to_verified_p95_s",
    "total_to_verified_s",
    *(f"{key}_ratio_vs_batch1" for key in RATIO_KEYS),
    *(f"{key}_ratio_vs_sqlite" for key in ENGINE_RATIO_KEYS),
)
COLUMNS = (
    ("engines", "engines", ""),
    ("mode", "mode", ""),
    ("batch", "batch_max", "d"),
    ("N", "agents", "d"),
    ("success", "success_rate", ".1%"),
    ("txs", "transactions", "d"),
    ("resp mean", "response_mean_s", ".2f"),
    ("total resp", "total_response_s", ".2f"),
    ("upl/s", "uploads_per_s", ".1f"),
    ("anch p50", "to_anchored_p50_s", ".2f"),
    ("total anch", "total_to_anchored_s", ".2f"),
    ("total verif", "total_to_verified_s", ".2f"),
    ("anch x b1", "total_to_anchored_s_ratio_vs_batch1", ".2f"),
    ("resp x sqlite", "total_response_s_ratio_vs_sqlite", ".2f"),
    ("verif x sqlite", "total_to_verified_s_ratio_vs_sqlite", ".2f"),
)
# What makes two rows the same configuration (besides the engines, or the batch size).
SAME = ("mode", "agents", "plaintext_bytes")


def main(argv: list[str]) -> int:
    """Run every configuration, print the table and write JSON, CSV and PNG results."""
    parser = argparse.ArgumentParser(prog="python -m bench concurrency", description=__doc__)
    parser.add_argument("--agents", type=int, nargs="+", help=f"N values (default {AGENTS})")
    parser.add_argument(
        "--block-times",
        type=float,
        nargs="+",
        help="block times in seconds, 0 = automine (default: automine, 1, 2)",
    )
    add_engines_argument(parser)
    add_arguments(parser)
    args = parser.parse_args(argv)
    check_arguments(parser, args)
    agents = args.agents or (QUICK_AGENTS if args.quick else AGENTS)
    block_times = tuple(b or None for b in args.block_times) if args.block_times else BLOCK_TIMES
    engines = engines_chosen(args)
    started = now_iso()
    report = report_header(NAME, args, started)
    report["settings"] |= engines_settings(parser, engines)
    runs = [
        upload_run(
            args,
            block_time=block_time,
            batch_max=batch_max,
            agents=n,
            plaintext_bytes=PLAINTEXT_BYTES,
            engines=engine,
        )
        for engine in engines
        for block_time in block_times
        for n in agents
        for batch_max in BATCH_SIZES
    ]
    rows = run_configurations(runs, measure)
    rows_ratios(rows)
    report["settings"] |= {
        "agents_per_run": list(agents),
        "block_times": ["automine" if b is None else b for b in block_times],
        "batch_sizes": list(BATCH_SIZES),
        "plaintext_bytes": PLAINTEXT_BYTES,
    }
    report["notes"].append(
        "ratio columns divide by ANCHOR_BATCH_MAX=1 (one transaction per record) of the same "
        "block mode, N and engines in this run: below 1 means batching is faster."
    )
    if len(engines) > 1:
        report["notes"].append(
            "x sqlite columns divide postgres-s3 (PostgreSQL + SeaweedFS S3) by sqlite-disk "
            "(SQLite + local disk) of the same block mode, batch size and N, measured in this "
            "run on this machine: above 1 means PostgreSQL + S3 took longer."
        )
    report["results"] = rows
    print_table(report, COLUMNS)
    write_results(NAME, report, FIELDS, args.results_dir, plot=_plot)
    return 0 if all(row["success_rate"] == 1 for row in rows) else 1


def rows_ratios(rows: list[dict[str, Any]]) -> None:
    """Batching against batch size 1, and postgres-s3 against sqlite-disk (same run)."""
    add_ratios(rows, ("engines", *SAME), RATIO_KEYS)
    add_engine_ratios(rows, ("batch_max", *SAME), ENGINE_RATIO_KEYS)


def _plot(report: dict[str, Any], path: Path) -> None:
    rows = report["results"]
    modes = list(dict.fromkeys(row["mode"] for row in rows))
    figure, axes = plt.subplots(1, len(modes), figsize=(5 * len(modes), 4.5), squeeze=False)
    for axis, mode in zip(axes[0], modes, strict=True):
        rate_axis = axis.twinx()
        engines = list(dict.fromkeys(row.get("engines", "sqlite-disk") for row in rows))
        for engine, batch in ((e, b) for e in engines for b in BATCH_SIZES):
            colour = {1: "tab:red", 100: "tab:blue"}.get(batch, "tab:gray")
            style = ENGINE_STYLES.get(engine, {})
            label = f"{engine_label(engine, engines)}batch {batch}"
            measured = [
                r
                for r in rows
                if r["mode"] == mode
                and r["batch_max"] == batch
                and r.get("engines", "sqlite-disk") == engine
            ]
            n = [r["agents"] for r in measured]
            axis.plot(
                n,
                [r.get("total_response_s") for r in measured],
                "o-",
                color=colour,
                label=f"{label}: all 201s",
                **style,
            )
            axis.plot(
                n,
                [r.get("total_to_verified_s") for r in measured],
                "s--",
                color=colour,
                label=f"{label}: all verified",
                **style,
            )
            rate_axis.plot(
                n,
                [100 * r["success_rate"] for r in measured],
                "x:",
                color=colour,
                alpha=0.6,
                label=f"{label}: success %",
            )
        axis.set_title(mode)
        axis.set_xlabel("concurrent agents (one 1 KB upload each)")
        axis.set_ylabel("total time, s")
        rate_axis.set_ylabel("success rate, % (verified / sent)")
        rate_axis.set_ylim(0, 105)
        axis.grid(True, alpha=0.3)
        axis.legend(fontsize=7, loc="upper left")
        rate_axis.legend(fontsize=7, loc="lower right")
    save_figure(figure, path, f"concurrency (paper Fig. 14): {machine_line(report)}")

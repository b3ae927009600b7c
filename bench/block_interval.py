"""Block interval (paper Fig. 16, its difficulty settings): automine, 1 s, 2 s and 5 s blocks.

Each block time, with ANCHOR_BATCH_MAX 1 (one transaction per record, the paper's way and the
baseline) and 100 (batching), is one configuration with a fresh stack (bench/rest.py): N
agents (default 300, as the paper's 300 Data_upload calls; `--quick`: 20) each POST one 1 KB
envelope through REST at once. Reported: average latency to anchored (and to verified, and the
response time), batching as a ratio against batch size 1 of the same block time in this run.

Run: `python -m bench block_interval [--agents N] [--block-times 0 1 2 5] [--quick]`.
Writes bench/results/block_interval.json, block_interval.csv and block_interval.png.
"""

import argparse
from pathlib import Path
from typing import Any

from bench import now_iso
from bench.common import add_ratios, print_table, run_configurations, write_results
from bench.plotting import machine_line, plt, save_figure
from bench.rest import add_arguments, check_arguments, measure, report_header, upload_run

NAME = "block_interval"
BLOCK_TIMES: tuple[float | None, ...] = (None, 1.0, 2.0, 5.0)  # None: automine
BATCH_SIZES = (1, 100)
AGENTS = 300
QUICK_AGENTS = 20
PLAINTEXT_BYTES = 1024
RATIO_KEYS = ("to_anchored_mean_s", "to_anchored_p95_s", "total_to_anchored_s")
FIELDS = (
    "mode",
    "block_time_s",
    "batch_max",
    "agents",
    "sent",
    "anchored",
    "verified",
    "success_rate",
    "transactions",
    "response_mean_s",
    "to_anchored_mean_s",
    "to_anchored_p50_s",
    "to_anchored_p95_s",
    "total_to_anchored_s",
    "anchored_per_s",
    "to_verified_mean_s",
    "to_verified_p95_s",
    *(f"{key}_ratio_vs_batch1" for key in RATIO_KEYS),
)
COLUMNS = (
    ("mode", "mode", ""),
    ("batch", "batch_max", "d"),
    ("N", "agents", "d"),
    ("success", "success_rate", ".1%"),
    ("txs", "transactions", "d"),
    ("resp mean s", "response_mean_s", ".3f"),
    ("anch mean s", "to_anchored_mean_s", ".2f"),
    ("anch p95 s", "to_anchored_p95_s", ".2f"),
    ("all anch s", "total_to_anchored_s", ".2f"),
    ("anch/s", "anchored_per_s", ".1f"),
    ("mean x b1", "to_anchored_mean_s_ratio_vs_batch1", ".2f"),
)


def main(argv: list[str]) -> int:
    """Run every block time and batch size, print the table and write JSON, CSV and PNG."""
    parser = argparse.ArgumentParser(prog="python -m bench block_interval", description=__doc__)
    parser.add_argument("--agents", type=int, help=f"uploads per run (default {AGENTS})")
    parser.add_argument(
        "--block-times", type=float, nargs="+", help="seconds, 0 = automine (default 0 1 2 5)"
    )
    add_arguments(parser)
    args = parser.parse_args(argv)
    check_arguments(parser, args)
    agents = args.agents or (QUICK_AGENTS if args.quick else AGENTS)
    block_times = tuple(b or None for b in args.block_times) if args.block_times else BLOCK_TIMES
    report = report_header(NAME, args, now_iso())
    runs = [
        upload_run(
            args,
            block_time=block_time,
            batch_max=batch_max,
            agents=agents,
            plaintext_bytes=PLAINTEXT_BYTES,
        )
        for block_time in block_times
        for batch_max in BATCH_SIZES
    ]
    rows = run_configurations(runs, measure)
    add_ratios(rows, ("mode",), RATIO_KEYS)
    report["settings"] |= {
        "agents_per_run": agents,
        "block_times": ["automine" if b is None else b for b in block_times],
        "batch_sizes": list(BATCH_SIZES),
        "plaintext_bytes": PLAINTEXT_BYTES,
    }
    report["notes"].append(
        "anvil's block time stands in for the paper's PoW difficulty / PoA period; ratio "
        "columns divide by ANCHOR_BATCH_MAX=1 of the same block time in this run."
    )
    report["results"] = rows
    print_table(report, COLUMNS)
    write_results(NAME, report, FIELDS, args.results_dir, plot=_plot)
    return 0 if all(row["success_rate"] == 1 for row in rows) else 1


def _plot(report: dict[str, Any], path: Path) -> None:
    rows = report["results"]
    modes = list(dict.fromkeys(row["mode"] for row in rows))
    figure, axis = plt.subplots(figsize=(8, 4.5))
    width = 0.38
    for offset, (batch, colour) in enumerate(
        zip(BATCH_SIZES, ("tab:red", "tab:blue"), strict=True)
    ):
        values = [
            next(
                (
                    r.get("to_anchored_mean_s") or 0
                    for r in rows
                    if r["mode"] == mode and r["batch_max"] == batch
                ),
                0,
            )
            for mode in modes
        ]
        bars = axis.bar(
            [i + (offset - 0.5) * width for i in range(len(modes))],
            values,
            width,
            color=colour,
            label=f"ANCHOR_BATCH_MAX={batch}",
        )
        axis.bar_label(bars, fmt="%.2f", fontsize=7)
    axis.set_xticks(range(len(modes)), modes)
    axis.set_ylabel("mean latency POST to anchored, s")
    axis.grid(True, axis="y", alpha=0.3)
    axis.legend(fontsize=8)
    save_figure(
        figure,
        path,
        f"block interval (paper Fig. 16): {rows[0]['agents'] if rows else 0} concurrent 1 KB "
        f"uploads per run; {machine_line(report)}",
    )

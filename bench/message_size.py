"""Message size (paper Fig. 15): 300 concurrent uploads of 1, 2, 4 and 8 KB each; response time.

Each size is one configuration with a fresh stack (bench/_stack.py): N agents (default 300,
`--quick`: 30) each POST one envelope of that plaintext size through REST at once, on anvil
with automine and ANCHOR_BATCH_MAX 100, and the benchmark waits until every record is anchored
and verified. Reported: average response time (POST to 201), as in the paper, with time to
anchored and to verified; each size as a ratio against 1 KB measured in the same run.

Run: `python -m bench message_size [--agents N] [--sizes 1024 2048 ...] [--quick]`.
Writes bench/results/message_size.json, message_size.csv and message_size.png.
"""

import argparse
import sys
from pathlib import Path
from typing import Any

if not __package__:  # run as `python bench/message_size.py`: make the repository importable
    sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt

from bench import now_iso
from bench._stack import (
    add_arguments,
    check_arguments,
    measure_all,
    print_table,
    report_header,
    upload_run,
    write_results,
)

NAME = "message_size"
SIZES = (1024, 2048, 4096, 8192)
AGENTS = 300
QUICK_AGENTS = 30
BATCH_MAX = 100
RATIO_KEYS = ("response_mean_s", "to_anchored_mean_s", "to_verified_mean_s")
FIELDS = (
    "plaintext_bytes",
    "envelope_bytes_mean",
    "mode",
    "batch_max",
    "agents",
    "sent",
    "verified",
    "success_rate",
    "transactions",
    "response_mean_s",
    "response_p50_s",
    "response_p95_s",
    "total_response_s",
    "to_anchored_mean_s",
    "to_anchored_p50_s",
    "to_verified_mean_s",
    "to_verified_p50_s",
    *(f"{key}_ratio_vs_1kb" for key in RATIO_KEYS),
)
COLUMNS = (
    ("plaintext B", "plaintext_bytes", "d"),
    ("envelope B", "envelope_bytes_mean", ".0f"),
    ("N", "agents", "d"),
    ("success", "success_rate", ".1%"),
    ("resp mean s", "response_mean_s", ".3f"),
    ("resp p95 s", "response_p95_s", ".3f"),
    ("x 1KB", "response_mean_s_ratio_vs_1kb", ".2f"),
    ("anch mean s", "to_anchored_mean_s", ".2f"),
    ("verif mean s", "to_verified_mean_s", ".2f"),
)


def main(argv: list[str]) -> int:
    """Run every size, print the table and write JSON, CSV and PNG results."""
    parser = argparse.ArgumentParser(prog="python -m bench message_size", description=__doc__)
    parser.add_argument("--agents", type=int, help=f"uploads per size (default {AGENTS})")
    parser.add_argument("--sizes", type=int, nargs="+", default=list(SIZES), help="bytes")
    add_arguments(parser)
    args = parser.parse_args(argv)
    check_arguments(parser, args)
    agents = args.agents or (QUICK_AGENTS if args.quick else AGENTS)
    report = report_header(NAME, args, now_iso())
    runs = [
        upload_run(args, block_time=None, batch_max=BATCH_MAX, agents=agents, plaintext_bytes=size)
        for size in args.sizes
    ]
    rows = measure_all(runs)
    baseline = next((row for row in rows if row["plaintext_bytes"] == 1024), None)
    for row in rows:
        for key in RATIO_KEYS:
            ours, theirs = row.get(key), baseline.get(key) if baseline else None
            row[f"{key}_ratio_vs_1kb"] = ours / theirs if ours is not None and theirs else None
    report["settings"] |= {
        "agents_per_size": agents,
        "sizes_bytes": args.sizes,
        "block_mode": "automine",
        "batch_max": BATCH_MAX,
    }
    report["notes"].append("ratio columns divide by the 1 KB run of this benchmark run.")
    report["results"] = rows
    print_table(report, COLUMNS)
    write_results(NAME, report, FIELDS, args.results_dir)
    _plot(report, args.results_dir / f"{NAME}.png")
    print(f"results: {args.results_dir}/{NAME}.json, {NAME}.csv, {NAME}.png")
    return 0 if all(row["success_rate"] == 1 for row in rows) else 1


def _plot(report: dict[str, Any], path: Path) -> None:
    rows = report["results"]
    labels = [f"{row['plaintext_bytes'] // 1024} KB" for row in rows]
    figure, axis = plt.subplots(figsize=(7, 4.5))
    positions = range(len(rows))
    bars = axis.bar(positions, [row.get("response_mean_s") or 0 for row in rows], color="tab:blue")
    axis.bar_label(bars, fmt="%.3f s", fontsize=8)
    axis.set_xticks(list(positions), labels)
    axis.set_xlabel("plaintext size per upload")
    axis.set_ylabel("average response time (POST to 201), s")
    axis.grid(True, axis="y", alpha=0.3)
    machine = report["machine"]
    figure.suptitle(
        f"message size (paper Fig. 15): {rows[0]['agents'] if rows else 0} concurrent uploads "
        f"per size, automine; {machine['logical_cores']} cores, {report['date']}",
        fontsize=9,
    )
    figure.tight_layout()
    figure.savefig(path, dpi=120)
    plt.close(figure)


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))

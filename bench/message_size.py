"""Message size (paper Fig. 15): 300 uploads of 1, 2, 4 and 8 KB each, one after another.

The paper calls Data_upload 300 times per size "through the simulated process" and reports the
average time. Here, for each size, one agent (one robot, one requests.Session) POSTs 300
envelopes of that plaintext size to `/api/v1/records/` in a row, each once the previous one was
answered, so the size is not hidden behind queueing (bench/rest.py; the stack is `make run`'s:
anvil with automine, Celery workers, gunicorn). Measured per upload: response time (POST to 201, the
paper's measure) and time to anchored on chain (POST to Record.anchored_at).

Each size runs twice, each time with a fresh stack: ANCHOR_BATCH_MAX 1 (one transaction per
record, as the paper's Data_upload: the baseline) and 100 (batching); batching's time to
anchored is reported as a ratio against batch size 1 of the same size, measured in the same run,
and each size's response time as a ratio against 1 KB of the same batch size. The sequential
1 KB run with batch size 1 is also the single-upload REST latency that the report sets beside
the paper's 15.5 ms per Data_upload on PoA. Then the same again concurrently, as a second
view (`--no-concurrent` skips it, halving the run time): 300 agents posting one upload each at
once, where queueing in the portal dominates the response time.

Run: `python -m bench message_size [--uploads N] [--sizes 1024 2048 ...] [--no-concurrent]
[--quick]`. Writes bench/results/message_size.json, message_size.csv and message_size.png.
"""

import argparse
from pathlib import Path
from typing import Any

from bench import now_iso
from bench.common import add_ratios, print_table, run_configurations, write_results
from bench.plotting import machine_line, plt, save_figure
from bench.rest import add_arguments, check_arguments, measure, report_header, upload_run

NAME = "message_size"
SIZES = (1024, 2048, 4096, 8192)
UPLOADS = 300
QUICK_UPLOADS = 30
BATCH_SIZES = (1, 100)  # 1: one transaction per record, the paper's way and the baseline
PATTERNS = ("sequential", "concurrent")
RATIO_KEYS = ("to_anchored_mean_s", "to_anchored_p95_s", "total_to_anchored_s", "response_mean_s")
SIZE_RATIO_KEYS = ("response_mean_s", "to_anchored_mean_s")
FIELDS = (
    "pattern",
    "agents",
    "uploads_per_agent",
    "plaintext_bytes",
    "envelope_bytes_mean",
    "mode",
    "batch_max",
    "sent",
    "verified",
    "success_rate",
    "transactions",
    "response_mean_s",
    "response_stdev_s",
    "response_p50_s",
    "response_p95_s",
    "total_response_s",
    "uploads_per_s",
    "to_anchored_mean_s",
    "to_anchored_stdev_s",
    "to_anchored_p50_s",
    "to_anchored_p95_s",
    "total_to_anchored_s",
    "to_verified_mean_s",
    "run_wall_s",
    *(f"{key}_ratio_vs_batch1" for key in RATIO_KEYS),
    *(f"{key}_ratio_vs_1kb" for key in SIZE_RATIO_KEYS),
)
COLUMNS = (
    ("pattern", "pattern", ""),
    ("bytes", "plaintext_bytes", "d"),
    ("batch", "batch_max", "d"),
    ("n", "sent", "d"),
    ("success", "success_rate", ".1%"),
    ("txs", "transactions", "d"),
    ("resp mean s", "response_mean_s", ".4f"),
    ("resp p50 s", "response_p50_s", ".4f"),
    ("x 1KB", "response_mean_s_ratio_vs_1kb", ".2f"),
    ("anch mean s", "to_anchored_mean_s", ".3f"),
    ("anch x b1", "to_anchored_mean_s_ratio_vs_batch1", ".2f"),
    ("wall s", "run_wall_s", ".0f"),
)


def main(argv: list[str]) -> int:
    """Run every size and batch size, print the table and write JSON, CSV and PNG results."""
    parser = argparse.ArgumentParser(prog="python -m bench message_size", description=__doc__)
    parser.add_argument(
        "--uploads", type=int, help=f"uploads per size and batch size (default {UPLOADS})"
    )
    parser.add_argument("--sizes", type=int, nargs="+", default=list(SIZES), help="bytes")
    parser.add_argument(
        "--concurrent",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="also N agents posting one upload each at once (default; about half the run time)",
    )
    add_arguments(parser)
    args = parser.parse_args(argv)
    check_arguments(parser, args)
    uploads = (
        args.uploads if args.uploads is not None else (QUICK_UPLOADS if args.quick else UPLOADS)
    )
    if uploads < 2:
        parser.error("--uploads must be at least 2")
    patterns = PATTERNS if args.concurrent else PATTERNS[:1]
    report = report_header(NAME, args, now_iso())
    runs = [
        upload_run(
            args,
            block_time=None,
            batch_max=batch_max,
            agents=1 if pattern == "sequential" else uploads,
            uploads_per_agent=uploads if pattern == "sequential" else 1,
            plaintext_bytes=size,
        )
        for pattern in patterns
        for size in args.sizes
        for batch_max in BATCH_SIZES
    ]
    rows = run_configurations(runs, measure)
    add_ratios(rows, ("pattern", "plaintext_bytes"), RATIO_KEYS)
    _add_size_ratios(rows)
    report["settings"] |= {
        "uploads_per_size": uploads,
        "sizes_bytes": args.sizes,
        "patterns": list(patterns),
        "block_mode": "automine",
        "batch_sizes": list(BATCH_SIZES),
        "agents": "sequential: one agent (one robot, one requests.Session) POSTs its envelopes "
        "to /api/v1/records/ one after another, each once the previous one was answered; "
        "concurrent: one thread and robot per upload, released by a barrier, one POST each",
    }
    report["notes"] += [
        "the paper's measure is the sequential rows' mean response time: one agent calling "
        "the upload N times in a row per size.",
        "sequential runs open (verify) their records after the last POST, so they report the "
        "verified count but no time to verified.",
        "x batch 1 columns divide by ANCHOR_BATCH_MAX=1 (one transaction per record) of the "
        "same pattern and size; x 1 KB columns divide by 1 KB of the same pattern and batch "
        "size; both measured in this run.",
    ]
    report["results"] = rows
    print_table(report, COLUMNS)
    write_results(NAME, report, FIELDS, args.results_dir, plot=_plot)
    return 0 if all(row["success_rate"] == 1 for row in rows) else 1


def _add_size_ratios(rows: list[dict[str, Any]]) -> None:
    """Each row's SIZE_RATIO_KEYS divided by the 1 KB row of the same pattern and batch size."""
    for row in rows:
        baseline = next(
            (
                other
                for other in rows
                if other["plaintext_bytes"] == 1024
                and other["pattern"] == row["pattern"]
                and other["batch_max"] == row["batch_max"]
            ),
            None,
        )
        for key in SIZE_RATIO_KEYS:
            ours, theirs = row.get(key), baseline.get(key) if baseline else None
            row[f"{key}_ratio_vs_1kb"] = ours / theirs if ours is not None and theirs else None


def _plot(report: dict[str, Any], path: Path) -> None:
    """Per pattern (a row of panels each): mean response and mean time to anchored by size,
    one line per batch size; response error bars are two standard errors of the mean."""
    rows = report["results"]
    sizes = sorted({row["plaintext_bytes"] for row in rows})
    patterns = [p for p in PATTERNS if any(row["pattern"] == p for row in rows)]
    figure, axes = plt.subplots(len(patterns), 2, figsize=(11, 4.2 * len(patterns)), squeeze=False)
    colours = {1: ("tab:red", "o-"), 100: ("tab:blue", "s-")}
    for (left, right), pattern in zip(axes, patterns, strict=True):
        for batch_max in sorted({row["batch_max"] for row in rows}):
            series = sorted(
                (r for r in rows if r["pattern"] == pattern and r["batch_max"] == batch_max),
                key=lambda row: row["plaintext_bytes"],
            )
            if not series:
                continue
            colour, style = colours.get(batch_max, ("tab:gray", "^-"))
            label = f"ANCHOR_BATCH_MAX={batch_max}"
            kilobytes = [row["plaintext_bytes"] / 1024 for row in series]
            errors = [
                2000 * (row.get("response_stdev_s") or 0) / max(row["sent"], 1) ** 0.5
                for row in series
            ]
            left.errorbar(
                kilobytes,
                [(row.get("response_mean_s") or 0) * 1000 for row in series],
                yerr=errors,
                fmt=style,
                color=colour,
                label=label,
                capsize=3,
            )
            right.plot(
                kilobytes,
                [row.get("to_anchored_mean_s") or 0 for row in series],
                style,
                color=colour,
                label=label,
            )
        uploads = (
            f"1 agent, {report['settings'].get('uploads_per_size')} uploads in a row"
            if pattern == "sequential"
            else f"{report['settings'].get('uploads_per_size')} agents at once"
        )
        for axis, title, unit in (
            (left, f"{uploads}: mean response (POST to 201)", "ms (bars: 2 standard errors)"),
            (right, f"{uploads}: mean time to anchored", "s"),
        ):
            axis.set_xscale("log", base=2)
            axis.set_xticks([s / 1024 for s in sizes], [f"{s / 1024:g} KB" for s in sizes])
            axis.set_xlabel("plaintext size per upload")
            axis.set_ylabel(unit)
            axis.set_ylim(bottom=0)
            axis.set_title(title, fontsize=10)
            axis.grid(True, alpha=0.3)
            axis.legend(fontsize=8)
    save_figure(
        figure, path, f"message size (paper Fig. 15), anvil automine; {machine_line(report)}"
    )

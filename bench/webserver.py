"""The web server under the paper's 700 concurrent uploads: the burst of bench/roots.py (each
agent its own robot token and connection, all opened at once from one selector loop, root
mode, automine, ANCHOR_BATCH_MAX 100), `--bursts` times, each on a fresh `make run` stack
served as make run serves it. Measures first POST to last answer and to last anchored, the
answers that were not 201, and the web's CPU up to the last record anchored.

The comparison of two web servers runs this from two checkouts (one per server) one burst at a
time in alternation, so that both see the same machine, then joins their results:
`python -m bench webserver --combine granian=A1.json gunicorn=B1.json granian=A2.json ...`
writes bench/results/webserver.json with every burst under its server's name, which
`python -m bench report` shows (bench/REPORT.md, "Web server").

Run: `python -m bench webserver [--agents 700] [--bursts 5]`; prints one JSON line per burst
and writes <results-dir>/webserver.json.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import statistics
from pathlib import Path

from bench import now_iso, run_in_child
from bench.rest import add_arguments, check_arguments, report_header, upload_run
from bench.rest import measure as concurrent_measure

NAME = "webserver"
PLAINTEXT_BYTES = 1024
FIELDS = (
    "burst",
    "sent",
    "http_201",
    "anchored",
    "verified",
    "first_answer_s",
    "answer_p99_s",
    "total_response_s",
    "total_to_anchored_s",
    "web_cpu_s",
)


SUMMARIZED = ("total_to_anchored_s", "total_response_s", "first_answer_s", "web_cpu_s")


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench webserver", description=__doc__)
    add_arguments(parser)
    parser.add_argument("--agents", type=int, default=700, help="concurrent uploads (700)")
    parser.add_argument("--bursts", type=int, default=5, help="bursts, each on a fresh stack")
    parser.add_argument(
        "--combine",
        nargs="+",
        metavar="SERVER=FILE",
        help="join runs' webserver.json files (in the order run) instead of running",
    )
    args = parser.parse_args(argv)
    if args.combine:
        return combine(args.combine, args.results_dir)
    check_arguments(parser, args)
    started = now_iso()
    run = dataclasses.replace(
        upload_run(
            args,
            block_time=None,
            batch_max=100,
            agents=args.agents,
            plaintext_bytes=PLAINTEXT_BYTES,
            anchor_mode="root",
        ),
        client="sockets",
        verify_after_anchored=True,
    )
    rows = []
    for number in range(args.bursts):
        measured = run_in_child(concurrent_measure, run)
        row = {"burst": number + 1} | {key: measured.get(key) for key in FIELDS if key in measured}
        row["web_cpu_s"] = (measured.get("stack_cpu_s") or {}).get("web")
        row["http_statuses"] = measured.get("http_statuses")
        print(json.dumps(row), flush=True)
        rows.append(row)
    report = report_header(NAME, args, started)
    totals = [row["total_to_anchored_s"] for row in rows if row.get("total_to_anchored_s")]
    report["summary"] = {
        "bursts": len(rows),
        "median_total_to_anchored_s": statistics.median(totals) if totals else None,
        "median_total_response_s": statistics.median(
            row["total_response_s"] for row in rows if row.get("total_response_s")
        )
        if rows
        else None,
        "not_201": sum(row["sent"] - row["http_201"] for row in rows),
    }
    report["results"] = rows
    print(json.dumps(report["summary"]), flush=True)
    args.results_dir.mkdir(parents=True, exist_ok=True)
    (args.results_dir / f"{NAME}.json").write_text(json.dumps(report, indent=2) + "\n")
    return 0 if all(row["http_201"] == row["sent"] for row in rows) else 1


def combine(items: list[str], results_dir: Path) -> int:
    """One report of runs from several checkouts: every burst with its server's name and its
    place in the alternation, the servers' command lines, and each run's load at start."""
    runs = []
    for item in items:
        server, _, path = item.partition("=")
        runs.append((server, json.loads(Path(path).read_text())))
    first = runs[0][1]
    results, commands, loads = [], {}, []
    for order, (server, report) in enumerate(runs, start=1):
        commands[server] = report["settings"]["web_command"]
        loads.append(report.get("load_average_at_start"))
        for row in report["results"]:
            results.append({"server": server, "order": order, **row})
    summary = {}
    for server in commands:
        rows = [row for row in results if row["server"] == server]
        summary[server] = {
            "bursts": len(rows),
            "not_201": sum(row["sent"] - row["http_201"] for row in rows),
            **{f"median_{key}": statistics.median(row[key] for row in rows) for key in SUMMARIZED},
        }
    combined = {
        "benchmark": NAME,
        "date": first["date"],
        "machine": first["machine"],
        "anvil": first.get("anvil"),
        "load_average_at_start": first.get("load_average_at_start"),
        "loads_at_start": loads,
        "settings": {**first["settings"], "web_commands": commands},
        "summary": summary,
        "results": results,
        "notes": [
            "each burst on a fresh make-run stack, the servers in alternation (order), one "
            "checkout per server; the figure of each server is the median of its bursts",
        ],
    }
    results_dir.mkdir(parents=True, exist_ok=True)
    (results_dir / f"{NAME}.json").write_text(json.dumps(combined, indent=2) + "\n")
    print(json.dumps(summary, indent=2))
    return 0

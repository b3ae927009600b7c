"""SM4 envelope seal/open of 1-8 KB and SM3 of 800 KB: smcrypto against pure-Python gmssl.

The paper's Figs. 17-26 measure SM4 encryption/decryption of 1, 2, 4 and 8 KB messages and
SM3 of an 800 KB message, 300 times each. smcrypto (cryptography/OpenSSL) is measured with
the real envelope (SM4-GCM seal/open); gmssl has no GCM, so its baseline for seal/open is SM4-CBC
encrypt/decrypt of the same sizes. Rows `sm4-cbc-*` compare CBC with CBC (the gmssl timings
are the same samples as the seal/open baseline).

Every measurement, smcrypto's and gmssl's, is timed --repeat times (default 300, as the paper)
after warm-up; gmssl's SM3 of 800 KB takes about 3 s a run, so a full run takes a quarter of an
hour. `--gmssl-budget SECONDS` opts in to fewer gmssl runs where 300 would take longer than
that; `--quick` (a smoke run) times 20 runs each with a 5 s budget. The repeats actually made are
in the results, per row.

Run: `python -m bench crypto [--repeat N] [--gmssl-budget S] [--quick]`.
Writes bench/results/crypto.json, crypto.csv and crypto.png.
"""

import argparse
import math
import os
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from cryptography.hazmat.backends.openssl import backend as openssl_backend
from gmssl.sm3 import sm3_hash
from gmssl.sm4 import SM4_DECRYPT, SM4_ENCRYPT, CryptSM4
from tqdm import tqdm

from bench import RESULTS_DIR, machine_info, measure, now_iso, progress_bar, summarize
from bench.common import write_results
from bench.plotting import plt, save_figure
from smcrypto import envelope, sm4
from smcrypto.sm3 import sm3_digest

REPEAT = 300  # the paper's 300 times, for smcrypto and gmssl alike
QUICK_REPEAT = 20
QUICK_GMSSL_BUDGET = 5.0
SMCRYPTO_WARMUP = 3
GMSSL_WARMUP = 1  # gmssl SM3 of 800 KB takes seconds a run
MESSAGE_SIZES = (1024, 2048, 4096, 8192)
SM3_SIZE = 800 * 1024
HEADER = {
    "owner": "bench",
    "robot": "bench-robot",
    "topic": "/odom",
    "type": "nav_msgs/Odometry",
    "seq": 0,
    "time": "2026-11-21T14:00:00.000000Z",
}
WHAT_IS_TIMED = {
    "seal": ("SM4-GCM envelope seal", "SM4-CBC encrypt"),
    "open": ("SM4-GCM envelope open", "SM4-CBC decrypt"),
    "sm4-cbc-encrypt": ("SM4-CBC encrypt", "SM4-CBC encrypt"),
    "sm4-cbc-decrypt": ("SM4-CBC decrypt", "SM4-CBC decrypt"),
    "sm3": ("SM3", "SM3"),
}
NOTES = [
    "smcrypto seal/open = Envelope v1 with SM4-GCM via cryptography/OpenSSL (header included).",
    "gmssl has no GCM: its seal/open baseline is gmssl SM4-CBC encrypt/decrypt (PKCS#7) "
    "of the same message sizes, without a header.",
    "sm4-cbc rows compare smcrypto SM4-CBC with the same gmssl CBC samples.",
    "gmssl SM3 timings include converting the message to the list gmssl takes (<1%).",
]


def main(argv: list[str]) -> int:
    """Run the benchmark, print the table and write JSON, CSV and PNG results."""
    parser = argparse.ArgumentParser(prog="python -m bench crypto", description=__doc__)
    parser.add_argument(
        "--repeat",
        type=int,
        help=f"timed runs per measurement, for both (default {REPEAT}; --quick {QUICK_REPEAT})",
    )
    parser.add_argument(
        "--gmssl-budget",
        type=float,
        help="opt in: seconds one gmssl measurement may take, fewer repeats if needed "
        f"(default: none, every measurement gets --repeat runs; --quick {QUICK_GMSSL_BUDGET:g})",
    )
    parser.add_argument("--quick", action="store_true", help="smoke run with small numbers")
    parser.add_argument("--results-dir", type=Path, default=RESULTS_DIR)
    args = parser.parse_args(argv)
    repeat = args.repeat if args.repeat is not None else (QUICK_REPEAT if args.quick else REPEAT)
    budget = args.gmssl_budget
    if budget is None and args.quick:
        budget = QUICK_GMSSL_BUDGET
    if repeat < 1:
        parser.error("--repeat must be at least 1")
    if budget is not None and budget <= 0:
        parser.error("--gmssl-budget must be positive")

    started = now_iso()
    rows = _run_all(repeat, budget)
    notes = list(NOTES)
    if budget is not None:
        notes.append(
            f"gmssl repeats were capped so one measurement stays within {budget:g} s "
            "(--gmssl-budget): see each row's repeats."
        )
    if any(row["gmssl"]["repeats"] < repeat for row in rows):
        notes.append(
            "fewer gmssl runs than smcrypto runs in: "
            + ", ".join(
                f"{row['operation']} {_size_label(row['size_bytes'])} ({row['gmssl']['repeats']})"
                for row in rows
                if row["gmssl"]["repeats"] < repeat
            )
            + "."
        )
    report = {
        "benchmark": "crypto",
        "date": started,
        "machine": machine_info(("cryptography", "gmssl", "matplotlib")),
        "openssl": openssl_backend.openssl_version_text(),
        "settings": {
            "repeat": repeat,
            "gmssl_budget_seconds": budget,
            "quick": args.quick,
            "warmup": {"smcrypto": SMCRYPTO_WARMUP, "gmssl": GMSSL_WARMUP},
            "message_sizes": list(MESSAGE_SIZES),
            "sm3_size": SM3_SIZE,
        },
        "notes": notes,
        "results": rows,
    }
    _print_table(report)
    write_results(
        "crypto", report, CSV_FIELDS, args.results_dir, plot=_plot, csv_rows=_csv_rows(rows)
    )
    return 0


def _run_all(repeat: int, gmssl_budget: float | None) -> list[dict[str, Any]]:
    key, iv = sm4.generate_key(), os.urandom(sm4.CBC_IV_SIZE)
    gmssl_encryptor, gmssl_decryptor = CryptSM4(), CryptSM4()
    gmssl_encryptor.set_key(key, SM4_ENCRYPT)
    gmssl_decryptor.set_key(key, SM4_DECRYPT)
    rows = []
    with progress_bar((6 * len(MESSAGE_SIZES) + 2) * repeat, "crypto") as progress:
        for size in MESSAGE_SIZES:
            message = os.urandom(size)
            sealed = envelope.seal(key, HEADER, message)
            cbc = sm4.cbc_encrypt(key, iv, message)
            if gmssl_encryptor.crypt_cbc(iv, message) != cbc:
                raise RuntimeError("gmssl and smcrypto SM4-CBC disagree: refusing to benchmark")
            progress.set_description(f"smcrypto {_size_label(size)}")
            seal = measure(
                lambda m=message: envelope.seal(key, HEADER, m), repeat, progress, SMCRYPTO_WARMUP
            )
            opened = measure(
                lambda s=sealed: envelope.open(key, s), repeat, progress, SMCRYPTO_WARMUP
            )
            cbc_encrypt = measure(
                lambda m=message: sm4.cbc_encrypt(key, iv, m), repeat, progress, SMCRYPTO_WARMUP
            )
            cbc_decrypt = measure(
                lambda c=cbc: sm4.cbc_decrypt(key, iv, c), repeat, progress, SMCRYPTO_WARMUP
            )
            progress.set_description(f"gmssl SM4-CBC {_size_label(size)}")
            gmssl_encrypt = _measure_gmssl(
                lambda m=message: gmssl_encryptor.crypt_cbc(iv, m), repeat, gmssl_budget, progress
            )
            gmssl_decrypt = _measure_gmssl(
                lambda c=cbc: gmssl_decryptor.crypt_cbc(iv, c), repeat, gmssl_budget, progress
            )
            for operation, ours, theirs in (
                ("seal", seal, gmssl_encrypt),
                ("open", opened, gmssl_decrypt),
                ("sm4-cbc-encrypt", cbc_encrypt, gmssl_encrypt),
                ("sm4-cbc-decrypt", cbc_decrypt, gmssl_decrypt),
            ):
                rows.append(_row(operation, size, ours, theirs))

        message = os.urandom(SM3_SIZE)
        if sm3_digest(message[:4096]).hex() != sm3_hash(list(message[:4096])):
            raise RuntimeError("gmssl and smcrypto SM3 disagree: refusing to benchmark")
        progress.set_description(f"smcrypto SM3 {_size_label(SM3_SIZE)}")
        ours = measure(lambda: sm3_digest(message), repeat, progress, SMCRYPTO_WARMUP)
        progress.set_description(f"gmssl SM3 {_size_label(SM3_SIZE)}")
        # gmssl hashes a list of ints and pads it in place, so each run converts afresh (<1%)
        theirs = _measure_gmssl(lambda: sm3_hash(list(message)), repeat, gmssl_budget, progress)
        rows.append(_row("sm3", SM3_SIZE, ours, theirs))
    return rows


def _measure_gmssl(
    operation: Callable[[], object], repeat: int, budget: float | None, progress: tqdm
) -> list[float]:
    """Like measure, with one warm-up run; with a budget, fewer repeats when repeat runs would
    take longer than budget seconds (at least 3)."""
    started = time.perf_counter()
    for _ in range(GMSSL_WARMUP):
        operation()  # warm-up, and how long one run takes
    affordable = repeat
    if budget is not None:
        one_run = (time.perf_counter() - started) / GMSSL_WARMUP
        affordable = min(repeat, max(3, math.floor(budget / one_run)))
        progress.total -= repeat - affordable
        progress.refresh()
    return measure(operation, affordable, progress, warmup=0)


def _row(operation: str, size: int, ours: list[float], theirs: list[float]) -> dict[str, Any]:
    ours_what, theirs_what = WHAT_IS_TIMED[operation]
    smcrypto_stats = summarize(ours)
    gmssl_stats = summarize(theirs)
    return {
        "operation": operation,
        "size_bytes": size,
        "smcrypto": {
            "what": ours_what,
            "repeats": len(ours),
            **smcrypto_stats,
            "samples_ms": [round(sample, 4) for sample in ours],
        },
        "gmssl": {
            "what": theirs_what,
            "repeats": len(theirs),
            **gmssl_stats,
            "samples_ms": [round(sample, 4) for sample in theirs],
        },
        "ratio_gmssl_over_smcrypto": gmssl_stats["median_ms"] / smcrypto_stats["median_ms"],
    }


def _size_label(size: int) -> str:
    return f"{size // 1024} KB"


def _print_table(report: dict[str, Any]) -> None:
    machine = report["machine"]
    print(
        f"crypto benchmark, {report['date']}: {machine['cpu_model']}, "
        f"{machine['logical_cores']} cores, {machine['memory_bytes'] / 2**30:.1f} GiB, "
        f"{machine['python']}, cryptography {machine['cryptography_version']} "
        f"({report['openssl']}), gmssl {machine['gmssl_version']}"
    )
    for note in report["notes"]:
        print(f"  note: {note}")
    header = (
        f"{'operation':<16} {'size':>7} {'n smcrypto':>10} {'n gmssl':>7} "
        f"{'median ms smcrypto':>18} {'median ms gmssl':>15} {'gmssl/smcrypto':>14}"
    )
    print(header)
    print("-" * len(header))
    for row in report["results"]:
        print(
            f"{row['operation']:<16} {_size_label(row['size_bytes']):>7} "
            f"{row['smcrypto']['repeats']:>10} {row['gmssl']['repeats']:>7} "
            f"{row['smcrypto']['median_ms']:>18.4f} {row['gmssl']['median_ms']:>15.3f} "
            f"{row['ratio_gmssl_over_smcrypto']:>14.0f}"
        )


CSV_STATS = ("median_ms", "mean_ms", "p5_ms", "p95_ms", "min_ms", "max_ms")
CSV_FIELDS = ("operation", "size_bytes", "implementation", "what", "repeats", *CSV_STATS)


def _csv_rows(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """One CSV row per measurement: each result row holds smcrypto's and gmssl's."""
    return [
        {"operation": row["operation"], "size_bytes": row["size_bytes"]}
        | {"implementation": implementation}
        | {key: row[implementation][key] for key in ("what", "repeats", *CSV_STATS)}
        for row in rows
        for implementation in ("smcrypto", "gmssl")
    ]


def _plot(report: dict[str, Any], path: Path) -> None:
    rows = report["results"]
    figure, (left, right) = plt.subplots(
        1, 2, figsize=(12, 5), gridspec_kw={"width_ratios": [3, 1]}
    )
    sizes_kb = [size / 1024 for size in MESSAGE_SIZES]
    series = [
        ("seal", "smcrypto", "smcrypto seal (SM4-GCM envelope)", "tab:blue", "o-"),
        ("open", "smcrypto", "smcrypto open (SM4-GCM envelope)", "tab:cyan", "s-"),
        ("seal", "gmssl", "gmssl SM4-CBC encrypt", "tab:red", "o--"),
        ("open", "gmssl", "gmssl SM4-CBC decrypt", "tab:orange", "s--"),
        ("sm4-cbc-encrypt", "smcrypto", "smcrypto SM4-CBC encrypt", "tab:green", "^:"),
        ("sm4-cbc-decrypt", "smcrypto", "smcrypto SM4-CBC decrypt", "tab:olive", "v:"),
    ]
    for operation, implementation, label, colour, style in series:
        measured = [
            row[implementation]
            for row in rows
            if row["operation"] == operation and row["size_bytes"] in MESSAGE_SIZES
        ]
        medians = [m["median_ms"] for m in measured]
        errors = [
            [m["median_ms"] - m["p5_ms"] for m in measured],
            [m["p95_ms"] - m["median_ms"] for m in measured],
        ]
        left.errorbar(
            sizes_kb, medians, yerr=errors, fmt=style, color=colour, label=label, capsize=3
        )
    left.set_yscale("log")
    left.set_xscale("log", base=2)
    left.set_xticks(sizes_kb, [f"{size:g} KB" for size in sizes_kb])
    left.set_xlabel("message size")
    left.set_ylabel("median time per message, ms (log; bars: p5-p95)")
    left.set_title("SM4 seal / open")
    left.grid(True, which="both", alpha=0.3)
    left.legend(fontsize=8)

    sm3_row = next(row for row in rows if row["operation"] == "sm3")
    names = [
        f"smcrypto\n(n={sm3_row['smcrypto']['repeats']})",
        f"gmssl\n(n={sm3_row['gmssl']['repeats']})",
    ]
    medians = [sm3_row["smcrypto"]["median_ms"], sm3_row["gmssl"]["median_ms"]]
    bars = right.bar(names, medians, color=["tab:blue", "tab:red"])
    right.bar_label(bars, labels=[f"{value:.4g} ms" for value in medians], fontsize=8)
    right.set_yscale("log")
    right.set_ylabel("median time, ms (log)")
    right.set_title(f"SM3 of {SM3_SIZE // 1024} KB")
    right.grid(True, axis="y", which="both", alpha=0.3)

    machine = report["machine"]
    save_figure(
        figure,
        path,
        f"smcrypto (cryptography {machine['cryptography_version']}, {report['openssl']}) "
        f"vs gmssl {machine['gmssl_version']} (pure Python): "
        f"{machine['cpu_model']}, {report['date']}",
    )

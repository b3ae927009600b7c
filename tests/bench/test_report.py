"""The benchmark report and the sustained benchmark's statistics, on made-up result files.

No benchmark runs here (they take minutes and measure time); these check that what the
benchmarks write is read back faithfully, and that nothing in the report is invented.
"""

import json
import math

import pytest

from bench import available, report, sustained
from bench.__main__ import main as bench_main


def _machine() -> dict:
    return {"cpu_model": "Test CPU", "logical_cores": 3, "memory_bytes": 5 * 2**30}


def _sustained_row(mode: str, batch_max: int, anchored_per_s: float) -> dict:
    return {
        "mode": mode,
        "batch_max": batch_max,
        "offered_per_s": 100.0,
        "accepted_per_s": 98.5,
        "anchored_per_s": anchored_per_s,
        "anchored_per_s_ratio_vs_batch1": anchored_per_s / 17.25,
        "pending_after_drain": 0,
        "to_anchored_p50_s": 0.75,
        "to_anchored_p95_s": 1.5,
        "to_anchored_p99_s": None,  # fell on a record never anchored
        "to_verified_p50_s": 1.25,
        "to_verified_p95_s": 2.0,
        "to_verified_p99_s": 3.0,
        "views": 40,
        "verified_views": 39,
        "web_cpu_mean_pct": 61.0,
        "workers_cpu_mean_pct": 87.0,
        "anvil_cpu_mean_pct": 12.0,
        "web_rss_peak_mib": 321.0,
        "workers_rss_peak_mib": 456.0,
    }


def test_the_report_quotes_the_paper_and_reads_every_number_from_the_results(tmp_path):
    results = tmp_path / "results"
    results.mkdir()
    (results / "sustained.json").write_text(
        json.dumps(
            {
                "benchmark": "sustained",
                "date": "2031-02-03T04:05:06Z",
                "machine": _machine(),
                "settings": {"agents": "7 robots", "duration_s": 42.0, "quick": False},
                "notes": ["a note from the run"],
                "results": [
                    _sustained_row("automine", 1, 17.25),
                    _sustained_row("automine", 100, 123.5),
                ],
            }
        )
    )
    output = tmp_path / "REPORT.md"

    assert report.main(["--results-dir", str(results), "--output", str(output)]) == 0

    text = output.read_text()
    assert "2031-02-03T04:05:06Z" in text
    assert "Test CPU; 3 logical cores; 5.0 GiB memory" in text
    assert "7 robots, for 42 s" in text
    assert "| automine | 100 | 100 | 98.5 | 123.5 | 7.16x | 0 | 0.75 / 1.50 / - |" in text
    assert "1.25 / 2.00 / 3.00 | 39/40 | 61 / 87 / 12 | 321 / 456 |" in text
    assert "123.5 records/s (automine, ANCHOR_BATCH_MAX 100) against 100 offered" in text
    assert "- a note from the run" in text
    assert "](results/sustained.png)" in text
    for missing in ("Concurrency", "Message size", "SM4 and SM3"):
        assert missing not in text  # no results, no section: nothing is made up


def test_without_results_the_report_says_so(tmp_path):
    output = tmp_path / "REPORT.md"
    assert report.main(["--results-dir", str(tmp_path), "--output", str(output)]) == 0
    assert "No results yet" in output.read_text()


def test_percentiles_are_nearest_rank_and_never_hide_an_unfinished_record():
    samples = [float(n) for n in range(1, 101)]
    assert sustained._percentiles(samples, "x") == {
        "x_p50_s": 50.0,
        "x_p95_s": 95.0,
        "x_p99_s": 99.0,
    }
    with_two_lost = [*samples[:98], math.inf, math.inf]
    assert sustained._percentiles(with_two_lost, "x") == {
        "x_p50_s": 50.0,
        "x_p95_s": 95.0,
        "x_p99_s": None,
    }
    assert sustained._percentiles([], "x") == {"x_p50_s": None, "x_p95_s": None, "x_p99_s": None}


def test_the_view_sample_is_about_one_in_n():
    import uuid

    ids = [str(uuid.uuid4()) for _ in range(5000)]
    share = sum(sustained._sampled(record_id, 5) for record_id in ids) / len(ids)
    assert 0.17 < share < 0.23


def test_ratios_divide_by_batch_one_of_the_same_mode():
    rows = [
        {"mode": "automine", "batch_max": 1, "anchored_per_s": 10.0, "to_anchored_p50_s": 4.0},
        {"mode": "automine", "batch_max": 100, "anchored_per_s": 50.0, "to_anchored_p50_s": 1.0},
        {"mode": "block-time 1s", "batch_max": 100, "anchored_per_s": 30.0},
    ]
    sustained._add_ratios(rows)
    assert rows[1]["anchored_per_s_ratio_vs_batch1"] == 5.0
    assert rows[1]["to_anchored_p50_s_ratio_vs_batch1"] == 0.25
    assert rows[2]["anchored_per_s_ratio_vs_batch1"] is None  # no baseline in this run


def test_every_benchmark_is_listed_and_an_unknown_one_is_refused(capsys):
    assert {"block_interval", "concurrency", "crypto", "message_size", "pipeline"} <= set(
        available()
    )
    assert {"report", "sustained"} <= set(available())
    assert bench_main(["no-such-bench"]) == 2
    assert "unknown benchmark 'no-such-bench'" in capsys.readouterr().err


@pytest.mark.parametrize("argv", [["--agents", "0"], ["--warmup", "70", "--duration", "60"]])
def test_sustained_refuses_nonsense_arguments(argv):
    with pytest.raises(SystemExit) as exit_info:
        sustained.main(argv)
    assert exit_info.value.code == 2

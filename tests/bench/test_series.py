"""The series benchmark's pure parts: the variants' turns, each variant's rows and their ratios
(against per record, and against unsigned on the same path), its arguments refused before
anything starts; and its section of the report, from a made-up series.json of a run with a
robot per variant. No stack starts here."""

import json

import pytest

from bench import report, series


def test_the_variants_take_turns_reading_first():
    assert list(series.series_orders(4, series.VARIANTS)) == [
        ("unsigned", "signed", "v2"),
        ("signed", "v2", "unsigned"),
        ("v2", "unsigned", "signed"),
        ("unsigned", "signed", "v2"),
    ]


def _measured(variant: str, series_seconds: list[float], per_record_s: float, workers: float):
    answers = [{"source_records": 100, "verified": 100, "refused": 0, "points": 100}]
    return {
        "upload_and_anchor_s": 3.0,
        "trees": 2,
        "series": {
            "seconds": series_seconds,
            "answers": answers * len(series_seconds),
            "records_checked": 100 * len(series_seconds),
            "web_cpu_ms_per_record": 0.1,
            "workers_cpu_ms_per_record": workers,
            "others_cpu_share": 0.25,
        },
        "per_record": {
            "seconds": [per_record_s] * 3,
            "failed": 0,
            "records_checked": 3,
            "web_cpu_ms_per_record": 5.0,
            "workers_cpu_ms_per_record": 10.0,
            "others_cpu_share": 0.5,
        },
    }


def _rows() -> list[dict]:
    run = series.SeriesRun(
        records=100, series_rounds=2, per_record_sample=3, workers=2, web_workers=0,
        redis_url="redis://127.0.0.1:6379/13", keep_logs=False,
    )  # fmt: skip
    measured = {
        "variants": {
            "unsigned": _measured("unsigned", [1.0, 1.0], 0.010, 0.2),
            "signed": _measured("signed", [2.0, 2.0], 0.012, 0.8),
            "v2": _measured("v2", [1.5, 1.5], 0.011, 0.4),
        }
    }
    return series._rows(measured, run)


def test_each_variant_has_a_per_record_and_a_series_row_with_both_ratios():
    rows = {(row["variant"], row["path"]): row for row in _rows()}

    assert len(rows) == 6
    assert rows[("signed", "per record")]["p50_s"] == pytest.approx(1.2)  # 12 ms x 100
    assert rows[("signed", "series")]["p50_ratio_vs_per_record"] == pytest.approx(2.0 / 1.2)
    assert rows[("v2", "series")]["p50_ratio_vs_unsigned"] == pytest.approx(1.5)
    assert rows[("v2", "series")]["workers_cpu_ratio_vs_unsigned"] == pytest.approx(2.0)
    assert rows[("signed", "per record")]["p50_ratio_vs_unsigned"] == pytest.approx(1.2)
    assert rows[("unsigned", "series")]["p50_ratio_vs_unsigned"] == 1.0


def test_without_an_unsigned_robot_there_is_no_ratio_against_it():
    rows = [row for row in _rows() if row["variant"] != "unsigned"]
    series.ratios_vs_unsigned(rows)
    assert {row["p50_ratio_vs_unsigned"] for row in rows} == {None}


@pytest.mark.parametrize("argv", [["--variants", "v3"], ["--variants", ""], ["--rounds", "0"]])
def test_series_refuses_nonsense_arguments_before_starting_anything(argv):
    with pytest.raises(SystemExit) as exit_info:
        series.main(argv)
    assert exit_info.value.code == 2


def test_the_series_section_sets_each_variant_beside_unsigned(tmp_path):
    results = tmp_path / "results"
    results.mkdir()
    rows = _rows()
    data = {
        "benchmark": "series",
        "date": "2031-02-03T04:05:06Z",
        "machine": {"cpu_model": "Test CPU", "logical_cores": 2, "memory_bytes": 4 * 2**30},
        "load_average_at_start": [1.5, 1.25, 1.0],
        "load_average_at_end": [2.5, 1.5, 1.0],
        "settings": {
            "quick": True,
            "records": 100,
            "per_post": 500,
            "variants": list(series.VARIANTS),
            "sm2_backend": "gmssl",
        },
        "goal_p50_s": 2.0,
        "goal_met": {"unsigned": True, "signed": False, "v2": True},
        "results": rows,
    }
    (results / "series.json").write_text(json.dumps(data))
    output = tmp_path / "REPORT.md"
    assert report.main(["--results-dir", str(results), "--output", str(output)]) == 0
    text = output.read_text()

    assert "one robot per variant (`unsigned`: a robot added by hand" in text
    assert "SM2 through smcrypto.sm2's `gmssl` backend" in text
    row = "| v2 | series | 1.50 | 1.50 | 0.100 | 0.400 | 1.36x | 1.50x | 1.00x, 2.00x | 25.0% |"
    assert row in text
    assert "| unsigned | per record | 1.00 | - |" in text
    judged = "for 18,000 records: this run has 100): unsigned **met**, signed **not met**, v2 "
    assert judged in text
    assert "![Series against per record](results/series.png)" in text


def test_the_scale_reads_and_first_plots_are_rows_of_their_own_and_plotted(tmp_path):
    run = series.SeriesRun(
        records=300, series_rounds=2, per_record_sample=3, workers=2, web_workers=0,
        redis_url="redis://127.0.0.1:6379/13", keep_logs=False, scale=(100,), first_plots=True,
    )  # fmt: skip
    found = _measured("v2", [3.0, 3.0], 0.011, 0.4)
    found["scale"] = {"100": found["series"] | {"seconds": [1.0, 1.2]}}
    found["first_plots"] = {
        "first plot, robot page": {
            "seconds": [0.8, 1.0],
            "verified": [60, 61],
            "timings_ms": [
                {"html": 100.0, "scripts_run": 150.0, "series_asked": 160.0, "series_in": 700.0},
                {"html": 120.0, "scripts_run": 170.0, "series_asked": 180.0, "series_in": 900.0},
            ],
        },
    }
    rows = series._rows({"variants": {"v2": found}}, run)
    by = {(row["path"], row["records"]): row for row in rows}

    assert by[("series, first records", 100)]["p50_s"] == pytest.approx(1.1)
    assert by[("series", 300)]["p50_s"] == 3.0
    plot = by[("first plot, robot page", 61)]
    assert (plot["p50_s"], plot["verified"], plot["rounds"]) == (pytest.approx(0.9), [60, 61], 2)
    assert plot["timings_ms"] == {
        "html": 110.0, "scripts_run": 160.0, "series_asked": 170.0, "series_in": 800.0,
        "drawn": 0.0,
    }  # fmt: skip
    assert plot["p50_ratio_vs_unsigned"] is None  # no unsigned robot, and no CPU of its own

    baseline = [dict(by[("series", 300)], p50_s=6.0)]
    series.ratios_vs_baseline(rows, baseline)
    assert by[("series", 300)]["p50_ratio_vs_baseline"] == pytest.approx(0.5)
    assert by[("series, first records", 100)]["p50_ratio_vs_baseline"] is None

    report = {
        "results": rows,
        "settings": {"records": 300},
        "goal_p50_s": 1.0,
        "machine": {"cpu_model": "Test CPU", "logical_cores": 2, "memory_bytes": 2**30},
        "date": "2031-02-03T04:05:06Z",
        "baseline": {"results": baseline},
    }
    series._plot(report, tmp_path / "series.png")
    assert (tmp_path / "series.png").stat().st_size > 0


@pytest.mark.parametrize("scale", ["300", "0", "x", "-5"])
def test_scale_counts_are_below_the_records(scale):
    with pytest.raises(SystemExit) as exit_info:
        series.main(["--records", "300", "--scale", scale])
    assert exit_info.value.code == 2


def test_first_plots_need_the_v2_robot():
    with pytest.raises(SystemExit) as exit_info:
        series.main(["--variants", "unsigned", "--first-plots"])
    assert exit_info.value.code == 2

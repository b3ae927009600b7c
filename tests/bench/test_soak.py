"""The soak benchmark's pure parts, on made-up samples: the latency p95, the memory growth, the
goals' verdicts and the report's section. The soak itself runs for an hour and measures time:
never here.
"""

import json

import pytest

import bench.__main__ as bench_entry
from bench import report, soak


def _sample(
    t: float,
    *,
    pending: int = 3,
    failed: int = 0,
    uploads: float = 660.0,
    rss: dict | None = None,
    audit: tuple[float | None, str] = (0.05, "200"),
    record: tuple[float | None, str] = (0.08, "200"),
) -> dict:
    return {
        "t_s": t,
        "at": "2031-01-01T00:00:00+00:00",
        "anchored": int(t * 11),
        "pending": pending,
        "failed": failed,
        "uploads_per_minute": uploads,
        "anchored_in_interval": 220,
        "latency_p95_s": 1.2,
        "rss_mib": rss if rss is not None else {"web": 600.0, "worker": 400.0, "anvil": 30.0},
        "pages": {
            "audit": {"s": audit[0], "status": audit[1]},
            "record": {"s": record[0], "status": record[1]},
        },
    }


def _samples(count: int = 8, **last: object) -> list[dict]:
    samples = [_sample(20.0 * n) for n in range(count - 1)]
    return [*samples, _sample(20.0 * (count - 1), **last)]


def _verdicts(samples: list[dict]) -> list[bool | None]:
    return [goal["met"] for goal in soak.goals_evaluate(samples)]


def test_the_latency_p95_is_nearest_rank_and_none_without_records():
    assert soak.latency_p95([float(n) for n in range(1, 101)]) == 95.0
    assert soak.latency_p95([float(n) for n in range(1, 21)]) == 19.0
    assert soak.latency_p95([2.5]) == 2.5
    assert soak.latency_p95([]) is None


def test_memory_growth_compares_the_last_quarter_median_with_the_first():
    values = [100.0, 110.0, 120.0, 130.0, 140.0, 150.0, 160.0, 170.0]
    samples = [_sample(20.0 * n, rss={"web": value}) for n, value in enumerate(values)]
    growth = soak.rss_growth(samples)["web"]
    assert growth["first_mib"] == 105.0  # median of the first two of eight
    assert growth["last_mib"] == 165.0
    assert growth["growth"] == pytest.approx(165 / 105 - 1)


def test_a_process_gone_at_some_samples_is_judged_on_the_others():
    samples = [_sample(20.0 * n, rss={"web": 100.0, "sim": None}) for n in range(3)]
    samples.append(_sample(60.0, rss={"web": 100.0, "sim": 80.0}))
    growth = soak.rss_growth(samples)
    assert growth["web"]["growth"] == 0.0
    assert growth["sim"] == {"first_mib": None, "last_mib": None, "growth": None}


def test_every_goal_is_met_by_a_calm_run():
    goals = soak.goals_evaluate(_samples())
    assert [goal["met"] for goal in goals] == [True, True, True, True]
    assert goals[3]["measured"] == "audit 50 ms (200), record 80 ms (200)"


def test_one_failed_record_at_any_sample_misses_the_first_goal():
    samples = _samples()
    samples[2]["failed"] = 1
    goal = soak.goals_evaluate(samples)[0]
    assert goal["met"] is False
    assert goal["measured"] == "0 failed at the end, at most 1 at a sample"


def test_pending_must_stay_under_a_minute_of_uploads_at_every_sample():
    samples = _samples()
    samples[4] |= {"pending": 700, "uploads_per_minute": 660.0}
    goal = soak.goals_evaluate(samples)[1]
    assert goal["met"] is False
    assert goal["measured"] == (
        "1 of 8 samples over; worst 700 pending against 660 uploads a minute (at 1.3 min)"
    )
    quiet = _samples(pending=0, uploads=0.0)  # nothing uploaded, nothing waiting
    assert soak.goals_evaluate(quiet)[1]["met"] is True


def test_memory_that_grows_misses_the_flat_memory_goal_but_anvil_is_not_judged():
    growing = [_sample(20.0 * n, rss={"web": 600.0 + 30 * n, "anvil": 30.0}) for n in range(8)]
    goal = soak.goals_evaluate(growing)[2]
    assert goal["met"] is False
    assert goal["measured"] == "largest growth web: 615 -> 795 MiB (+29.3%)"
    chain_grows = [_sample(20.0 * n, rss={"web": 600.0, "anvil": 30.0 + 10 * n}) for n in range(8)]
    assert soak.goals_evaluate(chain_grows)[2]["met"] is True
    assert _verdicts([_sample(0.0)])[2] is None  # one sample: no growth to judge


@pytest.mark.parametrize(
    "last",
    [
        {"audit": (0.31, "200")},
        {"record": (0.05, "503")},
        {"record": (None, "no anchored record")},
        {"audit": (None, "ReadTimeout")},
    ],
)
def test_a_slow_refused_or_missing_page_at_the_end_misses_the_page_goal(last):
    assert _verdicts(_samples(**last)) == [True, True, True, False]


def test_a_slow_page_before_the_end_does_not_count():
    samples = _samples()
    samples[3]["pages"]["audit"]["s"] = 2.0
    assert _verdicts(samples)[3] is True


def test_without_samples_nothing_is_claimed():
    assert _verdicts([]) == [None, None, None, None]


@pytest.mark.parametrize(
    "argv",
    [
        ["--minutes", "0"],
        ["--interval", "0"],
        ["--minutes", "1", "--interval", "61"],
        ["--redis-url", "redis://127.0.0.1:6379/0"],
    ],
)
def test_the_soak_refuses_nonsense_arguments(argv):
    with pytest.raises(SystemExit) as exit_info:
        soak.main(argv)
    assert exit_info.value.code == 2


def test_the_soak_runs_only_when_named(monkeypatch, capsys):
    ran = []
    monkeypatch.setattr(bench_entry, "_run", lambda name, args: ran.append(name) or 0)
    assert bench_entry.main([]) == 0
    assert "soak" not in ran
    assert ran[-1] == "report"
    assert bench_entry.main(["soak", "--minutes", "1"]) == 0
    assert ran[-1] == "soak"
    bench_entry.main(["--help"])
    assert "soak" in capsys.readouterr().out


def _soak_report(samples: list[dict], *, ran_s: float, minutes: float) -> dict:
    return {
        "benchmark": "soak",
        "date": "2031-05-06T07:08:09Z",
        "machine": {"cpu_model": "Test CPU", "logical_cores": 3, "memory_bytes": 5 * 2**30},
        "settings": {
            "minutes": minutes,
            "interval_s": 20.0,
            "stack": "python -m stack run --ros",
            "web_command": "gunicorn -k x",
            "anchor_batch_max": 100,
            "anchor_max_wait_s": 1.0,
        },
        "run": {"ran_s": ran_s, "stopped_early": None},
        "goals": soak.goals_evaluate(samples),
        "rss_growth": soak.rss_growth(samples),
        "notes": ["a note from the run"],
        "results": samples,
    }


def test_the_report_says_how_long_the_soak_ran_and_each_goal_met_or_not(tmp_path):
    results = tmp_path / "results"
    results.mkdir()
    samples = _samples(31, audit=(0.45, "200"))
    (results / "soak.json").write_text(json.dumps(_soak_report(samples, ran_s=600.4, minutes=10.0)))
    output = tmp_path / "REPORT.md"

    assert report.main(["--results-dir", str(results), "--output", str(output)]) == 0

    text = output.read_text()
    assert "## Soak: the `make run` stack with its simulated robot, 10 minutes" in text
    assert "It ran 10 minutes (31 samples every 20 s; 10 asked for)." in text
    assert "**A 10-minute run, not the soak of at least 60 minutes the issue asks for**" in text
    assert "| 0 failed records | 0 failed at the end, at most 0 at a sample | met |" in text
    assert (
        "| every page under 300 ms at the end | audit 450 ms (200), record 80 ms (200) "
        "| **not met** |"
    ) in text
    assert "| web | 600.0 | 600.0 | 0.0% |" in text
    assert "- a note from the run" in text
    assert "![Soak](results/soak.png)" in text


def test_an_hour_long_soak_is_not_called_short(tmp_path):
    results = tmp_path / "results"
    results.mkdir()
    samples = _samples(121)
    (results / "soak.json").write_text(
        json.dumps(_soak_report(samples, ran_s=3600.2, minutes=60.0))
    )
    output = tmp_path / "REPORT.md"

    assert report.main(["--results-dir", str(results), "--output", str(output)]) == 0

    text = output.read_text()
    assert "It ran 60 minutes (121 samples every 20 s; 60 asked for)." in text
    assert "not the soak" not in text

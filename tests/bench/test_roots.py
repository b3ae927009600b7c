"""The roots benchmark's bursts: the median burst is the figure, none is left out."""

import pytest

from bench import roots


@pytest.fixture
def bursts_of(monkeypatch):
    """Bursts answered in turn from the given results, no stack started."""

    def make(results):
        answers = iter(results)
        monkeypatch.setattr(roots, "run_in_child", lambda function, run: next(answers))

    return make


class _Run:
    def describe(self):
        return "a burst"


def _burst(total, *, anchored=700, transactions=30):
    return {
        "total_to_anchored_s": total,
        "anchored": anchored,
        "sent": 700,
        "verified": anchored,
        "transactions": transactions,
        "stack_cpu_s": {"web": total},
    }


def test_the_figure_is_the_median_burst_and_every_total_is_kept(bursts_of):
    bursts_of(
        [_burst(2.6, transactions=1), _burst(1.5, transactions=2), _burst(1.8, transactions=3)]
    )

    row = roots._bursts(_Run(), 3)

    assert row["concurrent_700_total_s"] == 1.8
    assert row["concurrent_700_total_s_runs"] == [2.6, 1.5, 1.8]
    # The other figures are the median burst's own, not a mix of bursts.
    assert row["concurrent_700_transactions"] == 3
    assert row["concurrent_700_stack_cpu_s"] == {"web": 1.8}
    assert (row["concurrent_700_anchored"], row["concurrent_700_sent"]) == (2100, 2100)
    assert row["concurrent_700_bursts"] == 3


def test_an_even_count_takes_the_lower_middle_burst(bursts_of):
    bursts_of([_burst(2.0), _burst(1.0), _burst(3.0), _burst(1.5)])

    assert roots._bursts(_Run(), 4)["concurrent_700_total_s"] == 1.5


def test_a_burst_that_did_not_finish_leaves_no_figure_and_counts_its_unanchored(bursts_of):
    bursts_of([_burst(1.5), _burst(None, anchored=650), _burst(1.7)])

    row = roots._bursts(_Run(), 3)

    assert row["concurrent_700_total_s"] is None
    assert row["concurrent_700_total_s_runs"] == [1.5, None, 1.7]
    assert (row["concurrent_700_anchored"], row["concurrent_700_sent"]) == (2050, 2100)
    assert roots._goals_met(row)["concurrent_all_anchored"] is False


def test_the_web_floor_is_the_single_uploads_cpu_spread_over_the_cores(monkeypatch):
    monkeypatch.setattr(roots.os, "cpu_count", lambda: 2)

    assert roots._web_floor({"single_upload_web_cpu_ms": 5.0}, 700) == pytest.approx(1.75)
    assert roots._web_floor({}, 700) is None


def test_profiles_name_paths_from_the_repository_and_the_virtual_environment(monkeypatch):
    """A run from a worktree uses a virtual environment outside it: both are shortened."""
    repository = str(roots.Path(roots.__file__).resolve().parents[1])
    monkeypatch.setattr(roots.sys, "prefix", "/elsewhere/.venv")
    monkeypatch.setattr(roots.sys, "base_prefix", "/usr")
    profile = (
        "   12 function calls in 0.002 seconds\n\n"
        "   ncalls  tottime  percall  cumtime  percall filename:lineno(function)\n"
        f"        1    0.000    0.000    0.001    0.001 {repository}/sharing/services.py:1(f)\n"
        "        1    0.000    0.000    0.001    0.001 /elsewhere/.venv/lib/django/a.py:2(g)\n"
        "        1    0.000    0.000    0.001    0.001 /usr/lib/python3.11/json/b.py:3(h)\n"
    )

    lines = roots._trimmed(profile).splitlines()

    assert lines[0].lstrip().startswith("ncalls")
    assert lines[1].endswith(" sharing/services.py:1(f)")
    assert lines[2].endswith(" .venv/lib/django/a.py:2(g)")
    assert lines[3].endswith(" /usr/lib/python3.11/json/b.py:3(h)")

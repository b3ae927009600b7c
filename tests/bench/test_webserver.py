"""The web server comparison's pure parts: runs of two checkouts joined into one report, and
the report's section. The bursts themselves start stacks and measure time: never here."""

import json

import bench.__main__ as bench_entry
from bench import report, webserver


def _run(tmp_path, name: str, command: str, anchored: float, cpu: float) -> str:
    run = {
        "date": "2031-01-01T00:00:00Z",
        "machine": {"cpu_model": "test CPU", "logical_cores": 2},
        "load_average_at_start": [1.0, 1.0, 1.0],
        "settings": {"web_command": command},
        "results": [
            {
                "burst": 1,
                "sent": 700,
                "http_201": 700,
                "first_answer_s": 0.2,
                "total_response_s": anchored - 0.5,
                "total_to_anchored_s": anchored,
                "web_cpu_s": cpu,
            }
        ],
    }
    path = tmp_path / f"{name}.json"
    path.write_text(json.dumps(run))
    return str(path)


def test_runs_of_two_servers_are_joined_in_their_order_and_shown_with_ratios(tmp_path):
    items = [
        f"granian={_run(tmp_path, 'a1', 'granian x', 4.0, 3.0)}",
        f"gunicorn={_run(tmp_path, 'b1', 'gunicorn y', 3.0, 3.3)}",
        f"granian={_run(tmp_path, 'a2', 'granian x', 6.0, 3.0)}",
        f"gunicorn={_run(tmp_path, 'b2', 'gunicorn y', 5.0, 3.3)}",
    ]
    assert webserver.combine(items, tmp_path / "results") == 0
    joined = json.loads((tmp_path / "results" / "webserver.json").read_text())
    assert [(r["order"], r["server"]) for r in joined["results"]] == [
        (1, "granian"),
        (2, "gunicorn"),
        (3, "granian"),
        (4, "gunicorn"),
    ]
    assert joined["summary"]["granian"]["median_total_to_anchored_s"] == 5.0
    assert joined["summary"]["gunicorn"]["median_total_to_anchored_s"] == 4.0
    assert joined["settings"]["web_commands"] == {"granian": "granian x", "gunicorn": "gunicorn y"}
    section = report._section_webserver(tmp_path / "results")
    assert "## Web server: gunicorn against granian" in section
    assert "| gunicorn | 2 | 0 | 4.00 | 0.80x |" in section
    assert "- gunicorn: `gunicorn y`" in section


def test_it_runs_only_when_named():
    assert "webserver" in bench_entry.ON_DEMAND

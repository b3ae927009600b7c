"""The sustained and concurrency benchmarks on PostgreSQL + SeaweedFS beside SQLite + disk:
the option, what a run's stack is given, the same-run ratios, the report; and, against a real
PostgreSQL server and a real SeaweedFS, that a postgres-s3 run's database and S3 server exist
while it runs and are gone after it, also when starting failed.

No benchmark runs here: the measurement is replaced by made-up rows.
"""

import csv
import json
import os

import psycopg
import pytest

from bench import __main__ as bench_main_module
from bench import common, concurrency, report, rest, stack, sustained
from bench.stack import BenchStack, StackOptions
from stack.seaweedfs import SeaweedError

# The engines are compared on real processes (anvil, PostgreSQL, SeaweedFS).
pytestmark = pytest.mark.process


def _options(engines: str = "sqlite-disk") -> StackOptions:
    return StackOptions(
        block_time=None,
        batch_max=1,
        workers=1,
        max_wait=0.2,
        redis_url="redis://127.0.0.1:6379/11",
        engines=engines,
    )


# --- what a run's stack is given ----------------------------------------------------------------


def test_a_stack_holds_its_redis_database_until_it_stops(tmp_path):
    """A second benchmark on the same Redis database is refused while a stack holds it (its
    start would flush the first one's queues), another database is not, and stop() lets go."""
    url = f"redis://127.0.0.1:6379/11?claim-test={os.getpid()}"
    first = BenchStack(_options(), tmp_path)
    first.redis_claim = stack.redis_database_claim(url)
    try:
        with pytest.raises(RuntimeError, match="another benchmark's stack is using this Redis"):
            stack.redis_database_claim(url)
        stack.redis_database_claim(f"{url}-other").close()
    finally:
        first.stop()
    assert first.redis_claim is None
    stack.redis_database_claim(url).close()


def test_sqlite_disk_is_the_default_and_keeps_everything_in_the_work_folder(tmp_path):
    bench_stack = BenchStack(_options(), tmp_path)

    settings = bench_stack.settings()
    assert StackOptions(None, 1, 1, 0.2, "redis://x/11").engines == "sqlite-disk"
    assert settings["DATABASE_URL"] == f"sqlite:///{tmp_path / 'var' / 'db.sqlite3'}"
    assert settings["ENVELOPE_STORAGE_URL"] == ""  # the local disk, whatever the shell says
    assert bench_stack.database_name == ""


def test_postgres_s3_gives_the_run_a_database_of_its_own_on_the_bench_server(tmp_path, monkeypatch):
    monkeypatch.setenv("BENCH_PG_URL", "postgres://bench:pw@db.example:6543/postgres?sslmode=off")

    first = BenchStack(_options("postgres-s3"), tmp_path / "a")
    second = BenchStack(_options("postgres-s3"), tmp_path / "b")

    assert first.database_name.startswith(f"authros_bench_{os.getpid()}_")
    assert first.database_name != second.database_name
    assert first.settings()["DATABASE_URL"] == (
        f"postgres://bench:pw@db.example:6543/{first.database_name}?sslmode=off"
    )
    # The bucket's settings exist only once SeaweedFS runs (start()).
    assert first.settings()["ENVELOPE_STORAGE_URL"] == ""
    first.storage_environment = {"ENVELOPE_STORAGE_URL": "s3://authros-bench/envelopes"}
    assert first.settings()["ENVELOPE_STORAGE_URL"] == "s3://authros-bench/envelopes"


def test_postgres_s3_without_a_server_is_refused_before_any_run(monkeypatch, capsys):
    monkeypatch.setenv("BENCH_PG_URL", "postgres://postgres@127.0.0.1:1/postgres")

    with pytest.raises(SystemExit) as exit_info:
        concurrency.main(["--engines", "postgres-s3", "--redis-url", "redis://127.0.0.1:6379/11"])

    assert exit_info.value.code == 2
    assert "needs a PostgreSQL server at BENCH_PG_URL" in capsys.readouterr().err


def test_unknown_engines_and_foreign_database_names_are_refused(tmp_path):
    with pytest.raises(ValueError, match="engines must be one of"):
        BenchStack(_options("mysql-nfs"), tmp_path)
    with pytest.raises(ValueError, match="not a database name of ours"):
        stack.database_drop("postgres://postgres@127.0.0.1/postgres", 'x"; DROP TABLE y; --')


def test_the_runs_of_both_benchmarks_carry_their_engines_to_the_stack():
    parser = rest.argparse.ArgumentParser()
    rest.add_engines_argument(parser)
    rest.add_arguments(parser)
    args = parser.parse_args(["--engines", "postgres-s3", "sqlite-disk", "postgres-s3"])
    assert rest.engines_chosen(args) == ("sqlite-disk", "postgres-s3")
    assert rest.engines_chosen(parser.parse_args([])) == ("sqlite-disk", "postgres-s3")
    with pytest.raises(SystemExit):
        parser.parse_args(["--engines", "mysql"])

    run = rest.upload_run(
        args, block_time=None, batch_max=1, agents=3, plaintext_bytes=1024, engines="postgres-s3"
    )
    assert run.stack_options().engines == "postgres-s3"
    assert run.describe().startswith("PostgreSQL + SeaweedFS (S3): automine")
    assert (
        rest.upload_run(args, block_time=None, batch_max=1, agents=3, plaintext_bytes=1024)
        .describe()
        .startswith("automine")
    )


# --- the option, the rows, the ratios, the files ------------------------------------------------


def _fake_measure(run) -> dict:
    """A made-up row of a run: PostgreSQL + S3 twice as slow, batching five times faster."""
    slower = 2.0 if run.engines == "postgres-s3" else 1.0
    faster = 5.0 if run.batch_max > 1 else 1.0
    row = {"engines": run.engines, "mode": run.mode, "batch_max": run.batch_max}
    if isinstance(run, sustained.SustainedRun):
        sample = {g: {"cpu_pct": 50.0, "rss_mib": 100.0} for g in sustained.GROUPS}
        resources = [{"t": 1.0} | sample]
        return row | {
            "agents": run.agents,
            "offered_per_s": 20.0,
            "accepted_per_s": 20.0,
            "anchored_per_s": 10.0 * faster / slower,
            "to_anchored_p50_s": 1.0 * slower / faster,
            "to_anchored_p99_s": 2.0 * slower / faster,
            "to_verified_p50_s": 1.5 * slower / faster,
            "response_p95_s": 0.1 * slower,
            "web_cpu_mean_pct": 40.0 * slower,
            "workers_cpu_mean_pct": 60.0,
            "failed_records": 0,
            "views": 10,
            "verified_views": 10,
            "timeline": {"accepted_per_s": [20], "anchored_per_s": [10], "resources": resources},
        }
    return row | {
        "agents": run.agents,
        "plaintext_bytes": run.plaintext_bytes,
        "success_rate": 1.0,
        "sent": run.agents,
        "http_201": run.agents,
        "transactions": run.agents // int(faster),
        "total_response_s": 2.0 * slower,
        "total_to_anchored_s": 4.0 * slower / faster,
        "total_to_verified_s": 5.0 * slower / faster,
        "to_anchored_p50_s": 1.0,
    }


@pytest.fixture
def fake_runs(monkeypatch):
    """The benchmarks' loops with made-up rows instead of stacks; the runs they asked for."""
    asked: list = []

    def run_configurations(runs, measure):
        asked.extend(runs)
        return [_fake_measure(run) for run in runs]

    for module in (concurrency, sustained):
        monkeypatch.setattr(module, "run_configurations", run_configurations)
        monkeypatch.setattr(
            module,
            "engines_settings",
            lambda parser, engines: {"engines": list(engines), "postgres": "PostgreSQL 99.1"},
        )
    return asked


def test_concurrency_runs_every_configuration_on_both_engines_with_same_run_ratios(
    tmp_path, fake_runs, capsys
):
    argv = ["--agents", "30", "--block-times", "0", "--redis-url", "redis://127.0.0.1:6379/11"]

    assert concurrency.main([*argv, "--results-dir", str(tmp_path)]) == 0

    assert [(r.engines, r.batch_max) for r in fake_runs] == [
        ("sqlite-disk", 1),
        ("sqlite-disk", 100),
        ("postgres-s3", 1),
        ("postgres-s3", 100),
    ]
    data = json.loads((tmp_path / "concurrency.json").read_text())
    assert data["settings"]["engines"] == ["sqlite-disk", "postgres-s3"]
    by_key = {(r["engines"], r["batch_max"]): r for r in data["results"]}
    postgres_batched = by_key[("postgres-s3", 100)]
    assert postgres_batched["total_to_verified_s_ratio_vs_sqlite"] == 2.0
    assert postgres_batched["total_response_s_ratio_vs_sqlite"] == 2.0
    # batching compares with batch 1 on the same engines
    assert postgres_batched["total_to_anchored_s_ratio_vs_batch1"] == pytest.approx(0.2)
    assert by_key[("sqlite-disk", 1)]["total_response_s_ratio_vs_sqlite"] == 1.0
    with (tmp_path / "concurrency.csv").open() as handle:
        rows = list(csv.DictReader(handle))
    assert rows[3]["engines"] == "postgres-s3"
    assert float(rows[3]["total_to_verified_s_ratio_vs_sqlite"]) == 2.0
    assert (tmp_path / "concurrency.png").stat().st_size > 0
    table = capsys.readouterr().out
    assert "verif x sqlite" in table
    assert "postgres-s3" in table
    assert any("x sqlite columns divide postgres-s3" in note for note in data["notes"])


def test_sustained_on_postgres_alone_has_no_baseline_to_divide_by(tmp_path, fake_runs):
    argv = ["--quick", "--block-times", "0", "--engines", "postgres-s3"]
    argv += ["--redis-url", "redis://127.0.0.1:6379/11"]

    assert sustained.main([*argv, "--results-dir", str(tmp_path)]) == 0

    assert {r.engines for r in fake_runs} == {"postgres-s3"}
    rows = json.loads((tmp_path / "sustained.json").read_text())["results"]
    assert [r["anchored_per_s_ratio_vs_sqlite"] for r in rows] == [None, None]
    assert rows[1]["anchored_per_s_ratio_vs_batch1"] == 5.0


def test_engine_ratios_divide_by_sqlite_disk_of_the_same_configuration():
    rows = [
        {"engines": "sqlite-disk", "mode": "automine", "batch_max": 1, "anchored_per_s": 10.0},
        {"engines": "sqlite-disk", "mode": "automine", "batch_max": 100, "anchored_per_s": 40.0},
        {"engines": "postgres-s3", "mode": "automine", "batch_max": 100, "anchored_per_s": 30.0},
        {"engines": "postgres-s3", "mode": "block-time 1s", "batch_max": 1, "anchored_per_s": 5.0},
    ]
    common.add_engine_ratios(rows, ("mode", "batch_max"), ("anchored_per_s",))
    assert [r["anchored_per_s_ratio_vs_sqlite"] for r in rows] == [1.0, 1.0, 0.75, None]


# --- the report ------------------------------------------------------------------------------


def _report_file(results, name: str, rows: list[dict], **settings) -> None:
    results.mkdir(exist_ok=True)
    data = {
        "benchmark": name,
        "date": "2031-05-06T07:08:09Z",
        "machine": {"cpu_model": "Test CPU", "logical_cores": 3, "memory_bytes": 5 * 2**30},
        "settings": {"agents": "10 robots", "duration_s": 15.0, "quick": False} | settings,
        "notes": [],
        "results": rows,
    }
    (results / f"{name}.json").write_text(json.dumps(data))


def test_the_report_sets_postgres_s3_beside_sqlite_disk_with_the_same_run_ratios(tmp_path):
    results = tmp_path / "results"
    runs = [
        sustained.SustainedRun(
            None, batch, 10, 2.0, 1.0, 15.0, 3.0, 60.0, 5, 5, 2, 0, 4, 0.2, "", False, engines
        )
        for engines in ("sqlite-disk", "postgres-s3")
        for batch in (1, 100)
    ]
    rows = [_fake_measure(run) for run in runs]
    sustained.rows_ratios(rows)
    engines = {"engines": ["sqlite-disk", "postgres-s3"], "postgres": "PostgreSQL 99.1"}
    _report_file(results, "sustained", rows, seaweedfs="SeaweedFS 4.48", **engines)
    upload_runs = [
        rest.UploadRun(None, batch, 30, 1024, 5, 2, 0, 4, 0.2, 900.0, "", False, engines=e)
        for e in ("sqlite-disk", "postgres-s3")
        for batch in (1, 100)
    ]
    rows = [_fake_measure(run) for run in upload_runs]
    concurrency.rows_ratios(rows)
    _report_file(results, "concurrency", rows, **engines)
    output = tmp_path / "REPORT.md"

    assert report.main(["--results-dir", str(results), "--output", str(output)]) == 0

    text = output.read_text()
    concurrency_part = text.split("## Whole pipeline")[0].split("## Concurrency")[1]
    sustained_part = text.split("## Whole pipeline")[1]
    for part in (concurrency_part, sustained_part):
        assert "| engines | block mode | batch max |" in part
        assert "Test CPU; 3 logical cores" in part
        assert "one after the other in this same run on this machine" in part
        assert "PostgreSQL 99.1" in part
        table = [line for line in part.splitlines() if line.startswith(("| SQLite", "| Postg"))]
        assert [line.split(" | ")[0] for line in table] == [
            "| SQLite + disk",
            "| PostgreSQL + S3",
            "| SQLite + disk",
            "| PostgreSQL + S3",
        ]  # each configuration's engines next to each other
    assert "verified x SQLite + disk" in concurrency_part
    assert "| 2.00x |" in concurrency_part
    assert "anchored rec/s x SQLite + disk" in sustained_part
    assert "| 0.50x |" in sustained_part
    assert "sustained anchored records/s 0.50x (higher is better)" in sustained_part
    assert "SeaweedFS 4.48" in sustained_part


def test_results_from_before_the_engines_show_no_engines_column(tmp_path):
    results = tmp_path / "results"
    row = {"mode": "automine", "batch_max": 1, "agents": 30, "success_rate": 1.0}
    _report_file(results, "concurrency", [row | {"http_201": 30, "sent": 30, "transactions": 30}])
    output = tmp_path / "REPORT.md"

    assert report.main(["--results-dir", str(results), "--output", str(output)]) == 0

    text = output.read_text()
    assert "| block mode | batch max |" in text
    assert "engines |" not in text
    assert "x SQLite + disk" not in text


# --- real PostgreSQL and SeaweedFS ------------------------------------------------------------


def _server_url() -> str:
    """BENCH_PG_URL, else the server of the suite's PostgreSQL pass, else the default."""
    if os.environ.get("BENCH_PG_URL"):
        return os.environ["BENCH_PG_URL"]
    suite = os.environ.get("DATABASE_URL", "")
    if suite.startswith(("postgres://", "postgresql://")):
        return stack.database_url_for(suite, "postgres")
    return stack.BENCH_PG_URL


def _databases(server_url: str) -> set[str]:
    with psycopg.connect(server_url, connect_timeout=5) as connection:
        return {name for (name,) in connection.execute("SELECT datname FROM pg_database")}


@pytest.fixture
def pg_server(monkeypatch) -> str:
    url = _server_url()
    try:
        _databases(url)
    except psycopg.Error as exc:
        pytest.skip(f"no PostgreSQL server at {url}: {exc}")
    monkeypatch.setenv("BENCH_PG_URL", url)
    return url


def test_a_postgres_s3_run_has_its_database_and_s3_while_it_runs_and_neither_after(
    tmp_path, pg_server
):
    bench_stack = BenchStack(_options("postgres-s3"), tmp_path)
    try:
        bench_stack._engines_start()
        assert bench_stack.database_name in _databases(pg_server)
        settings = bench_stack.settings()
        assert settings["ENVELOPE_STORAGE_URL"] == "s3://authros-bench/envelopes"
        client = bench_stack.seaweed.client()
        client.put_object(Bucket="authros-bench", Key="envelopes/x.env", Body=b"sealed")
        assert client.get_object(Bucket="authros-bench", Key="envelopes/x.env")["Body"].read()
        # A session still open in the run's database (a stuck worker's) does not stop the drop.
        connection = psycopg.connect(settings["DATABASE_URL"], autocommit=True)
        connection.execute("CREATE TABLE t (x int)")
        weed = bench_stack.seaweed.process
        bench_stack.stop()
        connection.close()
    finally:
        bench_stack.stop()
    assert weed.poll() is not None
    assert bench_stack.database_name not in _databases(pg_server)


def test_a_run_whose_s3_server_did_not_start_still_drops_its_database(
    tmp_path, pg_server, monkeypatch
):
    def refuse(folder):
        raise SeaweedError("no weed here")

    monkeypatch.setattr(stack, "start_seaweedfs", refuse)
    bench_stack = BenchStack(_options("postgres-s3"), tmp_path)
    try:
        with pytest.raises(SeaweedError):
            bench_stack._engines_start()
        assert bench_stack.database_name in _databases(pg_server)
    finally:
        bench_stack.stop()
    assert bench_stack.database_name not in _databases(pg_server)


def test_a_benchmark_refusing_its_arguments_does_not_stop_the_others(monkeypatch):
    ran = []

    def run(name, args):
        ran.append(name)
        if name == "concurrency":
            raise SystemExit(2)  # as --engines postgres-s3 without a server does
        return 0

    monkeypatch.setattr(bench_main_module.importlib, "import_module", _modules(run))

    assert bench_main_module.main([]) == 1

    assert "sustained" in ran
    assert ran[-1] == "report"


def _modules(run):
    """import_module giving each benchmark a main that calls run(name, args)."""

    class Module:
        def __init__(self, name):
            self.name = name

        def main(self, args):
            return run(self.name, args)

    return lambda dotted: Module(dotted.removeprefix("bench."))

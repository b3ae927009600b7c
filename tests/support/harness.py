"""Real Celery worker and beat processes, sharing the test's database, Redis and anvil,
and the portal itself (gunicorn) for clients that talk to it over HTTP.

The tests that use this are about the queue, so nothing runs eagerly: the test process only
writes rows and queues messages, exactly like the web processes do in production. The
processes are started by the stack package (stack/processes.py), as `make run` starts them;
this module only points them at the test's database, settings and a queue of its own.
"""

from __future__ import annotations

import os
import uuid
from collections.abc import Callable
from pathlib import Path

import psutil
import redis
import requests
from django.conf import settings
from django.db import connection

from portal.celery import app as celery_app
from stack.anvil import AnvilProcess, free_port, start_anvil
from stack.processes import (
    REPO_ROOT,
    WEB_MAX_REQUESTS,
    Children,
    StackError,
    WebSizing,
    celery_beat,
    celery_worker,
    web_server,
)
from stack.processes import wait_until as _wait_until

__all__ = ["REPO_ROOT", "WorkerStack", "database_url", "wait_for"]

WEB_THREADS = 4


def database_url() -> str:
    """The URL of the database the test is using (the test database, not the dev one)."""
    conf = connection.settings_dict
    if conf["ENGINE"].endswith("sqlite3"):
        return f"sqlite:///{conf['NAME']}"
    password = f":{conf['PASSWORD']}" if conf.get("PASSWORD") else ""
    port = f":{conf['PORT']}" if conf.get("PORT") else ""
    return f"postgres://{conf['USER']}{password}@{conf['HOST'] or '127.0.0.1'}{port}/{conf['NAME']}"


def wait_for(
    predicate: Callable[[], bool], *, timeout: float, what: str, interval: float = 0.25
) -> None:
    """Poll predicate until it holds; AssertionError after timeout seconds."""
    try:
        _wait_until(predicate, timeout=timeout, what=what, interval=interval)
    except StackError as exc:
        raise AssertionError(str(exc)) from None


class WorkerStack:
    """anvil + N Celery workers (+ beat, + the portal under gunicorn), configured like the
    test process."""

    def __init__(
        self,
        tmp_path: Path,
        *,
        block_time: float | None = None,
        env_overrides: dict[str, str] | None = None,
    ) -> None:
        self.tmp_path = tmp_path
        self.env_overrides = env_overrides or {}
        self.state_path = tmp_path / "anvil-state.json"
        self.block_time = block_time
        self.anvil: AnvilProcess = start_anvil(block_time=block_time, state_path=self.state_path)
        self.port = self.anvil.port
        self.redis_url = settings.REDIS_URL
        self.web_port: int | None = None
        self._web_ports: dict[str, int] = {}  # of portals started under other names
        # A queue of its own: test runs sharing this Redis must not take each other's tasks.
        self.queue = f"authros-test-{uuid.uuid4().hex[:12]}"
        self._queue_before: str | None = None
        self.logs = tmp_path / "logs"
        self.logs.mkdir(exist_ok=True)
        self.children = Children(self.logs)

    def configure_test_process(self, django_settings) -> None:
        """Point the test process at this stack's chain, with the stack's short timings."""
        django_settings.CHAIN_RPC_URL = self.anvil.url
        django_settings.ANCHOR_STALE_AFTER = 5
        django_settings.ANCHOR_MAX_WAIT = 0.5
        self._queue_before = celery_app.conf.task_default_queue
        celery_app.conf.task_default_queue = self.queue

    def start(self, django_settings, *, workers: int) -> WorkerStack:
        """Point the test process at this stack, clear what an earlier run left in Redis under
        its names, deploy the contract and start `workers` workers (w0, w1, ...) and beat."""
        from chainworker import services as chain_services

        self.configure_test_process(django_settings)
        self.redis_flush_own()
        chain_services._clients.clear()
        chain_services.contract_deploy()
        for index in range(workers):
            self.start_worker(f"w{index}")
        self.start_beat()
        return self

    def env(self) -> dict[str, str]:
        return {
            **os.environ,
            "DJANGO_SETTINGS_MODULE": "portal.settings",
            "DATABASE_URL": database_url(),
            "REDIS_URL": self.redis_url,
            "REDIS_KEY_PREFIX": settings.REDIS_KEY_PREFIX,
            "CELERY_QUEUE": self.queue,
            "CHAIN_RPC_URL": self.anvil.url,
            "CHAIN_RECEIPT_TIMEOUT": "60",
            "AUTHROS_VAR_DIR": str(self.tmp_path / "var"),
            "AUTHROS_SECRETS_DIR": str(settings.SECRETS_DIR),
            "AUTHROS_MEDIA_ROOT": str(settings.MEDIA_ROOT),
            "ANCHOR_MAX_WAIT": "0.5",
            "ANCHOR_STALE_AFTER": "5",
            "ANCHOR_SWEEP_INTERVAL": "2",
            "ANCHOR_LOCK_TTL": "6",
            "CHAIN_NONCE_LOCK_TIMEOUT": "5",
            "LOG_LEVEL": "INFO",
            "PYTHONUNBUFFERED": "1",
            **self.env_overrides,
        }

    # processes -------------------------------------------------------------------------

    def host_env(self, name: str, **extra: str) -> dict[str, str]:
        """The environment of a process on a "host" of its own: its own working folders
        (var, secrets, media under hosts/NAME), everything else as env() and `extra`."""
        folder = self.tmp_path / "hosts" / name
        for part in ("var", "secrets", "media"):
            (folder / part).mkdir(mode=0o700, parents=True, exist_ok=True)
        return {
            **self.env(),
            "AUTHROS_VAR_DIR": str(folder / "var"),
            "AUTHROS_SECRETS_DIR": str(folder / "secrets"),
            "AUTHROS_MEDIA_ROOT": str(folder / "media"),
            **extra,
        }

    def start_worker(
        self, name: str, *, queues: list[str] | None = None, env: dict[str, str] | None = None
    ) -> None:
        """A worker with one pool process; on both of the stack's queues unless told."""
        self.children.spawn(name, celery_worker(name, queues=queues or ()), env=env or self.env())

    def start_beat(self, *, env: dict[str, str] | None = None) -> None:
        self.children.spawn(
            "beat", celery_beat(self.tmp_path / "celerybeat-schedule"), env=env or self.env()
        )

    def start_web(
        self,
        *,
        workers: int = 2,
        timeout: float = 60,
        name: str = "web",
        env: dict[str, str] | None = None,
        max_requests: int = WEB_MAX_REQUESTS,
        max_requests_jitter: int = 0,
        host: str = "127.0.0.1",
    ) -> str:
        """The portal under gunicorn on 127.0.0.1 (the same port again after a stop_web);
        returns its URL once it answers and all its worker processes run. Another `name` is
        another portal, on its own port. `host` 0.0.0.0 listens on every address too, as
        `PORTAL_HOST=0.0.0.0 make run` does (the URL returned stays loopback's)."""
        if name == "web":
            self.web_port = self.web_port or free_port()
        port = self.web_port if name == "web" else self._web_ports.setdefault(name, free_port())
        command = web_server(
            host,
            port,
            WebSizing(workers, WEB_THREADS),
            max_requests=max_requests,
            max_requests_jitter=max_requests_jitter,
        )
        self.children.spawn(name, command, env=env or self.env(), stop_timeout=15)
        url = f"http://127.0.0.1:{port}"
        wait_for(
            lambda: self._web_answers(name, url),
            timeout=timeout,
            what=f"the portal {name} (gunicorn) to answer",
        )
        wait_for(
            lambda: len(self.web_processes(name)) == workers,
            timeout=timeout,
            what=f"all {workers} worker processes of the portal {name}",
        )
        return url

    def web_processes(self, name: str = "web") -> set[int]:
        """The pids of the web server's worker processes (the children of its master)."""
        return {child.pid for child in psutil.Process(self.children[name].pid).children()}

    @property
    def web_url(self) -> str:
        return f"http://127.0.0.1:{self.web_port}"

    def _web_answers(self, name: str, url: str) -> bool:
        if not self.children[name].running():
            raise AssertionError(f"the portal {name} exited:\n{self.worker_logs()[-3000:]}")
        try:
            # Any JSON answer from Django will do; this path is not rate limited.
            return requests.get(f"{url}/api/", timeout=2).status_code == 404
        except requests.RequestException:
            return False

    def stop_web(self) -> None:
        """Stop the portal (its port refuses connections until start_web)."""
        self.children.stop("web")

    def kill_worker(self, name: str) -> None:
        """kill -9 the worker and its pool processes, as a crash or an OOM kill would."""
        self.children.kill(name)

    def stop_anvil(self) -> None:
        self.anvil.stop()

    def restart_anvil(self) -> None:
        self.anvil = start_anvil(
            block_time=self.block_time, state_path=self.state_path, port=self.port
        )

    def kill_anvil(self) -> None:
        """kill -9 the node: it writes no state, so what it mined since its last dump is lost."""
        self.anvil.process.kill()
        self.anvil.process.wait(timeout=10)
        self.anvil.output.close()

    def reset_anvil(self) -> None:
        """Kill the node and start a new one on the same port with no state at all (a dev
        chain reset: an empty chain where the old one was)."""
        self.kill_anvil()
        self.state_path.unlink(missing_ok=True)
        self.restart_anvil()

    def anvil_rpc(self, method: str, *params: object) -> object:
        """A JSON-RPC call to the node (anvil_*, evm_* test methods); its result."""
        body = {"jsonrpc": "2.0", "id": 1, "method": method, "params": list(params)}
        answer = requests.post(self.anvil.url, json=body, timeout=30).json()
        if "error" in answer:
            raise AssertionError(f"{method}: {answer['error']}")
        return answer["result"]

    def redis_flush_own(self) -> int:
        """Flush what this test holds in the shared test Redis (its key prefix, its Celery
        queues), as a FLUSHDB would, leaving other tests' keys alone; how many keys went."""
        client = redis.Redis.from_url(self.redis_url)
        names = [
            *client.scan_iter(f"{settings.REDIS_KEY_PREFIX}:*"),
            *client.scan_iter(f"{self.queue}*"),
            *client.scan_iter(f"_kombu.binding.{self.queue}*"),
        ]
        return client.delete(*names) if names else 0

    def worker_logs(self) -> str:
        return "\n".join(path.read_text(errors="replace") for path in self.logs.glob("*.log"))

    def stop(self) -> None:
        self.children.stop_all(order=["web"])
        self.anvil.stop()
        if self._queue_before is not None:
            celery_app.conf.task_default_queue = self._queue_before

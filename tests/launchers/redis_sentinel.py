"""A throwaway Redis master, its replica and Sentinels that watch them, on free loopback ports,
from Debian's redis-server, for the tests that show the portal works through Sentinel URLs
and follows a failover:

    with start_redis_sentinels(folder) as sentinels:
        sentinels.url(db=0)          # sentinel://127.0.0.1:P1,...,127.0.0.1:P3/0?master=authros
        sentinels.kill_master()      # kill -9, as a crash would
        sentinels.await_failover()   # the Sentinels promoted the replica

The Sentinels decide quickly (down after half a second), so a failover takes a few seconds.
"""

from __future__ import annotations

import shutil
import signal
import subprocess
from dataclasses import dataclass, field
from pathlib import Path

import redis

from stack.anvil import HOST, free_port
from stack.processes import StackError, StopsOnExit, process_stop, wait_until

MASTER_NAME = "authros"
SENTINELS = 3
DOWN_AFTER_MS = 500
FAILOVER_TIMEOUT_MS = 3000
STARTUP_TIMEOUT = 30.0
FAILOVER_WAIT = 60.0
STOP_TIMEOUT = 10.0


@dataclass
class RedisSentinels(StopsOnExit):
    folder: Path
    data_ports: list[int]  # the master's (first, when started) and the replica's
    sentinel_ports: list[int]
    master_name: str = MASTER_NAME
    processes: dict[int, subprocess.Popen[bytes]] = field(default_factory=dict)  # by port

    def url(self, db: int = 0) -> str:
        """The portal's URL for this Redis (core/redis_url.py)."""
        hosts = ",".join(f"{HOST}:{port}" for port in self.sentinel_ports)
        return f"sentinel://{hosts}/{db}?master={self.master_name}"

    def master_port(self) -> int:
        """The port of the master the first Sentinel names now."""
        return self._ask_master(self.sentinel_ports[0])

    def kill_master(self) -> int:
        """kill -9 the master as a crash would; its port."""
        port = self.master_port()
        process = self.processes[port]
        process.send_signal(signal.SIGKILL)
        process.wait(timeout=STOP_TIMEOUT)
        return port

    def await_failover(self, old_port: int) -> int:
        """Wait until every Sentinel names another master than old_port and it serves as one;
        its port."""

        def promoted() -> bool:
            ports = {self._ask_master(port) for port in self.sentinel_ports}
            if len(ports) != 1 or old_port in ports:
                return False
            role = redis.Redis(host=HOST, port=ports.pop(), socket_timeout=2).role()
            return role[0] in (b"master", "master")

        _wait(promoted, timeout=FAILOVER_WAIT, what="the Sentinels to promote the replica")
        return self.master_port()

    def stop(self) -> None:
        for process in self.processes.values():
            process_stop(process, timeout=STOP_TIMEOUT)

    def _ask_master(self, sentinel_port: int) -> int:
        client = redis.Redis(host=HOST, port=sentinel_port, socket_timeout=2, decode_responses=True)
        try:
            return int(client.sentinel_get_master_addr_by_name(self.master_name)[1])
        finally:
            client.close()

    def _start(self, port: int, argv: list[str]) -> None:
        log = (self.folder / f"{port}.log").open("ab")
        with log:
            self.processes[port] = subprocess.Popen(
                argv, stdout=log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL
            )


def start_redis_sentinels(folder: Path, *, sentinels: int = SENTINELS) -> RedisSentinels:
    """A master, one replica of it, and `sentinels` Sentinels (a majority of them must agree
    on a failover) that know both and each other."""
    server = shutil.which("redis-server")
    if server is None:
        raise StackError("redis-server is not installed (apt-get install redis-server)")
    folder.mkdir(parents=True, exist_ok=True)
    stack = RedisSentinels(
        folder, [free_port(), free_port()], [free_port() for _ in range(sentinels)]
    )
    master, replica = stack.data_ports
    try:
        for port in stack.data_ports:
            node = folder / str(port)
            node.mkdir(exist_ok=True)
            replica_of = ["--replicaof", HOST, str(master)] if port == replica else []
            stack._start(
                port,
                [
                    server,
                    "--port", str(port),
                    "--bind", HOST,
                    "--dir", str(node),
                    "--save", "",
                    "--appendonly", "no",
                    "--repl-diskless-sync-delay", "0",
                    *replica_of,
                ],
            )  # fmt: skip
        # Started after the replica is in sync, the Sentinels learn of it from the master's
        # first INFO (they ask every ten seconds).
        _wait(
            lambda: (
                redis.Redis(host=HOST, port=replica).info("replication")["master_link_status"]
                == "up"
            ),
            timeout=STARTUP_TIMEOUT,
            what="the replica to sync",
        )
        quorum = sentinels // 2 + 1
        for port in stack.sentinel_ports:
            config = folder / f"sentinel-{port}.conf"
            config.write_text(
                f"port {port}\n"
                f"bind {HOST}\n"
                f"dir {folder}\n"
                f"sentinel monitor {MASTER_NAME} {HOST} {master} {quorum}\n"
                f"sentinel down-after-milliseconds {MASTER_NAME} {DOWN_AFTER_MS}\n"
                f"sentinel failover-timeout {MASTER_NAME} {FAILOVER_TIMEOUT_MS}\n"
                f"sentinel parallel-syncs {MASTER_NAME} 1\n"
            )
            stack._start(port, [server, str(config), "--sentinel"])

        def watching() -> bool:
            for port in stack.sentinel_ports:
                state = redis.Redis(host=HOST, port=port, decode_responses=True).sentinel_master(
                    MASTER_NAME
                )
                if state["num-slaves"] != 1 or state["num-other-sentinels"] != sentinels - 1:
                    return False
            return True

        _wait(
            watching,
            timeout=STARTUP_TIMEOUT,
            what="the Sentinels to know the replica and each other",
        )
    except BaseException:
        stack.stop()
        raise
    return stack


def _wait(predicate, *, timeout: float, what: str) -> None:
    def answered() -> bool:
        try:
            return bool(predicate())
        except (redis.RedisError, OSError):
            return False

    wait_until(answered, timeout=timeout, what=what, interval=0.1)

"""A throwaway Redis Cluster of three masters on free loopback ports, from Debian's
redis-server, for the tests that show the portal's Redis scripts are Cluster-safe:

    with start_redis_cluster(folder) as cluster:
        client = cluster.client()  # a redis.RedisCluster
        cluster.url()  # redis+cluster://127.0.0.1:P1,127.0.0.1:P2,127.0.0.1:P3 (REDIS_URL)
"""

from __future__ import annotations

import shutil
import subprocess
import time
from dataclasses import dataclass, field
from pathlib import Path

import redis

from stack.anvil import HOST, free_port
from stack.processes import StopsOnExit, process_stop

MASTERS = 3
STARTUP_TIMEOUT = 30.0
STOP_TIMEOUT = 10.0


class RedisClusterError(RuntimeError):
    """The cluster did not form; the message says where it stopped."""


@dataclass
class RedisCluster(StopsOnExit):
    folder: Path
    ports: list[int]
    processes: list[subprocess.Popen[bytes]] = field(default_factory=list)

    def client(self) -> redis.RedisCluster:
        return redis.RedisCluster(host=HOST, port=self.ports[0])

    def url(self) -> str:
        """The portal's URL for this cluster (core/redis_url.py)."""
        return "redis+cluster://" + ",".join(f"{HOST}:{port}" for port in self.ports)

    def stop(self) -> None:
        for process in self.processes:
            process_stop(process, timeout=STOP_TIMEOUT)


def start_redis_cluster(folder: Path) -> RedisCluster:
    """Three cluster-enabled redis-servers (no persistence), joined, all slots served."""
    server = shutil.which("redis-server")
    if server is None:
        raise RedisClusterError("redis-server is not installed (apt-get install redis-server)")
    cluster = RedisCluster(folder, [free_port() for _ in range(MASTERS)])
    # The cluster bus listens on a port of its own too (port + 10000 unless told): a free one.
    bus_ports = [free_port() for _ in range(MASTERS)]
    try:
        for port, bus_port in zip(cluster.ports, bus_ports, strict=True):
            node = folder / str(port)
            node.mkdir(parents=True, exist_ok=True)
            cluster.processes.append(
                subprocess.Popen(
                    [
                        server,
                        "--port", str(port),
                        "--bind", HOST,
                        "--cluster-enabled", "yes",
                        "--cluster-port", str(bus_port),
                        "--cluster-config-file", str(node / "nodes.conf"),
                        "--dir", str(node),
                        "--save", "",
                        "--appendonly", "no",
                    ],
                    stdout=subprocess.DEVNULL,
                    stderr=subprocess.DEVNULL,
                )
            )  # fmt: skip
        for port in cluster.ports:
            _await(lambda port=port: redis.Redis(host=HOST, port=port).ping(), f"node {port}")
        subprocess.run(
            [
                "redis-cli", "--cluster", "create",
                *(f"{HOST}:{port}" for port in cluster.ports),
                "--cluster-replicas", "0", "--cluster-yes",
            ],
            check=True,
            capture_output=True,
            timeout=STARTUP_TIMEOUT,
        )  # fmt: skip
        _await(lambda: cluster.client().cluster_info()["cluster_state"] == "ok", "cluster ok")
    except BaseException:
        cluster.stop()
        raise
    return cluster


def _await(predicate, what: str) -> None:
    deadline = time.monotonic() + STARTUP_TIMEOUT
    while True:
        try:
            if predicate():
                return
        except redis.RedisError:
            pass
        if time.monotonic() > deadline:
            raise RedisClusterError(f"no {what} after {STARTUP_TIMEOUT:.0f}s")
        time.sleep(0.1)

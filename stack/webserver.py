"""granian, replacing a web process only once its successor listens.

`python -m stack.webserver portal.wsgi:application --interface wsgi ...` takes granian's own
command line. granian replaces a process (its lifetime is up, it holds too much memory, a
reload) by starting the new one, sleeping `--respawn-interval` seconds, then stopping the old
one. Each process opens its own listening socket (SO_REUSEPORT) only once it has loaded the
portal, which takes 2-3 s on an idle 2-core machine and longer on a loaded one: with a fixed
sleep an old process could stop before its successor listened, and with every other process
being replaced too, new connections were refused (a full test run saw it with 10 s). Here the
old one is stopped as soon as the new one listens, and `--respawn-interval` is how long that
may take at most (then it is stopped anyway, as granian does, so that a successor that never
comes up cannot keep a leaking process alive for ever). A process that crashed is replaced at
once, as before.
"""

from __future__ import annotations

import time
from collections.abc import Callable

import granian.cli
import psutil
from granian.log import logger
from granian.server.mp import MPServer, WorkerProcess

READY_POLL_INTERVAL = 0.2


def listening(pid: int, port: int) -> bool:
    """Whether the process `pid` holds a listening TCP socket on `port`."""
    try:
        sockets = psutil.Process(pid).net_connections(kind="tcp")
    except psutil.Error:  # gone, or a zombie: it listens on nothing
        return False
    return any(s.status == psutil.CONN_LISTEN and s.laddr.port == port for s in sockets)


def successor_ready(
    worker: WorkerProcess, port: int, timeout: float, stopping: Callable[[], bool]
) -> bool:
    """Wait until the new worker listens on `port`: True once it does, False if it died, the
    server is stopping (a SIGTERM or Ctrl-C must not wait for it) or `timeout` seconds passed
    first."""
    deadline = time.monotonic() + timeout
    while True:
        if listening(worker._id(), port):
            return True
        if not worker.inner.is_alive() or stopping() or time.monotonic() >= deadline:
            return False
        time.sleep(READY_POLL_INTERVAL)


class ReadyReplacingServer(MPServer):
    """granian's process server whose replacements wait for the successor to listen rather
    than a fixed time (granian 2.8's `_respawn_workers`, with the sleep replaced)."""

    def _respawn_workers(
        self, workers: list[int], spawn_target, target_loader, delay: float = 0
    ) -> None:
        for idx in workers:
            self.respawned_wrks[idx] = time.monotonic()
            logger.info(f"Respawning worker-{idx + 1}")
            old_wrk = self.wrks.pop(idx)
            wrk = self._spawn_worker(idx=idx, target=spawn_target, callback_loader=target_loader)
            wrk.start()
            self.wrks.insert(idx, wrk)
            if delay:  # a graceful replacement; a crashed process has nothing left to serve
                started = time.monotonic()
                if successor_ready(wrk, self.bind_port, delay, self._stopping):
                    waited = time.monotonic() - started
                    logger.info(f"worker-{idx + 1} replacement listens after {waited:.1f}s")
                elif not self._stopping():
                    logger.warning(
                        f"worker-{idx + 1} replacement does not listen after {delay:g}s; "
                        "stopping the old one anyway"
                    )
            logger.info(f"Stopping old worker-{idx + 1}")
            old_wrk.terminate()
            old_wrk.join(self.workers_kill_timeout)
            if self.workers_kill_timeout:
                # the worker might still be reported alive after `join`, let's context switch
                if old_wrk.is_alive():
                    time.sleep(0.001)
                if old_wrk.is_alive():
                    logger.warning(
                        f"Killing old worker-{idx + 1} after it refused to gracefully stop"
                    )
                    old_wrk.kill()
                    old_wrk.join()
            logger.info(f"Stopped old worker-{idx + 1}")
        self._metrics.incr_spawn(len(workers))

    def _stopping(self) -> bool:
        """A SIGTERM or Ctrl-C arrived (granian's handler sets this)."""
        return self.interrupt_signal


def main() -> None:
    # granian's command line builds the server it imported under this name: the multi-process
    # one wherever the interpreter has a GIL (the threaded one otherwise, left as it is).
    if granian.cli.Server is MPServer:
        granian.cli.Server = ReadyReplacingServer
    granian.cli.entrypoint()


if __name__ == "__main__":
    main()

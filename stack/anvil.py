"""Start and stop a real anvil node for integration tests.

    with start_anvil() as node:
        w3 = Web3(Web3.HTTPProvider(node.url))

The binary is the one pinned in package.json (node_modules/@foundry-rs/anvil-<os>-<arch>);
ANVIL_BIN overrides it. Each node listens on a free port of 127.0.0.1, so parallel test
workers (pytest-xdist) do not collide.
"""

from __future__ import annotations

import json
import os
import platform
import shutil
import signal
import socket
import subprocess
import tempfile
import time
import urllib.error
import urllib.request
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import IO, Self

REPO_ROOT = Path(__file__).resolve().parent.parent
HOST = "127.0.0.1"
STARTUP_TIMEOUT = 15.0
STOP_TIMEOUT = 10.0
PORT_ATTEMPTS = 3

_OS_NAMES = {"Linux": "linux", "Darwin": "darwin", "Windows": "win32"}
_ARCH_NAMES = {"x86_64": "amd64", "AMD64": "amd64", "aarch64": "arm64", "arm64": "arm64"}


class AnvilError(RuntimeError):
    """anvil is missing, exited early or did not answer in time."""


def anvil_binary() -> Path:
    """The anvil executable: $ANVIL_BIN, else the npm platform package, else anvil on PATH."""
    if override := os.environ.get("ANVIL_BIN"):
        return Path(override)
    os_name = _OS_NAMES.get(platform.system(), platform.system().lower())
    arch = _ARCH_NAMES.get(platform.machine(), platform.machine())
    exe = "anvil.exe" if os_name == "win32" else "anvil"
    pinned = REPO_ROOT / "node_modules" / "@foundry-rs" / f"anvil-{os_name}-{arch}" / "bin" / exe
    if pinned.exists():
        return pinned
    if on_path := shutil.which("anvil"):
        return Path(on_path)
    raise AnvilError(f"anvil not found at {pinned} nor on PATH: run npm ci")


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        sock.bind((HOST, 0))
        return sock.getsockname()[1]


@dataclass
class AnvilProcess:
    """A running anvil node; stop() it, or use it as a context manager."""

    port: int
    process: subprocess.Popen[bytes]
    stderr: IO[bytes]

    @property
    def url(self) -> str:
        return f"http://{HOST}:{self.port}"

    def stop(self) -> None:
        """Stop the node gracefully (so --state is written), killing it if it hangs."""
        if self.process.poll() is None:
            self.process.send_signal(signal.SIGTERM)
            try:
                self.process.wait(timeout=STOP_TIMEOUT)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait()
        self.stderr.close()

    def __enter__(self) -> Self:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.stop()


def start_anvil(
    block_time: float | None = None, state_path: str | None = None, port: int | None = None
) -> AnvilProcess:
    """Start anvil on a free port and return once its JSON-RPC answers.

    block_time: seconds between blocks (interval mining); None mines one block per transaction.
    state_path: file the chain state is loaded from (if present) and written to on stop().
    port: a fixed port (e.g. to restart a node where its clients expect it); else a free one.
    """
    args = [str(anvil_binary()), "--host", HOST, "--silent"]
    if block_time is not None:
        args += ["--block-time", str(block_time)]
    if state_path is not None:
        args += ["--state", str(state_path)]
    last_error = ""
    # The free port may be taken by someone else before anvil binds it: try a few.
    fixed_port = port
    for _ in range(PORT_ATTEMPTS):
        port = fixed_port or free_port()
        stderr = tempfile.TemporaryFile()  # noqa: SIM115  (closed by AnvilProcess.stop)
        process = subprocess.Popen(
            [*args, "--port", str(port)], stdout=subprocess.DEVNULL, stderr=stderr
        )
        node = AnvilProcess(port=port, process=process, stderr=stderr)
        try:
            _wait_until_ready(node)
        except AnvilError as error:
            node.stop()
            last_error = str(error)
            continue
        return node
    raise AnvilError(f"anvil did not start after {PORT_ATTEMPTS} attempts: {last_error}")


def _wait_until_ready(node: AnvilProcess) -> None:
    body = json.dumps({"jsonrpc": "2.0", "id": 1, "method": "eth_chainId", "params": []})
    # Our own http://127.0.0.1 URL, never user input.
    rpc = urllib.request.Request(  # noqa: S310
        node.url, data=body.encode(), headers={"Content-Type": "application/json"}
    )
    deadline = time.monotonic() + STARTUP_TIMEOUT
    while time.monotonic() < deadline:
        if node.process.poll() is not None:
            node.stderr.seek(0)
            output = node.stderr.read().decode(errors="replace").strip()
            raise AnvilError(f"anvil exited with {node.process.returncode}: {output}")
        try:
            with urllib.request.urlopen(rpc, timeout=1) as response:  # noqa: S310
                if "result" in json.loads(response.read()):
                    return
        except (urllib.error.URLError, ConnectionError, TimeoutError, ValueError):
            pass
        time.sleep(0.05)
    raise AnvilError(f"anvil did not answer on {node.url} within {STARTUP_TIMEOUT} s")

"""Start and stop a real anvil node: for `make run`, the benchmarks and integration tests.

    with start_anvil() as node:
        w3 = Web3(Web3.HTTPProvider(node.url))

The binary is the one pinned in package.json (node_modules/@foundry-rs/anvil-<os>-<arch>);
ANVIL_BIN overrides it. Without a port each node listens on a free port of 127.0.0.1, so
parallel test workers (pytest-xdist) do not collide. `make run` starts its node with
zero_gas, as a private proof-of-authority network should run (docs/deployment.md): the portal
then sends new owners' EOAs no ether at all.
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

from stack.processes import exit_with_parent

REPO_ROOT = Path(__file__).resolve().parent.parent
HOST = "127.0.0.1"
STARTUP_TIMEOUT = 15.0
STOP_TIMEOUT = 10.0
PORT_ATTEMPTS = 3
# A base fee and gas price of zero, and no minimum tip suggested: gas costs nothing.
ZERO_GAS_ARGS = ("--base-fee", "0", "--gas-price", "0", "--disable-min-priority-fee")

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


def anvil_version() -> str:
    """`anvil --version`'s first line, or why it is unknown."""
    try:
        done = subprocess.run(
            [str(anvil_binary()), "--version"], capture_output=True, text=True, timeout=10
        )
    except (OSError, subprocess.TimeoutExpired, AnvilError) as exc:
        return f"unknown ({exc})"
    return done.stdout.strip().splitlines()[0] if done.stdout.strip() else "unknown"


def free_port() -> int:
    """A TCP port of 127.0.0.1 that nothing listens on right now."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        sock.bind((HOST, 0))
        return sock.getsockname()[1]


def rpc_answers(url: str, timeout: float = 1.0) -> bool:
    """Whether a JSON-RPC node answers eth_chainId at url."""
    body = json.dumps({"jsonrpc": "2.0", "id": 1, "method": "eth_chainId", "params": []})
    # A node URL from our own configuration, never from a request.
    rpc = urllib.request.Request(  # noqa: S310
        url, data=body.encode(), headers={"Content-Type": "application/json"}
    )
    try:
        with urllib.request.urlopen(rpc, timeout=timeout) as response:  # noqa: S310
            return "result" in json.loads(response.read())
    except (urllib.error.URLError, ConnectionError, TimeoutError, ValueError):
        return False


@dataclass
class AnvilProcess:
    """A running anvil node; stop() it, or use it as a context manager."""

    port: int
    process: subprocess.Popen[bytes]
    output: IO[bytes]

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
        self.output.close()

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
    block_time: float | None = None,
    state_path: str | Path | None = None,
    port: int | None = None,
    *,
    state_interval: float | None = None,
    log_path: Path | None = None,
    die_with_parent: bool = False,
    zero_gas: bool = False,
) -> AnvilProcess:
    """Start anvil on a free port and return once its JSON-RPC answers.

    block_time: seconds between blocks (interval mining); None mines one block per transaction.
    state_path: file the chain state is loaded from (if present) and written to on stop().
    port: a fixed port (e.g. to restart a node where its clients expect it); else a free one.
    state_interval: also write the state every this many seconds (survives a kill -9).
    log_path: anvil's output goes there (appended); else it is silent.
    die_with_parent: the kernel stops it if the process that started it dies (see Children).
    zero_gas: gas costs nothing (ZERO_GAS_ARGS); else anvil's own fees (1 gwei base fee).
    """

    args = [str(anvil_binary()), "--host", HOST]
    if log_path is None:
        args.append("--silent")
    if zero_gas:
        args += ZERO_GAS_ARGS
    if block_time is not None:
        args += ["--block-time", str(block_time)]
    if state_path is not None:
        args += ["--state", str(state_path)]
        if state_interval is not None:
            args += ["--state-interval", str(state_interval)]
    last_error = ""
    # The free port may be taken by someone else before anvil binds it: try a few.
    fixed_port = port
    for _ in range(PORT_ATTEMPTS):
        port = fixed_port or free_port()
        # Closed by AnvilProcess.stop.
        output = log_path.open("ab+") if log_path else tempfile.TemporaryFile()  # noqa: SIM115
        start = output.tell()
        process = subprocess.Popen(
            [*args, "--port", str(port)],
            stdout=output,
            stderr=subprocess.STDOUT,
            # Its own session: a Ctrl-C meant for whoever started it must not kill it before
            # its state is written; the owner stops it.
            start_new_session=True,
            preexec_fn=exit_with_parent if die_with_parent else None,
        )
        node = AnvilProcess(port=port, process=process, output=output)
        try:
            _wait_until_ready(node, start)
        except AnvilError as error:
            node.stop()
            last_error = str(error)
            continue
        return node
    raise AnvilError(f"anvil did not start after {PORT_ATTEMPTS} attempts: {last_error}")


def _wait_until_ready(node: AnvilProcess, log_start: int) -> None:
    deadline = time.monotonic() + STARTUP_TIMEOUT
    while time.monotonic() < deadline:
        if node.process.poll() is not None:
            node.output.seek(log_start)
            text = node.output.read().decode(errors="replace").strip()
            raise AnvilError(f"anvil exited with {node.process.returncode}: {text[-2000:]}")
        if rpc_answers(node.url):
            return
        time.sleep(0.05)
    raise AnvilError(f"anvil did not answer on {node.url} within {STARTUP_TIMEOUT} s")

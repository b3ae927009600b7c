"""Start and stop a real anvil node: for `make run`, the benchmarks and integration tests.

    with start_anvil() as node:
        w3 = Web3(Web3.HTTPProvider(node.url))

The binary is the one pinned in package.json (node_modules/@foundry-rs/anvil-<os>-<arch>);
ANVIL_BIN overrides it. Without a port each node listens on a free port of 127.0.0.1, so
parallel test workers (pytest-xdist) do not collide. `make run` starts its node with
zero_gas, as a private proof-of-authority network should run (docs/deployment.md): the portal
then sends new owners' EOAs no ether at all.

The chain state (state_path) is written by this module, not by anvil's own --state: anvil
truncates its state file and writes it in place (File::create), so a kill -9 during a write
leaves a file it then refuses to start from. A StateKeeper thread asks the node for its state
(anvil_dumpState) every state_interval seconds and on stop(), writes it to a temporary file,
keeps the last good copy as <state>.prev and renames the new one into place; at start a state
file that does not parse is set aside (<state>.bad) and the .prev copy is loaded instead.
"""

from __future__ import annotations

import hashlib
import json
import os
import platform
import re
import shutil
import signal
import socket
import subprocess
import tempfile
import threading
import time
import urllib.error
import urllib.request
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import IO

from stack.processes import StopsOnExit, exit_with_parent

REPO_ROOT = Path(__file__).resolve().parent.parent
HOST = "127.0.0.1"
STARTUP_TIMEOUT = 15.0
STOP_TIMEOUT = 10.0
PORT_ATTEMPTS = 3
# As anvil's own --state: the state is written every minute unless told otherwise.
DEFAULT_STATE_INTERVAL = 60.0
PREVIOUS_SUFFIX = ".prev"
BAD_SUFFIX = ".bad"
# A base fee and gas price of zero, and no minimum tip suggested: gas costs nothing.
ZERO_GAS_ARGS = ("--base-fee", "0", "--gas-price", "0", "--disable-min-priority-fee")
# A node that keeps only its latest blocks' transactions keeps only this many blocks' states,
# in memory: anvil otherwise writes every older state under ~/.foundry/anvil/tmp, tens of GB
# in a day of uploads, and leaves them there when it stops. Enough to replay a failed
# transaction at its parent block (chainworker/sender.py's _explain_failure).
KEPT_STATES = 64

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
class AnvilProcess(StopsOnExit):
    """A running anvil node; stop() it, or use it as a context manager."""

    port: int
    process: subprocess.Popen[bytes]
    output: IO[bytes]
    keeper: StateKeeper | None = None

    @property
    def url(self) -> str:
        return f"http://{HOST}:{self.port}"

    def stop(self) -> None:
        """Stop the node gracefully (its state written first), killing it if it hangs."""
        if self.keeper is not None:
            self.keeper.stop()  # a last write while the node still answers
        if self.process.poll() is None:
            self.process.send_signal(signal.SIGTERM)
            try:
                self.process.wait(timeout=STOP_TIMEOUT)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait()
        self.output.close()


def start_anvil(
    block_time: float | None = None,
    state_path: str | Path | None = None,
    port: int | None = None,
    *,
    state_interval: float | None = None,
    log_path: Path | None = None,
    die_with_parent: bool = False,
    zero_gas: bool = False,
    transaction_blocks: int | None = None,
) -> AnvilProcess:
    """Start anvil on a free port and return once its JSON-RPC answers.

    block_time: seconds between blocks (interval mining); None mines one block per transaction.
    state_path: file the chain state is loaded from (if present; else its .prev copy if it does
        not parse) and written to, atomically, on stop() and every state_interval seconds.
    port: a fixed port (e.g. to restart a node where its clients expect it); else a free one.
    state_interval: seconds between writes of the state (a kill -9 loses what came after the
        last one); DEFAULT_STATE_INTERVAL if None.
    log_path: anvil's output goes there (appended); else it is silent.
    die_with_parent: the kernel stops it if the process that started it dies (see Children).
    zero_gas: gas costs nothing (ZERO_GAS_ARGS); else anvil's own fees (1 gwei base fee).
    transaction_blocks: keep the transactions (and their receipts and logs) of only this many
        latest blocks, and the states of only KEPT_STATES, in memory; else all of them. The
        node's memory and its state file then grow with block headers alone (about 1.7 KiB a
        block, against several KiB with transactions).
    """

    args = [str(anvil_binary()), "--host", HOST]
    if log_path is None:
        args.append("--silent")
    if zero_gas:
        args += ZERO_GAS_ARGS
    if block_time is not None:
        args += ["--block-time", str(block_time)]
    if transaction_blocks is not None:
        args += ["--transaction-block-keeper", str(transaction_blocks)]
        args += ["--prune-history", str(KEPT_STATES)]
    if state_path is not None and (loaded := usable_state(Path(state_path))) is not None:
        args += ["--load-state", str(loaded)]
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
        if state_path is not None:
            node.keeper = StateKeeper(node, Path(state_path), state_interval)
            node.keeper.start()
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


def usable_state(path: Path) -> Path | None:
    """The state file to start from: `path` if it parses, else its .prev copy (a bad `path`,
    e.g. cut short by a kill -9 of an older anvil writing it, is kept as .bad). No `path` is a
    new chain: None, and a .prev left from a chain dropped with it is removed."""
    previous = path.with_name(path.name + PREVIOUS_SUFFIX)
    if not path.exists():
        previous.unlink(missing_ok=True)
        return None
    for candidate in (path, previous):
        if not candidate.exists():
            continue
        try:
            json.loads(candidate.read_bytes())
        except ValueError:
            candidate.replace(candidate.with_name(candidate.name + BAD_SUFFIX))
            continue
        return candidate
    return None


class StateKeeper(threading.Thread):
    """Writes the node's state to a file every `interval` seconds and once more on stop(), each
    time atomically: a temporary file renamed into place, the previous one kept as .prev.

    The state is streamed from the node to the file, never held whole in memory (it grows with
    the chain), and a write that finds the state unchanged (same SHA-256) replaces nothing. The
    pause after a write is at least PACE times what the write took, so the node never spends
    more than about 1/PACE of its time answering anvil_dumpState."""

    PACE = 4

    def __init__(self, node: AnvilProcess, path: Path, interval: float | None) -> None:
        super().__init__(name=f"anvil-state-{node.port}", daemon=True)
        self.node = node
        self.path = path
        self.interval = DEFAULT_STATE_INTERVAL if interval is None else interval
        self._stopping = threading.Event()
        self._lock = threading.Lock()
        self._written: str | None = None  # the SHA-256 of what the file holds
        self.last_duration = 0.0

    def run(self) -> None:
        while not self._stopping.wait(max(self.interval, self.PACE * self.last_duration)):
            if self.node.process.poll() is not None:
                return  # killed: what was written last is what a restart loads
            self.write()

    def stop(self) -> None:
        """Stop writing periodically, after a last write if the node still answers."""
        self._stopping.set()
        if self.is_alive() and self is not threading.current_thread():
            self.join(timeout=STOP_TIMEOUT)
        if self.node.process.poll() is None:
            self.write()

    def write(self) -> bool:
        """Write the node's state now if it changed; False if the node did not answer."""
        with self._lock:
            started = time.monotonic()
            partial = self.path.with_name(self.path.name + ".partial")
            try:
                with partial.open("wb") as out:
                    digest = _stream_state(self.node.url, out)
                    if digest is not None and digest != self._written:
                        out.flush()
                        os.fsync(out.fileno())
                if digest is None or digest == self._written:
                    partial.unlink(missing_ok=True)
                    return digest is not None
                if self.path.exists():
                    # A second name for the current copy, so the state file is never missing.
                    spare = self.path.with_name(self.path.name + PREVIOUS_SUFFIX + ".partial")
                    spare.unlink(missing_ok=True)
                    os.link(self.path, spare)
                    spare.replace(self.path.with_name(self.path.name + PREVIOUS_SUFFIX))
                partial.replace(self.path)
                self._written = digest
                return True
            finally:
                self.last_duration = time.monotonic() - started


# anvil's answer: {"jsonrpc":"2.0","id":1,"result":"0x<hex of the gzipped state>"}
_RESULT_START = re.compile(rb'"result"\s*:\s*"(?:0x)?')
_HEAD_LIMIT = 4096
_CHUNK = 1 << 18


def _stream_state(url: str, out: IO[bytes]) -> str | None:
    """Write the node's state, as anvil's --load-state reads it (anvil_dumpState gives it
    gzipped, in hex), to `out` a chunk at a time; its SHA-256, or None if the node did not
    answer with a whole state."""
    body = json.dumps({"jsonrpc": "2.0", "id": 1, "method": "anvil_dumpState", "params": []})
    # A node URL from our own configuration, never from a request.
    rpc = urllib.request.Request(  # noqa: S310
        url, data=body.encode(), headers={"Content-Type": "application/json"}
    )
    inflate = zlib.decompressobj(wbits=16 + zlib.MAX_WBITS)
    digest = hashlib.sha256()
    try:
        with urllib.request.urlopen(rpc, timeout=STOP_TIMEOUT) as response:  # noqa: S310
            head = b""
            while (found := _RESULT_START.search(head)) is None:
                chunk = response.read(256)
                if not chunk or len(head) > _HEAD_LIMIT:
                    return None  # an error answer, or not anvil's
                head += chunk
            pending = head[found.end() :]
            while True:
                end = pending.find(b'"')
                text = pending if end < 0 else pending[:end]
                even = len(text) - len(text) % 2
                data = inflate.decompress(bytes.fromhex(text[:even].decode("ascii")))
                out.write(data)
                digest.update(data)
                if end >= 0:
                    break
                more = response.read(_CHUNK)
                if not more:
                    return None  # cut short
                pending = text[even:] + more
        data = inflate.flush()
        out.write(data)
        digest.update(data)
    except (urllib.error.URLError, ConnectionError, TimeoutError, ValueError, OSError, zlib.error):
        return None
    return digest.hexdigest() if inflate.eof else None

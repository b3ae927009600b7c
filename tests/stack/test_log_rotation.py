"""make run's logs are rotated while its processes write them: a copy, then the log emptied in
place, where a process that keeps it open (O_APPEND) goes on writing at its start."""

import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

from stack import run as run_module
from stack.processes import Children, logs_rotate
from stack.run import Stack, StackConfig
from tests.support.harness import wait_for

# A process that writes numbered lines to its stdout (its log) until it is stopped.
WRITER = (
    "import itertools, sys, time\n"
    "for n in itertools.count():\n"
    "    sys.stdout.write(f'line {n:08d} ' + 'x' * 80 + chr(10)); sys.stdout.flush()\n"
    "    time.sleep(0.0005)\n"
)


def _lines(path: Path) -> list[str]:
    return path.read_text().splitlines()


@pytest.mark.process
def test_a_log_past_its_size_is_copied_and_emptied_while_its_process_goes_on_writing(tmp_path):
    log = tmp_path / "web.log"
    with log.open("ab") as output:
        writer = subprocess.Popen([sys.executable, "-c", WRITER], stdout=output)
    try:
        wait_for(lambda: log.stat().st_size > 200_000, timeout=30, what="200 kB of log")
        assert logs_rotate(tmp_path, max_bytes=100_000, keep=3) == [log]
        wait_for(lambda: log.stat().st_size > 20_000, timeout=30, what="the log written again")
    finally:
        writer.terminate()
        writer.wait()
    copy = _lines(tmp_path / "web.log.1")
    assert copy[0].startswith("line 00000000 ")
    written = log.read_bytes()
    # Written from its start again: no hole of zeros where the old content was.
    assert b"\0" not in written
    after = _lines(log)
    first_after = int(after[0].split()[1])
    last_copied = int(copy[-1].split()[1])
    # The copy ends where the log starts again, give or take the lines of that instant.
    assert 0 < first_after - last_copied <= 50
    assert all(line.startswith("line ") and len(line) == 94 for line in after[:-1])


def test_copies_move_up_and_the_oldest_is_dropped(tmp_path):
    log = tmp_path / "worker.log"
    for round_ in range(5):
        log.write_text(f"round {round_}\n" * 1000)
        assert logs_rotate(tmp_path, max_bytes=1000, keep=2) == [log]
        assert log.stat().st_size == 0
    assert sorted(path.name for path in tmp_path.iterdir()) == [
        "worker.log",
        "worker.log.1",
        "worker.log.2",
    ]
    assert (tmp_path / "worker.log.1").read_text().startswith("round 4")
    assert (tmp_path / "worker.log.2").read_text().startswith("round 3")


def test_small_logs_and_other_files_are_left_alone(tmp_path):
    (tmp_path / "beat.log").write_text("short\n")
    (tmp_path / "anvil.json").write_text("x" * 10_000)
    assert logs_rotate(tmp_path, max_bytes=1000, keep=3) == []
    assert (tmp_path / "beat.log").read_text() == "short\n"
    assert (tmp_path / "anvil.json").stat().st_size == 10_000
    assert not list(tmp_path.glob("*.1"))


def test_the_settings_come_from_the_environment(tmp_path):
    config = StackConfig.from_environment(
        {"AUTHROS_VAR_DIR": str(tmp_path), "STACK_LOG_MAX_BYTES": "5000", "STACK_LOG_KEEP": "7"}
    )
    assert (config.log_max_bytes, config.log_keep) == (5000, 7)
    default = StackConfig.from_environment({"AUTHROS_VAR_DIR": str(tmp_path)})
    assert (default.log_max_bytes, default.log_keep) == (32 * 1024**2, 3)


@pytest.mark.process
def test_the_running_stack_rotates_its_logs(tmp_path, monkeypatch):
    """Stack.wait, which make run sits in until a process exits or Ctrl-C, looks at the logs
    every LOG_ROTATE_INTERVAL seconds; with STACK_LOG_MAX_BYTES 0 it never rotates."""
    monkeypatch.setattr(run_module, "LOG_ROTATE_INTERVAL", 0.1)
    for max_bytes, rotated in ((1000, True), (0, False)):
        workdir = tmp_path / str(max_bytes)
        stack = Stack(StackConfig(workdir=workdir, log_max_bytes=max_bytes, log_keep=3))
        stack.children = Children(stack.logs)
        stack.logs.mkdir(parents=True)
        (stack.logs / "web.log").write_text("x" * 5000)
        stack.children.spawn(
            "short", [sys.executable, "-c", "import time; time.sleep(1.5)"], env=os.environ
        )
        started = time.monotonic()
        assert stack.wait() == 1  # the short process exited
        assert time.monotonic() - started >= 1.0
        assert (stack.logs / "web.log.1").exists() is rotated
        assert (stack.logs / "web.log").stat().st_size == (0 if rotated else 5000)

"""A program run in a fresh interpreter from the repository root: for what a process reads
of its environment and settings at start, which the test process has read already."""

import os
import subprocess
import sys
from collections.abc import Mapping, Sequence

from stack.processes import REPO_ROOT


def fresh_python(program: str, *, unset: Sequence[str] = ()) -> str:
    """The last line `program` prints, run with this environment but for the `unset`
    variables; it must exit 0."""
    done = fresh_python_run(program, unset=unset)
    assert done.returncode == 0, done.stderr
    return done.stdout.strip().splitlines()[-1]


def fresh_python_run(
    program: str, *, unset: Sequence[str] = (), env: Mapping[str, str] | None = None
) -> subprocess.CompletedProcess[str]:
    """`program` run with this environment, but for the `unset` variables and with `env`
    added, whatever its exit: its exit code, output and errors."""
    environment = {key: value for key, value in os.environ.items() if key not in unset}
    environment.update(env or {})
    return subprocess.run(
        [sys.executable, "-c", program],
        cwd=REPO_ROOT,
        env=environment,
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )

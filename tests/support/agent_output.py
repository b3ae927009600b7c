"""What the agent leaves for a test to read while it runs and after: the envelopes waiting in
its spool's queue, and the counters it logs (every so often, and once more on exit)."""

import re
from collections.abc import Callable
from pathlib import Path

_COUNTERS = re.compile(
    r"sent=(?P<sent>\d+) spooled=(?P<spooled>\d+) failed=(?P<failed>\d+) "
    r"dropped=(?P<dropped>\d+) queued=(?P<queued>\d+)"
)


def spool_queued(spool: Path) -> list[Path]:
    """The envelopes waiting in the spool for the portal, oldest first."""
    return sorted((spool / "queue").glob("*.env"))


def spool_queued_now_gone(spool: Path) -> Callable[[], bool]:
    """A condition: every envelope queued in the spool now has left its queue (sent, or
    rejected), whatever was queued since. Not "the spool empty" while the robot still
    captures: on a loaded machine the spool may never be seen empty between one capture and
    the next upload."""
    queued = {path.name for path in spool_queued(spool)}
    return lambda: not queued & {path.name for path in spool_queued(spool)}


def agent_stats(log: Path) -> list[dict[str, int]]:
    """Every set of counters the agent logged, in order."""
    return [
        {name: int(value) for name, value in match.groupdict().items()}
        for match in _COUNTERS.finditer(log.read_text())
    ]


def agent_final_stats(log: Path) -> dict[str, int]:
    """The counters the agent logged last (on exit, when it stopped cleanly)."""
    stats = agent_stats(log)
    assert stats, f"no counters logged by the agent:\n{log.read_text()[-3000:]}"
    return stats[-1]

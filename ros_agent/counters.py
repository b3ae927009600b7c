"""What the agent did so far, for its periodic log line and for anyone who asks."""

import threading
from dataclasses import dataclass, field


@dataclass
class AgentCounters:
    """Envelopes spooled, sent (confirmed by the portal), failed and dropped (spool full).

    `failed` counts messages that will never reach the portal: refused by it (moved to the
    spool's rejected/) or not convertible to a record at all.
    """

    spooled: int = 0
    sent: int = 0
    failed: int = 0
    dropped: int = 0
    _lock: threading.Lock = field(default_factory=threading.Lock, repr=False, compare=False)

    def add(self, name: str, amount: int = 1) -> int:
        """Add to one counter and return its new value."""
        with self._lock:
            value = getattr(self, name) + amount
            setattr(self, name, value)
            return value

    def snapshot(self) -> dict[str, int]:
        with self._lock:
            return {
                "spooled": self.spooled,
                "sent": self.sent,
                "failed": self.failed,
                "dropped": self.dropped,
            }


def worth_logging(count: int) -> bool:
    """True for 1, 10, 100, ...: repeated trouble is logged, but not once per message."""
    while count >= 10 and count % 10 == 0:
        count //= 10
    return count == 1

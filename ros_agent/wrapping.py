"""The paper's Fig. 4 record around a message's data, sealed as envelope v1 into the spool.

Plaintext (compact UTF-8 JSON):
    {"K": <extracted data>, "Owner": owner, "Time": capture time, "Type": ros type,
     "Topic": topic}
Envelope header: owner, robot, topic, type, seq (from the spool's counter), time (the same
capture time as "Time": the message's header stamp, or the time it was received when it has
no stamp). Unsigned: a paired robot signs each upload batch once, before it leaves, and numbers
its records then (ros_agent.batches).
"""

import json
import logging
import threading
from collections.abc import Callable
from datetime import UTC, datetime
from typing import Any

from ros_agent import LOGGER_NAME
from ros_agent.counters import AgentCounters, worth_logging
from ros_agent.extractors import ExtractionError, JsonDict, extract, iso_utc, stamp_datetime
from ros_agent.keyring import Keyring
from ros_agent.sealing import RobotSigningKey, seal_record
from ros_agent.spool import Spool

logger = logging.getLogger(f"{LOGGER_NAME}.wrapping")


def record_json(
    *, data: JsonDict, owner: str, topic: str, ros_type: str, captured_at: datetime
) -> bytes:
    """The Fig. 4 record as compact UTF-8 JSON."""
    record = {
        "K": data,
        "Owner": owner,
        "Time": iso_utc(captured_at),
        "Type": ros_type,
        "Topic": topic,
    }
    return json.dumps(record, separators=(",", ":"), ensure_ascii=False, allow_nan=False).encode()


def envelope_header(
    *, owner: str, robot: str, topic: str, ros_type: str, seq: int, captured_at: datetime
) -> dict[str, Any]:
    return {
        "owner": owner,
        "robot": robot,
        "topic": topic,
        "type": ros_type,
        "seq": seq,
        "time": iso_utc(captured_at),
    }


def capture_time(msg: Any, received_at: datetime) -> datetime:
    """The message's header stamp if it has a non-zero one, else when it was received."""
    stamp = getattr(getattr(msg, "header", None), "stamp", None)
    if stamp is not None and (stamp.secs or stamp.nsecs):
        return stamp_datetime(stamp)
    return received_at


class Recorder:
    """extract -> wrap -> seal -> spool, for one robot; called from any subscriber thread."""

    def __init__(
        self,
        *,
        spool: Spool,
        owner: str,
        robot: str,
        counters: AgentCounters,
        key: bytes | None = None,
        keyring: Keyring | None = None,
        signing_key: RobotSigningKey | None = None,
        on_spooled: Callable[[], None] = lambda: None,
    ) -> None:
        """Seals under `keyring`'s current key at each message (a paired robot's keyring
        changes when the owner rotates), or under the one `key`; unsigned, unless given a
        `signing_key`: then each record is signed on its own (provenance v1, which the agent
        no longer sends; the benchmarks measure it beside v2)."""
        if (key is None) == (keyring is None):
            raise ValueError("give the key or the keyring")
        self._spool = spool
        self._keyring = keyring or Keyring.of_one(key)
        self._signing_key = signing_key
        self._owner = owner
        self._robot = robot
        self._counters = counters
        self._on_spooled = on_spooled
        self._closed = False
        self._state = threading.Lock()
        self._dropping_since: int | None = None

    def record(
        self, msg: Any, *, topic: str, ros_type: str, received_at: datetime | None = None
    ) -> int | None:
        """Seal and spool one message; return its sequence number, or None if it was not."""
        if self._closed:
            return None
        received_at = received_at or datetime.now(UTC)
        captured_at = capture_time(msg, received_at)
        try:
            plaintext = record_json(
                data=extract(msg, ros_type),
                owner=self._owner,
                topic=topic,
                ros_type=ros_type,
                captured_at=captured_at,
            )
        except (ExtractionError, TypeError, ValueError) as exc:
            failures = self._counters.add("failed")
            if worth_logging(failures):
                logger.error(
                    "cannot record a %s message from %s: %s (%d failed so far)",
                    ros_type,
                    topic,
                    exc,
                    failures,
                )
            return None
        header = dict(
            owner=self._owner,
            robot=self._robot,
            topic=topic,
            ros_type=ros_type,
            captured_at=captured_at,
        )
        with self._state:
            if self._closed:
                return None
            try:
                _, key = self._keyring.current()
                seq = self._spool.append(
                    lambda seq: seal_record(
                        key, envelope_header(seq=seq, **header), plaintext, self._signing_key
                    )
                )
            except OSError as exc:
                logger.error("cannot write to the spool %s: %s", self._spool.directory, exc)
                seq = None
            self._note_spool_outcome(seq)
        if seq is not None:
            self._on_spooled()
        return seq

    def close(self) -> None:
        """Record nothing more (waits for a message being spooled right now)."""
        with self._state:
            self._closed = True

    def _note_spool_outcome(self, seq: int | None) -> None:
        if seq is None:
            dropped = self._counters.add("dropped")
            if self._dropping_since is None:
                self._dropping_since = dropped - 1
            lost = dropped - self._dropping_since
            if worth_logging(lost):
                logger.warning(
                    "spool %s is full (%d of %d bytes): dropped %d new message(s) so far; "
                    "queued data is kept and sent first",
                    self._spool.directory,
                    self._spool.used_bytes,
                    self._spool.max_bytes,
                    lost,
                )
            return
        self._counters.add("spooled")
        if self._dropping_since is not None:
            logger.warning(
                "spool has room again after dropping %d message(s)",
                self._counters.dropped - self._dropping_since,
            )
            self._dropping_since = None

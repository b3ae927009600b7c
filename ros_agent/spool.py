"""A bounded on-disk FIFO of envelopes, and the robot's sequence counter that lives beside it.

Layout of the spool directory (one agent at a time holds `lock`):

    queue/00000000000000000042.env     envelopes waiting for the portal, by sequence number
    rejected/000...042.env (+ .json)   envelopes the portal refused, with its answer
    seq                                the highest sequence number that may have been used
    topic_seq                          a paired robot's record counters (ros_agent.batches)

Every file is written to a temporary name, fsync'd, renamed into place and its directory
fsync'd, so after a crash a file is either whole or absent (leftover temporaries are removed
on open). Items leave the queue only through `ack` (the portal confirmed them) or `reject`.
The bound counts queue and rejected/ together; when full, new envelopes are refused, never
old ones thrown away.

Sequence numbers are never reused: they are reserved on disk in blocks before use, and a new
counter starts no lower than the current time in microseconds, so even a robot whose spool
directory was wiped continues above every number it sent before (the portal refuses a replayed
number, and the uploader takes such a refusal as "already delivered").
"""

import contextlib
import fcntl
import itertools
import json
import logging
import os
import re
import threading
import time
import uuid
from collections import deque
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ros_agent import LOGGER_NAME

logger = logging.getLogger(f"{LOGGER_NAME}.spool")

SEQ_RESERVATION = 1000
_ENVELOPE_NAME = re.compile(r"(\d{20})\.env")
_TEMP_PREFIX = ".tmp-"


class SpoolError(RuntimeError):
    """The spool directory cannot be used (locked by another agent, unreadable, misused)."""


@dataclass(frozen=True)
class SpoolItem:
    seq: int
    envelope: bytes


class Spool:
    """FIFO of sealed envelopes on disk, ordered by sequence number; safe across threads."""

    def __init__(self, directory: Path, *, max_bytes: int, seq_floor: int | None = None) -> None:
        self.directory = Path(directory)
        self.max_bytes = max_bytes
        self._queue_dir = self.directory / "queue"
        self._rejected_dir = self.directory / "rejected"
        self._lock = threading.Lock()
        for folder in (self.directory, self._queue_dir, self._rejected_dir):
            folder.mkdir(mode=0o700, parents=True, exist_ok=True)
        self._lock_file = _acquire_directory_lock(self.directory / "lock")
        try:
            for folder in (self.directory, self._queue_dir, self._rejected_dir):
                _remove_temporaries(folder)
            self._queue: deque[tuple[int, int]] = deque(_scan(self._queue_dir))
            rejected = list(_scan(self._rejected_dir))
            self._rejected_bytes = sum(size for _, size in rejected)
            self._queued_bytes = sum(size for _, size in self._queue)
            highest_on_disk = max((seq for seq, _ in [*self._queue, *rejected]), default=-1)
            floor = time.time_ns() // 1000 if seq_floor is None else seq_floor
            self._reserved = self._read_reserved()
            self._next_seq = max(self._reserved + 1, highest_on_disk + 1, floor)
        except BaseException:
            self._lock_file.close()
            raise

    # --- state -------------------------------------------------------------------------------

    def __len__(self) -> int:
        with self._lock:
            return len(self._queue)

    @property
    def queued_bytes(self) -> int:
        with self._lock:
            return self._queued_bytes

    @property
    def used_bytes(self) -> int:
        """Bytes counted against the bound: the queue and rejected/."""
        with self._lock:
            return self._queued_bytes + self._rejected_bytes

    # --- writing -----------------------------------------------------------------------------

    def append(self, build: Callable[[int], bytes]) -> int | None:
        """Take the next sequence number, build the envelope with it and queue it durably.

        Returns the sequence number, or None when the envelope does not fit in the bound
        (the number is spent all the same: numbers may have gaps, never repeats).
        """
        with self._lock:
            seq = self._take_seq()
            data = build(seq)
            if self._queued_bytes + self._rejected_bytes + len(data) > self.max_bytes:
                return None
            write_durably(self._queue_dir, _name(seq), data)
            self._queue.append((seq, len(data)))
            self._queued_bytes += len(data)
            return seq

    def head_while(self, keep: Callable[[SpoolItem], bool]) -> list[SpoolItem]:
        """The oldest queued items as long as `keep` holds for each, read one at a time (so
        that a long queue is not read whole to find its first few signed envelopes)."""
        with self._lock:
            items: list[SpoolItem] = []
            for seq, _ in self._queue:
                item = SpoolItem(seq, (self._queue_dir / _name(seq)).read_bytes())
                if not keep(item):
                    break
                items.append(item)
            return items

    def peek(self, limit: int, *, max_bytes: int | None = None) -> list[SpoolItem]:
        """The oldest queued items, at most `limit` and `max_bytes` (but at least one)."""
        with self._lock:
            items: list[SpoolItem] = []
            total = 0
            for seq, size in self._queue:
                if len(items) >= limit or (items and max_bytes and total + size > max_bytes):
                    break
                items.append(SpoolItem(seq, (self._queue_dir / _name(seq)).read_bytes()))
                total += size
            return items

    def ack(self, items: Sequence[SpoolItem]) -> None:
        """Remove delivered items; they must be the oldest ones, in order."""
        with self._lock:
            self._check_head(items)
            for item in items:
                (self._queue_dir / _name(item.seq)).unlink()
                _, size = self._queue.popleft()
                self._queued_bytes -= size
            _fsync_directory(self._queue_dir)

    def replace(self, seq: int, data: bytes) -> None:
        """Put `data` in place of the queued envelope `seq` (signed with its batch, or re-sealed
        under a new key), durably: after a crash the file holds the old envelope or the new one."""
        with self._lock:
            index = next((i for i, (queued, _) in enumerate(self._queue) if queued == seq), None)
            if index is None:
                raise SpoolError(f"seq {seq} is not queued")
            size = self._queue[index][1]
            write_durably(self._queue_dir, _name(seq), data)
            self._queue[index] = (seq, len(data))
            self._queued_bytes += len(data) - size

    def reject(self, items: Sequence[SpoolItem], reason: Mapping[str, Any]) -> None:
        """Move refused items to rejected/, each with `reason` beside it as JSON."""
        note = json.dumps(dict(reason), sort_keys=True, indent=1).encode()
        with self._lock:
            self._check_head(items)
            for item in items:
                name = _name(item.seq)
                write_durably(self._rejected_dir, name + ".json", note)
                os.replace(self._queue_dir / name, self._rejected_dir / name)
                _, size = self._queue.popleft()
                self._queued_bytes -= size
                self._rejected_bytes += size
            _fsync_directory(self._rejected_dir)
            _fsync_directory(self._queue_dir)

    def state_read(self, name: str) -> bytes | None:
        """A small file of state kept beside `seq` (its bytes, None if there is none yet)."""
        try:
            return (self.directory / name).read_bytes()
        except FileNotFoundError:
            return None

    def state_write(self, name: str, data: bytes) -> None:
        """Write a small file of state beside `seq`, durably: a crash leaves the old or the new."""
        with self._lock:
            write_durably(self.directory, name, data)

    def close(self) -> None:
        with self._lock:
            self._lock_file.close()

    # --- internals ---------------------------------------------------------------------------

    def _check_head(self, items: Sequence[SpoolItem]) -> None:
        head = [seq for seq, _ in itertools.islice(self._queue, len(items))]
        if head != [item.seq for item in items]:
            raise SpoolError(
                f"items {[item.seq for item in items]} are not the oldest queued ones {head}"
            )

    def _take_seq(self) -> int:
        seq = self._next_seq
        if seq > self._reserved:
            self._reserved = seq + SEQ_RESERVATION - 1
            write_durably(self.directory, "seq", f"{self._reserved}\n".encode())
        self._next_seq = seq + 1
        return seq

    def _read_reserved(self) -> int:
        path = self.directory / "seq"
        try:
            text = path.read_text(encoding="ascii")
        except FileNotFoundError:
            return -1
        try:
            return int(text.strip())
        except ValueError:
            raise SpoolError(
                f"{path} does not hold a sequence number ({text[:40]!r}); "
                "it is written atomically, so something else changed it"
            ) from None


def _name(seq: int) -> str:
    return f"{seq:020d}.env"


def _scan(folder: Path) -> list[tuple[int, int]]:
    found = []
    for entry in os.scandir(folder):
        match = _ENVELOPE_NAME.fullmatch(entry.name)
        if match:
            found.append((int(match.group(1)), entry.stat().st_size))
    return sorted(found)


def _remove_temporaries(folder: Path) -> None:
    for entry in os.scandir(folder):
        if entry.name.startswith(_TEMP_PREFIX):
            logger.warning("removing %s, left over by an interrupted write", entry.path)
            with contextlib.suppress(FileNotFoundError):
                os.unlink(entry.path)


def write_durably(folder: Path, name: str, data: bytes) -> None:
    """Write `name` in `folder` through a synced temporary file and a rename: whole or absent."""
    temporary = folder / f"{_TEMP_PREFIX}{name}-{uuid.uuid4().hex}"
    fd = os.open(temporary, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    try:
        try:
            view = memoryview(data)
            while view:
                view = view[os.write(fd, view) :]
            os.fsync(fd)
        finally:
            os.close(fd)
        os.replace(temporary, folder / name)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(temporary)
        raise
    _fsync_directory(folder)


def _fsync_directory(folder: Path) -> None:
    fd = os.open(folder, os.O_RDONLY | os.O_DIRECTORY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _acquire_directory_lock(path: Path) -> Any:
    lock_file = path.open("a+")
    try:
        fcntl.flock(lock_file, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        lock_file.close()
        raise SpoolError(
            f"the spool {path.parent} is in use by another agent; "
            "each agent needs its own spool_dir"
        ) from None
    return lock_file

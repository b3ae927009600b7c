"""Envelope files are durable before their upload commits: the syncs that threads of one
process need at the same time are shared, and none returns before a sync that started after
its files were written has finished."""

import os
import threading
import time

import pytest

from core import files as files_module
from sharing import storage as storage_module


class _SlowSyncfs:
    """A syncfs that takes a while and records when each call started and finished."""

    def __init__(self, seconds: float = 0.02, fails: bool = False) -> None:
        self.seconds = seconds
        self.fails = fails
        self.calls: list[tuple[float, float]] = []
        self._lock = threading.Lock()
        self.running = 0
        self.most_at_once = 0
        self.locations: list[str] = []

    def __call__(self, fd: int) -> int:
        started = time.monotonic()
        self.locations.append(os.readlink(f"/proc/self/fd/{fd}"))
        with self._lock:
            self.running += 1
            self.most_at_once = max(self.most_at_once, self.running)
        time.sleep(self.seconds)
        with self._lock:
            self.running -= 1
            self.calls.append((started, time.monotonic()))
        return -1 if self.fails else 0


@pytest.fixture
def slow_syncfs(monkeypatch):
    syncfs = _SlowSyncfs()
    monkeypatch.setattr(files_module, "_SYNCFS", syncfs)
    monkeypatch.setattr(files_module, "_sync_groups", {})
    return syncfs


def _callers(tmp_path, count: int) -> list[tuple[float, float]]:
    """`count` threads call _sync at once; (entered, returned) of each."""
    times: list[tuple[float, float]] = []
    lock = threading.Lock()
    barrier = threading.Barrier(count)

    def call(number: int) -> None:
        path = tmp_path / f"{number}.env"
        path.write_bytes(b"x")
        barrier.wait()
        entered = time.monotonic()
        storage_module._sync([str(path)], str(tmp_path))
        with lock:
            times.append((entered, time.monotonic()))

    threads = [threading.Thread(target=call, args=(number,)) for number in range(count)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    return times


def test_threads_that_sync_together_share_few_syncs_each_started_after_they_asked(
    slow_syncfs, tmp_path
):
    slow_syncfs.seconds = 0.3
    times = _callers(tmp_path, 32)
    assert len(times) == 32
    # One running when the others ask, then one for them (two more for stragglers).
    assert len(slow_syncfs.calls) <= 4
    assert slow_syncfs.most_at_once == 1
    for entered, returned in times:
        # A sync that started after this thread asked finished before it returned.
        assert any(entered <= start and end <= returned for start, end in slow_syncfs.calls)


def test_a_thread_arriving_during_a_sync_waits_for_the_next_one(slow_syncfs, tmp_path):
    """Its files may have been written after the running sync had passed them."""
    slow_syncfs.seconds = 0.2
    first = threading.Thread(target=storage_module._sync, args=(["a"], str(tmp_path)))
    first.start()
    while slow_syncfs.running == 0:  # until the first sync is running
        time.sleep(0.001)
    entered = time.monotonic()
    storage_module._sync(["b"], str(tmp_path))
    returned = time.monotonic()
    first.join()
    assert len(slow_syncfs.calls) == 2
    second_start, second_end = slow_syncfs.calls[1]
    assert entered <= second_start
    assert second_end <= returned


def test_a_failed_shared_sync_falls_back_to_fsync_of_each_file_and_folder(
    slow_syncfs, tmp_path, monkeypatch
):
    slow_syncfs.fails = True
    synced: list[str] = []
    monkeypatch.setattr(storage_module, "fsync_path", synced.append)
    times = _callers(tmp_path, 8)
    assert len(times) == 8
    files = {str(tmp_path / f"{number}.env") for number in range(8)}
    assert set(synced) == files | {str(tmp_path)}


def test_each_file_system_location_has_its_own_syncs(slow_syncfs, tmp_path):
    one, two = tmp_path / "one", tmp_path / "two"
    one.mkdir()
    two.mkdir()
    slow_syncfs.seconds = 0.1
    threads = [
        threading.Thread(target=storage_module._sync, args=(["x"], str(where)))
        for where in (one, two)
    ]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    assert sorted(slow_syncfs.locations) == [str(one), str(two)]

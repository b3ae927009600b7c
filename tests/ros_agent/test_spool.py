"""The on-disk spool: order, bound, acknowledgement, restarts, crashes, sequence numbers."""

import json
import shutil
import threading
import time

import pytest

from ros_agent.spool import SEQ_RESERVATION, Spool, SpoolError


def _payload(seq: int, size: int = 10) -> bytes:
    return f"env-{seq}:".encode().ljust(size, b".")


def _fill(spool: Spool, count: int, size: int = 10) -> list[int]:
    return [spool.append(lambda seq: _payload(seq, size)) for _ in range(count)]


def test_items_come_out_in_order_and_leave_only_when_acknowledged(tmp_path):
    spool = Spool(tmp_path, max_bytes=10_000, seq_floor=0)
    seqs = _fill(spool, 5)
    assert seqs == [0, 1, 2, 3, 4]

    batch = spool.peek(3)
    assert [item.seq for item in batch] == [0, 1, 2]
    assert [item.envelope for item in batch] == [_payload(s) for s in (0, 1, 2)]
    assert spool.peek(3) == batch  # peeking takes nothing
    spool.ack(batch)
    assert [item.seq for item in spool.peek(10)] == [3, 4]
    assert len(spool) == 2
    assert sorted(p.name for p in (tmp_path / "queue").iterdir()) == [
        "00000000000000000003.env",
        "00000000000000000004.env",
    ]


def test_peek_respects_a_byte_limit_but_returns_at_least_one(tmp_path):
    spool = Spool(tmp_path, max_bytes=10_000, seq_floor=0)
    _fill(spool, 4, size=100)
    assert len(spool.peek(10, max_bytes=250)) == 2
    assert len(spool.peek(10, max_bytes=50)) == 1


def test_only_the_oldest_items_can_be_acknowledged(tmp_path):
    spool = Spool(tmp_path, max_bytes=10_000, seq_floor=0)
    _fill(spool, 3)
    with pytest.raises(SpoolError, match="not the oldest"):
        spool.ack(spool.peek(3)[1:])
    assert len(spool) == 3


def test_a_full_spool_refuses_new_items_and_keeps_the_old(tmp_path):
    spool = Spool(tmp_path, max_bytes=35, seq_floor=0)
    assert _fill(spool, 4) == [0, 1, 2, None]  # 3 x 10 bytes fit, the 4th does not
    assert [item.seq for item in spool.peek(10)] == [0, 1, 2]
    assert spool.used_bytes == 30

    spool.ack(spool.peek(1))
    assert _fill(spool, 1) == [4]  # seq 3 was spent on the refused item: never reused
    assert [item.seq for item in spool.peek(10)] == [1, 2, 4]


def test_rejected_items_move_aside_with_the_reason_and_still_count_against_the_bound(tmp_path):
    spool = Spool(tmp_path, max_bytes=25, seq_floor=0)
    _fill(spool, 2)
    spool.reject(spool.peek(1), {"status": 403, "error": "unknown_key"})

    assert [item.seq for item in spool.peek(10)] == [1]
    rejected = tmp_path / "rejected" / "00000000000000000000.env"
    assert rejected.read_bytes() == _payload(0)
    reason = json.loads(rejected.with_name(rejected.name + ".json").read_text())
    assert reason == {"status": 403, "error": "unknown_key"}
    assert spool.used_bytes == 20
    assert _fill(spool, 1) == [None]


def test_queue_and_counter_survive_a_restart(tmp_path):
    spool = Spool(tmp_path, max_bytes=10_000, seq_floor=0)
    _fill(spool, 3)
    spool.ack(spool.peek(1))
    spool.close()

    again = Spool(tmp_path, max_bytes=10_000, seq_floor=0)
    assert [item.seq for item in again.peek(10)] == [1, 2]
    assert again.queued_bytes == 20
    assert _fill(again, 1) == [SEQ_RESERVATION]  # above the whole block reserved before


def test_sequence_numbers_never_repeat_even_with_an_empty_queue(tmp_path):
    spool = Spool(tmp_path, max_bytes=100_000, seq_floor=0)
    first = _fill(spool, SEQ_RESERVATION + 5)
    spool.ack(spool.peek(len(first)))
    spool.close()

    again = Spool(tmp_path, max_bytes=10_000, seq_floor=0)
    assert len(again) == 0
    assert _fill(again, 1)[0] > max(first)


def test_a_new_spool_starts_at_the_current_time_in_microseconds(tmp_path):
    before = time.time_ns() // 1000
    spool = Spool(tmp_path / "fresh", max_bytes=10_000)
    (seq,) = _fill(spool, 1)
    assert before <= seq <= time.time_ns() // 1000
    spool.close()
    # a wiped spool directory still does not reuse the numbers of the old one
    shutil.rmtree(tmp_path / "fresh")
    assert _fill(Spool(tmp_path / "fresh", max_bytes=10_000), 1)[0] > seq


def test_leftovers_of_an_interrupted_write_are_ignored_and_removed(tmp_path):
    spool = Spool(tmp_path, max_bytes=10_000, seq_floor=0)
    _fill(spool, 2)
    spool.close()
    leftover = tmp_path / "queue" / ".tmp-00000000000000000002.env-deadbeef"
    leftover.write_bytes(b"half an envel")
    (tmp_path / ".tmp-seq-0123").write_text("99")
    (tmp_path / "queue" / "README").write_text("not an envelope")

    again = Spool(tmp_path, max_bytes=10_000, seq_floor=0)
    assert [item.seq for item in again.peek(10)] == [0, 1]
    assert again.queued_bytes == 20
    assert not leftover.exists()
    assert not (tmp_path / ".tmp-seq-0123").exists()


def test_a_corrupt_counter_file_is_reported(tmp_path):
    (tmp_path / "seq").write_text("garbage")
    with pytest.raises(SpoolError, match="does not hold a sequence number"):
        Spool(tmp_path, max_bytes=100)


def test_two_agents_cannot_share_a_spool(tmp_path):
    spool = Spool(tmp_path, max_bytes=100)
    with pytest.raises(SpoolError, match="in use by another agent"):
        Spool(tmp_path, max_bytes=100)
    spool.close()
    Spool(tmp_path, max_bytes=100).close()


def test_concurrent_appends_get_distinct_increasing_numbers_in_queue_order(tmp_path):
    spool = Spool(tmp_path, max_bytes=1_000_000, seq_floor=0)
    threads = [threading.Thread(target=_fill, args=(spool, 25)) for _ in range(4)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    items = spool.peek(1000)
    assert [item.seq for item in items] == list(range(100))
    assert all(item.envelope == _payload(item.seq) for item in items)

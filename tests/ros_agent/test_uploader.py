"""Uploader against an in-test records endpoint: batching, order, outages, replays, poison."""

import logging

import pytest
from std_msgs.msg import String

from ros_agent.counters import AgentCounters
from ros_agent.keyring import Keyring
from ros_agent.spool import Spool
from ros_agent.uploader import Outcome, PortalClient, Uploader
from ros_agent.wrapping import Recorder
from smcrypto import envelope, sm4
from tests.ros_agent.conftest import OWNER, ROBOT, TOKEN, chatter_record, wait_until
from tests.support.records_server import RECORDS_PATH

DELIVERED, SPLIT, REJECTED, RETRY, EMPTY = (
    Outcome.DELIVERED,
    Outcome.SPLIT,
    Outcome.REJECTED,
    Outcome.RETRY,
    Outcome.EMPTY,
)


class Robot:
    """A spool, a recorder feeding it, and an uploader draining it to `portal`."""

    def __init__(self, tmp_path, key, portal, *, token=TOKEN, **uploader_options):
        self.spool = Spool(tmp_path / "spool", max_bytes=10**7)
        self.counters = AgentCounters()
        self.uploader = Uploader(
            spool=self.spool,
            client=PortalClient(records_url=portal.url + RECORDS_PATH, token=token, timeout=5),
            counters=self.counters,
            backoff_base=0.01,
            backoff_max=0.05,
            **uploader_options,
        )
        self.key = key
        self.recorder = self.recorder_with(key)
        self.published: list[str] = []

    def recorder_with(self, key: bytes) -> Recorder:
        return Recorder(
            spool=self.spool,
            key=key,
            owner=OWNER,
            robot=ROBOT,
            counters=self.counters,
            on_spooled=self.uploader.notify,
        )

    def publish(self, count: int, recorder: Recorder | None = None) -> list[int]:
        seqs = []
        for _ in range(count):
            text = f"message {len(self.published)}"
            self.published.append(text)
            seqs.append(
                (recorder or self.recorder).record(
                    String(data=text), topic="/chatter", ros_type="std_msgs/String"
                )
            )
        return seqs


@pytest.fixture
def robot(tmp_path, owner_key, portal):
    robot = Robot(tmp_path, owner_key, portal, batch_size=10)
    yield robot
    robot.spool.close()


def _texts(portal) -> list[str]:
    return [record.record["K"]["data"] for record in portal.records]


def test_batches_go_out_in_order_and_leave_the_spool_once_confirmed(robot, portal):
    seqs = robot.publish(23)

    assert robot.uploader.drain() is EMPTY

    assert [(upload.status, len(upload.seqs)) for upload in portal.uploads] == [
        (201, 10),
        (201, 10),
        (201, 3),
    ]
    assert portal.seqs == seqs
    assert _texts(portal) == robot.published
    assert len(robot.spool) == 0
    assert robot.counters.snapshot() == {"spooled": 23, "sent": 23, "failed": 0, "dropped": 0}
    first = portal.records[0]
    assert first.record == chatter_record("message 0", first.header["time"])


def test_a_batch_is_also_bounded_in_bytes(tmp_path, owner_key, portal):
    robot = Robot(tmp_path, owner_key, portal, batch_size=50, batch_max_bytes=1000)
    robot.publish(9)  # about 400 bytes each

    robot.uploader.drain()

    assert [len(upload.seqs) for upload in portal.uploads] == [2, 2, 2, 2, 1]


def test_portal_down_spool_grows_then_everything_arrives_once_in_order(robot, portal):
    portal.stop()
    robot.uploader._flush_interval = 0.05
    robot.uploader.start()
    robot.publish(25)
    wait_until(lambda: robot.uploader._failures >= 3, 5, "retries against the closed port")
    assert len(robot.spool) == 25
    assert robot.counters.sent == 0

    portal.start()
    wait_until(lambda: robot.counters.sent == 25, 10, "delivery after the portal came back")
    robot.publish(7)  # and the flow goes on
    wait_until(lambda: robot.counters.sent == 32, 10, "delivery of new messages")
    robot.uploader.stop(flush_timeout=1)

    assert _texts(portal) == robot.published
    assert portal.seqs == sorted(set(portal.seqs))
    assert len(robot.spool) == 0
    assert robot.counters.snapshot() == {"spooled": 32, "sent": 32, "failed": 0, "dropped": 0}


def test_overload_and_unavailability_are_retried_without_losing_the_batch(robot, portal):
    robot.publish(3)
    portal.fail_next(503, times=2)
    portal.fail_next(429, retry_after="0")

    assert [robot.uploader.deliver_next() for _ in range(4)] == [RETRY, RETRY, RETRY, DELIVERED]
    assert _texts(portal) == robot.published
    assert robot.counters.failed == 0


def test_backoff_grows_exponentially_with_jitter_up_to_a_cap_and_honours_retry_after(
    tmp_path, owner_key, portal
):
    robot = Robot(tmp_path, owner_key, portal)
    robot.uploader._backoff_base, robot.uploader._backoff_max = 0.5, 30.0
    delays = [robot.uploader.next_backoff() for _ in range(10)]
    for attempt, delay in enumerate(delays):
        ceiling = min(30.0, 0.5 * 2**attempt)
        assert ceiling / 2 <= delay <= ceiling
    assert len({round(d, 9) for d in delays[-3:]}) == 3  # jittered, not one fixed value

    robot.publish(1)
    portal.fail_next(429, retry_after="7")
    assert robot.uploader.deliver_next() is RETRY
    robot.uploader._failures = 0
    assert robot.uploader.next_backoff() == 7.0


def test_a_lost_confirmation_does_not_make_a_duplicate(robot, portal, caplog):
    seqs = robot.publish(4)
    portal.lose_next()  # stored, but the 201 never reaches the agent

    assert robot.uploader.deliver_next() is RETRY
    assert len(robot.spool) == 4
    with caplog.at_level(logging.WARNING):
        assert robot.uploader.drain() is EMPTY

    assert portal.seqs == seqs  # each once
    assert [upload.status for upload in portal.uploads] == [None, 409, 409, 409, 409, 409]
    assert "already has seq" in caplog.text
    assert robot.counters.sent == 4
    assert len(robot.spool) == 0


def test_other_data_under_a_used_seq_is_refused_not_counted_delivered(
    tmp_path, owner_key, portal, robot, caplog
):
    """Someone with the robot's token and key uploaded first, under the same seqs: the robot's
    own envelopes are other data under seqs the portal holds, refused and kept, never counted
    delivered in silence."""
    thief = Robot(tmp_path / "thief", owner_key, portal)
    thief.publish(3)
    assert thief.uploader.drain() is EMPTY
    robot.publish(2)

    with caplog.at_level(logging.ERROR):
        robot.uploader.drain()

    assert [upload.status for upload in portal.uploads[-2:]] == [409, 409]
    assert robot.counters.sent == 0
    assert robot.counters.failed == 2
    assert "someone else uploads with its token and key" in caplog.text
    assert _texts(portal) == thief.published  # the robot's own data was not taken for stored


def test_after_a_crash_the_stored_part_of_a_batch_is_acknowledged_and_the_rest_sent(robot, portal):
    robot.publish(3)
    portal.store([item.envelope for item in robot.spool.peek(3)])  # reached the portal before
    robot.publish(3)

    assert robot.uploader.drain() is EMPTY
    assert _texts(portal) == robot.published
    assert [upload.status for upload in portal.uploads] == [409, 409, 409, 409, 201, 201, 201]

    robot.publish(4)  # back to whole batches
    robot.uploader.drain()
    assert [len(upload.seqs) for upload in portal.uploads[-1:]] == [4]
    assert robot.counters.sent == 10


def test_a_poison_envelope_is_moved_to_rejected_and_the_others_delivered(robot, portal):
    good_before = robot.publish(2)
    (bad,) = robot.publish(1, recorder=robot.recorder_with(sm4.generate_key()))
    good_after = robot.publish(2)

    assert robot.uploader.drain() is EMPTY

    assert portal.seqs == good_before + good_after
    assert [upload.status for upload in portal.uploads] == [403, 201, 201, 403, 201, 201]
    rejected = robot.spool.directory / "rejected" / f"{bad:020d}.env"
    assert rejected.exists()
    reason = rejected.with_name(rejected.name + ".json").read_text()
    assert '"status": 403' in reason
    assert '"error": "unknown_key"' in reason
    assert robot.counters.snapshot() == {"spooled": 5, "sent": 4, "failed": 1, "dropped": 0}


def test_a_wrong_token_keeps_everything_for_later(tmp_path, owner_key, portal, caplog):
    robot = Robot(tmp_path, owner_key, portal, token="not-the-token")
    robot.publish(3)

    with caplog.at_level(logging.ERROR):
        assert robot.uploader.deliver_next() is RETRY

    assert len(robot.spool) == 3
    assert not any((robot.spool.directory / "rejected").iterdir())
    assert "HTTP 401 not_authenticated" in caplog.text


def test_a_partial_batch_goes_out_after_the_flush_interval(tmp_path, owner_key, portal):
    robot = Robot(tmp_path, owner_key, portal, batch_size=50, flush_interval=0.1)
    robot.uploader.start()
    robot.publish(3)
    wait_until(lambda: robot.counters.sent == 3, 5, "a flush of a partial batch")
    robot.uploader.stop(flush_timeout=1)
    assert [len(upload.seqs) for upload in portal.uploads] == [3]


def test_stop_sends_what_is_queued(tmp_path, owner_key, portal):
    robot = Robot(tmp_path, owner_key, portal, batch_size=50, flush_interval=60)
    robot.uploader.start()
    robot.publish(7)
    robot.uploader.stop(flush_timeout=2)
    assert _texts(portal) == robot.published
    assert len(robot.spool) == 0


# --- a key rotation (issue 14): nothing goes to rejected/ -------------------------------------


def test_envelopes_refused_after_a_rotation_are_resealed_under_the_new_key(tmp_path, portal):
    """The portal took a new key while the robot was offline (the stand-in refuses the old
    one outright): the paired agent fetches the new key, re-seals what it spooled and sends
    it again; nothing is rejected, and what it records next is sealed under the new key."""
    old_key, new_key = portal.key, sm4.generate_key()
    keyring = Keyring.of_one(old_key)
    fetched = []

    def fetch_new_key() -> bool:  # KeyUpdater's part that talks to the portal is tested e2e
        fetched.append(keyring.add(new_key))
        return True

    robot = Robot(
        tmp_path, old_key, portal, batch_size=4, keyring=keyring, key_updater=fetch_new_key
    )
    robot.recorder = Recorder(
        spool=robot.spool, keyring=keyring, owner=OWNER, robot=ROBOT, counters=robot.counters
    )
    try:
        seqs = robot.publish(6)
        portal.key = new_key  # the rotation
        assert robot.uploader.drain() is EMPTY
        robot.publish(2)
        assert robot.uploader.drain() is EMPTY
    finally:
        robot.spool.close()
    assert fetched[0] is True
    assert portal.seqs[:6] == seqs
    assert _texts(portal) == robot.published
    assert robot.counters.failed == 0
    assert not list((tmp_path / "spool" / "rejected").iterdir())
    assert {record.envelope[4:12] for record in portal.records} == {envelope.key_id(new_key)}


def test_a_refused_key_is_kept_when_the_new_key_cannot_be_fetched(tmp_path, portal):
    keyring = Keyring.of_one(portal.key)
    robot = Robot(
        tmp_path, portal.key, portal, batch_size=4, keyring=keyring, key_updater=lambda: None
    )
    try:
        robot.publish(3)
        portal.key = sm4.generate_key()
        assert robot.uploader.drain() is RETRY
        assert len(robot.spool) == 3
        assert robot.counters.failed == 0
    finally:
        robot.spool.close()

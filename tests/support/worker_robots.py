"""Robots for tests with real workers (tests/support/harness.py): robots whose owners the workers
have registered on chain, and a robot that keeps uploading while a test breaks something."""

import threading
import time
import uuid
from collections.abc import Iterator
from contextlib import contextmanager

from django.db import connection

from accounts.models import ChainState, Owner, Robot
from accounts.services.owners import owner_create
from accounts.services.pairing import robot_pairing_answer, robot_pairing_request
from accounts.services.robots import robot_create
from sharing.models import Record
from sharing.services.uploads import record_create
from smcrypto import sm2, sm4
from tests.support.harness import wait_for
from tests.support.robot_setup import TEST_PASSWORD, RobotSetup


def paired_robot(owner: Owner, key: bytes, *, name: str | None = None) -> RobotSetup:
    """A robot of `owner` (whose SM4 key is `key`) paired as the agent pairs, once the workers
    have registered its key on chain; its SM2 key pair and the token pairing gave it."""
    private_key, public_key = sm2.generate_keypair()
    pairing, _secret = robot_pairing_request(
        name=name or f"robot-{uuid.uuid4().hex[:6]}", public_key=public_key
    )
    pairing = robot_pairing_answer(owner=owner, code=pairing.code, approve=True, actor=owner.user)
    token = sm2.decrypt(private_key, pairing.token_sm2).decode("ascii")
    wait_for(
        lambda: Robot.objects.get(pk=pairing.robot_id).key_chain_state == ChainState.CONFIRMED,
        timeout=120,
        what="the robot's key registered on chain by the workers",
    )
    robot = Robot.objects.get(pk=pairing.robot_id)
    return RobotSetup(owner, key, robot, token, (private_key, public_key))


def registered_robots(count: int) -> list[RobotSetup]:
    """`count` owners with a robot each, once the workers have registered every owner on
    chain."""
    setups = []
    for _ in range(count):
        key = sm4.generate_key()
        owner = owner_create(
            username=f"owner-{uuid.uuid4().hex[:8]}", password=TEST_PASSWORD, sm4_key=key
        )
        robot, token = robot_create(owner=owner, name="robot")
        setups.append(RobotSetup(owner, key, robot, token))
    ids = [s.owner.pk for s in setups]
    wait_for(
        lambda: Owner.objects.filter(pk__in=ids, chain_state=ChainState.CONFIRMED).count() == count,
        timeout=120,
        what=f"{count} owners registered on chain by the workers",
    )
    for setup in setups:
        setup.owner.refresh_from_db()
    return setups


@contextmanager
def uploading(setup: RobotSetup, *, every: float = 0.2) -> Iterator[list[Record]]:
    """The robot uploads a record every `every` seconds (in a thread, through the upload
    service) while the block runs; yields the list of what it uploaded, growing."""
    stop_uploading = threading.Event()
    uploaded: list[Record] = []

    def upload() -> None:
        seq = 1
        try:
            while not stop_uploading.is_set():
                uploaded.append(record_create(robot=setup.robot, data=setup.seal(seq)))
                seq += 1
                time.sleep(every)
        finally:
            # This thread's own database connection: left open, it keeps the test database
            # from being dropped at the end of the run.
            connection.close()

    uploader = threading.Thread(target=upload)
    uploader.start()
    try:
        yield uploaded
    finally:
        stop_uploading.set()
        uploader.join()

"""Actions on owners, their keys and robots. Each is one transaction; chain work is queued
on commit (outbox), and the worker's tasks carry it out through the `*_on_chain` services
below: registration (fund, enroll, register) and key rotation."""

import secrets
from collections.abc import Sequence
from datetime import timedelta

from django.conf import settings
from django.contrib.auth import get_user_model
from django.contrib.auth.password_validation import validate_password
from django.contrib.auth.validators import UnicodeUsernameValidator
from django.core.exceptions import ValidationError
from django.db import IntegrityError, transaction
from django.utils import timezone
from eth_account import Account

from accounts import keywrap
from accounts.agent_config import Topic
from accounts.errors import (
    InvalidKeyMaterial,
    InvalidRobotName,
    InvalidUsername,
    KeyAlreadyUsed,
    RobotNameTaken,
    UsernameTaken,
    WeakPassword,
)
from accounts.models import (
    DEFAULT_TOPICS,
    ChainState,
    Owner,
    OwnerKey,
    Robot,
    validate_robot_topics,
)
from accounts.selectors import eoa_purpose, owner_eoa_account, robot_token_hash, sm4_key_purpose
from chainworker.services import chain_client, operator_account, operator_ensure_funded
from chainworker.work import ChainWorkNotReady, exclusive
from core.outbox import enqueue
from smcrypto import key_commitment, key_id, sm4

ROBOT_TOKEN_BYTES = 32


def owner_create(*, username: str, password: str, sm4_key: bytes) -> Owner:
    """A new owner with a custodial EOA; funding, enrolment and registration follow on chain."""
    User = get_user_model()
    try:
        UnicodeUsernameValidator()(username)
    except ValidationError as exc:
        raise InvalidUsername(" ".join(exc.messages)) from None
    if not username or len(username) > 150:
        raise InvalidUsername("a username has 1 to 150 characters")
    _check_sm4_key(sm4_key)
    candidate = User(username=username)
    try:
        validate_password(password, candidate)
    except ValidationError as exc:
        raise WeakPassword(list(exc.messages)) from None

    eoa = Account.create()
    try:
        with transaction.atomic():
            user = User.objects.create_user(username=username, password=password)
            owner = Owner.objects.create(user=user, eoa_address=eoa.address, eoa_key_wrapped=b"")
            owner.eoa_key_wrapped = keywrap.wrap(bytes(eoa.key), purpose=eoa_purpose(owner.pk))
            owner.save(update_fields=["eoa_key_wrapped"])
            _owner_key_add(owner, sm4_key)
            transaction.on_commit(lambda: enqueue("accounts.tasks.owner_register", owner.pk))
    except IntegrityError:
        raise UsernameTaken(f"the username {username!r} is taken") from None
    return owner


def key_rotate(*, owner: Owner, sm4_key: bytes) -> OwnerKey:
    """Make `sm4_key` the owner's current key; older keys stay to read older records."""
    _check_sm4_key(sm4_key)
    with transaction.atomic():
        if owner.keys.filter(key_id=key_id(sm4_key).hex()).exists():
            raise KeyAlreadyUsed("this key was used by this owner before: choose a new one")
        owner.keys.filter(is_current=True).update(is_current=False, retired_at=timezone.now())
        new_key = _owner_key_add(owner, sm4_key)
        transaction.on_commit(lambda: enqueue("accounts.tasks.key_rotate", new_key.pk))
    return new_key


def robot_create(
    *, owner: Owner, name: str, topics: Sequence[Topic] | None = None
) -> tuple[Robot, str]:
    """A robot and its API token; the token is returned once and only its hash is kept.

    `topics` (default: DEFAULT_TOPICS) are kept for the robot's agent config; topics that
    are not a valid list of {name, type} raise django.core.exceptions.ValidationError.
    """
    name = name.strip()
    if not name or len(name) > 100:
        raise InvalidRobotName("a robot name has 1 to 100 characters")
    chosen = DEFAULT_TOPICS if topics is None else topics
    topic_list = [{"name": topic.name, "type": topic.type} for topic in chosen]
    validate_robot_topics(topic_list)
    token = secrets.token_urlsafe(ROBOT_TOKEN_BYTES)
    try:
        with transaction.atomic():
            robot = Robot.objects.create(
                owner=owner,
                name=name,
                topics=topic_list,
                token_hash=robot_token_hash(token),
                token_prefix=token[:8],
            )
    except IntegrityError:
        raise RobotNameTaken(f"{owner} already has a robot named {name!r}") from None
    return robot, token


def robot_token_revoke(*, robot: Robot) -> Robot:
    """The robot's token stops working at once; its records stay."""
    Robot.objects.filter(pk=robot.pk).update(is_active=False, revoked_at=timezone.now())
    robot.refresh_from_db()
    return robot


# --- on chain (run by the worker) ---------------------------------------------------------


def owner_register_on_chain(*, owner_id: int) -> Owner:
    """Fund the owner's EOA, enroll it (operator) and register its key commitment."""
    with exclusive(f"owner:{owner_id}", timeout=settings.CHAIN_RECEIPT_TIMEOUT * 3 + 30):
        owner = Owner.objects.select_related("user").get(pk=owner_id)
        if owner.chain_state == ChainState.CONFIRMED:
            return owner
        client = chain_client()
        operator = operator_account()
        operator_ensure_funded(client=client, operator=operator)
        first_key = owner.keys.order_by("created_at").first()
        # Each step is written as soon as it is on chain, so progress pages move step by step.
        step = Owner.objects.filter(pk=owner.pk).update
        funding = settings.CHAIN_EOA_FUNDING_WEI
        if client.balance(owner.eoa_address) < funding // 2:
            step(fund_tx=client.transfer(operator, owner.eoa_address, funding).tx_hash)
        if not client.is_enrolled(owner.eoa_address):
            step(enroll_tx=client.enroll(operator, owner.eoa_address).tx_hash)
        if not client.is_registered(owner.eoa_address):
            commitment = bytes.fromhex(first_key.commitment.removeprefix("0x"))
            result = client.register(owner_eoa_account(owner), commitment)
            step(register_tx=result.tx_hash, registered_block=result.block_number)
            OwnerKey.objects.filter(pk=first_key.pk).update(
                chain_state=ChainState.CONFIRMED,
                tx_hash=result.tx_hash,
                block_number=result.block_number,
            )
        else:
            OwnerKey.objects.filter(pk=first_key.pk).update(chain_state=ChainState.CONFIRMED)
        step(chain_state=ChainState.CONFIRMED, chain_error="")
        owner.refresh_from_db()
    # Keys rotated (and records uploaded) while registration was pending can go now.
    for key in owner.keys.filter(chain_state=ChainState.PENDING):
        enqueue("accounts.tasks.key_rotate", key.pk)
    enqueue("sharing.tasks.records_anchor", owner.pk)
    return owner


def key_rotate_on_chain(*, owner_key_id: int) -> OwnerKey:
    """Put a rotated key's commitment on chain (`rotateKey`), in the order keys were made."""
    key = OwnerKey.objects.select_related("owner").get(pk=owner_key_id)
    owner = key.owner
    if key.chain_state == ChainState.CONFIRMED:
        return key
    if owner.chain_state != ChainState.CONFIRMED:
        raise ChainWorkNotReady(f"{owner} is not registered on chain yet")
    if owner.keys.filter(created_at__lt=key.created_at, chain_state=ChainState.PENDING).exists():
        raise ChainWorkNotReady(f"an older key of {owner} is not on chain yet")
    with exclusive(f"owner:{owner.pk}", timeout=settings.CHAIN_RECEIPT_TIMEOUT + 30):
        client = chain_client()
        commitment = bytes.fromhex(key.commitment.removeprefix("0x"))
        fields: dict[str, object] = {"chain_state": ChainState.CONFIRMED}
        if client.commitment_of(owner.eoa_address) != commitment:
            result = client.rotate_key(owner_eoa_account(owner), commitment)
            fields.update(tx_hash=result.tx_hash, block_number=result.block_number)
        OwnerKey.objects.filter(pk=key.pk).update(**fields)
    key.refresh_from_db()
    return key


def chain_work_sweep() -> dict[str, int]:
    """Queue again registrations and key rotations pending for longer than ANCHOR_STALE_AFTER
    (a lost message, a dead worker); their tasks are idempotent."""
    cutoff = timezone.now() - timedelta(seconds=settings.ANCHOR_STALE_AFTER)
    registrations = list(
        Owner.objects.filter(chain_state=ChainState.PENDING, created_at__lt=cutoff).values_list(
            "pk", flat=True
        )
    )
    for owner_id in registrations:
        enqueue("accounts.tasks.owner_register", owner_id)
    keys = list(
        OwnerKey.objects.filter(
            chain_state=ChainState.PENDING,
            created_at__lt=cutoff,
            owner__chain_state=ChainState.CONFIRMED,
        ).values_list("pk", flat=True)
    )
    for key_pk in keys:
        enqueue("accounts.tasks.key_rotate", key_pk)
    return {"registrations": len(registrations), "keys": len(keys)}


def _owner_key_add(owner: Owner, sm4_key: bytes) -> OwnerKey:
    kid = key_id(sm4_key).hex()
    return OwnerKey.objects.create(
        owner=owner,
        key_id=kid,
        key_wrapped=keywrap.wrap(sm4_key, purpose=sm4_key_purpose(owner.pk, kid)),
        commitment="0x" + key_commitment(owner.eoa_address, sm4_key).hex(),
        is_current=True,
        chain_state=ChainState.PENDING,
    )


def _check_sm4_key(sm4_key: bytes) -> None:
    if not isinstance(sm4_key, bytes) or len(sm4_key) != sm4.KEY_SIZE:
        raise InvalidKeyMaterial("an SM4 key is 16 bytes (32 hex digits)")
    if sm4_key == bytes(sm4.KEY_SIZE):
        raise InvalidKeyMaterial("an all-zero SM4 key is not a key")

"""Actions on owners, their keys and robots. Each is one transaction; chain work is queued
on commit (outbox), and the worker's tasks carry it out through the `*_on_chain` services
below: registration (fund, enroll, register) and key rotation."""

import logging
import re
import secrets
import uuid
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass
from datetime import timedelta
from itertools import pairwise

from django.conf import settings
from django.contrib.auth import get_user_model
from django.contrib.auth.base_user import AbstractBaseUser
from django.contrib.auth.password_validation import validate_password
from django.contrib.auth.validators import UnicodeUsernameValidator
from django.core.exceptions import ValidationError
from django.db import IntegrityError, transaction
from django.db.models import F, Max, Sum
from django.utils import timezone
from eth_account import Account
from eth_account.signers.local import LocalAccount

from accounts import keywrap
from accounts.agent_config import Topic
from accounts.errors import (
    IdentityMismatch,
    InvalidKeyMaterial,
    InvalidOwnerToken,
    InvalidPairingRequest,
    InvalidRetention,
    InvalidRobotName,
    InvalidUsername,
    KeyAlreadyUsed,
    MasterKeyRefused,
    PairingAlreadyAnswered,
    PairingAlreadyCollected,
    PairingExpired,
    PairingNotFound,
    PairingRefused,
    PairingSecretMismatch,
    RobotNameTaken,
    UsernameTaken,
    WeakPassword,
    WrongPassword,
)
from accounts.events import account_event_record
from accounts.identity import owner_identity_check
from accounts.models import (
    DEFAULT_TOPICS,
    RETENTION_MAX_DAYS,
    AccountEvent,
    Approval,
    ChainActivity,
    ChainState,
    EoaFunding,
    Owner,
    OwnerKey,
    OwnerToken,
    Robot,
    RobotPairing,
    validate_robot_topics,
)
from accounts.selectors import (
    OWNER_TOKEN_PREFIX,
    eoa_purpose,
    owner_eoa_account,
    owner_key_bytes,
    owner_key_current,
    pairing_code_normalize,
    robot_token_hash,
    sm4_key_purpose,
)
from chainworker.chain import AuthROSChain, ChainError, InsufficientFunds
from chainworker.gas import LowBalance
from chainworker.models import OperatorAlert
from chainworker.services import (
    chain_client,
    chain_work_check,
    operator_account,
    operator_alert_raise,
    operator_alert_resolve,
    operator_balance_check,
    operator_ensure_funded,
)
from chainworker.work import ChainWorkNotReady, exclusive
from core.outbox import enqueue
from smcrypto import InvalidKey, key_commitment, key_id, sm2, sm4

logger = logging.getLogger(__name__)
security_log = logging.getLogger("authros.security")

ROBOT_TOKEN_BYTES = 32


def owner_create(
    *, username: str, password: str, sm4_key: bytes, self_signup: bool = False
) -> Owner:
    """A new owner with a custodial EOA; funding, enrolment and registration follow on chain.

    `self_signup`: made on the open registration page, not by an operator's command; with
    SIGNUP_APPROVAL such an owner awaits an operator's approval (owner_approve) and nothing
    is done on chain until then.
    """
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
    awaiting = self_signup and settings.SIGNUP_APPROVAL
    try:
        with transaction.atomic():
            user = User.objects.create_user(username=username, password=password)
            owner = Owner.objects.create(
                user=user,
                eoa_address=eoa.address,
                eoa_key_wrapped=b"",
                approval=Approval.AWAITING if awaiting else Approval.APPROVED,
            )
            owner.eoa_key_wrapped = keywrap.wrap(bytes(eoa.key), purpose=eoa_purpose(owner.pk))
            owner.save(update_fields=["eoa_key_wrapped"])
            _owner_key_add(owner, sm4_key)
            if not awaiting:
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


def robot_token_revoke(*, robot: Robot, actor: AbstractBaseUser | None = None) -> Robot:
    """The robot's token stops working at once; its records stay. The owner's security page
    shows who revoked it (`actor`: the owner or an operator)."""
    with transaction.atomic():
        revoked = Robot.objects.filter(pk=robot.pk, is_active=True).update(
            is_active=False, revoked_at=timezone.now()
        )
        if revoked:
            account_event_record(
                owner=robot.owner,
                kind=AccountEvent.Kind.ROBOT_TOKEN_REVOKED,
                actor=actor,
                detail={"robot": robot.name, "robot_id": str(robot.pk)},
            )
    robot.refresh_from_db()
    return robot


def robot_retention_set(*, robot: Robot, days: int | None, actor: AbstractBaseUser) -> Robot:
    """Keep the robot's records `days` days after their capture (None: until deleted by
    hand); older ones are deleted by sharing.deletion.retention_apply, the beat task. The
    owner's security page shows the change."""
    if days is not None and (
        isinstance(days, bool) or not isinstance(days, int) or not 1 <= days <= RETENTION_MAX_DAYS
    ):
        raise InvalidRetention(
            f"keep records 1 to {RETENTION_MAX_DAYS} days, or leave it empty to keep them forever"
        )
    with transaction.atomic():
        before = Robot.objects.select_for_update().get(pk=robot.pk).retention_days
        if before != days:
            Robot.objects.filter(pk=robot.pk).update(retention_days=days)
            account_event_record(
                owner=robot.owner,
                kind=AccountEvent.Kind.RETENTION_SET,
                actor=actor,
                detail={
                    "robot": robot.name,
                    "before": _retention_text(before),
                    "now": _retention_text(days),
                },
            )
    robot.refresh_from_db()
    return robot


def _retention_text(days: int | None) -> str:
    return "forever" if days is None else f"{days} days"


def owner_password_confirm(*, owner: Owner, password: str) -> None:
    """WrongPassword unless `password` is the owner's: a sensitive action asks for it again
    (a stolen session cookie is not enough)."""
    if not isinstance(password, str) or not owner.user.check_password(password):
        raise WrongPassword("this is not your password: nothing was changed")


def owner_close(*, owner: Owner, actor: AbstractBaseUser) -> Owner:
    """The accounts side of deleting an account (sharing.deletion.account_delete does the
    records and grants, in the same transaction): no sign-in any more (inactive, no usable
    password), every owner API token and robot token revoked, pairing requests refused.

    The owner and user rows stay: the username stays taken, so nobody can register it and
    pass for the owner (envelopes and grants name owners by username), and the tombstones of
    the records keep naming their owner. The EOA's wrapped key stays too: the revocations of
    the owner's grants are signed with it (the chain keeps the EOA and its history forever).
    """
    now = timezone.now()
    with transaction.atomic():
        locked = Owner.objects.select_for_update().get(pk=owner.pk)
        if locked.deleted_at is not None:
            return locked
        Owner.objects.filter(pk=owner.pk).update(deleted_at=now)
        user = owner.user
        user.is_active = False
        user.set_unusable_password()
        user.save(update_fields=["is_active", "password"])
        tokens = OwnerToken.objects.filter(owner=owner, revoked_at__isnull=True).update(
            revoked_at=now
        )
        robots = Robot.objects.filter(owner=owner, is_active=True).update(
            is_active=False, revoked_at=now
        )
        RobotPairing.objects.filter(
            owner=owner, state__in=[RobotPairing.State.PENDING, RobotPairing.State.APPROVED]
        ).update(state=RobotPairing.State.REFUSED, token_sm2="", answered_at=now)
        account_event_record(
            owner=owner,
            kind=AccountEvent.Kind.ACCOUNT_DELETED,
            actor=actor,
            detail={"api_tokens_revoked": tokens, "robot_tokens_revoked": robots},
        )
    security_log.info("owner %s deleted their account", owner.pk)
    owner.refresh_from_db()
    return owner


# --- on chain (run by the worker) ---------------------------------------------------------


def owner_register_on_chain(*, owner_id: int) -> Owner:
    """Fund the owner's EOA, enroll it (operator) and register its key commitment."""
    with exclusive(f"owner:{owner_id}", timeout=settings.CHAIN_RECEIPT_TIMEOUT * 3 + 30):
        owner = Owner.objects.select_related("user").get(pk=owner_id)
        if owner.chain_state == ChainState.CONFIRMED or owner.approval != Approval.APPROVED:
            return owner
        chain_work_check()  # nothing goes to a reset chain
        client = chain_client()
        operator = operator_account()
        operator_ensure_funded(client=client, operator=operator)
        first_key = owner.keys.order_by("created_at").first()
        # Each step is written as soon as it is on chain, so progress pages move step by step.
        step = Owner.objects.filter(pk=owner.pk).update
        funding = eoa_funding_amount(fee_per_gas=client.fee_per_gas())
        if funding and client.balance(owner.eoa_address) < funding // 2:
            fund_tx = _eoa_fund(owner=owner, client=client, operator=operator, amount_wei=funding)
            if fund_tx is None:
                owner.refresh_from_db()
                return owner  # over the funding budget: it waits; chain_work_sweep retries it
            step(fund_tx=fund_tx)
            chain_activity_record(owner=owner, kind=ChainActivity.Kind.FUNDED, tx_hash=fund_tx)
        if not client.is_enrolled(owner.eoa_address):
            enrolled = client.enroll(operator, owner.eoa_address)
            step(enroll_tx=enrolled.tx_hash)
            chain_activity_record(
                owner=owner,
                kind=ChainActivity.Kind.ENROLLED,
                tx_hash=enrolled.tx_hash,
                block_number=enrolled.block_number,
            )
        if not client.is_registered(owner.eoa_address):
            commitment = bytes.fromhex(first_key.commitment.removeprefix("0x"))
            result = client.register(owner_eoa_account(owner), commitment)
            step(register_tx=result.tx_hash, registered_block=result.block_number)
            chain_activity_record(
                owner=owner,
                kind=ChainActivity.Kind.REGISTERED,
                tx_hash=result.tx_hash,
                block_number=result.block_number,
                detail={"key_id": first_key.key_id, "commitment": first_key.commitment},
            )
            OwnerKey.objects.filter(pk=first_key.pk).update(
                chain_state=ChainState.CONFIRMED,
                tx_hash=result.tx_hash,
                block_number=result.block_number,
            )
        else:
            OwnerKey.objects.filter(pk=first_key.pk).update(chain_state=ChainState.CONFIRMED)
        step(chain_state=ChainState.CONFIRMED, chain_error="")
        owner.refresh_from_db()
    # Read back what is on chain now: the commitment of the key the portal holds.
    owner_identity_check(owner=owner, fresh=True)
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
    chain_work_check()  # nothing goes to a reset chain
    with exclusive(f"owner:{owner.pk}", timeout=settings.CHAIN_RECEIPT_TIMEOUT + 30):
        client = chain_client()
        commitment = bytes.fromhex(key.commitment.removeprefix("0x"))
        fields: dict[str, object] = {"chain_state": ChainState.CONFIRMED}
        if client.commitment_of(owner.eoa_address) != commitment:
            try:
                result = client.rotate_key(owner_eoa_account(owner), commitment)
            except InsufficientFunds:
                # Waits for gas, using up nothing: the task retries and the sweep queues it again.
                enqueue("accounts.tasks.owner_top_up", owner.pk)
                raise
            fields.update(tx_hash=result.tx_hash, block_number=result.block_number)
            chain_activity_record(
                owner=owner,
                kind=ChainActivity.Kind.KEY_ROTATED,
                tx_hash=result.tx_hash,
                block_number=result.block_number,
                detail={"key_id": key.key_id, "commitment": key.commitment},
            )
        OwnerKey.objects.filter(pk=key.pk).update(**fields)
    key.refresh_from_db()
    owner_identity_check(owner=owner, fresh=True)
    return key


def chain_work_sweep() -> dict[str, int]:
    """Queue again registrations and key rotations pending for longer than ANCHOR_STALE_AFTER
    (a lost message, a dead worker, a registration waiting for the funding budget); their
    tasks are idempotent. Sign-ups awaiting or refused an operator's approval stay put."""
    cutoff = timezone.now() - timedelta(seconds=settings.ANCHOR_STALE_AFTER)
    registrations = list(
        Owner.objects.filter(
            chain_state=ChainState.PENDING, created_at__lt=cutoff, approval=Approval.APPROVED
        ).values_list("pk", flat=True)
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
    return {"registrations": len(registrations), "keys": len(keys), "top_ups": gas_sweep()}


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


# A key an owner chose is recovered offline from its public commitment if it can be guessed,
# so a key must look drawn at random. How often each rule refuses 16 uniformly random bytes:
# fewer than 8 distinct byte values (one repeated byte included): 6.4e-13; a pattern of at
# most 8 bytes repeated: 5.4e-20; 12 or more of the 15 steps between neighbouring bytes equal
# (counting up or down: 000102..., 00112233..., ffeedd...): 1.5e-24; every byte printable
# ASCII or NUL (a word or phrase, maybe zero-padded): (96/256)**16 = 1.5e-7. So one random key
# in 6.5 million is refused (sm4_key_generate draws another); a looser text rule, such as 12
# of 16 bytes printable, would refuse one in 430.
KEY_MIN_DISTINCT_BYTES = 8
KEY_MAX_PATTERN_BYTES = 8
KEY_MAX_EQUAL_STEPS = 11
_KEY_TEXT_BYTES = frozenset(range(0x20, 0x7F)) | {0}
_LET_THE_PORTAL_GENERATE = (
    "; let the portal generate your key instead (the registration and key pages do by "
    "default; `manage.py owner_create` does without --sm4-key-hex)"
)


def _check_sm4_key(sm4_key: bytes) -> None:
    if not isinstance(sm4_key, bytes) or len(sm4_key) != sm4.KEY_SIZE:
        raise InvalidKeyMaterial("an SM4 key is 16 bytes (32 hex digits)")
    weakness = _sm4_key_weakness(sm4_key)
    if weakness is not None:
        raise InvalidKeyMaterial(weakness + _LET_THE_PORTAL_GENERATE)


def _sm4_key_weakness(key: bytes) -> str | None:
    """Why `key` looks chosen rather than random, or None."""
    if key == bytes(len(key)):
        return "an all-zero SM4 key is not a key"
    if len(set(key)) < KEY_MIN_DISTINCT_BYTES:
        return f"this key has fewer than {KEY_MIN_DISTINCT_BYTES} different byte values"
    for period in range(1, KEY_MAX_PATTERN_BYTES + 1):
        if key[period:] == key[:-period]:
            return f"this key repeats a pattern of {period} bytes"
    steps = Counter((b - a) % 256 for a, b in pairwise(key))
    if steps.most_common(1)[0][1] > KEY_MAX_EQUAL_STEPS:
        return "this key counts up or down (a sequence of bytes)"
    if all(byte in _KEY_TEXT_BYTES for byte in key):
        return "this key is text (printable characters), not random bytes"
    return None


# --- account events: what the owner sees on the security page -------------------------------


def owner_active_set(*, owner: Owner, active: bool, actor: AbstractBaseUser) -> bool:
    """An operator deactivates (no sign-in, no session) or reactivates an owner's account;
    the owner sees who did it. Returns whether anything changed."""
    User = get_user_model()
    with transaction.atomic():
        changed = User.objects.filter(pk=owner.user_id, is_active=not active).update(
            is_active=active
        )
        if changed:
            account_event_record(
                owner=owner,
                kind=AccountEvent.Kind.ADMIN_ACTION,
                actor=actor,
                detail={"action": "reactivated" if active else "deactivated", "field": "is_active"},
            )
    owner.user.refresh_from_db(fields=["is_active"])
    return bool(changed)


# --- owner API tokens: an owner's scripts read and share with scopes, never a robot's token ---

OWNER_TOKEN_BYTES = 32
OWNER_TOKEN_MAX_LIFETIME = timedelta(days=365)
# A token's last use is written at most this often, so that most requests write nothing.
OWNER_TOKEN_USE_RESOLUTION = timedelta(minutes=1)


def owner_token_create(
    *, owner: Owner, name: str, scopes: Sequence[str], expires_in: timedelta
) -> tuple[OwnerToken, str]:
    """An API token for the owner's scripts; the key is returned once and only its hash kept.

    `scopes` is a non-empty subset of OwnerToken.Scope; the token expires after `expires_in`,
    at most OWNER_TOKEN_MAX_LIFETIME. The owner's security page shows it was made.
    """
    name = name.strip() if isinstance(name, str) else ""
    if not name or len(name) > 100 or "\x00" in name:
        raise InvalidOwnerToken("a token name has 1 to 100 characters")
    allowed = OwnerToken.Scope.values
    if isinstance(scopes, str) or not scopes or not set(scopes) <= set(allowed):
        raise InvalidOwnerToken(f"scopes are one or more of: {', '.join(allowed)}")
    if not isinstance(expires_in, timedelta) or not (
        timedelta(0) < expires_in <= OWNER_TOKEN_MAX_LIFETIME
    ):
        raise InvalidOwnerToken(
            f"a token expires within {OWNER_TOKEN_MAX_LIFETIME.days} days of being made"
        )
    key = OWNER_TOKEN_PREFIX + secrets.token_urlsafe(OWNER_TOKEN_BYTES)
    with transaction.atomic():
        token = OwnerToken.objects.create(
            owner=owner,
            name=name,
            token_hash=robot_token_hash(key),
            token_prefix=key[:12],
            scopes=[scope for scope in allowed if scope in scopes],
            expires_at=timezone.now() + expires_in,
        )
        account_event_record(
            owner=owner,
            kind=AccountEvent.Kind.TOKEN_CREATED,
            actor=owner.user,
            detail=_owner_token_detail(token),
        )
    return token, key


def owner_token_revoke(*, token: OwnerToken, actor: AbstractBaseUser | None) -> OwnerToken:
    """The token stops working at once (401); what it granted is
    sharing.services.grants_revoke_made_with's to take back."""
    with transaction.atomic():
        revoked = OwnerToken.objects.filter(pk=token.pk, revoked_at__isnull=True).update(
            revoked_at=timezone.now()
        )
        if revoked:
            account_event_record(
                owner=token.owner,
                kind=AccountEvent.Kind.TOKEN_REVOKED,
                actor=actor,
                detail=_owner_token_detail(token),
            )
    token.refresh_from_db()
    return token


def owner_token_mark_used(*, token: OwnerToken) -> None:
    """Note that the token was just used, at most once per OWNER_TOKEN_USE_RESOLUTION."""
    now = timezone.now()
    last = token.last_used_at
    if last is not None and now - last < OWNER_TOKEN_USE_RESOLUTION:
        return
    OwnerToken.objects.filter(pk=token.pk).exclude(
        last_used_at__gt=now - OWNER_TOKEN_USE_RESOLUTION
    ).update(last_used_at=now)
    token.last_used_at = now


def _owner_token_detail(token: OwnerToken) -> dict[str, object]:
    """What the security page says about a token: never its key."""
    return {
        "token": token.name,
        "token_id": token.pk,
        "prefix": token.token_prefix,
        "scopes": list(token.scopes),
        "expires_at": token.expires_at.isoformat(),
    }


# --- sign-up: funding within a budget, operator approval, generated keys ----------------------

# What a registration waiting for the funding budget shows its owner (Owner.chain_error).
FUNDING_BUDGET_SPENT = (
    "waiting: the portal has funded as many new accounts as it may for now; registration "
    "continues by itself later"
)
# The subject of the operator alert raised while the funding budget is spent.
FUNDING_BUDGET_SUBJECT = "eoa-funding-budget"


def eoa_funding_amount(*, fee_per_gas: int, gas: int | None = None) -> int:
    """Wei a new EOA is sent: CHAIN_EOA_FUNDING_GAS (or `gas`) gas units at `fee_per_gas` (the
    chain's current max fee per gas), at most CHAIN_EOA_FUNDING_WEI; 0 on a zero-gas chain."""
    units = settings.CHAIN_EOA_FUNDING_GAS if gas is None else gas
    return min(units * max(fee_per_gas, 0), settings.CHAIN_EOA_FUNDING_WEI)


def eoa_funding_spent() -> int:
    """Wei sent (or about to be) to owners' EOAs within the last SIGNUP_FUNDING_PERIOD."""
    since = timezone.now() - timedelta(seconds=settings.SIGNUP_FUNDING_PERIOD)
    total = EoaFunding.objects.filter(created_at__gte=since).aggregate(total=Sum("amount_wei"))
    return int(total["total"] or 0)


def _eoa_fund(
    *,
    owner: Owner,
    client: AuthROSChain,
    operator: LocalAccount,
    amount_wei: int,
    reason: str = "registration",
) -> str | None:
    """Send `amount_wei` to the owner's EOA if the period's funding budget allows it, recorded
    in EoaFunding; the transaction hash, or None (nothing sent) when the budget is spent (an
    operator alert says so). Raises InsufficientFunds (and alerts) when the operator cannot pay."""
    # A row of an earlier attempt that did not get its transaction out is reused, not re-counted.
    entry = owner.fundings.filter(tx_hash="").order_by("created_at").first()
    if entry is None:
        # One worker at a time between the sum and the new row, across processes and owners.
        with exclusive("eoa-funding-budget", timeout=30, wait=30):
            spent = eoa_funding_spent()
            budget = settings.SIGNUP_FUNDING_BUDGET_WEI
            if spent + amount_wei > budget:
                logger.warning(
                    "EOA funding budget spent (%s of %s wei in %.0f s): %s of %s waits",
                    spent,
                    budget,
                    settings.SIGNUP_FUNDING_PERIOD,
                    reason,
                    owner,
                )
                if reason == "registration":
                    Owner.objects.filter(pk=owner.pk).update(chain_error=FUNDING_BUDGET_SPENT)
                operator_alert_raise(
                    kind=OperatorAlert.Kind.FUNDING_BUDGET_SPENT,
                    subject=FUNDING_BUDGET_SUBJECT,
                    detail={
                        "spent_wei": str(spent),
                        "budget_wei": str(budget),
                        "period_seconds": settings.SIGNUP_FUNDING_PERIOD,
                        "waiting": f"{reason} of {owner}",
                    },
                )
                return None
            entry = EoaFunding.objects.create(owner=owner, amount_wei=amount_wei, reason=reason)
            operator_alert_resolve(
                kind=OperatorAlert.Kind.FUNDING_BUDGET_SPENT, subject=FUNDING_BUDGET_SUBJECT
            )
    try:
        tx_hash = client.transfer(operator, owner.eoa_address, int(entry.amount_wei)).tx_hash
    except InsufficientFunds:
        operator_alert_raise(
            kind=OperatorAlert.Kind.OPERATOR_CANNOT_PAY,
            subject=operator.address,
            detail={"amount_wei": str(entry.amount_wei), "to": owner.eoa_address},
        )
        raise
    operator_alert_resolve(kind=OperatorAlert.Kind.OPERATOR_CANNOT_PAY, subject=operator.address)
    EoaFunding.objects.filter(pk=entry.pk).update(tx_hash=tx_hash)
    return tx_hash


def owner_approve(*, owner: Owner, operator: AbstractBaseUser) -> bool:
    """An operator lets a sign-up awaiting approval onto the chain: its registration is queued.
    Returns whether it was awaiting."""
    with transaction.atomic():
        changed = Owner.objects.filter(pk=owner.pk, approval=Approval.AWAITING).update(
            approval=Approval.APPROVED, approved_by=operator, approved_at=timezone.now()
        )
        if changed:
            account_event_record(
                owner=owner, kind=AccountEvent.Kind.SIGNUP_APPROVED, actor=operator
            )
            transaction.on_commit(lambda: enqueue("accounts.tasks.owner_register", owner.pk))
    owner.refresh_from_db()
    return bool(changed)


def owner_refuse(*, owner: Owner, operator: AbstractBaseUser) -> bool:
    """An operator refuses a sign-up awaiting approval: the account is deactivated (no sign-in)
    and nothing goes on chain. Returns whether it was awaiting."""
    with transaction.atomic():
        changed = Owner.objects.filter(pk=owner.pk, approval=Approval.AWAITING).update(
            approval=Approval.REFUSED, approved_by=operator, approved_at=timezone.now()
        )
        if changed:
            get_user_model().objects.filter(pk=owner.user_id).update(is_active=False)
            account_event_record(owner=owner, kind=AccountEvent.Kind.SIGNUP_REFUSED, actor=operator)
    owner.refresh_from_db()
    owner.user.refresh_from_db(fields=["is_active"])
    return bool(changed)


def sm4_key_generate() -> bytes:
    """A new random SM4 key that owner_create and key_rotate take (a random key that looks
    chosen, one in millions, is drawn again)."""
    while True:
        key = sm4.generate_key()
        if _sm4_key_weakness(key) is None:
            return key


# --- the audit page's index of owners' transactions ----------------------------------------


def chain_activity_record(
    *,
    owner: Owner,
    kind: str,
    tx_hash: str,
    block_number: int | None = None,
    counterpart: Owner | None = None,
    record_count: int = 0,
    detail: dict[str, object] | None = None,
) -> ChainActivity | None:
    """Index a transaction of the owner's whose receipt the worker saw, for the audit page.

    Idempotent: a retry that sees the same transaction again updates its row (one per
    owner, kind and transaction) and keeps the time it was first seen. Nothing is written
    for an empty `tx_hash` (nothing was sent).
    """
    if not tx_hash:
        return None
    if kind not in ChainActivity.Kind.values:
        raise ValueError(f"unknown chain activity kind {kind!r}")
    activity, _created = ChainActivity.objects.update_or_create(
        owner=owner,
        kind=kind,
        tx_hash=tx_hash,
        defaults={
            "block_number": block_number,
            "counterpart": counterpart,
            "record_count": record_count,
            "detail": detail or {},
        },
    )
    return activity


# --- the portal's own secrets ------------------------------------------------------------------


def secrets_verify() -> list[str]:
    """What keeps the portal from serving with its secrets: a master key (KEK) that is
    missing, unreadable or not the one the owner keys were wrapped with (accounts.keywrap
    keeps its fingerprint on the first check)."""
    try:
        keywrap.kek_verify()
    except MasterKeyRefused as exc:
        return [str(exc)]
    return []


# --- gas: owners' EOAs kept able to pay --------------------------------------------------------

# EoaFunding.reason of a top-up (registration's is "registration").
TOPUP_REASON = "top-up"
# Owners whose balance one sweep or one admin page reads at most (one node call each).
GAS_SCAN_MAX = 200
# Owners who sent a transaction this recently are the ones the sweep keeps topped up.
GAS_SCAN_ACTIVE = timedelta(hours=1)


@dataclass(frozen=True)
class EoaGas:
    """An owner's EOA balance against the top-up threshold at the chain's current fee."""

    owner: Owner
    balance_wei: int
    fee_per_gas: int

    @property
    def zero_gas(self) -> bool:
        return self.fee_per_gas == 0

    @property
    def low_below_wei(self) -> int:
        """CHAIN_EOA_TOPUP_BELOW_GAS gas units at the current fee; 0 on a zero-gas chain."""
        return settings.CHAIN_EOA_TOPUP_BELOW_GAS * max(self.fee_per_gas, 0)

    @property
    def low(self) -> bool:
        return self.balance_wei < self.low_below_wei


def owner_eoa_gas(*, owner: Owner, client: AuthROSChain | None = None) -> EoaGas:
    """What the owner's EOA holds and whether that is low; raises ChainError if the node is away."""
    client = client or chain_client()
    return EoaGas(owner, client.balance(owner.eoa_address), client.fee_per_gas())


def owners_low_on_gas(*, active_since: timedelta | None = None) -> list[EoaGas]:
    """Registered owners whose EOA is below the top-up threshold (none on a zero-gas chain):
    the GAS_SCAN_MAX most recently active, or only those who sent within `active_since`."""
    client = chain_client()
    fee = client.fee_per_gas()
    if fee == 0:
        return []
    owners = Owner.objects.select_related("user").filter(chain_state=ChainState.CONFIRMED)
    if active_since is not None:
        owners = owners.filter(chain_activity__at__gte=timezone.now() - active_since)
    owners = owners.annotate(last_sent=Max("chain_activity__at")).order_by(
        F("last_sent").desc(nulls_last=True), "-pk"
    )
    gas = (EoaGas(owner, client.balance(owner.eoa_address), fee) for owner in owners[:GAS_SCAN_MAX])
    return [one for one in gas if one.low]


def owner_top_up(*, owner_id: int) -> EoaFunding | None:
    """Top a registered owner's EOA up to CHAIN_EOA_TOPUP_GAS gas units when it holds less than
    CHAIN_EOA_TOPUP_BELOW_GAS, within the funding budget; the funding row, or None when nothing
    was needed (a zero-gas chain, enough left) or the budget is spent (an operator alert says
    so; the sweep asks again). Queued by chain work that met InsufficientFunds, and the sweep."""
    chain_work_check()  # no ether goes to a reset or stalled chain
    # One top-up of an owner at a time (the one that waited finds the balance topped up); not
    # the owner's registration lock, which a sender meeting InsufficientFunds may hold.
    with exclusive(f"eoa-topup:{owner_id}", timeout=settings.CHAIN_RECEIPT_TIMEOUT + 30):
        owner = Owner.objects.filter(pk=owner_id, chain_state=ChainState.CONFIRMED).first()
        if owner is None:
            return None  # registration funds it
        client = chain_client()
        gas = owner_eoa_gas(owner=owner, client=client)
        if not gas.low:
            return None
        target = eoa_funding_amount(fee_per_gas=gas.fee_per_gas, gas=settings.CHAIN_EOA_TOPUP_GAS)
        if target <= gas.balance_wei:
            return None
        operator = operator_account()
        operator_ensure_funded(client=client, operator=operator)
        tx_hash = _eoa_fund(
            owner=owner,
            client=client,
            operator=operator,
            amount_wei=target - gas.balance_wei,
            reason=TOPUP_REASON,
        )
        if tx_hash is None:
            return None
        chain_activity_record(
            owner=owner,
            kind=ChainActivity.Kind.FUNDED,
            tx_hash=tx_hash,
            detail={"reason": TOPUP_REASON},
        )
    logger.info("topped up %s (%s) with %s wei", owner, owner.eoa_address, target - gas.balance_wei)
    return owner.fundings.filter(tx_hash=tx_hash).first()


def gas_sweep() -> int:
    """Queue a top-up for owners who sent lately and are low, and alert while the operator
    itself is low; how many were queued. Nothing when the node does not answer."""
    try:
        operator_balance_check()
        low = owners_low_on_gas(active_since=GAS_SCAN_ACTIVE)
    except ChainError as exc:
        logger.warning("gas sweep skipped: the chain did not answer (%s)", exc)
        return 0
    for gas in low:
        enqueue("accounts.tasks.owner_top_up", gas.owner.pk)
    return len(low)


# --- reconciliation with the chain (run by sharing.reconcile) ---------------------------------


def owners_reconcile(*, owners: Sequence[Owner]) -> dict[str, int]:
    """Put back on chain what the chain lost of these owners' registration and keys.

    A confirmed owner the chain does not know as enrolled and registered goes back to pending
    with its keys, and owner_register is queued (it skips what is on chain, then its later keys
    are rotated in order). When the commitment on chain is an older key's than the newest
    confirmed one (rotations lost), the keys after it go back to pending and key_rotate is
    queued for each. Any other commitment on chain is the identity check's business: it is
    called, and records the mismatch.
    """
    client = chain_client()
    counts = {"owners_checked": 0, "registrations_lost": 0, "rotations_lost": 0, "mismatches": 0}
    for owner in owners:
        if owner.chain_state != ChainState.CONFIRMED:
            continue
        counts["owners_checked"] += 1
        eoa = owner.eoa_address
        if not (client.is_enrolled(eoa) and client.is_registered(eoa)):
            _owner_registration_redo(client, owner)
            counts["registrations_lost"] += 1
            continue
        on_chain = "0x" + client.commitment_of(eoa).hex()
        keys = list(owner.keys.order_by("created_at", "pk"))
        commitments = [key.commitment.lower() for key in keys]
        confirmed = [i for i, key in enumerate(keys) if key.chain_state == ChainState.CONFIRMED]
        if not confirmed or on_chain == commitments[confirmed[-1]]:
            continue
        if on_chain in commitments[: confirmed[-1]]:
            _key_rotations_redo(client, owner, keys[commitments.index(on_chain) + 1 :])
            counts["rotations_lost"] += 1
            continue
        try:
            owner_identity_check(owner=owner, fresh=True)
        except IdentityMismatch:
            counts["mismatches"] += 1
    return counts


def owners_chain_reset() -> list[int]:
    """After a chain reset: every approved owner goes back to pending registration with all its
    keys (fund, enroll, register, then the later keys rotated in order), owner_register queued
    on commit for each. Returns their ids."""
    owners = Owner.objects.filter(approval=Approval.APPROVED).order_by("pk")
    ids = list(owners.values_list("pk", flat=True))
    with transaction.atomic():
        Owner.objects.filter(pk__in=ids).update(
            chain_state=ChainState.PENDING,
            chain_error="",
            fund_tx="",
            enroll_tx="",
            register_tx="",
            registered_block=None,
        )
        OwnerKey.objects.filter(owner_id__in=ids).update(
            chain_state=ChainState.PENDING, tx_hash="", block_number=None
        )
        for owner_id in ids:
            transaction.on_commit(lambda o=owner_id: enqueue("accounts.tasks.owner_register", o))
    client = chain_client()
    for eoa in owners.values_list("eoa_address", flat=True):
        client.resync_nonce(eoa)  # counters of the chain before the reset mean nothing now
    return ids


def _owner_registration_redo(client: AuthROSChain, owner: Owner) -> None:
    with transaction.atomic():
        changed = Owner.objects.filter(pk=owner.pk, chain_state=ChainState.CONFIRMED).update(
            chain_state=ChainState.PENDING, chain_error=""
        )
        if changed:
            OwnerKey.objects.filter(owner=owner).update(chain_state=ChainState.PENDING)
            transaction.on_commit(lambda: enqueue("accounts.tasks.owner_register", owner.pk))
    # Counters of transactions the chain lost: the owner's, and the operator's (funding, enrolment).
    client.resync_nonce(owner.eoa_address)
    client.resync_nonce(operator_account().address)
    logger.warning("the chain lost the registration of %s: registering it again", owner)


def _key_rotations_redo(client: AuthROSChain, owner: Owner, keys: Sequence[OwnerKey]) -> None:
    with transaction.atomic():
        OwnerKey.objects.filter(pk__in=[key.pk for key in keys]).update(
            chain_state=ChainState.PENDING
        )
        for key in keys:
            transaction.on_commit(lambda k=key.pk: enqueue("accounts.tasks.key_rotate", k))
    client.resync_nonce(owner.eoa_address)
    logger.warning("the chain lost %d key rotation(s) of %s: rotating again", len(keys), owner)


def eoa_low_balances() -> list[LowBalance]:
    """Owners' EOAs below the top-up threshold, as the admin's chain status page lists them."""
    return [
        LowBalance(
            label=gas.owner.user.username,
            address=gas.owner.eoa_address,
            balance_wei=gas.balance_wei,
            below_wei=gas.low_below_wei,
        )
        for gas in owners_low_on_gas()
    ]


# --- robot pairing: the agent's SM2 key pair, the owner's approval, the key sent to it ----------

# Crockford's base32 (no I, L, O, U): read aloud and typed without confusion.
PAIRING_CODE_ALPHABET = "0123456789ABCDEFGHJKMNPQRSTVWXYZ"
PAIRING_CODE_LENGTH = 8  # 40 bits: not guessable within a request's life at the rate limits
PAIRING_SECRET_BYTES = 32
_WELL_FORMED_PUBLIC_KEY = re.compile(r"(04)?[0-9a-fA-F]{128}")


@dataclass(frozen=True)
class PairingAnswer:
    """What a robot that asks with its secret is told: still `pending` (with when its request
    expires), or `delivered` with its robot id, owner, token and the owner's current key, the
    last two SM2-encrypted to the robot's public key (C1C3C2 hex)."""

    pairing: RobotPairing
    token_sm2: str = ""
    key_id: str = ""
    key_sm2: str = ""


def robot_pairing_request(*, name: str, public_key: str) -> tuple[RobotPairing, str]:
    """A robot asks to be paired: the request and its secret, returned once (only its hash is
    kept). The robot shows the request's short code to its owner, who approves it with
    robot_pairing_answer; the robot collects the answer with robot_pairing_collect."""
    name = name.strip() if isinstance(name, str) else ""
    if not name or len(name) > 100 or "\x00" in name:
        raise InvalidPairingRequest("a robot name has 1 to 100 characters")
    try:
        public_key = sm2.public_key_normalize(public_key)
    except InvalidKey as exc:
        if isinstance(public_key, str) and _WELL_FORMED_PUBLIC_KEY.fullmatch(public_key):
            # Well formed but off the curve: an invalid-curve attack on whoever encrypts to it.
            security_log.warning("pairing request with an SM2 public key off the curve refused")
        raise InvalidPairingRequest(f"public_key: {exc}") from None
    secret = secrets.token_urlsafe(PAIRING_SECRET_BYTES)
    expires_at = timezone.now() + timedelta(seconds=settings.ROBOT_PAIRING_TTL)
    for _attempt in range(5):
        code = "".join(secrets.choice(PAIRING_CODE_ALPHABET) for _ in range(PAIRING_CODE_LENGTH))
        try:
            with transaction.atomic():
                pairing = RobotPairing.objects.create(
                    code=code,
                    secret_hash=robot_token_hash(secret),
                    name=name,
                    public_key=public_key,
                    expires_at=expires_at,
                )
        except IntegrityError:
            continue  # the code of another request, once in a trillion
        return pairing, secret
    raise RuntimeError("no free pairing code after 5 draws")


def robot_pairing_answer(
    *,
    owner: Owner,
    code: str,
    approve: bool,
    actor: AbstractBaseUser | None,
    name: str | None = None,
) -> RobotPairing:
    """The owner approves (a robot named `name`, default the requested name, with its token
    kept encrypted to the robot's SM2 key until collected) or refuses the pending request
    whose code the robot printed. A request is answered once: a second answer is refused."""
    wanted = pairing_code_normalize(code)
    with transaction.atomic():
        pairing = RobotPairing.objects.select_for_update().filter(code=wanted).first()
        if pairing is None or (pairing.owner_id not in (None, owner.pk)):
            raise PairingNotFound("no pairing request has this code: check what the robot printed")
        if pairing.state != RobotPairing.State.PENDING:
            raise PairingAlreadyAnswered(f"the request {pairing.code} was answered already")
        if pairing.is_expired:
            raise PairingExpired(
                f"the request {pairing.code} expired: run the robot's pair command again"
            )
        now = timezone.now()
        pairing.owner, pairing.answered_by, pairing.answered_at = owner, actor, now
        detail = {
            "name": pairing.name,
            "code": pairing.code,
            "fingerprint": sm2.fingerprint(pairing.public_key),
        }
        if not approve:
            pairing.state = RobotPairing.State.REFUSED
            pairing.save(update_fields=["state", "owner", "answered_by", "answered_at"])
            account_event_record(
                owner=owner,
                kind=AccountEvent.Kind.ROBOT_PAIRING_REFUSED,
                actor=actor,
                detail=detail,
            )
            return pairing
        robot, token = robot_create(owner=owner, name=name or pairing.name)
        Robot.objects.filter(pk=robot.pk).update(public_key=pairing.public_key, paired_at=now)
        pairing.robot = robot
        pairing.token_sm2 = sm2.encrypt(pairing.public_key, token.encode("ascii"))
        pairing.state = RobotPairing.State.APPROVED
        pairing.save(
            update_fields=["state", "owner", "robot", "token_sm2", "answered_by", "answered_at"]
        )
        account_event_record(
            owner=owner,
            kind=AccountEvent.Kind.ROBOT_PAIRED,
            actor=actor,
            detail={**detail, "robot_id": str(robot.pk), "robot": robot.name},
        )
    return pairing


def robot_pairing_collect(*, pairing_id: uuid.UUID, secret: str) -> PairingAnswer:
    """What the robot holding `secret` gets for its request: `pending`, or once, after the
    owner's approval, its token and the owner's current SM4 key, encrypted to its SM2 key.
    Refused: a wrong secret (the owner's security page is told when it is a paired robot's),
    an expired or refused request, a second collection, a robot unpaired meanwhile."""
    found = RobotPairing.objects.select_related("owner__user").filter(pk=pairing_id).first()
    if found is None:
        raise PairingNotFound("no pairing request has this id")
    if not secrets.compare_digest(found.secret_hash, robot_token_hash(secret)):
        _pairing_secret_mismatch(found)
    with transaction.atomic():
        # The row alone, its robot and owner read after the lock: joined in the locked query,
        # PostgreSQL would show them as they were before an approval it waited for.
        pairing = RobotPairing.objects.select_for_update().get(pk=found.pk)
        state = pairing.state
        if state == RobotPairing.State.PENDING:
            if pairing.is_expired:
                raise PairingExpired("the request expired unanswered: pair again")
            return PairingAnswer(pairing)
        if state == RobotPairing.State.REFUSED:
            raise PairingRefused("the owner refused this robot")
        if state == RobotPairing.State.DELIVERED:
            raise PairingAlreadyCollected(
                "this robot's token and key were collected already; if that was not this "
                "robot, unpair it in the portal and pair again"
            )
        robot = Robot.objects.select_related("owner__user").filter(pk=pairing.robot_id).first()
        if robot is None or not robot.is_active:
            raise PairingRefused("the owner unpaired this robot before it collected its key")
        pairing.robot, pairing.owner = robot, robot.owner
        key = owner_key_current(robot.owner)
        answer = PairingAnswer(
            pairing,
            token_sm2=pairing.token_sm2,
            key_id=key.key_id,
            key_sm2=sm2.encrypt(robot.public_key, owner_key_bytes(key)),
        )
        pairing.state = RobotPairing.State.DELIVERED
        pairing.token_sm2 = ""
        pairing.delivered_at = timezone.now()
        pairing.save(update_fields=["state", "token_sm2", "delivered_at"])
    return answer


# Unanswered requests are deleted this long after they expired; answered ones stay (the
# robots page lists the latest answers).
PAIRING_KEEP_EXPIRED = timedelta(days=1)


def robot_pairings_purge() -> int:
    """Delete the requests that expired unanswered more than PAIRING_KEEP_EXPIRED ago (anyone
    may make requests: they must not pile up); how many went."""
    cutoff = timezone.now() - PAIRING_KEEP_EXPIRED
    stale = RobotPairing.objects.filter(state=RobotPairing.State.PENDING, expires_at__lt=cutoff)
    deleted, _ = stale.delete()
    return deleted


def _pairing_secret_mismatch(pairing: RobotPairing) -> None:
    security_log.warning(
        "pairing request %s (%s): asked for with a wrong secret", pairing.code, pairing.state
    )
    if pairing.owner is not None:
        account_event_record(
            owner=pairing.owner,
            kind=AccountEvent.Kind.PAIRING_SECRET_MISMATCH,
            detail={"name": pairing.name, "code": pairing.code},
        )
    raise PairingSecretMismatch("this is not the secret of the robot that made the request")

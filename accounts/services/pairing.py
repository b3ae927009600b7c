"""Robot pairing: a robot asks with its SM2 public key and shows a short code, the owner
approves or refuses it, and the robot collects its token and the owner's current SM4 key,
both encrypted to its key, so that neither crosses the network in the clear.

Anyone may ask: a request is answered only to the secret of the robot that made it, and the
requests that expired unanswered are purged.
"""

import logging
import re
import secrets
import uuid
from dataclasses import dataclass
from datetime import timedelta

from django.conf import settings
from django.contrib.auth.base_user import AbstractBaseUser
from django.db import IntegrityError, transaction
from django.utils import timezone

from accounts.errors import (
    InvalidPairingRequest,
    PairingAlreadyAnswered,
    PairingAlreadyCollected,
    PairingExpired,
    PairingNotFound,
    PairingRefused,
    PairingSecretMismatch,
    RobotKeyTaken,
)
from accounts.events import account_event_record
from accounts.models import AccountEvent, ChainState, Owner, Robot, RobotPairing
from accounts.selectors import (
    owner_key_bytes,
    owner_key_current,
    pairing_code_normalize,
    robot_pairing_pending,
    robot_token_hash,
)
from accounts.services.robot_keys import robot_key_claimed_elsewhere, robot_key_disputed
from accounts.services.robots import robot_create, robot_name_problem
from core.outbox import enqueue
from smcrypto import InvalidKey, provenance, sm2

security_log = logging.getLogger("authros.security")

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
    problem = robot_name_problem(name)
    if problem is not None:
        raise InvalidPairingRequest(problem)
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
    whose code the robot printed. A request is answered once: a second answer is refused.
    Approving a request whose key is another owner's robot's is refused (RobotKeyTaken: the
    request stays pending, unanswered)."""
    wanted = pairing_code_normalize(code)
    if approve:
        _robot_key_unclaimed_check(owner=owner, code=wanted, actor=actor)
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
        # The robot signs with this key: its owner's EOA registers it on chain (robot_keys.py).
        Robot.objects.filter(pk=robot.pk).update(
            public_key=pairing.public_key,
            paired_at=now,
            key_hash=provenance.key_hash(pairing.public_key),
            key_chain_state=ChainState.PENDING,
        )
        transaction.on_commit(lambda: enqueue("accounts.tasks.robot_key_register", str(robot.pk)))
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


def _robot_key_unclaimed_check(*, owner: Owner, code: str, actor: AbstractBaseUser | None) -> None:
    """RobotKeyTaken if the pending request `code` names a key another owner has (issue 46:
    any grantee reads a robot's public key in a proof answer, and a key is its registering
    owner's). Told as a dispute (a SecurityEvent, the alert of the owner whose robot has the
    key) and on the approver's security page; the request itself is left as it was."""
    pairing = robot_pairing_pending(code=code)
    if pairing is None or pairing.owner_id not in (None, owner.pk):
        return  # the answer refuses it for what it is
    key_hash = provenance.key_hash(pairing.public_key)
    dispute = robot_key_claimed_elsewhere(owner=owner, key_hash=key_hash)
    if dispute is None:
        return
    security_log.warning(
        "pairing request %s: its key %s is another owner's robot key; %s's approval refused",
        pairing.code,
        key_hash,
        owner,
    )
    with transaction.atomic():
        account_event_record(
            owner=owner,
            kind=AccountEvent.Kind.ROBOT_KEY_TAKEN,
            actor=actor,
            detail={
                "name": pairing.name,
                "code": pairing.code,
                "fingerprint": sm2.fingerprint(pairing.public_key),
            },
        )
        robot_key_disputed(dispute)
    raise RobotKeyTaken(
        "this robot's key is already registered to another owner's robot, so it cannot be "
        "paired with your account: on the robot, remove its key file (robot.sm2) and run its "
        "pair command again to make a new key"
    )


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

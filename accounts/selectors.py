"""Reads about owners, including the unwrapping of their secrets for the services."""

import hashlib
from datetime import datetime

from django.db.models import Q, QuerySet
from eth_account import Account
from eth_account.signers.local import LocalAccount

from accounts import keywrap
from accounts.agent_config import Topic
from accounts.errors import RobotNotPaired
from accounts.keywrap import eoa_purpose, sm4_key_purpose
from accounts.models import (
    AccountEvent,
    ChainState,
    Owner,
    OwnerKey,
    OwnerToken,
    Robot,
    RobotPairing,
)
from chainworker.services import chain_client
from core.rows import FixedSelect
from smcrypto import sm2


def owner_eoa_account(owner: Owner) -> LocalAccount:
    """The owner's custodial EOA, unwrapped from the KEK (keep it in memory only)."""
    return Account.from_key(keywrap.unwrap(owner.eoa_key_wrapped, purpose=eoa_purpose(owner.pk)))


def owner_key_current(owner: Owner) -> OwnerKey:
    """The owner's current key; OwnerKey.DoesNotExist if it has none."""
    return _owned_by(owner, [_OWNER_KEY_CURRENT.get(owner.pk, True)])[0]


# Answers to a robot's uploads name its owner's current key in this header, so that a paired
# robot learns of a rotation on its next contact and fetches the key (`/api/v1/robot-key/`).
KEY_ID_HEADER = "AuthROS-Key-Id"


def owner_key_current_id(owner_id: int) -> str | None:
    """The key id of the owner's current key (one indexed read, nothing unwrapped)."""
    current = OwnerKey.objects.filter(owner_id=owner_id, is_current=True)
    return current.values_list("key_id", flat=True).first()


def owner_key_by_id(owner: Owner, key_id: str) -> OwnerKey | None:
    found = _owned_by(owner, _OWNER_KEY.fetch(owner.pk, key_id))
    return found[0] if found else None


def owner_key_bytes(owner_key: OwnerKey) -> bytes:
    """The SM4 key itself, unwrapped from the KEK."""
    purpose = sm4_key_purpose(owner_key.owner_id, owner_key.key_id)
    return keywrap.unwrap(owner_key.key_wrapped, purpose=purpose)


def owner_by_username(username: str) -> Owner | None:
    """The owner of that username, unless the account was deleted."""
    return (
        Owner.objects.select_related("user")
        .filter(user__username=username, deleted_at__isnull=True)
        .first()
    )


def owner_by_address(address: str) -> Owner | None:
    """The owner of that EOA, unless the account was deleted."""
    return (
        Owner.objects.select_related("user")
        .filter(eoa_address__iexact=address, deleted_at__isnull=True)
        .first()
    )


def owner_by_identifier(identifier: str) -> Owner | None:
    """The owner named by a username or, 0x-prefixed, an EOA address in any case; surrounding
    blanks are ignored. None for anything else, NUL characters included."""
    identifier = identifier.strip()
    if not identifier or "\x00" in identifier:
        # PostgreSQL refuses NUL characters in a query, which would be a 500.
        return None
    if identifier.lower().startswith("0x"):
        return owner_by_address(identifier)
    return owner_by_username(identifier)


def owner_balance_wei(owner: Owner) -> int:
    """The balance of the owner's EOA on chain; raises chainworker.errors.ChainError when the
    node cannot be asked."""
    return chain_client().balance(owner.eoa_address)


# Every robot request reads these: written once, not compiled per request (core/rows.py).
_ROBOT_BY_TOKEN = FixedSelect(
    Robot,
    related=("owner__user",),
    where="t0.token_hash = %s AND t0.is_active = %s",
    params_of=("token_hash", "is_active"),
)
_OWNER_KEYS = FixedSelect(
    OwnerKey,
    where="t0.owner_id = %s",
    params_of=("owner",),
    order_by="t0.created_at DESC, t0.id DESC",
)
_OWNER_KEY = FixedSelect(
    OwnerKey, where="t0.owner_id = %s AND t0.key_id = %s", params_of=("owner", "key_id")
)
_OWNER_KEY_CURRENT = FixedSelect(
    OwnerKey, where="t0.owner_id = %s AND t0.is_current = %s", params_of=("owner", "is_current")
)
_OWNER_TOKEN_BY_HASH = FixedSelect(
    OwnerToken, related=("owner__user",), where="t0.token_hash = %s", params_of=("token_hash",)
)
_KEY_OWNER = OwnerKey._meta.get_field("owner")


def _owned_by(owner: Owner, keys: list[OwnerKey]) -> list[OwnerKey]:
    """Keys read for `owner`, each knowing its owner (as `owner.keys` would), read no more."""
    for key in keys:
        _KEY_OWNER.set_cached_value(key, owner)
    return keys


def robot_by_token(token: str) -> Robot | None:
    """The active robot holding `token` (its owner and user joined); tokens are compared by
    their SHA-256 only."""
    return _ROBOT_BY_TOKEN.fetch_one(robot_token_hash(token), True)


def robot_token_hash(token: str) -> str:
    return hashlib.sha256(token.encode()).hexdigest()


def owner_for_user(user: object) -> Owner | None:
    """The owner behind a logged-in user; None for operators (admin-only accounts)."""
    if not getattr(user, "is_authenticated", False):
        return None
    return Owner.objects.select_related("user").filter(user=user).first()


def owner_keys(owner: Owner) -> list[OwnerKey]:
    """All keys of an owner, newest first (the current one, then retired ones)."""
    return _owned_by(owner, _OWNER_KEYS.fetch(owner.pk))


def robot_list_of(owner: Owner) -> list[Robot]:
    """An owner's robots: active ones first, then by name."""
    return list(owner.robots.order_by("-is_active", "name"))


def robot_count_active(owner: Owner) -> int:
    """The owner's robots whose token still works."""
    return owner.robots.filter(is_active=True).count()


def robot_any_of(owner: Owner) -> bool:
    """Whether the owner ever had a robot, unpaired ones included: until then the dashboard
    is the first step, pairing one."""
    return owner.robots.exists()


def robot_topics(robot: Robot) -> tuple[Topic, ...]:
    """The topics kept with the robot when it was added: what its agent config lists."""
    return tuple(Topic(name=entry["name"], type=entry["type"]) for entry in robot.topics)


def chain_backlog() -> dict[str, int]:
    """Registrations and key rotations not yet confirmed on chain (admin's chain status)."""
    return {
        "registrations": Owner.objects.filter(chain_state=ChainState.PENDING).count(),
        "keys": OwnerKey.objects.filter(chain_state=ChainState.PENDING).count(),
    }


def account_events_of(owner: Owner) -> QuerySet[AccountEvent]:
    """What happened to the owner's account, newest first (the security page)."""
    return AccountEvent.objects.filter(owner=owner).select_related("actor")


def account_events_to_notice(owner: Owner, *, since: datetime) -> QuerySet[AccountEvent]:
    """Events since `since` the owner should look at: made by someone else (an operator), or
    an alarm (an identity check that failed, a robot's pairing answer asked for by another)."""
    by_others = Q(actor__isnull=False) & ~Q(actor_id=owner.user_id)
    return account_events_of(owner).filter(
        by_others | Q(kind__in=AccountEvent.ALARM_KINDS), created_at__gte=since
    )


# --- owner API tokens -------------------------------------------------------------------------

# Every owner API token starts with this: told apart from a robot token at a glance, and by
# secret scanners.
OWNER_TOKEN_PREFIX = "aro_"  # noqa: S105 (a marker, not a secret)


def owner_token_by_key(key: str) -> OwnerToken | None:
    """The owner API token whose key is `key`, live or not; compared by SHA-256 only (the same
    hash as robot tokens)."""
    return _OWNER_TOKEN_BY_HASH.fetch_one(robot_token_hash(key))


def owner_token_list(owner: Owner) -> list[OwnerToken]:
    """An owner's API tokens, newest first, revoked and expired ones included."""
    return list(owner.api_tokens.order_by("-created_at", "-id"))


def owner_token_of(owner: Owner, token_id: int) -> OwnerToken | None:
    """One of the owner's API tokens; None for another owner's."""
    return owner.api_tokens.filter(pk=token_id).first()


# --- robot pairing ----------------------------------------------------------------------------

# How people may type a code: any case, with blanks or dashes, O for 0 and I or L for 1.
_CODE_LOOKALIKES = str.maketrans({"O": "0", "I": "1", "L": "1"})


def pairing_code_normalize(code: str) -> str:
    """A pairing code as stored, from what a person typed (`abcd-efgh` is `ABCDEFGH`)."""
    if not isinstance(code, str):
        return ""
    kept = "".join(char for char in code.upper() if char not in " -\t")
    return kept.translate(_CODE_LOOKALIKES)[:16]


def pairing_code_display(code: str) -> str:
    """A code as the robot prints it: two groups of four (`ABCD-EFGH`)."""
    return f"{code[:4]}-{code[4:]}" if len(code) == 8 else code


def robot_pairing_pending(*, code: str) -> RobotPairing | None:
    """The request waiting for an answer whose code is `code` (typed by an owner), unexpired."""
    wanted = pairing_code_normalize(code)
    if not wanted:
        return None
    pairing = RobotPairing.objects.filter(code=wanted, state=RobotPairing.State.PENDING).first()
    return None if pairing is None or pairing.is_expired else pairing


def robot_pairings_answered(owner: Owner, *, limit: int = 10) -> list[RobotPairing]:
    """The owner's latest answered pairing requests, newest first (the robots page)."""
    return list(owner.pairings.select_related("robot").order_by("-answered_at")[:limit])


def public_key_fingerprint(public_key: str) -> str:
    """What people compare with what the robot printed (smcrypto.sm2.fingerprint)."""
    return sm2.fingerprint(public_key)


def robot_key_for(robot: Robot) -> tuple[OwnerKey, str]:
    """The owner's current key and its bytes SM2-encrypted to the robot's paired public key
    (C1C3C2 hex); RobotNotPaired for a robot added by hand (no public key)."""
    if not robot.public_key:
        raise RobotNotPaired(
            "this robot was added by hand and has no SM2 key to send the owner's key to: "
            "pair it (python -m ros_agent pair), or update its key file by hand"
        )
    key = owner_key_current(robot.owner)
    return key, sm2.encrypt(robot.public_key, owner_key_bytes(key))

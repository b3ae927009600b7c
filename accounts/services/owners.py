"""Owners' accounts: sign-up, an operator's approval or refusal, deactivation and closing.

An owner is a user with a custodial EOA and a first SM4 key, made in one transaction; its
registration on chain (registration.py) is queued on commit, or once an operator approves a
self sign-up when SIGNUP_APPROVAL is on. An operator's approval, refusal or deactivation and
the owner closing the account are AccountEvents the owner sees on the security page.
"""

import logging

from django.conf import settings
from django.contrib.auth import get_user_model
from django.contrib.auth.base_user import AbstractBaseUser
from django.contrib.auth.password_validation import validate_password
from django.core.exceptions import ValidationError
from django.db import IntegrityError, transaction
from django.utils import timezone
from eth_account import Account

from accounts import keywrap
from accounts.errors import UsernameTaken, WeakPassword, WrongPassword
from accounts.events import account_event_record
from accounts.models import (
    AccountEvent,
    Approval,
    ChainState,
    Owner,
    OwnerToken,
    Robot,
    RobotPairing,
)
from accounts.selectors import eoa_purpose
from accounts.services.keys import owner_key_add, sm4_key_check
from accounts.services.robot_keys import robot_key_revocations_release
from accounts.usernames import username_check, username_skeleton
from core.outbox import enqueue

security_log = logging.getLogger("authros.security")

# Taken, or confusable with a taken name (accounts.usernames): which of the two is not said.
_TAKEN = "the username {username!r} is taken, or looks like one that is: choose another"


def owner_create(
    *, username: str, password: str, sm4_key: bytes, self_signup: bool = False
) -> Owner:
    """A new owner with a custodial EOA; funding, enrolment and registration follow on chain.

    `self_signup`: made on the open registration page, not by an operator's command; with
    SIGNUP_APPROVAL such an owner awaits an operator's approval (owner_approve) and nothing
    is done on chain until then.
    """
    User = get_user_model()
    username_check(username)
    skeleton = username_skeleton(username)
    if Owner.objects.filter(name_skeleton=skeleton).exists():
        raise UsernameTaken(_TAKEN.format(username=username))
    sm4_key_check(sm4_key)
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
                name_skeleton=skeleton,
                approval=Approval.AWAITING if awaiting else Approval.APPROVED,
            )
            owner.eoa_key_wrapped = keywrap.wrap(bytes(eoa.key), purpose=eoa_purpose(owner.pk))
            owner.save(update_fields=["eoa_key_wrapped"])
            owner_key_add(owner=owner, sm4_key=sm4_key)
            if not awaiting:
                transaction.on_commit(lambda: enqueue("accounts.tasks.owner_register", owner.pk))
    except IntegrityError:
        raise UsernameTaken(_TAKEN.format(username=username)) from None
    return owner


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


def owner_password_confirm(*, owner: Owner, password: str) -> None:
    """WrongPassword unless `password` is the owner's: a sensitive action asks for it again
    (a stolen session cookie is not enough)."""
    if not isinstance(password, str) or not owner.user.check_password(password):
        raise WrongPassword("this is not your password: nothing was changed")


def owner_close(*, owner: Owner, actor: AbstractBaseUser) -> Owner:
    """The accounts side of deleting an account (sharing.services.deletion.account_delete does the
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
        active_robots = Robot.objects.filter(owner=owner, is_active=True)
        # Their keys are revoked on chain too (robot_keys.py), as unpairing each would.
        keyed = active_robots.filter(
            key_chain_state__in=[ChainState.PENDING, ChainState.CONFIRMED], key_revoke_state=""
        ).update(key_revoke_state=ChainState.PENDING)
        robots = active_robots.update(is_active=False, revoked_at=now)
        if keyed:
            transaction.on_commit(lambda: robot_key_revocations_release(owner_id=owner.pk))
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

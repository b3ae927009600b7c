"""Grants: an owner gives, changes and takes back a grantee's access to their records.

Each action is one transaction: the portal enforces the grant's new state at once, writes a
GrantChange (which credential did it, the terms before and after), and queues on commit the
chain call (`sharing.tasks.grant_sync`, sharing/services/grant_chain.py) and the recheck of the
grantee's exports. A grant takes effect once `authorityGrant` is confirmed on chain; a
revocation is refused by the portal at once and `authorityRevoke` follows. What a grant
covers is a GrantTerms (sharing/grant_terms.py).
"""

from dataclasses import dataclass
from datetime import UTC

from django.db import IntegrityError, transaction
from django.utils import timezone

from accounts.models import ChainState, Owner, OwnerToken
from alerts.services import grant_revoked_alert
from core.outbox import enqueue
from sharing.errors import (
    AlreadyGranted,
    GranteeNotRegistered,
    NoGrant,
    NotRegisteredYet,
    RevocationPending,
    SelfGrant,
    TokenCannotWiden,
)
from sharing.grant_terms import ALL_RECORDS_FOREVER, MIN_GRANT_LIFETIME, GrantTerms
from sharing.models import Grant, GrantChange
from sharing.selectors.grants import grant_list_changed_with, grant_list_made_with

# Withdraws the exports whose requester may no longer view every record in them.
EXPORTS_RECHECK_TASK = "sharing.tasks.exports_recheck"


def _terms_fields(terms: GrantTerms) -> dict[str, object]:
    scope = terms.scope
    return {
        "scope_robots": [str(robot) for robot in scope.robots],
        "scope_topics": list(scope.topics),
        "scope_since": scope.since,
        "scope_until": scope.until,
        "expires_at": terms.expires_at,
    }


_ALREADY_GRANTED = (
    "{grantee} already has access. To change which records they may read, change that grant "
    "instead."
)
_REVOCATION_PENDING = (
    "{grantee} no longer has access, but the revocation is still on its way to the chain. "
    "Give access again once it is confirmed, in a few seconds."
)
_GRANT_EXPIRED = (
    "Your grant to {grantee} expired at {expiry:%Y-%m-%d %H:%M} UTC. To give access again, "
    "change that grant: a new expiry, or none."
)

# Which credential made a grant (Grant.made_with): a browser session, an owner API token, or an
# operator's command.
GRANT_MADE_WITH = ("session", "token", "cli")


def grant_create(
    *,
    owner: Owner,
    grantee: Owner,
    made_with: str = "session",
    made_with_token: OwnerToken | None = None,
    terms: GrantTerms = ALL_RECORDS_FOREVER,
) -> Grant:
    """Let `grantee` read `owner`'s records (those `terms` cover, until its expiry);
    authorityGrant (authorityGrantScoped for limited terms) is sent on commit.

    `made_with` says which credential asked, `made_with_token` which owner API token (exactly
    when `made_with` is "token"), so that revoking the token can take its grants back.
    """
    _credential_check(owner, made_with, made_with_token)
    grant_create_check(owner=owner, grantee=grantee)
    try:
        with transaction.atomic():
            live = Grant.objects.filter(owner=owner, grantee=grantee, status__in=Grant.LIVE)
            _refuse_second_grant(live.first(), grantee)
            grant = Grant.objects.create(
                owner=owner,
                grantee=grantee,
                made_with=made_with,
                made_with_token=made_with_token,
                **_terms_fields(terms),
            )
            _grant_change_record(
                grant, GrantChange.Kind.CREATED, made_with, made_with_token, None, terms
            )
            transaction.on_commit(lambda: enqueue("sharing.tasks.grant_sync", grant.pk))
    except IntegrityError:
        # A simultaneous grant for the same pair won the race (one live grant per pair).
        raise AlreadyGranted(_ALREADY_GRANTED.format(grantee=grantee)) from None
    return grant


def _credential_check(owner: Owner, made_with: str, made_with_token: OwnerToken | None) -> None:
    if made_with not in GRANT_MADE_WITH or (made_with == "token") != (made_with_token is not None):
        raise ValueError(f"made_with is one of {GRANT_MADE_WITH}, with a token for 'token' only")
    if made_with_token is not None and made_with_token.owner_id != owner.pk:
        raise ValueError("a grant is changed with a token of its own owner")


def _grant_change_record(
    grant: Grant,
    kind: str,
    made_with: str,
    token: OwnerToken | None,
    before: GrantTerms | None,
    after: GrantTerms | None,
) -> None:
    GrantChange.objects.create(
        grant=grant,
        kind=kind,
        made_with=made_with,
        token=token,
        terms_before=None if before is None else before.as_json(),
        terms_after=None if after is None else after.as_json(),
    )


def grant_create_check(*, owner: Owner, grantee: Owner) -> None:
    """Why `grant_create` would refuse this pair, raised before anything is written (the
    grants page asks it before its confirmation step): a grant to oneself, an owner or grantee
    not registered on chain yet, or a live grant of the pair (grant_create checks that again
    in its transaction)."""
    if grantee.pk == owner.pk:
        raise SelfGrant("You always see your own records: name another owner.")
    if owner.chain_state != ChainState.CONFIRMED:
        raise NotRegisteredYet(
            "Your account is not registered on the chain yet: try again in a minute."
        )
    if grantee.chain_state != ChainState.CONFIRMED:
        raise GranteeNotRegistered(
            f"{grantee}'s account is not registered on the chain yet: try again in a minute."
        )
    live = Grant.objects.filter(owner=owner, grantee=grantee, status__in=Grant.LIVE)
    _refuse_second_grant(live.first(), grantee)


def _refuse_second_grant(live: Grant | None, grantee: Owner) -> None:
    """AlreadyGranted if the pair has a live grant. One past its expiry gives nothing, but it
    is the pair's grant still: renewed by a change of its terms, which the refusal says. One
    being revoked gives nothing either, and blocks a new grant until the chain has the
    revocation (RevocationPending)."""
    if live is None:
        return
    if live.status == Grant.Status.REVOKING:  # no access since the revocation: not "has access"
        raise RevocationPending(_REVOCATION_PENDING.format(grantee=grantee))
    if live.shown_status == "expired":  # the pages' word for it: pending or active, past expiry
        expiry = live.expires_at.astimezone(UTC)
        raise AlreadyGranted(_GRANT_EXPIRED.format(grantee=grantee, expiry=expiry))
    raise AlreadyGranted(_ALREADY_GRANTED.format(grantee=grantee))


def grant_terms_change(
    *,
    owner: Owner,
    grantee: Owner,
    terms: GrantTerms,
    made_with: str = "session",
    made_with_token: OwnerToken | None = None,
) -> Grant:
    """Change what a live grant covers or when it expires: the portal enforces the new terms
    at once (the grant is pending until authorityGrantScoped, a new transaction, confirms
    them; meanwhile nothing of it can be read), and the chain follows.

    An owner API token may narrow any grant, but widen (more records, a later expiry or none)
    only a grant that it made and that no other credential has changed since: a stolen token
    cannot turn the owner's grant into "all records, never expires" (TokenCannotWiden).
    """
    _credential_check(owner, made_with, made_with_token)
    with transaction.atomic():
        grant = (
            Grant.objects.select_for_update()
            .filter(
                owner=owner, grantee=grantee, status__in=[Grant.Status.PENDING, Grant.Status.ACTIVE]
            )
            .first()
        )
        if grant is None:
            raise NoGrant(f"{grantee} has no access to change: give access first.")
        fields = _terms_fields(terms)
        if all(getattr(grant, name) == value for name, value in fields.items()):
            return grant  # the same terms: nothing to send
        before = GrantTerms.of(grant)
        if made_with_token is not None and not terms.within(before):
            _token_widening_check(grant, made_with_token, grantee)
        for name, value in fields.items():
            setattr(grant, name, value)
        grant.status = Grant.Status.PENDING
        grant.save(update_fields=[*fields, "status", "updated_at"])
        _grant_change_record(
            grant, GrantChange.Kind.CHANGED, made_with, made_with_token, before, terms
        )
        transaction.on_commit(lambda: enqueue("sharing.tasks.grant_sync", grant.pk))
        # The grantee's exports may hold records outside the new terms (exports/withdraw.py).
        transaction.on_commit(lambda: enqueue(EXPORTS_RECHECK_TASK, grant.grantee_id))
    return grant


def _token_widening_check(grant: Grant, token: OwnerToken, grantee: Owner) -> None:
    """TokenCannotWiden unless `grant` is wholly `token`'s work: made with it, and every
    change since made with it too."""
    others = grant.changes.exclude(made_with="token", token=token)
    if grant.made_with_token_id == token.pk and not others.exists():
        return
    raise TokenCannotWiden(
        f"An API token can narrow your grant to {grantee} but not widen it (more records, a "
        "later expiry or none): it was given or changed in another way. Widen it on the "
        "grants page."
    )


def grant_revoke(
    *,
    owner: Owner,
    grantee: Owner,
    made_with: str = "session",
    made_with_token: OwnerToken | None = None,
) -> Grant:
    """Take access away: refused by the portal at once, authorityRevoke sent on commit."""
    _credential_check(owner, made_with, made_with_token)
    with transaction.atomic():
        grant = (
            Grant.objects.select_for_update()
            .filter(owner=owner, grantee=grantee, status__in=Grant.LIVE)
            .first()
        )
        if grant is None or grant.status == Grant.Status.REVOKING:
            raise NoGrant(f"{grantee} has no access to revoke.")
        grant.status = Grant.Status.REVOKING
        grant.save(update_fields=["status", "updated_at"])
        _grant_change_record(
            grant,
            GrantChange.Kind.REVOKED,
            made_with,
            made_with_token,
            GrantTerms.of(grant),
            None,
        )
        grant_revoked_alert(grantee=grant.grantee, owner=owner)
        transaction.on_commit(lambda: enqueue("sharing.tasks.grant_sync", grant.pk))
        transaction.on_commit(lambda: enqueue(EXPORTS_RECHECK_TASK, grant.grantee_id))
    return grant


@dataclass(frozen=True)
class TokenGrantsUndone:
    """What grants_undo_made_with did: grants revoked, and grants given back their terms."""

    revoked: list[Grant]
    restored: list[Grant]


def grants_undo_made_with(
    *, token: OwnerToken, revoke_made: bool = True, restore_changed: bool = True
) -> TokenGrantsUndone:
    """Undo what `token` (revoked, perhaps stolen) did to its owner's grants, with the owner's
    session as the credential: every live grant it made is revoked (`revoke_made`), and every
    live grant it changed last is given back the terms it had before the token's changes
    (`restore_changed`), or revoked if those terms have expired meanwhile (docs/grants.md).
    Grants the token revoked stay revoked: giving access again is the owner's to do."""
    revoked: list[Grant] = []
    restored: list[Grant] = []
    owner = token.owner
    if restore_changed:
        for grant, before in grant_list_changed_with(token):
            terms = GrantTerms.from_json(before)
            try:
                if terms.expires_at is not None and terms.expires_at < (
                    timezone.now() + MIN_GRANT_LIFETIME
                ):
                    revoked.append(grant_revoke(owner=owner, grantee=grant.grantee))
                else:
                    restored.append(
                        grant_terms_change(owner=owner, grantee=grant.grantee, terms=terms)
                    )
            except NoGrant:
                continue  # revoked meanwhile by someone else
    if revoke_made:
        for grant in grant_list_made_with(token):
            try:
                revoked.append(grant_revoke(owner=owner, grantee=grant.grantee))
            except NoGrant:
                continue
    return TokenGrantsUndone(revoked=revoked, restored=restored)

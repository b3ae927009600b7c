"""Reads of grants: which grants let a viewer read now (in the portal: active, not
expired), an owner's grants given and received and their counts, the grants an owner API token
made or changed, and the owner a grant names (by username or address)."""

import uuid
from collections.abc import Iterable

from django.db.models import Q, QuerySet
from django.utils import timezone

from accounts.models import Owner, OwnerToken, Robot
from accounts.selectors import owner_by_identifier
from sharing.errors import OwnerAmbiguous, OwnerNotFound
from sharing.models import Grant, GrantChange, Record


def _unexpired() -> Q:
    return Q(expires_at__isnull=True) | Q(expires_at__gt=timezone.now())


def grant_list_live_received(viewer: Owner) -> QuerySet[Grant]:
    """The grants that let `viewer` read now, in the portal: active and not expired."""
    return Grant.objects.filter(_unexpired(), grantee=viewer, status=Grant.Status.ACTIVE)


def grant_live(*, owner_id: int, viewer: Owner) -> Grant | None:
    """The grant from the owner that lets `viewer` read now, in the portal, if any."""
    return grant_list_live_received(viewer).filter(owner_id=owner_id).first()


# An owner's grants to one viewer that ended, newest first, looked at for a record's.
_ENDED_GRANTS_LOOKED_AT = 5


def grant_ended_covering(viewer: Owner, record_id: uuid.UUID) -> Grant | None:
    """The grant that once let `viewer` read another owner's record and no longer does
    (revoked, or expired), when no live grant from that owner covers it; None otherwise, and
    for a record that is not there: only a viewer who could read it learns why it is gone."""
    record = (
        Record.objects.filter(pk=record_id)
        .exclude(owner=viewer)
        .only("id", "owner_id", "robot_id", "topic", "captured_at")
        .first()
    )
    if record is None or grant_live(owner_id=record.owner_id, viewer=viewer) is not None:
        return None
    ended = (
        Grant.objects.filter(owner_id=record.owner_id, grantee=viewer)
        .filter(
            Q(status__in=[Grant.Status.REVOKED, Grant.Status.REVOKING])
            | (Q(status=Grant.Status.ACTIVE) & ~_unexpired())
        )
        .select_related("owner__user")
        .order_by("-updated_at")
    )
    for grant in ended[:_ENDED_GRANTS_LOOKED_AT]:
        if grant.scope.apply(Record.objects.filter(pk=record.pk)).exists():
            return grant
    return None


def owners_granting(viewer: Owner) -> QuerySet[Owner]:
    """Owners whose grant to `viewer` is active (and not expired) in the portal."""
    return Owner.objects.filter(pk__in=grant_list_live_received(viewer).values("owner_id"))


def grant_list_given(owner: Owner) -> QuerySet[Grant]:
    return Grant.objects.filter(owner=owner).select_related("grantee__user", "made_with_token")


def grant_list_received(owner: Owner) -> QuerySet[Grant]:
    return Grant.objects.filter(grantee=owner).select_related("owner__user")


# A grant counts, on both sides alike, while it is active or being granted on chain; one being
# revoked does not: its owner has taken it back.
GRANTS_COUNTED = (Grant.Status.ACTIVE, Grant.Status.PENDING)


def grants_described(grants: Iterable[Grant]) -> list[Grant]:
    """The grants, each with `robot_names` (its scope's robots by name, in one query for all),
    for the pages that show what a grant covers."""
    grants = list(grants)
    ids = {robot for grant in grants for robot in grant.scope_robots}
    names = dict(Robot.objects.filter(pk__in=ids).values_list("pk", "name")) if ids else {}
    for grant in grants:
        grant.robot_names = sorted(
            names.get(uuid.UUID(robot), "(removed robot)") for robot in grant.scope_robots
        )
    return grants


def grant_count_given(owner: Owner) -> int:
    return grant_list_given(owner).filter(_unexpired(), status__in=GRANTS_COUNTED).count()


def grant_count_received(owner: Owner) -> int:
    return grant_list_received(owner).filter(_unexpired(), status__in=GRANTS_COUNTED).count()


def grant_topic_choices(owner: Owner, robots: list[Robot]) -> list[str]:
    """Topics a grant of the owner's may name: those of its records and those its robots'
    agents are set up for, sorted."""
    # order_by(): the model's ordering would join DISTINCT (every record's topic read)
    recorded = (
        Record.objects.filter(owner=owner).order_by().values_list("topic", flat=True).distinct()
    )
    configured = {entry["name"] for robot in robots for entry in robot.topics}
    return sorted({*recorded, *configured})


def grant_terms_of(owner: Owner, grantee: Owner) -> Grant | None:
    """The owner's grant to `grantee` whose terms may be changed (pending or active)."""
    return Grant.objects.filter(
        owner=owner, grantee=grantee, status__in=[Grant.Status.PENDING, Grant.Status.ACTIVE]
    ).first()


def grant_list_made_with(token: OwnerToken) -> QuerySet[Grant]:
    """Grants made with an owner API token that can still be revoked (pending or active)."""
    return (
        Grant.objects.filter(
            made_with_token=token, status__in=(Grant.Status.PENDING, Grant.Status.ACTIVE)
        )
        .select_related("owner__user", "grantee__user")
        .order_by("-created_at")
    )


def grant_list_changed_with(token: OwnerToken) -> list[tuple[Grant, dict]]:
    """Live grants (pending or active) not made with `token` whose last change was, each with
    the terms it had before that run of the token's changes (GrantChange.terms_before)."""
    changed = (
        Grant.objects.filter(
            owner_id=token.owner_id,
            status__in=(Grant.Status.PENDING, Grant.Status.ACTIVE),
            changes__token=token,
        )
        .exclude(made_with_token=token)
        .distinct()
        .select_related("owner__user", "grantee__user")
        .order_by("-created_at")
    )
    found = []
    for grant in changed:
        before = None
        for change in grant.changes.order_by("-id"):
            if change.token_id != token.pk or change.kind != GrantChange.Kind.CHANGED:
                break
            before = change.terms_before
        if before is not None:
            found.append((grant, before))
    return found


def owner_resolve(identifier: str) -> Owner:
    """An owner named by username or by EOA address; OwnerNotFound for anything else."""
    owner = owner_by_identifier(identifier)
    if owner is None:
        raise OwnerNotFound(
            f"There is no owner with the username or address “{identifier.strip()}”: check the "
            "spelling, or ask them for their username."
        )
    return owner


def grantee_resolve(identifier: str) -> Owner:
    """The owner a new grant is for (owner_resolve), and OwnerAmbiguous when named by a
    username that another live owner's looks like (two accounts made before usernames were
    held apart, accounts.usernames): only the address tells them apart then. Changing or
    revoking a grant names its grantee exactly and needs no such care."""
    owner = owner_resolve(identifier)
    by_name = not identifier.strip().lower().startswith("0x")
    if by_name and owner_lookalikes(owner).exists():
        raise OwnerAmbiguous(
            f"Another owner's username looks like “{owner.username}”: ask them for their "
            "0x address and give that instead."
        )
    return owner


def owner_lookalikes(owner: Owner) -> QuerySet[Owner]:
    """The other live owners whose usernames look like this one's (the same skeleton)."""
    return Owner.objects.filter(name_skeleton=owner.name_skeleton, deleted_at__isnull=True).exclude(
        pk=owner.pk
    )

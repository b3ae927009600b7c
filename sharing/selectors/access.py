"""Reads of the access log: views of an owner's records (incoming) and the owner's own views
of records shared with them (outgoing), as Verdict or Access rows, filtered, and the filters'
choices; a viewer's latest verdict on a record."""

import uuid
from datetime import datetime

from django.db.models import Count, Exists, OuterRef, Q, QuerySet, Sum
from django.db.models.functions import TruncHour

from accounts.models import Owner, Robot
from sharing.models import Access, Record, Verdict
from sharing.selectors.grants import owners_granting
from sharing.selectors.records import record_list_shared_with, robots_in_scope_of


def verdict_latest(record: Record, viewer: Owner) -> Verdict | None:
    """The viewer's most recent integrity verdict on the record (their own views only)."""
    return (
        record.verdicts.filter(access__viewer=viewer, access__checked_by__isnull=True)
        .order_by("-created_at", "-pk")
        .first()
    )


# Which views an access log lists: those of the owner's records (by anyone, the owner and the
# operator included), or the owner's own views of records others shared with the owner.
ACCESS_LOG_INCOMING = "incoming"
ACCESS_LOG_OUTGOING = "outgoing"
ACCESS_LOG_DIRECTIONS = [
    (ACCESS_LOG_INCOMING, "views of my data"),
    (ACCESS_LOG_OUTGOING, "my views of data shared with me"),
]


def access_list_access_log(owner: Owner, *, direction: str) -> QuerySet[Access]:
    """The owner's access log as people read it: one row per access (a record page, a gallery
    page, a plot, an export, an operator's check), newest first, with everything a row shows
    in the same query.

    Incoming: every access to the owner's records (Access.record_owner, indexed with the time),
    refused ones included. Outgoing: the owner's own accesses to other owners' records that
    at least one record was granted for (one refused whole would show what a record the viewer
    may not read is; an operator's checks are made with the record owner's rights, so they are
    only ever incoming).
    """
    if direction == ACCESS_LOG_INCOMING:
        accesses = Access.objects.filter(record_owner=owner)
    elif direction == ACCESS_LOG_OUTGOING:
        granted = Verdict.objects.filter(access=OuterRef("pk")).exclude(
            outcome=Verdict.Outcome.NO_ACCESS
        )
        accesses = Access.objects.filter(
            Exists(granted), viewer=owner, checked_by__isnull=True
        ).exclude(record_owner=owner)
    else:
        raise ValueError(f"unknown access log direction {direction!r}")
    return accesses.select_related(
        "viewer__user", "record_owner__user", "record", "robot", "token", "checked_by"
    ).order_by("-created_at", "-id")


def access_own(owner: Owner) -> Q:
    """The owner's own views (not an operator's checks made with the owner's rights): what an
    access log of who read the owner's records leaves out unless asked (issue 48)."""
    return Q(viewer=owner, checked_by__isnull=True)


# The hours of the owner's own views the access log sums up, newest first.
ACCESS_OWN_HOURS_SHOWN = 24


def access_own_by_hour(own: QuerySet[Access]) -> list[dict[str, object]]:
    """The owner's own views grouped: one line per hour, kind of page and robot, with how many
    views and records (the access log's summary of what it leaves out; newest first)."""
    return list(
        own.order_by()
        .annotate(hour=TruncHour("created_at"))
        .values("hour", "kind", "robot__name")
        .annotate(views=Count("id"), records=Sum("count"))
        .order_by("-hour", "kind", "robot__name")[:ACCESS_OWN_HOURS_SHOWN]
    )


def access_list_filtered(
    accesses: QuerySet[Access],
    *,
    viewer: str | None = None,
    owner: str | None = None,
    robot: uuid.UUID | str | None = None,
    topic: str | None = None,
    verdict: str | None = None,
    credential: str | None = None,
    since: datetime | None = None,
    until: datetime | None = None,
) -> QuerySet[Access]:
    """The accesses that match every filter given (None or empty: not filtered): `viewer` and
    `owner` (the record's) are usernames, `robot` and `topic` those all its records share,
    `verdict` an outcome of any of its records, `credential` a Credential; access times
    half-open, [since, until)."""
    if viewer:
        accesses = accesses.filter(viewer__user__username=viewer)
    if owner:
        accesses = accesses.filter(record_owner__user__username=owner)
    if robot:
        accesses = accesses.filter(robot_id=robot)
    if topic:
        accesses = accesses.filter(topic=topic)
    if verdict:
        found = Verdict.objects.filter(access=OuterRef("pk"), outcome=verdict)
        accesses = accesses.filter(Exists(found))
    if credential:
        accesses = accesses.filter(credential=credential)
    if since is not None:
        accesses = accesses.filter(created_at__gte=since)
    if until is not None:
        accesses = accesses.filter(created_at__lt=until)
    return accesses


def access_log_filter_choices(owner: Owner, *, direction: str) -> dict[str, QuerySet]:
    """What the access log's filters offer, each a small query run only when read: robots
    (id, name, owner's username), topics, and the usernames of the other side (the owner and
    grantees, or the owners who shared with the owner)."""
    if direction == ACCESS_LOG_OUTGOING:
        # Only what the owner's live grants let it read now (their scopes), never the rest of
        # a granting owner's robots and topics, nor those of a revoked or expired grant.
        robots = robots_in_scope_of(owner)
        topics = record_list_shared_with(owner)
        people = owners_granting(owner)
    else:
        robots = Robot.objects.filter(owner=owner)
        topics = Record.objects.filter(owner=owner)
        people = Owner.objects.filter(Q(pk=owner.pk) | Q(grants_received__owner=owner))
    return {
        "robots": robots.order_by("owner__user__username", "name").values_list(
            "id", "name", "owner__user__username"
        ),
        "topics": topics.order_by("topic").values_list("topic", flat=True).distinct(),
        "people": people.order_by("user__username")
        .values_list("user__username", flat=True)
        .distinct(),
    }

"""Reads of alerts: an owner's choices, endpoints and delivery log, and what the watch looks at."""

import uuid
from collections.abc import Iterable
from dataclasses import dataclass
from datetime import datetime, timedelta

from django.db.models import QuerySet
from django.db.models.functions import Coalesce

from accounts.models import ChainState, Owner, Robot
from alerts.models import AlertCondition, AlertDelivery, AlertPreferences, WebhookEndpoint

DELIVERIES_SHOWN = 50


def alert_preferences_of(owner: Owner) -> AlertPreferences:
    """The owner's choices; nothing chosen (and not saved) for an owner who never chose."""
    preferences = AlertPreferences.objects.filter(owner=owner).first()
    if preferences is None:
        preferences = AlertPreferences(owner=owner, email=owner.user.email)
    return preferences


def webhook_endpoints_of(owner: Owner) -> QuerySet[WebhookEndpoint]:
    return WebhookEndpoint.objects.filter(owner=owner)


def webhook_endpoint_of(owner: Owner, endpoint_id: uuid.UUID) -> WebhookEndpoint | None:
    """The owner's endpoint with that id; None for another owner's."""
    return WebhookEndpoint.objects.filter(owner=owner, pk=endpoint_id).first()


def alert_deliveries_of(owner: Owner, *, limit: int = DELIVERIES_SHOWN) -> list[AlertDelivery]:
    """The owner's latest deliveries, newest first: the log on the alerts page."""
    return list(
        AlertDelivery.objects.filter(alert__owner=owner)
        .select_related("alert")
        .order_by("-created_at")[:limit]
    )


@dataclass(frozen=True)
class SilentRobot:
    robot: Robot
    silent_since: datetime
    minutes: int


def robots_silent(*, now: datetime) -> list[SilentRobot]:
    """Active robots of owners who watch for silence that sent nothing for longer than their
    owner's limit (a robot that never sent counts from when it was added)."""
    robots = (
        Robot.objects.filter(
            is_active=True,
            revoked_at__isnull=True,
            owner__alert_preferences__robot_silent_minutes__isnull=False,
        )
        .select_related("owner__alert_preferences")
        .annotate(last_heard=Coalesce("last_upload_at", "created_at"))
    )
    silent = []
    for robot in robots:
        minutes = robot.owner.alert_preferences.robot_silent_minutes
        if robot.last_heard < now - timedelta(minutes=minutes):
            silent.append(SilentRobot(robot, robot.last_heard, minutes))
    return silent


def alert_conditions_open(kind: str) -> QuerySet[AlertCondition]:
    return AlertCondition.objects.filter(kind=kind, resolved_at__isnull=True)


def alert_subjects_open(kind: str, subjects: Iterable[str]) -> set[str]:
    """Which of these subjects of `kind` were alerted already (their condition open): one
    read, so that a page that finds them again writes nothing."""
    return set(
        alert_conditions_open(kind)
        .filter(subject__in=list(subjects))
        .values_list("subject", flat=True)
    )


def owners_watching_gas() -> list[AlertPreferences]:
    """Preferences of registered owners who set a low-gas threshold."""
    return list(
        AlertPreferences.objects.filter(
            gas_low_below_wei__isnull=False, owner__chain_state=ChainState.CONFIRMED
        ).select_related("owner__user")
    )


def deliveries_stale(*, before: datetime) -> QuerySet[AlertDelivery]:
    """Deliveries still pending whose last attempt (or making) was before `before`."""
    return AlertDelivery.objects.filter(status=AlertDelivery.Status.PENDING, updated_at__lt=before)


def alert_deliveries_pending_count() -> int:
    """Deliveries not sent yet and not given up (the metrics); the (status, updated_at) index."""
    return AlertDelivery.objects.filter(status=AlertDelivery.Status.PENDING).count()

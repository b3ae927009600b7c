"""The robot page: is one robot of the owner alive, what it sends, its latest verified pose and
image, a plot of its recent trajectory, and whether any record of the last hour is missing.

Only the robot's owner sees it; anyone else gets the 404 of a robot that does not exist. The
numbers come from sharing/robot_status.py; the pose and image go through the integrity check
every record view goes through (`records_open`, both in one run and one access of the page,
in `_latest_verified` only), so they are shown only when the chain holds them. The page keeps
itself up to date by polling the status API (sharing.apis.robots.RobotStatusApi) from
static/portal/robot-page.js.
"""

import uuid
from dataclasses import dataclass
from datetime import timedelta

from django.http import Http404, HttpRequest, HttpResponse
from django.shortcuts import render
from django.urls import reverse
from django.utils import timezone
from django.views.decorators.http import require_GET

from accounts.decorators import no_store, owner_required, page_throttle
from accounts.errors import IdentityMismatch
from accounts.models import Owner
from sharing.content import ODOMETRY, Content, content_of
from sharing.errors import IntegrityCheckFailed
from sharing.models import Access, Credential, Record, Verdict
from sharing.robot_status import (
    HOUR,
    RobotActivity,
    robot_activity,
    robot_latest_image_record,
    robot_latest_pose_record,
    robot_of_owner,
)
from sharing.selectors.records import record_list_owned
from sharing.verification.access import PLOT_REFRESHES_COALESCED
from sharing.verification.opening import OpenedRecord, records_open
from sharing.views.completeness import completeness_shown

# The trajectory plot shows this much of the recent past, and how often it adds the newer
# records; it plots the whole window again as often as its refreshes begin a new access line.
PLOT_WINDOW = timedelta(minutes=10)
PLOT_REFRESH_SECONDS = 5
# How often the page's script asks the status API while the tab is visible, and how often it
# loads the page again for a newer verified pose and image (two integrity checks each time).
STATUS_POLL_SECONDS = 5
LATEST_REFRESH_SECONDS = 30
# The page says whether any record of this window (the rates' last hour) is missing.
COMPLETENESS_WINDOW = HOUR


@dataclass(frozen=True)
class LatestShown:
    """The newest anchored record of a kind, and its content once it passed the check, or why
    it is not shown."""

    record: Record
    content: Content | None = None
    refused: str = ""


@owner_required
@page_throttle()
@require_GET
def robot_page(request: HttpRequest, robot_id: uuid.UUID) -> HttpResponse:
    owner: Owner = request.owner
    robot = robot_of_owner(owner, robot_id)
    if robot is None:
        raise Http404("no such robot")
    now = timezone.now()
    activity = robot_activity(robot, now=now)
    pose, image = _latest_verified(
        [robot_latest_pose_record(robot), robot_latest_image_record(robot)], viewer=owner
    )
    odometry_topic = pose.record.topic if pose is not None else _topic_of_type(activity, ODOMETRY)
    # Is any record of the last hour missing: the window of the rates (capture time, no end).
    completeness = completeness_shown(
        record_list_owned(owner).filter(robot=robot, captured_at__gte=now - COMPLETENESS_WINDOW),
        list_url=reverse("records"),
    )
    context = {
        "robot": robot,
        "activity": activity,
        "pose": pose,
        "image": image,
        "odometry_topic": odometry_topic,
        "plot_minutes": int(PLOT_WINDOW.total_seconds() // 60),
        "plot_refresh_seconds": PLOT_REFRESH_SECONDS,
        "plot_replot_seconds": int(PLOT_REFRESHES_COALESCED.total_seconds()),
        "plot_replot_minutes": int(PLOT_REFRESHES_COALESCED.total_seconds() // 60),
        "poll_seconds": STATUS_POLL_SECONDS,
        "latest_refresh_seconds": LATEST_REFRESH_SECONDS,
        "completeness": completeness,
        "completeness_since": (now - COMPLETENESS_WINDOW).strftime("%Y-%m-%d %H:%M"),
    }
    return no_store(render(request, "sharing/robot_detail.html", context))


def _topic_of_type(activity: RobotActivity, data_type: str) -> str:
    """The busiest topic of this ROS type in the last hour; "" if none."""
    for rate in activity.topics:
        if rate.data_type == data_type:
            return rate.topic
    return ""


def _latest_verified(records: list[Record | None], *, viewer: Owner) -> list[LatestShown | None]:
    """The records (None: none of that kind) opened through the integrity check in one run,
    one access of the page in the access log, each with its content or why it is not shown."""
    present = [record for record in records if record is not None]
    try:
        results = iter(
            records_open(
                records=present,
                viewer=viewer,
                kind=Access.Kind.PAGE,
                credential=Credential.SESSION,
            )
        )
    except IdentityMismatch as exc:
        results = iter([exc] * len(present))
    return [None if record is None else _shown(record, next(results)) for record in records]


def _shown(record: Record, result: OpenedRecord | Exception) -> LatestShown:
    if isinstance(result, IntegrityCheckFailed):
        unsigned = (
            result.verdict is not None
            and result.verdict.outcome == Verdict.Outcome.SIGNATURE_REFUSED
        )
        what = "Signature not valid" if unsigned else "TAMPERED"
        return LatestShown(record, refused=f"{what}, not shown: {result}")
    if isinstance(result, Exception):
        return LatestShown(record, refused=f"not shown: {result}")
    content = content_of(data_type=record.data_type, plaintext=result.plaintext)
    return LatestShown(result.record, content=content)

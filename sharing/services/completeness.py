"""Records missing: a gap of a stream that no deletion explains (sharing/selectors/
completeness.py) is told to the robot's owner as an alert of kind `records_missing`, once per
gap, whoever's read found it (the owner's page, a grantee's list, the API, a series): the
portal holds nothing for numbers the robot signed, and only the owner can ask why.

Like a tampered record (sharing/verification/tamper.py), it is raised by the read that finds
it; a page that finds known gaps again writes nothing (one read of the open conditions)."""

import uuid

from accounts.models import Robot
from alerts.models import AlertKind
from alerts.selectors import alert_subjects_open
from alerts.services import records_missing_alert, records_missing_subject
from sharing.selectors.completeness import GAP_MISSING, Completeness, Gap, Stream

# Gaps alerted from one read at most; the next read alerts the next ones.
GAPS_ALERTED_PER_READ = 20


def records_missing_alerts_raise(completeness: Completeness) -> int:
    """Alert each robot's owner of the missing gaps of `completeness` not alerted yet; how
    many alerts were made."""
    found: list[tuple[Stream, Gap, str]] = []
    for stream in completeness.streams:
        for gap in stream.gaps:
            if gap.reason == GAP_MISSING:
                found.append((stream, gap, _subject(stream, gap)))
    found = found[:GAPS_ALERTED_PER_READ]
    if not found:
        return 0
    known = alert_subjects_open(AlertKind.RECORDS_MISSING, [subject for *_, subject in found])
    new = [(stream, gap) for stream, gap, subject in found if subject not in known]
    if not new:
        return 0
    robots = Robot.objects.select_related("owner__user").in_bulk(
        {uuid.UUID(stream.robot_id) for stream, _gap in new}
    )
    raised = 0
    for stream, gap in new:
        robot = robots[uuid.UUID(stream.robot_id)]
        alert = records_missing_alert(
            owner=robot.owner,
            robot_id=robot.pk,
            robot=robot.name,
            signer=stream.signer,
            topic=stream.topic,
            first=gap.start,
            last=gap.end,
        )
        raised += alert is not None
    return raised


def _subject(stream: Stream, gap: Gap) -> str:
    return records_missing_subject(
        robot_id=stream.robot_id,
        signer=stream.signer,
        topic=stream.topic,
        gap=f"{gap.start}-{gap.end}",
    )

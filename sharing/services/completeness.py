"""Records missing: a gap of a stream that no deletion explains (sharing/selectors/
completeness.py) is told to the robot's owner as an alert of kind `records_missing`, once per
gap, whoever's read found it (the owner's page, a grantee's list, the API, a series): the
portal holds nothing for numbers the robot signed, and only the owner can ask why.

Like a tampered record (sharing/verification/tamper.py), it is raised by the read that finds
it; a page that finds known gaps again writes nothing (one read of the open conditions). A
scan (`records_missing_scan`, on beat) reads every robot's recent streams too, so that a gap
nobody looks at is told all the same: a robot's refused uploads, a lost file or row, a restore
from an older backup.

    records_missing_scan(window=timedelta(days=1))   # alerts made
"""

import uuid
from datetime import timedelta

from django.utils import timezone

from accounts.models import Robot
from alerts.models import AlertKind
from alerts.selectors import alert_subjects_open
from alerts.services import records_missing_alert, records_missing_subject
from sharing.models import Record
from sharing.selectors.completeness import GAP_MISSING, Completeness, Gap, Stream, record_streams

# Gaps alerted from one read at most (the next read alerts the next ones), and gaps looked up
# among those already alerted.
GAPS_ALERTED_PER_READ = 20
GAPS_LOOKED_UP_PER_READ = 1000
# Gaps a scan alerts per robot at most: beyond, the owner has enough to act on.
GAPS_SCANNED_PER_ROBOT = 200


def records_missing_alerts_raise(
    completeness: Completeness, *, limit: int = GAPS_ALERTED_PER_READ
) -> int:
    """Alert each robot's owner of the missing gaps of `completeness` not alerted yet, at
    most `limit` of them; how many alerts were made."""
    found: list[tuple[Stream, Gap, str]] = []
    for stream in completeness.streams:
        for gap in stream.gaps:
            if gap.reason == GAP_MISSING and len(found) < GAPS_LOOKED_UP_PER_READ:
                found.append((stream, gap, _subject(stream, gap)))
    if not found:
        return 0
    known = alert_subjects_open(AlertKind.RECORDS_MISSING, [subject for *_, subject in found])
    new = [(stream, gap) for stream, gap, subject in found if subject not in known][:limit]
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


def records_missing_scan(*, window: timedelta) -> int:
    """Alert the owners of the missing gaps among the records of each robot captured over the
    last `window` (tombstones in, so deletions stay reasons); how many alerts were made. A few
    queries per robot that uploaded in the window; gaps already alerted write nothing."""
    since = timezone.now() - window
    # order_by(): the model's ordering would join DISTINCT, one "robot" a record (a day of a
    # robot's records scanned once for each of them: hours of a worker, every 10 minutes)
    robots = (
        Record.objects.filter(captured_at__gte=since, topic_seq__isnull=False)
        .order_by()
        .values_list("robot_id", flat=True)
        .distinct()
    )
    raised = 0
    for robot_id in robots:
        streams = record_streams(Record.objects.filter(robot_id=robot_id, captured_at__gte=since))
        if streams.missing:
            raised += records_missing_alerts_raise(streams, limit=GAPS_SCANNED_PER_ROBOT)
    return raised


def _subject(stream: Stream, gap: Gap) -> str:
    return records_missing_subject(
        robot_id=stream.robot_id,
        signer=stream.signer,
        topic=stream.topic,
        gap=f"{gap.start}-{gap.end}",
    )

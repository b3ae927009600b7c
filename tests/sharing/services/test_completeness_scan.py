"""The scan for records missing (sharing/services/completeness.py, on beat): a gap nobody has
looked at is told to the robot's owner all the same, once; deletions and retention are reasons,
not alerts; what lies outside the window is not read."""

from datetime import timedelta

import pytest
from django.utils import timezone

from alerts.models import Alert, AlertKind
from sharing.models import Record
from sharing.services.completeness import records_missing_scan
from tests.pages.conftest import pending_owner  # noqa: F401  (the fixture)
from tests.sharing.test_completeness import T0, robot, row, rows  # noqa: F401  (fixture)

pytestmark = pytest.mark.django_db

WINDOW = timedelta(days=30) + (timezone.now() - T0)


def _missing_alerts(owner) -> list[Alert]:
    return list(Alert.objects.filter(owner=owner, kind=AlertKind.RECORDS_MISSING))


def test_a_gap_nobody_looked_at_is_alerted_once(robot):  # noqa: F811
    rows(robot, [0, 1, 2, 5, 6])
    row(robot, 9)

    assert records_missing_scan(window=WINDOW) == 2
    alerts = _missing_alerts(robot.owner)
    assert sorted((a.detail["from"], a.detail["to"]) for a in alerts) == [(3, 4), (7, 8)]
    assert records_missing_scan(window=WINDOW) == 0  # known gaps: nothing written again
    assert len(_missing_alerts(robot.owner)) == 2


def test_deletions_and_retention_are_reasons_not_alerts(robot):  # noqa: F811
    rows(robot, [0, 1])
    row(robot, 2, deleted=timezone.now(), reason=Record.Deletion.OWNER)
    row(robot, 3, deleted=timezone.now(), reason=Record.Deletion.RETENTION)
    row(robot, 4)

    assert records_missing_scan(window=WINDOW) == 0
    assert _missing_alerts(robot.owner) == []


def test_records_outside_the_window_are_not_read(robot):  # noqa: F811
    rows(robot, [0, 1, 5])  # captured at T0, days ago

    assert records_missing_scan(window=timedelta(hours=1)) == 0
    assert _missing_alerts(robot.owner) == []


def test_a_robot_is_scanned_once_whatever_it_holds(robot, django_assert_max_num_queries):  # noqa: F811
    rows(robot, range(40))
    row(robot, 45)
    # one robot's queries (13 here), not one robot's for each of its records (173)
    with django_assert_max_num_queries(20):
        assert records_missing_scan(window=WINDOW) == 1

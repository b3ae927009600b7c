"""What one poll of the robot page's status costs (issue 35), at millions of records.

`python -m bench robot_status [--records N] [--polls K] [--database URL]` makes a database of
its own (a temporary SQLite file unless --database names another, which must be empty), one
owner and one robot that sent N records (odometry at 10 per second and images at 2, ending
now), then asks `GET /api/v1/robots/{id}/status/` K times as the page's script does and reports
the view's time per poll (p50, p95; the DRF view with its authentication, without the HTTP
server), the SQL queries per poll and the rate query's plan. Nothing reaches the chain or the
Celery queue: the rows are written directly.
"""

import argparse
import os
import secrets
import statistics
import sys
import tempfile
import time
import uuid
from datetime import UTC, datetime, timedelta
from pathlib import Path

RATES = (("/robot/odom", "nav_msgs/Odometry", 10), ("/camera/image", "sensor_msgs/Image", 2))
BATCH = 20_000
# The last seconds of the run are written last, so that they end when the polls start.
TAIL_SECONDS = 120


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench robot_status")
    parser.add_argument("--records", type=int, default=2_000_000)
    parser.add_argument("--polls", type=int, default=50)
    parser.add_argument("--database", default="")
    args = parser.parse_args(argv)
    workdir = Path(tempfile.mkdtemp(prefix="bench-robot-status-"))
    os.environ["DATABASE_URL"] = args.database or f"sqlite:///{workdir / 'db.sqlite3'}"
    os.environ["REDIS_KEY_PREFIX"] = f"bench-robot-status-{uuid.uuid4().hex[:8]}"
    os.environ.setdefault("DJANGO_SETTINGS_MODULE", "portal.settings")
    import django

    django.setup()
    from django.core.management import call_command

    call_command("migrate", verbosity=0)
    robot, user = _fleet(args.records)
    result = _polls(robot, user, args.polls)
    print(
        f"{args.records:,} records of one robot ({os.environ['DATABASE_URL'].split(':')[0]}): "
        f"status poll with the hour cached p50 {result['p50_ms']:.1f} ms, "
        f"p95 {result['p95_ms']:.1f} ms, "
        f"{result['queries']} queries per poll at most; a poll that reads the hour again "
        f"(once a minute) p50 {result['hour_read_ms']:.1f} ms; topics {result['topics']}"
    )
    print("rate query plan:", result["plan"])
    return 0


def _fleet(count: int) -> tuple[object, object]:
    """An owner and a robot whose `count` records end now, written directly."""
    from django.contrib.auth import get_user_model
    from django.db import connection
    from django.utils import timezone

    from accounts.models import ChainState, Owner, Robot

    user = get_user_model().objects.create_user(f"bench-{uuid.uuid4().hex[:6]}", password=None)
    owner = Owner.objects.create(
        user=user,
        eoa_address="0x" + secrets.token_hex(20),
        eoa_key_wrapped=b"",
        chain_state=ChainState.CONFIRMED,
    )
    now = timezone.now()
    robot = Robot.objects.create(
        owner=owner,
        name="bench",
        token_hash=secrets.token_hex(32),
        token_prefix=secrets.token_hex(4),
        last_upload_at=now,
    )
    per_second = sum(rate for _topic, _type, rate in RATES)
    span = timedelta(seconds=count / per_second)
    tail = min(count, TAIL_SECONDS * per_second)
    start = time.perf_counter()
    _write(owner, robot, range(count - tail), end=now, span=span, per_second=per_second)
    # As autovacuum would have by then: the planner's statistics, and (PostgreSQL) the
    # visibility map that lets a count read the index alone.
    with connection.cursor() as cursor:
        cursor.execute(
            "VACUUM ANALYZE sharing_record" if connection.vendor == "postgresql" else "ANALYZE"
        )
    # The last TAIL_SECONDS written last, ending when the polls start, however long the rest
    # took (the hour then has a gap of that long, before the tail).
    _write(
        owner,
        robot,
        range(count - tail, count),
        end=timezone.now(),
        span=span,
        per_second=per_second,
    )
    print(f"wrote {count:,} records in {time.perf_counter() - start:.0f} s", file=sys.stderr)
    return robot, user


def _write(
    owner: object, robot: object, indexes: range, *, end: datetime, span: timedelta, per_second: int
) -> None:
    """Records number `indexes` of the robot's run of `span` ending at `end`, in batches."""
    from sharing.models import Record

    rows = []
    for index in indexes:
        second, slot = divmod(index, per_second)
        topic, data_type = _topic_of(slot)
        rows.append(
            Record(
                owner=owner,
                robot=robot,
                topic=topic,
                data_type=data_type,
                seq=index + 1,
                captured_at=end - span + timedelta(seconds=second, microseconds=slot * 1000),
                key_id="0" * 16,
                digest="0" * 64,
                size=100,
                storage_name=f"bench/{index + 1}",
                status=Record.Status.ANCHORED,
            )
        )
        if len(rows) == BATCH:
            Record.objects.bulk_create(rows)
            rows = []
    Record.objects.bulk_create(rows)


def _topic_of(slot: int) -> tuple[str, str]:
    for topic, data_type, rate in RATES:
        if slot < rate:
            return topic, data_type
        slot -= rate
    raise AssertionError("slot beyond the rates")


def _polls(robot: object, user: object, polls: int) -> dict[str, object]:
    from django.core.cache import cache
    from django.db import connection
    from django.test.utils import CaptureQueriesContext
    from django.utils import timezone
    from rest_framework.test import APIRequestFactory, force_authenticate

    from sharing.apis.robots import RobotStatusApi
    from sharing.models import Record

    view = RobotStatusApi.as_view()
    factory = APIRequestFactory()
    times: dict[bool, list[float]] = {True: [], False: []}  # by: read the hour's counts again
    queries, answer = [], None
    for index in range(polls):
        hour_read = index % 10 == 0  # a tenth of the polls read the hour again (none cached)
        if hour_read:
            cache.delete(f"robot-rates-hour:{robot.pk}")
        request = factory.get(f"/api/v1/robots/{robot.pk}/status/")
        force_authenticate(request, user=user)
        with CaptureQueriesContext(connection) as seen:
            start = time.perf_counter()
            answer = view(request, robot_id=str(robot.pk))
            answer.render()
            times[hour_read].append(time.perf_counter() - start)
        queries.append(len(seen.captured_queries))
    assert answer.status_code == 200, answer.content
    hour_ago = timezone.now() - timedelta(hours=1)
    counts = (
        Record.objects.filter(robot=robot, captured_at__gte=hour_ago)
        .order_by()
        .values("topic", "data_type")
    )
    plan = counts.explain()
    return {
        "p50_ms": 1000 * statistics.median(times[False]),
        "p95_ms": 1000 * statistics.quantiles(times[False], n=20)[18],
        "queries": max(queries),
        "hour_read_ms": 1000 * statistics.median(times[True]),
        "topics": [(t["topic"], t["last_minute"], t["last_hour"]) for t in answer.data["topics"]],
        "plan": " | ".join(line.strip() for line in plan.splitlines()),
        "at": datetime.now(tz=UTC).isoformat(),
    }


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))

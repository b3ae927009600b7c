"""RecordSelection (sharing/selection.py): the one value of "records by robots, topics and a
capture-time window [since, until)" behind grant scopes, exports, deletions and the record
filters. Its checks and limits, its canonical form, and the same answer in Python (`covers`)
and in the database (`apply`), edges of the window included."""

import itertools
import uuid
from datetime import UTC, datetime, timedelta, timezone

import pytest

from sharing.errors import ExportRefused
from sharing.exports.create import export_create
from sharing.models import Record
from sharing.scope import ScopeError, scope_make
from sharing.selection import (
    BAD_ROBOT_ID,
    BAD_TOPIC,
    MAX_SELECTED_ROBOTS,
    MAX_SELECTED_TOPICS,
    MAX_TOPIC_LENGTH,
    NAIVE_TIME,
    TOO_MANY_ROBOTS,
    TOO_MANY_TOPICS,
    WINDOW_NOT_ORDERED,
    RecordSelection,
    SelectionError,
)

ONE, TWO = uuid.UUID(int=1), uuid.UUID(int=2)
NOON = datetime(2026, 3, 1, 12, 0, tzinfo=UTC)
MICRO = timedelta(microseconds=1)
BEIJING = timezone(timedelta(hours=8))


def refused_rule(**values: object) -> str:
    with pytest.raises(SelectionError) as refused:
        RecordSelection.of(**values)
    return refused.value.rule


# --- making one: canonical form, checks and limits -----------------------------------------


def test_of_is_canonical_whatever_the_order_duplicates_or_time_zone():
    selection = RecordSelection.of(
        robots=[str(TWO), ONE, ONE],
        topics=["/b", " /a ", "/b"],
        since=NOON.astimezone(BEIJING),
        until=NOON + timedelta(hours=1),
    )
    assert selection == RecordSelection(
        robots=(ONE, TWO), topics=("/a", "/b"), since=NOON, until=NOON + timedelta(hours=1)
    )
    assert selection.since.tzinfo == UTC
    assert RecordSelection.of() == RecordSelection()
    assert RecordSelection.of().is_all
    assert not RecordSelection.of(topics=["/a"]).is_all
    assert not RecordSelection.of(until=NOON).is_all


def test_the_limits_count_distinct_robots_and_topics():
    robots = [uuid.UUID(int=n) for n in range(1, MAX_SELECTED_ROBOTS + 1)]
    topics = [f"/t{n}" for n in range(MAX_SELECTED_TOPICS)]
    at_the_limit = RecordSelection.of(robots=robots + robots[:5], topics=topics + topics[:5])
    assert len(at_the_limit.robots) == MAX_SELECTED_ROBOTS
    assert len(at_the_limit.topics) == MAX_SELECTED_TOPICS
    assert refused_rule(robots=[*robots, uuid.UUID(int=0)]) == TOO_MANY_ROBOTS
    assert refused_rule(topics=[*topics, "/one-more"]) == TOO_MANY_TOPICS


def test_a_topic_is_text_of_at_most_the_column_length():
    assert RecordSelection.of(topics=["/" + "x" * (MAX_TOPIC_LENGTH - 1)]).topics
    for topic in ["/" + "x" * MAX_TOPIC_LENGTH, "", "   ", "a\x00", "\ud800", 5, None]:
        assert refused_rule(topics=[topic]) == BAD_TOPIC, topic


@pytest.mark.parametrize(
    ("values", "rule"),
    [
        ({"robots": ["robot-1"]}, BAD_ROBOT_ID),
        ({"robots": [ONE, "not-a-uuid"]}, BAD_ROBOT_ID),
        ({"since": datetime(2026, 1, 1)}, NAIVE_TIME),
        ({"until": datetime(2026, 1, 1)}, NAIVE_TIME),
        ({"since": NOON, "until": NOON}, WINDOW_NOT_ORDERED),
        ({"since": NOON, "until": NOON - MICRO}, WINDOW_NOT_ORDERED),
        # The same instant in two time zones is still an empty window.
        ({"since": NOON, "until": NOON.astimezone(BEIJING)}, WINDOW_NOT_ORDERED),
    ],
)
def test_refusals_name_the_rule(values, rule):
    assert refused_rule(**values) == rule


def test_the_shortest_window_and_open_ends_are_selections():
    assert RecordSelection.of(since=NOON, until=NOON + MICRO).until == NOON + MICRO
    assert RecordSelection.of(since=NOON).until is None
    assert RecordSelection.of(until=NOON).since is None


def test_a_grant_and_an_export_word_the_same_rules_their_own_way():
    """The rules are the selection's; a grant's scope adds only that its window's ends fit its
    encoding (from 1970 on)."""
    many = [uuid.UUID(int=n) for n in range(MAX_SELECTED_ROBOTS + 1)]
    with pytest.raises(ScopeError, match=f"a grant can name at most {MAX_SELECTED_ROBOTS} robots"):
        scope_make(robots=many)
    with pytest.raises(ScopeError, match="the start of the time window must be before its end"):
        scope_make(since=NOON, until=NOON)
    before_1970 = datetime(1969, 12, 31, tzinfo=UTC)
    assert RecordSelection.of(since=before_1970).since == before_1970
    with pytest.raises(ScopeError, match="after 1970-01-01"):
        scope_make(since=before_1970)


@pytest.mark.django_db
def test_an_export_refuses_with_its_own_words(make_robot):
    alice = make_robot("alice")
    many = [f"/t{n}" for n in range(MAX_SELECTED_TOPICS + 1)]
    too_many = f"select at most {MAX_SELECTED_ROBOTS} robots and {MAX_SELECTED_TOPICS} topics"
    with pytest.raises(ExportRefused, match=too_many):
        export_create(requester=alice.owner, topics=many)
    with pytest.raises(ExportRefused, match="the start of the time range is not before its end"):
        export_create(requester=alice.owner, since=NOON, until=NOON)


# --- one record: covers -------------------------------------------------------------------


def test_covers_is_half_open_and_needs_every_term():
    selection = RecordSelection.of(robots=[ONE], topics=["/a"], since=NOON, until=NOON + MICRO)
    inside = {"robot_id": ONE, "topic": "/a", "captured_at": NOON}
    assert selection.covers(**inside)
    assert selection.covers(**{**inside, "robot_id": str(ONE)})
    assert not selection.covers(**{**inside, "robot_id": TWO})
    assert not selection.covers(**{**inside, "topic": "/b"})
    assert not selection.covers(**{**inside, "captured_at": NOON - MICRO})
    assert not selection.covers(**{**inside, "captured_at": NOON + MICRO})
    assert RecordSelection().covers(robot_id=TWO, topic="/any", captured_at=NOON)


# --- rows: apply, the same rule in the database -------------------------------------------

EDGES = {"before": -MICRO, "since": timedelta(0), "last": timedelta(hours=1) - MICRO}
UNTIL = NOON + timedelta(hours=1)


@pytest.fixture
def rows(make_robot) -> tuple[list[Record], uuid.UUID, uuid.UUID]:
    """Records of two robots (two owners) on two topics, at each edge of [NOON, UNTIL) and
    at UNTIL itself: rows as the upload leaves them (the filter reads nothing else)."""
    robots = [make_robot("alice").robot, make_robot("bob").robot]
    moments = [NOON + offset for offset in EDGES.values()] + [UNTIL]
    made = [
        Record(
            owner=robot.owner,
            robot=robot,
            topic=topic,
            data_type="std_msgs/String",
            seq=seq,
            captured_at=moment,
            key_id="00" * 8,
            digest="00" * 32,
            size=1,
            storage_name=f"envelopes/{uuid.uuid4()}",
        )
        for robot in robots
        for seq, (topic, moment) in enumerate(itertools.product(("/a", "/b"), moments))
    ]
    Record.objects.bulk_create(made)
    return made, robots[0].pk, robots[1].pk


def selected(selection: RecordSelection, made: list[Record]) -> set[uuid.UUID]:
    records = Record.objects.filter(pk__in=[record.pk for record in made])
    return set(selection.apply(records).values_list("pk", flat=True))


def times_selected(selection: RecordSelection, made: list[Record]) -> set[datetime]:
    kept = selected(selection, made)
    return {record.captured_at for record in made if record.pk in kept}


@pytest.mark.django_db
def test_apply_keeps_the_window_edges_half_open(rows):
    made, _first, _second = rows
    window = RecordSelection.of(since=NOON, until=UNTIL)
    assert times_selected(window, made) == {NOON, UNTIL - MICRO}
    assert times_selected(RecordSelection.of(since=NOON), made) == {NOON, UNTIL - MICRO, UNTIL}
    assert times_selected(RecordSelection.of(until=NOON), made) == {NOON - MICRO}
    assert times_selected(RecordSelection.of(since=UNTIL - MICRO, until=UNTIL), made) == {
        UNTIL - MICRO
    }


@pytest.mark.django_db
def test_apply_filters_robots_and_topics(rows):
    made, first, second = rows
    assert selected(RecordSelection(), made) == {r.pk for r in made}
    only_a = selected(RecordSelection.of(topics=["/a"]), made)
    assert only_a == {r.pk for r in made if r.topic == "/a"}
    of_first = selected(RecordSelection.of(robots=[first]), made)
    assert of_first == {r.pk for r in made if r.robot_id == first}
    both = selected(RecordSelection.of(robots=[first, second], topics=["/a", "/b"]), made)
    assert both == {r.pk for r in made}
    assert selected(RecordSelection.of(robots=[uuid.uuid4()]), made) == set()


@pytest.mark.django_db
def test_apply_and_covers_agree_on_every_record(rows):
    """The database and the view's check decide alike, for every mix of terms."""
    made, first, second = rows
    choices = {
        "robots": [(), (first,), (second,), (first, second)],
        "topics": [(), ("/a",), ("/b",)],
        "window": [(None, None), (NOON, None), (None, UNTIL), (NOON, UNTIL), (NOON, NOON + MICRO)],
    }
    for robots, topics, (since, until) in itertools.product(*choices.values()):
        selection = RecordSelection.of(robots=robots, topics=topics, since=since, until=until)
        covered = {
            r.pk
            for r in made
            if selection.covers(robot_id=r.robot_id, topic=r.topic, captured_at=r.captured_at)
        }
        assert selected(selection, made) == covered, selection


@pytest.mark.django_db
def test_a_filters_selection_is_one_robot_and_one_topic_and_may_be_empty(rows):
    made, first, _second = rows
    one = RecordSelection.from_filters(robot=str(first), topic="/b", since=NOON, until=UNTIL)
    assert one == RecordSelection(robots=(first,), topics=("/b",), since=NOON, until=UNTIL)
    assert {(r.robot_id, r.topic) for r in made if r.pk in selected(one, made)} == {(first, "/b")}
    assert RecordSelection.from_filters(robot=None, topic="") == RecordSelection()
    # A list filter whose window holds nothing lists nothing; it is not refused.
    assert selected(RecordSelection.from_filters(since=NOON, until=NOON), made) == set()


# --- its JSON, as an export stores it -----------------------------------------------------


def test_json_round_trip_keeps_microseconds_in_utc():
    selection = RecordSelection.of(
        robots=[TWO, ONE], topics=["/a"], since=(NOON + MICRO).astimezone(BEIJING)
    )
    stored = selection.as_json()
    assert stored == {
        "robots": [str(ONE), str(TWO)],
        "topics": ["/a"],
        "since": "2026-03-01T12:00:00.000001Z",
        "until": None,
    }
    assert RecordSelection.from_json(stored) == selection
    assert RecordSelection.from_json({}) == RecordSelection()

"""Series: any numeric field of one robot's topic over a time range, from every record in it,
each one integrity-checked, one row per verified record (the API thins them for display).

`series_of` reads the records the caller may see in the range (their own, or a grant's within
its scope: record_list_visible_to and RecordSelection, so that nothing outside the scope is
counted), has the workers check every one of them (verification.opening.records_rows_open: one
access-log line of kind "plot", slices checked side by side), which read the fields (dotted
paths into the record's decoded message, `K` of the paper's Fig. 4 JSON, `record_values`) of
the verified ones and hand back only those, sealed for this read: one row per record, which
the series API thins for display (sharing/thinning.py). A record not verified is never
plotted: one not anchored yet (its anchoring still to come, or given up) is counted in
`not_anchored_yet`, any other (tampered, signature not valid, no access on chain) in `refused`.
"""

import math
import uuid
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass
from datetime import datetime

from django.conf import settings
from django.db.models import QuerySet

from accounts.models import Owner, OwnerToken
from sharing.content import Uninterpretable, document_parse
from sharing.errors import SeriesRefused
from sharing.models import Record
from sharing.selection import RecordSelection
from sharing.selectors.completeness import Completeness, record_streams
from sharing.selectors.records import record_list_visible_to
from sharing.verification.access import OwnerRead
from sharing.verification.opening import records_rows_open

# Fields of one series, and characters of one field's dotted path.
MAX_FIELDS = 8
MAX_FIELD_LENGTH = 200
# Points a series answers at most, and by default.
MAX_POINTS = 10_000
DEFAULT_POINTS = 1_000
# A field's path: names of at most this many levels (a list index is a number).
MAX_FIELD_DEPTH = 16
# A value further from zero than this is no measurement (and would overflow a plot's scale).
VALUE_LIMIT = 1e15


@dataclass(frozen=True)
class SeriesQuery:
    """What a series plots: one robot's topic, some fields, a capture-time range [since, until),
    at most `points` points."""

    robot: uuid.UUID
    topic: str
    fields: tuple[str, ...]
    since: datetime
    until: datetime
    points: int = DEFAULT_POINTS


@dataclass(frozen=True)
class Series:
    fields: tuple[str, ...]
    points: list[list[float | None]]  # [t (Unix seconds), v1, v2...], oldest first, all
    source_records: int  # records in the range the caller may see
    verified: int  # of them, checked and verified
    refused: int  # of them, refused by the check for what they are: never plotted
    not_anchored_yet: int  # of them, not verified because not anchored yet: not plotted yet
    without_values: int  # verified, but holding none of the fields as a number
    # The range's streams, first to last topic_seq and every gap (tombstones give reasons).
    completeness: Completeness

    def as_json(self) -> dict[str, object]:
        return {
            "fields": list(self.fields),
            "points": self.points,
            "source_records": self.source_records,
            "verified": self.verified,
            "refused": self.refused,
            "not_anchored_yet": self.not_anchored_yet,
            "without_values": self.without_values,
            **self.completeness.as_json(),
        }


def series_query_make(
    *,
    robot: uuid.UUID,
    topic: str,
    fields: list[str],
    since: datetime,
    until: datetime,
    points: int = DEFAULT_POINTS,
) -> SeriesQuery:
    """The query, checked: SeriesRefused (400) for no field or too many, a field that is not a
    dotted path of names and indexes, a window that is not ordered or longer than
    SERIES_MAX_RANGE, or points out of 2..MAX_POINTS."""
    if len(fields) > MAX_FIELDS:
        raise SeriesRefused(f"a series plots at most {MAX_FIELDS} fields")
    fields = [field.strip() for field in fields if field.strip()]
    if not fields:
        raise SeriesRefused("name at least one field, e.g. fields=position.x,position.y")
    if len(fields) > MAX_FIELDS:
        raise SeriesRefused(f"a series plots at most {MAX_FIELDS} fields")
    for field in fields:
        if len(field) > MAX_FIELD_LENGTH or not _is_path(field):
            raise SeriesRefused(
                f"a field is a dotted path of at most {MAX_FIELD_LENGTH} characters and "
                f"{MAX_FIELD_DEPTH} names (letters, digits, _ and -), e.g. position.x"
            )
    if not 2 <= points <= MAX_POINTS:
        raise SeriesRefused(f"points must be 2..{MAX_POINTS}")
    if since.tzinfo is None or until.tzinfo is None:
        raise SeriesRefused("since and until need a time zone (e.g. 2026-11-29T02:00:00Z)")
    if since >= until:
        raise SeriesRefused("since must be before until")
    longest = settings.SERIES_MAX_RANGE
    if until - since > longest:
        raise SeriesRefused(f"a series covers at most {longest}; choose a shorter range")
    return SeriesQuery(
        robot=robot, topic=topic, fields=tuple(fields), since=since, until=until, points=points
    )


def _is_path(field: str) -> bool:
    names = field.split(".")
    return len(names) <= MAX_FIELD_DEPTH and all(
        name and all(c.isascii() and (c.isalnum() or c in "_-") for c in name) for name in names
    )


def series_window(viewer: Owner, query: SeriesQuery) -> QuerySet[Record]:
    """The range's records the viewer may see (own, or in a live grant's scope), tombstones
    included: what its completeness is read from."""
    selection = RecordSelection.of(
        robots=[query.robot], topics=[query.topic], since=query.since, until=query.until
    )
    return selection.apply(record_list_visible_to(viewer))


def series_record_ids(viewer: Owner, query: SeriesQuery) -> tuple[list[str], list[OwnerRead], int]:
    """The ids of every record of the range the viewer may see (own, or in a live grant's
    scope), oldest first, what the plot's access line names of each record owner's, and how
    many of them are not anchored (pending, or anchoring given up). SeriesRefused when they
    are more than SERIES_MAX_RECORDS. Ids only: a range of hours holds hundreds of thousands
    of records, which the workers read themselves."""
    in_range = series_window(viewer, query).live().order_by("captured_at", "seq")
    most = settings.SERIES_MAX_RECORDS
    record_ids: list[str] = []
    by_owner: Counter[int] = Counter()
    first_of: dict[int, str] = {}
    unanchored = 0
    rows = in_range.values_list("pk", "owner_id", "status")[: most + 1]
    # Streamed, as text: 216,000 ids take about 25 MB so, twice that as UUIDs in a list.
    for pk, owner_id, status in rows.iterator(10_000):
        record_ids.append(str(pk))
        unanchored += status != Record.Status.ANCHORED
        by_owner[owner_id] += 1
        first_of.setdefault(owner_id, record_ids[-1])
    if len(record_ids) > most:
        raise SeriesRefused(f"the range holds more than {most} records; choose a shorter range")
    reads = [
        OwnerRead(
            owner_id=owner_id,
            count=count,
            record=Record.objects.get(pk=first_of[owner_id]) if count == 1 else None,
            robot_id=query.robot,
            topic=query.topic,
        )
        for owner_id, count in by_owner.items()
    ]
    return record_ids, reads, unanchored


def series_of(
    *,
    viewer: Owner,
    query: SeriesQuery,
    credential: str,
    token: OwnerToken | None = None,
    refresh: bool = False,
) -> Series:
    """The series of the query for the viewer: every record in range checked by the workers
    (one access of kind "plot"; a `refresh` adds to the viewer's recent line of the same plot;
    they hand back only the verified records' fields, sealed for this read:
    verification.opening.records_rows_open), one row per record, and the range's streams with
    their gaps (record_streams). VerificationUnavailable if the workers could not check them
    all."""
    record_ids, reads, unanchored = series_record_ids(viewer, query)
    checked = records_rows_open(
        record_ids=record_ids,
        reads=reads,
        viewer=viewer,
        fields=query.fields,
        credential=credential,
        token=token,
        refresh=refresh,
    )
    plotted = [row for row in checked.rows if any(value is not None for value in row[1:])]
    not_verified = len(record_ids) - checked.verified
    # Counted from the rows' status, not the verdicts (the workers answer only how many they
    # verified): a record not anchored when listed fails its check as not anchored yet, unless
    # its anchoring landed meanwhile (verified then) or the check refused it first for another
    # reason (a bad signature, counted here as not anchored yet).
    not_anchored_yet = min(unanchored, not_verified)
    return Series(
        fields=query.fields,
        points=plotted,
        source_records=len(record_ids),
        verified=checked.verified,
        refused=not_verified - not_anchored_yet,
        not_anchored_yet=not_anchored_yet,
        without_values=checked.verified - len(plotted),
        completeness=record_streams(series_window(viewer, query)),
    )


def record_values(plaintext: bytes, fields: Sequence[str]) -> list[float | None]:
    """The fields' numbers in a record's plaintext (document_parse's bounds hold: a record that
    is not JSON it takes has none); paths start in the message (`K`) when the record has one."""
    try:
        document = document_parse(plaintext)
    except Uninterpretable:
        return [None for _ in fields]
    message = document.get("K") if isinstance(document, dict) else None
    base = message if isinstance(message, dict | list) else document
    return [field_value(base, field) for field in fields]


def field_value(document: object, field: str) -> float | None:
    """The number at a dotted path (names of objects, indexes of lists) of a decoded message;
    None when there is none, or it is not a finite number within VALUE_LIMIT (a bool is not)."""
    value = document
    for name in field.split("."):
        if isinstance(value, dict):
            value = value.get(name)
        elif isinstance(value, list) and name.isdigit() and int(name) < len(value):
            value = value[int(name)]
        else:
            return None
    if isinstance(value, bool) or not isinstance(value, int | float):
        return None
    try:
        number = float(value)
    except OverflowError:
        return None
    return number if math.isfinite(number) and abs(number) <= VALUE_LIMIT else None

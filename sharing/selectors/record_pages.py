"""A record list a page at a time by capture time (keyset), so that a page stays what it was
while robots upload (issue 48).

A cursor is a record's place in capture order, (captured_at, id), written
`<microseconds since 1970 UTC>_<uuid hex>`. A list is read as of its newest record when it was
opened (`top`): what is captured later is counted ("n newer records"), never slid into the
pages, and `after` / `before` name the record a page starts after or ends before; no page is
an offset into a list that grows."""

import re
import uuid
from dataclasses import dataclass
from datetime import UTC, datetime, timedelta

from django.db.models import Q, QuerySet

from sharing.models import Record

# A cursor is `<microseconds since 1970 UTC>_<record id as 32 hex>`: every text of this shape
# (CURSOR_PATTERN, the API schema's) is a cursor that can be read (17 digits stay before 5138).
CURSOR_PATTERN = "^[0-9]{1,17}_[0-9a-f]{32}$"
_CURSOR = re.compile(CURSOR_PATTERN[1:-1])
_EPOCH = datetime(1970, 1, 1, tzinfo=UTC)
_MICROSECOND = timedelta(microseconds=1)
# Longer than any cursor this module writes: refused unread.
_MAX_CURSOR_LENGTH = 80


class BadCursor(ValueError):
    """A cursor that is not one this module wrote."""


@dataclass(frozen=True, order=True)
class RecordCursor:
    captured_at: datetime
    id: uuid.UUID

    @classmethod
    def of(cls, record: Record) -> "RecordCursor":
        return cls(record.captured_at, record.id)

    @classmethod
    def parse(cls, text: str) -> "RecordCursor":
        if len(text) > _MAX_CURSOR_LENGTH or not _CURSOR.fullmatch(text):
            raise BadCursor(text[:_MAX_CURSOR_LENGTH])
        micros, _, record_id = text.partition("_")
        return cls(_EPOCH + int(micros) * _MICROSECOND, uuid.UUID(hex=record_id))

    def __str__(self) -> str:
        return f"{(self.captured_at - _EPOCH) // _MICROSECOND}_{self.id.hex}"

    def q_after(self) -> Q:
        """Records after this one in capture order."""
        at = self.captured_at
        return Q(captured_at__gt=at) | Q(captured_at=at, id__gt=self.id)

    def q_before(self) -> Q:
        """Records before this one in capture order."""
        at = self.captured_at
        return Q(captured_at__lt=at) | Q(captured_at=at, id__lt=self.id)

    def q_up_to(self) -> Q:
        """This record and those before it: a list as of this record."""
        return ~self.q_after()


def record_cursor_newest(records: QuerySet[Record]) -> RecordCursor | None:
    """The newest of `records` in capture order: the `top` a list is read as of."""
    newest = records.order_by("-captured_at", "-id").values_list("captured_at", "id").first()
    return RecordCursor(*newest) if newest is not None else None


@dataclass
class RecordPage:
    """One page of a list in capture order, and where it sits among the list's records."""

    records: list[Record]
    number: int
    count: int
    size: int
    first: RecordCursor | None
    last: RecordCursor | None
    has_previous: bool
    has_next: bool

    @property
    def num_pages(self) -> int:
        return max(1, -(-self.count // self.size))


def record_page_by_capture(
    records: QuerySet[Record],
    *,
    descending: bool,
    size: int,
    after: RecordCursor | None = None,
    before: RecordCursor | None = None,
    last: bool = False,
) -> RecordPage:
    """The page of `records` (already bounded by its `top`) that starts just after `after`, or
    ends just before `before`, or the last page, or else the first; `after` and `before` are in
    the list's order (newest first when `descending`)."""
    forward = ("-captured_at", "-id") if descending else ("captured_at", "id")
    backward = ("captured_at", "id") if descending else ("-captured_at", "-id")
    count = records.count()

    def beyond(cursor: RecordCursor) -> Q:  # further on in the list's order
        return cursor.q_before() if descending else cursor.q_after()

    def behind(cursor: RecordCursor) -> Q:
        return cursor.q_after() if descending else cursor.q_before()

    if last:
        tail = count % size or size
        rows = list(records.order_by(*backward)[:tail])[::-1]
    elif before is not None:
        rows = list(records.filter(behind(before)).order_by(*backward)[:size])[::-1]
    elif after is not None:
        rows = list(records.filter(beyond(after)).order_by(*forward)[:size])
    else:
        rows = list(records.order_by(*forward)[:size])
    if not rows:
        return RecordPage([], 1, count, size, None, None, False, False)
    first, final = RecordCursor.of(rows[0]), RecordCursor.of(rows[-1])
    ahead = records.filter(behind(first)).count()
    return RecordPage(
        records=rows,
        number=ahead // size + 1,
        count=count,
        size=size,
        first=first,
        last=final,
        has_previous=ahead > 0,
        has_next=ahead + len(rows) < count,
    )

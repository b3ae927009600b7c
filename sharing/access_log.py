"""The access log as people read it: one line per access (a record page, a page of a gallery,
a plot, an export, an operator's check), who made it, when, how many records it read, what
their integrity checks found, and with which credential; one page of it, or all of it as CSV.

The rows are sharing.models.Access, listed by sharing.selectors.access.access_list_access_log and
access_list_filtered; each access's records' verdicts (the integrity trail, one per record and
check) are summed per access in one query per page or chunk. The CSV is streamed in chunks read
by keyset (time, id), so its memory does not grow with the log, and no cell can start a
spreadsheet formula. The REST API (`/api/v1/access-log/`) lists the same rows, through the same
selectors, redaction and outcomes.
"""

import csv
from collections import defaultdict
from collections.abc import Iterable, Iterator
from datetime import datetime

from django.core.paginator import Page, Paginator
from django.db.models import Count, Max, Q, QuerySet

from accounts.models import Owner
from sharing.models import Access, Credential, Verdict

# Rows read from the database at a time while the CSV streams.
CSV_CHUNK = 500
# Characters a spreadsheet may take as the start of a formula (OWASP "CSV injection"); tab
# and carriage return too, which some spreadsheets strip before looking.
_FORMULA_STARTS = ("=", "+", "-", "@", "\t", "\r")
_OUTCOME_LABELS = dict(Verdict.Outcome.choices)

CSV_COLUMNS = [
    "id",
    "accessed_at",
    "kind",
    "records",
    "viewer",
    "record_owner",
    "record",
    "robot",
    "robot_id",
    "topic",
    "type",
    "seq",
    "captured_at",
    "verdict",
    "verified",
    "refused",
    "credential",
    "token_name",
    "token_prefix",
    "operator",
]


def credential_label(access: Access) -> str:
    """The credential an access was made with, as the page and the CSV say it."""
    if access.credential == Credential.TOKEN:
        token = access.token
        if token is None:  # another owner's token (access_log_redacted)
            return "owner API token"
        return f"owner API token “{token.name}” ({token.token_prefix}…)"
    if access.credential == Credential.OPERATOR:
        operator = access.checked_by.get_username() if access.checked_by else "a former operator"
        return f"operator check in the admin ({operator})"
    return access.get_credential_display()


def access_log_redacted(rows: Iterable[Access], *, reader: Owner) -> list[Access]:
    """The rows as `reader` may see them: a grantee's own API token (its name and prefix) is
    the grantee's business; the record's owner learns only that a token was used. Changed
    in memory only."""
    shown = list(rows)
    for row in shown:
        if row.token_id is not None and row.viewer_id != reader.pk:
            row.token = None
    return shown


def access_outcomes(accesses: list[Access]) -> list[Access]:
    """Each access with `outcomes` (outcome -> how many of its records' checks found it),
    `outcome` (the one outcome when all agree, else "mixed"),
    `verified`, `refused` and `block_number` (the latest block its checks were made against),
    in one query for all."""
    counts: dict[int, dict[str, int]] = defaultdict(dict)
    blocks: dict[int, int] = {}
    rows = (
        Verdict.objects.filter(access_id__in=[access.pk for access in accesses])
        .values_list("access_id", "outcome")
        .annotate(n=Count("id"), block=Max("block_number"))
        .order_by()
    )
    for access_id, outcome, n, block in rows:
        counts[access_id][outcome] = n
        if block is not None:
            blocks[access_id] = max(block, blocks.get(access_id, block))
    for access in accesses:
        access.outcomes = counts.get(access.pk, {})
        access.outcome = next(iter(access.outcomes)) if len(access.outcomes) == 1 else "mixed"
        access.verified = access.outcomes.get(Verdict.Outcome.VERIFIED, 0)
        access.refused = sum(access.outcomes.values()) - access.verified
        access.block_number = blocks.get(access.pk)
    return accesses


def access_summary(access: Access) -> str:
    """What an access read, in words: "view", "page, 12 records", "plot, 18,000 records"."""
    if access.count == 1 and access.kind in (Access.Kind.VIEW, Access.Kind.CHECK):
        return access.get_kind_display()
    return f"{access.get_kind_display()}, {access.count:,} record{'s' if access.count != 1 else ''}"


def access_outcome_text(access: Access) -> str:
    """The checks' outcomes: the one outcome's label, or each outcome with its count."""
    if not access.outcomes:
        return "not checked yet"
    if access.count == 1 and len(access.outcomes) == 1:
        return _OUTCOME_LABELS.get(access.outcome, access.outcome)
    return ", ".join(
        f"{n:,} {_OUTCOME_LABELS.get(outcome, outcome)}"
        for outcome, n in sorted(access.outcomes.items(), key=lambda item: -item[1])
    )


def _rows(accesses: Iterable[Access], *, reader: Owner) -> list[Access]:
    shown = access_outcomes(access_log_redacted(accesses, reader=reader))
    for access in shown:
        access.credential_text = credential_label(access)
        access.summary = access_summary(access)
        access.outcome_text = access_outcome_text(access)
    return shown


def access_log_page(
    accesses: QuerySet[Access], *, reader: Owner, page: object, per_page: int
) -> Page:
    """One page of the log (a page past the last is the last, as Paginator.get_page gives
    it), each row with its `credential_text`, `summary` and `outcome_text`."""
    found = Paginator(accesses, per_page).get_page(page)
    found.object_list = _rows(found.object_list, reader=reader)
    return found


def csv_cell(value: object) -> str:
    """A value as a CSV cell that a spreadsheet shows as text, never runs as a formula."""
    if value is None:
        return ""
    text = value.isoformat() if isinstance(value, datetime) else str(value)
    if text.startswith(_FORMULA_STARTS):
        return "'" + text
    return text


def access_log_csv_row(access: Access) -> list[str]:
    record = access.record
    values = [
        access.pk,
        access.created_at,
        access.kind,
        access.count,
        access.viewer.username,
        access.record_owner.username,
        record.pk if record else None,
        access.robot.name if access.robot else None,
        access.robot_id,
        access.topic,
        record.data_type if record else None,
        record.seq if record else None,
        record.captured_at if record else None,
        access.outcome,
        access.verified,
        access.refused,
        access.credential or "not_recorded",
        access.token.name if access.token else "",
        access.token.token_prefix if access.token else "",
        access.checked_by.get_username() if access.checked_by else "",
    ]
    return [csv_cell(value) for value in values]


def access_log_csv(accesses: QuerySet[Access], *, reader: Owner) -> Iterator[str]:
    """The filtered log as CSV lines (a header first), newest first, read CSV_CHUNK rows at a
    time after the last one sent: no cursor held open between chunks, no OFFSET scans."""
    buffer = _Line()
    writer = csv.writer(buffer)
    writer.writerow(CSV_COLUMNS)
    yield buffer.take()
    ordered = accesses.order_by("-created_at", "-id")
    after: tuple[datetime, int] | None = None
    while True:
        chunk = ordered
        if after is not None:
            at, pk = after
            chunk = chunk.filter(Q(created_at__lt=at) | Q(created_at=at, id__lt=pk))
        rows = _rows(chunk[:CSV_CHUNK], reader=reader)
        writer.writerows(access_log_csv_row(access) for access in rows)
        if rows:
            yield buffer.take()
        if len(rows) < CSV_CHUNK:
            return
        after = (rows[-1].created_at, rows[-1].pk)


class _Line:
    """What csv.writer writes, taken a chunk at a time."""

    def __init__(self) -> None:
        self.text = ""

    def write(self, text: str) -> None:
        self.text += text

    def take(self) -> str:
        text, self.text = self.text, ""
        return text

"""The access log as people read it: who viewed which record, when, the verdict, and with
which credential; one page of it, or all of it as CSV.

The rows are the integrity verdicts every view leaves (sharing.models.Verdict), listed by
sharing.selectors.verdict_list_access_log and verdict_list_filtered. The CSV is streamed in
chunks read by keyset (time, id), so its memory does not grow with the log, and no cell can
start a spreadsheet formula.
"""

import csv
from collections.abc import Iterable, Iterator
from datetime import datetime

from django.core.paginator import Page, Paginator
from django.db.models import Q, QuerySet

from accounts.models import Owner
from sharing.models import Verdict

# Rows read from the database at a time while the CSV streams.
CSV_CHUNK = 500
# Characters a spreadsheet may take as the start of a formula (OWASP "CSV injection"); tab
# and carriage return too, which some spreadsheets strip before looking.
_FORMULA_STARTS = ("=", "+", "-", "@", "\t", "\r")

CSV_COLUMNS = [
    "id",
    "viewed_at",
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
    "credential",
    "token_name",
    "token_prefix",
    "operator",
    "block",
]


def credential_label(verdict: Verdict) -> str:
    """The credential a view was made with, as the page and the CSV say it."""
    if verdict.credential == Verdict.Credential.TOKEN:
        token = verdict.token
        if token is None:  # another owner's token (access_log_redacted)
            return "owner API token"
        return f"owner API token “{token.name}” ({token.token_prefix}…)"
    if verdict.credential == Verdict.Credential.OPERATOR:
        operator = verdict.checked_by.get_username() if verdict.checked_by else "a former operator"
        return f"operator check in the admin ({operator})"
    return verdict.get_credential_display()


def access_log_redacted(verdicts: Iterable[Verdict], *, reader: Owner) -> list[Verdict]:
    """The rows as `reader` may see them: a grantee's own API token (its name and prefix) is
    the grantee's business; the record's owner learns only that a token was used. Changed
    in memory only."""
    shown = list(verdicts)
    for verdict in shown:
        if verdict.token_id is not None and verdict.viewer_id != reader.pk:
            verdict.token = None
    return shown


def access_log_page(
    verdicts: QuerySet[Verdict], *, reader: Owner, page: object, per_page: int
) -> Page:
    """One page of the log (a page past the last is the last, as Paginator.get_page gives
    it), each row with its `credential_text`."""
    found = Paginator(verdicts, per_page).get_page(page)
    found.object_list = access_log_redacted(found.object_list, reader=reader)
    for verdict in found.object_list:
        verdict.credential_text = credential_label(verdict)
    return found


def csv_cell(value: object) -> str:
    """A value as a CSV cell that a spreadsheet shows as text, never runs as a formula."""
    if value is None:
        return ""
    text = value.isoformat() if isinstance(value, datetime) else str(value)
    if text.startswith(_FORMULA_STARTS):
        return "'" + text
    return text


def access_log_csv_row(verdict: Verdict) -> list[str]:
    record = verdict.record
    values = [
        verdict.pk,
        verdict.created_at,
        verdict.viewer.username,
        record.owner.username,
        record.pk,
        record.robot.name,
        record.robot_id,
        record.topic,
        record.data_type,
        record.seq,
        record.captured_at,
        verdict.outcome,
        verdict.credential or "not_recorded",
        verdict.token.name if verdict.token else "",
        verdict.token.token_prefix if verdict.token else "",
        verdict.checked_by.get_username() if verdict.checked_by else "",
        verdict.block_number,
    ]
    return [csv_cell(value) for value in values]


def access_log_csv(verdicts: QuerySet[Verdict], *, reader: Owner) -> Iterator[str]:
    """The filtered log as CSV lines (a header first), newest first, read CSV_CHUNK rows at a
    time after the last one sent: no cursor held open between chunks, no OFFSET scans."""
    buffer = _Line()
    writer = csv.writer(buffer)
    writer.writerow(CSV_COLUMNS)
    yield buffer.take()
    ordered = verdicts.order_by("-created_at", "-id")
    after: tuple[datetime, int] | None = None
    while True:
        chunk = ordered
        if after is not None:
            at, pk = after
            chunk = chunk.filter(Q(created_at__lt=at) | Q(created_at=at, id__lt=pk))
        rows = access_log_redacted(chunk[:CSV_CHUNK], reader=reader)
        writer.writerows(access_log_csv_row(verdict) for verdict in rows)
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

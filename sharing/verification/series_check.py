"""The worker's side of a series (`series_rows_check`, the task sharing.tasks.series_verify): a
slice of the series' records checked exactly as any read is (check.records_verify: access,
each envelope's SM3 against the chain's roots, the robot's key on chain, each distinct batch
signature verified once, one verdict each in bulk, all pointing to the plot's Access), then
only the plotted numbers of the verified ones handed back, sealed for the web process that
asked (verification/answers.py): no envelope in base64, no plaintext in the result backend.

The plaintext the check opened to verify a signature is read from it, not decrypted again; an
unsigned robot's record is decrypted here once.
"""

import uuid
from collections.abc import Sequence
from typing import Any

from accounts.models import OwnerKey
from sharing.models import Access
from sharing.series import record_values
from sharing.verification.answers import answer_key_unwrap, answer_seal
from sharing.verification.check import Verification, records_verify
from sharing.verification.keys import RecordKeys
from smcrypto.errors import CryptoError


def series_rows_check(
    *,
    record_ids: Sequence[uuid.UUID | str],
    viewer_id: int,
    credential: str,
    token_id: int | None,
    accesses: dict[int, int],
    fields: Sequence[str],
    read_id: str,
    answer_key: str,
    part: int,
) -> dict[str, Any]:
    """Check the records (one verdict each, under `accesses`, the plot's lines the web opened)
    and answer how many were verified, and the verified ones' rows `[t, v1, v2...]`
    (t the capture time in Unix seconds), in the order asked, sealed as part `part` of read
    `read_id` under its wrapped `answer_key` (unwrapped first: a key not wrapped for this read
    refuses the task before anything is checked)."""
    key = answer_key_unwrap(read_id=read_id, wrapped=answer_key)
    checked = records_verify(
        record_ids=record_ids,
        viewer_id=viewer_id,
        credential=credential,
        token_id=token_id,
        kind=Access.Kind.PLOT,
        accesses=accesses,
    )
    keys = RecordKeys()
    rows = []
    for verification in checked:
        plaintext = _plaintext(verification, keys)
        if plaintext is not None:
            moment = round(verification.verdict.record.captured_at.timestamp(), 6)
            rows.append([moment, *record_values(plaintext, fields)])
    return {
        "verified": len(rows),
        "rows": answer_seal(key=key, read_id=read_id, part=part, payload=rows),
    }


def _plaintext(verification: Verification, keys: RecordKeys) -> bytes | None:
    """A verified record's plaintext: the one its signature check opened, else decrypted from
    the bytes checked; None when it is not verified (or, anchored, does not open under its
    owner's key: never plotted)."""
    if verification.envelope is None:
        return None
    if verification.opened is not None:
        return verification.opened[1]
    record = verification.verdict.record
    try:
        _header, plaintext = keys.opening(record).open(verification.envelope)
    except (CryptoError, OwnerKey.DoesNotExist):
        return None
    return plaintext

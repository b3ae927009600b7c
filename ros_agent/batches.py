"""Provenance v2 on the robot: each upload batch signed once, every record counted (DESIGN.md
"Provenance v2", docs/provenance-batches.md).

A paired robot seals what it captures under the owner's key without a signature; the
uploader hands each batch to `BatchSigner.ready` before it leaves. For envelopes not yet
signed in a batch, it opens them (the keyring holds every key they may be sealed under),
gives each its `topic_seq` in its stream (signer = the hash of the robot's current public key,
topic), signs them once as one batch (smcrypto.provenance.sign_batch), re-seals each under the
same owner key with a new nonce and writes it back to the spool durably (`Spool.replace`), in
queue order; then it records the counters durably (`topic_seq` in the spool directory); only
then does the batch leave. Envelopes already signed in a batch by this key (the header has
`sig_size`) are sent as they are, never signed or numbered again: a resend after a crash, an
outage or a split sends the same bytes, and a rotation's re-seal keeps the header.

Counted without a skip or a reuse, across restarts: the counters file says, per signer and
topic, the next number. Each record's number is written into its envelope before the file,
and the file before any record it covers leaves the queue; so after a crash the next number
of a stream is the larger of the file's and one above the highest `topic_seq` of the
envelopes signed at the head of the queue (only the head is ever signed, in queue order, so a
record whose write did not happen has a number above every written one of its stream, and
gets it again). A record the portal refuses for good keeps its number: a gap the portal names
as missing. A new robot key (a new pairing) counts from 0 under its own signer, and envelopes
still spooled under the old key's batch signature are signed again by the new one.

    topic_seq   {"<signer>": {"<topic>": <next topic_seq>, ...}, ...}   (JSON)
"""

import json
import logging
from collections.abc import Mapping
from itertools import takewhile
from typing import Any

from ros_agent import LOGGER_NAME
from ros_agent.keyring import Keyring
from ros_agent.sealing import RobotSigningKey
from ros_agent.spool import Spool, SpoolError, SpoolItem
from smcrypto import CryptoError, envelope, provenance

logger = logging.getLogger(f"{LOGGER_NAME}.batches")

TOPIC_SEQ_FILE = "topic_seq"

Stream = tuple[str, str]  # (signer, topic)


class BatchSigner:
    """Signs a paired robot's head batch once, numbering its records; used by the uploader's
    one thread."""

    def __init__(self, *, spool: Spool, keyring: Keyring, signing_key: RobotSigningKey) -> None:
        self._spool = spool
        self._keyring = keyring
        self._signing_key = signing_key
        self.signer = provenance.key_hash(signing_key.public_key)
        self._next = topic_seq_read(spool)
        recorded = dict(self._next)
        for item in spool.head_while(lambda item: _batch_header(item) is not None):
            header = _batch_header(item)
            self._count((header["signer"], header["topic"]), header["topic_seq"])
        # numbers written into envelopes but not yet into the file (a crash between the two)
        self._unrecorded = self._next != recorded

    def ready(self, items: list[SpoolItem]) -> list[SpoolItem]:
        """The batch to send of the head `items` (the oldest queued, in order), every
        number in it recorded: the envelopes at its front this key signed already, as they
        are; else those not yet signed by it, signed now as one batch and written back.
        An envelope that cannot be opened is sent alone as it is, for the portal to refuse.
        OSError if the spool cannot be written (nothing leaves then)."""
        if self._signed_by_this_key(items[0]):
            batch = list(takewhile(self._signed_by_this_key, items))
        else:
            batch = self._sign(list(takewhile(lambda i: not self._signed_by_this_key(i), items)))
        if self._unrecorded:
            topic_seq_write(self._spool, self._next)
            self._unrecorded = False
        return batch

    def _sign(self, items: list[SpoolItem]) -> list[SpoolItem]:
        opened: list[tuple[SpoolItem, bytes, dict[str, Any], bytes]] = []
        for item in items:
            found = self._open(item)
            if found is None:
                if not opened:
                    return [item]
                break
            opened.append((item, *found))
        resigned = sum(1 for *_, header, _ in opened if "sig_size" in header)
        if resigned:
            logger.warning(
                "%d envelope(s) from seq %d were signed by another robot key (paired again?): "
                "signed again, and counted, with this robot's key %s",
                resigned,
                opened[0][0].seq,
                self.signer[:16],
            )
        numbered = []
        taken: dict[Stream, int] = {}
        for _, _, header, plaintext in opened:
            stream = (self.signer, header["topic"])
            topic_seq = taken.get(stream, self._next.get(stream, 0))
            taken[stream] = topic_seq + 1
            numbered.append(({**header, "topic_seq": topic_seq}, plaintext))
        headers = provenance.sign_batch(
            self._signing_key.private_key, self._signing_key.public_key, numbered
        )
        signed = []
        for (item, key, _, plaintext), header in zip(opened, headers, strict=True):
            data = envelope.seal(key, header, plaintext)
            self._spool.replace(item.seq, data)
            # counted as soon as written: a failed write later in the batch leaves it used
            self._count((self.signer, header["topic"]), header["topic_seq"])
            self._unrecorded = True
            signed.append(SpoolItem(item.seq, data))
        return signed

    def _count(self, stream: Stream, topic_seq: int) -> None:
        self._next[stream] = max(self._next.get(stream, 0), topic_seq + 1)

    def _signed_by_this_key(self, item: SpoolItem) -> bool:
        header = _batch_header(item)
        return header is not None and header["signer"] == self.signer

    def _open(self, item: SpoolItem) -> tuple[bytes, dict[str, Any], bytes] | None:
        """(its key, header, plaintext), or None (logged) for one this robot cannot open."""
        try:
            key_id = envelope.read_header(item.envelope).key_id.hex()
            key = self._keyring.get(key_id)
            if key is None:
                logger.error(
                    "cannot sign seq %d: it is sealed under key %s, which this robot does not "
                    "hold; sent unsigned, for the portal to refuse",
                    item.seq,
                    key_id,
                )
                return None
            header, plaintext = envelope.open(key, item.envelope)
        except CryptoError as exc:
            logger.error(
                "cannot sign seq %d: %s; sent as it is, for the portal to refuse", item.seq, exc
            )
            return None
        return key, header, plaintext


def _batch_header(item: SpoolItem) -> dict[str, Any] | None:
    """The header of an envelope signed in a batch (v2), else None."""
    try:
        header = envelope.read_header(item.envelope).header
    except CryptoError:
        return None
    return header if envelope.provenance_format(header) == "v2" else None


def topic_seq_read(spool: Spool) -> dict[Stream, int]:
    """The next `topic_seq` per (signer, topic) as last recorded in the spool (empty at first).
    SpoolError if the file is not what this module writes."""
    data = spool.state_read(TOPIC_SEQ_FILE)
    if data is None:
        return {}
    try:
        document = json.loads(data)
        counters = {
            (str(signer), str(topic)): value
            for signer, topics in document.items()
            for topic, value in topics.items()
        }
    except (ValueError, AttributeError) as exc:
        counters, problem = {}, str(exc)
    else:
        wrong = [value for value in counters.values() if type(value) is not int or value < 0]
        problem = f"a count of {wrong[0]!r}" if wrong else ""
    if problem:
        raise SpoolError(
            f"{spool.directory / TOPIC_SEQ_FILE} does not hold record counters ({problem}); "
            "it is written atomically, so something else changed it"
        )
    return counters


def topic_seq_write(spool: Spool, counters: Mapping[Stream, int]) -> None:
    """Record the next `topic_seq` per (signer, topic) durably in the spool."""
    document: dict[str, dict[str, int]] = {}
    for (signer, topic), value in counters.items():
        document.setdefault(signer, {})[topic] = value
    spool.state_write(TOPIC_SEQ_FILE, (json.dumps(document, sort_keys=True) + "\n").encode())

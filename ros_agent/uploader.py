"""Send the spool to the portal in order, in batches: nothing lost, nothing sent twice.

`POST {portal}/api/v1/records/` with `Authorization: Token <token>` and
`{"envelopes": [base64, ...]}`; the portal stores a batch all or nothing and answers 201 with
one `{"id", "digest", "status"}` per envelope. What the uploader does with each answer:

| answer                                | what happens                                          |
|---------------------------------------|-------------------------------------------------------|
| 201 with one result per envelope      | delivered: removed from the spool                     |
| 409 replayed_sequence, one envelope   | delivered before (its 201 was lost): removed          |
| 409 replayed_sequence, a batch        | the batch is sent again one by one, to see which      |
| 409 sequence_conflict, one envelope   | the portal holds other data under that seq: refused,  |
|                                       | moved to rejected/, an error that names a stolen token|
| 400/403/413/other 4xx, one envelope   | refused for good: moved to rejected/, counted failed  |
| 400/403/413/other 4xx, a batch        | sent again one by one, so only the bad one is refused |
| 403 unknown_key, on a paired robot    | the owner rotated its key: the new key is fetched     |
|                                       | (SM2-encrypted to the robot) and the refused envelopes|
|                                       | are re-sealed under it in the spool and sent again    |
| 401, 404, 405                         | our token or URL is wrong: kept, retried with backoff |
| 408, 429, 5xx, no answer, 201 without | kept, retried after an exponential backoff with       |
| a result per envelope, anything else  | jitter, capped; Retry-After honoured up to that cap   |

A later envelope is never sent before an earlier one: the head of the queue is retried until
it is delivered or refused.

A paired robot signs each batch once before it leaves (provenance v2, ros_agent.batches): its
envelopes are numbered (`topic_seq`), signed and written back to the spool, so a retry, a
split or a resend after a crash sends the very bytes signed first. A record refused for good
keeps its number, and the portal will show it as missing: the log says which.

Every answer to a paired robot's upload names the owner's current key (header
`AuthROS-Key-Id`); when it sees another id than its own it fetches the new key at once
(`key_updater`), so that what it records from then on is sealed under it. A rotation never
sends anything to rejected/: envelopes captured before it are accepted under the old key, the
others re-sealed, header, signature and `topic_seq` unchanged (a batch signature does not
cover the key an envelope is sealed under).
"""

import base64
import enum
import logging
import random
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from datetime import UTC, datetime
from email.utils import parsedate_to_datetime
from typing import Any

import requests

from ros_agent import LOGGER_NAME
from ros_agent.batches import BatchSigner
from ros_agent.counters import AgentCounters, worth_logging
from ros_agent.keyring import Keyring
from ros_agent.sealing import RobotSigningKey
from ros_agent.spool import Spool, SpoolItem
from smcrypto import CryptoError, envelope

logger = logging.getLogger(f"{LOGGER_NAME}.uploader")

REPLAYED_SEQUENCE = "replayed_sequence"
SEQUENCE_CONFLICT = "sequence_conflict"
TOPIC_SEQ_REUSED = "topic_seq_reused"
UNKNOWN_KEY = "unknown_key"
KEY_ID_HEADER = "AuthROS-Key-Id"
_OUR_MISTAKE = frozenset({401, 404, 405})
_TRANSIENT = frozenset({408, 425, 429})
BACKOFF_BASE = 0.5


@dataclass(frozen=True)
class PortalAnswer:
    """The portal's answer to one upload; status None when there was no HTTP answer."""

    status: int | None
    body: Any = None
    error: str = ""
    detail: str = ""
    retry_after: float | None = None
    key_id: str = ""  # the owner's current key, as the portal named it

    def describe(self) -> str:
        if self.status is None:
            return f"no answer ({self.detail})"
        return f"HTTP {self.status} {self.error or ''}: {self.detail or ''}".strip(" :")


class PortalClient:
    """Uploads envelopes to the portal's records endpoint with the robot's token."""

    def __init__(
        self,
        *,
        records_url: str,
        token: str,
        tls_verify: bool | str = True,
        timeout: float = 10,
        robot_key_url: str = "",
    ) -> None:
        self.records_url = records_url
        self.robot_key_url = robot_key_url
        self._timeout = timeout
        self._verify = tls_verify
        self._session = requests.Session()
        self._session.headers.update({"Authorization": f"Token {token}"})

    def upload(self, envelopes: Sequence[bytes]) -> PortalAnswer:
        body = {"envelopes": [base64.b64encode(data).decode("ascii") for data in envelopes]}
        return self._call("POST", self.records_url, json=body)

    def fetch_key(self) -> PortalAnswer:
        """`GET /api/v1/robot-key/`: the owner's current key, SM2-encrypted to this robot."""
        return self._call("GET", self.robot_key_url)

    def _call(self, method: str, url: str, **kwargs: Any) -> PortalAnswer:
        try:
            response = self._session.request(
                method,
                url,
                timeout=self._timeout,
                verify=self._verify,
                allow_redirects=False,
                **kwargs,
            )
        except requests.RequestException as exc:
            return PortalAnswer(status=None, detail=f"{type(exc).__name__}: {exc}")
        try:
            payload = response.json()
        except ValueError:
            payload = None
        error = detail = ""
        if isinstance(payload, dict):
            error = str(payload.get("error", ""))
            detail = str(payload.get("detail", ""))
        elif response.status_code >= 300:
            detail = response.text[:200]
        return PortalAnswer(
            status=response.status_code,
            body=payload,
            error=error,
            detail=detail,
            retry_after=_retry_after(response.headers.get("Retry-After")),
            key_id=response.headers.get(KEY_ID_HEADER, "").strip().lower(),
        )

    def close(self) -> None:
        self._session.close()


class Outcome(enum.Enum):
    EMPTY = "nothing queued"
    DELIVERED = "delivered"
    SPLIT = "batch to be resent one by one"
    RESEALED = "re-sealed under the owner's new key, to be sent again"
    REJECTED = "refused for good"
    RETRY = "kept for a retry"


class Uploader:
    """Drains the spool to the portal from its own thread (or step by step, for tests)."""

    def __init__(
        self,
        *,
        spool: Spool,
        client: PortalClient,
        counters: AgentCounters,
        batch_size: int = 50,
        batch_max_bytes: int = 1024 * 1024,
        flush_interval: float = 1.0,
        backoff_max: float = 30.0,
        backoff_base: float = BACKOFF_BASE,
        keyring: Keyring | None = None,
        key_updater: Callable[[], bool | None] | None = None,
        signing_key: RobotSigningKey | None = None,
    ) -> None:
        """`key_updater` (a paired robot's) fetches the owner's current key into `keyring`:
        True when it got one, False when the portal refused, None without an answer. With
        `signing_key` (a paired robot's) each batch is signed once before it leaves, its
        envelopes opened with `keyring`'s keys; SpoolError if the spool's record counters
        are unreadable."""
        if key_updater is not None and keyring is None:
            raise ValueError("a key updater needs the keyring it updates")
        if signing_key is not None and keyring is None:
            raise ValueError("signing batches needs the keyring their envelopes are sealed under")
        self._keyring = keyring
        self._key_updater = key_updater
        self._batch_signer = (
            BatchSigner(spool=spool, keyring=keyring, signing_key=signing_key)
            if signing_key is not None and keyring is not None
            else None
        )
        self._key_asked_for: str | None = None
        self._spool = spool
        self._client = client
        self._counters = counters
        self._batch_size = batch_size
        self._batch_max_bytes = batch_max_bytes
        self._flush_interval = flush_interval
        self._backoff_max = backoff_max
        self._backoff_base = backoff_base
        self._failures = 0
        self._retry_after: float | None = None
        self._one_by_one_through: int | None = None
        self._wake = threading.Event()
        self._stopping = threading.Event()
        self._flush_deadline = 0.0
        self._thread: threading.Thread | None = None

    # --- the thread --------------------------------------------------------------------------

    def start(self) -> None:
        self._thread = threading.Thread(target=self._run, name="authros-uploader", daemon=True)
        self._thread.start()

    def notify(self) -> None:
        """Something was spooled: look again whether a batch is ready."""
        self._wake.set()

    def stop(self, flush_timeout: float) -> None:
        """Send what can be sent within flush_timeout seconds, then stop; the spool keeps the rest.

        Called once, from the thread that started it.
        """
        self._flush_deadline = time.monotonic() + flush_timeout
        self._stopping.set()
        self._wake.set()
        if self._thread is not None:
            self._thread.join(flush_timeout + 1)
            if self._thread.is_alive():
                logger.warning("uploader still waiting for the portal at shutdown; leaving it")
        self._client.close()

    def _run(self) -> None:
        if self._key_updater is not None:
            self._key_updater()  # a rotation while the robot was off: learnt before sending
        waiting_since: float | None = None
        while not self._stopping.is_set():
            if not self._batch_ready():
                now = time.monotonic()
                if len(self._spool) == 0:
                    waiting_since = None
                    timeout = self._flush_interval
                else:
                    waiting_since = waiting_since or now
                    timeout = self._flush_interval - (now - waiting_since)
                if timeout > 0:
                    self._wake.wait(timeout)
                    self._wake.clear()
                    continue
            waiting_since = None
            outcome = self.deliver_next()
            if outcome is Outcome.RETRY:
                self._stopping.wait(self.next_backoff())
        self._flush_at_shutdown()

    def _flush_at_shutdown(self) -> None:
        while time.monotonic() < self._flush_deadline:
            outcome = self.deliver_next()
            if outcome in (Outcome.EMPTY, Outcome.RETRY):
                break
        left = len(self._spool)
        if left:
            logger.info(
                "%d envelope(s) stay in the spool %s for later", left, self._spool.directory
            )

    def _batch_ready(self) -> bool:
        return (
            self._one_by_one_through is not None
            or len(self._spool) >= self._batch_size
            or self._spool.queued_bytes >= self._batch_max_bytes
        )

    # --- one step ----------------------------------------------------------------------------

    def deliver_next(self) -> Outcome:
        """Send the oldest queued batch once and act on the portal's answer."""
        items = self._next_batch()
        if not items:
            return Outcome.EMPTY
        if self._batch_signer is not None:
            try:
                items = self._batch_signer.ready(items)
            except OSError as exc:
                logger.error(
                    "cannot write the signed batch from seq %d to the spool %s: %s; kept, retrying",
                    items[0].seq,
                    self._spool.directory,
                    exc,
                )
                return Outcome.RETRY
        answer = self._client.upload([item.envelope for item in items])
        return self._settle(items, answer)

    def drain(self) -> Outcome:
        """Deliver until the queue is empty or the portal asks us to wait (for tests, tools)."""
        while True:
            outcome = self.deliver_next()
            if outcome in (Outcome.EMPTY, Outcome.RETRY):
                return outcome

    def next_backoff(self) -> float:
        """Seconds to wait before retrying after one more failure in a row."""
        self._failures += 1
        ceiling = min(self._backoff_max, self._backoff_base * 2 ** min(self._failures - 1, 30))
        delay = random.uniform(ceiling / 2, ceiling)
        if self._retry_after:
            delay = max(delay, min(self._retry_after, self._backoff_max))
        return delay

    def _next_batch(self) -> list[SpoolItem]:
        if self._one_by_one_through is not None:
            head = self._spool.peek(1)
            if head and head[0].seq <= self._one_by_one_through:
                return head
            self._one_by_one_through = None
        return self._spool.peek(self._batch_size, max_bytes=self._batch_max_bytes)

    def _settle(self, items: list[SpoolItem], answer: PortalAnswer) -> Outcome:
        self._retry_after = answer.retry_after
        outcome = self._act_on(items, answer)
        if outcome is not Outcome.RETRY and self._failures:
            logger.info(
                "the portal answers again after %d failed attempt(s); %d queued",
                self._failures,
                len(self._spool),
            )
            self._failures = 0
        return outcome

    def _act_on(self, items: list[SpoolItem], answer: PortalAnswer) -> Outcome:
        seqs = _seq_range(items)
        status = answer.status
        self._note_current_key(answer.key_id)
        if status == 403 and answer.error == UNKNOWN_KEY and self._key_updater is not None:
            resealed = self._reseal(items)
            if resealed is not None:
                return resealed
        if status == 201 and _confirms(answer.body, len(items)):
            self._delivered(items)
            return Outcome.DELIVERED
        if status == 409 and answer.error == REPLAYED_SEQUENCE:
            if len(items) == 1:
                logger.warning(
                    "the portal already has seq %s (its confirmation was lost): "
                    "counted as delivered, not sent again",
                    seqs,
                )
                self._delivered(items)
                return Outcome.DELIVERED
            return self._split(items, answer)
        if status is not None and 400 <= status < 500:
            if status in _OUR_MISTAKE:
                return self._retry(items, answer, level=logging.ERROR)
            if status not in _TRANSIENT:
                if len(items) > 1:
                    return self._split(items, answer)
                self._reject(items, answer)
                return Outcome.REJECTED
        return self._retry(items, answer, level=logging.WARNING)

    def _note_current_key(self, advertised: str) -> None:
        """Fetch the owner's key when the portal names another current key than ours (once
        per name, unless the fetch got no answer)."""
        if (
            self._key_updater is None
            or not advertised
            or advertised == self._keyring.current_id
            or advertised == self._key_asked_for
        ):
            return
        logger.info("the owner's current key is now %s: fetching it from the portal", advertised)
        if self._key_updater() is not None:
            self._key_asked_for = advertised

    def _reseal(self, items: list[SpoolItem]) -> Outcome | None:
        """The portal refused envelopes sealed under a key it no longer takes for them: fetch
        the current key and re-seal, in the spool, those we hold the old key of, their header
        as it is (a batch's signature and `topic_seq` stay). RETRY when the key cannot be
        fetched now; None when nothing could be re-sealed."""
        if self._key_updater() is None:
            return Outcome.RETRY
        current_id, key = self._keyring.current()
        resealed = 0
        for item in items:
            try:
                old_id = envelope.read_header(item.envelope).key_id.hex()
                old_key = self._keyring.get(old_id)
                if old_id == current_id or old_key is None:
                    continue
                header, plaintext = envelope.open(old_key, item.envelope)
            except CryptoError as exc:
                logger.error("cannot re-seal seq %d: %s", item.seq, exc)
                continue
            self._spool.replace(item.seq, envelope.seal(key, header, plaintext))
            resealed += 1
        if not resealed:
            return None
        logger.warning(
            "re-sealed %d envelope(s) of seq %s under the owner's new key %s; sending them again",
            resealed,
            _seq_range(items),
            current_id,
        )
        return Outcome.RESEALED

    def _delivered(self, items: list[SpoolItem]) -> None:
        self._spool.ack(items)
        self._counters.add("sent", len(items))

    def _split(self, items: list[SpoolItem], answer: PortalAnswer) -> Outcome:
        logger.info(
            "the portal refused the batch %s (%s): sending it one by one",
            _seq_range(items),
            answer.describe(),
        )
        self._one_by_one_through = items[-1].seq
        return Outcome.SPLIT

    def _reject(self, items: list[SpoolItem], answer: PortalAnswer) -> None:
        self._spool.reject(
            items,
            {
                "status": answer.status,
                "error": answer.error,
                "detail": answer.detail,
                "rejected_at": datetime.now(UTC).isoformat(),
            },
        )
        failed = self._counters.add("failed", len(items))
        if answer.error == SEQUENCE_CONFLICT:
            logger.error(
                "the portal holds other data under seq %s of this robot: the robot lost its "
                "state, or someone else uploads with its token and key. Check the robot, and "
                "revoke its token in the portal if it is not in your hands",
                _seq_range(items),
            )
        if answer.error == TOPIC_SEQ_REUSED:
            logger.error(
                "the portal already holds records under the topic_seq of seq %s for this "
                "robot's key: the robot lost its spool (and with it its record counters), or "
                "someone else signs with its key. Pair the robot again (a new key counts from 0); "
                "if the spool was not lost, treat the pairing key as stolen",
                _seq_range(items),
            )
        logger.error(
            "the portal refused seq %s for good (%s): moved to %s/rejected (%d failed so far)",
            _seq_range(items),
            answer.describe(),
            self._spool.directory,
            failed,
        )
        for item in items:
            try:
                header = envelope.read_header(item.envelope).header
            except CryptoError:
                continue
            if "topic_seq" in header:
                logger.error(
                    "topic_seq %d of %s (seq %d) will never reach the portal: a gap in this "
                    "robot's records that the portal will show as missing",
                    header["topic_seq"],
                    header["topic"],
                    item.seq,
                )

    def _retry(self, items: list[SpoolItem], answer: PortalAnswer, *, level: int) -> Outcome:
        if worth_logging(self._failures + 1):
            logger.log(
                level,
                "could not deliver seq %s to %s: %s; %d queued, retrying (attempt %d)",
                _seq_range(items),
                self._client.records_url,
                answer.describe(),
                len(self._spool),
                self._failures + 1,
            )
        return Outcome.RETRY


def _confirms(body: Any, count: int) -> bool:
    results = [body] if count == 1 and isinstance(body, dict) else body
    return (
        isinstance(results, list)
        and len(results) == count
        and all(isinstance(result, dict) and "id" in result for result in results)
    )


def _seq_range(items: Sequence[SpoolItem]) -> str:
    first, last = items[0].seq, items[-1].seq
    return str(first) if first == last else f"{first}..{last}"


def _retry_after(value: str | None) -> float | None:
    if not value:
        return None
    try:
        return max(0.0, float(value))
    except ValueError:
        pass
    try:
        moment = parsedate_to_datetime(value)
    except (TypeError, ValueError):
        return None
    return max(0.0, (moment - datetime.now(UTC)).total_seconds())

"""An in-test stand-in for the portal's records endpoint (DESIGN.md "REST API for agents").

It keeps the contract the agent relies on: `POST /api/v1/records/` with `Authorization:
Token <token>` and `{"envelope": b64}` or `{"envelopes": [b64, ...]}`; every envelope must
parse, name this robot and owner, open under the owner's key, and the batch's sequence numbers
must strictly increase and lie above every one stored before (else 409: replayed_sequence
if these very envelopes are stored already, sequence_conflict if not). A
batch is stored all or nothing; 201 answers one `{"id", "digest", "status"}` per envelope.
Errors are `{"error": code, "detail": text}`.

For a paired robot (`robot_public_key` set) every envelope must also carry this robot's valid
signature (DESIGN.md "Provenance"), else 400 `invalid_signature`, as the portal refuses
unsigned or wrongly signed uploads of a paired robot.

Faults on demand: `stop()` closes the port (connection refused) and `start()` opens it again
on the same port; `fail_next(status)` answers the next requests with an error; `lose_next()`
stores the next upload and then drops the connection without answering, as if the portal had
stored it and the agent had crashed before reading the 201.
"""

from __future__ import annotations

import base64
import binascii
import json
import threading
import uuid
from collections import deque
from dataclasses import dataclass, field
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from typing import Any

from smcrypto import CryptoError, SignatureInvalid, envelope, provenance
from smcrypto.errors import WrongKey
from stack.anvil import free_port

RECORDS_PATH = "/api/v1/records/"


@dataclass(frozen=True)
class StoredRecord:
    id: str
    seq: int
    header: dict[str, Any]
    record: dict[str, Any]  # the decrypted Fig. 4 JSON
    envelope: bytes


@dataclass(frozen=True)
class UploadLog:
    status: int | None  # None: connection dropped without an answer
    seqs: list[int]


@dataclass
class _Fault:
    status: int
    error: str
    retry_after: str | None = None


class PortalRefusal(Exception):
    def __init__(self, status: int, error: str, detail: str) -> None:
        super().__init__(detail)
        self.status, self.error, self.detail = status, error, detail


@dataclass
class RecordsServer:
    token: str
    key: bytes
    owner: str
    robot: str
    max_body_bytes: int = 4 * 1024 * 1024
    robot_public_key: str | None = None  # a paired robot's: its signature is required
    port: int = field(default_factory=free_port)
    records: list[StoredRecord] = field(default_factory=list)
    uploads: list[UploadLog] = field(default_factory=list)
    last_seq: int = -1

    def __post_init__(self) -> None:
        self._lock = threading.Lock()
        self._faults: deque[_Fault] = deque()
        self._lose = 0
        self._httpd: ThreadingHTTPServer | None = None
        self._thread: threading.Thread | None = None

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.port}"

    @property
    def seqs(self) -> list[int]:
        with self._lock:
            return [record.seq for record in self.records]

    def start(self) -> None:
        handler = type("Handler", (_Handler,), {"portal": self})
        self._httpd = ThreadingHTTPServer(("127.0.0.1", self.port), handler)
        self._httpd.daemon_threads = True
        self._thread = threading.Thread(target=self._httpd.serve_forever, args=(0.05,), daemon=True)
        self._thread.start()

    def stop(self) -> None:
        if self._httpd is not None:
            self._httpd.shutdown()
            self._httpd.server_close()
            self._thread.join(5)
            self._httpd = None

    def fail_next(self, status: int, *, times: int = 1, retry_after: str | None = None) -> None:
        error = {429: "throttled", 503: "unavailable"}.get(status, "failure")
        with self._lock:
            self._faults.extend(_Fault(status, error, retry_after) for _ in range(times))

    def lose_next(self, times: int = 1) -> None:
        with self._lock:
            self._lose += times

    def store(self, envelopes: list[bytes]) -> list[dict[str, Any]]:
        """Check and store a batch as the portal would; raise PortalRefusal if it would not."""
        checked = [self._check(data) for data in envelopes]
        seqs = [header["seq"] for header, _ in checked]
        if seqs != sorted(set(seqs)):
            raise PortalRefusal(
                400, "invalid_envelope", "sequence numbers in one upload must strictly increase"
            )
        with self._lock:
            if seqs[0] <= self.last_seq:
                held = {record.seq: record.envelope for record in self.records}
                replay = all(
                    held.get(seq) == data for seq, data in zip(seqs, envelopes, strict=True)
                )
                raise PortalRefusal(
                    409,
                    "replayed_sequence" if replay else "sequence_conflict",
                    f"seq {seqs[0]} is not above {self.last_seq}, the last one of this robot",
                )
            stored = []
            for data, (header, plaintext) in zip(envelopes, checked, strict=True):
                record = StoredRecord(
                    id=str(uuid.uuid4()),
                    seq=header["seq"],
                    header=header,
                    record=json.loads(plaintext),
                    envelope=data,
                )
                self.records.append(record)
                stored.append(
                    {"id": record.id, "digest": envelope.digest(data).hex(), "status": "pending"}
                )
            self.last_seq = seqs[-1]
            return stored

    def _check(self, data: bytes) -> tuple[dict[str, Any], bytes]:
        try:
            info = envelope.read_header(data)
        except CryptoError as exc:
            raise PortalRefusal(400, "invalid_envelope", str(exc)) from None
        if info.header["owner"] != self.owner or info.header["robot"] != self.robot:
            raise PortalRefusal(
                403, "header_mismatch", "the envelope's owner and robot must be this robot's"
            )
        try:
            header, plaintext = envelope.open(self.key, data)
        except WrongKey:
            raise PortalRefusal(
                403, "unknown_key", "the envelope is not sealed under the owner's current key"
            ) from None
        except CryptoError:
            raise PortalRefusal(
                403, "forged_envelope", "the envelope does not open under the owner's key"
            ) from None
        if self.robot_public_key is not None:
            try:
                provenance.signature_check(self.robot_public_key, header, plaintext)
            except SignatureInvalid as exc:
                raise PortalRefusal(400, "invalid_signature", f"{exc.reason}: {exc}") from None
        return header, plaintext

    def _take_fault(self) -> _Fault | None:
        with self._lock:
            return self._faults.popleft() if self._faults else None

    def _take_loss(self) -> bool:
        with self._lock:
            if self._lose:
                self._lose -= 1
                return True
            return False


class _Handler(BaseHTTPRequestHandler):
    portal: RecordsServer

    def log_message(self, format: str, *args: Any) -> None:
        pass

    def do_POST(self) -> None:
        if self.path != RECORDS_PATH:
            return self._answer(404, {"error": "not_found", "detail": self.path})
        if self.headers.get("Authorization") != f"Token {self.portal.token}":
            return self._answer(401, {"error": "not_authenticated", "detail": "bad token"})
        length = int(self.headers.get("Content-Length") or 0)
        if length > self.portal.max_body_bytes:
            return self._answer(413, {"error": "request_too_large", "detail": f"{length} bytes"})
        body = self.rfile.read(length)
        fault = self.portal._take_fault()
        if fault is not None:
            self.portal.uploads.append(UploadLog(fault.status, []))
            headers = {"Retry-After": fault.retry_after} if fault.retry_after else {}
            return self._answer(fault.status, {"error": fault.error, "detail": ""}, headers)
        try:
            single, envelopes = _parse(body)
            stored = self.portal.store(envelopes)
        except PortalRefusal as refusal:
            self.portal.uploads.append(UploadLog(refusal.status, []))
            return self._answer(refusal.status, {"error": refusal.error, "detail": refusal.detail})
        seqs = [envelope.read_header(data).header["seq"] for data in envelopes]
        if self.portal._take_loss():
            self.portal.uploads.append(UploadLog(None, seqs))
            self.close_connection = True
            return None
        self.portal.uploads.append(UploadLog(201, seqs))
        return self._answer(201, stored[0] if single else stored)

    def _answer(self, status: int, payload: Any, headers: dict[str, str] | None = None) -> None:
        data = json.dumps(payload).encode()
        self.send_response(status)
        self.send_header("Content-Type", "application/json")
        self.send_header("Content-Length", str(len(data)))
        for name, value in (headers or {}).items():
            self.send_header(name, value)
        self.end_headers()
        self.wfile.write(data)


def _parse(body: bytes) -> tuple[bool, list[bytes]]:
    try:
        payload = json.loads(body)
    except ValueError:
        raise PortalRefusal(400, "invalid_request", "the body is not JSON") from None
    if isinstance(payload, dict) and isinstance(payload.get("envelope"), str):
        single, encoded = True, [payload["envelope"]]
    elif isinstance(payload, dict) and isinstance(payload.get("envelopes"), list):
        single, encoded = False, payload["envelopes"]
    else:
        raise PortalRefusal(400, "invalid_request", 'expected "envelope" or "envelopes"')
    if not encoded or not all(isinstance(item, str) for item in encoded):
        raise PortalRefusal(400, "invalid_request", "envelopes must be a non-empty list of base64")
    try:
        return single, [base64.b64decode(item, validate=True) for item in encoded]
    except (binascii.Error, ValueError):
        raise PortalRefusal(400, "invalid_envelope", "an envelope is not base64") from None

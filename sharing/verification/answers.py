"""A read's answer sealed between the web process that asked and the worker that checked, so that
what the worker decrypted never sits in Redis (the Celery result backend) in plaintext.

The web makes a random SM4 key per read (`answer_key_make`) and sends it to the worker wrapped
under the KEK (accounts.keywrap, purpose `read-answer:<read id>`: a wrapped key copied to another
read does not open); the worker seals each part of its answer under it with SM4-GCM
(`answer_seal`), the read id and the part's number in the authenticated data, so that a part
cannot be swapped for another read's or another part's; the web, which never sent the key in
clear, opens them (`answer_open`). The key lives for one read in the web's memory only.
"""

import base64
import json
import secrets
import uuid
from dataclasses import dataclass, field

from accounts import keywrap
from smcrypto import sm4

ANSWER_DOMAIN = b"AuthROS/read-answer/v1"


@dataclass(frozen=True)
class AnswerKey:
    """One read's answer key: the id it is wrapped for, and the key wrapped (base64) to send."""

    read_id: str
    wrapped: str
    key: bytes = field(repr=False)


def answer_key_make() -> AnswerKey:
    read_id = uuid.uuid4().hex
    key = sm4.generate_key()
    wrapped = keywrap.wrap(key, purpose=_purpose(read_id))
    return AnswerKey(read_id, base64.b64encode(wrapped).decode("ascii"), key)


def answer_key_unwrap(*, read_id: str, wrapped: str) -> bytes:
    """The worker's copy of the read's key (keywrap.UnwrapFailed if it was not wrapped for
    this read), unwrapped before anything is checked."""
    return keywrap.unwrap(base64.b64decode(wrapped), purpose=_purpose(read_id))


def answer_seal(*, key: bytes, read_id: str, part: int, payload: object) -> str:
    """`payload` (plain JSON) sealed for the read: base64 of nonce || SM4-GCM ciphertext."""
    nonce = secrets.token_bytes(sm4.GCM_NONCE_SIZE)
    data = json.dumps(payload, separators=(",", ":"), allow_nan=False).encode()
    sealed = nonce + sm4.gcm_encrypt(key, nonce, data, _aad(read_id, part))
    return base64.b64encode(sealed).decode("ascii")


def answer_open(*, key: AnswerKey, part: int, sealed: str) -> object:
    """The payload of one part sealed for this read. smcrypto's AuthenticationFailed if it was
    not sealed under this read's key as this part."""
    raw = base64.b64decode(sealed)
    nonce, data = raw[: sm4.GCM_NONCE_SIZE], raw[sm4.GCM_NONCE_SIZE :]
    return json.loads(sm4.gcm_decrypt(key.key, nonce, data, _aad(key.read_id, part)))


def _purpose(read_id: str) -> str:
    return f"read-answer:{read_id}"


def _aad(read_id: str, part: int) -> bytes:
    return b"|".join((ANSWER_DOMAIN, read_id.encode(), str(part).encode()))

"""What `authros_verify record` asks the portal, and the caller's secrets it reads.

The portal is asked, never trusted: its two answers (the record's content, re-sealed under the
caller's key, and its proof) are checked by authros_verify/record.py against each other, the
caller's own key and the chain. docs/api.md describes both answers.
"""

import stat
import uuid
from pathlib import Path
from typing import Any

import requests

KEY_SIZE = 16  # SM4


class PortalUnusable(Exception):
    """The portal cannot be asked, or would not answer (the record was not checked)."""


class SecretUnusable(Exception):
    """A key or token file that cannot be read, or that others may read."""


class PortalClient:
    """GETs of the portal's REST API with an owner API token (`Authorization: Token ...`)."""

    def __init__(self, url: str, token: str, *, timeout: float = 120.0) -> None:
        self.url = url.rstrip("/")
        self._session = requests.Session()
        self._session.headers.update(
            {"Authorization": f"Token {token}", "Accept": "application/json"}
        )
        self.timeout = timeout

    def record_answers(self, record: uuid.UUID) -> tuple[dict[str, Any], dict[str, Any]]:
        """The record's (content, proof) answers."""
        proof = self._get(f"/api/v1/records/{record}/proof/")
        content = self._get(f"/api/v1/records/{record}/content/")
        return content, proof

    def _get(self, path: str) -> dict[str, Any]:
        try:
            answer = self._session.get(self.url + path, timeout=self.timeout)
        except requests.RequestException as exc:
            raise PortalUnusable(f"the portal cannot be reached at {self.url}: {exc}") from None
        try:
            body = answer.json()
        except ValueError:
            body = None
        if answer.status_code != 200:
            error = body if isinstance(body, dict) else {}
            raise PortalUnusable(
                f"the portal answered {answer.status_code} to GET {path}: "
                f"{error.get('error', 'no error code')}: {error.get('detail', answer.reason)}"
            )
        if not isinstance(body, dict):
            raise PortalUnusable(f"the portal's answer to GET {path} is not a JSON object")
        return body


def read_key_file(path: Path) -> bytes:
    """The caller's SM4 key: 32 hex digits in a file only its owner may read (as the agent's
    key file, ros_agent/config.py)."""
    text = _read_private_file(path, "key file")
    try:
        key = bytes.fromhex(text)
    except ValueError:
        key = b""
    if len(key) != KEY_SIZE:
        raise SecretUnusable(f"the key file {path} must hold the SM4 key as 32 hex digits")
    return key


def read_token_file(path: Path) -> str:
    token = _read_private_file(path, "token file")
    if not token:
        raise SecretUnusable(f"the token file {path} is empty")
    return token


def _read_private_file(path: Path, what: str) -> str:
    try:
        mode = path.stat().st_mode
    except OSError as exc:
        raise SecretUnusable(f"cannot read the {what} {path}: {exc.strerror}") from None
    if not stat.S_ISREG(mode):
        raise SecretUnusable(f"the {what} {path} is not a regular file")
    if mode & 0o077:
        raise SecretUnusable(
            f"the {what} {path} has mode {stat.S_IMODE(mode):04o}, so other users may read "
            f"it; run: chmod 600 {path}"
        )
    try:
        return path.read_text(encoding="ascii").strip()
    except (OSError, UnicodeDecodeError) as exc:
        raise SecretUnusable(f"cannot read the {what} {path} as ASCII text: {exc}") from None

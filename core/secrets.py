"""Secrets kept outside the database: read from a 0600 file, created on first use."""

import os
import secrets
import stat
from pathlib import Path


class SecretFileError(RuntimeError):
    """A secret file exists but cannot be trusted (wrong permissions or content)."""


def load_or_create_secret(path: Path, *, nbytes: int) -> bytes:
    """Return the secret stored at `path`, creating it with `nbytes` random bytes if absent.

    Creation uses O_EXCL, so concurrent processes on one host agree on a single secret.
    """
    path = Path(path)
    path.parent.mkdir(mode=0o700, parents=True, exist_ok=True)
    try:
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    except FileExistsError:
        return _read_secret(path, nbytes=nbytes)
    with os.fdopen(fd, "w") as handle:
        handle.write(secrets.token_hex(nbytes) + "\n")
        handle.flush()
        os.fsync(handle.fileno())
    return _read_secret(path, nbytes=nbytes)


def _read_secret(path: Path, *, nbytes: int) -> bytes:
    mode = path.stat().st_mode
    if mode & (stat.S_IRWXG | stat.S_IRWXO):
        raise SecretFileError(
            f"{path} is readable by other users (mode {oct(mode & 0o777)}); run: chmod 600 {path}"
        )
    text = path.read_text().strip()
    try:
        value = bytes.fromhex(text)
    except ValueError:
        raise SecretFileError(f"{path} does not contain hex digits") from None
    if len(value) != nbytes:
        raise SecretFileError(f"{path} holds {len(value)} bytes, expected {nbytes}")
    return value

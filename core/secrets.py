"""Secrets kept outside the database: read from a 0600 file, created on first use."""

import os
import secrets
import stat
import tempfile
from contextlib import suppress
from pathlib import Path

from core.files import fsync_path


class SecretFileError(RuntimeError):
    """A secret file exists but cannot be trusted (wrong permissions or content)."""


def load_or_create_secret(path: Path, *, nbytes: int) -> bytes:
    """Return the secret stored at `path`, creating it with `nbytes` random bytes if absent.

    The secret is written whole to a temporary file and linked into place, which fails if
    the name exists: concurrent processes on one host agree on a single secret, and none
    ever reads an empty or partly written file.
    """
    path = Path(path)
    seen = _file_state(path)
    read = _secrets_read.get((path, nbytes))
    if read is not None and seen is not None and read[0] == seen:
        return read[1]  # the file as it was read: the same inode, size, time and mode
    path.parent.mkdir(mode=0o700, parents=True, exist_ok=True)
    if seen is None:
        _create_secret(path, nbytes=nbytes)
        seen = _file_state(path)
    value = _read_secret(path, nbytes=nbytes)
    _secrets_read[(path, nbytes)] = (seen, value)
    return value


# Secrets as last read, with the file's state then: a request that needs one (the master key,
# at every upload and view) pays one stat, not a read; a file replaced, changed or chmod'ed
# is read (and its permissions checked) again.
_secrets_read: dict[tuple[Path, int], tuple[tuple[int, ...], bytes]] = {}


def _file_state(path: Path) -> tuple[int, ...] | None:
    try:
        state = os.stat(path)
    except FileNotFoundError:
        return None
    return (state.st_dev, state.st_ino, state.st_size, state.st_mtime_ns, state.st_mode)


def _create_secret(path: Path, *, nbytes: int) -> None:
    # mkstemp makes the file 0600, in the same directory so that the link stays on one device.
    fd, temporary = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "w") as handle:
            handle.write(secrets.token_hex(nbytes) + "\n")
            handle.flush()
            os.fsync(handle.fileno())
        try:
            os.link(temporary, path)
        except FileExistsError:
            return  # another process linked its secret first: that one is complete, and wins
    finally:
        with suppress(FileNotFoundError):
            os.unlink(temporary)
    # The new name durable: a crash after this keeps the file that was handed out.
    fsync_path(path.parent)


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

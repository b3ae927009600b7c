"""The owner's SM4 keys as the agent holds them: the current one seals, older ones re-seal.

A paired robot keeps them in `keys_file` (JSON, mode 0600, written atomically):

    {"current": "<key id>", "keys": {"<key id>": "<32 hex digits>", ...}}

where a key id is the hex of the first 8 bytes of SM3(key), as in the envelope. A new key
fetched after a rotation is added and made current; the old ones stay, so that envelopes
spooled under them can still be opened and re-sealed under the new key (ros_agent.uploader).
A robot set up by hand has one key from `key_file` and no file of keys.
"""

import json
import os
import stat
import threading
import uuid
from pathlib import Path

from smcrypto import envelope, sm4


class KeyringError(ValueError):
    """The file of keys is missing, unsafe or malformed; the message says which and how."""


def key_id_hex(key: bytes) -> str:
    return envelope.key_id(key).hex()


class Keyring:
    """The owner's keys by key id, one of them current; safe across threads."""

    def __init__(self, keys: dict[str, bytes], current: str, *, path: Path | None = None) -> None:
        if current not in keys:
            raise KeyringError(f"the current key {current} is not among the keys")
        self._keys = dict(keys)
        self._current = current
        self._path = path
        self._lock = threading.Lock()

    @classmethod
    def of_one(cls, key: bytes) -> "Keyring":
        """One key, kept in memory only (a robot whose key file is updated by hand)."""
        return cls({key_id_hex(key): key}, key_id_hex(key))

    @classmethod
    def load(cls, path: Path) -> "Keyring":
        """The keys of a paired robot, from its 0600 file."""
        try:
            mode = path.stat().st_mode
        except OSError as exc:
            raise KeyringError(f"cannot read the keys file {path}: {exc.strerror}") from None
        if mode & 0o077:
            raise KeyringError(
                f"the keys file {path} has mode {stat.S_IMODE(mode):04o}, so other users may "
                f"read it; run: chmod 600 {path}"
            )
        try:
            data = json.loads(path.read_text(encoding="utf-8"))
            keys = {str(kid): bytes.fromhex(text) for kid, text in data["keys"].items()}
            current = str(data["current"])
        except (OSError, ValueError, KeyError, TypeError, AttributeError) as exc:
            raise KeyringError(f"the keys file {path} is not a valid file of keys: {exc}") from None
        for kid, key in keys.items():
            if len(key) != sm4.KEY_SIZE or key_id_hex(key) != kid:
                raise KeyringError(f"the keys file {path} holds a wrong key under id {kid}")
        return cls(keys, current, path=path)

    @property
    def current_id(self) -> str:
        with self._lock:
            return self._current

    def current(self) -> tuple[str, bytes]:
        """The current key's id and bytes."""
        with self._lock:
            return self._current, self._keys[self._current]

    def get(self, kid: str) -> bytes | None:
        with self._lock:
            return self._keys.get(kid)

    def add(self, key: bytes) -> bool:
        """Make `key` current (kept on disk first, for a paired robot); whether it changed."""
        if len(key) != sm4.KEY_SIZE:
            raise KeyringError(f"an SM4 key is {sm4.KEY_SIZE} bytes, not {len(key)}")
        kid = key_id_hex(key)
        with self._lock:
            if kid == self._current:
                return False
            keys = {**self._keys, kid: key}
            if self._path is not None:
                write_keys_file(self._path, keys, kid)
            self._keys, self._current = keys, kid
            return True


def write_keys_file(path: Path, keys: dict[str, bytes], current: str) -> None:
    """Write the file of keys durably, mode 0600: a crash leaves the old file or the new one."""
    text = json.dumps(
        {"current": current, "keys": {kid: key.hex() for kid, key in keys.items()}},
        indent=1,
        sort_keys=True,
    )
    write_private_file(path, text + "\n")


def write_private_file(path: Path, text: str) -> None:
    """A file only its owner may read, written to a temporary name, synced and renamed."""
    path = Path(path)
    temporary = path.with_name(f".tmp-{path.name}-{uuid.uuid4().hex}")
    fd = os.open(temporary, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as handle:
            handle.write(text)
            handle.flush()
            os.fsync(handle.fileno())
        os.replace(temporary, path)
    except BaseException:
        temporary.unlink(missing_ok=True)
        raise
    directory = os.open(path.parent, os.O_RDONLY | os.O_DIRECTORY)
    try:
        os.fsync(directory)
    finally:
        os.close(directory)

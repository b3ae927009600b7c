"""`authros_verify keys`: every robot key ever registered for an owner, from chain events alone.

The contract logs RobotKeyAdded(owner, keyHash, publicKey) and RobotKeyRevoked(owner, keyHash)
with the owner as the first indexed topic, so one log query lists an owner's keys, with the
blocks they were added and revoked in, without the portal and without the contract's state.
Whoever holds an owner's custodial EOA (the portal's KEK) can register a key of their own and
sign records with it; this list is where the owner notices a key it never paired
(DESIGN.md "Provenance"). The contract cannot afford SM3 and does not check that a key hashes
to its keyHash: a key that does not is flagged here.
"""

from dataclasses import dataclass

from authros_verify.chain import ChainReader
from smcrypto import sm2
from smcrypto.errors import CryptoError
from smcrypto.sm3 import sm3_digest


@dataclass
class RegisteredKey:
    key_hash: bytes
    public_key: bytes | None  # x||y as registered (None: its RobotKeyAdded is not in the range)
    added_block: int | None
    added_tx: str | None
    revoked_block: int | None = None
    revoked_tx: str | None = None

    @property
    def hash_holds(self) -> bool:
        """Whether the registered public key hashes (SM3) to the key hash."""
        return self.public_key is not None and sm3_digest(self.public_key) == self.key_hash

    @property
    def public_key_hex(self) -> str | None:
        return None if self.public_key is None else "04" + self.public_key.hex()

    @property
    def fingerprint(self) -> str | None:
        """The short name the portal shows for a robot's pairing key (smcrypto.sm2)."""
        try:
            return sm2.fingerprint(self.public_key_hex) if self.public_key_hex else None
        except CryptoError:  # not a point on the curve
            return None


def robot_keys(
    chain: ChainReader, *, contract: str, owner: str, from_block: int = 0
) -> list[RegisteredKey]:
    """The owner's robot keys, in the order they were added."""
    keys: dict[bytes, RegisteredKey] = {}
    for event in chain.robot_key_events(contract, owner, from_block=from_block):
        key = keys.setdefault(event.key_hash, RegisteredKey(event.key_hash, None, None, None))
        if event.kind == "added":
            key.public_key, key.added_block, key.added_tx = event.public_key, event.block, event.tx
        else:
            key.revoked_block, key.revoked_tx = event.block, event.tx
    return list(keys.values())

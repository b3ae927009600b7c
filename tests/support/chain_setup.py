"""What tests of the chain client set up on a node: an owner registered on the contract, and
an anchor item for a new record.

No Django here: tests/chainworker/test_sender_anvil.py sends from processes it spawns, which
import the test module and this one, and no portal app.
"""

import uuid
from datetime import UTC, datetime

from eth_account import Account
from eth_account.signers.local import LocalAccount

from chainworker.client import AuthROSChain
from chainworker.codec import AnchorItem
from smcrypto import key_commitment, sm3, sm4


def make_registered_owner(
    client: AuthROSChain, admin: LocalAccount, *, key: bytes | None = None
) -> LocalAccount:
    """A new EOA, funded, enrolled by the admin and registered with a key commitment."""
    account = Account.create()
    client.transfer(admin, account.address, 10**18)
    client.enroll(admin, account.address)
    client.register(account, key_commitment(account.address, key or sm4.generate_key()))
    return account


def anchor_item() -> AnchorItem:
    """What the chain client anchors for a new record: a random id and digest, captured now."""
    return AnchorItem(
        record_id=uuid.uuid4(),
        digest=sm3.sm3_digest(uuid.uuid4().bytes),
        time=datetime.now(tz=UTC),
        data_type="std_msgs/String",
    )

"""The client's reads, writes and events of the contract by name, against the session's anvil
over the JSON-RPC path production runs."""

import uuid
from datetime import UTC, datetime

import pytest
from eth_account import Account

from chainworker.client import AuthROSChain
from chainworker.codec import AnchorItem, record_id_to_bytes32
from chainworker.errors import ContractNotDeployed, TransactionReverted
from smcrypto import key_commitment, sm3, sm4
from tests.support.chain_setup import make_registered_owner


def _item(data_type: str = "nav_msgs/Odometry") -> AnchorItem:
    return AnchorItem(
        record_id=uuid.uuid4(),
        digest=sm3.sm3_digest(uuid.uuid4().bytes),
        time=datetime(2026, 11, 21, 14, 0, 0, 123456, tzinfo=UTC),
        data_type=data_type,
    )


def test_deploy_makes_operator_admin(chain, operator):
    assert chain.has_code(chain.address)
    assert chain.admin() == operator.address
    assert chain.record_count() == 0


def test_register_flow_emits_decoded_events(chain, operator):
    owner = Account.create()
    chain.transfer(operator, owner.address, 10**18)
    assert chain.balance(owner.address) == 10**18

    enrolled = chain.enroll(operator, owner.address)
    assert [e.name for e in enrolled.events] == ["Enrolled"]
    assert enrolled.events[0].args == {"eoa": owner.address}
    assert chain.is_enrolled(owner.address)

    commitment = key_commitment(owner.address, sm4.generate_key())
    registered = chain.register(owner, commitment)
    assert registered.events[0].name == "Registered"
    assert registered.events[0].args["commitment"] == commitment
    assert chain.is_registered(owner.address)
    assert chain.commitment_of(owner.address) == commitment

    rotated = key_commitment(owner.address, sm4.generate_key())
    result = chain.rotate_key(owner, rotated)
    assert result.events[0].args == {
        "eoa": owner.address,
        "oldCommitment": commitment,
        "newCommitment": rotated,
    }
    assert chain.commitment_of(owner.address) == rotated


def test_upload_query_and_check(chain, registered_owner):
    item = _item()
    result = chain.data_upload(registered_owner, item)
    event = result.events[0]
    assert event.name == "DataUploaded"
    assert event.args["owner"] == registered_owner.address
    assert event.args["digest"] == item.digest
    assert result.block_number > 0
    assert result.tx_hash.startswith("0x")

    on_chain = chain.data_query(item.record_id, owner=registered_owner.address)
    assert on_chain is not None
    assert on_chain.owner == registered_owner.address
    assert on_chain.digest == item.digest
    assert on_chain.time == item.time
    assert on_chain.data_type == "nav_msgs/Odometry"
    assert chain.data_check(item.record_id, item.digest, owner=registered_owner.address)
    assert not chain.data_check(
        item.record_id, sm3.sm3_digest(b"other"), owner=registered_owner.address
    )
    assert chain.data_query(uuid.uuid4(), owner=registered_owner.address) is None


def test_batch_upload_anchors_every_item(chain, registered_owner):
    items = [_item() for _ in range(20)]
    result = chain.data_upload_batch(registered_owner, items)
    assert [e.args["id"] for e in result.events] == [
        record_id_to_bytes32(i.record_id) for i in items
    ]
    assert all(
        chain.data_check(i.record_id, i.digest, owner=registered_owner.address) for i in items
    )
    assert chain.record_count() == 20
    with pytest.raises(ValueError, match="at least one"):
        chain.data_upload_batch(registered_owner, [])


def test_refusals_carry_the_custom_error_name(chain, operator, registered_owner):
    stranger = Account.create()
    chain.transfer(operator, stranger.address, 10**18)

    with pytest.raises(TransactionReverted) as refused:
        chain.enroll(stranger, stranger.address)
    assert refused.value.error_name == "NotAdmin"
    assert refused.value.error_args == {"caller": stranger.address}
    assert "enroll" in str(refused.value)

    with pytest.raises(TransactionReverted) as refused:
        chain.data_upload(stranger, _item())
    assert refused.value.error_name == "NotRegistered"

    item = _item()
    chain.data_upload(registered_owner, item)
    with pytest.raises(TransactionReverted) as refused:
        chain.data_upload(registered_owner, item)
    assert refused.value.error_name == "RecordExists"
    assert refused.value.error_args["id"] == record_id_to_bytes32(item.record_id)

    with pytest.raises(TransactionReverted) as refused:
        chain.authority_revoke(registered_owner, stranger.address)
    assert refused.value.error_name == "NoGrant"


def test_grant_and_revoke_change_access(chain, operator, registered_owner):
    viewer = make_registered_owner(chain, operator)
    assert chain.has_access(registered_owner.address, registered_owner.address)
    assert not chain.has_access(registered_owner.address, viewer.address)

    granted = chain.authority_grant(registered_owner, viewer.address)
    assert granted.events[0].name == "AuthorityGranted"
    assert chain.has_access(registered_owner.address, viewer.address)

    revoked = chain.authority_revoke(registered_owner, viewer.address)
    assert revoked.events[0].args == {"owner": registered_owner.address, "grantee": viewer.address}
    assert not chain.has_access(registered_owner.address, viewer.address)


def test_events_reads_the_whole_history_in_order(chain, operator, registered_owner):
    viewer = make_registered_owner(chain, operator)
    chain.authority_grant(registered_owner, viewer.address)
    chain.data_upload(registered_owner, _item())
    names = [e.name for e in chain.events()]
    assert names == [
        "Enrolled",
        "Registered",
        "Enrolled",
        "Registered",
        "AuthorityGranted",
        "DataUploaded",
    ]
    uploads = chain.events(names=["DataUploaded"])
    assert len(uploads) == 1
    assert uploads[0].args["owner"] == registered_owner.address
    blocks = [e.block_number for e in chain.events()]
    assert blocks == sorted(blocks)


def test_events_naming_an_address_are_filtered_by_the_node(chain, operator, registered_owner):
    viewer = make_registered_owner(chain, operator)
    other = make_registered_owner(chain, operator)
    chain.authority_grant(registered_owner, viewer.address)
    chain.authority_grant(other, registered_owner.address)
    chain.data_upload(registered_owner, _item())
    chain.data_upload(other, _item())
    chain.authority_revoke(registered_owner, viewer.address)
    arguments = {
        "Registered": ("eoa",),
        "DataUploaded": ("owner",),
        "AuthorityGranted": ("owner", "grantee"),
        "AuthorityRevoked": ("owner", "grantee"),
    }

    mine = chain.events_naming(registered_owner.address, arguments)

    assert [(e.name, e.args.get("owner"), e.args.get("grantee")) for e in mine] == [
        ("Registered", None, None),
        ("AuthorityGranted", registered_owner.address, viewer.address),
        ("AuthorityGranted", other.address, registered_owner.address),
        ("DataUploaded", registered_owner.address, None),
        ("AuthorityRevoked", registered_owner.address, viewer.address),
    ]
    theirs = chain.events_naming(viewer.address.lower(), arguments)
    assert [e.name for e in theirs] == ["Registered", "AuthorityGranted", "AuthorityRevoked"]
    assert chain.events_naming(Account.create().address, arguments) == []
    with pytest.raises(ValueError, match="not an indexed argument"):
        chain.events_naming(viewer.address, {"Registered": ("commitment",)})


def test_no_contract_means_contract_not_deployed(isolated_portal, redis_client):
    client = AuthROSChain(isolated_portal, redis_client=redis_client)
    with pytest.raises(ContractNotDeployed):
        client.data_query(uuid.uuid4(), owner="0x" + "11" * 20)


def test_a_read_at_an_address_without_code_is_contract_not_deployed(chain):
    # A chain reset leaves the recorded address empty: reads must say so, not crash.
    chain.use_contract(Account.create().address)
    with pytest.raises(ContractNotDeployed):
        chain.commitment_of(Account.create().address)
    with pytest.raises(ContractNotDeployed):  # the lean read of every view, too
        chain.root_of(Account.create().address, b"\x01" * 32)

"""The chain client against the session's anvil, over the JSON-RPC path production runs."""

import threading
import uuid
from datetime import UTC, datetime
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

import pytest
from eth_account import Account

from chainworker import sender as chain_sender
from chainworker.client import AuthROSChain
from chainworker.codec import (
    AnchorItem,
    bytes32_to_data_type,
    bytes32_to_record_id,
    chain_time_to_datetime,
    data_type_to_bytes32,
    datetime_to_chain_time,
    record_id_to_bytes32,
)
from chainworker.errors import (
    ChainUnavailable,
    ContractNotDeployed,
    InsufficientFunds,
    NodeRefused,
    TransactionDropped,
    TransactionReverted,
)
from smcrypto import key_commitment, sm3, sm4
from stack.anvil import free_port
from tests.chain_setup import make_registered_owner


def _item(data_type: str = "nav_msgs/Odometry") -> AnchorItem:
    return AnchorItem(
        record_id=uuid.uuid4(),
        digest=sm3.sm3_digest(uuid.uuid4().bytes),
        time=datetime(2026, 11, 21, 14, 0, 0, 123456, tzinfo=UTC),
        data_type=data_type,
    )


def test_record_id_is_uuid_left_aligned_and_zero_padded():
    record_id = uuid.UUID("12345678-1234-5678-1234-567812345678")
    raw = record_id_to_bytes32(record_id)
    assert raw == record_id.bytes + bytes(16)
    assert bytes32_to_record_id(raw) == record_id


def test_data_type_fits_or_is_hashed():
    assert data_type_to_bytes32("nav_msgs/Odometry") == b"nav_msgs/Odometry".ljust(32, b"\0")
    assert bytes32_to_data_type(data_type_to_bytes32("sensor_msgs/Image")) == "sensor_msgs/Image"
    long_type = "geometry_msgs/PoseWithCovarianceStamped"
    hashed = data_type_to_bytes32(long_type)
    assert len(hashed) == 32
    assert hashed != long_type.encode()[:32]
    with pytest.raises(ValueError, match="non-empty"):
        data_type_to_bytes32("")


def test_chain_time_keeps_microseconds():
    moment = datetime(2026, 11, 21, 14, 0, 0, 123456, tzinfo=UTC)
    assert chain_time_to_datetime(datetime_to_chain_time(moment)) == moment
    with pytest.raises(ValueError, match="timezone"):
        datetime_to_chain_time(datetime(2026, 1, 1))


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


def test_send_without_waiting_then_wait(chain, registered_owner):
    items = [_item() for _ in range(5)]
    hashes = [chain.data_upload(registered_owner, i, wait=False) for i in items]
    assert len(set(hashes)) == 5
    for tx_hash in hashes:
        assert chain.wait_for_receipt(tx_hash)["status"] == 1
    assert chain.record_count() == 5


def test_nonce_counter_ahead_of_node_is_resynced(
    chain, registered_owner, redis_client, monkeypatch
):
    monkeypatch.setattr(chain_sender, "DROPPED_CHECK_INTERVAL", 0.1)
    chain.data_upload(registered_owner, _item())
    key = chain.nonces._key(registered_owner.address)
    # A fresh counter far ahead of the node: the node holds the transaction behind the gap,
    # the wait says it will never be mined, and the counter is resynced from the node.
    redis_client.set(key, "999:9999999999")
    with pytest.raises(TransactionDropped):
        chain.data_upload(registered_owner, _item())
    chain.data_upload(registered_owner, _item())
    assert chain.record_count() == 2


def test_stale_counter_ahead_of_node_yields_to_the_node(chain, registered_owner, redis_client):
    key = chain.nonces._key(registered_owner.address)
    redis_client.set(key, "50:1000")  # written long ago: those transactions were dropped
    chain.data_upload(registered_owner, _item())
    assert chain.record_count() == 1


def test_lagging_node_is_covered_by_the_counter(chain, registered_owner):
    next_nonce = chain._pending_nonce(registered_owner.address)
    chain.nonces.forget(registered_owner.address)
    with chain.nonces.reserve(registered_owner.address, lambda _addr: next_nonce - 1) as slot:
        assert slot.nonce == next_nonce - 1  # no counter yet: trust the node
        slot.commit()
    with chain.nonces.reserve(registered_owner.address, lambda _addr: 0) as slot:
        assert slot.nonce == next_nonce  # counter is fresh and ahead of a lagging node


def test_a_send_the_node_already_has_is_not_signed_again(chain, registered_owner, monkeypatch):
    """The node accepted the transaction but its answer was lost; our retry hears "already
    known". That transaction is sent: signing it again with the next nonce would send it twice.
    """
    real_rpc = chain.rpc.request
    sent: list[str] = []

    def accepted_then_already_known(method, params, *, label):
        if method != "eth_sendRawTransaction":
            return real_rpc(method, params, label=label)
        sent.append(params[0])
        answer = real_rpc(method, params, label=label)
        if len(sent) == 1:
            raise NodeRefused(label, "already known")
        return answer

    monkeypatch.setattr(chain.rpc, "request", accepted_then_already_known)
    nonce = chain._pending_nonce(registered_owner.address)
    tx_hash = chain.data_upload(registered_owner, _item(), wait=False)
    assert chain.wait_for_receipt(tx_hash)["status"] == 1
    assert chain.w3.eth.get_transaction(tx_hash)["nonce"] == nonce
    chain.data_upload(registered_owner, _item())  # the next send takes the next nonce
    assert len(sent) == 2
    assert chain.record_count() == 2
    assert chain._pending_nonce(registered_owner.address) == nonce + 2


def test_a_send_whose_nonce_lock_expired_does_not_happen(
    chain, registered_owner, monkeypatch, redis_client
):
    """Another process may have taken the sender's lock and the nonce: sending would collide."""
    key = chain.nonces._key(registered_owner.address) + ":lock"
    real_sign = registered_owner.sign_transaction

    def slow_sign(tx):
        redis_client.delete(key)  # our lock expired while we were slow
        return real_sign(tx)

    monkeypatch.setattr(registered_owner, "sign_transaction", slow_sign)
    with pytest.raises(ChainUnavailable, match="lost the nonce lock"):
        chain.data_upload(registered_owner, _item())
    assert chain.record_count() == 0


def test_a_node_behind_a_proxy_answering_503_is_unavailable(redis_client):
    class Overloaded(BaseHTTPRequestHandler):
        def do_POST(self):
            self.send_response(503)
            self.send_header("Content-Length", "0")
            self.end_headers()

        def log_message(self, *args):
            pass

    server = ThreadingHTTPServer(("127.0.0.1", 0), Overloaded)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    try:
        client = AuthROSChain(f"http://127.0.0.1:{server.server_port}", redis_client=redis_client)
        with pytest.raises(ChainUnavailable, match="HTTP error"):
            client.latest_block()
    finally:
        server.shutdown()
        server.server_close()


def test_unfunded_sender_gets_insufficient_funds(chain):
    pauper = Account.create()
    with pytest.raises(InsufficientFunds):
        chain.transfer(pauper, chain.address, 1)


def test_no_contract_means_contract_not_deployed(isolated_portal, redis_client):
    client = AuthROSChain(isolated_portal, redis_client=redis_client)
    with pytest.raises(ContractNotDeployed):
        client.data_query(uuid.uuid4(), owner="0x" + "11" * 20)


def test_unreachable_node_raises_chain_unavailable(redis_client):
    client = AuthROSChain(f"http://127.0.0.1:{free_port()}", redis_client=redis_client)
    assert not client.is_connected()
    with pytest.raises(ChainUnavailable):
        client.latest_block()
    with pytest.raises(ChainUnavailable):
        client.chain_id  # noqa: B018


def test_unsupported_url_is_refused(redis_client):
    with pytest.raises(ValueError, match="unsupported chain URL"):
        AuthROSChain("ftp://example.invalid", redis_client=redis_client)


def test_a_read_at_an_address_without_code_is_contract_not_deployed(chain):
    # A chain reset leaves the recorded address empty: reads must say so, not crash.
    chain.use_contract(Account.create().address)
    with pytest.raises(ContractNotDeployed):
        chain.commitment_of(Account.create().address)
    with pytest.raises(ContractNotDeployed):  # the lean read of every view, too
        chain.root_of(Account.create().address, b"\x01" * 32)


def test_a_reset_chain_is_told_from_the_old_one_by_its_genesis(
    isolated_portal, fresh_chain, settings, redis_client
):
    """A reset chain has the same chain id and a genesis of its own, even when made within the
    second anvil dates its genesis to: the client's chain key (its nonce namespace) changes."""
    before = AuthROSChain(isolated_portal, redis_client=redis_client)
    fresh_chain()
    after = AuthROSChain(settings.CHAIN_RPC_URL, redis_client=redis_client)
    assert after.chain_id == before.chain_id
    assert after.genesis_hash != before.genesis_hash
    assert after.chain_key != before.chain_key

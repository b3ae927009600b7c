"""Sending transactions against the session's anvil: nonces shared through Redis and resynced
from the node, a send the node already has, a lost lock, an unfunded sender, the chain key."""

import pytest
from eth_account import Account

from chainworker import sender as chain_sender
from chainworker.client import AuthROSChain
from chainworker.errors import (
    ChainUnavailable,
    InsufficientFunds,
    NodeRefused,
    TransactionDropped,
)
from tests.support.chain_setup import anchor_item


def test_send_without_waiting_then_wait(chain, registered_owner):
    items = [anchor_item() for _ in range(5)]
    hashes = [chain.data_upload(registered_owner, i, wait=False) for i in items]
    assert len(set(hashes)) == 5
    for tx_hash in hashes:
        assert chain.wait_for_receipt(tx_hash)["status"] == 1
    assert chain.record_count() == 5


def test_nonce_counter_ahead_of_node_is_resynced(
    chain, registered_owner, redis_client, monkeypatch
):
    monkeypatch.setattr(chain_sender, "DROPPED_CHECK_INTERVAL", 0.1)
    chain.data_upload(registered_owner, anchor_item())
    key = chain.nonces._key(registered_owner.address)
    # A fresh counter far ahead of the node: the node holds the transaction behind the gap,
    # the wait says it will never be mined, and the counter is resynced from the node.
    redis_client.set(key, "999:9999999999")
    with pytest.raises(TransactionDropped):
        chain.data_upload(registered_owner, anchor_item())
    chain.data_upload(registered_owner, anchor_item())
    assert chain.record_count() == 2


def test_stale_counter_ahead_of_node_yields_to_the_node(chain, registered_owner, redis_client):
    key = chain.nonces._key(registered_owner.address)
    redis_client.set(key, "50:1000")  # written long ago: those transactions were dropped
    chain.data_upload(registered_owner, anchor_item())
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
    tx_hash = chain.data_upload(registered_owner, anchor_item(), wait=False)
    assert chain.wait_for_receipt(tx_hash)["status"] == 1
    assert chain.w3.eth.get_transaction(tx_hash)["nonce"] == nonce
    chain.data_upload(registered_owner, anchor_item())  # the next send takes the next nonce
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
        chain.data_upload(registered_owner, anchor_item())
    assert chain.record_count() == 0


def test_unfunded_sender_gets_insufficient_funds(chain):
    pauper = Account.create()
    with pytest.raises(InsufficientFunds):
        chain.transfer(pauper, chain.address, 1)


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

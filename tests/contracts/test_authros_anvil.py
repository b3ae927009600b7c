"""AuthROS on a real node: anvil over HTTP JSON-RPC, with a locally signing custodial EOA."""

import pytest
from eth_account import Account
from web3 import Web3
from web3.exceptions import ContractCustomError

from stack.anvil import start_anvil

pytestmark = pytest.mark.process

ANVIL_CHAIN_ID = 31337


def send_signed(w3, call, account):
    """Sign locally and send raw, as the portal's chain worker does with custodial keys."""
    transaction = call.build_transaction(
        {"from": account.address, "nonce": w3.eth.get_transaction_count(account.address)}
    )
    signed = account.sign_transaction(transaction)
    return w3.eth.wait_for_transaction_receipt(w3.eth.send_raw_transaction(signed.raw_transaction))


def test_enroll_register_upload_query_on_anvil(artifact, record, reverts):
    with start_anvil() as node:
        w3 = Web3(Web3.HTTPProvider(node.url))
        assert w3.eth.chain_id == ANVIL_CHAIN_ID
        admin = w3.eth.accounts[0]  # anvil's unlocked dev account
        factory = w3.eth.contract(abi=artifact["abi"], bytecode=artifact["bytecode"])
        deployed = w3.eth.wait_for_transaction_receipt(
            factory.constructor().transact({"from": admin})
        )
        authros = w3.eth.contract(address=deployed["contractAddress"], abi=artifact["abi"])
        owner = Account.create()
        w3.eth.wait_for_transaction_receipt(
            w3.eth.send_transaction({"from": admin, "to": owner.address, "value": 10**18})
        )

        # Refusals come back from a real node as ContractCustomError carrying the data.
        with pytest.raises(ContractCustomError):
            authros.functions.register(b"\x01" * 32).call({"from": owner.address})
        with reverts("NotEnrolled", owner.address):
            send_signed(w3, authros.functions.register(b"\x01" * 32), owner)

        assert authros.functions.enroll(owner.address).transact({"from": admin})
        assert send_signed(w3, authros.functions.register(b"\x01" * 32), owner)["status"] == 1
        record_id, digest, time, data_type = record(0)
        receipt = send_signed(
            w3, authros.functions.dataUpload(record_id, digest, time, data_type), owner
        )

        assert receipt["status"] == 1
        (event,) = authros.events.DataUploaded().process_receipt(receipt)
        assert event["args"]["owner"] == owner.address
        assert authros.functions.dataQueryOf(owner.address, record_id).call() == [
            owner.address,
            digest,
            time,
            data_type,
        ]
        assert authros.functions.dataCheckOf(owner.address, record_id, digest).call() is True
        assert authros.functions.hasAccess(owner.address, owner.address).call() is True
        with reverts("RecordExists", record_id):
            send_signed(w3, authros.functions.dataUpload(record_id, digest, time, data_type), owner)
    assert node.process.poll() is not None


def test_anvil_keeps_state_across_restarts(tmp_path):
    state = tmp_path / "anvil-state.json"
    with start_anvil(block_time=0.2, state_path=str(state)) as node:
        w3 = Web3(Web3.HTTPProvider(node.url))
        tx_hash = w3.eth.send_transaction(
            {"from": w3.eth.accounts[0], "to": w3.eth.accounts[1], "value": 12345}
        )
        block = w3.eth.wait_for_transaction_receipt(tx_hash, poll_latency=0.05)["blockNumber"]
    assert state.exists()

    with start_anvil(state_path=str(state)) as node:
        w3 = Web3(Web3.HTTPProvider(node.url))
        assert w3.eth.block_number >= block
        assert w3.eth.get_transaction(tx_hash)["value"] == 12345

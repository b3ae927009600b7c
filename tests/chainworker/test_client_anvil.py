"""The client against a real anvil node of the module: the contract's flow over HTTP, and a
read that is one eth_call."""

import pytest
import requests
from eth_account import Account

from chainworker.client import AuthROSChain
from chainworker.errors import ContractNotDeployed, TransactionReverted
from tests.support.chain_setup import anchor_item, make_registered_owner

pytestmark = pytest.mark.process


def test_full_contract_flow_over_http(deploy_on, anvil, redis_client):
    client, operator = deploy_on(anvil.url)
    owner = make_registered_owner(client, operator)
    viewer = make_registered_owner(client, operator)
    item = anchor_item()
    result = client.data_upload(owner, item)
    assert result.events[0].name == "DataUploaded"
    assert client.data_query(item.record_id, owner=owner.address).digest == item.digest
    client.authority_grant(owner, viewer.address)
    assert client.has_access(owner.address, viewer.address)
    with pytest.raises(TransactionReverted) as refused:
        client.authority_grant(owner, viewer.address)
    assert refused.value.error_name == "AlreadyGranted"
    assert client.client_version.lower().startswith("anvil")


def test_a_read_is_one_request_to_the_node(deploy_on, anvil, redis_client, monkeypatch):
    """web3 asks for the chain id before an eth_call; it is asked once per connection, so a
    view's rootOf or dataQuery is one HTTP request."""
    client, operator = deploy_on(anvil.url)
    owner = make_registered_owner(client, operator)
    item = anchor_item()
    client.data_upload(owner, item)
    client.anchor_root(owner, b"\x02" * 32, 5)
    client.data_query(
        item.record_id, owner=owner.address
    )  # the connection has asked its chain id by now
    methods = []
    session_post = requests.Session.post

    def post(session, url, *args, **kwargs):
        methods.append(kwargs["json"]["method"] if "json" in kwargs else kwargs.get("data"))
        return session_post(session, url, *args, **kwargs)

    monkeypatch.setattr(requests.Session, "post", post)
    assert client.data_query(item.record_id, owner=owner.address).digest == item.digest
    assert client.root_of(owner.address, b"\x01" * 32) is None
    anchored = client.root_of(owner.address, b"\x02" * 32)
    assert anchored.size == 5
    assert anchored.sender == owner.address
    assert len(methods) == 3
    assert all(b"eth_call" in m if isinstance(m, bytes) else m == "eth_call" for m in methods)


def test_the_views_read_at_an_address_without_code_is_contract_not_deployed(anvil, redis_client):
    """rootOf goes past web3's contract layer over HTTP: an empty answer (a reset chain) is
    still ContractNotDeployed, not a crash."""
    client = AuthROSChain(anvil.url, redis_client=redis_client)
    client.use_contract(Account.create().address)
    with pytest.raises(ContractNotDeployed):
        client.root_of(Account.create().address, b"\x01" * 32)

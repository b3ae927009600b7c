"""The node's connection against a real anvil node: one session per process, read from the
environment once, shared by threads, fork-safe; a node going away."""

import multiprocessing
import threading

import pytest
import requests
from web3 import Web3

from chainworker.client import AuthROSChain
from chainworker.errors import ChainUnavailable
from chainworker.rpc import rpc_session
from stack.anvil import start_anvil
from tests.support.chain_setup import make_registered_owner

pytestmark = pytest.mark.process


def test_node_going_away_raises_chain_unavailable(deploy_on, redis_client):
    node = start_anvil()
    client, _operator = deploy_on(node.url)
    node.stop()
    with pytest.raises(ChainUnavailable):
        client.record_count()
    assert not client.is_connected()
    assert Web3.is_checksum_address(client.address)


def test_the_nodes_session_reads_the_environment_once_and_is_shared_by_threads(
    deploy_on, anvil, redis_client, monkeypatch
):
    """Proxies and CA bundle from the environment when the client is made, not at every call
    (requests would read every variable again); one session for all of a process's threads."""
    monkeypatch.setenv("HTTP_PROXY", "http://proxy.invalid:3128")
    monkeypatch.setenv("NO_PROXY", "127.0.0.1,localhost")
    monkeypatch.setenv("REQUESTS_CA_BUNDLE", "/etc/ssl/certs/ca-certificates.crt")
    assert rpc_session("http://10.1.2.3:8545").proxies == {"http": "http://proxy.invalid:3128"}
    assert rpc_session("http://10.1.2.3:8545").verify == "/etc/ssl/certs/ca-certificates.crt"
    assert rpc_session(anvil.url).proxies == {}  # NO_PROXY names it

    client, operator = deploy_on(anvil.url)
    owner = make_registered_owner(client, operator)
    environment_read = []
    real_proxies = requests.utils.get_environ_proxies
    monkeypatch.setattr(
        requests.utils,
        "get_environ_proxies",
        lambda *a, **k: environment_read.append(a) or real_proxies(*a, **k),
    )
    sessions = set()
    session_post = requests.Session.post

    def post(session, url, *args, **kwargs):
        sessions.add(id(session))
        return session_post(session, url, *args, **kwargs)

    monkeypatch.setattr(requests.Session, "post", post)
    threads = [
        threading.Thread(target=client.root_of, args=(owner.address, b"\x01" * 32))
        for _ in range(4)
    ]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    client.anchor_root(owner, b"\x03" * 32, 2)
    assert client.last_root_of(owner.address) == b"\x03" * 32
    assert environment_read == []
    assert len(sessions) == 1


def _forked_reads(client: AuthROSChain, owner: str, answers) -> None:
    """In a forked child: the pool it inherited is empty, and its reads get their answers."""
    session = client.w3.provider._request_session_manager._explicit_session
    inherited = len(session.adapters["http://"].poolmanager.pools)
    results = [client.last_root_of(owner) for _ in range(30)]
    answers.put((inherited, {result.hex() for result in results}))


def test_a_process_forked_after_a_call_opens_its_own_connections(deploy_on, anvil, redis_client):
    """Celery's pool processes fork from a parent that checked the chain: a connection they
    shared would hand each of them the other's answers."""
    client, operator = deploy_on(anvil.url)
    owner = make_registered_owner(client, operator)
    client.anchor_root(owner, b"\x07" * 32, 3)
    session = client.w3.provider._request_session_manager._explicit_session
    assert client.last_root_of(owner.address) == b"\x07" * 32
    assert len(session.adapters["http://"].poolmanager.pools) == 1  # a connection is open
    context = multiprocessing.get_context("fork")
    answers = context.Queue()
    children = [
        context.Process(target=_forked_reads, args=(client, owner.address, answers))
        for _ in range(3)
    ]
    for child in children:
        child.start()
    # Meanwhile the parent reads too, on the connection it kept.
    assert {type(client.w3.eth.block_number) for _ in range(30)} == {int}
    outcomes = [answers.get(timeout=60) for _ in children]
    for child in children:
        child.join(timeout=60)
    assert outcomes == [(0, {"07" * 32})] * 3

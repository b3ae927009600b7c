"""The connection to the node, and the raw JSON-RPC requests the client sends on it.

`connect` makes the web3 connection of one node (``http(s)://`` only) on the process's one
HTTP session (`rpc_session`: shared by its threads, fork-safe, the environment read once).
`NodeRpc` sends a request, or a batch of them, through the provider itself, past web3's
middleware and formatters: the reads of every view and upload (an eth_call of rootOf,
grantOf, commitmentOf) and every send's estimate, fees, raw transaction and receipt. Those
layers cost more CPU than the request (bench/REPORT.md, "worker_check": a records-mode check
through web3's contract call, a root-mode check through this path; 10.7 to 5.5 ms of CPU per
anchorRoot and its receipt when sends came here), so this is the client's only way to call the
contract; web3 stays for the node's own reads (blocks, logs, transactions), which are not on
the hot path.
"""

from __future__ import annotations

import os
import weakref
from typing import Any

import requests
from hexbytes import HexBytes
from web3 import Web3
from web3.middleware import ExtraDataToPOAMiddleware

from chainworker.errors import NodeRefused, translated_errors

# Connections kept to the node per process: a web process's threads and a worker's share them.
RPC_POOL_SIZE = 32


def connect(url: str, *, timeout: float = 10.0) -> Web3:
    """A Web3 connection for the node at `url`."""
    if url.startswith(("http://", "https://")):
        # web3 asks the node for its chain id before every eth_call and transaction; a node's
        # chain id does not change, so it is asked once per connection (a view is one eth_call).
        provider = Web3.HTTPProvider(
            url,
            request_kwargs={"timeout": timeout},
            session=rpc_session(url),
            cache_allowed_requests=True,
            cacheable_requests={"eth_chainId"},
        )
        w3 = Web3(provider)
        # Proof-of-authority networks (geth clique) carry signer data in extraData.
        w3.middleware_onion.inject(ExtraDataToPOAMiddleware, layer=0)
        return w3
    raise ValueError(f"unsupported chain URL {url!r}: use http(s)://host:port")


def rpc_session(url: str) -> requests.Session:
    """The HTTP session of every call to the node at `url`, shared by this process's threads.

    Proxies and the CA bundle come from the environment, read here once: requests otherwise
    reads every variable of the environment again at each call (HTTP(S)_PROXY, NO_PROXY,
    REQUESTS_CA_BUNDLE), about a tenth of a chain worker's CPU. A forked child closes its
    copy's connections (it opens its own).
    """
    session = requests.Session()
    session.trust_env = False
    proxies = requests.utils.get_environ_proxies(url)
    session.proxies.update({scheme: at for scheme, at in proxies.items() if scheme != "no"})
    bundle = os.environ.get("REQUESTS_CA_BUNDLE") or os.environ.get("CURL_CA_BUNDLE")
    if bundle:
        session.verify = bundle
    adapter = requests.adapters.HTTPAdapter(pool_connections=1, pool_maxsize=RPC_POOL_SIZE)
    session.mount("http://", adapter)
    session.mount("https://", adapter)
    # A process forked from this one (Celery's pool, from a parent that checked the chain)
    # must not share its open connections: two processes reading answers from one socket get
    # each other's. The child drops them and opens its own.
    held = weakref.ref(session)
    os.register_at_fork(after_in_child=lambda: _session_forget_connections(held))
    return session


def _session_forget_connections(held: weakref.ref[requests.Session]) -> None:
    session = held()
    if session is not None:
        session.close()


class NodeRpc:
    """JSON-RPC requests to one node sent by its provider, their raw results back."""

    def __init__(self, w3: Web3) -> None:
        self.w3 = w3

    def request(self, method: str, params: list[Any], *, label: str) -> Any:
        """One request; its raw result, or NodeRefused with what the node said. `label` names
        what the request is for in errors (a contract function, "receipt", "nonce")."""
        with translated_errors():
            answer = self.w3.provider.make_request(method, params)
        return _rpc_result(answer, label)

    def batch(self, calls: list[tuple[str, list[Any]]], *, label: str) -> list[Any]:
        """Several requests in one JSON-RPC batch (one round trip): each answer's result, or
        the NodeRefused the node's error for it makes, in order."""
        with translated_errors():
            answers = self.w3.provider.make_batch_request(calls)
        if not isinstance(answers, list):  # the node refused the whole batch
            raise NodeRefused(label, _error_message(answers.get("error")))
        results: list[Any] = []
        for answer in answers:
            try:
                results.append(_rpc_result(answer, label))
            except NodeRefused as refused:
                results.append(refused)
        return results

    def call(self, call: dict[str, Any], *, label: str, block: str | int = "latest") -> bytes:
        """One eth_call (`call`'s to and data as hex, perhaps from and value) at `block`: the
        bytes it returned (empty when there is no code at `to`), or NodeRefused."""
        at = block if isinstance(block, str) else hex(block)
        return bytes(HexBytes(self.request("eth_call", [call, at], label=label) or b""))


def _error_message(error: Any) -> str:
    return str(error.get("message", error)) if isinstance(error, dict) else str(error)


def _rpc_result(answer: Any, label: str) -> Any:
    """A JSON-RPC answer's result, or NodeRefused with its error's message and data."""
    error = answer.get("error") if isinstance(answer, dict) else "no answer"
    if error is not None:
        data = error.get("data") if isinstance(error, dict) else None
        raise NodeRefused(label, _error_message(error), data if isinstance(data, str) else None)
    return answer.get("result")

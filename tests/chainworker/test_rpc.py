"""The connection to the node: URLs it takes, and a node that cannot be reached or answers an
HTTP error as ChainUnavailable."""

import threading
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

import pytest

from chainworker.client import AuthROSChain
from chainworker.errors import ChainUnavailable
from stack.anvil import free_port


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

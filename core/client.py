"""The connection of the client a request is served to, while it is served: whether the client
has gone (closed its end), so that work done only for it (a read waiting for its integrity
checks) can stop.

Set per request by portal.request_context from the WSGI server's socket (gunicorn puts it in
the environ as `gunicorn.socket`; behind a proxy, the proxy's connection, which it closes when
its client goes); a request without one (another server, a test client) is never taken as gone.
"""

import contextvars
import select
import socket

_connection: contextvars.ContextVar[socket.socket | None] = contextvars.ContextVar(
    "client_connection", default=None
)


def client_connection_set(connection: object) -> contextvars.Token:
    """The request's client socket (anything else counts as none), until reset."""
    return _connection.set(connection if isinstance(connection, socket.socket) else None)


def client_connection_reset(token: contextvars.Token) -> None:
    _connection.reset(token)


def client_gone() -> bool:
    """Whether the request's client closed its connection (what it sent but nobody read yet,
    a next request on a kept-alive connection, is a client still there)."""
    connection = _connection.get()
    if connection is None:
        return False
    try:
        poller = select.poll()
        poller.register(connection, select.POLLIN)
        if not poller.poll(0):
            return False
        return connection.recv(1, socket.MSG_PEEK) == b""
    except (BlockingIOError, InterruptedError):
        return False
    except ConnectionError:
        return True
    except (OSError, ValueError):  # closed here already, or a TLS socket (no peeking)
        return False

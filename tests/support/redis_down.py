"""A Redis client with nobody behind it, for tests of what the portal does without Redis.

It fails at once: redis-py's default client retries a refused connection ten times (about 3 s
per command), which would only make those tests wait, not test more.
"""

import redis
from redis.backoff import NoBackoff
from redis.retry import Retry

from stack.anvil import free_port


def redis_nobody_answers() -> redis.Redis:
    """A client for a free port: every command raises ConnectionError without retrying."""
    return redis.Redis(port=free_port(), socket_connect_timeout=1, retry=Retry(NoBackoff(), 0))

"""What the chain client's tests against an anvil of their own share."""

from collections.abc import Callable

import pytest
import redis
from eth_account import Account
from eth_account.signers.local import LocalAccount

from chainworker.client import AuthROSChain


@pytest.fixture
def deploy_on(redis_client: redis.Redis) -> Callable[[str], tuple[AuthROSChain, LocalAccount]]:
    """`deploy_on(url)`: a client of the node at `url` with the contract deployed by a new
    operator the node's faucet funded."""

    def deploy(url: str) -> tuple[AuthROSChain, LocalAccount]:
        client = AuthROSChain(url, redis_client=redis_client, receipt_timeout=30)
        operator = Account.create()
        assert client.dev_faucet(operator.address, 10**21)
        client.deploy(operator)
        return client, operator

    return deploy

"""Accounts that pay for the apps' chain work and run low on gas, for the admin's chain status
page. The apps own those accounts (owners' EOAs) and this layer imports none of them: each app
registers a lister here when Django starts (its AppConfig.ready), as with backlog.py.
"""

from collections.abc import Callable
from dataclasses import dataclass


@dataclass(frozen=True)
class LowBalance:
    """An account below its top-up threshold (`below_wei`) at the chain's current fee."""

    label: str
    address: str
    balance_wei: int
    below_wei: int


LowBalanceLister = Callable[[], list[LowBalance]]

_listers: list[LowBalanceLister] = []


def low_balance_lister_register(lister: LowBalanceLister) -> None:
    if lister not in _listers:
        _listers.append(lister)


def low_balances() -> list[LowBalance]:
    """Every registered lister's accounts; raises ChainError when the node does not answer."""
    return [low for lister in _listers for low in lister()]

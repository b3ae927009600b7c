"""The check of the portal's own secrets, run as a Django check before the portal serves
and the worker starts (accounts/apps.py): the master key that wraps the owners' keys."""

from accounts import keywrap
from accounts.errors import MasterKeyRefused


def secrets_verify() -> list[str]:
    """What keeps the portal from serving with its secrets: a master key (KEK) that is
    missing, unreadable or not the one the owner keys were wrapped with (accounts.keywrap
    keeps its fingerprint on the first check)."""
    try:
        keywrap.kek_verify()
    except MasterKeyRefused as exc:
        return [str(exc)]
    return []

from collections.abc import Sequence
from typing import Any

from django.apps import AppConfig
from django.core import checks
from django.db import DEFAULT_DB_ALIAS, connections

# The tag of the checks that keep the portal from serving and the worker from running while
# the portal's own secrets are wrong: run by portal/middleware.py, portal/celery.py and
# `manage.py check --database default`.
SERVICE_CHECKS = "authros_service"


class AccountsConfig(AppConfig):
    name = "accounts"

    def ready(self) -> None:
        # Models load only once the registry is ready, hence the imports here.
        from accounts.selectors import chain_backlog
        from accounts.services.funding import eoa_low_balances
        from chainworker.backlog import backlog_counter_register
        from chainworker.gas import low_balance_lister_register

        backlog_counter_register(chain_backlog)
        low_balance_lister_register(eoa_low_balances)
        checks.register(service_check, SERVICE_CHECKS, checks.Tags.database)


def service_check(
    app_configs: Sequence[AppConfig] | None = None,
    databases: Sequence[str] | None = None,
    **kwargs: Any,
) -> list[checks.CheckMessage]:
    """The master key opens what is wrapped under it and the operator key is the contract's
    admin. Only when asked with the database (it reads rows), and once it is migrated."""
    if not databases or DEFAULT_DB_ALIAS not in databases or not _migrated():
        return []
    from accounts.services.portal_secrets import secrets_verify
    from chainworker.errors import ChainError
    from chainworker.services import operator_verify

    messages: list[checks.CheckMessage] = [
        checks.Error(problem, id="accounts.E101") for problem in secrets_verify()
    ]
    try:
        messages += [checks.Error(problem, id="accounts.E102") for problem in operator_verify()]
    except ChainError as exc:
        messages.append(
            checks.Warning(
                f"the operator key was not checked: the chain did not answer ({exc})",
                hint="it is checked again once the chain answers",
                id="accounts.W101",
            )
        )
    return messages


def _migrated() -> bool:
    """Whether the tables the checks read exist (`migrate` runs the checks before migrating)."""
    from accounts.models import OwnerKey, SecretFingerprint
    from chainworker.models import Deployment

    tables = set(connections[DEFAULT_DB_ALIAS].introspection.table_names())
    return {m._meta.db_table for m in (SecretFingerprint, OwnerKey, Deployment)} <= tables

from django.apps import AppConfig


class AccountsConfig(AppConfig):
    name = "accounts"

    def ready(self) -> None:
        # Models load only once the registry is ready, hence the imports here.
        from accounts.selectors import chain_backlog
        from chainworker.backlog import backlog_counter_register

        backlog_counter_register(chain_backlog)

from django.apps import AppConfig


class SharingConfig(AppConfig):
    name = "sharing"

    def ready(self) -> None:
        # Models load only once the registry is ready, hence the imports here.
        from chainworker.backlog import backlog_counter_register
        from sharing.selectors import chain_backlog

        backlog_counter_register(chain_backlog)

from django.apps import AppConfig


class SharingConfig(AppConfig):
    name = "sharing"

    def ready(self) -> None:
        # Models load only once the registry is ready, hence the imports here.
        from accounts.services.registration import owner_chain_ready_listener_register
        from accounts.services.robot_keys import (
            robot_key_dispute_listener_register,
            robot_key_revoke_wait_register,
        )
        from chainworker.backlog import backlog_counter_register
        from sharing.selectors.activity import chain_backlog
        from sharing.services.anchoring import (
            anchor_after_chain_ready,
            robot_records_await_anchoring,
        )
        from sharing.services.robot_key_disputes import robot_key_dispute_record

        backlog_counter_register(chain_backlog)
        owner_chain_ready_listener_register(anchor_after_chain_ready)
        robot_key_revoke_wait_register(robot_records_await_anchoring)
        robot_key_dispute_listener_register(robot_key_dispute_record)

"""Celery tasks of accounts: each loads by id and calls one service (chain work, retried)."""

from celery import shared_task

from accounts.services import funding, pairing, registration, robot_keys
from chainworker.work import CHAIN_TASK


@shared_task(name="accounts.tasks.owner_register", **CHAIN_TASK)
def owner_register(owner_id: int) -> str:
    return registration.owner_register_on_chain(owner_id=owner_id).chain_state


@shared_task(name="accounts.tasks.key_rotate", **CHAIN_TASK)
def key_rotate(owner_key_id: int) -> str:
    return registration.key_rotate_on_chain(owner_key_id=owner_key_id).chain_state


@shared_task(name="accounts.tasks.robot_key_register", **CHAIN_TASK)
def robot_key_register(robot_id: str) -> str:
    return robot_keys.robot_key_register_on_chain(robot_id=robot_id).key_chain_state


@shared_task(name="accounts.tasks.robot_key_revoke", **CHAIN_TASK)
def robot_key_revoke(robot_id: str) -> str:
    return robot_keys.robot_key_revoke_on_chain(robot_id=robot_id).key_revoke_state


@shared_task(name="accounts.tasks.chain_work_sweep", soft_time_limit=60, time_limit=90)
def chain_work_sweep() -> dict[str, int]:
    return registration.chain_work_sweep()


@shared_task(name="accounts.tasks.owner_top_up", **CHAIN_TASK)
def owner_top_up(owner_id: int) -> str | None:
    funding_row = funding.owner_top_up(owner_id=owner_id)
    return funding_row.tx_hash if funding_row else None


@shared_task(name="accounts.tasks.robot_pairings_purge", soft_time_limit=60, time_limit=90)
def robot_pairings_purge() -> int:
    return pairing.robot_pairings_purge()

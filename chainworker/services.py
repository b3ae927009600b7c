"""The chain layer's own actions: the one client per process, the operator account,
deploying the contract once per chain, and the status an operator reads. Nothing here knows
owners, records or grants: the apps that own them call down into this layer."""

import logging
import threading
from dataclasses import dataclass

from django.conf import settings
from django.db import transaction
from eth_account import Account
from eth_account.signers.local import LocalAccount

from chainworker.chain import AuthROSChain, ContractNotDeployed
from chainworker.models import Deployment
from chainworker.selectors import deployment_active
from chainworker.work import exclusive
from core.redis_client import get_redis
from core.secrets import SecretFileError, load_or_create_secret

logger = logging.getLogger(__name__)

# The operator pays for deployment and funds new EOAs; keep it topped up on dev chains.
DEV_OPERATOR_FLOAT_WEI = 10_000 * 10**18

_clients: dict[str, AuthROSChain] = {}
_clients_lock = threading.Lock()


def operator_account() -> LocalAccount:
    """The operator (contract admin) account: from CHAIN_OPERATOR_KEY, else a 0600 file."""
    key = settings.CHAIN_OPERATOR_KEY
    if key:
        return Account.from_key(key)
    secret = load_or_create_secret(settings.SECRETS_DIR / "operator.key", nbytes=32)
    return Account.from_key(secret)


def chain_client() -> AuthROSChain:
    """The process's client for the configured chain, pointed at the active deployment."""
    url = settings.CHAIN_RPC_URL
    with _clients_lock:
        client = _clients.get(url)
        if client is None:
            client = AuthROSChain(
                url,
                redis_client=get_redis(),
                receipt_timeout=settings.CHAIN_RECEIPT_TIMEOUT,
                rpc_timeout=settings.CHAIN_RPC_TIMEOUT,
                confirmations=settings.CHAIN_CONFIRMATIONS,
                redis_prefix=settings.REDIS_KEY_PREFIX,
                nonce_lock_timeout=settings.CHAIN_NONCE_LOCK_TIMEOUT,
            )
            _clients[url] = client
    address = settings.CHAIN_CONTRACT_ADDRESS or _recorded_address(client)
    if address and address != client._address:
        client.use_contract(address)
    return client


def _recorded_address(client: AuthROSChain) -> str | None:
    deployment = deployment_active(chain_id=client.chain_id, genesis_hash=client.genesis_hash)
    return deployment.address if deployment else None


def operator_ensure_funded(*, client: AuthROSChain, operator: LocalAccount) -> None:
    """On a development chain, top up the operator; on a real one, only warn."""
    if client.balance(operator.address) >= DEV_OPERATOR_FLOAT_WEI // 10:
        return
    if settings.CHAIN_DEV_FAUCET and client.dev_faucet(operator.address, DEV_OPERATOR_FLOAT_WEI):
        return
    logger.warning(
        "operator %s has a low balance on chain %s: fund it (genesis alloc on a PoA network)",
        operator.address,
        client.chain_id,
    )


@dataclass(frozen=True)
class DeployOutcome:
    deployment: Deployment
    created: bool
    reason: str


def contract_deploy(*, force: bool = False) -> DeployOutcome:
    """Deploy the AuthROS contract once per chain and record where it is.

    Idempotent: with an active deployment whose code is still on chain, nothing is sent.
    `force` deploys a new contract and retires the old record.
    """
    client = chain_client()
    operator = operator_account()
    with exclusive(f"deploy:{client.chain_key}", timeout=300, wait=300):
        current = deployment_active(chain_id=client.chain_id, genesis_hash=client.genesis_hash)
        if current and not force:
            if client.has_code(current.address):
                client.use_contract(current.address)
                return DeployOutcome(current, created=False, reason="already deployed")
            reason = f"no code at recorded address {current.address} (chain was reset)"
        else:
            reason = "forced" if current else "first deployment"
        operator_ensure_funded(client=client, operator=operator)
        result = client.deploy(operator)
        with transaction.atomic():
            if current:
                Deployment.objects.filter(pk=current.pk).update(is_active=False)
            deployment = Deployment.objects.create(
                chain_id=client.chain_id,
                genesis_hash=client.genesis_hash,
                address=client.address,
                tx_hash=result.tx_hash,
                block_number=result.block_number,
                deployer=operator.address,
                compiler_version=client.artifact.compiler_version,
                source_keccak=client.artifact.source_keccak,
                rpc_url=settings.CHAIN_RPC_URL if not client.is_in_process else "",
            )
    logger.info(
        "deployed AuthROS at %s on chain %s (%s)", deployment.address, client.chain_id, reason
    )
    return DeployOutcome(deployment, created=True, reason=reason)


def chain_status() -> dict[str, object]:
    """What an operator wants to know about the chain; raises ChainUnavailable if it is down."""
    client = chain_client()
    operator = operator_account()
    status: dict[str, object] = {
        "node_url": settings.CHAIN_RPC_URL,
        "client_version": client.client_version,
        "chain_id": client.chain_id,
        "latest_block": client.latest_block(),
        "contract_address": None,
        "admin": None,
        "operator": operator.address,
        "operator_balance_wei": client.balance(operator.address),
        "confirmations": settings.CHAIN_CONFIRMATIONS,
    }
    try:
        status["contract_address"] = client.address
        status["admin"] = client.admin()
        status["record_count"] = client.record_count()
    except ContractNotDeployed:
        status["problem"] = "contract not deployed: run `manage.py chain_deploy`"
    return status


def operator_verify() -> list[str]:
    """Why the operator key cannot do this portal's chain work: it must be the admin of the
    contract in use. Nothing to say while no contract is deployed; raises ChainError when the
    node does not answer, which is no refusal: ask again later."""
    deployed = Deployment.objects.filter(is_active=True).exists()
    if not (deployed or settings.CHAIN_CONTRACT_ADDRESS):
        return []
    try:
        operator = operator_account()
    except (ValueError, SecretFileError) as exc:
        return [f"the operator key cannot be read ({exc}): restore operator.key"]
    client = chain_client()
    try:
        address = client.address
    except ContractNotDeployed:
        return []  # none on this chain yet (another chain's deployment is recorded)
    if not client.has_code(address):
        return []  # the chain was reset: `manage.py chain_deploy` says so and deploys again
    admin = client.admin()
    if admin.lower() != operator.address.lower():
        return [
            f"the operator key (address {operator.address}) is not the admin of the AuthROS "
            f"contract at {address} (admin {admin}): restore operator.key or CHAIN_OPERATOR_KEY"
        ]
    return []

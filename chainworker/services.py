"""The chain layer's own actions: the one client per process, the operator account,
deploying the contract once per chain, the status an operator reads, operator alerts, the
chain's identity (a reset is told from the genesis) and a stalled chain. Nothing here knows
owners, records or grants: the apps that own them call down into this layer.

It is over 500 lines because its parts call each other both ways: the stall check needs the
client and the operator alerts, while chain_work_check and chain_status need the stall verdict.
Split in two, they would import each other; a split wants the client and the alerts in a
module of their own below the rest first.
"""

import json
import logging
import threading
import time
from contextlib import suppress
from dataclasses import dataclass

from django.conf import settings
from django.db import IntegrityError, transaction
from django.db.models import QuerySet
from django.utils import timezone
from eth_account import Account
from eth_account.signers.local import LocalAccount
from redis.exceptions import RedisError

from chainworker.client import AuthROSChain
from chainworker.errors import ContractNotDeployed
from chainworker.models import Deployment, OperatorAlert
from chainworker.selectors import deployment_active
from chainworker.work import ChainWorkNotReady, exclusive
from core.redis_client import get_redis, redis_key
from core.secrets import SecretFileError, load_or_create_secret

logger = logging.getLogger(__name__)
# Where an operator looks for what needs them (docs/security.md).
security_log = logging.getLogger("authros.security")

# The operator pays for deployment and funds new EOAs; keep it topped up on dev chains.
DEV_OPERATOR_FLOAT_WEI = 10_000 * 10**18

# How long a process keeps the active deployment's address it read from the database before
# reading it again: a contract deployed by another process is followed within this time (the
# deploying process switches at once). Reading it for every request cost a query per upload
# and per view.
DEPLOYMENT_RECHECK_SECONDS = 2.0


@dataclass
class _ProcessClient:
    chain: AuthROSChain
    address_read_at: float | None = None  # time.monotonic() of the last read that found one


_clients: dict[str, _ProcessClient] = {}
_clients_lock = threading.Lock()


def operator_account() -> LocalAccount:
    """The operator (contract admin) account: from CHAIN_OPERATOR_KEY, else a 0600 file."""
    key = settings.CHAIN_OPERATOR_KEY
    if key:
        return Account.from_key(key)
    secret = load_or_create_secret(settings.SECRETS_DIR / "operator.key", nbytes=32)
    return Account.from_key(secret)


def chain_client() -> AuthROSChain:
    """The process's client for the configured chain, pointed at the active deployment (read
    again at most every DEPLOYMENT_RECHECK_SECONDS once one was found)."""
    url = settings.CHAIN_RPC_URL
    with _clients_lock:
        entry = _clients.get(url)
        if entry is None:
            entry = _ProcessClient(
                AuthROSChain(
                    url,
                    redis_client=get_redis(),
                    receipt_timeout=settings.CHAIN_RECEIPT_TIMEOUT,
                    rpc_timeout=settings.CHAIN_RPC_TIMEOUT,
                    confirmations=settings.CHAIN_CONFIRMATIONS,
                    redis_prefix=settings.REDIS_KEY_PREFIX,
                    nonce_lock_timeout=settings.CHAIN_NONCE_LOCK_TIMEOUT,
                )
            )
            _clients[url] = entry
    client = entry.chain
    address = settings.CHAIN_CONTRACT_ADDRESS
    if not address:
        now = time.monotonic()
        read_at = entry.address_read_at
        if client._address and read_at is not None and now - read_at < DEPLOYMENT_RECHECK_SECONDS:
            return client
        address = _recorded_address(client)
        entry.address_read_at = now if address else None
    if address and address != client._address:
        client.use_contract(address)
    return client


def chain_head(client: AuthROSChain) -> int:
    """The chain's latest block, as every process saw it at most IDENTITY_BLOCK_CACHE_SECONDS
    ago (kept in Redis): a burst of views and uploads costs one eth_blockNumber."""
    seconds = settings.IDENTITY_BLOCK_CACHE_SECONDS
    if seconds <= 0:
        return client.latest_block()
    key = redis_key("latest-block", client.chain_key)
    with suppress(RedisError):
        if (cached := get_redis().get(key)) is not None:
            return int(cached)
    block = client.latest_block()
    with suppress(RedisError):
        get_redis().set(key, str(block), px=max(1, int(seconds * 1000)))
    return block


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


def contract_deploy(*, force: bool = False, replace_outdated: bool = False) -> DeployOutcome:
    """Deploy the AuthROS contract once per chain and record where it is.

    Idempotent: with an active deployment whose code is still on chain, nothing is sent.
    `force` deploys a new contract and retires the old record; `replace_outdated` does so only
    if the active one was built from another contracts/AuthROS.sol, decided under the lock, so
    that processes handling one reset at once deploy once.
    """
    client = chain_client()
    operator = operator_account()
    with exclusive(f"deploy:{client.chain_key}", timeout=300, wait=300):
        current = deployment_active(chain_id=client.chain_id, genesis_hash=client.genesis_hash)
        if current and not force:
            outdated = replace_outdated and _deployment_outdated(client, current)
            if client.has_code(current.address) and not outdated:
                client.use_contract(current.address)
                return DeployOutcome(current, created=False, reason="already deployed")
            reason = (
                f"the contract at {current.address} was built from an older source"
                if outdated
                else f"no code at recorded address {current.address} (chain was reset)"
            )
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
                rpc_url=settings.CHAIN_RPC_URL,
            )
    logger.info(
        "deployed AuthROS at %s on chain %s (%s)", deployment.address, client.chain_id, reason
    )
    return DeployOutcome(deployment, created=True, reason=reason)


def chain_status() -> dict[str, object]:
    """What an operator wants to know about the chain; raises ChainUnavailable if it is down."""
    identity = chain_identity()  # first: it drops a client built for the chain before a reset
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
        "chain_identity": identity.state,
    }
    if identity.state == IDENTITY_RESET:
        status["problem"] = f"chain reset: {identity.reason}; " + (
            "this development chain is redeployed and re-created from the database by the "
            "reconciliation job (or `manage.py chain_resync`)"
            if identity.development
            else "sending is stopped: check the node, then `manage.py chain_resync` deploys "
            "and re-creates everything from the database"
        )
        return status
    try:
        status["contract_address"] = client.address
        status["admin"] = client.admin()
        status["record_count"] = client.record_count()
    except ContractNotDeployed:
        status["problem"] = "contract not deployed: run `manage.py chain_deploy`"
    stall = chain_stall_check()
    status["chain_stalled"] = stall.stalled
    status["seconds_since_block"] = round(stall.seconds_without_block)
    if stall.stalled:
        paused = (
            f"chain stalled: {stall.reason}; sending is paused (no attempt is used up) and "
            "resumes by itself once the node makes blocks again: check the node's miners or "
            "validators"
        )
        status["problem"] = "; ".join(filter(None, [status.get("problem"), paused]))
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


# --- operator alerts and the operator's gas ------------------------------------------------


def operator_alert_raise(
    *, kind: str, subject: str, detail: dict[str, object] | None = None
) -> OperatorAlert:
    """Open an alert for the operator, or refresh the open one of this kind and subject (one
    at most); logged on "authros.security" when it opens."""
    detail = detail or {}
    open_alerts = OperatorAlert.objects.filter(kind=kind, subject=subject, resolved_at=None)
    if not open_alerts.update(detail=detail, last_seen_at=timezone.now()):
        try:
            with transaction.atomic():
                alert = OperatorAlert.objects.create(kind=kind, subject=subject, detail=detail)
        except IntegrityError:
            open_alerts.update(detail=detail, last_seen_at=timezone.now())  # lost a race
        else:
            security_log.error("operator alert %s on %s: %s", kind, subject, detail)
            return alert
    return open_alerts.get()


def operator_alert_resolve(*, kind: str, subject: str) -> bool:
    """Close the open alert of this kind and subject; whether there was one."""
    resolved = OperatorAlert.objects.filter(kind=kind, subject=subject, resolved_at=None).update(
        resolved_at=timezone.now()
    )
    if resolved:
        security_log.warning("operator alert %s on %s resolved", kind, subject)
    return bool(resolved)


@dataclass(frozen=True)
class OperatorGas:
    address: str
    balance_wei: int
    fee_per_gas: int

    @property
    def low(self) -> bool:
        """Below CHAIN_OPERATOR_LOW_WEI on a chain with gas prices (a zero-gas chain needs none)."""
        return self.fee_per_gas > 0 and self.balance_wei < settings.CHAIN_OPERATOR_LOW_WEI


def operator_gas() -> OperatorGas:
    """The operator's balance and the chain's fee per gas; raises ChainError if the node is away."""
    client = chain_client()
    address = operator_account().address
    return OperatorGas(address, client.balance(address), client.fee_per_gas())


def operator_balance_check() -> OperatorGas:
    """Raise the operator's low-balance alert while it is low, resolve it once it is not."""
    gas = operator_gas()
    kind = OperatorAlert.Kind.OPERATOR_LOW_BALANCE
    if gas.low:
        operator_alert_raise(
            kind=kind,
            subject=gas.address,
            detail={
                "balance_wei": str(gas.balance_wei),
                "low_wei": str(settings.CHAIN_OPERATOR_LOW_WEI),
            },
        )
    else:
        operator_alert_resolve(kind=kind, subject=gas.address)
    return gas


# --- chain identity: is the node still the chain the portal deployed on? --------------------

IDENTITY_SAME = "same"
IDENTITY_RESET = "reset"
IDENTITY_UNDEPLOYED = "undeployed"


@dataclass(frozen=True)
class ChainIdentity:
    """The node compared with the active deployment: "same"; "reset" (another genesis or chain
    id, or no contract code at the address); "undeployed" (no contract recorded yet)."""

    state: str
    reason: str
    development: bool
    deployment: Deployment | None


def chain_is_development(client: AuthROSChain) -> bool:
    """A chain the portal may fund and redeploy on by itself, as operator_ensure_funded decides:
    CHAIN_DEV_FAUCET on, and anvil."""
    if not settings.CHAIN_DEV_FAUCET:
        return False
    return client.client_version.lower().startswith("anvil")


def chain_identity() -> ChainIdentity:
    """Compare the node's chain id, genesis hash and contract code with the active deployment.

    Reads the node afresh (a long-lived client caches its chain id and genesis); a client
    built for another chain is dropped so the next chain_client() follows the node. Raises
    ChainUnavailable when the node does not answer.
    """
    client = chain_client()
    # The uncached reads of the client's cached properties.
    chain_id = AuthROSChain.chain_id.func(client)
    genesis = AuthROSChain.genesis_hash.func(client)
    if (chain_id, genesis) != (client.chain_id, client.genesis_hash):
        with _clients_lock:
            _clients.pop(settings.CHAIN_RPC_URL, None)
        client = chain_client()
    development = chain_is_development(client)
    active = Deployment.objects.filter(is_active=True).order_by("-created_at")
    deployment = active.filter(chain_id=chain_id, genesis_hash=genesis).first() or active.first()
    pinned = settings.CHAIN_CONTRACT_ADDRESS
    if deployment is None and not pinned:
        return ChainIdentity(IDENTITY_UNDEPLOYED, "no contract deployed yet", development, None)
    if deployment is not None and (deployment.chain_id, deployment.genesis_hash) != (
        chain_id,
        genesis,
    ):
        reason = (
            f"the node is chain id {chain_id} with genesis {genesis[:18]}…, but the contract "
            f"was deployed on chain id {deployment.chain_id} with genesis "
            f"{deployment.genesis_hash[:18]}… (a new chain or a reset)"
        )
        return ChainIdentity(IDENTITY_RESET, reason, development, deployment)
    address = pinned or deployment.address
    if not client.has_code(address):
        reason = f"no contract code at {address} on chain id {chain_id} (the chain was reset)"
        return ChainIdentity(IDENTITY_RESET, reason, development, deployment)
    if development and not pinned and _deployment_outdated(client, deployment):
        # A development chain (`make run`'s anvil state) holding the contract of an older
        # contracts/AuthROS.sol: deployed again and re-created from the database like a reset
        # one. A real network keeps its contract: docs/operations.md says how to upgrade it.
        reason = (
            f"the contract at {address} was built from an older contracts/AuthROS.sol "
            f"({deployment.source_keccak[:12]}…, now {client.artifact.source_keccak[:12]}…)"
        )
        return ChainIdentity(IDENTITY_RESET, reason, development, deployment)
    return ChainIdentity(IDENTITY_SAME, "", development, deployment)


def _deployment_outdated(client: AuthROSChain, deployment: Deployment) -> bool:
    """Whether the deployment was built from another source than the artifact in use (rows
    recorded without a source hash count as current)."""
    recorded = deployment.source_keccak
    return bool(recorded) and recorded != client.artifact.source_keccak


def _identity_cache_key() -> str:
    return redis_key("chain-identity", settings.CHAIN_RPC_URL)


def chain_work_check() -> None:
    """Raise ChainWorkNotReady while the node is not the chain the portal deployed on, so that
    nothing is sent to a reset chain, and while the chain is stalled (chain_stalled). Each
    verdict is kept in Redis for CHAIN_IDENTITY_CACHE_SECONDS, so the senders of every process
    cost one chain look-up.

    A verdict names the chain it was made for. A process whose client was built for another
    chain (before a reset that another process found and repaired) checks for itself, which
    replaces its client: otherwise it would go on with the old chain's nonce counters, and a
    nonce above the account's on the new chain waits in the node's pool for ever."""
    cached = None
    with suppress(RedisError):
        cached = get_redis().get(_identity_cache_key())
    verdict = json.loads(cached) if cached is not None else None
    if verdict is None or verdict.get("chain") != _chain_of(chain_client()):
        identity = chain_identity()
        verdict = {
            "state": identity.state,
            "reason": identity.reason,
            "chain": _chain_of(chain_client()),
        }
        with suppress(RedisError):
            get_redis().set(
                _identity_cache_key(),
                json.dumps(verdict),
                px=max(1, int(settings.CHAIN_IDENTITY_CACHE_SECONDS * 1000)),
            )
    if verdict["state"] == IDENTITY_RESET:
        raise ChainWorkNotReady(f"sending is stopped: {verdict['reason']}")
    # A stalled chain: every sender pauses, using up no attempt, until blocks move again.
    if stalled := _stall_reason():
        raise ChainWorkNotReady(f"sending is paused, the chain is stalled: {stalled}")


def _chain_of(client: AuthROSChain) -> str:
    """The chain a client was built for (its cached chain id and genesis)."""
    return f"{client.chain_id}:{client.genesis_hash}"


def chain_identity_forget() -> None:
    """Drop the kept verdict of chain_work_check (after a redeployment)."""
    with suppress(RedisError):
        get_redis().delete(_identity_cache_key())


def contract_redeploy_after_reset() -> DeployOutcome:
    """Deploy the contract on the chain the node is now (a reset chain) and make it the only
    active deployment; the operator's nonce counter starts again from the node."""
    chain_identity()  # drops a client built for the chain before the reset
    # A development chain's outdated contract still has code at its address: replaced; not
    # forced, or every process handling the same reset would deploy again over the others.
    outcome = contract_deploy(replace_outdated=True)
    Deployment.objects.filter(is_active=True).exclude(pk=outcome.deployment.pk).update(
        is_active=False
    )
    chain_client().resync_nonce(operator_account().address)
    chain_identity_forget()
    return outcome


def reconcile_window(*, name: str, queryset: QuerySet, size: int) -> list:
    """The next `size` rows of `queryset` in primary key order after a cursor kept in Redis,
    from the start again once the end is reached: every row is seen within len/size calls.
    Without Redis, the first `size` rows."""
    key = redis_key("reconcile-cursor", name)
    cursor = None
    with suppress(RedisError):
        cursor = get_redis().get(key)
    ordered = queryset.order_by("pk")
    rows = list(ordered.filter(pk__gt=cursor.decode())[:size]) if cursor else []
    if len(rows) < size:
        taken = {row.pk for row in rows}
        rows += [row for row in ordered[: size - len(rows)] if row.pk not in taken]
    with suppress(RedisError):
        if rows:
            get_redis().set(key, str(rows[-1].pk))
        else:
            get_redis().delete(key)
    return rows


# --- a stalled chain: no new block while work waits -----------------------------------------

# The operator alert of a stalled chain (subject: the chain id, never the node URL, which may
# carry an API key).
CHAIN_STALLED_ALERT = "chain-stalled"


@dataclass(frozen=True)
class ChainStall:
    """The node's latest block and whether the chain has stopped making blocks."""

    stalled: bool
    reason: str
    latest_block: int
    seconds_without_block: float
    waiting: int | None  # transactions the node holds ready and has not mined; None: unknown


def _waiting_key() -> str:
    return redis_key("chain-waiting-since", settings.CHAIN_RPC_URL)


def _waiting_since(*, latest: int, waiting: bool, since: float | None, now: float) -> float | None:
    """When work was first seen waiting on top of block `latest` (kept in Redis, so that a
    check that sees a transaction just arrived on a long idle chain does not call it a stall);
    None while nothing waits."""
    if not waiting:
        with suppress(RedisError):
            get_redis().delete(_waiting_key())
        return None
    start = since if since is not None else now
    with suppress(RedisError, ValueError, KeyError, TypeError):
        kept = get_redis().get(_waiting_key())
        seen = json.loads(kept) if kept else None
        if seen and seen["block"] == latest:
            start = min(start, float(seen["since"]))
    with suppress(RedisError):
        get_redis().set(
            _waiting_key(), json.dumps({"block": latest, "since": start}), ex=7 * 24 * 3600
        )
    return start


def chain_stalled(*, since: float | None = None) -> ChainStall:
    """Whether the chain has stopped making blocks; `since`: the caller has a transaction of
    its own waiting to be mined since then (epoch seconds), e.g. a receipt that timed out.

    "No new block for CHAIN_STALL_AFTER seconds" alone cannot be the test: a node that mines
    only when transactions arrive (anvil's automine, `make run`'s default; a proof-of-authority
    network without empty blocks) makes no block at all while the portal is idle. So:
    - CHAIN_BLOCK_TIME set (the operator says the node makes a block every so often even with
      nothing to mine, as anvil --block-time or a Besu/geth PoA network does): the latest
      block older than CHAIN_STALL_AFTER is a stall, idle or not;
    - else (the default): only while work waits, that is the node holds transactions ready to
      mine (txpool_status, else its pending block) or the caller has one of its own (`since`):
      no new block for CHAIN_STALL_AFTER since both the latest block and the moment the
      waiting was first seen is a stall.
    Raises ChainUnavailable when the node does not answer (that is an outage, not a stall).
    """
    client = chain_client()
    latest, timestamp = client.head()
    now = timezone.now().timestamp()
    after = settings.CHAIN_STALL_AFTER
    pending = client.pending_transaction_count()
    if settings.CHAIN_BLOCK_TIME > 0:
        quiet = max(0.0, now - timestamp)
        expected = f"a block every {settings.CHAIN_BLOCK_TIME:g} s is expected"
    else:
        # A node that cannot tell its pool: what we saw waiting on this block still waits.
        waiting = bool(pending) or since is not None or (pending is None and _still_waiting(latest))
        start = _waiting_since(latest=latest, waiting=waiting, since=since, now=now)
        quiet = 0.0 if start is None else max(0.0, now - max(timestamp, start))
        expected = f"{pending if pending is not None else 'some'} transaction(s) wait"
    if quiet < after:
        return ChainStall(False, "", latest, max(0.0, now - timestamp), pending)
    reason = (
        f"no new block for {quiet:.0f} s after block {latest} while {expected} "
        f"(CHAIN_STALL_AFTER {after:g} s)"
    )
    return ChainStall(True, reason, latest, max(0.0, now - timestamp), pending)


def _still_waiting(latest: int) -> bool:
    with suppress(RedisError, ValueError, KeyError, TypeError):
        kept = get_redis().get(_waiting_key())
        return bool(kept) and json.loads(kept)["block"] == latest
    return False


def _stall_cache_key() -> str:
    return redis_key("chain-stall", settings.CHAIN_RPC_URL)


def chain_stall_check(*, since: float | None = None) -> ChainStall:
    """chain_stalled, with its consequences: the operator alert raised while the chain is
    stalled and resolved once blocks move again, and the verdict kept in Redis for
    CHAIN_IDENTITY_CACHE_SECONDS for chain_work_check. Raises ChainUnavailable."""
    stall = chain_stalled(since=since)
    subject = f"chain {chain_client().chain_id}"
    if stall.stalled:
        operator_alert_raise(
            kind=CHAIN_STALLED_ALERT,
            subject=subject,
            detail={
                "reason": stall.reason,
                "latest_block": stall.latest_block,
                "seconds_without_block": round(stall.seconds_without_block),
                "waiting": stall.waiting,
            },
        )
    else:
        operator_alert_resolve(kind=CHAIN_STALLED_ALERT, subject=subject)
    with suppress(RedisError):
        get_redis().set(
            _stall_cache_key(),
            stall.reason if stall.stalled else "",
            px=max(1, int(settings.CHAIN_IDENTITY_CACHE_SECONDS * 1000)),
        )
    return stall


def chain_stall_forget() -> None:
    """Drop the kept stall verdict of chain_work_check (e.g. once the operator restarted mining)."""
    with suppress(RedisError):
        get_redis().delete(_stall_cache_key())


def _stall_reason() -> str:
    """Why the chain is stalled ("" if it is not), from Redis or asked afresh."""
    cached = None
    with suppress(RedisError):
        cached = get_redis().get(_stall_cache_key())
    if cached is not None:
        return cached.decode()
    stall = chain_stall_check()
    return stall.reason if stall.stalled else ""

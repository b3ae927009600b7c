"""A grant on chain, run by the worker: the chain made to agree with the portal's grant.

`grant_sync_on_chain` (task `sharing.tasks.grant_sync`) sends `authorityGrant`,
`authorityGrantScoped` or `authorityRevoke` from the owner's EOA, under a lock per pair of
owners, unless the chain holds the grant as the portal has it already
(sharing.grant_terms.grant_on_chain_matches); a refusal that a lost race explains counts as
done, one that will never pass fails the grant with the reason in words.
"""

import logging
from collections.abc import Callable

from django.conf import settings

from accounts.models import ChainActivity, ChainState
from accounts.selectors import owner_eoa_account
from accounts.services.activity import chain_activity_record
from alerts.services import grant_received_alert
from chainworker.codec import TxResult
from chainworker.errors import InsufficientFunds, TransactionReverted
from chainworker.services import chain_client, chain_work_check
from chainworker.work import WAITING_FOR_GAS, ChainWorkNotReady, exclusive
from core.outbox import enqueue
from sharing.grant_terms import grant_on_chain_matches
from sharing.models import Grant
from sharing.scope import ALL_RECORDS_COMMITMENT, scope_commitment

logger = logging.getLogger(__name__)


def grant_sync_on_chain(*, grant_id: int) -> Grant:
    """Make the chain agree with the portal's grant: authorityGrant or authorityRevoke."""
    grant = Grant.objects.select_related("owner", "grantee").get(pk=grant_id)
    for party in (grant.owner, grant.grantee):
        if party.chain_state != ChainState.CONFIRMED:
            raise ChainWorkNotReady(f"{party} is not registered on chain yet")
    chain_work_check()  # nothing goes to a reset chain
    pair = f"grant:{grant.owner_id}:{grant.grantee_id}"
    with exclusive(pair, timeout=settings.CHAIN_RECEIPT_TIMEOUT + 30):
        grant.refresh_from_db()
        try:
            _grant_sync(grant)
        except InsufficientFunds:
            # The owner's account cannot pay for gas: the grant waits (no failure), says why,
            # and is sent again once the operator topped the account up.
            Grant.objects.filter(pk=grant.pk).update(failure_reason=WAITING_FOR_GAS)
            enqueue("accounts.tasks.owner_top_up", grant.owner_id)
            raise
        except TransactionReverted as exc:
            if grant.status != Grant.Status.PENDING:
                raise  # a revocation is never given up: it fails loudly and the sweep retries
            # The contract will refuse this grant every time: say so, do not retry forever.
            Grant.objects.filter(pk=grant.pk, status=Grant.Status.PENDING).update(
                status=Grant.Status.FAILED,
                failure_reason=GRANT_REFUSALS.get(exc.error_name, str(exc))[:300],
            )
            logger.error("grant %s refused on chain: %s", grant.pk, exc)
    Grant.objects.filter(pk=grant.pk, failure_reason=WAITING_FOR_GAS).update(failure_reason="")
    grant.refresh_from_db()
    return grant


# Why a scoped or expiring grant cannot be written to a contract deployed before they existed.
CONTRACT_WITHOUT_SCOPES = (
    "the contract deployed on this chain predates scoped and expiring grants: an operator must "
    'upgrade it (docs/grants.md, "Upgrading a deployment"); a grant of all records without '
    "expiry works meanwhile"
)


# The chain's refusals of a grant that the owner can act on, in words.
GRANT_REFUSALS = {
    "ScopedGrantsUnsupported": CONTRACT_WITHOUT_SCOPES,
    "ExpiryInPast": "the expiry passed before the grant reached the chain: give access again "
    "with a later expiry",
}


def _grant_sync(grant: Grant) -> None:
    client = chain_client()
    owner, grantee = grant.owner, grant.grantee
    on_chain = client.grant_of(owner.eoa_address, grantee.eoa_address)
    if on_chain is None:  # a contract from before scoped grants
        has_access = client.has_access(owner.eoa_address, grantee.eoa_address)
        exists, same_terms = has_access, has_access
    else:
        has_access = on_chain.live
        # An expired grant is still there (its terms are nonzero) until revoked.
        exists = on_chain.live or on_chain.expiry != 0 or on_chain.scope != ALL_RECORDS_COMMITMENT
        same_terms = grant_on_chain_matches(grant, on_chain)
    if grant.status == Grant.Status.PENDING:
        fields: dict[str, object] = {"status": Grant.Status.ACTIVE}
        if not same_terms:
            if on_chain is None and grant.is_limited:
                raise TransactionReverted("ScopedGrantsUnsupported")
            account = owner_eoa_account(owner)
            if not exists and not grant.is_limited:
                # The plain grant of DESIGN.md, as before scopes: all records, no expiry.
                send, tolerated = (
                    lambda: client.authority_grant(account, grantee.eoa_address),
                    "AlreadyGranted",
                )
            else:
                send, tolerated = (
                    lambda: client.authority_grant_scoped(
                        account,
                        grantee.eoa_address,
                        scope_commitment(grant.scope),
                        grant.expiry,
                    ),
                    "SameTerms",
                )
            result = _tolerating(tolerated, send)
            if result is not None:
                fields.update(grant_tx=result.tx_hash, grant_block=result.block_number)
                _grant_activity_record(grant, ChainActivity.Kind.GRANTED, result)
        if Grant.objects.filter(pk=grant.pk, status=Grant.Status.PENDING).update(**fields):
            grant_received_alert(grantee=grantee, owner=owner)
    elif grant.status == Grant.Status.REVOKING:
        fields = {"status": Grant.Status.REVOKED}
        if exists:
            result = _tolerating(
                "NoGrant",
                lambda: client.authority_revoke(owner_eoa_account(owner), grantee.eoa_address),
            )
            if result is not None:
                fields.update(revoke_tx=result.tx_hash, revoke_block=result.block_number)
                _grant_activity_record(grant, ChainActivity.Kind.REVOKED, result)
        Grant.objects.filter(pk=grant.pk, status=Grant.Status.REVOKING).update(**fields)


def _grant_activity_record(grant: Grant, kind: str, result: TxResult) -> None:
    """The audit page's entry of a grant or revocation, for the owner and the grantee."""
    chain_activity_record(
        owner=grant.owner,
        counterpart=grant.grantee,
        kind=kind,
        tx_hash=result.tx_hash,
        block_number=result.block_number,
    )


def _tolerating(error_name: str, send: Callable[[], TxResult]) -> TxResult | None:
    """Send; a refusal meaning "already the case" (a lost race) counts as done."""
    try:
        return send()
    except TransactionReverted as exc:
        if exc.error_name == error_name:
            return None
        raise

"""Whether a viewer may read an owner's records at this moment: the portal's grant, live and
not expired, and the chain's (`grantOf`, one eth_call) holding the same terms. The worker asks
it once per record owner in a check run; the owner's own records need no grant (OWN).

The comparison of the portal's terms with the chain's is
`sharing.grant_terms.grant_on_chain_matches`, the one the grants' chain sync uses too.
"""

import logging

from accounts.models import Owner
from chainworker.client import AuthROSChain
from sharing.grant_terms import grant_on_chain_matches
from sharing.models import Grant, Record
from sharing.selectors.grants import grant_live

logger = logging.getLogger(__name__)

# The owner's own records need no grant: grant_checked answers this for the owner.
OWN = Grant(status=Grant.Status.ACTIVE)


def grant_checked(record: Record, viewer: Owner, client: AuthROSChain) -> Grant | None:
    """The grant that lets `viewer` read the record owner's records, if it holds in the
    portal (active, not expired) and on chain (grantOf, one eth_call: live at the latest
    block, the same scope commitment and expiry as the portal's); OWN for the owner."""
    if viewer.pk == record.owner_id:
        return OWN
    grant = grant_live(owner_id=record.owner_id, viewer=viewer)
    if grant is None:
        return None
    owner_eoa, viewer_eoa = record.owner.eoa_address, viewer.eoa_address
    on_chain = client.grant_of(owner_eoa, viewer_eoa)
    if on_chain is None:  # a contract from before scoped grants: only plain grants hold
        holds = not grant.is_limited and client.has_access(owner_eoa, viewer_eoa)
    else:
        holds = grant_on_chain_matches(grant, on_chain)
    if not holds:
        logger.info("grant %s does not hold on chain as the portal has it", grant.pk)
        return None
    return grant


def grant_covers(grant: Grant, record: Record) -> bool:
    """The record is inside the grant's scope (every record is inside OWN)."""
    return grant is OWN or grant.scope.covers(
        robot_id=record.robot_id, topic=record.topic, captured_at=record.captured_at
    )

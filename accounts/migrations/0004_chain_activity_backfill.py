"""Fill the audit page's index (ChainActivity) from what the database already knows of each
owner's transactions: registration steps, key rotations, anchoring batches, grants and
revocations. New rows are written by the worker as it sees receipts; this covers the past.

Only the times are approximate (when the row was made, or its record anchored), and the
blocks of funding and enrolment are not kept anywhere, so they stay empty.
"""

from django.db import migrations
from django.db.models import Count, Max
from django.utils import timezone


def chain_activity_backfill(apps, schema_editor) -> None:
    ChainActivity = apps.get_model("accounts", "ChainActivity")
    Owner = apps.get_model("accounts", "Owner")
    OwnerKey = apps.get_model("accounts", "OwnerKey")
    Record = apps.get_model("sharing", "Record")
    Grant = apps.get_model("sharing", "Grant")
    rows = []
    register_txs = {}
    for owner in Owner.objects.all().iterator():
        if owner.fund_tx:
            rows.append(
                ChainActivity(
                    owner=owner, kind="funded", tx_hash=owner.fund_tx, at=owner.created_at
                )
            )
        if owner.enroll_tx:
            rows.append(
                ChainActivity(
                    owner=owner, kind="enrolled", tx_hash=owner.enroll_tx, at=owner.created_at
                )
            )
        if owner.register_tx:
            register_txs[owner.pk] = owner.register_tx
    for key in OwnerKey.objects.exclude(tx_hash="").order_by("created_at").iterator():
        registration = register_txs.get(key.owner_id) == key.tx_hash
        rows.append(
            ChainActivity(
                owner_id=key.owner_id,
                kind="registered" if registration else "key_rotated",
                tx_hash=key.tx_hash,
                block_number=key.block_number,
                detail={"key_id": key.key_id, "commitment": key.commitment},
                at=key.created_at,
            )
        )
    keyed = {(row.owner_id, row.tx_hash) for row in rows if row.kind == "registered"}
    for owner in Owner.objects.exclude(register_tx="").iterator():
        if (owner.pk, owner.register_tx) not in keyed:  # its key row lost the transaction
            rows.append(
                ChainActivity(
                    owner=owner,
                    kind="registered",
                    tx_hash=owner.register_tx,
                    block_number=owner.registered_block,
                    at=owner.created_at,
                )
            )
    batches = (
        Record.objects.exclude(tx_hash="")
        .values("owner_id", "tx_hash")
        .annotate(count=Count("id"), block=Max("block_number"), at=Max("anchored_at"))
        .order_by()
    )
    for batch in batches.iterator():
        rows.append(
            ChainActivity(
                owner_id=batch["owner_id"],
                kind="anchored",
                tx_hash=batch["tx_hash"],
                block_number=batch["block"],
                record_count=batch["count"],
                at=batch["at"] or timezone.now(),
            )
        )
    for grant in Grant.objects.exclude(grant_tx="").iterator():
        rows.append(
            ChainActivity(
                owner_id=grant.owner_id,
                counterpart_id=grant.grantee_id,
                kind="granted",
                tx_hash=grant.grant_tx,
                block_number=grant.grant_block,
                at=grant.created_at,
            )
        )
    for grant in Grant.objects.exclude(revoke_tx="").iterator():
        rows.append(
            ChainActivity(
                owner_id=grant.owner_id,
                counterpart_id=grant.grantee_id,
                kind="revoked",
                tx_hash=grant.revoke_tx,
                block_number=grant.revoke_block,
                at=grant.updated_at,
            )
        )
    # Rows the worker already wrote (one per owner, kind and transaction) stay as they are.
    ChainActivity.objects.bulk_create(rows, ignore_conflicts=True, batch_size=500)


class Migration(migrations.Migration):
    dependencies = [
        ("accounts", "0003_trust_model"),
        ("sharing", "0003_grant_credential"),
    ]

    operations = [
        migrations.RunPython(chain_activity_backfill, migrations.RunPython.noop, elidable=True),
    ]

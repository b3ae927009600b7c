# One access log (issue 43): a verdict's viewer, record owner, operator, credential and token
# are its Access's. Verdicts without an Access get one of their own (one record), then the
# copied columns go.

import django.db.models.deletion
from django.conf import settings
from django.db import migrations, models
from django.db.models import OuterRef, Subquery

CHUNK = 1000


def backfill(apps, schema_editor):
    """Each verdict without an access becomes an access of its own, of one record, with the
    verdict's viewer, operator, credential, token and time, CHUNK verdicts at a time."""
    Access = apps.get_model("sharing", "Access")
    Verdict = apps.get_model("sharing", "Verdict")
    orphans = Verdict.objects.filter(access__isnull=True).select_related("record")
    while True:
        chunk = list(orphans.order_by("pk")[:CHUNK])
        if not chunk:
            return
        made = Access.objects.bulk_create(
            Access(
                kind="check" if verdict.checked_by_id else "view",
                viewer_id=verdict.viewer_id,
                record_owner_id=verdict.record.owner_id,
                checked_by_id=verdict.checked_by_id,
                credential=verdict.credential,
                token_id=verdict.token_id,
                count=1,
                record_id=verdict.record_id,
                robot_id=verdict.record.robot_id,
                topic=verdict.record.topic,
            )
            for verdict in chunk
        )
        for access, verdict in zip(made, chunk, strict=True):
            access.created_at = verdict.created_at
            verdict.access_id = access.pk
        Access.objects.bulk_update(made, ["created_at"])
        Verdict.objects.bulk_update(chunk, ["access_id"])


def restore(apps, schema_editor):
    """Back: each verdict's copies of its access's columns."""
    Access = apps.get_model("sharing", "Access")
    Verdict = apps.get_model("sharing", "Verdict")
    of_access = Access.objects.filter(pk=OuterRef("access_id"))
    Verdict.objects.update(
        **{
            column: Subquery(of_access.values(column)[:1])
            for column in (
                "viewer_id",
                "record_owner_id",
                "checked_by_id",
                "credential",
                "token_id",
            )
        }
    )


class Migration(migrations.Migration):
    dependencies = [
        ("sharing", "0016_export_credential"),
        migrations.swappable_dependency(settings.AUTH_USER_MODEL),
    ]

    operations = [
        # Nullable first, so that the way back can add it again before refilling it.
        migrations.AlterField(
            model_name="verdict",
            name="viewer",
            field=models.ForeignKey(
                null=True,
                on_delete=django.db.models.deletion.CASCADE,
                related_name="verdicts",
                to="accounts.owner",
            ),
        ),
        migrations.RunPython(backfill, restore, elidable=False),
        migrations.RemoveIndex(model_name="verdict", name="verdict_owner_time"),
        migrations.RemoveIndex(model_name="verdict", name="verdict_viewer_time"),
        migrations.RemoveField(model_name="verdict", name="checked_by"),
        migrations.RemoveField(model_name="verdict", name="credential"),
        migrations.RemoveField(model_name="verdict", name="record_owner"),
        migrations.RemoveField(model_name="verdict", name="token"),
        migrations.RemoveField(model_name="verdict", name="viewer"),
        migrations.AlterField(
            model_name="verdict",
            name="access",
            field=models.ForeignKey(
                on_delete=django.db.models.deletion.CASCADE,
                related_name="verdicts",
                to="sharing.access",
            ),
        ),
    ]

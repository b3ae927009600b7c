"""Owners' name skeletons (accounts.usernames): each existing owner's filled in, oldest first;
an owner whose skeleton an older owner already has is marked a look-alike and keeps its name."""

from django.db import migrations, models


def skeletons_fill(apps, schema_editor):
    from accounts.usernames import username_skeleton

    Owner = apps.get_model("accounts", "Owner")
    seen: set[str] = set()
    for owner in Owner.objects.select_related("user").order_by("pk"):
        skeleton = username_skeleton(owner.user.username)
        owner.name_skeleton = skeleton
        owner.name_lookalike = skeleton in seen
        seen.add(skeleton)
        owner.save(update_fields=["name_skeleton", "name_lookalike"])


class Migration(migrations.Migration):
    dependencies = [("accounts", "0008_robot_signing_keys")]

    operations = [
        migrations.AddField(
            model_name="owner",
            name="name_skeleton",
            field=models.CharField(db_index=True, default="", max_length=750),
            preserve_default=False,
        ),
        migrations.AddField(
            model_name="owner",
            name="name_lookalike",
            field=models.BooleanField(default=False),
        ),
        migrations.RunPython(skeletons_fill, migrations.RunPython.noop),
        migrations.AddConstraint(
            model_name="owner",
            constraint=models.UniqueConstraint(
                condition=models.Q(("name_lookalike", False)),
                fields=("name_skeleton",),
                name="owner_name_skeleton_unique",
            ),
        ),
    ]

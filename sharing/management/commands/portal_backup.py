"""`manage.py portal_backup --to DIR`: the database, the envelopes and the secrets, in a new
0700 folder with a manifest of SM3 digests (sharing/services/backup.py); safe while the portal
runs."""

from pathlib import Path
from typing import Any

from django.core.management.base import BaseCommand, CommandError, CommandParser

from sharing.services.backup import BackupRefused, portal_backup


class Command(BaseCommand):
    help = "Back up the portal's database, envelopes and secrets into a new folder."

    def add_arguments(self, parser: CommandParser) -> None:
        parser.add_argument("--to", required=True, type=Path, help="a new or empty folder")

    def handle(self, *args: Any, **options: Any) -> None:
        try:
            manifest = portal_backup(to=options["to"])
        except BackupRefused as exc:
            raise CommandError(str(exc)) from exc
        counts = manifest["database"]["counts"]
        secrets = manifest["secrets"]
        envelopes = manifest["envelopes"]
        lines = [
            f"backup in {options['to']}",
            f"database: {sum(counts.values())} rows ({counts.get('sharing.record', 0)} records)",
            f"envelopes: {envelopes['count']} files, {envelopes['bytes']} bytes",
            f"secrets copied: {', '.join(sorted(secrets['files'])) or 'none'}",
        ]
        for name, setting in sorted(secrets["from_environment"].items()):
            lines.append(f"secret {name} comes from the environment ({setting}): back it up there")
        for name in secrets["missing"]:
            lines.append(f"secret {name}: no file in SECRETS_DIR and not in the environment")
        for key, said in (
            ("written_during_backup", "records written during the backup, not in it"),
            ("records_without_envelope", "records whose envelope was missing"),
            ("envelopes_without_record", "envelopes with no record in the snapshot"),
        ):
            if manifest[key]:
                lines.append(f"{len(manifest[key])} {said} (listed in the manifest)")
        self.stdout.write("\n".join(lines))

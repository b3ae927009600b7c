"""`manage.py portal_restore --from DIR [--force]`: a backup of `portal_backup` into this
portal (sharing/services/backup.py). Run `manage.py migrate` first; every digest is checked before
anything changes, and a database that holds rows is replaced only with --force."""

from pathlib import Path
from typing import Any

from django.core.management.base import BaseCommand, CommandError, CommandParser

from sharing.services.backup import BackupRefused, portal_restore


class Command(BaseCommand):
    help = "Restore a portal_backup folder: database, envelopes and secrets."

    def add_arguments(self, parser: CommandParser) -> None:
        parser.add_argument("--from", dest="source", required=True, type=Path)
        parser.add_argument(
            "--force", action="store_true", help="replace the rows a non-empty database holds"
        )

    def handle(self, *args: Any, **options: Any) -> None:
        try:
            restored = portal_restore(source=options["source"], force=options["force"])
        except BackupRefused as exc:
            raise CommandError(str(exc)) from exc
        counts = restored["counts"]
        self.stdout.write(
            f"restored {sum(counts.values())} rows ({counts.get('sharing.record', 0)} records), "
            f"{restored['envelopes']} envelope files written, "
            f"secrets: {', '.join(restored['secrets']) or 'unchanged'}"
        )

"""Backup and restore of a portal: its database, its envelopes and its secrets, in one folder.

A backup folder (0700, every file 0600) holds:

- `database.json`: Django's dumpdata of auth users and groups and the project's apps, with
  natural foreign keys (permissions, content types), so that it loads into SQLite or
  PostgreSQL alike; read in one snapshot of the database while the portal runs.
- `envelopes/`: every file of STORAGES["envelopes"], as stored.
- `secrets/`: the files of SECRETS_DIR (master.key, operator.key, sm2-private.key,
  django-secret-key); a secret given in the environment is named, never copied.
- `manifest.json`: when, versions, counts, every file's SM3 digest and the KEK fingerprint;
  never a secret.

Records written while the files were copied are not in the database snapshot: they are
listed (`written_during_backup`), and so are records whose envelope was missing.

Restore checks every digest before it changes anything, refuses a database that holds rows
unless forced, writes each file atomically (temporary file, fsync, rename), and loads the
database last, in one transaction: a restore that fails leaves no half-loaded database.
"""

import json
import logging
import os
import platform
import tempfile
import tomllib
from collections.abc import Iterator
from contextlib import contextmanager, suppress
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import django
from django.apps import apps
from django.conf import settings
from django.core.files.base import ContentFile
from django.core.files.storage import Storage
from django.core.management import call_command
from django.db import connection, transaction
from django.db.migrations.recorder import MigrationRecorder
from django.db.models import Model

from accounts.keywrap import KEK_FINGERPRINT, kek_fingerprint
from accounts.models import SecretFingerprint
from core.files import fsync_path
from core.secrets import SecretFileError, load_or_create_secret
from sharing.errors import SharingError
from sharing.models import Record
from sharing.storage import envelope_storage
from smcrypto import sm3, sm4

logger = logging.getLogger(__name__)

BACKUP_FORMAT = 1
MANIFEST = "manifest.json"
DATABASE_DUMP = "database.json"
ENVELOPES = "envelopes"
SECRETS = "secrets"
# What is dumped: users and groups (with their permissions by natural key) and the project.
DUMPED = ["auth.group", "auth.user", "accounts", "sharing", "chainworker"]
PROJECT_APPS = ["accounts", "sharing", "chainworker"]
# Secret files of SECRETS_DIR, and the setting (environment) that replaces each.
SECRET_FILES = {
    "master.key": "AUTHROS_MASTER_KEY",
    "operator.key": "CHAIN_OPERATOR_KEY",
    "sm2-private.key": "AUTHROS_SM2_PRIVATE_KEY",
    "django-secret-key": "DJANGO_SECRET_KEY",
}


class BackupRefused(SharingError):
    """A backup or restore that would lose or corrupt data is refused; nothing was changed."""

    code = "backup_refused"


# --- backup ----------------------------------------------------------------------------------


def portal_backup(*, to: Path) -> dict[str, Any]:
    """Write a backup of the portal into the new or empty folder `to`; return its manifest."""
    to = Path(to)
    if to.exists() and any(to.iterdir()):
        raise BackupRefused(f"{to} is not empty: a backup goes into a new folder")
    to.mkdir(mode=0o700, parents=True, exist_ok=True)
    os.chmod(to, 0o700)
    started = datetime.now(tz=UTC)
    dump = to / DATABASE_DUMP
    with _snapshot():
        call_command(
            "dumpdata",
            *DUMPED,
            natural_foreign=True,
            output=str(dump),
            verbosity=0,
        )
        counts = _row_counts()
        envelopes_of_records = dict(Record.objects.values_list("storage_name", "id"))
        # Deleted records whose ciphertext was removed on purpose: no envelope is expected.
        purged = set(
            Record.objects.filter(purged_at__isnull=False).values_list("storage_name", flat=True)
        )
        fingerprint = (
            SecretFingerprint.objects.filter(name=KEK_FINGERPRINT)
            .values_list("fingerprint", flat=True)
            .first()
        )
        migrations = _applied_migrations()
    os.chmod(dump, 0o600)
    files = _copy_envelopes(envelope_storage(), to / ENVELOPES)
    # After the copy: records the snapshot did not hold were written during the backup.
    written_during = Record.objects.exclude(id__in=envelopes_of_records.values())
    manifest = {
        "format": BACKUP_FORMAT,
        "started_at": started.isoformat(),
        "finished_at": datetime.now(tz=UTC).isoformat(),
        "versions": {
            "portal": _portal_version(),
            "django": django.get_version(),
            "python": platform.python_version(),
            "database_engine": connection.vendor,
            "migrations": migrations,
        },
        "database": {"file": DATABASE_DUMP, "sm3": _sm3_of_file(dump), "counts": counts},
        "envelopes": {
            "count": len(files),
            "bytes": sum(entry["size"] for entry in files.values()),
            "files": files,
        },
        "records_without_envelope": sorted(
            str(record_id)
            for name, record_id in envelopes_of_records.items()
            if name not in files and name not in purged
        ),
        "envelopes_without_record": sorted(set(files) - set(envelopes_of_records)),
        "written_during_backup": sorted(
            str(record_id) for record_id in written_during.values_list("id", flat=True)
        ),
        "secrets": _copy_secrets(to / SECRETS),
        "kek_fingerprint": fingerprint,
    }
    _write_private(to / MANIFEST, json.dumps(manifest, indent=2, sort_keys=True).encode())
    logger.info(
        "backup in %s: %d rows, %d envelopes, %d records written during the backup",
        to,
        sum(counts.values()),
        len(files),
        len(manifest["written_during_backup"]),
    )
    return manifest


@contextmanager
def _snapshot() -> Iterator[None]:
    """Read everything in one snapshot of the database, without holding up its writers."""
    if connection.in_atomic_block:
        yield  # already in a transaction (a test's): its reads are one snapshot
    elif connection.vendor == "sqlite":
        # A deferred read transaction: in WAL mode writers go on while it reads one snapshot
        # (the portal's own transactions take the write lock up front, IMMEDIATE).
        connection.ensure_connection()
        with connection.cursor() as cursor:
            cursor.execute("BEGIN DEFERRED")
        try:
            yield
        finally:
            with connection.cursor() as cursor:
                cursor.execute("COMMIT")
    else:
        with transaction.atomic():
            if connection.vendor == "postgresql":
                with connection.cursor() as cursor:
                    cursor.execute("SET TRANSACTION ISOLATION LEVEL REPEATABLE READ READ ONLY")
            yield


def _dumped_models() -> list[type[Model]]:
    found: list[type[Model]] = [apps.get_model("auth", "Group"), apps.get_model("auth", "User")]
    for label in PROJECT_APPS:
        found.extend(apps.get_app_config(label).get_models())
    return found


def _row_counts() -> dict[str, int]:
    return {model._meta.label_lower: model._base_manager.count() for model in _dumped_models()}


def _applied_migrations() -> dict[str, list[str]]:
    applied: dict[str, list[str]] = {}
    for app, name in MigrationRecorder(connection).applied_migrations():
        if app in PROJECT_APPS or app in ("auth", "contenttypes"):
            applied.setdefault(app, []).append(name)
    return {app: sorted(names) for app, names in sorted(applied.items())}


def _portal_version() -> str:
    with open(Path(settings.BASE_DIR) / "pyproject.toml", "rb") as handle:
        return str(tomllib.load(handle).get("project", {}).get("version", "unknown"))


def _storage_names(storage: Storage, folder: str = "") -> Iterator[str]:
    directories, files = storage.listdir(folder)
    for name in files:
        yield f"{folder}/{name}" if folder else name
    for directory in directories:
        yield from _storage_names(storage, f"{folder}/{directory}" if folder else directory)


def _copy_envelopes(storage: Storage, into: Path) -> dict[str, dict[str, Any]]:
    into.mkdir(mode=0o700)
    files: dict[str, dict[str, Any]] = {}
    try:
        names = sorted(_storage_names(storage))
    except FileNotFoundError:
        names = []  # nothing stored yet
    for name in names:
        try:
            with storage.open(name, "rb") as handle:
                data = handle.read()
        except FileNotFoundError:
            continue  # deleted since it was listed (an upload that failed)
        target = into / name
        target.parent.mkdir(mode=0o700, parents=True, exist_ok=True)
        _write_private(target, data)
        files[name] = {"sm3": sm3.sm3_hex(data), "size": len(data)}
    return files


def _copy_secrets(into: Path) -> dict[str, Any]:
    into.mkdir(mode=0o700)
    copied: dict[str, str] = {}
    from_environment: dict[str, str] = {}
    missing: list[str] = []
    for name, setting in SECRET_FILES.items():
        path = Path(settings.SECRETS_DIR) / name
        if _secret_from_environment(setting):
            from_environment[name] = setting
        elif path.is_file():
            data = path.read_bytes()
            _write_private(into / name, data)
            copied[name] = sm3.sm3_hex(data)
        else:
            missing.append(name)
    return {"files": copied, "from_environment": from_environment, "missing": missing}


def _secret_from_environment(setting: str) -> bool:
    if setting == "DJANGO_SECRET_KEY":
        return bool(os.environ.get(setting))  # settings.SECRET_KEY is set either way
    return bool(getattr(settings, setting, ""))


# --- restore ---------------------------------------------------------------------------------


def portal_restore(*, source: Path, force: bool = False) -> dict[str, Any]:
    """Restore the backup in `source` into this portal's database, storage and SECRETS_DIR.

    Refused (BackupRefused, nothing changed) when a file is missing or its digest is not the
    manifest's, when the database lacks the backup's migrations, when the restored master key
    is not the one the backup's owner keys were wrapped under, and when the database holds
    rows unless `force` (which replaces them).
    """
    source = Path(source)
    manifest = _manifest_checked(source)
    _migrations_check(manifest)
    held = {label: count for label, count in _row_counts().items() if count}
    if held and not force:
        shown = ", ".join(f"{label} {count}" for label, count in sorted(held.items()))
        raise BackupRefused(f"the database is not empty ({shown}); restore with --force")
    _kek_check(source, manifest)
    secrets = _restore_secrets(source / SECRETS, manifest)
    envelopes = _restore_envelopes(source / ENVELOPES, manifest, envelope_storage())
    with transaction.atomic():
        if held:
            _delete_rows()
        call_command("loaddata", str(source / DATABASE_DUMP), verbosity=0)
    counts = _row_counts()
    logger.info(
        "restored %s: %d rows, %d envelopes, secrets %s",
        source,
        sum(counts.values()),
        envelopes,
        ", ".join(secrets) or "none",
    )
    return {"counts": counts, "envelopes": envelopes, "secrets": secrets, "replaced_rows": held}


def _manifest_checked(source: Path) -> dict[str, Any]:
    try:
        manifest = json.loads((source / MANIFEST).read_text())
    except (OSError, ValueError) as exc:
        raise BackupRefused(f"no readable {MANIFEST} in {source}: {exc}") from None
    if manifest.get("format") != BACKUP_FORMAT:
        raise BackupRefused(f"backup format {manifest.get('format')!r}, expected {BACKUP_FORMAT}")
    expected = {DATABASE_DUMP: manifest["database"]["sm3"]}
    for name, entry in manifest["envelopes"]["files"].items():
        expected[f"{ENVELOPES}/{name}"] = entry["sm3"]
    for name, digest in manifest["secrets"]["files"].items():
        expected[f"{SECRETS}/{name}"] = digest
    wrong = []
    for relative, digest in sorted(expected.items()):
        path = source / relative
        if not _inside(source, path) or not path.is_file():
            wrong.append(f"{relative} (missing)")
        elif _sm3_of_file(path) != digest:
            wrong.append(f"{relative} (SM3 digest differs from the manifest's)")
    if wrong:
        shown = "; ".join(wrong[:10]) + (f"; and {len(wrong) - 10} more" if len(wrong) > 10 else "")
        raise BackupRefused(f"the backup in {source} is damaged: {shown}")
    return manifest


def _inside(root: Path, path: Path) -> bool:
    return path.resolve().is_relative_to(root.resolve())


def _migrations_check(manifest: dict[str, Any]) -> None:
    applied = _applied_migrations()
    lacking = [
        f"{app}.{name}"
        for app, names in manifest["versions"]["migrations"].items()
        for name in names
        if name not in applied.get(app, [])
    ]
    if lacking:
        raise BackupRefused(
            f"the database lacks migrations the backup was taken at ({', '.join(lacking[:5])}): "
            "run `manage.py migrate` first"
        )


def _kek_check(source: Path, manifest: dict[str, Any]) -> None:
    """The master key the portal will have after the restore must open the backup's rows."""
    expected = manifest.get("kek_fingerprint")
    if not expected:
        return  # nothing was wrapped yet when the backup was taken
    if settings.AUTHROS_MASTER_KEY:
        try:
            kek = bytes.fromhex(settings.AUTHROS_MASTER_KEY)
        except ValueError:
            raise BackupRefused("AUTHROS_MASTER_KEY is not hex") from None
    else:
        path = source / SECRETS / "master.key"
        if not path.is_file():
            raise BackupRefused(
                "the backup holds no master.key (it came from AUTHROS_MASTER_KEY): set "
                "AUTHROS_MASTER_KEY to that key before restoring"
            )
        try:
            kek = load_or_create_secret(path, nbytes=sm4.KEY_SIZE)
        except SecretFileError as exc:
            raise BackupRefused(str(exc)) from None
    if kek_fingerprint(kek) != expected:
        raise BackupRefused(
            "the master key is not the one the backup's owner keys were wrapped with "
            f"(fingerprint {kek_fingerprint(kek)[:8]}, expected {expected[:8]})"
        )


def _restore_secrets(folder: Path, manifest: dict[str, Any]) -> list[str]:
    """Put the backup's secret files in SECRETS_DIR; a different file there is kept aside."""
    secrets_dir = Path(settings.SECRETS_DIR)
    secrets_dir.mkdir(mode=0o700, parents=True, exist_ok=True)
    stamp = datetime.now(tz=UTC).strftime("%Y%m%dT%H%M%SZ")
    restored = []
    for name in sorted(manifest["secrets"]["files"]):
        data = (folder / name).read_bytes()
        target = secrets_dir / name
        if target.is_file():
            if target.read_bytes() == data:
                continue
            # Not deleted: a key that opens something the backup does not hold stays at hand.
            os.replace(target, secrets_dir / f"{name}.before-restore-{stamp}")
        _write_private(target, data)
        restored.append(name)
    return restored


def _restore_envelopes(folder: Path, manifest: dict[str, Any], storage: Storage) -> int:
    written = 0
    for name, entry in sorted(manifest["envelopes"]["files"].items()):
        data = (folder / name).read_bytes()
        if storage.exists(name):
            with storage.open(name, "rb") as handle:
                if sm3.sm3_hex(handle.read()) == entry["sm3"]:
                    continue
        _store_atomically(storage, name, data)
        written += 1
    return written


def _store_atomically(storage: Storage, name: str, data: bytes) -> None:
    try:
        path = Path(storage.path(name))
    except NotImplementedError:
        # A remote storage: its own save is as atomic as it gets.
        if storage.exists(name):
            storage.delete(name)
        saved = storage.save(name, ContentFile(data))
        if saved != name:
            raise BackupRefused(f"the storage saved {name} as {saved}") from None
        return
    path.parent.mkdir(parents=True, exist_ok=True)
    _write_atomically(path, data, mode=0o644)


def _delete_rows() -> None:
    # Dependants first: records and grants before owners and robots, owners before users.
    for label in reversed(PROJECT_APPS):
        for model in reversed(list(apps.get_app_config(label).get_models())):
            model._base_manager.all().delete()
    apps.get_model("auth", "User")._base_manager.all().delete()
    apps.get_model("auth", "Group")._base_manager.all().delete()


# --- files -----------------------------------------------------------------------------------


def _sm3_of_file(path: Path) -> str:
    return sm3.sm3_hex(Path(path).read_bytes())


def _write_private(path: Path, data: bytes) -> None:
    _write_atomically(path, data, mode=0o600)


def _write_atomically(path: Path, data: bytes, *, mode: int) -> None:
    """Whole or not at all: a temporary file in the same folder, fsynced, renamed into place."""
    fd, temporary = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as handle:
            handle.write(data)
            handle.flush()
            os.fsync(handle.fileno())
        os.chmod(temporary, mode)
        os.replace(temporary, path)
    finally:
        with suppress(FileNotFoundError):
            os.unlink(temporary)
    fsync_path(path.parent)

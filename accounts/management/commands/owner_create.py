"""`manage.py owner_create --username U [--sm4-key-sm2 C | --sm4-key-file F]`: a new owner,
registered on chain.

The password is read from standard input (prompted twice on a terminal), never from the
command line. The key is, in order of preference:
- generated (no key option): printed once, as `sm4_key_hex` in the JSON output. Robots paired
  with `python -m ros_agent pair` receive it by SM2 and need no copy of it;
- `--sm4-key-sm2 C`: the key SM2-encrypted to the portal's public key (`GET
  /api/v1/sm2-public-key/`, C1C3C2 hex), as the registration page sends it (DESIGN.md);
- `--sm4-key-file F`: 32 hex digits in a file only its owner may read (mode 0600);
- `--sm4-key-hex K`: kept for scripts written against the fixed interface, but the key is then
  on the command line (`ps`, shell history): a warning says so.
A given key that does not look random (a word, a pattern, a sequence) is refused. The command
returns once the owner's EOA is funded, enrolled and registered on chain, and prints JSON with
the EOA (`eoa`, also as `address`); it exits non-zero if that cannot be done.
"""

import getpass
import json
import stat
import sys
import time
from pathlib import Path
from typing import IO, Any

from django.core.management.base import BaseCommand, CommandError, CommandParser

from accounts.errors import AccountError, WeakPassword
from accounts.keyexchange import sm4_key_from_submission
from accounts.models import Owner
from accounts.selectors import owner_key_current
from accounts.services.keys import sm4_key_generate
from accounts.services.owners import owner_create
from accounts.services.registration import owner_register_on_chain
from chainworker.errors import ChainError
from chainworker.services import chain_client
from chainworker.work import TRANSIENT


class Command(BaseCommand):
    stealth_options = ("stdin",)  # for call_command in tests
    help = (
        "Create an owner with a custodial EOA and register it on chain. The password is read "
        "from standard input."
    )

    def add_arguments(self, parser: CommandParser) -> None:
        parser.add_argument("--username", required=True)
        key = parser.add_mutually_exclusive_group()
        key.add_argument(
            "--sm4-key-hex",
            help="the owner's SM4 key, 32 hex digits (default: a new random key, printed once)",
        )
        key.add_argument(
            "--sm4-key-file",
            type=Path,
            help="a file holding the SM4 key as 32 hex digits, mode 0600 (keeps it out of `ps`)",
        )
        key.add_argument(
            "--sm4-key-sm2",
            metavar="HEX",
            help="the SM4 key SM2-encrypted to the portal's public key (C1C3C2 hex), as the "
            "registration page sends it",
        )
        parser.add_argument(
            "--timeout",
            type=float,
            default=180.0,
            help="seconds to wait for the registration on chain (default 180)",
        )

    def handle(self, *args: Any, **options: Any) -> None:
        given = any(
            options[name] is not None for name in ("sm4_key_hex", "sm4_key_file", "sm4_key_sm2")
        )
        if options["sm4_key_sm2"] is not None:
            try:
                sm4_key = sm4_key_from_submission(options["sm4_key_sm2"])
            except AccountError as exc:
                raise CommandError(str(exc)) from exc
        elif given:
            if options["sm4_key_hex"] is not None:
                self.stderr.write(
                    "warning: --sm4-key-hex puts the key on the command line, where `ps` and "
                    "the shell history show it; prefer --sm4-key-sm2 or --sm4-key-file"
                )
            sm4_key = _sm4_key(options["sm4_key_hex"], options["sm4_key_file"])
        else:
            sm4_key = sm4_key_generate()
        password = _password(options.get("stdin") or sys.stdin)
        try:
            chain_client().address  # noqa: B018 (fails early if the chain or contract is missing)
        except ChainError as exc:
            raise CommandError(f"the chain is not ready, nothing was created: {exc}") from exc
        try:
            owner = owner_create(username=options["username"], password=password, sm4_key=sm4_key)
        except WeakPassword as exc:
            raise CommandError("the password is too weak: " + " ".join(exc.messages)) from exc
        except AccountError as exc:
            raise CommandError(str(exc)) from exc
        try:
            owner = _registered(owner, timeout=options["timeout"])
        except CommandError as exc:
            if given:
                raise
            # The owner exists: without this one showing, nobody would know its key.
            raise CommandError(f"{exc}; its generated SM4 key is {sm4_key.hex()}") from exc
        result = {
            "username": owner.username,
            "eoa": owner.eoa_address,
            "address": owner.eoa_address,
            "key_id": owner_key_current(owner).key_id,
            "chain_state": owner.chain_state,
            "register_tx": owner.register_tx or None,
            "registered_block": owner.registered_block,
        }
        if not given:
            # Shown this once: the portal keeps it only wrapped under its master key.
            result["sm4_key_hex"] = sm4_key.hex()
        self.stdout.write(json.dumps(result, sort_keys=True))


def _sm4_key(key_hex: str | None, key_file: Path | None) -> bytes:
    if key_file is not None:
        try:
            mode = key_file.stat().st_mode
            if mode & 0o077:
                raise CommandError(
                    f"the key file {key_file} has mode {stat.S_IMODE(mode):04o}, so other users "
                    f"may read it; run: chmod 600 {key_file}"
                )
            key_hex = key_file.read_text(encoding="ascii")
        except (OSError, UnicodeDecodeError) as exc:
            raise CommandError(f"cannot read the key file {key_file}: {exc}") from exc
    text = (key_hex or "").strip().lower().removeprefix("0x")
    try:
        key = bytes.fromhex(text)
    except ValueError:
        key = b""
    if len(key) != 16:
        raise CommandError("the SM4 key must be 32 hex digits (16 bytes)")
    return key


def _password(stdin: IO[str]) -> str:
    if stdin.isatty():
        password = getpass.getpass("Password: ")
        if getpass.getpass("Password (again): ") != password:
            raise CommandError("the passwords differ")
    else:
        password = stdin.readline().rstrip("\r\n")
    if not password:
        raise CommandError("give the password on standard input, e.g. `... < password-file`")
    return password


def _registered(owner: Owner, *, timeout: float) -> Owner:
    """Register now, in this process, so that no worker needs to be running."""
    deadline = time.monotonic() + timeout
    delay = 1.0
    while True:
        try:
            return owner_register_on_chain(owner_id=owner.pk)
        except TRANSIENT as exc:
            problem = f"{type(exc).__name__}: {exc}"
        except ChainError as exc:
            raise CommandError(_not_registered(owner, f"{type(exc).__name__}: {exc}")) from exc
        if time.monotonic() + delay > deadline:
            raise CommandError(_not_registered(owner, problem))
        time.sleep(delay)
        delay = min(delay * 2, 15.0)


def _not_registered(owner: Owner, problem: str) -> str:
    return (
        f"owner {owner.username} ({owner.eoa_address}) was created but is not registered on "
        f"chain yet ({problem}); the chain worker finishes it when the chain answers: check "
        "with `manage.py chain_status` and the admin"
    )

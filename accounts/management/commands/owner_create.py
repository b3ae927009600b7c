"""`manage.py owner_create --username U [--sm4-key-hex K]`: a new owner, registered on chain.

The password is read from standard input (prompted twice on a terminal), never from the
command line. Without --sm4-key-hex or --sm4-key-file a random key is generated and printed
once, as `sm4_key_hex` in the JSON output: keep it, the robots' key files need it. A given key
that does not look random (a word, a pattern, a sequence) is refused. The command returns once
the owner's EOA is funded, enrolled and registered on chain, and prints JSON with the EOA
(`eoa`, also as `address`); it exits non-zero if that cannot be done.
"""

import getpass
import json
import sys
import time
from pathlib import Path
from typing import IO, Any

from django.core.management.base import BaseCommand, CommandError, CommandParser

from accounts.errors import AccountError, WeakPassword
from accounts.models import Owner
from accounts.selectors import owner_key_current
from accounts.services import owner_create, owner_register_on_chain, sm4_key_generate
from chainworker.chain import ChainError
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
            help="a file holding the SM4 key as 32 hex digits (keeps it out of `ps`)",
        )
        parser.add_argument(
            "--timeout",
            type=float,
            default=180.0,
            help="seconds to wait for the registration on chain (default 180)",
        )

    def handle(self, *args: Any, **options: Any) -> None:
        given = options["sm4_key_hex"] is not None or options["sm4_key_file"] is not None
        if given:
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

"""Pairing: the robot gets its token and its owner's SM4 key by SM2, not by hand.

    python -m ros_agent pair --portal https://portal.example.org --name arm-3 [--dir DIR]

1. The robot makes an SM2 key pair; the private key goes to `robot.sm2` (mode 0600) and never
   leaves the robot, which signs every batch it uploads with it (ros_agent.batches).
2. It asks the portal (`POST /api/v1/robot-pairings/`) with its name and public key, and gets
   a request id, a secret only it knows (kept in `pairing.json`, 0600, so that a pair command
   that was interrupted carries on), a short code and the key's fingerprint. It prints the
   code and the fingerprint.
3. The owner types the code on the portal's robots page, checks the name and fingerprint
   there against what the robot printed, and approves (or refuses).
4. The robot polls with its secret (`POST /api/v1/robot-pairings/{id}/collect/`). Once
   approved it gets, once, its upload token and the owner's current key, both encrypted to its
   SM2 public key (C1C3C2), decrypts them and writes `robot.token`, `owner-keys.json` (0600)
   and `agent.yaml`; then `python -m ros_agent --config DIR/agent.yaml` runs the agent.

The code is for people to match, not a credential: without the secret and the private key
nobody gets the answer. After a key rotation the agent fetches the new key the same way
(`KeyUpdater`, `GET /api/v1/robot-key/` with the robot's token).
"""

import argparse
import json
import logging
import sys
import time
from collections.abc import Callable
from datetime import UTC, datetime
from pathlib import Path
from typing import Any, TextIO

import requests
import yaml

from ros_agent import LOGGER_NAME
from ros_agent.config import ConfigError, check_portal_url, read_sm2_key_file
from ros_agent.keyring import Keyring, key_id_hex, write_keys_file, write_private_file
from ros_agent.uploader import PortalClient
from smcrypto import CryptoError, sm2, sm4

logger = logging.getLogger(f"{LOGGER_NAME}.pairing")

SM2_KEY_FILE = "robot.sm2"
TOKEN_FILE = "robot.token"  # noqa: S105 (a file name)
KEYS_FILE = "owner-keys.json"
PAIRING_FILE = "pairing.json"
CONFIG_FILE = "agent.yaml"
DEFAULT_TIMEOUT = 900.0
REQUEST_TIMEOUT = 15.0


class PairingFailed(RuntimeError):
    """The pairing did not happen (refused, expired, the portal said no); the message says why."""


def decrypt_key(private_key: str, key_id: str, key_sm2: str) -> bytes:
    """The owner's SM4 key sent SM2-encrypted to this robot, checked against its key id."""
    try:
        key = sm2.decrypt(private_key, key_sm2)
    except CryptoError as exc:
        raise PairingFailed(f"the key sent by the portal does not decrypt: {exc}") from None
    if len(key) != sm4.KEY_SIZE or key_id_hex(key) != key_id:
        raise PairingFailed("the key sent by the portal is not the key it names")
    return key


class KeyUpdater:
    """Fetches the owner's current key for a paired robot into its keyring (the uploader calls
    it when the portal names another key, or refuses an envelope's key)."""

    def __init__(self, *, client: PortalClient, keyring: Keyring, sm2_private_key: str) -> None:
        self._client = client
        self._keyring = keyring
        self._private_key = sm2_private_key

    def __call__(self) -> bool | None:
        """True when the key was fetched (new or not), False when the portal refused, None
        when it did not answer."""
        answer = self._client.fetch_key()
        if answer.status is None or answer.status >= 500 or answer.status in (408, 429):
            logger.warning("cannot fetch the owner's key now: %s", answer.describe())
            return None
        body = answer.body if isinstance(answer.body, dict) else {}
        if answer.status != 200:
            logger.error("the portal refuses to send the owner's key: %s", answer.describe())
            return False
        try:
            key = decrypt_key(self._private_key, str(body["key_id"]), str(body["key_sm2"]))
        except (KeyError, PairingFailed) as exc:
            logger.error("the portal's answer holds no usable key: %s", exc)
            return False
        if self._keyring.add(key):
            logger.warning(
                "the owner rotated its key: sealing under %s from now on", key_id_hex(key)
            )
        return True


def pair(
    *,
    portal_url: str,
    name: str,
    folder: Path,
    timeout: float = DEFAULT_TIMEOUT,
    tls_verify: bool | str = True,
    out: TextIO = sys.stdout,
    machine: bool = False,
    sleep: Callable[[float], None] = time.sleep,
) -> Path:
    """Pair this robot (see the module's description); returns the agent.yaml written.

    `machine`: print one JSON object per line (`requested`, then `paired`) instead of text.
    """
    folder.mkdir(mode=0o700, parents=True, exist_ok=True)
    session = requests.Session()
    session.verify = tls_verify
    api = portal_url.rstrip("/") + "/api/v1/robot-pairings/"
    private_key, public_key = _robot_key_pair(folder / SM2_KEY_FILE)
    request = _pending_request(folder / PAIRING_FILE, portal_url, public_key)
    if request is None:
        answer = _post(session, api, {"name": name, "public_key": public_key})
        if answer.status_code != 201:
            raise PairingFailed(f"the portal refused the pairing request: {_describe(answer)}")
        request = {**answer.json(), "portal_url": portal_url, "public_key": public_key}
        write_private_file(folder / PAIRING_FILE, json.dumps(request, indent=1) + "\n")
    _say(out, machine, "requested", request)
    deadline = time.monotonic() + timeout
    collect = f"{api}{request['id']}/collect/"
    while True:
        answer = _post(session, collect, {"secret": request["secret"]})
        if answer.status_code == 200:
            break
        if answer.status_code == 202:
            interval = float(answer.json().get("poll_interval", 3))
        elif answer.status_code == 429 or answer.status_code >= 500:
            interval = float(answer.headers.get("Retry-After") or 5)
        else:
            if answer.status_code in (403, 404, 409):
                (folder / PAIRING_FILE).unlink(missing_ok=True)  # a new pair starts afresh
            raise PairingFailed(f"pairing {request['code']} failed: {_describe(answer)}")
        if time.monotonic() + interval > deadline:
            raise PairingFailed(
                f"no answer to pairing {request['code']} within {timeout:.0f} s; run the "
                "same command again to keep waiting while the request lasts"
            )
        sleep(interval)
    return _write_config(folder, portal_url, private_key, answer.json(), tls_verify, out, machine)


def _robot_key_pair(path: Path) -> tuple[str, str]:
    """The robot's SM2 key pair: the one in `path`, or a new one written there (0600)."""
    if path.exists():
        try:
            private_key = read_sm2_key_file(path)
        except ConfigError as exc:
            raise PairingFailed(str(exc)) from None
        return private_key, sm2.public_key_from_private(private_key)
    private_key, public_key = sm2.generate_keypair()
    write_private_file(path, private_key + "\n")
    return private_key, public_key


def _pending_request(path: Path, portal_url: str, public_key: str) -> dict[str, Any] | None:
    """An earlier request of this robot to this portal that has not expired, if any."""
    try:
        request = json.loads(path.read_text())
        expires_at = datetime.fromisoformat(request["expires_at"].replace("Z", "+00:00"))
    except (OSError, ValueError, KeyError, TypeError, AttributeError):
        return None
    same = request.get("portal_url") == portal_url and request.get("public_key") == public_key
    return request if same and expires_at > datetime.now(UTC) else None


def _write_config(
    folder: Path,
    portal_url: str,
    private_key: str,
    answer: dict[str, Any],
    tls_verify: bool | str,
    out: TextIO,
    machine: bool,
) -> Path:
    try:
        token = sm2.decrypt(private_key, answer["token_sm2"]).decode("ascii")
    except (CryptoError, KeyError, UnicodeDecodeError) as exc:
        raise PairingFailed(f"the token sent by the portal does not decrypt: {exc}") from None
    key = decrypt_key(private_key, str(answer["key_id"]), str(answer["key_sm2"]))
    write_private_file(folder / TOKEN_FILE, token + "\n")
    keys_path = folder / KEYS_FILE
    keys = Keyring.load(keys_path) if keys_path.exists() else None
    if keys is None:
        write_keys_file(keys_path, {key_id_hex(key): key}, key_id_hex(key))
    else:
        keys.add(key)
    settings = {
        "portal_url": portal_url.rstrip("/"),
        "token_file": TOKEN_FILE,
        "robot": str(answer["robot"]),
        "owner": str(answer["owner"]),
        "sm2_key_file": SM2_KEY_FILE,
        "keys_file": KEYS_FILE,
        "topics": answer.get("topics") or [],
        "spool_dir": "spool",
    }
    if tls_verify is not True:
        settings["tls_verify"] = tls_verify
    header = (
        f"# AuthROS agent settings for robot {answer.get('name')!r} of {answer['owner']}, paired "
        f"{datetime.now(UTC):%Y-%m-%d %H:%M} UTC.\n"
        "# Run it with: authros-agent --config agent.yaml. The token, the SM2 key and\n"
        "# the owner's keys are in the 0600 files named below; a rotated key is fetched by\n"
        "# the agent itself.\n"
    )
    config = folder / CONFIG_FILE
    write_private_file(config, header + yaml.safe_dump(settings, sort_keys=False))
    (folder / PAIRING_FILE).unlink(missing_ok=True)
    _say(
        out,
        machine,
        "paired",
        {"robot": settings["robot"], "owner": settings["owner"], "config": str(config)},
    )
    return config


def _post(session: requests.Session, url: str, body: dict[str, Any]) -> requests.Response:
    try:
        return session.post(url, json=body, timeout=REQUEST_TIMEOUT, allow_redirects=False)
    except requests.RequestException as exc:
        raise PairingFailed(f"the portal at {url} does not answer: {exc}") from None


def _describe(answer: requests.Response) -> str:
    try:
        body = answer.json()
        return f"HTTP {answer.status_code} {body.get('error')}: {body.get('detail')}"
    except (ValueError, AttributeError):
        return f"HTTP {answer.status_code}: {answer.text[:200]}"


def _say(out: TextIO, machine: bool, event: str, data: dict[str, Any]) -> None:
    if machine:
        shown = {k: v for k, v in data.items() if k not in ("secret", "public_key")}
        out.write(json.dumps({"event": event, **shown}, sort_keys=True) + "\n")
    elif event == "requested":
        out.write(
            f"Pairing code: {data['code']}\n"
            f"Key fingerprint: {data['fingerprint']}\n"
            f"Type the code on the portal's robots page ({data['portal_url'].rstrip('/')}"
            f"/robots/) and approve the robot if the fingerprint there is this one.\n"
            f"Waiting for the answer until {data['expires_at']} ...\n"
        )
    else:
        out.write(
            f"Paired: robot {data['robot']} of {data['owner']}.\n"
            f"Run the agent with: authros-agent --config {data['config']} (--ros2 on ROS 2)\n"
        )
    out.flush()


def main(argv: list[str]) -> int:
    """`python -m ros_agent pair ...`"""
    parser = argparse.ArgumentParser(
        prog="python -m ros_agent pair",
        description="Pair this robot with its owner on the portal: SM2, no key copied by hand.",
    )
    parser.add_argument("--portal", required=True, help="the portal's URL, http(s)://host[:port]")
    parser.add_argument("--name", required=True, help="the robot's name, as the owner sees it")
    parser.add_argument(
        "--dir", type=Path, default=Path("."), help="where the 0600 files and agent.yaml go [.]"
    )
    parser.add_argument(
        "--timeout", type=float, default=DEFAULT_TIMEOUT, help="seconds to wait for the owner"
    )
    parser.add_argument(
        "--insecure", action="store_true", help="do not check the portal's TLS certificate"
    )
    parser.add_argument("--json", action="store_true", help="print JSON lines, for programs")
    args = parser.parse_args(argv)
    try:
        portal_url = check_portal_url(args.portal, "--portal")
        config = pair(
            portal_url=portal_url,
            name=args.name,
            folder=args.dir.resolve(),
            timeout=args.timeout,
            tls_verify=not args.insecure,
            machine=args.json,
        )
    except (ConfigError, PairingFailed) as exc:
        print(f"pairing failed: {exc}", file=sys.stderr)
        return 1
    return 0 if config.exists() else 1

"""Clients of the REST API: a robot with its token, an owner with an owner API token or a
browser session, nobody."""

import base64
from collections.abc import Callable

import pytest
from rest_framework.test import APIClient

from accounts.models import Owner, Robot
from sharing.models import Record
from sharing.storage import envelope_storage
from tests.support.robot_setup import RobotSetup

RECORDS = "/api/v1/records/"
GRANTS = "/api/v1/grants/"


def b64(data: bytes) -> str:
    return base64.b64encode(data).decode("ascii")


def token_client(token: str) -> APIClient:
    client = APIClient()
    client.credentials(HTTP_AUTHORIZATION=f"Token {token}")
    return client


def session_client(owner: Owner, *, enforce_csrf: bool = False) -> APIClient:
    client = APIClient(enforce_csrf_checks=enforce_csrf)
    client.force_login(owner.user)
    return client


def stored_files() -> list[str]:
    storage = envelope_storage()
    if not storage.exists(""):
        return []
    folders, _ = storage.listdir("")
    return [f"{folder}/{name}" for folder in folders for name in storage.listdir(folder)[1]]


class Snapshot:
    """What an upload may change: records, stored envelopes, the robots' last seq."""

    def __init__(self) -> None:
        self.records = sorted(Record.objects.values_list("pk", flat=True))
        self.files = stored_files()
        self.last_seqs = dict(Robot.objects.values_list("pk", "last_seq"))

    def unchanged(self) -> bool:
        return Snapshot().__dict__ == self.__dict__


@pytest.fixture
def robot(make_robot) -> RobotSetup:
    return make_robot()


@pytest.fixture
def robot_api(robot) -> APIClient:
    return token_client(robot.token)


@pytest.fixture
def owner_api(make_owner_token) -> Callable[..., APIClient]:
    """A client acting for an owner with an owner API token (both scopes unless told)."""

    def client_for(owner: Owner, *, scopes: tuple[str, ...] = ("read", "share")) -> APIClient:
        _, key = make_owner_token(owner, scopes=scopes)
        return token_client(key)

    return client_for


@pytest.fixture
def upload(django_capture_on_commit_callbacks) -> Callable:
    """POST envelopes as a robot; anchoring (queued on commit) runs inline."""

    def post(client: APIClient, *envelopes: bytes, batch: bool | None = None):
        batch = len(envelopes) > 1 if batch is None else batch
        body = (
            {"envelopes": [b64(data) for data in envelopes]}
            if batch
            else {"envelope": b64(envelopes[0])}
        )
        with django_capture_on_commit_callbacks(execute=True):
            return client.post(RECORDS, body, format="json")

    return post


@pytest.fixture(autouse=True)
def fast_password_hashing(settings) -> None:
    """Owners are made by the dozen here; their password hashes are not under test."""
    settings.PASSWORD_HASHERS = ["django.contrib.auth.hashers.MD5PasswordHasher"]

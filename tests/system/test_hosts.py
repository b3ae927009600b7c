"""Several hosts, proven: two web hosts and two worker hosts, each a separate process with a
working folder of its own and its secrets given through the environment, over one
PostgreSQL, Redis, S3 server (SeaweedFS) and anvil. What one web host takes, the other shows;
a worker host killed while it anchors loses nothing; no host keeps state in its folder."""

import base64
import json
import secrets
from datetime import timedelta
from pathlib import Path

import pytest
import requests
from django.conf import settings as django_settings
from eth_account import Account

from accounts.services.api_tokens import owner_token_create
from chainworker import services as chain_services
from core.storage_url import envelope_storage_config
from sharing.models import Record
from smcrypto import envelope
from stack.seaweedfs import start_seaweedfs
from tests.support.anchoring_checks import assert_anchored_exactly_once
from tests.support.harness import WorkerStack, wait_for
from tests.support.worker_robots import registered_robots

pytestmark = [
    pytest.mark.skipif(
        "postgresql" not in django_settings.DATABASES["default"]["ENGINE"],
        reason="hosts share one PostgreSQL: this runs in the suite's PostgreSQL pass",
    ),
    pytest.mark.worker,
    pytest.mark.process,
    pytest.mark.django_db(transaction=True),
]

BATCHES = 12
PER_BATCH = 25


@pytest.fixture
def seaweedfs(tmp_path):
    with start_seaweedfs(tmp_path / "seaweedfs") as server:
        server.bucket_create("envelopes")
        yield server


def _secrets(settings) -> dict[str, str]:
    """The portal's secrets as an operator hands them to every host, in the environment; the
    test process uses the same ones."""
    values = {
        "AUTHROS_MASTER_KEY": secrets.token_hex(16),
        "CHAIN_OPERATOR_KEY": Account.create().key.hex(),
        "AUTHROS_SM2_PRIVATE_KEY": secrets.token_hex(32),
        "DJANGO_SECRET_KEY": secrets.token_urlsafe(50),
    }
    settings.AUTHROS_MASTER_KEY = values["AUTHROS_MASTER_KEY"]
    settings.CHAIN_OPERATOR_KEY = values["CHAIN_OPERATOR_KEY"]
    settings.AUTHROS_SM2_PRIVATE_KEY = values["AUTHROS_SM2_PRIVATE_KEY"]
    return values


def _upload(url: str, setup, first: int) -> None:
    envelopes = [setup.seal(seq) for seq in range(first, first + PER_BATCH)]
    answer = requests.post(
        f"{url}/api/v1/records/",
        json={"envelopes": [base64.b64encode(data).decode() for data in envelopes]},
        headers={"Authorization": f"Token {setup.token}"},
        timeout=60,
    )
    assert answer.status_code == 201, answer.text


def _files_in(folder: Path) -> list[Path]:
    return [path for path in folder.rglob("*") if path.is_file()]


def test_two_web_hosts_and_two_worker_hosts_share_only_the_services(tmp_path, settings, seaweedfs):
    host_secrets = _secrets(settings)
    storage = seaweedfs.environment("envelopes", "portal")
    settings.STORAGES = {
        **settings.STORAGES,
        "envelopes": envelope_storage_config(
            storage["ENVELOPE_STORAGE_URL"],
            media_root=settings.MEDIA_ROOT,
            endpoint_url=storage["ENVELOPE_S3_ENDPOINT_URL"],
            region=storage["ENVELOPE_S3_REGION"],
        ),
    }
    stack = WorkerStack(tmp_path)
    try:
        stack.configure_test_process(settings)
        stack.redis_flush_own()
        chain_services._clients.clear()
        chain_services.contract_deploy()
        hosts = {
            name: stack.host_env(name, **host_secrets, **storage)
            for name in ("worker-a", "worker-b", "web-a", "web-b")
        }
        stack.start_worker("worker-a", env=hosts["worker-a"])
        stack.start_worker("worker-b", env=hosts["worker-b"])
        stack.start_beat(env=hosts["worker-a"])
        web_a = stack.start_web(name="web-a", env=hosts["web-a"])
        web_b = stack.start_web(name="web-b", env=hosts["web-b"])

        setups = registered_robots(2)
        for batch in range(BATCHES):
            for setup in setups:
                _upload(web_a, setup, first=batch * PER_BATCH + 1)
            if batch == BATCHES // 2:
                # Worker host b dies while records are being anchored: host a carries on.
                wait_for(
                    lambda: Record.objects.filter(status=Record.Status.ANCHORED).exists(),
                    timeout=120,
                    what="anchoring under way",
                )
                stack.kill_worker("worker-b")
        total = BATCHES * PER_BATCH * len(setups)
        wait_for(
            lambda: Record.objects.filter(status=Record.Status.ANCHORED).count() == total,
            timeout=300,
            what=f"{total} records anchored by the worker host left",
            interval=0.5,
        )
        assert not Record.objects.exclude(status=Record.Status.ANCHORED).exists()
        assert_anchored_exactly_once(chain_services.chain_client())

        # Taken by web host a, shown by web host b: verified against the chain, decrypted.
        for setup in setups:
            _token, key = owner_token_create(
                owner=setup.owner, name="reader", scopes=["read"], expires_in=timedelta(hours=1)
            )
            for record in Record.objects.filter(robot=setup.robot).order_by("seq")[::60]:
                answer = requests.get(
                    f"{web_b}/api/v1/records/{record.id}/content/",
                    headers={"Authorization": f"Token {key}"},
                    timeout=60,
                )
                assert answer.status_code == 200, answer.text
                assert answer.json()["verified"] is True
                data = base64.b64decode(answer.json()["envelope"])
                _header, plaintext = envelope.open(setup.key, data)
                assert json.loads(plaintext) == {"K": {"seq": record.seq}}

        # Nothing any host needs is in its own folder: no secret written, no envelope kept.
        for name in hosts:
            folder = tmp_path / "hosts" / name
            assert _files_in(folder / "secrets") == [], name
            assert _files_in(folder / "media") == [], name
        listed = seaweedfs.client().list_objects_v2(Bucket="envelopes", Prefix="portal/")
        assert listed["KeyCount"] == min(total, 1000)
    finally:
        stack.stop()

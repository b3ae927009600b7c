"""Issue 44 end to end: a real agent's v2 batches verify for the owner and a grantee, and a
record the portal drops is named `missing` everywhere it is counted.

Real parts only: a paired robot's agent as a process of its own (`python -m ros_agent import`
of a small MCAP recording: the agent's own Recorder, spool, BatchSigner and Uploader), the
portal under gunicorn for the robot and the API clients, the same portal (live server, same
database) in Chromium, Celery workers and beat, anvil, the export made by the worker and checked
by `authros-verify` as a process of its own.

1. The owner: the record page says verified and signed; the content API verified; the proof
   carries its batch and topic_seq; the series and the completeness answer count every record
   uploaded, without a gap.
2. A grantee (granted through the grants API): the content verified, the series' streams the
   same.
3. An export, downloaded: `authros-verify --complete` passes and names the streams.
4. One record in the middle of a stream dropped behind the portal's back (its row and stored
   envelope removed): the completeness answer, the series and the robot page name a `missing`
   gap at its topic_seq; a new export fails `--complete` on it and passes without it, the gap
   printed.
"""

import json
import subprocess
import sys
import uuid
from datetime import UTC, datetime, timedelta
from pathlib import Path

import pytest
import requests
import yaml
from playwright.sync_api import Browser, expect

from accounts.models import ChainState, Owner, Robot
from accounts.services.owners import owner_create
from chainworker import services as chain_services
from core.redis_client import get_redis
from ros_agent.keyring import key_id_hex, write_keys_file
from sharing.cache import _key as cache_key
from sharing.models import Grant, Record
from sharing.storage import envelope_storage
from smcrypto import provenance, sm4
from tests.support.harness import REPO_ROOT, wait_for
from tests.support.recordings import CHATTER, ODOM, make_samples, ros2_store, write_ros2_bag
from tests.support.robot_setup import TEST_PASSWORD
from tests.support.worker_robots import paired_robot

pytestmark = [
    pytest.mark.worker,
    pytest.mark.process,
    pytest.mark.django_db(transaction=True),
    pytest.mark.timeout(600),
]

PER_TOPIC = 6  # records of each topic in the recording
BATCH_SIZE = 5  # the agent's upload batches: 12 records in 5, 5 and 2
DROPPED = 2  # the topic_seq of the /robot/odom record the portal loses


def _owner(name: str) -> tuple[Owner, bytes]:
    key = sm4.generate_key()
    owner = owner_create(username=name, password=TEST_PASSWORD, sm4_key=key)
    return owner, key


def _registered(*owners: Owner) -> None:
    ids = [owner.pk for owner in owners]
    wait_for(
        lambda: (
            Owner.objects.filter(pk__in=ids, chain_state=ChainState.CONFIRMED).count() == len(ids)
        ),
        timeout=120,
        what="the owners registered on chain by the workers",
    )
    for owner in owners:
        owner.refresh_from_db()


def _paired_robot(owner: Owner, key: bytes, folder: Path, url: str) -> tuple[Robot, Path]:
    """A robot of `owner` paired as the agent pairs (its key registered on chain by the
    workers), and what pairing leaves on it: its SM2 key, the owner's keys, its token and an
    agent.yaml naming them and the recording's two topics."""
    setup = paired_robot(owner, key, name="cart-1")
    robot, token, (private_key, _public_key) = setup.robot, setup.token, setup.signing_key
    folder.mkdir(parents=True)
    (folder / "robot.sm2").write_text(private_key + "\n")
    (folder / "robot.sm2").chmod(0o600)
    write_keys_file(folder / "owner-keys.json", {key_id_hex(key): key}, key_id_hex(key))
    (folder / "robot.token").write_text(token)
    (folder / "robot.token").chmod(0o600)
    config = {
        "portal_url": url,
        "token_file": "robot.token",
        "robot": str(robot.id),
        "owner": owner.user.username,
        "sm2_key_file": "robot.sm2",
        "keys_file": "owner-keys.json",
        "topics": [{"name": name, "type": ros_type} for name, ros_type in (ODOM, CHATTER)],
        "spool_dir": "spool",
        "batch_size": BATCH_SIZE,
        "backoff_max": 1.0,
    }
    (folder / "agent.yaml").write_text(yaml.safe_dump(config))
    return robot, folder / "agent.yaml"


def _recording(folder: Path, start: datetime) -> Path:
    """An MCAP recording of odometry and chatter, PER_TOPIC messages each, from `start`."""
    ts = ros2_store()
    base_ns = int(start.timestamp()) * 10**9
    samples = [
        sample
        for sample in make_samples(ts, PER_TOPIC, base_ns=base_ns)
        if (sample.topic, sample.ros_type) in (ODOM, CHATTER)
    ]
    return write_ros2_bag(folder, samples, ts, mcap=True)


class Api:
    """An owner's API client on the portal (gunicorn), with an owner token."""

    def __init__(self, url: str, key: str) -> None:
        self.url = url
        self.session = requests.Session()
        self.session.headers["Authorization"] = f"Token {key}"

    def get(self, path: str, **params: str) -> dict:
        answer = self.session.get(f"{self.url}{path}", params=params, timeout=60)
        assert answer.status_code == 200, (path, answer.status_code, answer.text)
        return answer.json()

    def post(self, path: str, body: dict) -> requests.Response:
        return self.session.post(f"{self.url}{path}", json=body, timeout=60)

    def download(self, path: str) -> bytes:
        answer = self.session.get(f"{self.url}{path}", timeout=60)
        assert answer.status_code == 200, (path, answer.status_code, answer.text)
        return answer.content


def _stream(robot: Robot, topic: str, count: int, gaps: list[dict]) -> dict:
    return {
        "signer": robot.key_hash,
        "topic": topic,
        "robot": str(robot.id),
        "first": 0,
        "last": PER_TOPIC - 1,
        "count": count,
        "gaps": gaps,
    }


def _series(api: Api, robot: Robot, start: datetime) -> dict:
    return api.get(
        "/api/v1/records/series/",
        robot=str(robot.id),
        topic=ODOM[0],
        fields="position.x",
        since=_iso(start - timedelta(minutes=1)),
        until=_iso(start + timedelta(minutes=1)),
    )


def _iso(moment: datetime) -> str:
    return moment.isoformat().replace("+00:00", "Z")


def _exported(api: Api, robot: Robot, folder: Path) -> tuple[Path, Path]:
    """An export of the robot's records made by the worker, its two files downloaded."""
    answer = api.post("/api/v1/exports/", {"robots": [str(robot.id)]})
    assert answer.status_code == 202, answer.text
    export_id = answer.json()["id"]
    done: dict = {}

    def ready() -> bool:
        done.update(api.get(f"/api/v1/exports/{export_id}/"))
        assert done["status"] not in ("failed", "withdrawn"), done
        return done["status"] == "done"

    wait_for(ready, timeout=120, what="the export made by the worker")
    folder.mkdir()
    bundle, mcap = folder / "proofs.json", folder / "export.mcap"
    bundle.write_bytes(api.download(done["bundle_url"]))
    mcap.write_bytes(api.download(done["mcap_url"]))
    return bundle, mcap


def _verify(bundle: Path, mcap: Path, rpc: str, contract: str, *flags: str):
    """`authros-verify` as an auditor runs it, in a process of its own."""
    return subprocess.run(
        [
            sys.executable,
            "-m",
            "authros_verify",
            str(bundle),
            *("--mcap", str(mcap), "--rpc", rpc, "--contract", contract),
            *flags,
        ],
        cwd=REPO_ROOT,
        capture_output=True,
        text=True,
        timeout=180,
        check=False,
    )


def test_a_real_agents_v2_batches_verify_and_a_dropped_record_is_named_missing(
    stack, live_server, browser: Browser, artifacts: Path, make_owner_token, tmp_path
):
    url = stack.start_web(workers=1)
    suffix = uuid.uuid4().hex[:6]
    (alice, alice_key), (bob, _bob_key) = _owner(f"alice-{suffix}"), _owner(f"bob-{suffix}")
    _registered(alice, bob)
    robot, config = _paired_robot(alice, alice_key, tmp_path / "robot", url)
    signer = robot.key_hash
    assert signer == provenance.key_hash(robot.public_key)

    # --- the agent imports a recording and uploads it in v2 batches --------------------------
    start = datetime.now(UTC).replace(microsecond=0) - timedelta(minutes=3)
    recording = _recording(tmp_path / "drive", start)
    total = 2 * PER_TOPIC
    agent = subprocess.run(
        [
            sys.executable, "-m", "ros_agent", "import", "--config", str(config),
            "--no-progress", "--upload-timeout", "120", str(recording),
        ],
        cwd=REPO_ROOT, capture_output=True, text=True, timeout=240, check=False,
    )  # fmt: skip
    output = agent.stdout + agent.stderr
    assert agent.returncode == 0, output
    assert f"total: {total} message(s) sealed" in output
    assert f"uploaded {total}, refused by the portal 0, waiting in the spool 0" in output
    wait_for(
        lambda: Record.objects.filter(robot=robot, status=Record.Status.ANCHORED).count() == total,
        timeout=180,
        what=f"the {total} records anchored by the workers",
        interval=0.5,
    )
    records = list(Record.objects.filter(robot=robot).order_by("seq"))
    assert len(records) == total
    assert {record.signer for record in records} == {signer}
    by_stream = {
        topic: sorted((r for r in records if r.topic == topic), key=lambda r: r.topic_seq)
        for topic in (ODOM[0], CHATTER[0])
    }
    for topic, stream in by_stream.items():
        assert [r.topic_seq for r in stream] == list(range(PER_TOPIC)), topic

    # --- 1. the owner --------------------------------------------------------------------------
    _, alice_token = make_owner_token(alice, scopes=("read", "share"))
    owner_api = Api(url, alice_token)
    batches = {}
    for record in records:
        content = owner_api.get(f"/api/v1/records/{record.id}/content/")
        assert content["verified"] is True
        proof = owner_api.get(f"/api/v1/records/{record.id}/proof/")
        assert proof["topic_seq"] == record.topic_seq
        assert proof["signature"]["signer"] == signer
        batch = proof["batch"]
        assert 0 <= batch["sig_index"] < batch["sig_size"]
        batches.setdefault(batch["root"], []).append((batch["sig_index"], batch["sig_size"]))
    # the agent's batches: each signed once, its records in its leaves
    assert sorted(len(leaves) for leaves in batches.values()) == [2, BATCH_SIZE, BATCH_SIZE]
    for leaves in batches.values():
        assert sorted(leaves) == [(index, len(leaves)) for index in range(len(leaves))]

    whole = [
        _stream(robot, CHATTER[0], PER_TOPIC, []),
        _stream(robot, ODOM[0], PER_TOPIC, []),
    ]
    series = _series(owner_api, robot, start)
    assert (series["source_records"], series["verified"], series["refused"]) == (6, 6, 0)
    assert series["streams"] == [whole[1]]
    assert series["uncounted"] == 0
    completeness = owner_api.get("/api/v1/records/completeness/", robot=str(robot.id))
    assert completeness == {"streams": whole, "uncounted": 0}

    page = browser.new_page()
    base = live_server.url
    page.goto(f"{base}/login/")
    page.fill("#id_username", alice.user.username)
    page.fill("#id_password", TEST_PASSWORD)
    page.click("#login-submit")
    page.wait_for_url("**/dashboard/")
    shown = by_stream[ODOM[0]][DROPPED + 1]
    page.goto(f"{base}/records/{shown.id}/")
    verdict = page.get_by_test_id("verdict")
    expect(verdict).to_have_attribute("data-verdict", "verified", timeout=60_000)
    expect(page.get_by_test_id("verified-signature")).to_contain_text(f"robot key {signer}")
    expect(page.get_by_test_id("record-signer")).to_contain_text(f"robot key {signer[:16]}")
    page.screenshot(path=artifacts / "v2-record-verified.png", full_page=True)

    # --- 2. a grantee, granted through the API -------------------------------------------------
    granted = owner_api.post("/api/v1/grants/", {"grantee": bob.user.username})
    assert granted.status_code == 201, granted.text
    wait_for(
        lambda: Grant.objects.get(owner=alice, grantee=bob).status == Grant.Status.ACTIVE,
        timeout=120,
        what="the grant confirmed on chain by the workers",
    )
    _, bob_token = make_owner_token(bob, scopes=("read",))
    grantee_api = Api(url, bob_token)
    for record in records:
        assert grantee_api.get(f"/api/v1/records/{record.id}/content/")["verified"] is True
    grantee_series = _series(grantee_api, robot, start)
    assert grantee_series["streams"] == series["streams"]
    assert grantee_series["verified"] == PER_TOPIC

    # --- 3. an export, checked by the auditor's command ----------------------------------------
    rpc, contract = stack.anvil.url, chain_services.chain_client().address
    bundle, mcap = _exported(owner_api, robot, tmp_path / "export-1")
    document = json.loads(bundle.read_text())
    assert document["streams"] == {"streams": whole, "uncounted": 0}
    counted = sorted((entry["topic"], entry["topic_seq"]) for entry in document["records"])
    assert counted == [(t, n) for t in (CHATTER[0], ODOM[0]) for n in range(PER_TOPIC)]
    complete = _verify(bundle, mcap, rpc, contract, "--complete")
    assert complete.returncode == 0, complete.stdout + complete.stderr
    assert f"{total} of {total} records verified against the chain: {total} genuine" in (
        complete.stdout
    )
    for topic in (ODOM[0], CHATTER[0]):
        assert (
            f"topic {topic} (robot {robot.id}): topic_seq 0..{PER_TOPIC - 1}, "
            f"{PER_TOPIC} records, nothing" in complete.stdout
        ), complete.stdout
    assert complete.stdout.rstrip().splitlines()[-1].startswith("VERIFIED: ")

    # --- 4. a record dropped behind the portal's back ------------------------------------------
    dropped = by_stream[ODOM[0]][DROPPED]
    storage = envelope_storage()
    assert storage.exists(dropped.storage_name)
    storage.delete(dropped.storage_name)
    get_redis().delete(cache_key(dropped.pk))
    Record.objects.filter(pk=dropped.pk).delete()

    gap = [{"from": DROPPED, "to": DROPPED, "reason": "missing"}]
    broken = [whole[0], _stream(robot, ODOM[0], PER_TOPIC - 1, gap)]
    completeness = owner_api.get("/api/v1/records/completeness/", robot=str(robot.id))
    assert completeness == {"streams": broken, "uncounted": 0}
    series = _series(owner_api, robot, start)
    assert series["streams"] == [broken[1]]
    assert _series(grantee_api, robot, start)["streams"] == [broken[1]]

    page.goto(f"{base}/robots/{robot.id}/")
    section = page.get_by_test_id("robot-completeness")
    warning = section.get_by_test_id("completeness-gaps")
    expect(warning).to_be_visible()
    expect(warning).to_have_attribute("role", "alert")
    expect(section.get_by_test_id("completeness-summary")).to_contain_text(
        f"Last hour: {total - 1} records, 1 missing"
    )
    missing = section.get_by_test_id("gap")
    expect(missing).to_have_count(1)
    expect(missing).to_have_attribute("data-reason", "missing")
    expect(missing).to_have_attribute("data-from", str(DROPPED))
    expect(missing).to_contain_text(f"1 record missing on {ODOM[0]}")
    expect(missing).to_contain_text(f"(#{DROPPED})")
    plot = page.get_by_test_id("robot-plot")
    expect(plot).to_have_attribute("data-state", "ready", timeout=30_000)
    expect(plot).to_have_attribute("data-missing", "1")
    page.screenshot(path=artifacts / "v2-robot-missing.png", full_page=True)

    bundle, mcap = _exported(owner_api, robot, tmp_path / "export-2")
    strict = _verify(bundle, mcap, rpc, contract, "--complete")
    assert strict.returncode == 1, strict.stdout + strict.stderr
    assert f"    GAP {DROPPED} (1 records): missing" in strict.stdout
    assert "FAILED: 1 gaps, 0 records no stream counts (--complete)" in strict.stdout
    plain = _verify(bundle, mcap, rpc, contract)
    assert plain.returncode == 0, plain.stdout + plain.stderr
    assert (
        f"topic {ODOM[0]} (robot {robot.id}): topic_seq 0..{PER_TOPIC - 1}, "
        f"{PER_TOPIC - 1} records, 1 gaps" in plain.stdout
    ), plain.stdout
    assert f"    GAP {DROPPED} (1 records): missing\n" in plain.stdout
    assert plain.stdout.rstrip().splitlines()[-1].startswith("VERIFIED: ")

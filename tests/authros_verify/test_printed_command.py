"""The verify command an export's page prints runs as printed: taken from the page, run in a
shell in a folder of its own holding the files as downloaded (never the project's folder),
with the project's `.venv/bin` on PATH (`. .venv/bin/activate`: scripts/bootstrap.sh installs
`authros-verify` there), against the session's anvil named by PUBLIC_RPC_URL. It checks the
export, draws nothing on a stderr that is piped, and ends with its verdict line."""

import html
import os
import re
import subprocess

import pytest
from django.urls import reverse

from sharing.exports.create import export_create
from sharing.models import Export
from sharing.services.uploads import record_create_batch
from tests.authros_verify.conftest import chatter_envelopes
from tests.support.harness import REPO_ROOT

pytestmark = [pytest.mark.django_db, pytest.mark.process]

COMMAND = re.compile(r'data-testid="verify-command"><code>(.*?)</code>', re.S)
FILENAME = re.compile(r'filename="([^"]+)"')


def test_the_command_the_export_page_prints_runs_as_printed_in_the_downloads_folder(
    make_paired_robot, django_capture_on_commit_callbacks, deployed, settings, client, tmp_path
):
    settings.PUBLIC_RPC_URL = settings.CHAIN_RPC_URL  # the session's anvil, as users reach it
    alice = make_paired_robot("alice")  # its envelopes are signed: genuine
    envelopes = chatter_envelopes(alice, (1, 2))
    with django_capture_on_commit_callbacks(execute=True):
        record_create_batch(robot=alice.robot, envelopes=envelopes)
    with django_capture_on_commit_callbacks(execute=True):
        export = export_create(requester=alice.owner)
    export.refresh_from_db()
    assert export.status == Export.Status.DONE, export.error

    client.force_login(alice.owner.user)
    page = client.get(reverse("export-detail", args=[export.pk])).content.decode()
    (printed,) = COMMAND.findall(page)
    command = html.unescape(printed)
    downloads = tmp_path / "Downloads"
    downloads.mkdir()
    for part in ("mcap", "bundle"):
        answer = client.get(reverse("api-v1:export-file", args=[export.pk, part]))
        assert answer.status_code == 200
        (name,) = FILENAME.findall(answer["Content-Disposition"])
        (downloads / name).write_bytes(b"".join(answer.streaming_content))

    environment = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "VIRTUAL_ENV")}
    environment["PATH"] = f"{REPO_ROOT / '.venv' / 'bin'}{os.pathsep}{environment['PATH']}"
    done = subprocess.run(
        ["bash", "-c", command],  # as pasted into a shell
        cwd=downloads,
        env=environment,
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    assert done.returncode == 0, f"{command}\n{done.stdout}\n{done.stderr}"
    assert "2 of 2 records verified against the chain" in done.stdout
    chain_id = deployed.w3.eth.chain_id
    assert done.stdout.splitlines()[-1] == (
        f"VERIFIED: 2 records, 0 refused, chain {chain_id} contract {deployed.address}"
    )
    assert done.stderr == ""  # piped: no progress bar

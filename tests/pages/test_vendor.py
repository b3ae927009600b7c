"""The vendored sm-crypto that pages load: the pinned package's build, and it interoperates."""

import json
import shutil
import subprocess
from pathlib import Path

import pytest

from accounts.keyexchange import portal_sm2_public_key, sm4_key_from_submission
from smcrypto import sm4

REPO = Path(__file__).resolve().parents[2]
VENDORED = REPO / "static" / "vendor" / "sm-crypto-0.3.13" / "sm2.js"
PACKAGE = REPO / "node_modules" / "sm-crypto"

# What static/portal/keyexchange.js does with a key, on the vendored file.
ENCRYPT_AS_THE_PAGE_DOES = """
const sm2 = require(process.argv[1]);
const input = JSON.parse(require('fs').readFileSync(0, 'utf8'));
const bytes = [];
for (let i = 0; i < input.key.length; i += 2) bytes.push(parseInt(input.key.substr(i, 2), 16));
console.log(sm2.doEncrypt(bytes, input.public_key, 1));
"""

needs_package = pytest.mark.skipif(
    not PACKAGE.is_dir(), reason="needs the pinned npm sm-crypto (npm ci)"
)


@needs_package
def test_vendored_copy_is_the_pinned_package():
    package = json.loads((PACKAGE / "package.json").read_text())
    pinned = json.loads((REPO / "package.json").read_text())["dependencies"]["sm-crypto"]
    assert package["version"] == pinned == "0.3.13"
    assert VENDORED.read_bytes() == (PACKAGE / "dist" / "sm2.js").read_bytes()
    licence = VENDORED.parent / "LICENCE_MIT"
    assert licence.read_bytes() == (PACKAGE / "LICENCE_MIT").read_bytes()


@pytest.mark.process
@pytest.mark.skipif(shutil.which("node") is None, reason="needs node")
def test_key_encrypted_by_the_vendored_script_opens_in_the_portal(settings, tmp_path):
    settings.SECRETS_DIR = tmp_path
    key = sm4.generate_key()
    done = subprocess.run(
        ["node", "-e", ENCRYPT_AS_THE_PAGE_DOES, str(VENDORED)],
        input=json.dumps({"key": key.hex(), "public_key": portal_sm2_public_key()}),
        capture_output=True,
        text=True,
        check=True,
        timeout=60,
    )
    assert sm4_key_from_submission(done.stdout.strip()) == key

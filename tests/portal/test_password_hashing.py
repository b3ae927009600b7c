"""The portal hashes passwords with Django's PBKDF2 at full strength (the test process uses
fewer iterations, tests/support/hashers.py; a fresh process has the portal's own settings)."""

import json

import pytest
from django.contrib.auth.hashers import PBKDF2PasswordHasher

from tests.support.fresh_python import fresh_python

pytestmark = [pytest.mark.process, pytest.mark.nodb]


def test_the_portal_hashes_passwords_with_pbkdf2_at_djangos_iterations():
    program = (
        "import json, django\n"
        "django.setup()\n"
        "from django.contrib.auth.hashers import check_password, get_hasher, make_password\n"
        "hashed = make_password('correct horse battery')\n"
        "print(json.dumps({'hasher': type(get_hasher()).__name__, 'hashed': hashed, "
        "'checks': check_password('correct horse battery', hashed)}))"
    )
    made = json.loads(fresh_python(program))
    assert made["hasher"] == "PBKDF2PasswordHasher"
    algorithm, iterations, _salt, _digest = made["hashed"].split("$")
    assert algorithm == "pbkdf2_sha256"
    assert int(iterations) == PBKDF2PasswordHasher.iterations >= 1_000_000
    assert made["checks"] is True


def test_a_test_hash_is_one_the_portal_checks():
    """What the test process makes, a web process a test starts accepts at login."""
    from django.contrib.auth.hashers import make_password

    hashed = make_password("correct horse battery")
    assert hashed.startswith("pbkdf2_sha256$1000$")
    program = (
        "import django\n"
        "django.setup()\n"
        "from django.contrib.auth.hashers import check_password\n"
        f"print(check_password('correct horse battery', {hashed!r}))"
    )
    assert fresh_python(program) == "True"

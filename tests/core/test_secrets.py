"""Secret files: created atomically, so that processes starting together agree on one secret
and none ever reads an empty or partly written file (F5)."""

import multiprocessing
import queue
from pathlib import Path

import pytest

from core import secrets as core_secrets
from core.secrets import SecretFileError, load_or_create_secret

pytestmark = pytest.mark.nodb

PROCESSES = 8
ROUNDS = 60
NBYTES = 16


def _race(directory: str, rounds: int, barrier, results) -> None:
    """One of the processes racing: each round, all start together on a fresh path."""
    for round_number in range(rounds):
        path = Path(directory) / f"round-{round_number}" / "secret.key"
        barrier.wait()
        try:
            value = load_or_create_secret(path, nbytes=NBYTES).hex()
        except Exception as exc:  # the crash is what the test reports
            value = f"crashed: {type(exc).__name__}: {exc}"
        results.put((round_number, value))


def test_processes_starting_together_agree_on_one_secret_and_none_crashes(tmp_path):
    context = multiprocessing.get_context("spawn")
    barrier = context.Barrier(PROCESSES)
    results = context.Queue()
    processes = [
        context.Process(target=_race, args=(str(tmp_path), ROUNDS, barrier, results))
        for _ in range(PROCESSES)
    ]
    for process in processes:
        process.start()
    by_round: dict[int, list[str]] = {}
    try:
        for _ in range(PROCESSES * ROUNDS):
            round_number, value = results.get(timeout=120)
            by_round.setdefault(round_number, []).append(value)
    except queue.Empty:
        pytest.fail(f"the racing processes stopped answering after {by_round}")
    finally:
        for process in processes:
            process.join(timeout=30)
            if process.is_alive():
                process.kill()
    crashed = [value for values in by_round.values() for value in values if "crashed" in value]
    assert crashed == []
    for round_number, values in by_round.items():
        stored = (tmp_path / f"round-{round_number}" / "secret.key").read_text().strip()
        assert set(values) == {stored}
        # Nothing is left of the losers' attempts.
        assert [p.name for p in (tmp_path / f"round-{round_number}").iterdir()] == ["secret.key"]


def test_the_secret_file_never_exists_empty_while_it_is_being_written(tmp_path, monkeypatch):
    """What another process would see at the worst moment: while the secret is generated and
    written, the final name holds nothing or a complete secret, never an empty file."""
    path = tmp_path / "secrets" / "master.key"
    seen: list[str | None] = []
    token_hex = core_secrets.secrets.token_hex

    def observed_token_hex(nbytes: int) -> str:
        seen.append(path.read_text() if path.exists() else None)
        return token_hex(nbytes)

    monkeypatch.setattr(core_secrets.secrets, "token_hex", observed_token_hex)
    value = load_or_create_secret(path, nbytes=NBYTES)
    assert seen == [None]
    assert path.read_text() == value.hex() + "\n"


def test_a_new_secret_file_is_private_and_leaves_no_temporary_file(tmp_path):
    path = tmp_path / "secrets" / "operator.key"
    first = load_or_create_secret(path, nbytes=32)
    assert path.stat().st_mode & 0o777 == 0o600
    assert [p.name for p in path.parent.iterdir()] == ["operator.key"]
    assert load_or_create_secret(path, nbytes=32) == first


def test_an_existing_secret_is_read_not_replaced(tmp_path):
    path = tmp_path / "django-secret-key"
    path.write_text("ab" * 32 + "\n")
    path.chmod(0o600)
    assert load_or_create_secret(path, nbytes=32) == bytes.fromhex("ab" * 32)


@pytest.mark.parametrize(
    ("content", "mode", "problem"),
    [
        ("", 0o600, "holds 0 bytes"),
        ("not hex\n", 0o600, "does not contain hex digits"),
        ("ab" * 32, 0o644, "readable by other users"),
    ],
)
def test_a_secret_file_that_cannot_be_trusted_is_refused(tmp_path, content, mode, problem):
    path = tmp_path / "master.key"
    path.write_text(content)
    path.chmod(mode)
    with pytest.raises(SecretFileError, match=problem):
        load_or_create_secret(path, nbytes=32)
    assert path.read_text() == content


def test_a_secret_is_read_once_until_its_file_changes(tmp_path, monkeypatch):
    """A request pays a stat, not a read; a file rewritten, replaced or made readable by
    others is read and checked again."""
    path = tmp_path / "master.key"
    first = load_or_create_secret(path, nbytes=NBYTES)
    reads = []
    real_read = core_secrets._read_secret
    monkeypatch.setattr(
        core_secrets, "_read_secret", lambda *a, **k: reads.append(a) or real_read(*a, **k)
    )
    assert load_or_create_secret(path, nbytes=NBYTES) == first
    assert load_or_create_secret(path, nbytes=NBYTES) == first
    assert reads == []

    other = bytes(range(NBYTES))
    replacement = tmp_path / "new.key"
    replacement.write_text(other.hex() + "\n")
    replacement.chmod(0o600)
    replacement.replace(path)  # another inode
    assert load_or_create_secret(path, nbytes=NBYTES) == other
    assert len(reads) == 1

    path.chmod(0o644)
    with pytest.raises(SecretFileError, match="readable by other users"):
        load_or_create_secret(path, nbytes=NBYTES)
    path.chmod(0o600)
    path.write_text("zz\n")  # the same inode, rewritten
    with pytest.raises(SecretFileError, match="hex digits"):
        load_or_create_secret(path, nbytes=NBYTES)

    path.unlink()
    created = load_or_create_secret(path, nbytes=NBYTES)
    assert created not in (first, other)
    assert load_or_create_secret(path, nbytes=NBYTES) == created

"""authros-verify on a long run: a progress bar on stderr only when stderr is a terminal (a
piped or redirected stderr gets nothing), and one verdict line last on stdout, VERIFIED or
FAILED, with the exit codes as before."""

import io
import sys

import pytest

from authros_verify.__main__ import main
from authros_verify.progress import ProgressBar
from tests.authros_verify.conftest import chatter_envelopes, export_of

pytestmark = pytest.mark.django_db


class Terminal(io.StringIO):
    """What the verifier writes to a terminal, kept."""

    def isatty(self) -> bool:
        return True


def test_the_bar_draws_on_a_terminal_only_and_wipes_its_line():
    piped = io.StringIO()
    bar = ProgressBar(piped)
    bar.show("records", 1, 2)
    bar.close()
    assert piped.getvalue() == ""

    terminal = Terminal()
    bar = ProgressBar(terminal)
    bar.show("records", 1, 2)
    bar.show("records", 1, 2)  # nothing new to say: not drawn again
    bar.show("MCAP file", 3 * 1024 * 1024, 4 * 1024 * 1024, in_bytes=True)
    drawn = terminal.getvalue()
    assert drawn.count("\r") == 2
    assert f"records [{'#' * 15}{'.' * 15}]  50%  1 of 2" in drawn
    assert "MCAP file [" in drawn
    assert "75%  3.0 of 4.0 MiB" in drawn
    bar.close()
    assert terminal.getvalue().endswith("\r")


def test_a_piped_run_prints_no_bar_and_ends_with_its_verdict(
    make_paired_robot,
    django_capture_on_commit_callbacks,
    deployed,
    isolated_portal,
    tmp_path,
    capsys,
    monkeypatch,
):
    setup = make_paired_robot("alice")
    envelopes = chatter_envelopes(setup, (1, 2))
    bundle, mcap = export_of(setup, django_capture_on_commit_callbacks, envelopes)
    (tmp_path / "proofs.json").write_bytes(bundle)
    (tmp_path / "export.mcap").write_bytes(mcap)
    arguments = [str(tmp_path / "proofs.json"), "--mcap", str(tmp_path / "export.mcap")]
    arguments += ["--rpc", isolated_portal, "--contract", deployed.address]
    chain = f"chain {deployed.w3.eth.chain_id} contract {deployed.address}"
    capsys.readouterr()  # the portal's logs of making the export

    assert main(arguments) == 0
    out, err = capsys.readouterr()
    assert err == ""  # capsys's stderr is no terminal
    assert out.splitlines()[-1] == f"VERIFIED: 2 records, 0 refused, {chain}"

    # On a terminal the bar follows the MCAP file's two reads, then the records, and is wiped.
    terminal = Terminal()
    monkeypatch.setattr(sys, "stderr", terminal)
    assert main(arguments) == 0
    drawn = terminal.getvalue()
    assert "MCAP file [" in drawn
    assert f"records   [{'#' * 30}] 100%  2 of 2" in drawn
    assert drawn.endswith("\r")
    assert capsys.readouterr().out.splitlines()[-1].startswith("VERIFIED: 2 records")
    monkeypatch.undo()

    (tmp_path / "export.mcap").write_bytes(mcap.replace(b"msg 2", b"msg 3"))
    assert main(arguments) == 1
    out, err = capsys.readouterr()
    assert err == ""
    assert out.splitlines()[-1] == (
        "FAILED: 1 of 2 records refused, 1 problems with the bundle or the MCAP file"
    )
    assert main([*arguments[:3], "--rpc", "http://127.0.0.1:9"]) == 2

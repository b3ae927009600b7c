"""The stylesheets parse as written: every block closed where it was opened. A rule block left
open swallows all the rules after it into its @media query (a merge once left the phone layout's
block open, and the Robots table's desktop rules applied to no desktop)."""

import re
from pathlib import Path

import pytest

from tests.support.harness import REPO_ROOT

STYLESHEETS = sorted((REPO_ROOT / "static").rglob("*.css"))


def _depths(css: str) -> list[int]:
    """The nesting depth after each brace, comments and strings left out."""
    text = re.sub(r"/\*.*?\*/", "", css, flags=re.S)
    text = re.sub(r"\"(?:[^\"\\\\]|\\\\.)*\"|'(?:[^'\\\\]|\\\\.)*'", "", text)
    depth, depths = 0, []
    for char in text:
        if char in "{}":
            depth += 1 if char == "{" else -1
            depths.append(depth)
    return depths


@pytest.mark.parametrize("path", STYLESHEETS, ids=lambda path: path.name)
def test_every_block_is_closed(path: Path):
    depths = _depths(path.read_text())
    assert min(depths, default=0) >= 0, "a } closes nothing"
    assert depths[-1:] in ([], [0]), "a block is left open at the end"


def test_a_top_level_comment_heads_no_rule_inside_a_media_query():
    # The blocks each engineer appends start with a "/* --- " comment, at the top level.
    css = (REPO_ROOT / "static" / "portal" / "portal.css").read_text()
    for match in re.finditer(r"^/\* --- ", css, flags=re.M):
        before = _depths(css[: match.start()])
        assert before[-1:] in ([], [0]), css[match.start() : match.start() + 60]

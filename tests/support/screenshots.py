"""Where the browser tests' screenshots go (test-artifacts/e2e/, ignored by git), and numbered
full-page screenshots of a test's steps."""

from pathlib import Path

from playwright.sync_api import Page

from stack.processes import REPO_ROOT

ARTIFACTS = REPO_ROOT / "test-artifacts" / "e2e"


class Screenshots:
    """Numbered full-page screenshots, in the order the steps happen."""

    def __init__(self, directory: Path) -> None:
        self.directory = directory
        self.count = 0

    def __call__(self, page: Page, name: str) -> None:
        self.count += 1
        page.screenshot(path=self.directory / f"{self.count:02d}-{name}.png", full_page=True)

"""Fixtures of the sharing tests that the page tests have too."""

from tests.pages.conftest import upload  # noqa: F401  (the fixture, for tests/sharing/)

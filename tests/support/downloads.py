"""Where the packaging tests keep the wheels they download: the machine's cache, not the
checkout, so that a fresh clone (CI's) takes what an earlier run on the machine fetched, as
pip's own cache does, and fetches only what a changed lock adds.

The files are checked by their hashes each time (`pip download --require-hashes`), so a file
from an earlier run is used only where it is the file the lock names. AUTHROS_TEST_DOWNLOADS
moves the folder.
"""

import os
from pathlib import Path

DOWNLOADS = Path(
    os.environ.get("AUTHROS_TEST_DOWNLOADS")
    or Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "authros-portal-tests"
)

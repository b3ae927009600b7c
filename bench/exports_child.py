"""One export run as the export worker runs it, in an interpreter of its own whose portal code
is the tree on PYTHONPATH (today's, or the baseline's worktree: bench/exports.py), measured.

    PYTHONPATH=<tree> python bench/exports_child.py EXPORT_ID

Prints one line of JSON: the Export's status and counts, wall and CPU time, peak RSS
(getrusage: the whole process, Django and the libraries included), the RSS before exporting,
and the time spent in the integrity check every view runs (`_verified`). Imports nothing of
bench/, so that the baseline's export runs the baseline's code only.
"""

import json
import os
import resource
import sys
import time
from typing import Any

# The script's folder (bench/) is not where the portal's packages are looked up: PYTHONPATH is.
if sys.path and os.path.abspath(sys.path[0]) == os.path.dirname(os.path.abspath(__file__)):
    del sys.path[0]


def main(export_id: str) -> dict[str, Any]:
    import django

    django.setup()
    from sharing.exports import run
    from sharing.models import Export

    in_check = [0.0]
    checked = run._verified

    def timed(*args: Any, **kwargs: Any) -> Any:
        started = time.perf_counter()
        try:
            return checked(*args, **kwargs)
        finally:
            in_check[0] += time.perf_counter() - started

    run._verified = timed
    rss_before = _rss_mib()
    cpu = os.times()
    started = time.perf_counter()
    run.export_run(export_id=export_id)
    seconds = time.perf_counter() - started
    after = os.times()
    export = Export.objects.get(pk=export_id)
    return {
        "status": export.status,
        "error": export.error,
        "exported": export.exported,
        "seconds": seconds,
        "cpu_seconds": (after.user - cpu.user)
        + (after.system - cpu.system)
        + (after.children_user - cpu.children_user)
        + (after.children_system - cpu.children_system),
        "peak_rss_mib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
        # Its forked encoder's, if it had one (today's exporter), and its CPU.
        "peak_rss_children_mib": resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024,
        "rss_before_mib": rss_before,
        "check_seconds": in_check[0],
        "mcap_bytes": export.mcap_size,
        "bundle_bytes": export.bundle_size,
    }


def _rss_mib() -> float:
    with open("/proc/self/statm") as statm:
        return int(statm.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20


if __name__ == "__main__":
    print(json.dumps(main(sys.argv[1])))

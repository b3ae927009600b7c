"""`python -m bench` runs every benchmark but the soak; `python -m bench NAME [args]` runs one."""

import importlib
import sys

from bench import available

# Run only when named: the soak takes an hour (`make soak`), too long for a run of them all;
# webserver compares two checkouts' web servers (bench/webserver.py); robot_status writes
# millions of rows first; single_view compares two ways of one check on one stack.
ON_DEMAND = ("soak", "webserver", "robot_status", "single_view")


def main(argv: list[str]) -> int:
    """Dispatch to bench/<name>.py's main(argv); with no name run them all."""
    names = [*available(), *ON_DEMAND]
    if argv and argv[0] in ("-h", "--help"):
        print(f"usage: python -m bench [NAME [args]]\nbenchmarks: {', '.join(names)}")
        return 0
    if not argv:  # every benchmark, then the report of what they wrote
        failures = []
        for name in [name for name in available() if name != "report"]:
            print(f"== bench {name} ==", file=sys.stderr)
            if _run(name, []) != 0:
                failures.append(name)
        _run("report", [])
        if failures:
            print(f"benchmarks with failures: {', '.join(failures)}", file=sys.stderr)
        return 1 if failures else 0
    name, args = argv[0], argv[1:]
    if name not in names:
        print(f"unknown benchmark {name!r}; available: {', '.join(names)}", file=sys.stderr)
        return 2
    return _run(name, args)


def _run(name: str, args: list[str]) -> int:
    module = importlib.import_module(f"bench.{name}")
    try:
        return module.main(args) or 0
    except SystemExit as exc:  # refused its arguments (e.g. postgres-s3 without a server):
        return exc.code if isinstance(exc.code, int) else 1  # the others still run


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))

"""The wheel's console scripts, `authros-agent` and `authros-verify`.

Each loads its command here, not at the script's import: both scripts are in every
environment the wheel is installed in, and one run where its extra is missing (`authros-agent
pair` in an auditor's environment, which has no PyYAML; `authros-verify` on a robot, which has
no web3; `authros-agent --ros2` without Cyclone DDS) says in one line which locked set to
install and exits 2, instead of a traceback. `--version` answers wherever the wheel is.
Nothing of the project is imported here until the command runs.
"""

import importlib
import sys
from importlib import metadata

DISTRIBUTION = "authros-portal"
# The extra that installs a module, where it is not the command's own extra.
EXTRA_OF_MODULE = {"cyclonedds": "ros2"}
# A missing module of the project itself is a broken install, not a missing extra.
OWN_PACKAGES = {"ros_agent", "authros_verify", "smcrypto", "authros_commands"}


def agent() -> int:
    """`authros-agent`."""
    return command_run("authros-agent", "ros_agent.__main__", extra="agent")


def verify() -> int:
    """`authros-verify`."""
    return command_run("authros-verify", "authros_verify.__main__", extra="verify")


def version() -> str:
    """The installed wheel's version."""
    try:
        return metadata.version(DISTRIBUTION)
    except metadata.PackageNotFoundError:
        return "(not installed: run from a checkout)"


def command_run(command: str, module: str, *, extra: str) -> int:
    """Run the command's `main` with the script's arguments: its exit code, or 2 with what to
    install when a module of an extra is missing."""
    arguments = sys.argv[1:]
    if arguments in (["--version"], ["-V"]):
        print(f"{command} {version()}")
        return 0
    try:
        return importlib.import_module(module).main(arguments)
    except ModuleNotFoundError as exc:
        missing = (exc.name or "").split(".")[0]
        if not missing or missing in OWN_PACKAGES:
            raise
        needed = EXTRA_OF_MODULE.get(missing, extra)
        print(
            f"{command}: this environment lacks the [{needed}] extra (no module named "
            f"{missing!r}): install requirements/{needed}.txt into it (docs/deployment.md)",
            file=sys.stderr,
        )
        return 2

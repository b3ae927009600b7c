"""`authros-agent` (or `python -m ros_agent`): the agent's one command.

`authros-agent --config agent.yaml`: run the agent node on ROS 1 (see ros_agent.node); without
arguments it reads the node's private ROS parameters (deploy/ros1/authros_agent.launch).
`authros-agent pair --portal URL --name NAME`: pair the robot (ros_agent.pairing).
`authros-agent --ros2 --config agent.yaml`: the agent on a ROS 2 robot (ros_agent.ros2).
`authros-agent import --config agent.yaml FILE...`: import recordings (ros_agent.bags).
None of the last three needs ROS 1. `authros-agent --help` lists them.
"""

import importlib.util
import logging
import sys
from collections.abc import Sequence

USAGE = """usage: authros-agent [--ros2] --config agent.yaml | pair ... | import ...

The AuthROS agent: seals a robot's ROS topics (SM4-GCM, signed with the robot's SM2 key) and
uploads them to the portal.

commands:
  pair --portal URL --name NAME   pair this robot with its owner's account; writes agent.yaml
  --config agent.yaml             record the configured topics on ROS 1 (needs Debian's rospy)
  --ros2 --config agent.yaml      record them on ROS 2 through Cyclone DDS (no ROS 2 install)
  import --config agent.yaml FILE...
                                  seal and upload recordings (.bag, .db3, .mcap)

Each command's own options: authros-agent pair --help, authros-agent --ros2 --help,
authros-agent import --help, authros-agent --config agent.yaml --help.
"""
NO_ROSPY = (
    "ROS 1's rospy is not importable: install Debian's python3-rospy (and make the agent's "
    "virtual environment of Debian's Python with --system-site-packages: "
    "/usr/bin/python3 -m venv --system-site-packages DIR), or run the agent with --ros2"
)


def main(argv: Sequence[str] | None = None) -> int:
    arguments = list(sys.argv[1:] if argv is None else argv)
    if arguments in (["-h"], ["--help"]):
        print(USAGE, end="")
        return 0
    command = arguments[0] if arguments else ""
    if command == "pair":
        from ros_agent.pairing import main as pairing_main

        return pairing_main(arguments[1:])
    if command == "import" or "--ros2" in arguments:
        logging.basicConfig(
            level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s"
        )
    if command == "import":
        from ros_agent.bags import main as import_main

        return import_main(arguments[1:])
    if "--ros2" in arguments:
        asks_help = {"-h", "--help"} & set(arguments)
        if not asks_help and importlib.util.find_spec("cyclonedds") is None:  # imported later
            raise ModuleNotFoundError("No module named 'cyclonedds'", name="cyclonedds")
        from ros_agent.ros2 import main as ros2_main

        return ros2_main([arg for arg in arguments if arg != "--ros2"])
    try:
        from ros_agent.node import main as node_main
    except ModuleNotFoundError as exc:
        if exc.name not in ("rospy", "roslib", "genpy"):
            raise
        print(NO_ROSPY, file=sys.stderr)
        return 2
    # Without arguments the node reads its private ROS parameters (a launch file's <param>s);
    # rospy strips the __name:= and __log:= arguments roslaunch adds.
    return node_main([sys.argv[0], *arguments])


if __name__ == "__main__":
    sys.exit(main())

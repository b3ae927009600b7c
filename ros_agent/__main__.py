"""`python -m ros_agent --config agent.yaml`: run the agent node (see ros_agent.node).

`python -m ros_agent pair --portal URL --name NAME`: pair the robot (ros_agent.pairing).
`python -m ros_agent --ros2 --config agent.yaml`: the agent on a ROS 2 robot (ros_agent.ros2).
`python -m ros_agent import --config agent.yaml FILE...`: import recordings (ros_agent.bags).
None of the last three needs ROS 1.
"""

import logging
import sys

if sys.argv[1:2] == ["pair"]:
    from ros_agent.pairing import main as pairing_main

    sys.exit(pairing_main(sys.argv[2:]))
if sys.argv[1:2] == ["import"] or "--ros2" in sys.argv[1:]:
    logging.basicConfig(
        level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s"
    )
if sys.argv[1:2] == ["import"]:
    from ros_agent.bags import main as import_main

    sys.exit(import_main(sys.argv[2:]))
if "--ros2" in sys.argv[1:]:
    from ros_agent.ros2 import main as ros2_main

    sys.exit(ros2_main([arg for arg in sys.argv[1:] if arg != "--ros2"]))

from ros_agent.node import main

sys.exit(main())

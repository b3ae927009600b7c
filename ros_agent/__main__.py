"""`python -m ros_agent --config agent.yaml`: run the agent node (see ros_agent.node);
`python -m ros_agent pair --portal URL --name NAME`: pair the robot (ros_agent.pairing, no ROS
needed)."""

import sys

if sys.argv[1:2] == ["pair"]:
    from ros_agent.pairing import main as pairing_main

    sys.exit(pairing_main(sys.argv[2:]))

from ros_agent.node import main

sys.exit(main())

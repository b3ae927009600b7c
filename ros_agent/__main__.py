"""`python -m ros_agent --config agent.yaml`: run the agent node (see ros_agent.node)."""

import sys

from ros_agent.node import main

sys.exit(main())

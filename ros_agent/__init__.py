"""The AuthROS robot agent: subscribe ROS topics, seal each message, upload it to the portal.

    python -m ros_agent --config agent.yaml     # the node (ros_agent.node)
    python -m ros_agent.sim                     # a simulated robot publishing the paper's topics
    python -m ros_agent --ros2 --config agent.yaml   # on ROS 2, over Cyclone DDS (ros_agent.ros2)
    python -m ros_agent.sim2                    # the simulated robot on ROS 2
    python -m ros_agent import --config agent.yaml FILE...   # .bag, .db3, .mcap (ros_agent.bags)

Flow per message: extractors (message -> `K`) -> wrapping (Fig. 4 JSON, sealed as an envelope
with the next sequence number, signed by a paired robot: sealing.py) -> spool (durable, on
disk) -> uploader (batches to the portal, removed from the spool only once the portal
confirmed them). Only node.py and sim.py import rospy; everything else runs and is tested
without a ROS master. ROS 2 and recorded messages (rosbags) reach the same extractors through
ros2msg.ros1_view, and the same spool and uploader through pipeline.py.
"""

# Children of rospy's "rosout" logger: the same output as rospy.loginfo(..., logger_name=...),
# on the console, in the node's log file and on /rosout, once the node is initialised.
LOGGER_NAME = "rosout.authros_agent"

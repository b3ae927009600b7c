"""The AuthROS agent in a ROS 2 launch, from the ament package around this folder:
`ros2 launch authros_agent authros_agent.launch.py [config:=FILE]`.

The agent talks DDS itself (Cyclone DDS, no rclpy), so it is a process of the launch, not a
Node: `authros-agent --ros2 --config FILE`, started again if it dies, stopped with SIGINT (it
sends what it can, the rest stays in its spool). `config` is the agent.yaml that
`authros-agent pair --dir DIR` wrote; `agent` is the command where it is not on PATH.
ROS_DOMAIN_ID, CYCLONEDDS_URI and AMENT_PREFIX_PATH (custom messages) come from the
environment the launch runs in, as for any ROS 2 node.
"""

from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, ExecuteProcess
from launch.substitutions import LaunchConfiguration

ARGUMENTS = {
    "config": ("/var/lib/authros-agent/agent.yaml", "the agent.yaml authros-agent pair wrote"),
    "agent": ("authros-agent", "the agent's command (e.g. /opt/authros-agent/bin/authros-agent)"),
}


def generate_launch_description() -> LaunchDescription:
    return LaunchDescription(
        [
            *(
                DeclareLaunchArgument(name, default_value=default, description=description)
                for name, (default, description) in ARGUMENTS.items()
            ),
            ExecuteProcess(
                cmd=[
                    LaunchConfiguration("agent"),
                    "--ros2",
                    "--config",
                    LaunchConfiguration("config"),
                ],
                name="authros_agent",
                output="screen",
                respawn=True,
                respawn_delay=5.0,
                sigterm_timeout="30",
            ),
        ]
    )

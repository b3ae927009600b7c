"""`make run` with the robot on ROS 2 (STACK_ROS2): its settings and the environment its
processes get; the whole run is what tests/ros_agent/test_ros2.py drives piece by piece."""

from stack.run import Stack, StackConfig


def test_stack_ros2_puts_dds_on_loopback_in_the_chosen_domain_without_a_ros_master(tmp_path):
    config = StackConfig.from_environment(
        {"AUTHROS_VAR_DIR": str(tmp_path), "STACK_ROS2": "true", "ROS_DOMAIN_ID": "42"}
    )
    assert (config.ros, config.ros2, config.ros_domain_id) == (True, True, 42)
    env = Stack(config).environment()
    assert env["CYCLONEDDS_URI"] == (tmp_path.resolve() / "cyclonedds.xml").as_uri()
    assert env["ROS_DOMAIN_ID"] == "42"
    assert "ROS_MASTER_URI" not in env


def test_the_ros1_robot_stays_the_default(tmp_path):
    config = StackConfig.from_environment({"AUTHROS_VAR_DIR": str(tmp_path)})
    assert (config.ros, config.ros2) == (True, False)
    env = Stack(config).environment()
    assert "CYCLONEDDS_URI" not in env
    assert env["ROS_MASTER_URI"] == "http://127.0.0.1:11311"

"""The ament_python package of the agent's ROS 2 launch file (no Python of its own: the agent is
the pip-installed `authros-agent`). colcon runs this; it installs what `ros2 launch` looks for:
share/authros_agent/launch/*.launch.py, package.xml, and the package's ament index marker."""

from glob import glob

from setuptools import setup

PACKAGE = "authros_agent"

setup(
    name=PACKAGE,
    version="0.1.0",
    packages=[],
    data_files=[
        ("share/ament_index/resource_index/packages", [f"resource/{PACKAGE}"]),
        (f"share/{PACKAGE}", ["package.xml"]),
        (f"share/{PACKAGE}/launch", glob("launch/*.launch.py")),
    ],
    install_requires=["setuptools"],
    zip_safe=True,
    maintainer="AuthROS",
    maintainer_email="robots@example.org",
    description="The AuthROS agent in a ROS 2 launch",
    license="Apache-2.0",
)

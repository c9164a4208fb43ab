"""Install with colcon (ament_python) inside a ROS 2 workspace, or with pip outside ROS."""

from glob import glob

from setuptools import find_packages, setup

package_name = "vi3_ros"

setup(
    name=package_name,
    version="0.1.0",
    description="Metric dense geometry from a 3D foundation model anchored by an IMU (VI3) as a ROS 2 node",
    license="Apache-2.0",
    packages=find_packages(include=["vi3_core", "vi3_core.*", "vi3_ros", "vi3_ros.*", "msg_adapters",
                                    "msg_adapters.*"]),
    data_files=[
        ("share/ament_index/resource_index/packages", ["resource/" + package_name]),
        ("share/" + package_name, ["package.xml"]),
        ("share/" + package_name + "/launch", glob("launch/*.launch.py")),
        # parameters, calibration and the views (RViz2 config, Foxglove layout)
        ("share/" + package_name + "/config", glob("config/*.yaml") + glob("config/*.rviz") + glob("config/*.json")),
    ],
    python_requires=">=3.10",
    install_requires=[
        "numpy>=1.24",
        "scipy>=1.10",
        "torch>=2.1",
        "opencv-python-headless>=4.8",
        "rosbags>=0.10",
        "mcap>=1.1",
        "mcap-ros2-support>=0.5",
        "matplotlib>=3.7",
        "tqdm>=4.60",
        "threadpoolctl>=3.1",
        "pyyaml>=6.0",
        "simplejpeg>=1.7",
    ],
    extras_require={
        # vi3_node without a sourced ROS 2: rclpy, Fast DDS and the message packages the node uses, as PyPI's ROS 2
        # Jazzy wheels (Linux x86-64, CPython 3.10-3.12; elsewhere source a ROS 2 Jazzy instead). tf2_msgs has no wheel:
        # /tf is then not published (the node says so at start). Pinned: they are one distribution's build.
        "ros": [f"ros-jazzy-{name}=={version}; platform_system == 'Linux' and platform_machine == 'x86_64'"
                for name, version in (("rclpy", "7.1.6"), ("rmw-fastrtps-cpp", "8.4.3"), ("std-msgs", "5.3.6"),
                                      ("sensor-msgs", "5.3.6"), ("geometry-msgs", "5.3.6"), ("nav-msgs", "5.3.6"),
                                      ("diagnostic-msgs", "5.3.6"))],
        # vi3 eval --ray: evaluation on a Ray cluster (vi3_core.eval.distributed); in the test extra so the suite
        # covers it.
        "ray": ["ray>=2.9"],
        "test": ["pytest>=8", "hypothesis>=6.100", "ruff>=0.6", "filelock>=3.12", "ray>=2.9"],
    },
    entry_points={
        "console_scripts": [
            "vi3 = vi3_ros.entry:program",
            "vi3_node = vi3_ros.node:main",
        ],
    },
    zip_safe=True,
)

"""Launch vi3_node with config/euroc.yaml (override with params_file:=...) and the EuRoC cam0 calibration
(override with calib_file:=...). Arguments: params_file, calib_file, backbone, mode, device."""

from launch.actions import DeclareLaunchArgument
from launch.substitutions import LaunchConfiguration, PathJoinSubstitution
from launch_ros.actions import Node
from launch_ros.substitutions import FindPackageShare

from launch import LaunchDescription


def generate_launch_description() -> LaunchDescription:
    share = FindPackageShare("vi3_ros")
    args = [
        DeclareLaunchArgument("params_file", default_value=PathJoinSubstitution([share, "config", "euroc.yaml"]),
                              description="ROS 2 parameter file for vi3_node"),
        DeclareLaunchArgument("calib_file", default_value=PathJoinSubstitution(
            [share, "config", "euroc_cam0_sensor.yaml"]), description="EuRoC sensor.yaml or Kalibr camchain YAML"),
        DeclareLaunchArgument("backbone", default_value="classical", description="3D foundation model"),
        DeclareLaunchArgument("mode", default_value="init", description="init | cond | ttr"),
        DeclareLaunchArgument("device", default_value="cpu", description="torch device"),
    ]
    node = Node(
        package="vi3_ros",
        executable="vi3_node",
        name="vi3_node",
        output="screen",
        parameters=[LaunchConfiguration("params_file"),
                    {name: LaunchConfiguration(name) for name in ("calib_file", "backbone", "mode", "device")}],
    )
    return LaunchDescription([*args, node])

"""Launch vi3_node with config/euroc.yaml (override with params_file:=...) and the EuRoC cam0 calibration
(override with calib_file:=...). Arguments: params_file, calib_file, backbone, mode, device;
px4:=true publishes px4_msgs/VehicleOdometry for PX4 over uXRCE-DDS (parameter px4_odom; needs px4_msgs);
mavros:=true publishes nav_msgs/Odometry on /mavros/odometry/out for MAVROS's odometry plugin, PX4 or ArduPilot
(parameter mavros_odom); rviz:=true starts rviz2 with config/vi3.rviz; views:=true (the default with rviz:=true) puts
~/poses and ~/points in odom and publishes the odom TF, as the views (RViz2, config/vi3_foxglove.json) expect.
Like backbone, mode and device, these arguments override the parameter file. docs/node.md: "Feeding PX4 / ArduPilot"
and "Views"."""

from launch.actions import DeclareLaunchArgument
from launch.conditions import IfCondition
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
        DeclareLaunchArgument("px4", default_value="false",
                              description="publish px4_msgs/VehicleOdometry for PX4 (uXRCE-DDS)"),
        DeclareLaunchArgument("mavros", default_value="false",
                              description="publish nav_msgs/Odometry for MAVROS's odometry plugin (PX4, ArduPilot)"),
        DeclareLaunchArgument("rviz", default_value="false", description="start rviz2 with config/vi3.rviz"),
        DeclareLaunchArgument("views", default_value=LaunchConfiguration("rviz"),
                              description="poses and points in odom, odom TF published (what the views show)"),
    ]
    views = LaunchConfiguration("views")
    node = Node(
        package="vi3_ros",
        executable="vi3_node",
        name="vi3_node",
        output="screen",
        parameters=[LaunchConfiguration("params_file"),
                    {name: LaunchConfiguration(name) for name in ("calib_file", "backbone", "mode", "device")},
                    {"px4_odom": LaunchConfiguration("px4"), "mavros_odom": LaunchConfiguration("mavros"),
                     "outputs_in_odom": views, "publish_odom_tf": views}],
    )
    rviz = Node(package="rviz2", executable="rviz2", name="rviz2", output="screen",
                arguments=["-d", PathJoinSubstitution([share, "config", "vi3.rviz"])],
                condition=IfCondition(LaunchConfiguration("rviz")))
    return LaunchDescription([*args, node, rviz])

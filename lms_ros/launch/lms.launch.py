"""Launch lms_node with its parameter file (Jazzy: ros2 launch lms_ros lms.launch.py).

Arguments: params_file (default: this package's config/lms_node.yaml), namespace,
use_sim_time. Remap the relative input/output topics (input/points, with
separate_probabilities also input/probabilities; output/points, output/segments,
output/markers) with the launch file's remappings or by namespacing.
"""
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.substitutions import LaunchConfiguration, PathJoinSubstitution
from launch_ros.actions import Node
from launch_ros.substitutions import FindPackageShare


def generate_launch_description():
    params_file = LaunchConfiguration("params_file")
    return LaunchDescription([
        DeclareLaunchArgument(
            "params_file",
            default_value=PathJoinSubstitution([FindPackageShare("lms_ros"), "config", "lms_node.yaml"]),
            description="Parameter YAML of lms_node"),
        DeclareLaunchArgument("namespace", default_value="", description="Node namespace"),
        DeclareLaunchArgument("use_sim_time", default_value="false", description="Use /clock"),
        Node(
            package="lms_ros",
            executable="lms_node",
            name="lms_node",
            namespace=LaunchConfiguration("namespace"),
            parameters=[params_file, {"use_sim_time": LaunchConfiguration("use_sim_time")}],
            output="screen",
        ),
    ])

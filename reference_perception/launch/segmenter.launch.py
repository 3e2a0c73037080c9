"""Launch segmenter_node with its parameter file
(Jazzy: ros2 launch reference_perception segmenter.launch.py).

Arguments: params_file (default: this package's config/segmenter_node.yaml), namespace,
use_sim_time, points (input cloud topic, remapped to input/points).
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
            default_value=PathJoinSubstitution([FindPackageShare("reference_perception"), "config",
                                                "segmenter_node.yaml"]),
            description="Parameter YAML of segmenter_node"),
        DeclareLaunchArgument("namespace", default_value="", description="Node namespace"),
        DeclareLaunchArgument("use_sim_time", default_value="false", description="Use /clock"),
        DeclareLaunchArgument("points", default_value="/lidar/points", description="Input cloud topic"),
        Node(
            package="reference_perception",
            executable="segmenter_node",
            name="segmenter_node",
            namespace=LaunchConfiguration("namespace"),
            parameters=[params_file, {"use_sim_time": LaunchConfiguration("use_sim_time")}],
            remappings=[("input/points", LaunchConfiguration("points"))],
            output="screen",
        ),
    ])

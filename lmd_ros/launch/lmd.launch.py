"""Launch lmd_node with its parameter file (Jazzy: ros2 launch lmd_ros lmd.launch.py).

Arguments: params_file (default: this package's config/lmd_node.yaml), namespace,
use_sim_time. Remap the relative input/output topics with the launch file's remappings
or by namespacing. proposal_mode and the model files (classifier_path / regressor_path,
empty: the shipped models/lmd/lmd_<proposal_mode>_*) are set in the params file; the
node refuses to start without valid models.
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
            default_value=PathJoinSubstitution([FindPackageShare("lmd_ros"), "config", "lmd_node.yaml"]),
            description="Parameter YAML of lmd_node"),
        DeclareLaunchArgument("namespace", default_value="", description="Node namespace"),
        DeclareLaunchArgument("use_sim_time", default_value="false", description="Use /clock"),
        Node(
            package="lmd_ros",
            executable="lmd_node",
            name="lmd_node",
            namespace=LaunchConfiguration("namespace"),
            parameters=[params_file, {"use_sim_time": LaunchConfiguration("use_sim_time")}],
            output="screen",
        ),
    ])

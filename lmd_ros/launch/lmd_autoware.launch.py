"""Launch lmd_node between an Autoware lidar detector and its tracker (Jazzy:
ros2 launch lmd_ros lmd_autoware.launch.py).

The node reads the detector's DetectedObjects (``base_link``) and the lidar cloud, and
publishes the same objects with the meta confidence as ``existence_probability`` on
``output_objects``: point the tracker (or Autoware's object merger) at that topic.

Arguments: input_objects (default Autoware's CenterPoint output), input_pointcloud (the
concatenated cloud), output_objects, params_file (default config/lmd_node.yaml, then
config/lmd_node_autoware.yaml on top), namespace, use_sim_time.
"""
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.substitutions import LaunchConfiguration, PathJoinSubstitution
from launch_ros.actions import Node
from launch_ros.substitutions import FindPackageShare

DETECTION = "/perception/object_recognition/detection"


def generate_launch_description():
    config = PathJoinSubstitution([FindPackageShare("lmd_ros"), "config"])
    arg = LaunchConfiguration
    return LaunchDescription([
        DeclareLaunchArgument("input_objects", default_value=f"{DETECTION}/centerpoint/objects",
                              description="The detector's DetectedObjects"),
        DeclareLaunchArgument("input_pointcloud",
                              default_value="/sensing/lidar/concatenated/pointcloud",
                              description="The lidar cloud the detector saw (PointCloud2)"),
        DeclareLaunchArgument("output_objects",
                              default_value=f"{DETECTION}/centerpoint/objects_scored",
                              description="The scored DetectedObjects, for the tracker"),
        DeclareLaunchArgument("params_file",
                              default_value=PathJoinSubstitution([config, "lmd_node_autoware.yaml"]),
                              description="Autoware settings, on top of config/lmd_node.yaml"),
        DeclareLaunchArgument("namespace", default_value="", description="Node namespace"),
        DeclareLaunchArgument("use_sim_time", default_value="false", description="Use /clock"),
        Node(
            package="lmd_ros",
            executable="lmd_node",
            name="lmd_node",
            namespace=arg("namespace"),
            parameters=[PathJoinSubstitution([config, "lmd_node.yaml"]), arg("params_file"),
                        {"use_sim_time": arg("use_sim_time")}],
            remappings=[("input/detections", arg("input_objects")),
                        ("input/points", arg("input_pointcloud")),
                        ("output/objects", arg("output_objects"))],
            output="screen",
        ),
    ])

"""Launches the PSSNet completion node with its parameter file and the camera's topics remapped onto its inputs.

    ros2 launch pssnet_ros completion.launch.py depth:=/camera/depth/image_rect_raw \
        camera_info:=/camera/depth/camera_info mask:=/segmentation/mask [namespace:=arm] \
        [params_file:=my_params.yaml] [autostart:=false]

With ``autostart:=false`` the node stays unconfigured until a lifecycle manager (e.g. nav2_lifecycle_manager)
drives it through configure and activate on ``<namespace>/pssnet/change_state``.
"""

from launch_ros.actions import Node
from launch_ros.parameter_descriptions import ParameterValue
from launch_ros.substitutions import FindPackageShare

from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.substitutions import LaunchConfiguration, PathJoinSubstitution

#: The node's input topics (relative names of its subscriptions), each remappable by a launch argument.
INPUTS = {
    "depth": "depth image: 32FC1 metres or 16UC1 millimetres",
    "mask": "segmentation mask of the target object: mono8 or 8UC1, non-zero = object",
    "camera_info": "CameraInfo of the depth image",
}


def generate_launch_description() -> LaunchDescription:
    arguments = [
        DeclareLaunchArgument("namespace", default_value="", description="namespace of the node"),
        DeclareLaunchArgument(
            "params_file", default_value=PathJoinSubstitution([FindPackageShare("pssnet_ros"), "config",
                                                               "completion_node.yaml"]),
            description="parameter file of the node (the installed defaults)"),
        DeclareLaunchArgument("autostart", default_value="true",
                              description="configure and activate at start; false = wait for a lifecycle manager"),
    ] + [DeclareLaunchArgument(topic, default_value=topic, description=text) for topic, text in INPUTS.items()]
    node = Node(
        package="pssnet_ros",
        executable="completion_node",
        name="pssnet",
        namespace=LaunchConfiguration("namespace"),
        parameters=[LaunchConfiguration("params_file"),
                    {"autostart": ParameterValue(LaunchConfiguration("autostart"), value_type=bool)}],
        remappings=[(topic, LaunchConfiguration(topic)) for topic in INPUTS],
        output="screen",
        emulate_tty=True,
    )
    return LaunchDescription([*arguments, node])

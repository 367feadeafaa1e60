"""Launches the PSSNet completion node with its parameter file and the camera's topics remapped onto its inputs.

    ros2 launch pssnet_ros completion.launch.py depth:=/camera/depth/image_rect_raw \
        camera_info:=/camera/depth/camera_info mask:=/segmentation/mask [namespace:=arm] \
        [params_file:=my_params.yaml] [autostart:=false] [rviz:=true] [compressed_depth:=true]

With ``autostart:=false`` the node stays unconfigured until a lifecycle manager (e.g. nav2_lifecycle_manager)
drives it through configure and activate on ``<namespace>/pssnet/change_state``. With ``rviz:=true`` RViz 2 starts
too (``rviz2`` must be installed: ``ros-jazzy-rviz2``, not a dependency of this package, since a robot rarely has a
display) with the installed ``config/pssnet.rviz``: it draws what the node publishes (continuous mode, or every
service result with the parameter ``publish_service_results: true``).

With ``compressed_depth:=true`` the depth stream arrives compressed (a camera on another machine, or a bag
recorded with ``<depth>/compressedDepth``): image_transport's ``republish`` (``ros-jazzy-image-transport`` and
``ros-jazzy-compressed-depth-image-transport``, installed on the robot, not dependencies of this package) subscribes
to ``<depth>/compressedDepth`` and feeds the node the decompressed image on ``depth_decompressed``.
"""

from launch_ros.actions import Node
from launch_ros.parameter_descriptions import ParameterValue
from launch_ros.substitutions import FindPackageShare

from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.conditions import IfCondition
from launch.substitutions import LaunchConfiguration, PathJoinSubstitution, PythonExpression

#: Where image_transport's republisher puts the decompressed depth image (relative: in the launch's namespace).
DECOMPRESSED_DEPTH = "depth_decompressed"

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
        DeclareLaunchArgument("rviz", default_value="false",
                              description="also start RViz 2 with the installed config/pssnet.rviz"),
        DeclareLaunchArgument("compressed_depth", default_value="false",
                              description="the depth topic is published compressed (<depth>/compressedDepth): "
                                          "decompress it with image_transport's republish"),
    ] + [DeclareLaunchArgument(topic, default_value=topic, description=text) for topic, text in INPUTS.items()]
    compressed = LaunchConfiguration("compressed_depth")
    remappings = {topic: LaunchConfiguration(topic) for topic in INPUTS}
    remappings["depth"] = PythonExpression(["'", DECOMPRESSED_DEPTH, "' if '", compressed, "'.lower() == 'true' else '",
                                            LaunchConfiguration("depth"), "'"])
    node = Node(
        package="pssnet_ros",
        executable="completion_node",
        name="pssnet",
        namespace=LaunchConfiguration("namespace"),
        parameters=[LaunchConfiguration("params_file"),
                    {"autostart": ParameterValue(LaunchConfiguration("autostart"), value_type=bool)}],
        remappings=list(remappings.items()),
        output="screen",
        emulate_tty=True,
    )
    rviz = Node(
        package="rviz2",
        executable="rviz2",
        name="rviz2",
        namespace=LaunchConfiguration("namespace"),
        arguments=["-d", PathJoinSubstitution([FindPackageShare("pssnet_ros"), "config", "pssnet.rviz"])],
        condition=IfCondition(LaunchConfiguration("rviz")),
    )
    decompress = Node(
        package="image_transport",
        executable="republish",
        name="pssnet_depth_decompress",
        namespace=LaunchConfiguration("namespace"),
        parameters=[{"in_transport": "compressedDepth", "out_transport": "raw"}],
        # The subscriber's topic is its base topic "in" + "/compressedDepth", remapped as a whole.
        remappings=[("in/compressedDepth", [LaunchConfiguration("depth"), "/compressedDepth"]),
                    ("out", DECOMPRESSED_DEPTH)],
        condition=IfCondition(compressed),
    )
    return LaunchDescription([*arguments, decompress, node, rviz])

"""ament_python package pssnet_ros: the ROS-free library pssnet_core and the thin ROS 2 layer pssnet_ros."""

from glob import glob

from setuptools import find_packages, setup

PACKAGE = "pssnet_ros"

setup(
    name=PACKAGE,
    version="0.1.0",
    packages=find_packages(include=["pssnet_core", "pssnet_core.*", "pssnet_ros", "pssnet_ros.*"]),
    package_data={"pssnet_core": ["checkpoints/*.pt"]},
    data_files=[
        ("share/ament_index/resource_index/packages", [f"resource/{PACKAGE}"]),
        (f"share/{PACKAGE}", ["package.xml", "LICENSE"]),
        (f"share/{PACKAGE}/config", glob("config/*")),
        (f"share/{PACKAGE}/launch", glob("launch/*.launch.py")),
    ],
    install_requires=["setuptools"],
    zip_safe=False,
    maintainer="PSSNet-ROS maintainers",
    maintainer_email="pssnet@example.com",
    description="Diverse plausible shape completions from one depth image, and grasps scored across them.",
    license="BSD-3-Clause",
    entry_points={
        "console_scripts": [
            "completion_node = pssnet_ros.completion_node:main",
            "pssnet = pssnet_core.cli:main",
        ],
        # Subcommands of `pssnet` that need ROS (pssnet_core.cli.PLUGIN_GROUP).
        "pssnet.commands": ["bag = pssnet_ros.bag_cli"],
    },
)

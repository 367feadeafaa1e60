"""ament_python package pssnet_ros: what a robot runs, the completion node over pssnet_core's pipeline (message
conversions, parameters, the stamp synchroniser, diagnostics, `pssnet bag`), its launch file and parameters."""

from glob import glob

from setuptools import find_packages, setup

PACKAGE = "pssnet_ros"

setup(
    name=PACKAGE,
    version="0.1.0",
    packages=find_packages(include=[PACKAGE, f"{PACKAGE}.*"]),
    data_files=[
        ("share/ament_index/resource_index/packages", [f"resource/{PACKAGE}"]),
        (f"share/{PACKAGE}", ["package.xml", "LICENSE"]),
        (f"share/{PACKAGE}/config", glob("config/*")),
        (f"share/{PACKAGE}/launch", glob("launch/*.launch.py")),
    ],
    install_requires=["setuptools"],
    extras_require={"test": ["pytest"]},  # colcon test runs pytest only for packages that declare it
    zip_safe=False,
    maintainer="PSSNet-ROS maintainers",
    maintainer_email="pssnet@example.com",
    description="Diverse plausible shape completions from one depth image, and grasps scored across them.",
    license="BSD-3-Clause",
    entry_points={
        "console_scripts": ["completion_node = pssnet_ros.completion_node:main"],
        # Subcommands of `pssnet` that need ROS (pssnet_core.cli.PLUGIN_GROUP).
        "pssnet.commands": ["bag = pssnet_ros.bag_cli"],
    },
)

"""ament_python package pssnet_core: the ROS-free library (shapes, data, models, training, inference, grasps,
evaluation) and its command line `pssnet`, with the shipped checkpoint."""

from setuptools import find_packages, setup

PACKAGE = "pssnet_core"

setup(
    name=PACKAGE,
    version="0.1.0",
    packages=find_packages(include=[PACKAGE, f"{PACKAGE}.*"]),
    package_data={PACKAGE: ["checkpoints/*.pt"]},
    data_files=[
        ("share/ament_index/resource_index/packages", [f"resource/{PACKAGE}"]),
        (f"share/{PACKAGE}", ["package.xml", "LICENSE"]),
    ],
    install_requires=["setuptools"],
    extras_require={"test": ["pytest"]},  # colcon test runs pytest only for packages that declare it
    zip_safe=False,
    maintainer="PSSNet-ROS maintainers",
    maintainer_email="pssnet@example.com",
    description="Diverse plausible shape completions from one depth image, and grasps scored across them (no ROS).",
    license="BSD-3-Clause",
    entry_points={"console_scripts": ["pssnet = pssnet_core.cli:main"]},
)

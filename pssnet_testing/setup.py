"""ament_python package pssnet_testing: what the tests, the benchmarks and the demo use to run the completion node
(child processes, ROS domain claims, the service client, the chaos scenarios, process metrics), the synthetic
camera and the demo. A development package: scripts/setup.sh installs it; a robot never needs it."""

from setuptools import find_packages, setup

PACKAGE = "pssnet_testing"

setup(
    name=PACKAGE,
    version="0.1.0",
    packages=find_packages(include=[PACKAGE, f"{PACKAGE}.*"]),
    data_files=[
        ("share/ament_index/resource_index/packages", [f"resource/{PACKAGE}"]),
        (f"share/{PACKAGE}", ["package.xml", "LICENSE"]),
    ],
    install_requires=["setuptools"],
    extras_require={"test": ["pytest"]},  # colcon test runs pytest only for packages that declare it
    zip_safe=False,
    maintainer="PSSNet-ROS maintainers",
    maintainer_email="pssnet@example.com",
    description="Test harness, synthetic camera and demo of the PSSNet completion node (development only).",
    license="BSD-3-Clause",
)

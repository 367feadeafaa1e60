"""Each package.xml declares what that package imports (rosdep and colcon resolve from them, not from pip).

The repository holds four packages, one per folder: pssnet_core (ROS-free library), pssnet_ros (the node),
pssnet_testing (harness, synthetic camera, demo) and pssnet_interfaces (messages). Their Python modules are
scanned here; each package's tests are the files its pytest.ini names (test/test_colcon.py checks that every
test file belongs to exactly one package).
"""

from __future__ import annotations

import ast
import configparser
import importlib.util
import re
import subprocess
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest
import yaml

ROOT = Path(__file__).resolve().parents[1]
PYTHON_PACKAGES = ("pssnet_core", "pssnet_ros", "pssnet_testing")
OWN = (*PYTHON_PACKAGES, "pssnet_interfaces")
#: Declared though not imported by name: what needs them.
INDIRECT = {"lifecycle_msgs": "rclpy.lifecycle (the managed node) imports it"}
IMPORT = re.compile(r"^\s*(?:from|import)\s+([A-Za-z_][A-Za-z0-9_]*)", re.MULTILINE)


def is_ros_package(module: str) -> bool:
    """A ROS package (rosdep and colcon know it by this name): ROS itself, a message package, or one of ours."""
    return (module in ("rclpy", "launch", "launch_ros", "ament_index_python") or module in OWN
            or module.endswith(("_msgs", "_srvs", "_interfaces")))


def module_files(package: str) -> list[Path]:
    """The Python files a package installs (pssnet_ros: also its launch file)."""
    files = sorted((ROOT / package / package).rglob("*.py"))
    return files + sorted((ROOT / package / "launch").glob("*.py"))


def package_test_files(package: str) -> list[Path]:
    """The test files `colcon test` runs for a package (the testpaths of its pytest.ini), and test/conftest.py,
    which pytest loads for each of them."""
    ini = configparser.ConfigParser()
    ini.read(ROOT / package / "pytest.ini")
    files = {f for pattern in ini["pytest"]["testpaths"].split() for f in (ROOT / package).glob(pattern)}
    return sorted(files | {ROOT / "test" / "conftest.py"})


def imported_ros_packages(files: list[Path], exclude: str = "") -> set[str]:
    return {m for f in files for m in IMPORT.findall(f.read_text()) if is_ros_package(m) and m != exclude}


def dependencies(package: str, *kinds: str) -> set[str]:
    root = ET.parse(ROOT / package / "package.xml").getroot()
    return {e.text.strip() for kind in kinds for e in root.iter(kind)}


def test_the_packages_are_folders_of_the_root():
    """colcon finds every package of a clone in ws/src; a package.xml at the root would hide the others."""
    assert not (ROOT / "package.xml").exists()
    assert {path.parent.name for path in ROOT.glob("*/package.xml")} == set(OWN)
    for package in OWN:
        assert ET.parse(ROOT / package / "package.xml").getroot().findtext("name") == package
    for package in PYTHON_PACKAGES:
        assert (ROOT / package / "resource" / package).is_file() and package_test_files(package)


@pytest.mark.parametrize("package", PYTHON_PACKAGES)
def test_every_imported_ros_package_is_declared(package):
    modules = imported_ros_packages(module_files(package), exclude=package)
    if package == "pssnet_ros":
        assert {"rclpy", "diagnostic_msgs", "std_srvs", "launch_ros", "pssnet_interfaces", "pssnet_core"} <= modules
    exec_depends = dependencies(package, "exec_depend")
    assert modules - exec_depends == set(), "imported by the package but not an exec_depend"
    tests = imported_ros_packages(package_test_files(package), exclude=package)
    assert tests - exec_depends - dependencies(package, "test_depend") == set(), "imported by its tests, not declared"


@pytest.mark.parametrize("package", PYTHON_PACKAGES)
def test_declared_ros_packages_are_imported_or_launch_tools(package):
    declared = {d for d in dependencies(package, "exec_depend") if is_ros_package(d)}
    modules = imported_ros_packages(module_files(package), exclude=package)
    assert declared - modules - set(INDIRECT) == set(), "declared but never imported: stale dependency"
    tests = {d for d in dependencies(package, "test_depend") if is_ros_package(d)}
    assert tests - imported_ros_packages(package_test_files(package)) == set(), "test_depend that no test imports"


def test_the_import_graph_has_no_cycle():
    """pssnet_core needs no ROS and none of the other packages; the node package never needs the harness, not
    even for its tests (colcon orders packages by test dependencies too: that would be a cycle)."""
    core = imported_ros_packages(module_files("pssnet_core"), exclude="pssnet_core")
    assert core == set(), f"pssnet_core must stay ROS-free, imports {core}"
    assert "pssnet_testing" not in imported_ros_packages(module_files("pssnet_ros"))
    assert "pssnet_testing" not in imported_ros_packages(package_test_files("pssnet_ros"))
    assert "pssnet_testing" not in dependencies("pssnet_ros", *DEPEND_TAGS)
    assert "from rclpy.lifecycle import" in (ROOT / "pssnet_ros" / "pssnet_ros" / "completion_node.py").read_text()


# ------------------------------------------------------------------------------- rosdep keys (rosdistro)
#: The rosdistro entries of every name in the package.xml files (scripts/rosdep_extract.py writes it).
ROSDISTRO = yaml.safe_load((ROOT / "test" / "data" / "rosdep_keys.yaml").read_text())
DEPEND_TAGS = ("depend", "build_depend", "buildtool_depend", "build_export_depend", "exec_depend", "test_depend",
               "doc_depend")
#: Python module -> the rosdep key that installs it.
KEY_OF_MODULE = {
    "numpy": "python3-numpy",
    "scipy": "python3-scipy",
    "yaml": "python3-yaml",
    "cv2": "python3-opencv",
    "tqdm": "python3-tqdm",
    "torch": "python3-torch",
    "open3d": "python3-open3d-pip",
    "trimesh": "python3-trimesh-pip",
    "rosbags": "python3-rosbags-pip",
    "matplotlib": "python3-matplotlib",
    "mpl_toolkits": "python3-matplotlib",
    "skimage": "python3-skimage",
    "mujoco": "python3-mujoco-pip",
    "pytest": "python3-pytest",
    "hypothesis": "python3-hypothesis",
}
#: Python modules that rosdistro has no key for (checked at the extract's commit): pip installs them.
NO_KEY = {"manifold3d", "coacd", "ray"}
#: What the node loads to start and to answer a call (the support plane: open3d), and `pssnet bag`.
RUNTIME_MODULES = ("pssnet_ros.completion_node", "pssnet_core.pipeline", "pssnet_core.inference",
                   "pssnet_core.models", "pssnet_core.sampling", "pssnet_core.support_plane", "pssnet_ros.bag")


def all_dependencies(package: str) -> dict[str, set[str]]:
    """Dependency tag -> names, for one package.xml."""
    root = ET.parse(ROOT / package / "package.xml").getroot()
    return {tag: {e.text.strip() for e in root.iter(tag)} for tag in DEPEND_TAGS}


def resolves(rule: object, codename: str) -> bool:
    """Whether a rosdep rule for one OS (a list, {pip: ...}, or {codename or '*': ...}) installs something."""
    if isinstance(rule, list):
        return bool(rule)
    if not isinstance(rule, dict):
        return False
    if "pip" in rule or "packages" in rule:
        return True
    if codename in rule:
        return resolves(rule[codename], codename)
    return resolves(rule.get("*"), codename)


def third_party_imports(files: list[Path]) -> set[str]:
    """Top-level modules the files import that are neither the standard library, ROS, nor this repository's."""
    local = {f.stem for d in (*PYTHON_PACKAGES, "test", "benchmarks", "scripts") for f in (ROOT / d).rglob("*.py")}
    local |= set(OWN)
    modules = set()
    for f in files:
        for node in ast.walk(ast.parse(f.read_text())):
            if isinstance(node, ast.Import):
                modules.update(alias.name.split(".")[0] for alias in node.names)
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                modules.add(node.module.split(".")[0])
    return {m for m in modules
            if m not in sys.stdlib_module_names and m not in local and not is_ros_package(m) and m != "__future__"}


def python_keys(package: str, kind: str) -> set[str]:
    return {k for k in dependencies(package, kind) if k in ROSDISTRO["rosdep_keys"]}


def test_every_dependency_is_a_rosdistro_key_or_released_package():
    keys, released = ROSDISTRO["rosdep_keys"], ROSDISTRO["released_packages"]
    for package in OWN:
        for tag, names in all_dependencies(package).items():
            unknown = sorted(names - set(OWN) - set(keys) - set(released))
            assert not unknown, (f"{package}/package.xml <{tag}> {unknown}: no rosdep key of rosdistro "
                                 f"{ROSDISTRO['rosdistro_commit'][:12]} nor a released {ROSDISTRO['distro']} package "
                                 "(see the header of test/data/rosdep_keys.yaml)")


def test_rosdep_keys_resolve_on_every_release_platform():
    """A key that exists can still resolve to nothing: python3-open3d is null on Ubuntu 24.04 (noble)."""
    for key, entry in ROSDISTRO["rosdep_keys"].items():
        for os_name, codenames in ROSDISTRO["release_platforms"].items():
            for codename in codenames:
                assert resolves(entry[os_name], codename), f"rosdep key {key} installs nothing on {codename}"
    assert not resolves({"*": ["python3-open3d"], "noble": None}, "noble")  # the check bites
    assert resolves({"*": ["python3-torch"], "focal": None}, "noble") and resolves({"pip": {"packages": ["x"]}}, "")


@pytest.mark.parametrize("package", PYTHON_PACKAGES)
def test_every_third_party_import_has_a_key_or_is_known_to_have_none(package):
    modules, tests = third_party_imports(module_files(package)), third_party_imports(package_test_files(package))
    if package == "pssnet_core":
        assert {"torch", "open3d", "manifold3d"} <= modules and {"pytest", "hypothesis"} <= tests  # the scan works
    unmapped = (modules | tests) - set(KEY_OF_MODULE) - NO_KEY
    assert not unmapped, f"imported, but neither in KEY_OF_MODULE (with its rosdep key) nor in NO_KEY: {unmapped}"
    declared = dependencies(package, "exec_depend", "test_depend")
    missing = {m: KEY_OF_MODULE[m] for m in modules | tests if m in KEY_OF_MODULE and KEY_OF_MODULE[m] not in declared}
    assert not missing, f"{package} imports these, but their rosdep keys are not in its package.xml: {missing}"
    stale = python_keys(package, "exec_depend") | python_keys(package, "test_depend")
    stale -= {KEY_OF_MODULE[m] for m in modules | tests if m in KEY_OF_MODULE}
    stale -= {"python3-pytest-timeout"}  # a pytest plugin (the `timeout` option of pytest.ini), never imported
    assert not stale, f"{package} declares these, but neither its modules nor its tests import them: {stale}"
    for module in NO_KEY:
        assert not any(k.startswith(f"python3-{module}") for k in ROSDISTRO["rosdep_keys"]), module


def test_the_harness_declares_what_it_runs_with():
    """pssnet_testing is a tool package: every library its modules import is an exec_depend."""
    needed = {KEY_OF_MODULE[m] for m in third_party_imports(module_files("pssnet_testing")) if m in KEY_OF_MODULE}
    assert needed == python_keys("pssnet_testing", "exec_depend")


@pytest.mark.skipif(importlib.util.find_spec("rclpy") is None, reason="needs rclpy (the node's imports)")
def test_what_the_node_loads_is_an_exec_depend():
    """Imports the node and `pssnet bag` in a fresh interpreter: the Python keys among the exec_depends of
    pssnet_core and pssnet_ros are exactly those of the modules each imports that the node loads (the rest of a
    package's libraries are test_depends)."""
    code = (f"import importlib, sys\nfor m in {RUNTIME_MODULES!r}: importlib.import_module(m)\n"
            "print(' '.join(sorted({n.split('.')[0] for n in sys.modules})))")
    loaded = set(subprocess.run([sys.executable, "-c", code], check=True, capture_output=True, text=True,
                                timeout=120).stdout.split())
    assert {"torch", "open3d", "cv2", "rosbags", "rclpy"} <= loaded
    assert not loaded & NO_KEY, f"the node loads modules without a rosdep key: {loaded & NO_KEY}"
    assert "pssnet_testing" not in loaded
    needed = {KEY_OF_MODULE[m] for m in loaded if m in KEY_OF_MODULE}
    exec_keys = {}
    for package in ("pssnet_core", "pssnet_ros"):
        exec_keys[package] = python_keys(package, "exec_depend")
        imports = {KEY_OF_MODULE[m] for m in third_party_imports(module_files(package)) & loaded if m in KEY_OF_MODULE}
        assert imports - exec_keys[package] == set(), f"{package}: the node loads these, but they are not exec_depend"
        assert exec_keys[package] - imports == set(), f"{package}: exec_depend, but the node does not load it"
    assert needed == exec_keys["pssnet_core"] | exec_keys["pssnet_ros"], "loaded, but no package imports it"


def test_license_file_matches_package_xml():
    for package in OWN:  # each package carries its license file
        assert ET.parse(ROOT / package / "package.xml").getroot().findtext("license") == "BSD-3-Clause"
        assert (ROOT / package / "LICENSE").read_text() == (ROOT / "LICENSE").read_text()
    text = (ROOT / "LICENSE").read_text()
    assert text.startswith("BSD 3-Clause License\n") and "Copyright (c) 2026, PSSNet-ROS contributors" in text
    assert "Neither the name of the copyright holder nor the names of its" in text


# ------------------------------------------------------------------------- requirements-runtime.txt
#: rosdep key -> the PyPI distribution requirements-runtime.txt installs for it
PIP_OF_KEY = {"python3-numpy": "numpy", "python3-scipy": "scipy", "python3-yaml": "pyyaml",
              "python3-opencv": "opencv-python-headless", "python3-tqdm": "tqdm", "python3-torch": "torch",
              "python3-open3d-pip": "open3d-cpu", "python3-rosbags-pip": "rosbags"}
#: development, test, training and evaluation packages of requirements.txt: never on the robot
NOT_RUNTIME = ("ros-jazzy-", "colcon", "ruff", "pytest", "hypothesis", "ray", "mujoco", "coacd", "manifold3d",
               "trimesh", "matplotlib", "scikit-image", "setuptools")


def pins(path: Path) -> dict[str, str]:
    """Distribution name (lower case, extras dropped) -> the rest of the line, e.g. '==1.26.4'."""
    result = {}
    for line in path.read_text().splitlines():
        line = line.split("#")[0].strip()
        if line:
            match = re.match(r"([A-Za-z0-9_.-]+)(\[[^]]*\])?\s*(.*)", line)
            result[match.group(1).lower()] = match.group(3)
    return result


def test_runtime_requirements_fit_an_apt_jazzy_robot():
    runtime, development = pins(ROOT / "requirements-runtime.txt"), pins(ROOT / "requirements.txt")
    assert runtime["numpy"].startswith("==1.26."), "Jazzy's message packages are built against numpy 1.x"
    assert not [name for name in runtime if name.startswith(NOT_RUNTIME)], "a ROS wheel or a development package"
    exec_keys = python_keys("pssnet_core", "exec_depend") | python_keys("pssnet_ros", "exec_depend")
    assert set(PIP_OF_KEY) == exec_keys, "PIP_OF_KEY must name the pip package of every Python exec_depend"
    assert set(runtime) == set(PIP_OF_KEY.values()), "requirements-runtime.txt is the exec_depends, by pip name"
    for name, spec in runtime.items():
        assert spec.startswith("=="), f"{name} is not pinned"
        if name != "numpy":
            assert development.get(name) == spec, f"{name}{spec}, but requirements.txt has {development.get(name)}"

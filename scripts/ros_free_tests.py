"""Prints the test files that need no ROS 2: neither they nor the repository modules they import load rclpy,
a message package or launch. `make test-py312` runs them on Python 3.12 with numpy 1.26, without ROS.

A test file counts as ROS when any of its imports (also those inside test functions) reaches a ROS module;
a repository module counts as ROS when its module-level imports do (imports inside its functions run only
when those functions do, as `pssnet_ros.bag_cli`'s import of `pssnet_ros.bag`).

Usage: python scripts/ros_free_tests.py [--ros]   (--ros: print the other files instead)
"""

from __future__ import annotations

import ast
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
TEST = ROOT / "test"
ROS_MODULES = ("rclpy", "launch", "launch_ros", "ament_index_python", "rosidl_runtime_py", "builtin_interfaces")
ROS_SUFFIXES = ("_msgs", "_srvs", "_interfaces")


def is_ros(module: str) -> bool:
    top = module.split(".")[0]
    return top in ROS_MODULES or top.endswith(ROS_SUFFIXES)


def source_of(module: str) -> Path | None:
    """The repository file of a module (package, submodule, or a helper beside the tests), or None."""
    parts = module.split(".")
    for base in (ROOT / "pssnet_core", ROOT / "pssnet_ros", ROOT / "pssnet_testing", TEST):
        path = base.joinpath(*parts)
        for candidate in (path.with_suffix(".py"), path / "__init__.py"):
            if candidate.is_file():
                return candidate
    return None


def imports(path: Path, module_level_only: bool) -> set[str]:
    """Absolute module names a file imports ('from a.b import c' gives a.b and a.b.c)."""
    tree = ast.parse(path.read_text())
    nodes = tree.body if module_level_only else list(ast.walk(tree))
    if module_level_only:  # module-level also covers `if`/`try` blocks at the top, but not TYPE_CHECKING ones
        nodes = [n for top in tree.body if not _type_checking(top) for n in _shallow(top)]
    names: set[str] = set()
    for node in nodes:
        if isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            names.add(node.module)
            names.update(f"{node.module}.{alias.name}" for alias in node.names)
    return names


def _type_checking(node: ast.stmt) -> bool:
    return isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test)


def _shallow(node: ast.stmt) -> list[ast.AST]:
    """A statement and, for if/try/with blocks, the statements nested in them (not function bodies)."""
    if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef | ast.ClassDef):
        return [node]
    out: list[ast.AST] = [node]
    for child in ast.iter_child_nodes(node):
        if isinstance(child, ast.stmt):
            out.extend(_shallow(child))
        elif isinstance(child, ast.ExceptHandler):
            for stmt in child.body:
                out.extend(_shallow(stmt))
    return out


def reaches_ros(modules: set[str]) -> bool:
    """Whether importing these modules loads a ROS module (through the repository's module-level imports)."""
    seen: set[str] = set()
    todo = list(modules)
    while todo:
        module = todo.pop()
        if module in seen:
            continue
        seen.add(module)
        if is_ros(module):
            return True
        parent = module.rpartition(".")[0]
        if parent:  # importing a.b runs a/__init__.py first
            todo.append(parent)
        path = source_of(module)
        if path is not None:
            todo.extend(imports(path, module_level_only=True))
    return False


def main(argv: list[str]) -> int:
    want_ros = "--ros" in argv
    for path in sorted(TEST.glob("test_*.py")):
        ros = reaches_ros(imports(path, module_level_only=False))
        if ros == want_ros:
            print(path.relative_to(ROOT))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))

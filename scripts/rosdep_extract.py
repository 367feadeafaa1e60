"""Writes test/data/rosdep_keys.yaml: the rosdistro entries of every dependency the packages' package.xml files name.

Usage (ROSDISTRO: a clone of github.com/ros/rosdistro, bare or not; REV: the commit to read, default HEAD):

    python scripts/rosdep_extract.py ROSDISTRO [--rev REV] [--out test/data/rosdep_keys.yaml]

A name found in neither rosdep/base.yaml, rosdep/python.yaml nor the distribution's released packages is left
out (and printed), so test/test_package_xml.py fails until package.xml names a key that exists.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parents[1]
#: one package per folder of the repository root (pssnet_core, pssnet_interfaces, pssnet_ros, pssnet_testing)
PACKAGE_XMLS = tuple(sorted(ROOT.glob("*/package.xml")))
DEPEND_TAGS = ("depend", "build_depend", "buildtool_depend", "build_export_depend", "exec_depend", "test_depend",
               "doc_depend")
ROSDEP_FILES = ("rosdep/base.yaml", "rosdep/python.yaml")
DISTRO = "jazzy"
#: The platforms whose rules are copied (the distribution's release platforms of Ubuntu and Debian).
PLATFORMS = ("ubuntu", "debian")


def declared_names() -> tuple[set[str], set[str]]:
    """(every dependency name in the package.xml files, the names of the packages they define)."""
    names: set[str] = set()
    own: set[str] = set()
    for path in PACKAGE_XMLS:
        root = ET.parse(path).getroot()
        own.add(root.findtext("name"))
        for tag in DEPEND_TAGS:
            names.update(e.text.strip() for e in root.iter(tag))
    return names, own


def show(repo: Path, rev: str, path: str) -> str:
    return subprocess.run(["git", "-C", str(repo), "show", f"{rev}:{path}"], check=True, capture_output=True,
                          text=True).stdout


def released_packages(distribution: dict) -> dict[str, str]:
    """Package name -> release repository, for every package the distribution releases."""
    packages: dict[str, str] = {}
    for repo_name, repo in distribution["repositories"].items():
        release = repo.get("release")
        if release is None:
            continue
        for name in release.get("packages", [repo_name]):
            packages[name] = repo_name
    return packages


def extract(repo: Path, rev: str) -> tuple[dict, list[str]]:
    commit = subprocess.run(["git", "-C", str(repo), "rev-parse", rev], check=True, capture_output=True,
                            text=True).stdout.strip()
    date = subprocess.run(["git", "-C", str(repo), "show", "-s", "--format=%cI", commit], check=True,
                          capture_output=True, text=True).stdout.strip()
    rules = {path: yaml.safe_load(show(repo, commit, path)) for path in ROSDEP_FILES}
    distribution = yaml.safe_load(show(repo, commit, f"{DISTRO}/distribution.yaml"))
    released = released_packages(distribution)
    names, own = declared_names()
    keys: dict[str, dict] = {}
    packages: dict[str, str] = {}
    missing: list[str] = []
    for name in sorted(names - own):
        for path, table in rules.items():
            if name in table:
                keys[name] = {"file": path} | {p: table[name].get(p) for p in PLATFORMS}
                break
        else:
            if name in released:
                packages[name] = released[name]
            else:
                missing.append(name)
    data = {
        "rosdistro_commit": commit,
        "rosdistro_commit_date": date,
        "distro": DISTRO,
        "release_platforms": {p: distribution["release_platforms"].get(p, []) for p in PLATFORMS},
        "rosdep_keys": keys,
        "released_packages": packages,
    }
    return data, missing


HEADER = """\
# The rosdistro entries of every dependency named in the packages' package.xml files (*/package.xml): rosdep keys
# (rosdep/base.yaml, rosdep/python.yaml; the Ubuntu and Debian rules only) and the ROS packages the {distro}
# distribution releases (package -> release repository). test/test_package_xml.py fails when a package.xml
# names a dependency that is not here, or a key that resolves to nothing on the release platforms.
# Copied from github.com/ros/rosdistro at the commit below. To refresh (after adding a dependency, or to
# re-check against a newer rosdistro), from the repository root:
#   git clone https://github.com/ros/rosdistro /tmp/rosdistro
#   python scripts/rosdep_extract.py /tmp/rosdistro
"""


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("rosdistro", type=Path, help="a git clone of ros/rosdistro (bare or not)")
    parser.add_argument("--rev", default="HEAD", help="the rosdistro commit to read")
    parser.add_argument("--out", type=Path, default=ROOT / "test" / "data" / "rosdep_keys.yaml")
    args = parser.parse_args(argv)
    data, missing = extract(args.rosdistro, args.rev)
    args.out.write_text(HEADER.format(distro=DISTRO) + yaml.safe_dump(data, sort_keys=False, width=120))
    print(f"wrote {args.out}: {len(data['rosdep_keys'])} rosdep keys, {len(data['released_packages'])} ROS packages")
    if missing:
        print(f"not in rosdistro (fix package.xml): {', '.join(missing)}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())

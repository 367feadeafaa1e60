"""What runs record about the code that made them (pssnet_core.provenance)."""

from __future__ import annotations

import subprocess

from pssnet_core import provenance


def test_code_version_is_the_commit_and_dirty_only_when_the_package_itself_changed(tmp_path, monkeypatch):
    repo = tmp_path / "repo"
    package = repo / "pssnet_core"
    package.mkdir(parents=True)
    (package / "module.py").write_text("x = 1\n")
    (repo / "notes.md").write_text("a\n")

    def git(*args: str) -> str:
        return subprocess.run(["git", "-C", str(repo), *args], check=True, capture_output=True, text=True).stdout

    git("init", "-q")
    git("add", ".")
    git("-c", "user.name=t", "-c", "user.email=t@t", "commit", "-qm", "first")
    commit = git("rev-parse", "--short=12", "HEAD").strip()
    monkeypatch.setattr(provenance, "PACKAGE_DIR", package)
    assert provenance.code_version() == f"git {commit}"
    (repo / "notes.md").write_text("b\n")  # results and notes edited beside a run
    (package / "scratch.py").write_text("")  # an untracked file
    assert provenance.code_version() == f"git {commit}"
    (package / "module.py").write_text("x = 2\n")
    assert provenance.code_version() == f"git {commit}-dirty"


def test_code_version_outside_a_work_tree_is_the_installed_version(tmp_path, monkeypatch):
    monkeypatch.setattr(provenance, "PACKAGE_DIR", tmp_path)
    monkeypatch.setenv("GIT_CEILING_DIRECTORIES", str(tmp_path.parent))
    assert subprocess.run(["git", "-C", str(tmp_path), "rev-parse", "HEAD"], capture_output=True).returncode != 0
    version = provenance.code_version()
    assert version.startswith("pssnet_core ") or version == "unknown"

"""What an experiment's output files must say about the code and machine that made them.

Runs are made over many commits and resumed across sessions; a results folder that records only its command
cannot say which sampler defaults a run had, nor whether it mixed two versions of the code. Each evaluation
command writes ``methods.json`` (:func:`method_settings` of every method) and each grasp-trial invocation appends
a line to ``provenance.jsonl`` (:func:`invocation`).
"""

from __future__ import annotations

import platform
import subprocess
import time
from dataclasses import asdict
from importlib import metadata
from pathlib import Path
from typing import Any

from pssnet_core.bench import cpu_kind

PACKAGE_DIR = Path(__file__).resolve().parent


def code_version() -> str:
    """``git <commit>`` of the checkout this package runs from, ``-dirty`` when the package's own files differ from
    it (results and notes edited beside a run do not count), or the installed package's version where it is not a
    git work tree (a wheel, a colcon install)."""
    def git(*args: str) -> str | None:
        try:
            done = subprocess.run(["git", "-C", str(PACKAGE_DIR), *args], capture_output=True, text=True, timeout=10,
                                  check=False)
        except (OSError, subprocess.TimeoutExpired):
            return None
        return done.stdout.strip() if done.returncode == 0 else None

    commit = git("rev-parse", "--short=12", "HEAD")
    if commit:
        changed = git("status", "--porcelain", "--untracked-files=no", "--", ".")
        return f"git {commit}" + ("-dirty" if changed else "")
    try:
        return f"pssnet_core {metadata.version('pssnet_core')}"
    except metadata.PackageNotFoundError:
        return "unknown"


def method_settings(completer: Any) -> dict[str, Any]:
    """What decides a completer's samples: its checkpoint, sampler (with every checked-sampler parameter, defaults
    included), box temperature and number format. ``completer``: a :class:`pssnet_core.inference.Completer` or a
    :class:`pssnet_core.sampling.CheckedSampler`."""
    from pssnet_core.sampling import CheckedSampler

    checked = isinstance(completer, CheckedSampler)
    model = completer.completer if checked else completer
    settings: dict[str, Any] = {"checkpoint": model.info.get("path"), "model": model.model_name,
                                "sampler": "checked" if checked else "posterior",
                                "box_temperature": float(model.box_temperature), "precision": model.precision,
                                "device": str(model.device)}
    if checked:
        settings["checked_sampler"] = asdict(completer.sampler_config)
    return settings


def invocation(**settings: Any) -> dict[str, Any]:
    """One command's record: the code version, the machine, torch's version, the time, and ``settings``."""
    import torch

    return {"code": code_version(), "cpu": cpu_kind(), "python": platform.python_version(),
            "torch": torch.__version__, "started": time.strftime("%Y-%m-%dT%H:%M:%S%z"), **settings}

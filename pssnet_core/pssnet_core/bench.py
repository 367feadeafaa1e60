"""The machine description every benchmark prints with its numbers (the scripts are in the repository's
benchmarks/ folder: tools for developers, run from a source checkout as ``python benchmarks/NAME.py``, and not
part of the installed package).

It lives in the ROS-free core, not in the ROS test harness (pssnet_testing), because most benchmarks need no ROS
and must run where only pssnet_core is installed (e.g. a lent GPU machine without ROS).
"""

from __future__ import annotations

from pathlib import Path


def cpu_kind() -> str:
    """The CPU's model name (lscpu's "Model name", from /proc/cpuinfo) and whether it has AVX512-BF16 / AMX."""
    try:
        text = Path("/proc/cpuinfo").read_text()
    except OSError:
        return "unknown CPU"
    fields = dict(line.split(":", 1) for line in text.splitlines() if ":" in line)
    fields = {k.strip(): v.strip() for k, v in fields.items()}
    flags = set(fields.get("flags", "").split())
    kind = f"{fields.get('model name', 'unknown CPU')}, avx512_bf16 {'present' if 'avx512_bf16' in flags else 'absent'}"
    return kind + (", amx_bf16 present" if "amx_bf16" in flags else "")

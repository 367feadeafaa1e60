"""Fixtures shared by several test modules (opt-in by name), and the Hypothesis profiles of the fuzz suites."""

from __future__ import annotations

import os
from collections.abc import Iterator

import pytest
import torch
from hypothesis import settings

# Hypothesis profiles (test/test_fuzz_*.py), chosen with HYPOTHESIS_PROFILE (default "ci"):
# - "ci": derandomized, so every CI run draws the same examples: a red CI means a change broke something, never
#   that a new random draw happened to find an old bug. No example database, so nothing a developer's earlier
#   runs saved changes what CI tests. Few examples keep the default run short; no deadline, because a shared
#   2-core machine makes single-example timings meaningless.
# - "fuzz": random, many examples, with the example database (.hypothesis/) so that a failure found once is
#   replayed first next time: HYPOTHESIS_PROFILE=fuzz .venv/bin/pytest -q test/test_fuzz_*.py
settings.register_profile("ci", derandomize=True, database=None, max_examples=100, deadline=None,
                          print_blob=True)
settings.register_profile("fuzz", max_examples=3000, deadline=None, print_blob=True)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "ci"))


@pytest.fixture
def one_torch_thread() -> Iterator[None]:
    """Tiny models run fastest (and reproducibly) on one thread; restores the caller's setting."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)

"""Smoke run of benchmarks/fuzz_bench.py against the real node: 50 fuzzed requests and 50 fuzzed topic messages.

The full run (10,000 of each, RELIABILITY.md) takes minutes; this one (~10 s) keeps the benchmark working and the
node's answer to every kind of malformed input in CI. RSS growth is not checked here: a 20-request warm-up does
not reach the allocator's high-water mark, so a short run's growth says nothing about leaks.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
from test_node_helpers import domain_for

from pssnet_testing.processes import ros_env

pytestmark = pytest.mark.ros
BENCHMARK = Path(__file__).resolve().parents[1] / "benchmarks" / "fuzz_bench.py"


def test_node_answers_every_fuzzed_request_and_survives_fuzzed_topics(tmp_path: Path):
    domain = domain_for(21)
    numbers_path = tmp_path / "fuzz.json"
    run = subprocess.run([sys.executable, str(BENCHMARK), "--requests", "50", "--messages", "50", "--warm-up", "20",
                          "--seed", "0", "--domain-id", str(domain), "--json", str(numbers_path)],
                         env=ros_env(domain), capture_output=True, text=True, timeout=180)
    assert numbers_path.is_file(), f"benchmark exited {run.returncode} without numbers:\n{run.stdout[-4000:]}"
    numbers = json.loads(numbers_path.read_text())
    assert numbers["requests_sent"] == numbers["answered"] == 50, run.stdout[-4000:]
    assert numbers["unanswered"] == 0 and numbers["node_crashes"] == 0
    assert numbers["unexpected_outcomes"] == [], "a valid request was refused or a corrupt one completed"
    assert numbers["succeeded"] > 0 and numbers["refused"] > 0
    assert numbers["topic_messages_sent"] >= 50 and numbers["node_counters"]["messages_received"] > 0
    assert numbers["final_request_succeeded"] and numbers["node_exit_code"] == 0

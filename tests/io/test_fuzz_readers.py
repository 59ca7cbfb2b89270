"""A short run of benchmarks/fuzz.py in CI: random and mutated inputs to the WitMotion and
Livox parsers and the rosbag and EuRoC readers raise nothing but JaxSlamError. The long run
(100k inputs per target) is ``python benchmarks/fuzz.py``."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import pytest

_PATH = Path(__file__).resolve().parents[2] / "benchmarks" / "fuzz.py"
_spec = importlib.util.spec_from_file_location("jaxslam_fuzz", _PATH)
fuzz = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(fuzz)


@pytest.mark.parametrize(
    ("target", "count"),
    [
        ("witmotion", 3000),
        ("livox", 3000),
        ("rosbag", 400),
        ("euroc", 1500),
    ],
)
def test_fuzz_only_jaxslam_errors(target, count):
    tally = fuzz.run_target(target, count, seed=123)
    assert tally.counts["inputs"] == count
    other = {m: n for m, n in tally.errors.items() if m.startswith("OTHER")}
    assert tally.counts["other"] == 0, other
    if target in ("livox", "rosbag", "euroc"):
        assert tally.counts["jaxslam_error"] > 0 and tally.counts["ok"] > 0  # both paths exercised

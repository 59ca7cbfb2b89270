"""``benchmarks/op_profile.py``: per-op times read back from a ``jax.profiler`` trace."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import jax
import jax.numpy as jnp
import pytest

_PATH = Path(__file__).resolve().parents[1] / "benchmarks" / "op_profile.py"
_spec = importlib.util.spec_from_file_location("jaxslam_op_profile", _PATH)
op_profile = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(op_profile)


def test_ops_are_summed_per_call_from_the_trace() -> None:
    x = jnp.arange(512 * 512, dtype=jnp.float64).reshape(512, 512) / 1e5
    f = jax.jit(lambda a: jnp.tanh(a @ a.T).sum())
    prof = op_profile.op_profile(lambda: f(x), repeats=3)
    assert prof["repeats"] == 3 and prof["wall_ms_per_call"] > 0
    ops = prof["ops"]
    assert ops and all(op["ms_per_call"] >= 0 for op in ops)
    assert [op["ms_per_call"] for op in ops] == sorted((op["ms_per_call"] for op in ops), reverse=True)
    # the product runs once per call, as one op of XLA's program
    dots = [op for op in ops if "dot" in op["name"] or "ynn" in op["name"] or "fusion" in op["name"]]
    assert dots and any(op["count_per_call"] == 1.0 for op in dots)


def test_unknown_target_is_one_line() -> None:
    with pytest.raises(SystemExit, match="unknown target 'nope'"):
        op_profile.kernel("nope")

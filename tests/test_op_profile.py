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


def test_loop_kinds_read_the_llvm_ir_dump(tmp_path: Path) -> None:
    vector = "\n".join(
        [
            "vector.body:",
            "  %a = load <8 x float>, ptr %p, align 4",
            "  %b = fmul <8 x float> %a, %a",
            "  %c = fadd <8 x float> %b, %a",
            "  store <8 x float> %c, ptr %q, align 4",
        ]
    )
    scalar = "\n".join(["  %a = load float, ptr %p, align 4", "  %b = fmul float %a, %a", "  store float %b, ptr %q"])
    assert op_profile.loop_kind(vector) == "vector"
    assert op_profile.loop_kind(scalar) == "scalar"
    # one file per fused op and program; the program with the most kernels wins a shared name
    (tmp_path / "module_0002.jit_main.fusion.3_kernel_module.ir-with-opt.ll").write_text(vector)
    (tmp_path / "module_0002.jit_main.fusion_kernel_module.ir-with-opt.ll").write_text(scalar)
    (tmp_path / "module_0004.jit_join.fusion.3_kernel_module.ir-with-opt.ll").write_text(scalar)
    (tmp_path / "module_0002.jit_main.fusion.3_kernel_module.ir-no-opt.ll").write_text(scalar)
    assert op_profile.loop_kinds(tmp_path) == {"fusion.3": "vector", "fusion": "scalar"}


def test_loops_flag_refuses_a_started_backend() -> None:
    jax.block_until_ready(jnp.ones(3) + 1)
    with pytest.raises(SystemExit, match="before JAX starts"):
        op_profile.main(["imu", "--loops"])

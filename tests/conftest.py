"""Shared test setup: strict JAX numerics (STYLE 12), the GTSAM oracle, random numbers.

Every test runs in float64 with ``jax_numpy_rank_promotion="raise"``, so an implicit
rank-broadcast in library code fails loudly here instead of hiding a shape bug.
"""

from __future__ import annotations

import os
from pathlib import Path

# The CLI keeps compiled programs on disk; tests call it in-process, so keep the test
# session's JAX configuration untouched (a test checks the cache in a subprocess).
os.environ["JAXSLAM_CACHE_DIR"] = ""

import atexit
import importlib
import shutil
import tempfile

import jax
import numpy as np
import pytest

jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_rank_promotion", "raise")

# One persistent compilation cache per test session (a fresh temporary folder, removed at
# exit): many tests build the same programs from new closures (an estimator, a solver or a
# tuner per test), which JAX's in-memory caches key by function identity and compile again;
# the on-disk cache keys by the program itself, so each distinct program compiles once per
# session. Results are unchanged (the same executable), and nothing outlives the session.
# Under pytest-xdist the workers share the controller's folder (they inherit its
# environment), so a program compiled by one worker is read by the other; only the process
# that made the folder removes it.
_CACHE_DIR = os.environ.get("JAXSLAM_TEST_JIT_DIR", "")
if not _CACHE_DIR or not os.path.isdir(_CACHE_DIR):
    _CACHE_DIR = tempfile.mkdtemp(prefix="jaxslam-test-jit-")
    os.environ["JAXSLAM_TEST_JIT_DIR"] = _CACHE_DIR
    atexit.register(shutil.rmtree, _CACHE_DIR, ignore_errors=True)
jax.config.update("jax_compilation_cache_dir", _CACHE_DIR)
jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.2)


def _import_gtsam():
    try:
        return importlib.import_module("gtsam")
    except ImportError:  # pragma: no cover - gtsam is a dev dependency
        return None


_GTSAM = _import_gtsam()


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """Tests marked ``gtsam`` skip cleanly (with a reason) when the wheel is missing."""
    if _GTSAM is not None:
        return
    skip = pytest.mark.skip(reason="gtsam is not importable (pip install gtsam==4.3.0)")
    for item in items:
        if item.get_closest_marker("gtsam") is not None:
            item.add_marker(skip)


@pytest.fixture(scope="session")
def gtsam():
    """The gtsam module (the oracle); skips the test when it cannot be imported."""
    if _GTSAM is None:
        pytest.skip("gtsam is not importable (pip install gtsam==4.3.0)")
    return _GTSAM


# Compile options for test-only jit: XLA's LLVM optimisation passes dominate compile time
# for the large, run-once graphs tests build (vmapped Jacobians); they do not change
# float64 results.
FAST_COMPILE = {"xla_backend_optimization_level": 0}


def fast_jit(fun):
    """``jax.jit(fun)`` compiled with :data:`FAST_COMPILE`, once per argument signature."""
    jitted = jax.jit(fun)
    compiled = {}

    def call(*args):
        leaves, tree = jax.tree.flatten(args)
        key = (tree, tuple((np.shape(x), np.result_type(x)) for x in leaves))
        if key not in compiled:
            compiled[key] = jitted.lower(*args).compile(compiler_options=FAST_COMPILE)
        return compiled[key](*args)

    return call


@pytest.fixture(scope="session", name="fast_jit")
def fast_jit_fixture():
    """:func:`fast_jit` as a fixture: jit for run-once test computations."""
    return fast_jit


@pytest.fixture
def rng() -> np.random.Generator:
    """A fresh, seeded generator per test: tests do not depend on their order."""
    return np.random.default_rng(20240601)


@pytest.fixture(scope="module")
def module_rng() -> np.random.Generator:
    """A seeded generator for module-scoped fixtures."""
    return np.random.default_rng(7)


@pytest.fixture(scope="session")
def short_tunnel_bag(tmp_path_factory) -> Path:
    """A short simulated tunnel recording (4 m out and back, ~18 s, ROS1 bag with its
    ``.rig.yaml`` beside it), made once per session: the estimator's and the tuner's end-to-end
    tests read it (read-only; tests that damage a recording copy it first)."""
    from jaxslam.sim import SimConfig, TunnelConfig, simulate_tunnel

    path = tmp_path_factory.mktemp("short-tunnel") / "short.bag"
    simulate_tunnel(SimConfig(seed=3, tunnel=TunnelConfig(length=4.0)), path, fmt="bag")
    return path

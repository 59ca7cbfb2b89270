"""Sharding training sequences across JAX devices (``TuneConfig.devices``): on this CPU-only
machine two host devices are forced in a subprocess (``XLA_FLAGS`` must be set before JAX
starts), and the sharded tuning must equal the one-device tuning while each sequence's
arrays live on its own device."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap

import jax
import pytest

from jaxslam.errors import ConfigError, SolverError
from jaxslam.tune import Shards

_SCRIPT = textwrap.dedent(
    """
    import json, os
    os.environ["XLA_FLAGS"] = "--xla_force_host_platform_device_count=2"
    import jax, jax.numpy as jnp, numpy as np
    # the test session's compilation cache: the two-device tuning's programs on the first
    # device are the one-device tuning's, which this process already compiled
    jax.config.update("jax_compilation_cache_dir", os.environ["JAXSLAM_TEST_JIT_DIR"])
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.2)
    import jaxslam
    from jaxslam.core import Pose3Var
    from jaxslam.tune import GROUPS, DifferentiableSolver, Shards, TuneConfig, tune_graphs, tunnel_capture
    from jaxslam.tune._tune import factor_fn_for

    runs = [tunnel_capture(s, 30.0, length=12.0) for s in (1, 2, 3)]
    one = tune_graphs(runs, TuneConfig(steps=3, devices=1))
    two = tune_graphs(runs, TuneConfig(steps=3, devices=2))
    rnd1 = tune_graphs(runs, TuneConfig(steps=3, devices=1, search="random"))
    rnd2 = tune_graphs(runs, TuneConfig(steps=3, devices=2, search="random"))
    sh = Shards(3, 0)
    th = jnp.zeros(len(GROUPS)).at[GROUPS.index("lidar.translation")].set(0.5)
    solvers = sh.map(lambda i: DifferentiableSolver(factor_fn_for(runs[i]), runs[i].values, sh.put(i, th)))
    grads = sh.map(lambda i: jax.grad(lambda t: jnp.sum(solvers[i](t).params(Pose3Var)[:, 4:] ** 2))(sh.put(i, th)))
    placed = sh.map(lambda i: [str(d) for d in solvers[i](sh.put(i, th)).params(Pose3Var).devices()])
    sh.close()
    print(json.dumps({
        "devices": [str(d) for d in jax.devices()],
        "placed": placed,
        "grad_devices": [[str(d) for d in g.devices()] for g in grads],
        "theta": [one.theta.tolist(), two.theta.tolist()],
        "history": [one.history, two.history],
        "random": [rnd1.history, rnd2.history, rnd1.theta.tolist(), rnd2.theta.tolist()],
    }))
    """
)


def test_sharded_tuning_equals_one_device_and_places_each_sequence_on_its_device() -> None:
    env = {k: v for k, v in os.environ.items() if k != "XLA_FLAGS"}
    out = subprocess.run([sys.executable, "-c", _SCRIPT], capture_output=True, text=True, env=env, timeout=900)
    assert out.returncode == 0, out.stderr[-3000:]
    res = json.loads(out.stdout.strip().splitlines()[-1])
    assert len(res["devices"]) == 2
    # round-robin: sequences 0 and 2 on the first device, 1 on the second
    assert [p[0] for p in res["placed"]] == [res["devices"][0], res["devices"][1], res["devices"][0]]
    assert all(len(p) == 1 for p in res["placed"])
    assert [g[0] for g in res["grad_devices"]] == [p[0] for p in res["placed"]]
    h1, h2 = res["history"]
    assert len(h1) == len(h2) >= 2
    assert h1[-1] < h1[0]  # the tuning did something
    for a, b in zip(h1, h2):
        assert b == pytest.approx(a, rel=1e-9)
    for a, b in zip(*res["theta"]):
        assert b == pytest.approx(a, rel=1e-7, abs=1e-9)
    r1, r2, t1, t2 = res["random"]
    assert r2 == pytest.approx(r1, rel=1e-9)
    assert t2 == pytest.approx(t1, rel=1e-12, abs=1e-12)


def test_shards_keep_order_and_hand_back_errors() -> None:
    sh = Shards(5, 0)
    try:

        def fn(i: int) -> int:
            if i == 3:
                raise SolverError("no convergence")
            return i * i

        out = sh.map(fn)
    finally:
        sh.close()
    assert out[:3] == [0, 1, 4] and out[4] == 16
    assert isinstance(out[3], SolverError)
    assert sh.device_of(0) == jax.local_devices()[0]


@pytest.mark.parametrize("devices", [-1, 10_000])
def test_shards_refuse_a_device_count_jax_does_not_have(devices: int) -> None:
    with pytest.raises(ConfigError, match="devices"):
        Shards(2, devices)

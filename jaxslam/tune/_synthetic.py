"""A captured graph without a recording: the simulator's tunnel pose graph with wrong
odometry weights, for trying :func:`jaxslam.tune.tune_graphs` (tests, the sharding benchmark)."""

from __future__ import annotations

from collections.abc import Sequence

import jax.numpy as jnp
import numpy as np

from ..core import Cauchy, Gaussian, Pose3Var, Values
from ..factors import BetweenFactor, PriorFactor
from ..lie import SE3
from ..sim import tunnel_pose_graph
from ._tune import Captured


def tunnel_capture(
    seed: int,
    odo_overtrust: float = 1.0,
    lever: Sequence[float] = (0.0, 0.0, 0.0),
    length: float = 30.0,
    step: float = 0.5,
) -> Captured:
    """A tunnel pose graph (``length`` m out and back, a keyframe every ``step`` m) whose
    odometry (kind ``lidar``) is trusted ``odo_overtrust`` times too much in translation and
    whose loops (kind ``loop``, Cauchy) have their true sigmas; the truth is the prism at
    ``lever`` on each body, surveyed in a frame rigidly moved away from the estimate's. The
    initial values are the true poses."""
    g = tunnel_pose_graph(length=length, step=step, seed=seed, odom_sigma=(0.002, 0.02), loop_sigma=(0.005, 0.01))
    n = len(g.ground_truth)
    odo = ~g.is_loop
    sig_odo = np.array([0.002] * 3 + [0.02 / odo_overtrust] * 3)
    sig_loop = np.array([0.005] * 3 + [0.01] * 3)
    lidar = BetweenFactor.create(
        Pose3Var(g.edges_i[odo]),
        Pose3Var(g.edges_j[odo]),
        SE3(jnp.asarray(g.measured[odo])),
        Gaussian.diagonal(jnp.asarray(sig_odo), n=int(odo.sum())),
    )
    loop = BetweenFactor.create(
        Pose3Var(g.edges_i[g.is_loop]),
        Pose3Var(g.edges_j[g.is_loop]),
        SE3(jnp.asarray(g.measured[g.is_loop])),
        Gaussian.diagonal(jnp.asarray(sig_loop), n=int(g.is_loop.sum())),
        robust=Cauchy(1.0),
    )
    prior = PriorFactor.create(
        Pose3Var(np.array([0])), SE3(jnp.asarray(g.ground_truth[:1])), Gaussian.diagonal(jnp.full(6, 1e-3))
    )
    gt = SE3(jnp.asarray(g.ground_truth))
    truth = np.asarray(gt.act(jnp.broadcast_to(jnp.asarray(lever, dtype=jnp.float64), (n, 3))))
    # the survey lives in its own frame: a rigid motion away from the estimate's
    T = SE3.exp(jnp.array([0.1, -0.2, 0.3, 5.0, -3.0, 1.0]))
    truth = np.asarray(T.act(jnp.asarray(truth)))
    values = Values.create({Pose3Var(np.arange(n)): gt})
    return Captured(
        f"seed{seed}", {"lidar": [lidar], "loop": [loop]}, [prior], values, np.arange(n), truth, np.asarray(lever), "x"
    )

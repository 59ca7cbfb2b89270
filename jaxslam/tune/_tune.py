"""``jaxslam tune``: learn the estimator's relative noise weights from surveyed trajectories.

Data flow (one *round*; ``rounds`` repeat it, since the front end's gates depend on the
weights)::

    training recordings ──Estimator (current config)──▶ final factor graph, every factor
        tagged by kind (imu, bias, lidar, vision, loop, prior), + its optimum
        + ground truth at the keyframes: full poses, or total-station prism positions
          (interpolated to the keyframe times; the prism sits at a lever arm on the body)
    theta = log sigma multipliers per weight group ──factor_fn──▶ re-weighted graph
        ──DifferentiableSolver (optimum + adjoint gradient)──▶ loss: mean squared error of
          the SE(3)-aligned prism/body positions (APE², the alignment held fixed: by the
          envelope theorem that is the exact gradient of the aligned loss)
        ──bounded L-BFGS on theta (all sequences: a loop that reuses the compiled kernels;
          with several JAX devices the sequences are sharded across them, one host thread
          per device, each sequence's arrays committed to its device)──▶ theta
    theta ──apply_weights──▶ a new PipelineConfig (``imu.noise_scale``, the rig's bias random
        walks, ``{lidar,vision,loop}.axis_weights``) ──▶ next round
    after the last round (``select="best"``): one more run per recording with its weights;
        the start's or a round's weights, whichever whole runs fit the truth best ──▶ weights.yaml

Only relative weights matter (SPEC §6: scaling every sigma by one factor leaves the optimum
unchanged, up to the fixed priors): the common scale, which the loss hardly sees, is held
near the start by a small Tikhonov term, like every weight the loss cannot see. Held-out
recordings are run with the starting and the learned configuration and their APE reported;
they never enter the loss.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import json
import time
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from ..core import Factor, Gaussian, Pose3Var, Values
from ..errors import ConfigError, InputFormatError, SolverError
from ..lie import SE3
from ..solvers._problem import concatenate_factors
from ._implicit import DifferentiableSolver

GROUPS: tuple[str, ...] = (
    "imu",
    "bias",
    "lidar.rotation",
    "lidar.translation",
    "vision.rotation",
    "vision.translation",
    "loop.rotation",
    "loop.translation",
)
"""Weight groups: one log-sigma multiplier each (factor kind and axis group)."""

_KIND_GROUPS = {
    "imu": ("imu",),
    "bias": ("bias",),
    "lidar": ("lidar.rotation", "lidar.translation"),
    "vision": ("vision.rotation", "vision.translation"),
    "loop": ("loop.rotation", "loop.translation"),
}


@dataclasses.dataclass(frozen=True)
class TuneConfig:
    steps: int = 40
    """Loss + gradient evaluations per round (L-BFGS-B, bounded; all training graphs each)."""
    regularization: float = 0.01
    """Tikhonov weight on the log multipliers, relative to the starting loss: a multiplier
    of e costs 1 % of the starting loss, so weights the loss cannot see stay put."""
    rounds: int = 2
    """Estimator runs per training recording: after each, the graphs are re-captured with
    the weights learned so far (the front end's gates depend on them)."""
    max_log_change: float = float(np.log(100.0))
    """Bound on each log multiplier per round (100x)."""
    truth: str = "auto"
    """``poses`` (full ground-truth poses), ``positions`` (total-station prism fixes and
    ``lever_arm``), or ``auto`` (poses when the recording has them)."""
    lever_arm: tuple[float, float, float] = (0.0, 0.0, 0.0)
    """The prism's position in the body frame (m), for ``positions``."""
    max_fix_gap: float = 0.5
    """A keyframe gets a surveyed position when fixes bracket it within this (s)."""
    search: str = "gradient"
    """``gradient`` (Adam on adjoint gradients) or ``random`` (the baseline: ``steps + 1``
    log-uniform draws within ``random_range`` of the current weights, the same graph
    solves and estimator runs, the best by training loss kept)."""
    random_range: float = float(np.log(30.0))
    seed: int = 0
    select: str = "best"
    """Which configuration :func:`tune` returns: ``best`` runs the estimator once more on
    the training recordings with the last round's weights, then keeps, of the start and
    every round's weights, the one whose *whole runs* had the lowest mean aligned position
    RMSE on the training recordings (the graph loss cannot see how the front end's gates
    and predictions react to the weights; a whole run can); ``last`` keeps the last round's
    weights without that run."""
    devices: int = 0
    """JAX devices to shard the training sequences across (round-robin, one host thread per
    device): 0 = every local device, 1 = the default device only. On a CPU-only machine
    there is one device unless ``XLA_FLAGS=--xla_force_host_platform_device_count=N``."""


@dataclasses.dataclass
class Captured:
    """One training recording's final factor graph and truth at its keyframes."""

    name: str
    kinds: dict[str, list[Factor]]
    """Per weighted kind, its factors concatenated by class (a kind may hold two: visual
    odometry is a ``ScaledBetweenFactor`` or, outside the scale, a ``BetweenFactor``)."""
    fixed: list[Factor]
    values: Values
    keyframes: np.ndarray  # (M,) indices of keyframes with truth
    truth: np.ndarray  # (M, 3) surveyed points (prism or body origin)
    lever_arm: np.ndarray  # (3,)
    truth_kind: str
    ape_m: float | None = None
    run_rmse_m: float | None = None
    """The estimator run's own aligned position RMSE against this truth (before re-weighting)."""


def _interp_truth(
    kf_times: np.ndarray, t: np.ndarray, xyz: np.ndarray, max_gap: float
) -> tuple[np.ndarray, np.ndarray]:
    order = np.argsort(t)
    t, xyz = t[order], xyz[order]
    j = np.searchsorted(t, kf_times)
    ok = (j > 0) & (j < len(t))
    jj = np.clip(j, 1, max(len(t) - 1, 1))
    t0, t1 = t[jj - 1], t[jj]
    ok &= (t1 - t0) <= max_gap
    w = np.where(t1 > t0, (kf_times - t0) / np.where(t1 > t0, t1 - t0, 1.0), 0.0)[:, None]
    pts = (1 - w) * xyz[jj - 1] + w * xyz[jj]
    return np.nonzero(ok)[0], pts[ok]


def capture(est: Any, res: dict[str, Any], gt: Any, cfg: TuneConfig, name: str) -> Captured:
    """The estimator's final graph, grouped by kind, and the truth at its keyframes."""
    by_kind: dict[str, list[Factor]] = {}
    fixed: list[Factor] = []
    for kind, f in est.graph:
        (by_kind.setdefault(kind, []) if kind in _KIND_GROUPS else fixed).append(f)
    kinds = {}
    for k, v in by_kind.items():
        by_class: dict[type, list[Factor]] = {}
        for f in v:
            by_class.setdefault(type(f), []).append(f)
        kinds[k] = [concatenate_factors(fs) for fs in by_class.values()]
    times = np.asarray(res["times"])
    mode = cfg.truth
    if mode == "auto":
        mode = "poses" if gt is not None else "positions"
    if mode == "poses":
        if gt is None:
            raise InputFormatError("no ground-truth poses in the recording (try --truth positions)", name)
        gt_t = np.asarray(gt.timestamps)
        gt_xyz = np.asarray(gt.poses.params)[:, 4:]
        lever = np.zeros(3)
    elif mode == "positions":
        if not est.fixes:
            raise InputFormatError("no total-station positions in the recording", name)
        gt_t = np.array([f.t for f in est.fixes])
        gt_xyz = np.stack([f.xyz for f in est.fixes])
        lever = np.asarray(cfg.lever_arm, dtype=np.float64)
    else:
        raise ConfigError(f"truth must be auto, poses or positions, got {cfg.truth!r}")
    idx, pts = _interp_truth(times, gt_t, gt_xyz, cfg.max_fix_gap)
    if len(idx) < 3:
        raise InputFormatError(f"only {len(idx)} keyframes have ground truth (need 3)", name)
    return Captured(name, kinds, fixed, est.solver.estimate(), idx, pts, lever, mode)


def factor_fn_for(run: Captured) -> Callable[[Array_], list[Factor]]:
    """``theta (len(GROUPS),) -> factors``: each weighted kind's square-root information
    multiplied by ``exp(-theta)`` on its group's residual components (sigma x exp(theta))."""
    index = {g: i for i, g in enumerate(GROUPS)}

    def build(theta: Array_) -> list[Factor]:
        out = list(run.fixed)
        for kind, fs in run.kinds.items():
            groups = _KIND_GROUPS[kind]
            for f in fs:
                if len(groups) == 1:
                    s = jnp.full(f.noise.dim, jnp.exp(-theta[index[groups[0]]]))
                else:
                    rot, trans = (jnp.exp(-theta[index[g]]) for g in groups)
                    s = jnp.concatenate([jnp.full(3, rot), jnp.full(3, trans)])
                out.append(f.with_noise(Gaussian(f.noise.sqrt_info * s[None, None, :])))
        return out

    return build


Array_ = Any


def aligned_position_loss(x: Values, run: Captured) -> jax.Array:
    """Mean squared distance between the surveyed points and the estimate's (body origin +
    rotated lever arm), after the best rigid alignment (held fixed for the gradient)."""
    P = x.params(Pose3Var)[run.keyframes]
    pts = SE3(P).act(jnp.broadcast_to(jnp.asarray(run.lever_arm), (P.shape[0], 3)))
    R, t = _kabsch(jax.lax.stop_gradient(pts), jnp.asarray(run.truth))
    err = pts @ R.T + t[None, :] - jnp.asarray(run.truth)
    return jnp.mean(jnp.sum(err * err, axis=1))


def _kabsch(a: jax.Array, b: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Rotation and translation minimising ``|R a + t - b|^2`` (Umeyama without scale)."""
    ma, mb = a.mean(0), b.mean(0)
    u, _, vt = jnp.linalg.svd((b - mb[None, :]).T @ (a - ma[None, :]))
    d = jnp.sign(jnp.linalg.det(u @ vt))
    R = u @ jnp.diag(jnp.array([1.0, 1.0, d])) @ vt
    return R, mb - R @ ma


@dataclasses.dataclass
class GraphTuneResult:
    theta: np.ndarray
    history: list[float]
    grad_norms: list[float]
    forward_s: float
    backward_s: float


class Shards:
    """Sequences spread round-robin over JAX devices: sequence ``i`` lives on
    ``devices[i % len(devices)]``. :meth:`map` runs ``fn(i)`` for every sequence with its
    device as the default and ``theta`` committed to it, so each sequence's kernels (its
    linearisations, Hessian-vector products and VJPs: computation follows data) run there;
    one host thread per device, results in sequence order (so the sums over sequences, and
    every result, are the same however many devices share the work). The host parts of a
    solve (the sparse Cholesky) run in the device's thread."""

    def __init__(self, n: int, devices: int = 0):
        local = jax.local_devices()
        if devices < 0:
            raise ConfigError(f"devices must be >= 0 (0 = all local devices), got {devices}")
        if devices > len(local):
            raise ConfigError(f"devices={devices} but JAX sees {len(local)} local device(s): {local}")
        self.devices = local[: devices or len(local)][: max(n, 1)]
        self.n = n
        self._pool = ThreadPoolExecutor(len(self.devices), "jaxslam-shard") if len(self.devices) > 1 else None

    def device_of(self, i: int) -> Any:
        return self.devices[i % len(self.devices)]

    def map(self, fn: Callable[[int], Any]) -> list[Any]:
        """``[fn(0), ..., fn(n-1)]``, each run on its sequence's device; an exception is
        returned in its sequence's place, not raised (the caller decides)."""
        k = len(self.devices)

        def shard(d: int) -> dict[int, Any]:
            out: dict[int, Any] = {}
            with jax.default_device(self.devices[d]):
                for i in range(d, self.n, k):
                    try:
                        out[i] = fn(i)
                    except Exception as e:  # handed back to the caller
                        out[i] = e
            return out

        if self._pool is None:
            parts = [shard(0)]
        else:
            parts = list(self._pool.map(shard, range(k)))
        merged = {i: v for part in parts for i, v in part.items()}
        return [merged[i] for i in range(self.n)]

    def put(self, i: int, x: Any) -> Any:
        """``x`` committed to sequence ``i``'s device."""
        return jax.device_put(x, self.device_of(i))

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown()


def _raise_unexpected(results: list[Any], expected: tuple[type[BaseException], ...] = (SolverError,)) -> None:
    """Re-raise the first exception in ``results`` that is not ``expected``."""
    for r in results:
        if isinstance(r, BaseException) and not isinstance(r, expected):
            raise r


def tune_graphs(
    runs: Sequence[Captured],
    cfg: TuneConfig,
    progress: Callable[[int, float], None] | None = None,
) -> GraphTuneResult:
    """Bounded L-BFGS (L-BFGS-B, SciPy) on the log-sigma multipliers against the captured
    graphs (``theta = 0``: the weights they were captured with), every evaluation a forward
    solve and an adjoint gradient per graph, the graphs sharded across ``cfg.devices``
    (:class:`Shards`). L-BFGS scales its steps by the curvature it has seen; Adam (tried
    first) moves every weight at its full step whatever the size of its gradient, and drove
    weights the position loss hardly sees 100x away, which the front end then suffered from."""
    if cfg.search not in ("gradient", "random"):
        raise ConfigError(f"search must be gradient or random, got {cfg.search!r}")
    present = np.zeros(len(GROUPS), bool)
    for r in runs:
        for k in r.kinds:
            for g in _KIND_GROUPS[k]:
                present[GROUPS.index(g)] = True
    shards = Shards(len(runs), cfg.devices)
    try:
        th0 = jnp.zeros(len(GROUPS))
        built = shards.map(lambda i: DifferentiableSolver(factor_fn_for(runs[i]), runs[i].values, shards.put(i, th0)))
        _raise_unexpected(built, expected=())
        solvers: list[DifferentiableSolver] = built
        t = _Tuning(runs, solvers, shards, present)
        return (_random_search if cfg.search == "random" else _lbfgs)(t, cfg, progress)
    finally:
        shards.close()


@dataclasses.dataclass(frozen=True)
class _Tuning:
    """What both searches work on: the captured graphs, their solvers and shards, and which
    weight groups the graphs have."""

    runs: Sequence[Captured]
    solvers: list[DifferentiableSolver]
    shards: Shards
    present: np.ndarray


def _lbfgs(t: _Tuning, cfg: TuneConfig, progress: Callable[[int, float], None] | None) -> GraphTuneResult:
    runs, solvers, shards, present = t.runs, t.solvers, t.shards, t.present
    from scipy.optimize import minimize

    history: list[float] = []
    gnorms: list[float] = []
    best: list[Any] = [np.inf, np.zeros(len(GROUPS))]
    times = [0.0, 0.0]
    scale: list[float] = []

    def one(i: int, th: np.ndarray) -> tuple[float, np.ndarray, float, float]:
        r, ds = runs[i], solvers[i]
        lv, g = jax.value_and_grad(lambda t: aligned_position_loss(ds(t), r))(shards.put(i, th))
        return float(lv), np.asarray(g), ds.forward_time_s, ds.backward.time_s

    def fun(x: np.ndarray) -> tuple[float, np.ndarray]:
        if len(history) > cfg.steps:  # the evaluation budget is spent (L-BFGS-B may overrun maxfun)
            raise _BudgetSpent
        th = np.where(present, x, 0.0)
        results = shards.map(lambda i: one(i, th))
        _raise_unexpected(results)
        failed = [i for i, res in enumerate(results) if isinstance(res, SolverError)]
        if failed:  # a step into weights where a graph does not converge
            for i in failed:
                solvers[i].reset()
            return 1e3 * (scale[0] if scale else 1.0), np.zeros(len(GROUPS))
        total = 0.0
        grad = np.zeros(len(GROUPS))
        for lv, g, t_fwd, t_bwd in results:  # in sequence order: the same sums on any sharding
            total += lv / len(runs)
            grad = grad + g / len(runs)
            times[0] += t_fwd
            times[1] += t_bwd
        if not scale:
            scale.append(total)
        # Tikhonov term: a weight the loss cannot see stays where it was
        reg = cfg.regularization * scale[0]
        value = total + reg * float(np.sum(x * x))
        g_all = np.where(present, grad + 2 * reg * x, 0.0)
        history.append(total)
        gnorms.append(float(np.linalg.norm(g_all)))
        if total < best[0]:
            best[0], best[1] = total, np.where(present, x, 0.0)
        if progress is not None:
            progress(len(history) - 1, total)
        return value, g_all

    bounds = [(-cfg.max_log_change, cfg.max_log_change) if p else (0.0, 0.0) for p in present]
    with contextlib.suppress(_BudgetSpent):
        minimize(
            fun,
            np.zeros(len(GROUPS)),
            jac=True,
            method="L-BFGS-B",
            bounds=bounds,
            options={"maxfun": cfg.steps + 1, "maxiter": cfg.steps + 1},
        )
    # the best iterate by training loss (L-BFGS-B may end on a trial point)
    return GraphTuneResult(np.asarray(best[1]), history, gnorms, times[0], times[1])


class _BudgetSpent(Exception):
    pass


def _random_search(t: _Tuning, cfg: TuneConfig, progress: Callable[[int, float], None] | None) -> GraphTuneResult:
    runs, solvers, shards, present = t.runs, t.solvers, t.shards, t.present
    rng = np.random.default_rng(cfg.seed)
    best, best_loss = np.zeros(len(GROUPS)), np.inf
    history: list[float] = []
    fwd = 0.0

    def one(i: int, cand: np.ndarray) -> tuple[float, float]:
        loss = float(aligned_position_loss(solvers[i].solve(shards.put(i, cand)), runs[i]))
        return loss, solvers[i].forward_time_s

    for step in range(cfg.steps + 1):
        cand = np.zeros(len(GROUPS)) if step == 0 else rng.uniform(-cfg.random_range, cfg.random_range, len(GROUPS))
        cand = np.where(present, cand - cand[present].mean(), 0.0)
        results = shards.map(functools.partial(one, cand=cand))
        _raise_unexpected(results)
        total = 0.0
        for i, res in enumerate(results):
            if isinstance(res, SolverError):  # weights so wrong that the graph does not converge
                total = np.inf
                solvers[i].reset()
                continue
            total += res[0] / len(runs)
            fwd += res[1]
        if total < best_loss:
            best, best_loss = cand, total
        history.append(best_loss)
        if progress is not None:
            progress(step, best_loss)
    return GraphTuneResult(best, history, [], fwd, 0.0)


def apply_weights(config: Any, theta: np.ndarray) -> Any:
    """A PipelineConfig with the learned multipliers folded in (sigma x exp(theta))."""
    th = dict(zip(GROUPS, np.asarray(theta, dtype=np.float64)))
    rig = config.rig
    e = {k: float(np.exp(v)) for k, v in th.items()}
    new = config.replace(
        imu={"noise_scale": config.imu.noise_scale * e["imu"]},
        lidar={"axis_weights": _aw(config.lidar.axis_weights, e["lidar.rotation"], e["lidar.translation"])},
        vision={"axis_weights": _aw(config.vision.axis_weights, e["vision.rotation"], e["vision.translation"])},
        loop={"axis_weights": _aw(config.loop.axis_weights, e["loop.rotation"], e["loop.translation"])},
    )
    return dataclasses.replace(
        new,
        rig=dataclasses.replace(
            rig,
            accelerometer_random_walk=rig.accelerometer_random_walk * e["bias"],
            gyroscope_random_walk=rig.gyroscope_random_walk * e["bias"],
        ),
    )


def _aw(old: tuple[float, float], s_rot: float, s_trans: float) -> tuple[float, float]:
    # information weight = 1 / sigma multiplier^2
    return (float(old[0] / s_rot**2), float(old[1] / s_trans**2))


def weights_summary(config: Any) -> dict[str, Any]:
    """The tunable weights of a configuration (for reports)."""
    return {
        "imu.noise_scale": config.imu.noise_scale,
        "rig.accelerometer_random_walk": config.rig.accelerometer_random_walk,
        "rig.gyroscope_random_walk": config.rig.gyroscope_random_walk,
        "lidar.axis_weights": list(config.lidar.axis_weights),
        "vision.axis_weights": list(config.vision.axis_weights),
        "loop.axis_weights": list(config.loop.axis_weights),
    }


@dataclasses.dataclass
class TuneReport:
    config: Any
    history: list[float]
    rounds: list[dict[str, Any]]
    heldout: list[dict[str, Any]]
    estimator_runs: int
    time_s: float
    enhancement: dict[str, Any] | None = None
    selected: str = ""
    """Whose weights :attr:`config` holds: ``start`` or ``round N`` (:attr:`TuneConfig.select`)."""
    run_rmse_m: dict[str, float] = dataclasses.field(default_factory=dict)
    """Mean aligned position RMSE of the whole estimator runs on the training recordings, per
    configuration run (``start``, ``round 1``, ...; the last round's only with ``select="best"``)."""

    def to_json(self) -> dict[str, Any]:
        return {
            "enhancement": self.enhancement,
            "selected": self.selected,
            "train_run_rmse_m": self.run_rmse_m,
            "weights": weights_summary(self.config),
            "loss_history": self.history,
            "rounds": self.rounds,
            "heldout": self.heldout,
            "estimator_runs": self.estimator_runs,
            "time_s": self.time_s,
        }


def tune(
    recordings: Sequence[str | Path],
    config: Any,
    cfg: TuneConfig,
    workdir: str | Path,
    holdout: Sequence[str | Path] = (),
    log: Callable[[str], None] = print,
    bar: Callable[..., Any] | None = None,
) -> TuneReport:
    """Rounds of (estimator runs on ``recordings`` → graph tuning); then ``holdout`` runs
    with the starting and the learned configuration. ``bar(total=..., desc=...)`` makes a
    progress bar (tqdm's signature)."""
    from ..pipeline._run import run_recording

    if cfg.select not in ("best", "last"):
        raise ConfigError(f"select must be best or last, got {cfg.select!r}")
    t0 = time.perf_counter()
    work = Path(workdir)
    start = config
    history: list[float] = []
    rounds: list[dict[str, Any]] = []
    runs_done = 0
    # (whose weights: "start" / "round N", config, mean whole-run RMSE on the training recordings)
    tried: list[tuple[str, Any, float]] = []

    def run_all(config: Any, tag: str, label: str, weights: str) -> list[Captured]:
        nonlocal runs_done
        caps: list[Captured] = []
        for path in recordings:
            holder: list[Captured] = []
            name = Path(path).stem

            def keep(est: Any, res: dict[str, Any], gt: Any, _n: str = name, _h: list = holder) -> None:
                _h.append(capture(est, res, gt, cfg, _n))

            m = run_recording(path, work / tag / name, config, plots=False, on_finish=keep)
            runs_done += 1
            cap = holder[0]
            cap.ape_m = m.get("ape_rmse_m")
            cap.run_rmse_m = float(np.sqrt(aligned_position_loss(cap.values, cap)))
            caps.append(cap)
            log(
                f"{label}: {name}: {len(cap.keyframes)} keyframes with truth, APE {_f(m)}, "
                f"aligned {cap.truth_kind} RMSE {cap.run_rmse_m:.4f} m"
            )
        tried.append((weights, config, float(np.mean([c.run_rmse_m for c in caps]))))
        return caps

    for rnd in range(cfg.rounds):
        caps = run_all(config, f"round{rnd}", f"round {rnd + 1}", f"round {rnd}" if rnd else "start")
        pbar = bar(total=cfg.steps + 1, desc=f"tune round {rnd + 1}") if bar is not None else None

        def progress(step: int, loss: float, _p: Any = pbar) -> None:
            if _p is not None:
                _p.update(1)
                _p.set_postfix(loss=f"{np.sqrt(max(loss, 0.0)):.4f} m")

        try:
            res = tune_graphs(caps, cfg, progress)
        finally:
            if pbar is not None:
                pbar.close()
        history += res.history
        config = apply_weights(config, res.theta)
        rounds.append(
            {
                "train_ape_m": {c.name: c.ape_m for c in caps},
                "train_run_rmse_m": {c.name: c.run_rmse_m for c in caps},
                "graph_rmse_before_m": float(np.sqrt(res.history[0])),
                "graph_rmse_after_m": float(np.sqrt(res.history[-1])),
                "theta": dict(zip(GROUPS, res.theta.tolist())),
                "forward_s": res.forward_s,
                "backward_s": res.backward_s,
                "truth": caps[0].truth_kind,
            }
        )
        log(
            f"round {rnd + 1}: aligned RMSE on the training graphs {np.sqrt(res.history[0]):.4f} -> "
            f"{np.sqrt(res.history[-1]):.4f} m"
        )
    selected = f"round {cfg.rounds}"
    if cfg.select == "best":
        run_all(config, "validation", "validation", selected)
        selected, config, _ = min(tried, key=lambda t: t[2])
        log(
            "whole runs on the training recordings, mean aligned RMSE: "
            + ", ".join(f"{w} {v:.4f} m" for w, _, v in tried)
            + f"; keeping the weights of {selected}"
        )
    heldout = []
    for path in holdout:
        name = Path(path).stem
        row: dict[str, Any] = {"recording": str(path)}
        for label, c in (("before", start), ("after", config)):
            m = run_recording(path, work / "heldout" / label / name, c, plots=False)
            runs_done += 1
            row[f"ape_{label}_m"] = m.get("ape_rmse_m")
            row[f"registered_{label}"] = m.get("registered_frames")
        log(f"held out {name}: APE {_g(row['ape_before_m'])} -> {_g(row['ape_after_m'])} m")
        heldout.append(row)
    return TuneReport(
        config,
        history,
        rounds,
        heldout,
        runs_done,
        time.perf_counter() - t0,
        selected=selected,
        run_rmse_m={w: v for w, _, v in tried},
    )


def _f(m: dict[str, Any]) -> str:
    return _g(m.get("ape_rmse_m")) + " m"


def _g(x: Any) -> str:
    return "n/a" if x is None else f"{x:.4f}"


def sample_frame_pairs(
    recordings: Sequence[str | Path], pairs: int = 4, spacing_s: float = 2.0
) -> tuple[np.ndarray, np.ndarray]:
    """Consecutive grey camera frames ``(a, b)`` (``b`` the frame after ``a``), ``pairs`` from
    each recording, ``spacing_s`` apart from its middle on: the views the enhancement proxy
    compares (no noise twins exist in a real recording)."""
    from ..io import open_recording
    from ..measurements import Image

    out_a: list[np.ndarray] = []
    out_b: list[np.ndarray] = []
    for path in recordings:
        rec = open_recording(path)
        spans = [(st.t_start, st.t_end) for st in rec.streams() if np.isfinite(st.t_start)]
        t_mid = 0.5 * (min(a for a, _ in spans) + max(b for _, b in spans))
        want, prev, got = t_mid, None, 0
        for r in rec:
            if not isinstance(r, Image):
                continue
            img = r.data if r.data.ndim == 2 else r.data.max(axis=2)
            if prev is not None and prev[0] >= want:
                out_a.append(prev[1])
                out_b.append(img)
                got += 1
                want = prev[0] + spacing_s
                if got >= pairs:
                    break
            prev = (r.t, img)
        if got == 0:
            raise InputFormatError("no camera frames after the middle of the recording", path)
    shapes = {x.shape for x in out_a}
    if len(shapes) != 1:
        raise InputFormatError(f"the recordings' images differ in size: {sorted(shapes)}")
    return np.stack(out_a), np.stack(out_b)


def plot_loss(path: str | Path, report: TuneReport, steps_per_round: int) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4))
    h = np.sqrt(np.maximum(np.asarray(report.history), 0.0))
    ax.plot(np.arange(len(h)), h, lw=1.5)
    for r in range(1, len(report.rounds)):
        ax.axvline(r * (steps_per_round + 1) - 0.5, color="grey", ls=":", lw=1)
    ax.set_xlabel("step (dotted: a new round, graphs re-captured by the estimator)")
    ax.set_ylabel("aligned position RMSE on training graphs (m)")
    ax.set_title("jaxslam tune: training loss")
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def write_report(path: str | Path, report: TuneReport) -> None:
    Path(path).write_text(json.dumps(report.to_json(), indent=2) + "\n")

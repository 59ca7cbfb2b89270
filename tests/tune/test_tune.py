"""``jaxslam tune``: weight groups, the aligned position loss (full poses and prism + lever
arm), graph tuning from wrong weights checked on a held-out graph, the config mapping, and
the CLI end to end on a short simulated recording."""

from __future__ import annotations

import json
import types
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxslam.cli import main as cli
from jaxslam.pipeline import PipelineConfig, load_config
from jaxslam.tune import GROUPS, Captured, TuneConfig, aligned_position_loss, apply_weights, tune_graphs
from jaxslam.tune._synthetic import tunnel_capture
from jaxslam.tune._tune import _interp_truth, factor_fn_for


def _captured(seed: int, odo_overtrust: float, lever=(0.0, 0.0, 0.0)) -> Captured:
    return tunnel_capture(seed, odo_overtrust, lever)


def test_interpolated_truth_skips_gaps() -> None:
    t = np.array([0.0, 0.2, 0.4, 2.0, 2.2])
    xyz = np.stack([t, 2 * t, np.zeros(5)], axis=1)
    idx, pts = _interp_truth(np.array([-0.1, 0.1, 0.3, 1.0, 2.1, 3.0]), t, xyz, max_gap=0.5)
    np.testing.assert_array_equal(idx, [1, 2, 4])
    np.testing.assert_allclose(pts[:, 0], [0.1, 0.3, 2.1])
    np.testing.assert_allclose(pts[:, 1], [0.2, 0.6, 4.2])


def test_aligned_loss_is_zero_at_truth_and_its_gradient_matches_differences() -> None:
    run = _captured(0, 1.0, lever=(0.1, 0.0, 0.55))
    assert float(aligned_position_loss(run.values, run)) < 1e-20  # alignment recovers the frame
    fn = factor_fn_for(run)
    from jaxslam.tune import DifferentiableSolver

    ds = DifferentiableSolver(fn, run.values, jnp.zeros(len(GROUPS)))
    theta = jnp.array([0.0, 0.0, 0.3, -0.2, 0.0, 0.0, 0.1, 0.4])
    grad = jax.grad(lambda th: aligned_position_loss(ds(th), run))(theta)
    assert float(jnp.abs(grad[0])) == 0.0 and float(jnp.abs(grad[4])) == 0.0  # kinds absent here
    h = 1e-5
    for i in (2, 3, 6, 7):
        e = jnp.zeros(len(GROUPS)).at[i].set(h)
        fd = (
            float(aligned_position_loss(ds.solve(theta + e), run))
            - float(aligned_position_loss(ds.solve(theta - e), run))
        ) / (2 * h)
        assert abs(float(grad[i]) - fd) <= 1e-5 * float(jnp.max(jnp.abs(grad))), (i, float(grad[i]), fd)


def test_tuning_from_wrong_weights_helps_a_held_out_graph() -> None:
    train = [_captured(1, 30.0, lever=(0.0, 0.0, 0.55))]
    res = tune_graphs(train, TuneConfig(steps=25))
    assert res.history[-1] < 0.7 * res.history[0]
    th = res.theta
    # the over-trusted odometry translation gets larger sigmas relative to the loops'
    assert th[GROUPS.index("lidar.translation")] > th[GROUPS.index("loop.translation")]
    held = _captured(2, 30.0, lever=(0.0, 0.0, 0.55))
    from jaxslam.tune import DifferentiableSolver

    ds = DifferentiableSolver(factor_fn_for(held), held.values, jnp.zeros(len(GROUPS)))
    before = float(aligned_position_loss(ds.solve(jnp.zeros(len(GROUPS))), held))
    after = float(aligned_position_loss(ds.solve(jnp.asarray(th)), held))
    assert after < 0.8 * before, (before, after)


def test_random_search_keeps_the_best_draw() -> None:
    train = [_captured(1, 30.0)]
    res = tune_graphs(train, TuneConfig(steps=6, search="random"))
    assert res.history[0] >= res.history[-1]
    assert all(a >= b for a, b in zip(res.history, res.history[1:]))


@pytest.mark.parametrize(
    ("select", "errors", "kept"),
    [("best", (0.3, 0.1, 0.2), "round 1"), ("best", (0.1, 0.3, 0.2), "start"), ("last", (0.3, 0.1, 0.2), "round 2")],
)
def test_tune_keeps_the_weights_whose_whole_runs_fit_best(monkeypatch, tmp_path, select, errors, kept) -> None:
    """The estimator, the capture and the graph tuning replaced by stand-ins: configuration
    ``n`` (the start is 0, round r's weights r) makes whole runs with aligned RMSE
    ``errors[n]``; ``select="best"`` keeps the lowest (one validation run more per
    recording), ``last`` the last round's."""
    from jaxslam.pipeline import _run
    from jaxslam.tune import _tune

    runs: list[int] = []

    def run_recording(path, out, config, plots, on_finish):
        runs.append(config)
        on_finish(config, {}, None)
        return {"ape_rmse_m": errors[config]}

    def capture(est, res, gt, cfg, name):
        return types.SimpleNamespace(keyframes=np.arange(5), truth_kind="poses", values=est, ape_m=None, name=name)

    def tune_graphs(caps, cfg, progress):
        return _tune.GraphTuneResult(np.zeros(len(GROUPS)), [1.0, 0.5], [1.0], 0.0, 0.0)

    monkeypatch.setattr(_run, "run_recording", run_recording)
    monkeypatch.setattr(_tune, "capture", capture)
    monkeypatch.setattr(_tune, "tune_graphs", tune_graphs)
    monkeypatch.setattr(_tune, "apply_weights", lambda config, theta: config + 1)
    monkeypatch.setattr(_tune, "aligned_position_loss", lambda values, cap: errors[values] ** 2)
    rep = _tune.tune(["a.bag", "b.bag"], 0, TuneConfig(rounds=2, select=select), tmp_path, log=lambda s: None)
    assert rep.selected == kept
    assert rep.config == (0 if kept == "start" else int(kept.split()[1]))
    assert runs == ([0, 0, 1, 1, 2, 2] if select == "best" else [0, 0, 1, 1])
    assert rep.estimator_runs == len(runs)
    assert set(rep.run_rmse_m) == ({"start", "round 1", "round 2"} if select == "best" else {"start", "round 1"})
    assert rep.run_rmse_m["start"] == pytest.approx(errors[0])


def test_tune_refuses_an_unknown_selection(tmp_path) -> None:
    from jaxslam.errors import ConfigError
    from jaxslam.tune import _tune

    with pytest.raises(ConfigError, match="select must be best or last"):
        _tune.tune([], PipelineConfig(), TuneConfig(select="median"), tmp_path)


def test_apply_weights_maps_groups_to_the_config() -> None:
    cfg = PipelineConfig()
    assert apply_weights(cfg, np.zeros(len(GROUPS))) == cfg
    th = np.zeros(len(GROUPS))
    th[GROUPS.index("imu")] = np.log(2.0)
    th[GROUPS.index("bias")] = np.log(3.0)
    th[GROUPS.index("lidar.translation")] = np.log(2.0)  # sigma x2: information / 4
    th[GROUPS.index("loop.rotation")] = -np.log(10.0)
    out = apply_weights(cfg, th)
    assert out.imu.noise_scale == pytest.approx(2.0 * cfg.imu.noise_scale)
    assert out.rig.gyroscope_random_walk == pytest.approx(3.0 * cfg.rig.gyroscope_random_walk)
    assert out.lidar.axis_weights == pytest.approx((1.0, 0.25))
    assert out.loop.axis_weights == pytest.approx((100.0, 1.0))
    assert out.vision.axis_weights == (1.0, 1.0)


def test_captures_positions_with_a_lever_arm() -> None:
    from jaxslam.measurements import PositionFix
    from jaxslam.tune._tune import capture

    run = _captured(0, 1.0)
    fixes = [PositionFix(float(t), np.array([t, 0.0, 1.0])) for t in np.arange(0.0, 10.0, 0.2)]
    est = types.SimpleNamespace(
        graph=[("prior", run.fixed[0]), ("lidar", run.kinds["lidar"][0]), ("loop", run.kinds["loop"][0])],
        fixes=fixes,
        solver=types.SimpleNamespace(estimate=lambda: run.values),
    )
    res = {"times": np.arange(len(run.truth)) * 0.5}
    cap = capture(est, res, None, TuneConfig(truth="auto", lever_arm=(0.0, 0.0, 0.55)), "x")
    assert cap.truth_kind == "positions"
    np.testing.assert_allclose(cap.lever_arm, [0.0, 0.0, 0.55])
    assert cap.keyframes.max() * 0.5 <= 9.8 + 1e-9
    np.testing.assert_allclose(cap.truth[:, 0], res["times"][cap.keyframes])
    with pytest.raises(Exception, match="no ground-truth poses"):
        capture(est, res, None, TuneConfig(truth="poses"), "x")


def test_a_kind_of_two_factor_classes_is_captured_and_weighted_per_class() -> None:
    """Visual odometry is a ScaledBetweenFactor, or a BetweenFactor where it stays out of the
    scale (``vision.unscaled_min_inliers``): the capture keeps one concatenated factor per
    class of a kind, and the weighting multiplies each by the kind's sigmas."""
    from jaxslam.core import Gaussian, Pose3Var, ScaleVar
    from jaxslam.factors import BetweenFactor, ScaledBetweenFactor
    from jaxslam.lie import host
    from jaxslam.measurements import PositionFix
    from jaxslam.tune._tune import capture

    run = _captured(0, 1.0)
    T = host.matrix_to_params(np.eye(4))[None]
    noise = Gaussian.diagonal(jnp.full(6, 0.01))
    plain = [BetweenFactor.create(Pose3Var(np.array([k])), Pose3Var(np.array([k + 1])), T, noise) for k in (0, 2)]
    scaled = [
        ScaledBetweenFactor.create(
            Pose3Var(np.array([k])), Pose3Var(np.array([k + 1])), ScaleVar(np.array([k + 1])), T, noise
        )
        for k in (1, 3)
    ]
    graph = [("prior", run.fixed[0]), ("vision", plain[0]), ("vision", scaled[0]), ("vision", plain[1])]
    graph.append(("vision", scaled[1]))
    fixes = [PositionFix(float(t), np.array([t, 0.0, 1.0])) for t in np.arange(0.0, 10.0, 0.2)]
    est = types.SimpleNamespace(graph=graph, fixes=fixes, solver=types.SimpleNamespace(estimate=lambda: run.values))
    cap = capture(est, {"times": np.arange(len(run.truth)) * 0.5}, None, TuneConfig(truth="auto"), "x")
    assert sorted(type(f).__name__ for f in cap.kinds["vision"]) == ["BetweenFactor", "ScaledBetweenFactor"]
    assert all(f.num_constraints == 2 for f in cap.kinds["vision"])
    theta = np.zeros(len(GROUPS))
    theta[GROUPS.index("vision.translation")] = np.log(2.0)
    out = [f for f in factor_fn_for(cap)(jnp.asarray(theta)) if type(f) in (BetweenFactor, ScaledBetweenFactor)]
    assert len(out) == 2
    for f in out:
        d = np.abs(np.asarray(f.noise.sqrt_info)[:, np.arange(6), np.arange(6)])
        np.testing.assert_allclose(d[:, :3], 100.0)
        np.testing.assert_allclose(d[:, 3:], 50.0)  # sigma 0.01 x 2


def test_cli_refuses_bad_input(tmp_path, capsys) -> None:
    assert cli(["tune", str(tmp_path / "missing.bag"), "-o", str(tmp_path / "w.yaml")]) != 0
    assert "no such recording" in capsys.readouterr().err
    (tmp_path / "r.bag").write_bytes(b"not a bag")
    assert cli(["tune", str(tmp_path / "r.bag"), "-o", str(tmp_path / "w.txt")]) != 0
    assert ".yaml" in capsys.readouterr().err
    assert cli(["tune", str(tmp_path / "r.bag"), "-o", str(tmp_path / "w.yaml"), "--devices", "99"]) != 0
    assert "--devices must be 0 (all) to" in capsys.readouterr().err


@pytest.mark.slow
def test_cli_end_to_end_with_prism_positions(tmp_path, short_tunnel_bag) -> None:
    from jaxslam.sim import SimConfig

    bag = short_tunnel_bag
    sim = SimConfig()  # the recording's rig: the prism lever arm is the simulator's default
    out = tmp_path / "w.yaml"
    start = tmp_path / "start.yaml"  # the estimator settings of tests/pipeline: their compiled programs
    start.write_text("vision:\n  threaded: false\n  max_keypoints: 600\n")
    # --select last: one estimator run (the selection between whole runs is
    # test_tune_keeps_the_weights_whose_whole_runs_fit_best's)
    args = ["tune", str(bag), "-o", str(out), "--config", str(start), "--rounds", "1", "--steps", "2"]
    args += ["--select", "last"]
    args += ["--truth", "positions", "-q"]
    args += ["--lever-arm", *map(str, sim.prism)]
    assert cli(args) == 0
    cfg = load_config(out)  # usable by jaxslam run --config
    assert isinstance(cfg, PipelineConfig)
    assert cfg.vision.max_keypoints == 600 and not cfg.vision.threaded  # the starting config carried over
    rep = json.loads(out.with_suffix(".report.json").read_text())
    assert rep["rounds"][0]["truth"] == "positions"
    assert 1 <= len(rep["loss_history"]) <= 3 and all(np.isfinite(rep["loss_history"]))  # the budget holds
    # one training run with the start's weights; round 1's weights are kept
    assert rep["heldout"] == [] and rep["estimator_runs"] == 1
    assert rep["selected"] == "round 1" and set(rep["train_run_rmse_m"]) == {"start"}
    assert 0.0 < rep["train_run_rmse_m"]["start"] < 0.5
    assert Path(out.with_suffix(".loss.png")).stat().st_size > 1000

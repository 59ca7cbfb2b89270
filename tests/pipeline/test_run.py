"""The fused estimator end to end on a short simulated tunnel: the results folder, its metrics
against ground truth, the CLI, and the robustness cases of issue 6 (camera dark for 10 s, LiDAR
missing for 5 s, an IMU gap of 0.5 s, NaN samples, a timestamp jump backwards, a truncated
bag), each finishing with a trajectory, a warning with counts and bounded extra error."""

from __future__ import annotations

import itertools
import json
from pathlib import Path

import jax.numpy as jnp
import numpy as np
import pytest

from jaxslam import eval as ev
from jaxslam.core import ScaleVar
from jaxslam.io import Trajectory, open_recording, read_ply
from jaxslam.lie import SE3, host
from jaxslam.measurements import PoseStamped
from jaxslam.pipeline import Estimator, PipelineConfig, load_rig, run_recording
from jaxslam.sim import (
    CameraDark,
    NanSamples,
    SensorDropout,
    TimeJump,
    inject_faults,
    truncate_file,
)

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def bag(short_tunnel_bag) -> Path:
    return short_tunnel_bag


@pytest.fixture(scope="module")
def records(bag: Path) -> list:
    return list(open_recording(bag))


@pytest.fixture(scope="module")
def config(bag: Path) -> PipelineConfig:
    cfg = PipelineConfig(rig=load_rig(bag.with_suffix(".rig.yaml")))
    return cfg.replace(vision={"threaded": False, "max_keypoints": 600})


def _gt(records: list) -> Trajectory:
    poses = [r for r in records if isinstance(r, PoseStamped)]
    return Trajectory(np.array([p.t for p in poses]), SE3(jnp.asarray(np.stack([p.pose for p in poses]))))


def _run(records, config, faults=()) -> tuple[Estimator, dict, float]:
    est = Estimator(config)
    for r in inject_faults(iter(records), list(faults)):
        est.feed(r)
    res = est.finish()
    traj = Trajectory(res["times"], SE3(jnp.asarray(host.matrix_to_params(res["poses"]))))
    ape = ev.ape(_gt(records), traj, align="se3").stats["rmse"]
    return est, res, ape


@pytest.fixture(scope="module")
def baseline(records, config):
    return _run(records, config)


def test_clean_run_is_accurate(baseline, records) -> None:
    est, res, ape = baseline
    t = res["times"]
    assert ape < 0.1, ape
    assert t[0] - records[0].t < 2.0 and records[-1].t - t[-1] < 1.0  # the whole run is covered
    assert sum(kf.registered for kf in est.keyframes) >= 0.9 * len(est.keyframes)
    faults = ("bad sample", "timestamp", "gap", "no scan", "recording")  # data faults: none here
    assert not [k for k in est.warnings if any(f in k for f in faults)], est.warnings


def test_bayes_tree_engine_runs_the_estimator(baseline, records, config) -> None:
    """``solver.engine: bayes_tree`` (iSAM2's partial re-elimination, lazy back-substitution)
    gives a trajectory as good as the default engine's; the final refinement takes both to
    the same optimum."""
    _, res0, ape0 = baseline
    est, res, ape = _run(records, config.replace(solver={"engine": "bayes_tree"}))
    assert est.solver.config.engine == "bayes_tree"
    assert ape < 0.1 and ape <= 1.5 * ape0 + 0.01, (ape, ape0)
    assert len(res["poses"]) == len(res0["poses"])
    drift = np.linalg.norm(res["poses"][:, :3, 3] - res0["poses"][:, :3, 3], axis=1)
    assert np.median(drift) < 0.05, np.median(drift)


def test_visual_poses_are_fitted_on_aligned_patches(baseline, records, config) -> None:
    """``vision.patch_refine`` (the default): most visual-odometry poses are fitted again on
    the older image's patches found in the newer one; off, none are and the run stays
    accurate."""
    assert baseline[0].visual.patch_refined >= 0.8 * len(baseline[0].visual_edges) > 0
    off, _, ape = _run(records, config.replace(vision={"patch_refine": False}))
    assert off.visual.patch_refined == 0 and len(off.visual_edges) > 0
    assert ape < 0.1, ape


def test_the_last_keyframe_is_always_tried_for_a_loop(records, config) -> None:
    """A drive out and back ends where it started: the recording's last keyframe is tried for
    a loop even when ``loop.every`` skips it (with patch refinement the short tunnel once
    ended one keyframe after a multiple of three and accepted no loop at all)."""
    est, _, ape = _run(records, config.replace(loop={"every": 1000}))
    last = len(est.keyframes) - 1
    assert est.loops.attempts == 1 and [lp.j for lp in est.loops.accepted] == [last], est.loops.rejected
    assert ape < 0.1, ape


def test_run_recording_writes_the_results_folder(bag, config, tmp_path) -> None:
    m = run_recording(bag, tmp_path, config.replace(loop={"enabled": True}))
    for name in (
        "trajectory_tum.txt",
        "trajectory_kitti.txt",
        "map.ply",
        "metrics.json",
        "config.yaml",
        "trajectory.png",
        "errors.png",
        "residuals.png",
    ):
        assert (tmp_path / name).stat().st_size > 0, name
    saved = json.loads((tmp_path / "metrics.json").read_text())
    for key in (
        "ape_rmse_m", "ape_mean_m", "ape_max_m", "rpe_rmse", "loop_error_m", "loop_error_ratio", "path_length_m",
        "reproj_rmse_px", "registered_frames", "total_frames", "runtime_s", "sequence_duration_s",
        "degenerate_scans", "loops_accepted", "loops_rejected",
    ):  # fmt: skip
        assert key in saved, key
    assert saved["ape_rmse_m"] == pytest.approx(m["ape_rmse_m"])
    assert saved["machine"]["cpus"] >= 1 and saved["machine"]["cpu"]  # timings say what they ran on
    assert saved["compile_s"] >= 0.0  # JIT compilation inside the run, reported apart
    assert saved["zero_velocity_updates"] > 0  # the stops at both ends and the turn on the spot
    assert saved["ape_rmse_m"] < 0.1
    assert saved["loops_false"] in (0, None)
    ratios = saved["odometry_length_ratio"]  # each front end's length against ground truth
    assert ratios["lidar odometry"]["pairs"] > 0
    for r in ratios.values():
        assert 0.9 < r["total"] < 1.1 and 0.9 < r["median"] < 1.1, ratios
    cons = saved["factor_consistency"]  # each front end's stated sigmas against its errors
    assert cons["lidar odometry"]["measurements"] >= ratios["lidar odometry"]["pairs"]
    for c in cons.values():
        assert np.isfinite(c["nees"]) and c["nees"] > 0 and 0 <= c["over_95"] <= 1, cons
    # the written trajectory gives the same APE through the evaluation CLI (evo-equal numbers)
    from jaxslam.cli import main

    gt = tmp_path / "gt.tum"
    from jaxslam.io import write_tum

    write_tum(gt, open_recording(bag).ground_truth())
    assert main(["eval", str(gt), str(tmp_path / "trajectory_tum.txt"), "--json", str(tmp_path / "ev.json")]) == 0
    cli = json.loads((tmp_path / "ev.json").read_text())
    assert cli["ape"]["stats"]["rmse"] == pytest.approx(saved["ape_rmse_m"], rel=1e-9)
    assert cli["loop_error_m"] == pytest.approx(saved["loop_error_m"], rel=1e-9)
    pts, _ = read_ply(tmp_path / "map.ply")
    assert len(pts) > 1000 and np.all(np.isfinite(pts))


def test_threaded_vision_is_deterministic(records, config) -> None:
    """The worker's factors join at a fixed keyframe lag: two threaded runs agree exactly."""
    threaded = config.replace(vision={"threaded": True})
    a, b = (_run(records, threaded)[1]["poses"] for _ in range(2))
    np.testing.assert_array_equal(a, b)


def test_length_sigma_softens_only_where_the_lidar_is_anchored(records, config, baseline) -> None:
    """``vision.length_sigma_ratio`` (0.015 by default): every visual factor over keyframe
    pairs whose LiDAR odometry was anchored along the axis throughout (and no other) gets the
    length variance; 0 turns it off; either way the run stays accurate."""
    est = baseline[0]
    assert config.vision.length_sigma_ratio > 0
    anchored = [vm for vm in est.visual_edges if all((k, k + 1) in est._lidar_rel for k in range(vm.i, vm.j))]
    assert 0 < est.length_softened == len(anchored) < len(est.visual_edges) + 1
    off, _, ape = _run(records, config.replace(vision={"length_sigma_ratio": 0.0}))
    assert off.length_softened == 0
    assert ape < baseline[2] + 0.05 and baseline[2] < ape + 0.05, (ape, baseline[2])


def _scale_priors(est: Estimator) -> list[tuple[int, float]]:
    """(keyframe, sigma) of every prior on a visual length scale in the estimator's graph."""
    out = []
    for kind, f in est.graph:
        if kind == "scale" and type(f).__name__ == "PriorFactor":
            sigma = 1.0 / np.abs(np.asarray(f.noise.sqrt_info)[:, 0, 0])
            out += list(zip(np.asarray(f.variables[0].ids).tolist(), sigma.tolist()))
    return sorted(out)


def test_scale_mean_reversion_pulls_each_keyframes_scale_towards_one(records, config, baseline) -> None:
    """``vision.scale_revert_m`` (0 = off, the default): every keyframe's log scale after the
    first gets a prior towards 0 of sigma ``scale_revert_m * scale_walk_sigma / sqrt(step)``
    (a first-order Gauss-Markov scale); the run stays accurate and its scales are no further
    from 1 than without."""
    assert config.vision.scale_revert_m == 0.0
    assert [k for k, _ in _scale_priors(baseline[0])] == [0]  # off: the first keyframe's only
    est, res, ape = _run(records, config.replace(vision={"scale_revert_m": 5.0}))
    priors = _scale_priors(est)
    assert [k for k, _ in priors] == list(range(len(est.keyframes)))
    walk = config.vision.scale_walk_sigma
    for k, sigma in priors[1:]:
        step = max(float(np.linalg.norm(res["poses"][k][:3, 3] - res["poses"][k - 1][:3, 3])), 0.05)
        assert sigma == pytest.approx(5.0 * walk / np.sqrt(step), rel=0.3), (k, sigma)  # predicted step
    assert ape < baseline[2] + 0.02, (ape, baseline[2])
    on = np.abs(np.asarray(est.solver.estimate().params(ScaleVar))).max()
    off = np.abs(np.asarray(baseline[0].solver.estimate().params(ScaleVar))).max()
    assert on <= off + 1e-4, (on, off)


def test_scale_reverts_to_a_run_wide_scale_the_graph_estimates(records, config, baseline) -> None:
    """``vision.scale_revert_to = "run"``: the keyframes' log scales revert to one more
    ScaleVar (id ``RUN_SCALE_ID``, the first keyframe's prior) instead of to 0, through a
    between factor each of the same sigma. That variable only enters linear factors, so at the
    end it is exactly the precision-weighted mean of the keyframes' log scales (its prior's
    mean 0 counted once): the closed form of its own normal equation."""
    from jaxslam.pipeline._estimator import RUN_SCALE_ID

    est, res, ape = _run(records, config.replace(vision={"scale_revert_m": 5.0, "scale_revert_to": "run"}))
    assert [k for k, _ in _scale_priors(est)] == [0, RUN_SCALE_ID]  # the run scale's and the first's
    pulls = {}
    for kind, f in est.graph:
        if kind == "scale" and type(f).__name__ == "BetweenFactor":
            a, b = (np.asarray(v.ids).tolist() for v in f.variables)
            sigma = (1.0 / np.abs(np.asarray(f.noise.sqrt_info)[:, 0, 0])).tolist()
            pulls.update({j: s for i, j, s in zip(a, b, sigma) if i == RUN_SCALE_ID})
    assert sorted(pulls) == list(range(1, len(est.keyframes)))
    walk = config.vision.scale_walk_sigma
    for k, sigma in pulls.items():
        step = max(float(np.linalg.norm(res["poses"][k][:3, 3] - res["poses"][k - 1][:3, 3])), 0.05)
        assert sigma == pytest.approx(5.0 * walk / np.sqrt(step), rel=0.3), (k, sigma)
    value = {k: float(est.solver.value(ScaleVar, k)[0]) for k in [RUN_SCALE_ID, *pulls]}
    w = {k: 1.0 / s**2 for k, s in pulls.items()}
    expect = sum(w[k] * value[k] for k in w) / (1.0 / config.vision.scale_prior_sigma**2 + sum(w.values()))
    assert value[RUN_SCALE_ID] == pytest.approx(expect, rel=1e-6, abs=1e-9)
    assert abs(value[RUN_SCALE_ID]) > 1e-6  # it moved: the data pulls it
    assert ape < baseline[2] + 0.02, (ape, baseline[2])


def test_well_aligned_visual_factors_leave_the_scale_out(records, config, baseline) -> None:
    """``vision.unscaled_min_inliers`` (50 by default; 0 = every visual factor scaled): a
    patch-refined visual factor with at least that many inliers is a plain between factor,
    every other one a ScaledBetweenFactor on its keyframe's scale; the run stays accurate."""

    def kinds(est):
        facs = [f for kind, f in est.graph if kind == "vision"]
        assert len(facs) == len(est.visual_edges)
        return [type(f).__name__ for f in facs]

    def expected(est, n_min):
        return [
            "BetweenFactor" if n_min > 0 and vm.refined and vm.inliers >= n_min else "ScaledBetweenFactor"
            for vm in est.visual_edges
        ]

    est0 = baseline[0]
    assert config.vision.unscaled_min_inliers == 50
    assert kinds(est0) == expected(est0, 50)
    refined = sorted(vm.inliers for vm in est0.visual_edges if vm.refined)
    assert len(refined) >= 4 and refined[0] < refined[-1], refined  # both sides of the bar below
    for n_min in (refined[len(refined) // 2], 0):
        est, _, ape = _run(records, config.replace(vision={"unscaled_min_inliers": n_min}))
        got = kinds(est)
        assert got == expected(est, n_min)
        assert ("BetweenFactor" in got) == (n_min > 0) and "ScaledBetweenFactor" in got
        assert ape < baseline[2] + 0.02, (ape, baseline[2])


def test_axis_sigma_scale_reaches_every_factor_kind(records, config, baseline) -> None:
    """``{lidar,vision,loop}.axis_sigma_scale`` and ``loop.visual_axis_sigma_scale``: in a
    run, every LiDAR odometry factor's, visual odometry factor's and loop factor's information
    is exactly its front end's with the along-axis sigma scaled (``axis_sigma_scaled``), and
    the run stays accurate."""
    from jaxslam.pipeline._lidar_frontend import axis_sigma_scaled, axis_weighted, information_for_factor

    s = {"lidar": 1.5, "vision": 1.3, "loop": 0.7, "visual loop": 1.2}
    cfg = config.replace(
        lidar={"axis_sigma_scale": s["lidar"]},
        vision={"axis_sigma_scale": s["vision"], "length_sigma_ratio": 0.0},
        loop={"axis_sigma_scale": s["loop"], "visual_axis_sigma_scale": s["visual loop"]},
    )
    est, _, ape = _run(records, cfg)
    edges: dict[str, dict] = {}
    for kind, i, j, _T, info in est.edges:
        edges.setdefault(kind, {}).setdefault((i, j), []).append(info)
    lid = 0
    for (i, j), infos in edges["lidar odometry"].items():
        if j != i + 1:
            continue
        reg = est.keyframes[j].scan.registration
        raw = information_for_factor(reg.strong_information(), est.T_bl, cfg.lidar, cfg.lidar.information_scale)
        expect = axis_sigma_scaled(axis_weighted(raw, cfg.lidar.axis_weights), s["lidar"])
        np.testing.assert_allclose(infos[0], expect, rtol=1e-12)
        lid += 1
    for vm in est.visual_edges:
        expect = axis_sigma_scaled(axis_weighted(vm.information, cfg.vision.axis_weights), s["vision"])
        assert any(np.allclose(x, expect, rtol=1e-12, atol=0) for x in edges["visual odometry"][(vm.i, vm.j)])
    loops = [*est.loops.accepted, *(est.visual_loops.accepted if est.visual_loops else [])]
    for lp in loops:
        expect = axis_sigma_scaled(lp.information, s["visual loop" if type(lp).__name__ == "VisualLoop" else "loop"])
        assert any(np.allclose(x, expect, rtol=1e-12, atol=0) for x in edges["loop closure"][(lp.i, lp.j)])
    assert lid > 10 and len(est.visual_edges) > 10 and len(loops) > 0
    assert ape < baseline[2] + 0.02, (ape, baseline[2])


def test_scans_standing_still_are_held(records, config, baseline) -> None:
    """``lidar.hold_still`` keeps scans taken while the IMU says the vehicle stands still at
    the last scan's pose, unregistered. By default only at the standing start
    (``hold_still_start_only``): the simulated run starts standing, so the baseline holds the
    scans after the first up to the first one that moves, as many as a run holding every
    stop holds there; with ``hold_still`` off none is held. All three runs stay accurate."""
    assert config.lidar.hold_still and config.lidar.hold_still_start_only
    start_held = baseline[0].lidar.held
    assert start_held > 0
    for hold, start_only in ((True, False), (False, True)):
        est = Estimator(config.replace(lidar={"hold_still": hold, "hold_still_start_only": start_only}))
        scans: list = []
        process = est.lidar.process
        est.lidar.process = lambda *a, _s=scans, _p=process, **k: _s.append(_p(*a, **k)) or _s[-1]
        for r in records:
            est.feed(r)
        res = est.finish()
        held = [s.index for s in scans if s.held]
        assert est.lidar.held == len(held)
        if hold:
            assert held and held[0] == 1, held
            assert all(s.registration is None for s in scans if s.held)
            moved = next(s.index for s in scans[1:] if not s.held)
            assert held[: moved - 1] == list(range(1, moved)) and moved - 1 == start_held, (held, moved, start_held)
        else:
            assert held == [] and all(s.registration is not None for s in scans[1:])
        traj = Trajectory(res["times"], SE3(jnp.asarray(host.matrix_to_params(res["poses"]))))
        ape = ev.ape(_gt(records), traj, align="se3").stats["rmse"]
        assert ape < baseline[2] + 0.02, (hold, ape, baseline[2])


def test_loop_factors_carry_their_kinds_kernel_scale(baseline, config) -> None:
    """LiDAR and visual loops share one factor group, so each loop factor holds its Cauchy
    scale per constraint: ``loop.cauchy_scale`` on LiDAR loops, ``loop.visual_cauchy_scale``
    on visual ones (a scalar would give all of them the first loop's)."""
    est = baseline[0]
    scales = sorted(float(np.asarray(f.robust.k)[0]) for kind, f in est.graph if kind == "loop")
    n_visual = len(est.visual_loops.accepted) if est.visual_loops else 0
    assert len(scales) == len(est.loops.accepted) + n_visual > 0
    lidar, visual = config.loop.cauchy_scale, config.loop.visual_cauchy_scale
    assert scales == sorted([lidar] * len(est.loops.accepted) + [visual] * n_visual)


def test_cli_run_shows_progress(bag, tmp_path, capsys) -> None:
    """``jaxslam run`` without ``-q``: the progress bar starts with an unknown total (it once
    crashed formatting None). Four seconds travel less than RPE's 1 m delta: the run still
    finishes with its metrics (RPE none, said in the warnings; it once failed at the end)."""
    from jaxslam.cli import main

    out = tmp_path / "out"
    assert main(["run", str(bag), "-o", str(out), "--max-seconds", "4", "--no-plots"]) == 0
    captured = capsys.readouterr()
    err = captured.err
    assert "run:" in err and "/? s" in err and " s [" in err, err[-500:]
    assert "real time" in captured.out and "JIT compilation in it: " in captured.out  # compile apart
    assert (out / "trajectory_tum.txt").stat().st_size > 0
    m = json.loads((out / "metrics.json").read_text())
    assert m["rpe_rmse"] is None and m["ape_rmse_m"] < 0.1
    assert any(k.startswith("eval: no RPE") for k in m["warnings"]), m["warnings"]


def test_cli_bad_recording_is_one_line(tmp_path, capsys) -> None:
    from jaxslam.cli import main

    bad = tmp_path / "x.bag"
    bad.write_bytes(b"not a bag at all")
    assert main(["run", str(bad), "-o", str(tmp_path / "out"), "-q"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "x.bag" in err[0]


# --- robustness: each fault finishes with a trajectory, a counted warning, bounded extra error ----
def _check(run, baseline, warning: str, extra: float) -> None:
    est, res, ape = run
    assert len(res["times"]) > 0.8 * len(baseline[1]["times"])
    assert any(warning in k for k in est.warnings), est.warnings
    assert ape < baseline[2] + extra, (ape, baseline[2])


def test_camera_dark_for_10_s(records, config, baseline) -> None:
    _check(
        _run(records, config, [CameraDark(start=8.0, duration=10.0)]), baseline, "camera: keyframe not registered", 0.1
    )


def test_lidar_missing_for_5_s(records, config, baseline) -> None:
    _check(_run(records, config, [SensorDropout("lidar", start=10.0, duration=5.0)]), baseline, "lidar: no scan", 0.1)


def test_lidar_odometry_resumes_with_the_dropouts_motion(records, config, baseline) -> None:
    """The first scan after a LiDAR dropout is registered from the odometry pose moved by all
    the IMU motion since the last scan, through the image-driven events in between. It once
    took only the last event's motion, so the odometry lost what was driven during the gap:
    where that was little (the dropout at 10 s, ~0.4 m) registration to the map mostly made
    up for it, but under a robust kernel on the visual odometry one run's long LiDAR pairs
    back over the gap came out ~0.5 m off (APE 0.18 m); here the robot drives ~2 m blind."""
    run = _run(records, config, [SensorDropout("lidar", start=5.0, duration=5.0)])
    _check(run, baseline, "lidar: no scan", 0.1)
    est = run[0]
    gt = [r for r in records if isinstance(r, PoseStamped)]
    gt_t = np.array([p.t for p in gt])

    def gt_pose(t: float) -> np.ndarray:
        return host.params_to_matrix(np.asarray(gt[int(np.argmin(np.abs(gt_t - t)))].pose))

    scans = [kf.scan for kf in est.keyframes if kf.scan is not None]
    a, b = max(itertools.pairwise(scans), key=lambda ab: ab[1].t - ab[0].t)
    assert b.t - a.t > 4.0  # the pair across the dropout
    moved = host.inverse(gt_pose(a.t)) @ gt_pose(b.t)
    odom = host.inverse(a.T_odom) @ b.T_odom
    assert np.linalg.norm(moved[:3, 3]) > 1.0  # the robot drove during the dropout
    assert np.linalg.norm(odom[:3, 3] - moved[:3, 3]) < 0.1, (odom[:3, 3], moved[:3, 3])


def test_imu_gap_of_half_a_second(records, config, baseline) -> None:
    _check(_run(records, config, [SensorDropout("imu", start=12.0, duration=0.5)]), baseline, "imu: gap", 0.05)


def test_nan_samples(records, config, baseline) -> None:
    faults = [NanSamples("imu", every=97), NanSamples("lidar", every=13), NanSamples("image", every=11)]
    _check(_run(records, config, faults), baseline, "bad sample", 0.05)


def test_timestamp_jump_backwards(records, config, baseline) -> None:
    faults = [
        TimeJump("imu", at=9.0, back=0.3),
        TimeJump("lidar", at=11.0, back=0.5),
        TimeJump("image", at=13.0, back=0.5),
    ]
    _check(_run(records, config, faults), baseline, "timestamp not increasing", 0.05)


def test_truncated_bag(bag, config, tmp_path) -> None:
    cut = tmp_path / "cut.bag"
    truncate_file(bag, cut, 0.6)
    m = run_recording(cut, tmp_path / "out", config, plots=False)  # repaired on the fly, original kept
    assert cut.exists() and (tmp_path / "out" / "cut.reindexed.bag").exists()
    assert m["keyframes"] > 10
    full = max(s.t_end - s.t_start for s in open_recording(bag).streams())
    assert m["sequence_duration_s"] < 0.75 * full
    assert m["ape_rmse_m"] < 0.15
    assert any("reindexed" in k for k in m["warnings"]), m["warnings"]

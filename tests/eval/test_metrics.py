"""jaxslam.eval against evo (the oracle, at test time) and in closed form."""

from __future__ import annotations

from pathlib import Path

import jax.numpy as jnp
import numpy as np
import pytest

from jaxslam.errors import ConfigError, InputFormatError
from jaxslam.eval import (
    PositionTrack,
    align,
    ape,
    associate,
    loop_error,
    loop_error_ratio,
    match_indices,
    path_length,
    plot_ape_over_distance,
    plot_residual_histograms,
    plot_trajectory,
    rpe,
    umeyama,
)
from jaxslam.io import Trajectory
from jaxslam.lie import SE3, SO3

TOL = 1e-9


def smooth_path(n: int = 300, seed: int = 0) -> Trajectory:
    """A smooth 3-D figure-eight with varying attitude and irregular time steps."""
    rng = np.random.default_rng(seed)
    t = 100.0 + np.cumsum(rng.uniform(0.05, 0.15, n))
    s = np.linspace(0.0, 1.0, n)
    pos = np.stack([20 * np.sin(2 * np.pi * s), 10 * np.sin(4 * np.pi * s), 0.5 * s + 0.2 * np.cos(6 * np.pi * s)], -1)
    rv = np.stack([0.1 * np.sin(3 * s), 0.05 * np.cos(5 * s), 2 * np.pi * s], -1)
    q = np.asarray(SO3.exp(jnp.asarray(rv)).params)
    return Trajectory(t, SE3(jnp.asarray(np.concatenate([q, pos], -1))))


def noisy_estimate(ref: Trajectory, seed: int = 1, scale: float = 1.0, drop: bool = True) -> Trajectory:
    """``ref`` in another world frame, scaled, noisy; stamps jittered, some dropped, some
    pushed beyond the association window (all kept, stamps unchanged, when not ``drop``)."""
    rng = np.random.default_rng(seed)
    n = len(ref)
    frame = SE3.exp(jnp.asarray([0.1, -0.2, 0.3, 1.0, 2.0, -0.5]))
    noise = np.concatenate([0.01 * rng.standard_normal((n, 3)), 0.05 * rng.standard_normal((n, 3))], -1)
    p = np.array((frame @ ref.poses @ SE3.exp(jnp.asarray(noise))).params)
    p[:, 4:] *= scale
    t = ref.timestamps + rng.uniform(-0.008, 0.008, n)
    t[rng.random(n) < 0.1] += 0.03
    keep = rng.random(n) > 0.1
    if not drop:
        return Trajectory(ref.timestamps, SE3(jnp.asarray(p)))
    return Trajectory(t[keep], SE3(jnp.asarray(p[keep])))


def evo_traj(tr: Trajectory):
    from evo.core.trajectory import PoseTrajectory3D

    p = np.asarray(tr.poses.params)
    return PoseTrajectory3D(p[:, 4:], p[:, :4], tr.timestamps)


def evo_synced(ref: Trajectory, est: Trajectory, mode: str, max_diff: float = 0.01, offset: float = 0.0):
    from evo.core import sync

    r, e = sync.associate_trajectories(evo_traj(ref), evo_traj(est), max_diff=max_diff, offset_2=offset)
    out = None
    if mode in ("se3", "sim3"):
        out = e.align(r, correct_scale=mode == "sim3")
    elif mode == "origin":
        out = e.align_origin(r)
    return r, e, out


@pytest.fixture(scope="module")
def pair() -> tuple[Trajectory, Trajectory]:
    ref = smooth_path()
    return ref, noisy_estimate(ref, scale=1.3)


def test_associate_matches_evo(pair: tuple[Trajectory, Trajectory]) -> None:
    pytest.importorskip("evo")
    ref, est = pair
    for r, e, offset in [(ref, est, 0.0), (ref, est, 0.004), (est, ref, 0.0), (est, ref, -0.003)]:
        er, ee, _ = evo_synced(r, e, "none", offset=offset)
        mr, me = associate(r, e, offset=offset)
        assert len(mr) == ee.num_poses > 0.5 * len(est)
        np.testing.assert_array_equal(mr.timestamps, er.timestamps)
        np.testing.assert_array_equal(me.timestamps, ee.timestamps)
    i_ref, i_est = match_indices(ref.timestamps, est.timestamps)
    assert len(np.unique(i_ref)) == len(i_ref)  # one-to-one on this data
    assert np.all(np.abs(ref.timestamps[i_ref] - est.timestamps[i_est]) <= 0.01)


def test_associate_tie_goes_to_the_earlier_stamp() -> None:
    i_ref, i_est = match_indices(np.array([0.0, 1.0, 2.0]), np.array([0.5, 1.9]), max_diff=0.5)
    assert i_ref.tolist() == [0, 2] and i_est.tolist() == [0, 1]


def test_no_overlap_names_both_time_ranges(pair: tuple[Trajectory, Trajectory]) -> None:
    ref, est = pair
    late = Trajectory(est.timestamps + 1000.0, est.poses)
    with pytest.raises(InputFormatError, match=r"no matching timestamps.*reference spans \[100\.\d+, .*estimate \[11"):
        associate(ref, late)


@pytest.mark.parametrize("mode", ["none", "se3", "sim3", "origin"])
def test_ape_and_alignment_match_evo(pair: tuple[Trajectory, Trajectory], mode: str) -> None:
    pytest.importorskip("evo")
    from evo.core import metrics

    ref, est = pair
    r, e, transform = evo_synced(ref, est, mode)
    m = metrics.APE(metrics.PoseRelation.translation_part)
    m.process_data((r, e))
    ours = ape(ref, est, align=mode)
    assert ours.matched == len(m.error)
    np.testing.assert_allclose(ours.errors, m.error, rtol=0, atol=TOL)
    stats = m.get_all_statistics()
    assert set(stats) == set(ours.stats)
    for k, v in stats.items():
        assert ours.stats[k] == pytest.approx(v, abs=TOL), k
    np.testing.assert_allclose(ours.distances, r.distances, atol=TOL)
    if mode in ("se3", "sim3"):
        rot, t, s = transform
        np.testing.assert_allclose(ours.alignment.rotation, rot, atol=TOL)
        np.testing.assert_allclose(ours.alignment.translation, t, atol=TOL)
        assert ours.alignment.scale == pytest.approx(s, abs=TOL)
    if mode != "none":
        mr, me = associate(ref, est)
        aligned, _ = align(mr, me, mode)
        np.testing.assert_allclose(np.asarray(aligned.positions), e.positions_xyz, atol=TOL)
        q_ours, q_evo = np.asarray(aligned.poses.params)[:, :4], e.orientations_quat_wxyz
        sign = np.sign(np.sum(q_ours * q_evo, axis=1, keepdims=True))
        np.testing.assert_allclose(q_ours * sign, q_evo, atol=TOL)


RELATIONS = {
    "trans": "translation_part",
    "rot_deg": "rotation_angle_deg",
    "rot_rad": "rotation_angle_rad",
    "full": "full_transformation",
    "point_distance": "point_distance",
}


@pytest.mark.parametrize("relation", list(RELATIONS))
@pytest.mark.parametrize(("delta", "unit"), [(1, "frames"), (7, "frames"), (2.5, "m")])
@pytest.mark.parametrize("mode", ["none", "sim3"])
def test_rpe_matches_evo(
    pair: tuple[Trajectory, Trajectory], relation: str, delta: float, unit: str, mode: str
) -> None:
    pytest.importorskip("evo")
    from evo.core import metrics
    from evo.core.units import Unit

    ref, est = pair
    r, e, _ = evo_synced(ref, est, mode)
    evo_unit = Unit.frames if unit == "frames" else Unit.meters
    m = metrics.RPE(getattr(metrics.PoseRelation, RELATIONS[relation]), delta, evo_unit, all_pairs=False)
    m.process_data((r, e))
    ours = rpe(ref, est, delta, unit, relation, align=mode)
    assert len(ours.errors) == len(m.error) > 3
    np.testing.assert_array_equal(ours.pairs[:, 1], m.delta_ids)
    np.testing.assert_allclose(ours.errors, m.error, rtol=0, atol=TOL)
    for k, v in m.get_all_statistics().items():
        assert ours.stats[k] == pytest.approx(v, abs=TOL), k


def test_path_length_matches_evo(pair: tuple[Trajectory, Trajectory]) -> None:
    pytest.importorskip("evo")
    ref, _ = pair
    assert path_length(ref) == pytest.approx(evo_traj(ref).path_length, abs=TOL)


def test_known_rigid_transform_and_scale_are_removed(pair: tuple[Trajectory, Trajectory]) -> None:
    ref, _ = pair
    frame = SE3.exp(jnp.asarray([0.3, -0.1, 2.0, 5.0, -3.0, 1.0]))
    moved = Trajectory(ref.timestamps, frame @ ref.poses)
    res = ape(ref, moved, align="se3")
    assert res.stats["max"] < 1e-10
    np.testing.assert_allclose(res.alignment.rotation, np.asarray(frame.inverse().rotation.as_matrix()), atol=1e-12)
    assert ape(ref, moved, align="none").stats["min"] > 1.0
    p = np.array(moved.poses.params)
    p[:, 4:] *= 0.25
    scaled = Trajectory(ref.timestamps, SE3(jnp.asarray(p)))
    res = ape(ref, scaled, align="sim3")
    assert res.alignment.scale == pytest.approx(4.0, rel=1e-12) and res.stats["max"] < 1e-10
    assert ape(ref, scaled, align="se3").stats["rmse"] > 1.0
    assert rpe(ref, moved, 3, "frames", "rot_deg").stats["max"] < 1e-9


def test_umeyama_closed_form_and_degenerate() -> None:
    rng = np.random.default_rng(3)
    x = rng.standard_normal((20, 3))
    rot = np.asarray(SO3.exp(jnp.asarray([0.4, -1.0, 2.5])).as_matrix())
    y = 2.5 * x @ rot.T + np.array([1.0, 2.0, 3.0])
    r, t, s = umeyama(x, y, with_scale=True)
    np.testing.assert_allclose(r, rot, atol=1e-12)
    np.testing.assert_allclose(t, [1.0, 2.0, 3.0], atol=1e-12)
    assert s == pytest.approx(2.5, rel=1e-12)
    line = np.outer(np.arange(10.0), [1.0, 2.0, 0.5])
    with pytest.raises(InputFormatError, match="degenerate"):
        umeyama(line, line + 1.0)


def test_lever_arm_ape_closed_form(pair: tuple[Trajectory, Trajectory]) -> None:
    ref, _ = pair
    arm = np.array([0.1, -0.2, 0.55])
    rot = np.asarray(ref.poses.rotation.as_matrix())
    prism = PositionTrack(ref.timestamps, np.asarray(ref.positions) + rot @ arm)
    for mode in ("none", "se3"):
        assert ape(prism, ref, align=mode, lever_arm=arm).stats["max"] < 1e-10
    without = ape(prism, ref, align="none")
    np.testing.assert_allclose(without.errors, np.linalg.norm(arm), rtol=1e-12)
    r = rpe(prism, ref, 4, "frames", "point_distance", lever_arm=arm)
    assert r.stats["max"] < 1e-10
    assert rpe(prism, ref, 4, "frames", "point_vector", lever_arm=arm).stats["max"] < 1e-10
    assert rpe(prism, ref, 4, "frames", "point_distance").stats["max"] > 1e-3
    with pytest.raises(ValueError, match="position-only"):
        rpe(prism, ref, 1, "frames", "trans")
    with pytest.raises(ValueError, match="lever_arm needs"):
        rpe(ref, ref, 1, "frames", "trans", lever_arm=arm)


def test_positions_from_identity_quaternion_tum(pair: tuple[Trajectory, Trajectory]) -> None:
    ref, _ = pair
    arm = np.array([0.0, 0.0, 0.55])
    prism = np.asarray(ref.positions) + np.asarray(ref.poses.rotation.as_matrix()) @ arm
    ident = np.tile([1.0, 0, 0, 0], (len(ref), 1))
    gt = Trajectory(ref.timestamps, SE3(jnp.asarray(np.concatenate([ident, prism], -1))))
    res = ape(PositionTrack.from_trajectory(gt), ref, lever_arm=arm)
    assert res.stats["max"] < 1e-10


def test_loop_error_closed_form() -> None:
    s = np.linspace(0.0, 2 * np.pi, 201)
    circle = np.stack([10 * np.cos(s), 10 * np.sin(s), np.zeros_like(s)], -1)
    t = np.arange(len(s), dtype=float)
    gt = PositionTrack(t, circle)
    drift = np.array([0.3, -0.4, 0.0])
    est = PositionTrack(t, circle + np.linspace(0, 1, len(s))[:, None] * drift)
    assert loop_error(gt) < 1e-12
    assert loop_error(est) == pytest.approx(0.5, rel=1e-12)
    assert loop_error(est, gt) == pytest.approx(0.5, rel=1e-12)
    assert loop_error_ratio(est, gt) == pytest.approx(0.5 / path_length(gt), rel=1e-12)
    # a true path that does not close: only the estimate's deviation from it counts
    open_gt = PositionTrack(t, circle + np.linspace(0, 1, len(s))[:, None] * np.array([0.0, 0.0, 2.0]))
    open_est = PositionTrack(t, open_gt.positions + np.linspace(0, 1, len(s))[:, None] * drift)
    assert loop_error(open_est, open_gt) == pytest.approx(0.5, rel=1e-12)
    assert path_length(gt) == pytest.approx(20 * np.pi, rel=1e-3)


def test_rpe_bad_delta(pair: tuple[Trajectory, Trajectory]) -> None:
    ref, est = pair
    with pytest.raises(ConfigError, match="no pose pair"):
        rpe(ref, est, 1e6, "m")
    with pytest.raises(ConfigError, match="whole number"):
        rpe(ref, est, 1.5, "frames")


def test_plots_write_pngs(pair: tuple[Trajectory, Trajectory], tmp_path: Path) -> None:
    ref, est = pair
    res = ape(ref, est)
    rng = np.random.default_rng(0)
    files = [
        plot_trajectory(tmp_path / "traj.png", est, ref, title="t"),
        plot_trajectory(tmp_path / "traj_xz.png", est, side="xz"),
        plot_ape_over_distance(tmp_path / "ape.png", res),
        plot_residual_histograms(
            tmp_path / "sub" / "res.png",
            {"odometry": rng.standard_normal(500), "reprojection": np.append(rng.standard_normal((100, 2)), np.nan)},
            unit="px",
        ),
    ]
    for f in files:
        assert f.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and f.stat().st_size > 5000

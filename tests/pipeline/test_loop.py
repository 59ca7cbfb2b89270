"""Loop closure in a tunnel whose stretches look alike: the simulated tunnel's walls are the
same everywhere, so geometry alone would 'verify' a loop at the wrong place along the axis.
The loop closer must (a) not let such a loop pull along the axis (degenerate information),
(b) measure correctly what it does constrain, (c) reject a loop inconsistent with the
odometry."""

from __future__ import annotations

import numpy as np
import pytest

from jaxslam.lidar import deskew, voxel_downsample
from jaxslam.lie import host
from jaxslam.pipeline import Keyframe, LoopConfig
from jaxslam.pipeline._lidar_frontend import ScanResult
from jaxslam.pipeline._loop import LoopCloser
from jaxslam.sim import SimConfig, Simulation

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def tunnel():
    sim = Simulation.create(SimConfig(seed=0))
    T_bl = host.make_pose(np.eye(3), np.asarray(sim.config.lidar.translation))
    tr = sim.trajectory

    def keyframe(index: int, t: float) -> tuple[Keyframe, np.ndarray]:
        scan = sim.lidar.scan(t, tr.pose)
        dur = float(scan["point_times"].max())
        times = t + np.linspace(0, dur, 6)
        st = tr.state(times)
        poses = host.make_poses(st["R"], st["p"]) @ T_bl
        ref = t + dur / 2
        pts = deskew(
            scan["points"], t + scan["point_times"], (poses[:, :3, :3], poses[:, :3, 3], times), reference_time=ref
        )
        body = host.transform_points(T_bl, np.asarray(voxel_downsample(pts, 0.1)))
        s = tr.state(np.array([ref]))
        T = host.make_pose(s["R"][0], s["p"][0])
        reg = type("Reg", (), {"converged": True})()
        return Keyframe(index, ref, ScanResult(ref, T, reg, body, False, 1.0)), T  # type: ignore[arg-type]

    old = [keyframe(i, t) for i, t in enumerate(np.arange(3.0, 60.0, 1.0))]
    # the return leg: the robot drives back along -x from ~t = 73 s
    cur_kf, cur_T = keyframe(len(old), 100.0)
    return [k for k, _ in old], np.stack([T for _, T in old]), cur_kf, cur_T


def _detect(tunnel, shift: np.ndarray, config: LoopConfig | None = None):
    kfs, T_old, cur, T_cur = tunnel
    est_cur = T_cur @ host.make_pose(np.eye(3), shift)  # the current estimate is wrong by `shift` (body)
    poses = np.concatenate([T_old, est_cur[None]])
    closer = LoopCloser(config or LoopConfig(every=1, chi2_gate=1e9), np.eye(4))
    loops = closer.detect(len(kfs), [*kfs, cur], poses)
    return closer, loops, T_old, T_cur


def _axis_sigma(loop) -> float:
    """Sigma of the loop measurement along the tunnel (world x) in the current body frame."""
    cov = np.linalg.inv(loop.information)
    return float(np.sqrt(cov[3, 3]))  # body x is the tunnel axis (the robot drives along it)


def test_correct_place_loop_measures_the_truth(tunnel) -> None:
    closer, loops, T_old, T_cur = _detect(tunnel, np.zeros(3))
    assert len(loops) == 1, closer.rejected
    lp = loops[0]
    T_gt = host.inverse(T_old[lp.i]) @ T_cur
    e = host.se3_log(host.inverse(lp.T) @ T_gt)
    assert np.linalg.norm(e[4:]) < 0.02 and np.degrees(np.linalg.norm(e[:3])) < 0.3, e


def test_loop_at_the_wrong_place_along_the_axis_cannot_pull(tunnel) -> None:
    """The estimate is 1.5 m off along the axis: the walls match anyway (a false loop for an
    appearance-only system); the measurement keeps the estimate's axis position and says so
    with a large sigma along the axis, while lateral, vertical and rotation are right."""
    closer, loops, T_old, T_cur = _detect(tunnel, np.array([1.5, 0.0, 0.0]))
    assert len(loops) == 1, closer.rejected
    lp = loops[0]
    assert lp.degenerate
    assert _axis_sigma(lp) > 0.3, _axis_sigma(lp)
    T_gt = host.inverse(T_old[lp.i]) @ T_cur
    e = host.se3_log(host.inverse(lp.T) @ T_gt)
    assert np.linalg.norm(e[4:]) < 0.03 and np.degrees(np.linalg.norm(e[:3])) < 0.3, e  # lateral, vertical


def test_inconsistent_loop_is_rejected_by_the_gate(tunnel) -> None:
    """An estimate 0.6 m off sideways after little travel: registration snaps to the wall, and
    the chi^2 gate against the odometry (drift 1 % of the distance) rejects the jump."""
    closer, loops, _, _ = _detect(tunnel, np.array([0.0, 0.6, 0.0]), LoopConfig(every=1, drift_per_m=0.001))
    assert not loops
    assert any("inconsistent" in r[2] or "fitness" in r[2] or "registration" in r[2] for r in closer.rejected)

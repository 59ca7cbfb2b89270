"""The sparse visual map (Table 10): tracks triangulated at known poses and refined by the
structure-only bundle adjustment recover the points, and report pixel-noise-sized residuals."""

from __future__ import annotations

import numpy as np

from jaxslam.lie import host
from jaxslam.pipeline import Keyframe
from jaxslam.pipeline._mapping import build_sparse_map
from jaxslam.pipeline._visual import KeyframeFeatures

F = 300.0
T_BC = host.params_to_matrix(np.array([0.5, -0.5, 0.5, -0.5, 0.2, 0.0, 0.3]))  # camera looks along body x


def _scene(noise_px: float, seed: int = 0):
    rng = np.random.default_rng(seed)
    pts = np.stack([rng.uniform(4, 12, 200), rng.uniform(-1.5, 1.5, 200), rng.uniform(0, 3, 200)], 1)
    poses = np.stack(
        [host.make_pose(host.so3_exp(np.array([0, 0, 0.01 * k])), np.array([0.3 * k, 0, 0.5])) for k in range(6)]
    )
    kfs = []
    for k, T in enumerate(poses):
        Xc = host.transform_points(host.inverse(T @ T_BC), pts)
        xn = Xc[:, :2] / Xc[:, 2:3] + rng.normal(0, noise_px / F, (len(pts), 2))
        seen = np.arange(len(pts)) % 6 != k  # each point misses one keyframe
        feats = KeyframeFeatures(
            k,
            float(k),
            xn[seen] * F,
            xn[seen],
            np.zeros((seen.sum(), 64)),
            np.ones(seen.sum()),
            np.full((seen.sum(), 3), np.nan),
            np.nonzero(seen)[0],
        )
        kfs.append(Keyframe(k, float(k), None, feats, None, True))
    return pts, poses, kfs


def test_exact_observations_give_the_points_and_zero_residuals() -> None:
    pts, poses, kfs = _scene(0.0)
    sm = build_sparse_map(kfs, poses, T_BC, F)
    assert len(sm.points) == len(pts)
    np.testing.assert_allclose(np.sort(sm.points, axis=0), np.sort(pts, axis=0), atol=1e-8)
    assert sm.residuals_px.max() < 1e-6
    assert sm.statistics()["track_length_min"] == 5 and sm.statistics()["residuals"] == 5 * len(pts)


def test_noisy_observations_give_pixel_noise_residuals() -> None:
    _, poses, kfs = _scene(0.5, seed=1)
    st = build_sparse_map(kfs, poses, T_BC, F).statistics()
    # 5 observations (10 residuals) of 3 unknowns: the RMS of the 2-D error norm is
    # sigma * sqrt(2 * (10 - 3) / 10) = 0.59 px
    assert 0.5 < st["reproj_rmse_px"] < 0.7, st
    assert st["points"] == 200 and st["residuals_below_1px"] > 0.9


def test_unregistered_keyframes_and_single_observations_are_left_out() -> None:
    _, poses, kfs = _scene(0.0)
    for kf in kfs[1:]:
        kf.registered = False
    sm = build_sparse_map(kfs, poses, T_BC, F)
    assert len(sm.points) == 0 and sm.statistics()["residuals"] == 0

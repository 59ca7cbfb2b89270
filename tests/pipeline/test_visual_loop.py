"""Visual loops by projection (jaxslam.pipeline._visual_loop) on the simulated tunnel: the back
leg's camera sees the wall patches the outbound leg saw, from the mirrored position. Given the
outbound keyframe's features (with depth from its "LiDAR" points) and a prediction of the
current pose that is wrong along the tunnel by tens of centimetres (what the degenerate LiDAR
and a slightly short visual odometry leave), the closer must measure the true relative pose to
about a centimetre along the axis; and it must refuse a candidate from another stretch of the
same-looking tunnel that the estimate wrongly puts here."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from jaxslam.lie import host
from jaxslam.pipeline import LoopConfig, PipelineConfig, RigConfig
from jaxslam.pipeline._visual import VisualFrontend, distort_normalized, plane_depth, undistort_normalized
from jaxslam.pipeline._visual_loop import LoopQuery, VisualLoopCloser, translation_only
from jaxslam.sim import SimConfig, Simulation
from jaxslam.sim._recording import rig_calibration

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def scene(frames):
    rig, _, kfs = frames
    return rig, *(kf[:3] for kf in kfs)


@pytest.fixture(scope="module")
def frames():
    """The rig, the visual front end and three keyframes, each ``(features, image, T_wb,
    body-frame "LiDAR" points)``: outbound at x = 20 m, back at 26 m, outbound at 13 m."""
    sim = Simulation.create(SimConfig(seed=0))
    rig = RigConfig(**{k: tuple(v) if isinstance(v, list) else v for k, v in rig_calibration(sim.config).items()})
    front = VisualFrontend(PipelineConfig().vision, rig)
    tr, cam = sim.trajectory, sim.camera
    t = np.arange(0.0, tr.duration, 0.05)
    st = tr.state(t)
    x = st["p"][:, 0]
    heading = st["R"][:, 0, 0]

    def at(x_want: float, outbound: bool) -> int:
        leg = np.nonzero((heading > 0.99) if outbound else (heading < -0.99))[0]
        return int(leg[np.argmin(np.abs(x[leg] - x_want))])

    def keyframe(i: int, index: int):
        cam.exposure_gain = None  # meter this frame afresh
        img, _ = cam.render(t[i], st["R"][i], st["p"][i], st["v"][i], st["omega"][i])
        R_wc, p_wc = cam.pose(st["R"][i], st["p"][i])
        _, depth = cam.radiance(R_wc, p_wc)
        # "LiDAR": the scene's surface points on a coarse pixel grid, in the body frame
        pc = np.stack([cam.xn * depth, cam.yn * depth, depth], axis=-1)[::6, ::6].reshape(-1, 3)
        T_wb = host.make_pose(st["R"][i], st["p"][i])
        body = host.transform_points(front.T_bc, pc[np.isfinite(pc).all(axis=1)])
        feats = front.features(index, t[i], img, body)
        return feats, img, T_wb, body

    out_i = keyframe(at(20.0, True), 0)
    back = keyframe(at(26.0, False), 1)  # looks down the tunnel at the patches out_i saw
    elsewhere = keyframe(at(13.0, True), 0)  # the same-looking tunnel 7 m away (one lamp spacing)
    return rig, front, (out_i, back, elsewhere)


def _closer(rig: RigConfig, **changes) -> VisualLoopCloser:
    """One query's loops, returned at once (the confirmation by a later query has its own
    tests in test_visual_loop_confirm.py)."""
    cfg = dataclasses.replace(LoopConfig(), **{"min_gap_s": 0.0, "visual_confirm_m": 0.0, **changes})
    T_bc = host.params_to_matrix(np.asarray(rig.body_T_camera))
    K = rig.K()
    return VisualLoopCloser(cfg, T_bc, 0.5 * (K[0, 0] + K[1, 1]), rig.camera_size, K, rig.camera_distortion)


def _query(T_old: np.ndarray, T_cur_est: np.ndarray, travelled: float = 30.0) -> LoopQuery:
    return LoopQuery(1, 100.0, np.stack([T_old, T_cur_est]), np.array([0.0, travelled]), np.array([0.0, 100.0]))


@pytest.mark.parametrize("error", [(0.3, 0.0, 0.0), (-0.4, 0.01, 0.02)])
def test_measures_the_axis_from_the_mirrored_view(scene, error):
    rig, (f_old, img_old, T_old), (_, img_cur, T_cur), _ = scene
    wrong = T_cur @ host.make_pose(np.eye(3), np.asarray(error))  # body x is along the tunnel
    closer = _closer(rig)
    loops = closer.detect(_query(T_old, wrong), img_cur, {0: f_old}, {0: img_old})
    assert len(loops) == 1, closer.rejected
    lp = loops[0]
    T_true = host.inverse(T_old) @ T_cur
    e = host.se3_log(host.inverse(lp.T) @ T_true)
    assert abs(e[3]) < 0.02  # along the axis: 30-40 cm of prediction error measured to 2 cm
    assert np.linalg.norm(e[4:]) < 0.03
    assert lp.inliers >= 15 and lp.ncc > 0.8
    # the information says the loop knows the axis well (a LiDAR loop here would not)
    assert np.all(np.linalg.eigvalsh(lp.information) > 0)
    assert lp.information[3, 3] > 1.0 / 0.05**2


def test_learned_loop_weights_scale_the_information(scene):
    """``loop.axis_weights`` (learned by ``jaxslam tune``, which re-weights every factor tagged
    "loop", visual ones included) multiply the visual loop's information as they do a LiDAR
    loop's: the same measurement, its (rotation, translation) blocks scaled."""
    rig, (f_old, img_old, T_old), (_, img_cur, T_cur), _ = scene
    wrong = T_cur @ host.make_pose(np.eye(3), np.array([0.3, 0.0, 0.0]))
    plain = _closer(rig).detect(_query(T_old, wrong), img_cur, {0: f_old}, {0: img_old})
    weighted = _closer(rig, axis_weights=(4.0, 9.0)).detect(_query(T_old, wrong), img_cur, {0: f_old}, {0: img_old})
    assert len(plain) == len(weighted) == 1
    np.testing.assert_allclose(weighted[0].T, plain[0].T, atol=1e-12)
    s = np.array([2.0] * 3 + [3.0] * 3)
    np.testing.assert_allclose(weighted[0].information, plain[0].information * s[:, None] * s[None, :], rtol=1e-12)


def test_refuses_a_lookalike_stretch_the_estimate_puts_here(scene):
    """The candidate keyframe really sits 7 m away (a lamp spacing: lamps, joints and trays
    repeat); the estimate wrongly puts it where the mirrored view would see it. Its patches
    must not align, whatever shift along the track is tried."""
    rig, (_, _, T_old), (_, img_cur, T_cur), (f_far, img_far, _) = scene
    closer = _closer(rig)
    loops = closer.detect(_query(T_old, T_cur), img_cur, {0: f_far}, {0: img_far})
    assert loops == []
    assert closer.rejected and closer.attempts == 1


@pytest.mark.parametrize("error", [0.28, -0.29])
def test_a_drift_at_the_range_edge_does_not_hand_the_loop_to_an_alias(scene, error):
    """Over 20 m at 0.5 %/m the expected drift gives the smallest search range, 0.3 m; a prediction wrong
    by nearly that much puts the true peak at the range's edge, where it cannot show as a
    peak, and an alias of the cable-tray rungs (0.3 m apart) inside it. The search reaches
    ``visual_alias_margin`` further, so the true peak is found and wins; with no margin the
    same scene hands the loop to the alias (the trap is real)."""
    rig, (f_old, img_old, T_old), (_, img_cur, T_cur), _ = scene
    wrong = T_cur @ host.make_pose(np.eye(3), np.array([error, 0.0, 0.0]))
    T_true = host.inverse(T_old) @ T_cur
    along = {}
    for margin in (0.0, LoopConfig().visual_alias_margin):
        closer = _closer(rig, visual_alias_margin=margin, visual_drift_per_m=0.005)
        loops = closer.detect(_query(T_old, wrong, travelled=20.0), img_cur, {0: f_old}, {0: img_old})
        assert len(loops) == 1, closer.rejected
        along[margin] = abs(host.se3_log(host.inverse(loops[0].T) @ T_true)[3])
    assert along[LoopConfig().visual_alias_margin] < 0.02
    assert along[0.0] > 0.2


@pytest.mark.parametrize("error", [0.33, -0.5, 0.7])
def test_a_drift_past_the_range_is_measured_or_refused_never_faked(scene, error):
    """The prediction is wrong by more than the 0.3 m range (20 m at 0.5 %/m). Just past it
    (0.33 m, within ``visual_alias_margin``) the true peak is still found, beats the rung
    aliases inside and passes the consistency gate (drift sigma 0.1 m here); at 0.5 m the gate
    refuses it; at 0.7 m, beyond the search, only aliases align and they tie. No alias is
    ever taken."""
    rig, (f_old, img_old, T_old), (_, img_cur, T_cur), _ = scene
    wrong = T_cur @ host.make_pose(np.eye(3), np.array([error, 0.0, 0.0]))
    closer = _closer(rig, visual_drift_per_m=0.005)
    loops = closer.detect(_query(T_old, wrong, travelled=20.0), img_cur, {0: f_old}, {0: img_old})
    assert len(loops) == (1 if abs(error) < 0.4 else 0), closer.rejected
    for lp in loops:
        e = host.se3_log(host.inverse(lp.T) @ (host.inverse(T_old) @ T_cur))
        assert abs(e[3]) < 0.02


def test_a_wide_search_keeps_the_first_searchs_competitors(scene):
    """The prediction 1.5 m off over 20 m: the first search (0.6 m) finds two rung aliases
    that tie (-0.3 / +0.3 m) and is ambiguous; the wide one (1.5 m) has more peaks than
    ``visual_hypotheses`` and, left to its own, drops the +0.3 m alias and hands the loop to
    the other (1.2 m off). With the first search's hypotheses aligned too, the tie stands
    and nothing is accepted."""
    rig, (f_old, img_old, T_old), (_, img_cur, T_cur), _ = scene
    wrong = T_cur @ host.make_pose(np.eye(3), np.array([1.5, 0.0, 0.0]))
    q = _query(T_old, wrong, travelled=20.0)
    closer = _closer(rig, visual_drift_per_m=0.005, visual_wide_drift_per_m=0.02, visual_widen_ambiguous=True)
    assert closer.detect(q, img_cur, {0: f_old}, {0: img_old}) == [], closer.accepted
    assert closer.wide_searches == 1 and closer.rejected[-1][2].startswith("wide search: ambiguous")
    # the trap is real: the wide search alone takes the alias
    alone = _closer(rig, visual_drift_per_m=0.005, visual_wide_drift_per_m=0.02)
    alone._rectified = {}
    T_ki = host.inverse(q.poses[1] @ alone.T_bc) @ q.poses[0] @ alone.T_bc  # camera k <- camera i
    loop, _ = alone._verify_at(0, 1, f_old, (img_old, img_cur), T_ki, 20.0, q.poses, 0.02, True)
    assert loop is not None
    assert abs(host.se3_log(host.inverse(loop.T) @ (host.inverse(T_old) @ T_cur))[3]) > 1.0


def test_a_wide_search_follows_too_few_aligned_patches_only(scene, monkeypatch):
    """The second search, at ``visual_wide_drift_per_m``, runs only where the first found too
    few aligned patches (on dark seed 6's way back the estimate was 0.64 m off keyframes 15 m
    back, past the 0.6 m searched), or was ambiguous with ``visual_widen_ambiguous``, and only
    where it reaches further (its own clamp, ``visual_wide_max_shift``); the first search's
    refusal is then not counted as a refused loop. Other refusals (inconsistent, across the
    track) are final."""
    rig = scene[0]
    # the semantics, not the defaults: a 1 % wide drift clamped like the first search
    base = {"visual_wide_drift_per_m": 0.01, "visual_wide_max_shift": 1.0, "visual_widen_ambiguous": False}
    calls: list[float] = []

    def stub(result, why):
        def verify_at(self, i, k, fi, images, T_ki, travelled, poses, drift_per_m, wide=False, extra=()):
            calls.append(drift_per_m)
            assert wide == (drift_per_m == cfg.visual_wide_drift_per_m)
            if wide and result is not None:
                return result, ""
            self.rejected.append((i, k, why))
            # "N patches align": too few
            return None, "too few" if why[0].isdigit() else "ambiguous" if why.startswith("ambiguous") else "other"

        return verify_at

    found = object()
    for why, travelled, expect_calls, expect, changes in [
        ("3 patches align", 15.0, [0.005, 0.01], found, {}),  # too few: searched again, found
        ("ambiguous: 30 and 28 patches align", 15.0, [0.005], None, {}),
        ("ambiguous: 30 and 28 patches align", 15.0, [0.005, 0.01], found, {"visual_widen_ambiguous": True}),
        ("inconsistent with odometry (chi2 40.0)", 15.0, [0.005], None, {"visual_widen_ambiguous": True}),
        ("3 patches align", 300.0, [0.005], None, {}),  # both ranges at visual_max_shift
        ("3 patches align", 300.0, [0.005, 0.01], found, {"visual_wide_max_shift": 2.0}),
        ("3 patches align", 2.0, [0.005], None, {}),  # both at visual_min_shift
    ]:
        calls.clear()
        monkeypatch.setattr(VisualLoopCloser, "_verify_at", stub(found, why))
        cfg = dataclasses.replace(LoopConfig(), **{**base, **changes})
        closer = _closer(rig, **{**base, **changes})
        assert closer._verify(0, 1, None, (None, None), np.eye(4), travelled, None) is expect, why
        assert calls == expect_calls, why
        assert closer.wide_searches == (len(expect_calls) - 1)
        assert closer.rejected == ([] if expect is found else [(0, 1, why)])
    monkeypatch.setattr(VisualLoopCloser, "_verify_at", stub(None, "3 patches align"))
    closer = _closer(rig, **base)
    assert closer._verify(0, 1, None, (None, None), np.eye(4), 15.0, None) is None
    assert closer.rejected == [(0, 1, "wide search: 3 patches align")]  # one refusal, the last
    closer = _closer(rig, **{**base, "visual_wide_drift_per_m": 0.0})
    calls.clear()
    assert closer._verify(0, 1, None, (None, None), np.eye(4), 15.0, None) is None and calls == [0.005]
    assert closer.search_range(0.005, 15.0) == pytest.approx(0.6)
    assert closer.search_range(0.01, 15.0) == pytest.approx(0.75)
    wide = _closer(rig, visual_wide_max_shift=2.5)  # the wide clamp is the wide search's only
    assert wide.search_range(0.02, 100.0) == pytest.approx(1.3)
    assert wide.search_range(0.02, 100.0, wide=True) == pytest.approx(2.8)
    assert wide.search_range(0.02, 30.0, wide=True) == pytest.approx(2.1)


def test_a_dark_wide_search_never_takes_an_alias(frames):
    """Dark frames (mean grey level 5), the prediction 0.55 m off over 15 m: the first search
    aligns too few patches, the wide one is run and finds the rung aliases tied with the
    truth, so nothing is accepted; where the first search finds the loop (0.2 m off, bright),
    no second search runs."""
    rig, front, ((_, img_old, T_old, body_old), (_, img_cur, T_cur, _), _) = frames
    dark_old, dark_cur = _darken(img_old, 1, 5.0), _darken(img_cur, 2, 5.0)
    f_dark = front.features(0, 0.0, dark_old, body_old)
    wrong = T_cur @ host.make_pose(np.eye(3), np.array([0.55, 0.0, 0.0]))
    closer = _closer(rig)
    assert closer.detect(_query(T_old, wrong, travelled=15.0), dark_cur, {0: f_dark}, {0: dark_old}) == []
    assert closer.wide_searches == 1 and len(closer.rejected) == 1
    assert closer.rejected[0][2].startswith("wide search:")
    f_old = front.features(0, 0.0, img_old, body_old)
    wrong = T_cur @ host.make_pose(np.eye(3), np.array([0.2, 0.0, 0.0]))
    closer = _closer(rig)
    loops = closer.detect(_query(T_old, wrong, travelled=15.0), img_cur, {0: f_old}, {0: img_old})
    assert len(loops) == 1 and closer.wide_searches == 0
    assert loops[0].drift_per_m == LoopConfig().visual_drift_per_m
    assert abs(host.se3_log(host.inverse(loops[0].T) @ (host.inverse(T_old) @ T_cur))[3]) < 0.02


def test_not_due_without_vision_loops_or_at_the_first_keyframe(scene):
    rig = scene[0]
    assert not _closer(rig).due(0)
    assert _closer(rig).due(2) and not _closer(rig).due(3)
    assert not _closer(rig, visual=False).due(2)
    assert not _closer(rig, enabled=False).due(2)


def test_too_far_or_too_recent_candidates_are_skipped(scene):
    rig, (f_old, img_old, T_old), (_, img_cur, T_cur), _ = scene
    far = T_cur @ host.make_pose(np.eye(3), np.array([20.0, 0.0, 0.0]))
    closer = _closer(rig)
    assert closer.detect(_query(T_old, far), img_cur, {0: f_old}, {0: img_old}) == []
    recent = dataclasses.replace(_query(T_old, T_cur), times=np.array([95.0, 100.0]))
    closer = _closer(rig, min_gap_s=15.0)
    assert closer.detect(recent, img_cur, {0: f_old}, {0: img_old}) == [] and closer.attempts == 0


def test_translation_only_recovers_a_translation():
    rng = np.random.default_rng(3)
    X = rng.uniform([-2, -1, 3], [2, 1, 8], size=(40, 3))
    T = host.make_pose(host.so3_exp(np.array([0.01, -0.02, 0.005])), np.array([0.1, -0.05, 0.4]))
    Xc = host.transform_points(T, X)
    x = Xc[:, :2] / Xc[:, 2:3]
    start = T.copy()
    start[:3, 3] += [0.05, 0.02, -0.3]
    fit = translation_only(X, x, start, 300.0)
    assert fit is not None
    T_fit, inliers, err, H = fit
    np.testing.assert_allclose(T_fit[:3, 3], T[:3, 3], atol=1e-6)
    assert len(inliers) == 40 and np.max(err) < 1e-6
    assert np.all(np.linalg.eigvalsh(H) > 0)


def test_distortion_round_trip():
    K = np.array([[280.0, 0, 256], [0, 280.0, 160], [0, 0, 1]])
    dist = (-0.25, 0.06, 2e-4, -1e-4)
    xn = np.random.default_rng(0).uniform([-0.8, -0.5], [0.8, 0.5], size=(50, 2))
    xd = distort_normalized(xn, dist)
    uv = np.stack([K[0, 0] * xd[:, 0] + K[0, 2], K[1, 1] * xd[:, 1] + K[1, 2]], 1)
    np.testing.assert_allclose(undistort_normalized(uv, K, dist, iters=60), xn, atol=1e-9)
    np.testing.assert_array_equal(distort_normalized(xn, (0.0, 0.0, 0.0, 0.0)), xn)


def test_plane_depth_normals_face_the_camera():
    rng = np.random.default_rng(1)
    # a wall x = 1.5 m (camera frame) seen at a grazing angle
    P = np.stack([np.full(400, 1.5), rng.uniform(-1, 1, 400), rng.uniform(2, 8, 400)], 1)
    xn = P[:50, :2] / P[:50, 2:3]
    X, n = plane_depth(xn, P, radius=0.05, normals=True)
    ok = np.isfinite(X[:, 0])
    assert ok.sum() > 40
    np.testing.assert_allclose(X[ok], P[:50][ok], atol=1e-9)
    np.testing.assert_allclose(n[ok], np.tile([-1.0, 0.0, 0.0], (ok.sum(), 1)), atol=1e-9)


def test_dark_or_flat_images_give_no_loop_and_no_error(scene):
    """A black current frame (camera dark), a flat old frame: nothing to compare, no loop."""
    rig, (f_old, img_old, T_old), (_, img_cur, T_cur), _ = scene
    closer = _closer(rig)
    black = np.zeros_like(img_cur)
    assert closer.detect(_query(T_old, T_cur), black, {0: f_old}, {0: img_old}) == []
    flat = np.full_like(img_old, 128)
    assert closer.detect(_query(T_old, T_cur), img_cur, {0: f_old}, {0: flat}) == []
    assert len(closer.rejected) == 2


def _darken(img: np.ndarray, seed: int, mean: float = 4.0, noise: float = 2.0) -> np.ndarray:
    """The frame as the darkest stretch of a dark recording gives it (seed 4 dark, 10-28 m:
    mean grey level 3-7 at full gain, where shot and read noise come to about 2 grey levels;
    ``jaxslam.sim`` camera model): scaled down, noisy, quantised."""
    x = img.astype(np.float64) * (mean / img.mean()) + np.random.default_rng(seed).normal(0.0, noise, img.shape)
    return np.clip(np.rint(x), 0, 255).astype(np.uint8)


def test_dark_frames_align_on_slightly_blurred_images_and_never_to_an_alias(frames):
    """Both frames darkened to a mean grey level of 4-8 with 2 grey levels of noise, the
    prediction 30 cm off along the track, two noise draws each. On the sharp images the noise
    caps a true patch's NCC: at mean 4 only a few patches align at the true shift; the retry
    on images blurred by ``visual_dim_blur_px`` aligns several times as many there. The
    cable-tray rungs (0.3 m apart) align too, so most pairs are refused as ambiguous; what is
    accepted is the true shift (within 3 cm along the axis, never an alias), is marked as
    aligned on blurred images, and with the retry off nothing is accepted at mean 4-6."""
    rig, front, ((_, img_old, T_old, body_old), (_, img_cur, T_cur, _), _) = frames
    wrong = T_cur @ host.make_pose(np.eye(3), np.array([0.3, 0.0, 0.0]))
    T_true = host.inverse(T_old) @ T_cur
    truth = -0.3  # the shift along the track that undoes the prediction's error

    def at_truth(closer: VisualLoopCloser) -> int:
        return max([n for n, moved in closer.last_hypotheses if abs(moved - truth) < 0.05], default=0)

    accepted = []
    for mean in (4.0, 5.0, 6.0, 8.0):
        for seed in (1, 3):
            dark_old, dark_cur = _darken(img_old, seed, mean), _darken(img_cur, seed + 1, mean)
            f_old = front.features(0, 0.0, dark_old, body_old)
            args = (_query(T_old, wrong), dark_cur, {0: f_old}, {0: dark_old})
            sharp = _closer(rig, visual_dim_blur_px=0.0)
            sharp_loops = sharp.detect(*args)
            closer = _closer(rig)
            loops = closer.detect(*args)
            if mean == 4.0:
                assert at_truth(sharp) < LoopConfig().visual_min_inliers // 2
                assert at_truth(closer) >= 3 * max(at_truth(sharp), 1)
            if mean <= 6.0:
                assert sharp_loops == []
            for lp in [*sharp_loops, *loops]:
                assert abs(host.se3_log(host.inverse(lp.T) @ T_true)[3]) < 0.03, (mean, seed)
            accepted += [lp for lp in loops if lp.blur_px > 0]
    # the default rungs (1 px; with a ladder also 2 px where 1 px aligned too few: these frames are dark)
    rungs = {r * LoopConfig().visual_dim_blur_px for r in range(1, LoopConfig().visual_dim_blur_rungs + 1)}
    assert accepted and all(lp.blur_px in rungs for lp in accepted)


def test_the_dim_retry_climbs_its_blur_rungs_and_inflates_the_blurred_variance(scene, monkeypatch):
    """``visual_dim_blur_rungs``: where the sharp images and every rung before align too few
    patches, rung r aligns on images blurred by r x ``visual_dim_blur_px``; the rungs stop at
    the first that aligns enough. ``visual_blur_noise_px``: a loop aligned at b px blur gets
    its along-track variance times 1 + (b / noise)^2. Here the sharp and the 1 px alignments
    are made to fail (a bright scene 0.2 m off, where every rung aligns the true shift; blur
    lets the alias 0.28 m further align nearly as well, so ``visual_peak_ratio`` is raised
    here to let the blurred loop through)."""
    rig, (f_old, img_old, T_old), (_, img_cur, T_cur), _ = scene
    wrong = T_cur @ host.make_pose(np.eye(3), np.array([0.2, 0.0, 0.0]))
    T_true = host.inverse(T_old) @ T_cur
    real = VisualLoopCloser._align_hypotheses
    blurs: list[float] = []

    def below(limit: float):
        def align(self, fi, pts, images, T_ki, hyps, reach, blur):
            blurs.append(blur)
            return real(self, fi, pts, images, T_ki, hyps, reach, blur) if blur >= limit else []

        return align

    def run(limit: float, **changes):
        blurs.clear()
        monkeypatch.setattr(VisualLoopCloser, "_align_hypotheses", below(limit))
        # a bright scene: the ladder's darkness gate open, and no inflation unless asked
        changes = {"visual_dim_ladder_max_grey": 255.0, "visual_blur_noise_px": 0.0, **changes}
        closer = _closer(rig, visual_wide_drift_per_m=0.0, visual_peak_ratio=0.95, **changes)
        return closer.detect(_query(T_old, wrong, travelled=15.0), img_cur, {0: f_old}, {0: img_old}), list(blurs)

    loops, tried = run(2.0, visual_dim_blur_rungs=1)
    assert loops == [] and tried == [0.0, 1.0]  # one rung: the 2 px alignment is never tried
    loops, tried = run(2.0, visual_dim_blur_rungs=2)
    assert tried == [0.0, 1.0, 2.0] and len(loops) == 1 and loops[0].blur_px == 2.0
    assert abs(host.se3_log(host.inverse(loops[0].T) @ T_true)[3]) < 0.02
    # the ladder's gate: rungs above the first only where both images are darker than it
    grey = max(float(np.mean(img_old)), float(np.mean(img_cur)))
    gated, tried = run(2.0, visual_dim_blur_rungs=2, visual_dim_ladder_max_grey=grey + 0.5)
    assert tried == [0.0, 1.0, 2.0] and len(gated) == 1
    gated, tried = run(2.0, visual_dim_blur_rungs=2, visual_dim_ladder_max_grey=grey)
    assert gated == [] and tried == [0.0, 1.0]  # as bright as the gate: one rung only
    ladder = {"visual_dim_blur_rungs": 2, "visual_dim_ladder_max_grey": 255.0}
    closer = _closer(rig, visual_wide_drift_per_m=0.0, visual_peak_ratio=0.95, **ladder)
    closer.detect(_query(T_old, wrong, travelled=15.0), img_cur, {0: f_old}, {0: img_old})
    assert closer.ladder_climbs == 1  # counted (metrics.json: visual_loop_ladder_climbs)
    assert run(0.0, visual_dim_blur_rungs=3)[1] == [0.0]  # the sharp images align: no rung
    assert run(1.0, visual_dim_blur_rungs=3)[1] == [0.0, 1.0]  # stops at the first that aligns
    assert run(0.0, visual_dim_blur_rungs=0)[1] == [0.0] and run(9.0, visual_dim_blur_rungs=0)[0] == []
    loose = run(2.0, visual_dim_blur_rungs=2, visual_blur_noise_px=1.0)[0]
    loose_sharp = run(0.0, visual_blur_noise_px=1.0)[0]
    sharp = run(0.0)[0]

    def along_info(lp) -> float:  # the along-track part: body x of the newer keyframe
        return lp.information[3, 3] - 1.0 / LoopConfig().visual_loose_sigma ** 2

    assert along_info(loops[0]) == pytest.approx(5.0 * along_info(loose[0]), rel=1e-9)  # 1 + (2 / 1)^2
    assert along_info(loose_sharp[0]) == pytest.approx(along_info(sharp[0]), rel=1e-12)  # sharp: untouched


def test_a_dark_lookalike_is_refused_on_blurred_images_too(frames):
    """The blurred retry must not make the 7 m look-alike (see above) align: dark frames, the
    estimate wrongly putting the far keyframe here, no loop."""
    rig, front, ((_, _, T_old, _), (_, img_cur, T_cur, _), (_, img_far, _, body_far)) = frames
    for seed in (1, 3):
        dark_far, dark_cur = _darken(img_far, seed), _darken(img_cur, seed + 1)
        f_far = front.features(0, 0.0, dark_far, body_far)
        closer = _closer(rig)
        assert closer.detect(_query(T_old, T_cur), dark_cur, {0: f_far}, {0: dark_far}) == []
        assert closer.rejected and closer.attempts == 1

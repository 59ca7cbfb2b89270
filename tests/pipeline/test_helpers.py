"""The estimator's host-side helpers: NumPy SO(3)/SE(3) (jaxslam.lie.host) against
jaxslam.lie, the pipeline configuration, IMU bookkeeping against closed forms and the
preintegration, and the visual front end's undistortion and LiDAR plane depth."""

from __future__ import annotations

import dataclasses

import jax.numpy as jnp
import numpy as np
import pytest

from jaxslam.errors import ConfigError
from jaxslam.factors import PreintegrationParams, cut_imu_stream, predict_imu_state, preintegrate
from jaxslam.lie import SE3, SO3, host
from jaxslam.pipeline import PipelineConfig, RigConfig, config_from_dict, find_rig, load_config, load_rig, save_config
from jaxslam.pipeline._imu import ImuBuffer, NavState, gravity_alignment, preintegrate_interval, propagate
from jaxslam.pipeline._visual import plane_depth, undistort_normalized
from jaxslam.sim._camera import distort

TOL = 1e-12


def unit(rng: np.random.Generator, n: int) -> np.ndarray:
    a = rng.normal(size=(n, 3))
    return a / np.linalg.norm(a, axis=1, keepdims=True)


def rotvecs(rng: np.random.Generator, n: int, angles) -> np.ndarray:
    """Rotation vectors with the given angles (scalar or (n,)) about random axes."""
    return unit(rng, n) * np.broadcast_to(np.asarray(angles, float), (n,))[:, None]


# angles: generic, tiny (series branches), the SE(3) V-matrix threshold region, near pi
ANGLES = {
    "random": None,
    "zero": 0.0,
    "1e-9": 1e-9,
    "1e-7": 1e-7,
    "1e-3": 1e-3,
    "pi-1e-9": np.pi - 1e-9,
    "pi-1e-6": np.pi - 1e-6,
    "pi": np.pi,
}


def angles_for(name: str, rng: np.random.Generator, n: int) -> np.ndarray:
    return rng.uniform(0, np.pi, n) if ANGLES[name] is None else np.full(n, ANGLES[name])


# --- jaxslam.lie.host ----------------------------------------------------------------------------


@pytest.mark.parametrize("name", list(ANGLES))
def test_so3_exp_and_log_match_jaxslam_lie(name):
    rng = np.random.default_rng(0)
    w = rotvecs(rng, 64, angles_for(name, rng, 64))
    R = host.so3_exp(w)
    np.testing.assert_allclose(R, np.asarray(SO3.exp(w).as_matrix()), rtol=0, atol=TOL)
    np.testing.assert_allclose(R @ np.swapaxes(R, -1, -2), np.broadcast_to(np.eye(3), R.shape), atol=TOL)
    back = host.so3_log(R)
    if name == "pi":  # log at pi is defined up to sign: compare the rotation it gives
        np.testing.assert_allclose(host.so3_exp(back), R, rtol=0, atol=TOL)
        np.testing.assert_allclose(np.linalg.norm(back, axis=1), np.pi, rtol=0, atol=TOL)
    else:
        np.testing.assert_allclose(back, w, rtol=0, atol=1e-9 if name.startswith("pi") else TOL)
        np.testing.assert_allclose(back, np.asarray(SO3.from_matrix(R).log()), rtol=0, atol=1e-9)


def test_so3_log_near_pi_is_accurate_in_the_rotation():
    """Near pi the vector is ill-conditioned in the matrix (d theta ~ eps / (pi - theta)), so
    the check is the round trip through exp, and agreement with jaxslam.lie to 1e-12."""
    rng = np.random.default_rng(1)
    for gap in (1e-3, 1e-6, 1e-9, 0.0):
        R = np.asarray(SO3.exp(rotvecs(rng, 32, np.pi - gap)).as_matrix())
        w = host.so3_log(R)
        np.testing.assert_allclose(host.so3_exp(w), R, rtol=0, atol=TOL)
        assert np.all(np.linalg.norm(w, axis=1) <= np.pi + 1e-12)


def test_quaternion_round_trips_and_batch_shapes():
    rng = np.random.default_rng(2)
    q = rng.normal(size=(4, 5, 4))
    q /= np.linalg.norm(q, axis=-1, keepdims=True)
    q = np.where(q[..., :1] < 0, -q, q)
    R = host.quat_to_matrix(q)
    assert R.shape == (4, 5, 3, 3)
    np.testing.assert_allclose(R, np.asarray(SO3(jnp.asarray(q)).as_matrix()), rtol=0, atol=TOL)
    np.testing.assert_allclose(host.matrix_to_quat(R), q, rtol=0, atol=TOL)
    np.testing.assert_allclose(host.quat_to_matrix(3.0 * q), R, rtol=0, atol=TOL)  # normalised first
    # every Shepperd branch: rotations of pi about x, y, z and identity
    for w in (np.zeros(3), [np.pi, 0, 0], [0, np.pi, 0], [0, 0, np.pi], [2.0, 2.0, 0.1]):
        Rw = host.so3_exp(np.asarray(w, float))
        qw = host.matrix_to_quat(Rw)
        assert qw.shape == (4,) and qw[0] >= 0
        np.testing.assert_allclose(host.quat_to_matrix(qw), Rw, rtol=0, atol=TOL)


def test_params_and_matrices_match_se3():
    rng = np.random.default_rng(3)
    xi = np.concatenate([rotvecs(rng, 50, rng.uniform(0, np.pi, 50)), rng.normal(size=(50, 3)) * 5], 1)
    g = SE3.exp(xi)
    params = np.asarray(g.params)
    T = host.params_to_matrix(params)
    np.testing.assert_allclose(T, np.asarray(g.as_matrix()), rtol=0, atol=TOL)
    p2 = host.matrix_to_params(T)
    p2 = np.where((p2[:, :1] < 0) != (params[:, :1] < 0), -p2 * [1, 1, 1, 1, -1, -1, -1], p2)  # q ~ -q
    np.testing.assert_allclose(p2, params, rtol=0, atol=TOL)
    np.testing.assert_allclose(host.inverse(T), np.asarray(g.inverse().as_matrix()), rtol=0, atol=TOL)
    pts = rng.normal(size=(7, 3))
    np.testing.assert_allclose(host.transform_points(T[0], pts), np.asarray(g[0].act(pts)), rtol=0, atol=TOL)


@pytest.mark.parametrize("name", ["random", "zero", "1e-9", "1e-3", "pi-1e-6"])
def test_se3_exp_and_log_match_jaxslam_lie(name):
    rng = np.random.default_rng(4)
    xi = np.concatenate([rotvecs(rng, 64, angles_for(name, rng, 64)), rng.normal(size=(64, 3)) * 3], 1)
    T = host.se3_exp(xi)
    np.testing.assert_allclose(T, np.asarray(SE3.exp(xi).as_matrix()), rtol=0, atol=TOL)
    back = host.se3_log(T)
    np.testing.assert_allclose(back, np.asarray(SE3.exp(xi).log()), rtol=0, atol=1e-9 if name.startswith("pi") else TOL)


@pytest.mark.parametrize("angle", [1.1e-6, 3e-6, 1e-5])
def test_se3_exp_small_rotation_precision(angle):
    rng = np.random.default_rng(5)
    xi = np.concatenate([rotvecs(rng, 200, angle), rng.normal(size=(200, 3))], 1)
    np.testing.assert_allclose(host.se3_exp(xi), np.asarray(SE3.exp(xi).as_matrix()), rtol=0, atol=TOL)


def test_adjoint_conjugates_the_exponential():
    rng = np.random.default_rng(6)
    xi_T = np.concatenate([rotvecs(rng, 40, rng.uniform(0, 3, 40)), rng.normal(size=(40, 3)) * 4], 1)
    T = host.se3_exp(xi_T)
    xi = np.concatenate([rotvecs(rng, 40, rng.uniform(0, 3, 40)), rng.normal(size=(40, 3))], 1)
    A = host.adjoint(T)
    np.testing.assert_allclose(A, np.asarray(SE3.exp(xi_T).adjoint()), rtol=0, atol=TOL)
    lhs = T @ host.se3_exp(xi) @ host.inverse(T)
    rhs = host.se3_exp(np.einsum("nij,nj->ni", A, xi))
    np.testing.assert_allclose(lhs, rhs, rtol=0, atol=1e-11)


def test_interpolate_pose():
    rng = np.random.default_rng(7)
    for _ in range(10):
        g0 = SE3.exp(np.concatenate([rotvecs(rng, 1, rng.uniform(0, 3))[0], rng.normal(size=3)]))
        d = np.concatenate([rotvecs(rng, 1, rng.uniform(0, 3))[0], rng.normal(size=3)])
        g1 = g0 @ SE3.exp(d)
        T0, T1 = np.asarray(g0.as_matrix()), np.asarray(g1.as_matrix())
        s = np.array([0.0, 0.25, 0.5, 1.0])
        out = host.interpolate_pose(T0, T1, s)
        np.testing.assert_allclose(out[0], T0, rtol=0, atol=TOL)
        np.testing.assert_allclose(out[-1], T1, rtol=0, atol=1e-11)
        for k, sk in enumerate(s):
            R_want = np.asarray((g0.rotation @ SO3.exp(sk * d[:3])).as_matrix())
            np.testing.assert_allclose(out[k, :3, :3], R_want, rtol=0, atol=1e-11)
            np.testing.assert_allclose(out[k, :3, 3], (1 - sk) * T0[:3, 3] + sk * T1[:3, 3], rtol=0, atol=TOL)


# --- pipeline configuration ----------------------------------------------------------------------


def test_config_round_trip(tmp_path):
    cfg = PipelineConfig().replace(
        rig={
            "camera_intrinsics": (300.125, 299.5, 256.0, 160.25),
            "gravity": 9.80665,
            "accelerometer_noise_density": 1.23e-7,
        },
        vision={"enhance": False, "max_keypoints": 777, "detector": "sift"},
        lidar={"voxel": 0.1 + 0.2},
        solver={"mode": "batch"},
    )
    save_config(cfg, tmp_path / "c.yaml")
    back = load_config(tmp_path / "c.yaml")
    assert back == cfg
    assert isinstance(back.rig.camera_intrinsics, tuple) and back.lidar.voxel == 0.1 + 0.2
    assert load_config(tmp_path / "c.yaml", base=PipelineConfig()) == cfg


def test_config_partial_file_keeps_defaults(tmp_path):
    (tmp_path / "c.yaml").write_text("vision:\n  enhance: false\nloop:\n")
    cfg = load_config(tmp_path / "c.yaml")
    assert cfg == PipelineConfig().replace(vision={"enhance": False})


def test_replace():
    cfg = PipelineConfig()
    new = cfg.replace(vision={"enhance": False})
    assert new.vision.enhance is False and cfg.vision.enhance is True
    assert dataclasses.replace(new.vision, enhance=True) == cfg.vision and new.rig == cfg.rig
    with pytest.raises(ConfigError, match="enhanse"):
        cfg.replace(vision={"enhanse": False})


@pytest.mark.parametrize(
    ("data", "named"),
    [
        ({"visoin": {}}, "visoin"),
        ({"vision": {"enhanse": False}}, "enhanse"),
        ({"rig": {"camera_intrinsic": [1, 2, 3, 4]}}, "camera_intrinsic"),
        ({"vision": "yes"}, "vision"),
    ],
)
def test_unknown_sections_and_keys_raise_naming_them(tmp_path, data, named):
    with pytest.raises(ConfigError, match=named):
        config_from_dict(data)
    import yaml

    (tmp_path / "c.yaml").write_text(yaml.safe_dump(data))
    with pytest.raises(ConfigError, match=named):
        load_config(tmp_path / "c.yaml")


@pytest.mark.parametrize(
    "data",
    [
        {"vision": {"enhance": "yes"}},
        {"vision": {"enhance": 1}},
        {"vision": {"ratio": "0.8"}},
        {"rig": {"camera_size": "512x320"}},
        {"keyframe": {"distance": None}},
    ],
)
def test_wrong_types_raise(data):
    with pytest.raises(ConfigError):
        config_from_dict(data)


@pytest.mark.parametrize(
    "data",
    [
        {"vision": {"detector": 5}},
        {"vision": {"scale_depth": "lidar"}},
        {"vision": {"length_sigma_ratio": -0.01}},
        {"loop": {"visual_alias_margin": -0.1}},
        {"vision": {"wide_inlier_px": float("nan")}},
        {"loop": {"visual_dim_blur_px": float("nan")}},
        {"loop": {"visual_dim_blur_px": -1.0}},
        {"loop": {"visual_blur_px": -0.5}},
        {"loop": {"visual_blur_noise_px": -1.0}},
        {"loop": {"visual_blur_noise_px": float("inf")}},
        {"loop": {"visual_dim_blur_rungs": -1}},
        {"loop": {"visual_dim_blur_rungs": 1.5}},
        {"loop": {"visual_dim_ladder_max_grey": -1.0}},
        {"loop": {"visual_dim_ladder_max_grey": float("nan")}},
        {"imu": {"zupt_hold_sigma": -0.001}},
        {"imu": {"zupt_hold_sigma": float("nan")}},
        {"vision": {"guided_information_scale": 0.0}},
        {"vision": {"guided_information_scale": float("inf")}},
        {"vision": {"odometry_kernel_scale": -1.0}},
        {"vision": {"odometry_kernel_scale": float("nan")}},
        {"vision": {"odometry_kernel": "tukey"}},
        {"vision": {"patch_min_fraction": 1.5}},
        {"vision": {"patch_min_fraction": float("nan")}},
        {"vision": {"patch_min_ncc": 1.5}},
        {"vision": {"patch_min_ncc": float("nan")}},
        {"vision": {"patch_half": 0}},
        {"vision": {"patch_half": 6.5}},
        {"vision": {"patch_retry_half": -1}},
        {"vision": {"unscaled_min_inliers": -1}},
        {"vision": {"unscaled_min_inliers": 2.5}},
        {"vision": {"patch_retry_min_ncc": -2.0}},
        {"vision": {"patch_retry_min_fraction": 1.1}},
        {"lidar": {"anchor_gap_scans": -1}},
        {"rig": {"lidar_model": None}},
        {"imu": {"noise_scale": True}},
        {"vision": {"max_keypoints": 10.5}},
        {"rig": {"camera_intrinsics": [1.0, 2.0]}},
        {"rig": {"camera_intrinsics": ["a", "b", "c", "d"]}},
    ],
)
def test_wrong_types_raise_more(data):
    with pytest.raises(ConfigError):
        config_from_dict(data)


def test_pair_lists_take_any_length():
    cfg = config_from_dict({"vision": {"pairs": [1, 4]}, "lidar": {"pairs": [1, 10]}})
    assert cfg.vision.pairs == (1, 4) and cfg.lidar.pairs == (1, 10)
    for bad in ([], [0, 2], [1.5]):
        with pytest.raises(ConfigError, match="pairs"):
            config_from_dict({"vision": {"pairs": bad}})


def test_solver_engine_is_checked():
    assert config_from_dict({"solver": {"engine": "bayes_tree"}}).solver.engine == "bayes_tree"
    with pytest.raises(ConfigError, match="engine"):
        config_from_dict({"solver": {"engine": "isam"}})


def test_solver_chunk_sizes_any_length_ascending():
    assert config_from_dict({"solver": {"chunk_sizes": [8, 64, 512]}}).solver.chunk_sizes == (8, 64, 512)
    for bad in ([], [64, 8], [0], [16, 16], [8.5]):
        with pytest.raises(ConfigError, match="chunk_sizes"):
            config_from_dict({"solver": {"chunk_sizes": bad}})


def test_replace_unknown_section_raises_config_error():
    with pytest.raises(ConfigError, match="visoin"):
        PipelineConfig().replace(visoin={"enhance": False})


def test_missing_and_bad_files(tmp_path):
    with pytest.raises(ConfigError, match="not found"):
        load_config(tmp_path / "none.yaml")
    (tmp_path / "bad.yaml").write_text("vision: [1, 2\n")
    with pytest.raises(ConfigError, match="YAML"):
        load_config(tmp_path / "bad.yaml")


def test_load_rig_reads_the_simulator_calibration(tmp_path):
    from jaxslam.sim import SimConfig
    from jaxslam.sim._recording import rig_calibration, write_rig

    write_rig(SimConfig(), tmp_path / "run.rig.yaml")
    rig = load_rig(tmp_path / "run.rig.yaml")
    assert isinstance(rig, RigConfig)
    want = {k: tuple(v) if isinstance(v, list) else v for k, v in rig_calibration(SimConfig()).items()}
    assert dataclasses.asdict(rig) == want
    assert set(want) == {f.name for f in dataclasses.fields(RigConfig)}  # every field written
    np.testing.assert_allclose(rig.K()[[0, 1, 0, 1], [0, 1, 2, 2]], want["camera_intrinsics"])
    # a bare mapping (no rig: section) reads the same; unknown keys are named
    import yaml

    (tmp_path / "bare.yaml").write_text(yaml.safe_dump(rig_calibration(SimConfig())))
    assert load_rig(tmp_path / "bare.yaml") == rig
    (tmp_path / "bad.yaml").write_text("rig:\n  focal: 3\n")
    with pytest.raises(ConfigError, match="focal"):
        load_rig(tmp_path / "bad.yaml")
    with pytest.raises(ConfigError):
        load_rig(tmp_path / "none.yaml")


def test_find_rig(tmp_path):
    bag = tmp_path / "run.bag"
    bag.write_bytes(b"")
    assert find_rig(bag) is None
    (tmp_path / "run.rig.yaml").write_text("rig: {}\n")
    assert find_rig(bag) == tmp_path / "run.rig.yaml"
    folder = tmp_path / "euroc"
    folder.mkdir()
    (folder / "rig.yaml").write_text("rig: {}\n")
    assert find_rig(folder) == folder / "rig.yaml"
    (tmp_path / "euroc.rig.yaml").write_text("rig: {}\n")
    assert find_rig(folder) == tmp_path / "euroc.rig.yaml"  # <stem>.rig.yaml first


# --- IMU -----------------------------------------------------------------------------------------

G = np.array([0.0, 0.0, -9.81])


def buffer(t: np.ndarray, acc: np.ndarray, gyro: np.ndarray) -> ImuBuffer:
    buf = ImuBuffer()
    for k in range(len(t)):
        assert buf.append(float(t[k]), acc[k], gyro[k])
    return buf


def test_buffer_append_rejects_old_samples_and_grows():
    buf = ImuBuffer()
    t = np.arange(3000) * 0.005
    for k in range(3000):
        buf.append(t[k], np.full(3, k), np.zeros(3))
    assert buf.n == 3000 and buf.last_time == t[-1] and buf.acc[2999, 0] == 2999
    assert not buf.append(t[-1], np.zeros(3), np.zeros(3))
    assert not buf.append(t[-1] - 1, np.zeros(3), np.zeros(3))
    assert buf.n == 3000


def test_interval_holds_each_sample_until_the_next():
    t = np.arange(10) * 0.01
    acc = np.arange(30.0).reshape(10, 3)
    buf = buffer(t, acc, -acc)
    a, g, dt, gap = buf.interval(0.003, 0.047)
    np.testing.assert_array_equal(a, acc[0:5])
    np.testing.assert_array_equal(g, -acc[0:5])
    np.testing.assert_allclose(dt, [0.007, 0.01, 0.01, 0.01, 0.007], rtol=0, atol=1e-15)
    assert dt.sum() == pytest.approx(0.044, abs=1e-15) and gap == pytest.approx(0.01)
    a, _, dt, _ = buf.interval(0.02, 0.05)  # ta on a sample: that sample opens the interval
    np.testing.assert_array_equal(a, acc[2:5])
    np.testing.assert_allclose(dt, [0.01] * 3, atol=1e-15)
    a, _, dt, gap = buf.interval(0.0212, 0.0288)  # inside one hold
    np.testing.assert_array_equal(a, acc[2:3])
    np.testing.assert_allclose(dt, [0.0076], atol=1e-15)
    a, _, dt, gap = buf.interval(0.095, 0.2)  # past the last sample: the last one held
    np.testing.assert_array_equal(a, acc[9:10])
    assert dt.sum() == pytest.approx(0.105) and gap == pytest.approx(0.105)


def test_interval_max_gap_and_agreement_with_cut_imu_stream():
    rng = np.random.default_rng(8)
    t = np.cumsum(rng.uniform(0.004, 0.006, 400))
    t = np.delete(t, np.arange(150, 190))  # a gap of ~0.2 s
    acc, gyro = rng.normal(size=(len(t), 3)), rng.normal(size=(len(t), 3))
    buf = buffer(t, acc, gyro)
    kf = np.sort(rng.uniform(t[0], t[-1], 6))
    iv = cut_imu_stream(t, acc, gyro, kf)
    for k in range(len(kf) - 1):
        a, g, dt, gap = buf.interval(kf[k], kf[k + 1])
        m = iv.mask[k]
        np.testing.assert_array_equal(a, iv.acc[k][m])
        np.testing.assert_array_equal(g, iv.gyro[k][m])
        np.testing.assert_allclose(dt, iv.dt[k][m], rtol=0, atol=1e-15)
        assert dt.sum() == pytest.approx(kf[k + 1] - kf[k], abs=1e-12)
        assert gap == pytest.approx(dt.max())
    a, g, dt, gap = buf.interval(t[140], t[200])
    assert gap == pytest.approx(t[150] - t[149])


def _gamma2(phi: np.ndarray) -> np.ndarray:
    """int_0^1 int_0^s Exp(u phi) du ds = I/2 + (t - sin t)/t^3 K + (t^2/2 + cos t - 1)/t^4 K^2
    (the second of the Gamma functions in Forster et al.'s supplementary material)."""
    th = np.linalg.norm(phi)
    K = host.skew(phi)
    return 0.5 * np.eye(3) + (th - np.sin(th)) / th**3 * K + (th**2 / 2 + np.cos(th) - 1) / th**4 * (K @ K)


def _exact(R0, p0, v0, w, f, T):
    """Constant body rate ``w`` and specific force ``f`` for ``T`` s: R, p, v (closed form)."""
    R = R0 @ np.asarray(SO3.exp(w * T).as_matrix())
    g1 = np.asarray(SE3.exp(np.concatenate([w * T, f * T])).translation)  # T Jl(wT) f
    v = v0 + G * T + R0 @ g1
    p = p0 + v0 * T + 0.5 * G * T**2 + R0 @ (T**2 * _gamma2(w * T) @ f)
    return R, p, v


def _constant_state(rate: float, seconds: float = 1.0, t0: float = 10.0):
    rng = np.random.default_rng(9)
    w, f = np.array([0.3, -0.2, 0.5]), np.array([1.0, -0.5, 9.81])
    bias = np.concatenate([rng.normal(size=3) * 0.05, rng.normal(size=3) * 0.01])
    t = t0 + np.arange(int(seconds * rate) + 2) / rate
    n = len(t)
    buf = buffer(t, np.tile(f + bias[:3], (n, 1)), np.tile(w + bias[3:], (n, 1)))
    R0 = host.so3_exp(np.array([0.1, 0.2, -0.3]))
    start = NavState(t0, host.make_pose(R0, np.array([1.0, 2.0, 3.0])), np.array([0.5, 0.0, -0.1]), bias)
    return buf, start, w, f


def test_propagate_converges_to_the_constant_rate_closed_form():
    T = 1.0
    errs = []
    for rate in (200.0, 400.0, 800.0):
        buf, s, w, f = _constant_state(rate)
        end, _ = propagate(buf, s, s.t + T, G)
        R, p, v = _exact(s.T[:3, :3], s.T[:3, 3], s.v, w, f, T)
        np.testing.assert_allclose(end.T[:3, :3], R, rtol=0, atol=1e-12)  # rotation exact
        errs.append((np.linalg.norm(end.v - v), np.linalg.norm(end.T[:3, 3] - p)))
        assert end.t == s.t + T
    errs = np.array(errs)
    assert errs[0, 0] < 1e-2 and errs[0, 1] < 1e-2, errs
    np.testing.assert_allclose(errs[:-1] / errs[1:], 2.0, rtol=0.05)  # first order in dt


def test_propagate_matches_preintegration_and_returns_poses_at_times():
    rng = np.random.default_rng(10)
    rate = 200.0
    t = 5.0 + np.arange(120) / rate
    acc = np.array([0.3, -0.1, 9.81]) + rng.normal(size=(120, 3)) * 0.5
    gyro = rng.normal(size=(120, 3)) * 0.4
    buf = buffer(t, acc, gyro)
    bias = np.array([0.02, -0.01, 0.03, 0.001, -0.002, 0.003])
    start = NavState(5.0013, host.se3_exp(np.array([0.1, -0.2, 0.3, 1.0, 2.0, 3.0])), np.array([1.0, 0.2, 0.0]), bias)
    tb = 5.0013 + 0.5
    end, _ = propagate(buf, start, tb, G)
    a, g, dt, _ = buf.interval(start.t, tb)
    params = PreintegrationParams.create(2e-3, 1.7e-4, 3e-4, 2e-5, gravity=G)
    pim = preintegrate(a[None], g[None], dt[None], params, bias_hat=bias[None])
    pose, vel = predict_imu_state(
        pim.preintegrated,
        pim.delta_time,
        G[None],
        SE3(jnp.asarray(host.matrix_to_params(start.T)[None])),
        start.v[None],
    )
    # the same Euler scheme in velocity/position; the tangent rotation recurrence differs
    # from the product of exponentials at second order in the step's rotation (~1e-6 here)
    np.testing.assert_allclose(end.T, np.asarray(pose.as_matrix())[0], rtol=0, atol=1e-5)
    np.testing.assert_allclose(end.v, np.asarray(vel)[0], rtol=0, atol=1e-5)
    # poses at times: the start, the end, and linear between the integrated stamps
    times = np.array([start.t, tb, t[60], t[60] + 0.002])
    _, poses = propagate(buf, start, tb, G, times=times)
    np.testing.assert_allclose(poses[0], start.T, atol=TOL)
    np.testing.assert_allclose(poses[1], end.T, atol=1e-12)
    at, _ = propagate(buf, start, t[60], G)  # on a sample stamp: the integrated pose
    np.testing.assert_allclose(poses[2], at.T, atol=1e-12)
    mid, _ = propagate(buf, start, t[60] + 0.002, G)  # between: interpolated, ~1/2 a dt^2 off
    np.testing.assert_allclose(poses[3], mid.T, atol=1e-4)


def test_propagate_equals_preintegration_for_a_constant_rate():
    """Constant rate about a fixed axis: the tangent recurrence is exact too, so the two
    agree to rounding."""
    buf, s, _, _ = _constant_state(200.0, seconds=0.6)
    tb = s.t + 0.5123
    end, _ = propagate(buf, s, tb, G)
    a, g, dt, _ = buf.interval(s.t, tb)
    params = PreintegrationParams.create(2e-3, 1.7e-4, 3e-4, 2e-5, gravity=G)
    pim = preintegrate(a[None], g[None], dt[None], params, bias_hat=s.bias[None])
    pose, vel = predict_imu_state(
        pim.preintegrated, pim.delta_time, G[None], SE3(jnp.asarray(host.matrix_to_params(s.T)[None])), s.v[None]
    )
    np.testing.assert_allclose(end.T, np.asarray(pose.as_matrix())[0], rtol=0, atol=1e-9)
    np.testing.assert_allclose(end.v, np.asarray(vel)[0], rtol=0, atol=1e-9)


def test_preintegrate_interval_equals_unpadded_preintegration():
    rng = np.random.default_rng(11)
    n = 103
    acc = rng.normal(size=(n, 3)) + np.array([0, 0, 9.81])
    gyro = rng.normal(size=(n, 3)) * 0.3
    dt = rng.uniform(0.004, 0.006, n)
    params = PreintegrationParams.create(2e-3, 1.7e-4, 3e-4, 2e-5)
    bias = rng.normal(size=6) * 0.01
    got = preintegrate_interval(acc, gyro, dt, params, bias)
    want = preintegrate(acc[None], gyro[None], dt[None], params, bias_hat=bias[None])
    for name in ("preintegrated", "delta_time", "bias_jacobian", "covariance", "bias_hat"):
        np.testing.assert_allclose(
            np.asarray(getattr(got, name)), np.asarray(getattr(want, name)), rtol=1e-12, atol=1e-15
        )
    assert bool(np.asarray(got.valid)[0])


@pytest.mark.parametrize(("roll", "pitch"), [(0.0, 0.0), (0.2, -0.1), (-0.7, 0.4), (2.5, 0.3), (np.pi, 0.0)])
def test_gravity_alignment_recovers_roll_and_pitch_with_zero_yaw(roll, pitch):
    Rx = host.so3_exp(np.array([roll, 0.0, 0.0]))
    Ry = host.so3_exp(np.array([0.0, pitch, 0.0]))
    R_wb = Ry @ Rx  # ZYX Euler angles with yaw 0
    f = R_wb.T @ np.array([0.0, 0.0, 9.81])  # a still IMU measures -gravity in the body frame
    for scale in (1.0, 1.02):
        R = gravity_alignment(f * scale)
        np.testing.assert_allclose(R, R_wb, rtol=0, atol=1e-12)
        np.testing.assert_allclose(R @ f / np.linalg.norm(f), [0, 0, 1], atol=1e-12)
        assert abs(np.arctan2(R[1, 0], R[0, 0])) < 1e-12


# --- visual --------------------------------------------------------------------------------------


@pytest.mark.parametrize("dist", [(0.0, 0.0, 0.0, 0.0), (-0.28, 0.07, 2e-4, -1e-4), (0.1, -0.02, 1e-3, 5e-4)])
def test_undistort_inverts_radtan(dist):
    rng = np.random.default_rng(12)
    K = np.array([[281.6, 0, 255.5], [0, 281.6, 159.5], [0, 0, 1.0]])
    xn = rng.uniform([-0.9, -0.55], [0.9, 0.55], (500, 2))
    xd, yd = distort(xn[:, 0], xn[:, 1], dist)
    uv = np.stack([K[0, 0] * xd + K[0, 2], K[1, 1] * yd + K[1, 2]], 1)
    np.testing.assert_allclose(undistort_normalized(uv, K, dist), xn, rtol=0, atol=1e-9)


def _plane_points(rng, n, normal, d, noise=0.0):
    """Points on ``normal . X = d`` in front of the camera (z in about 2..6 m)."""
    normal = np.asarray(normal, float) / np.linalg.norm(normal)
    xy = rng.uniform(-2.0, 2.0, (n, 2))
    z = (d - normal[0] * xy[:, 0] - normal[1] * xy[:, 1]) / normal[2]
    pts = np.concatenate([xy, z[:, None]], 1)
    return pts + rng.normal(size=pts.shape) * noise, normal


@pytest.mark.parametrize("noise", [0.0, 0.002])
def test_plane_depth_hits_the_plane(noise):
    rng = np.random.default_rng(13)
    pts, n = _plane_points(rng, 4000, [0.2, -0.1, 1.0], 4.0, noise)
    xn = rng.uniform(-0.3, 0.3, (200, 2))
    X = plane_depth(xn, pts, radius=0.05)
    rays = np.concatenate([xn, np.ones((200, 1))], 1)
    want = rays * (4.0 / (rays @ n))[:, None]  # the plane is n . X = 4, |n| = 1
    ok = np.isfinite(X[:, 0])
    assert ok.mean() > 0.95
    np.testing.assert_allclose(X[ok], want[ok], rtol=0, atol=1e-9 if noise == 0 else 5 * noise)
    np.testing.assert_allclose(X[ok, :2] / X[ok, 2:], xn[ok], atol=1e-12)  # on the ray


def test_plane_depth_nan_without_enough_points():
    rng = np.random.default_rng(14)
    pts, _ = _plane_points(rng, 2000, [0.0, 0.0, 1.0], 3.0)
    pts = pts[pts[:, 0] < 0]  # only the left half
    xn = np.array([[-0.2, 0.0], [0.3, 0.0], [5.0, 5.0]])
    X = plane_depth(xn, pts, radius=0.06)
    np.testing.assert_allclose(X[0], [-0.6, 0.0, 3.0], atol=1e-9)
    assert np.all(np.isnan(X[1:]))
    assert np.all(np.isnan(plane_depth(xn, pts[:4], radius=10.0)))  # fewer than min_points in all
    assert plane_depth(np.zeros((0, 2)), pts, 0.1).shape == (0, 3)


def test_plane_depth_nan_at_a_corner():
    """A front wall (z = 3, x <= 1) meeting a side wall (x = 1, z <= 3) seen from inside:
    sparse LiDAR (0.15 m); rays near the corner line (x_n = 1/3) see both planes -> NaN;
    rays well inside either wall get that wall's depth."""
    g = np.arange(-1.0, 1.0 + 1e-9, 0.15)
    front = np.array([[x, y, 3.0] for x in g for y in g])
    side = np.array([[1.0, y, z] for z in np.arange(1.0, 3.0 - 1e-9, 0.15) for y in g])
    pts = np.concatenate([front, side])
    corner = np.stack([1 / 3 + np.linspace(-0.025, 0.0, 6), np.zeros(6)], 1)
    assert np.all(np.isnan(plane_depth(corner, pts, radius=0.1)))
    X = plane_depth(np.array([[0.0, 0.0], [0.1, 0.05], [0.6, 0.0]]), pts, radius=0.1)
    np.testing.assert_allclose(X[0], [0.0, 0.0, 3.0], atol=1e-9)
    np.testing.assert_allclose(X[1], [0.3, 0.15, 3.0], atol=1e-9)
    np.testing.assert_allclose(X[2], [1.0, 0.0, 1 / 0.6], atol=1e-9)


def _tunnel_wall_points(rng, n):
    """``n`` points on the walls of a 3 m square tunnel 2-12 m ahead of a camera (camera
    frame: z forward)."""
    z = rng.uniform(2.0, 12.0, n)
    side = rng.integers(0, 4, n)
    u = rng.uniform(-1.5, 1.5, n)
    x = np.where(side == 0, -1.5, np.where(side == 1, 1.5, u))
    y = np.where(side == 2, -1.5, np.where(side == 3, 1.5, np.where(side < 2, u, 0.0)))
    return np.c_[x, y, z]


@pytest.mark.parametrize("scale_depth", ["scan", "map"])
def test_visual_length_from_each_keyframes_own_scan(scale_depth):
    """Depths from a local map whose scans sit at LiDAR-odometry poses repeat the odometry's
    along-axis error in their keyframe-to-keyframe difference (here: the map of keyframe b is
    1 cm too deep, 4 % of the 0.25 m step); each keyframe's own scan is metric. With
    ``scale_depth: scan`` the length comes from the scan depths (a band of the features),
    with ``map`` it inherits the map's error."""
    from jaxslam.pipeline._visual import KeyframeFeatures, VisualFrontend

    cfg = PipelineConfig()
    vis = dataclasses.replace(cfg.vision, scale_depth=scale_depth, ransac=False)
    fe = VisualFrontend(vis, cfg.rig)
    rng = np.random.default_rng(21)
    n = 400
    Xa = _tunnel_wall_points(rng, n)
    step = np.array([0.02, -0.01, 0.25])  # camera b = camera a moved (no rotation)
    Xb = Xa - step

    def feats(kf, X, X_map, X_scan, track):
        xn = X[:, :2] / X[:, 2:]
        uv = xn * fe.K[0, 0] + fe.K[:2, 2]  # distortion is not used by relative()
        desc = np.eye(n, 64, dtype=np.float32) + 0.01 * np.arange(n)[:, None].astype(np.float32)
        return KeyframeFeatures(kf, float(kf), uv, xn, desc, np.ones(n), X_map, track, X_scan)

    band = np.abs(Xa[:, 1] / Xa[:, 2]) < 0.1  # the LiDAR's band: a fraction of the features
    scan_a = np.where(band[:, None], Xa, np.nan)
    scan_b = np.where(band[:, None], Xb, np.nan)
    map_b = Xb + np.array([0.0, 0.0, 0.01])  # b's map 1 cm too deep along the axis
    a = feats(0, Xa, Xa, scan_a, np.arange(n))
    b = feats(1, Xb, map_b, scan_b, np.arange(n, 2 * n))
    T_cacb = np.eye(4)
    T_cacb[:3, 3] = step
    T_ab = fe.T_bc @ T_cacb @ fe.T_cb
    vm = fe.relative(a, b, T_ab)
    assert vm is not None and band.sum() >= 10
    length = np.linalg.norm(vm.T[:3, 3])
    true = np.linalg.norm(step)
    if scale_depth == "scan":
        assert abs(length / true - 1) < 1e-3, length / true
    else:
        assert abs(length / true - 1) > 0.02, length / true  # the map's error passes through


def _repeated_texture_pair(fe, rng, n=400, kinds=40):
    """Two keyframes 0.25 m apart in a tunnel whose features come in ``kinds`` descriptors,
    each repeated ten times across the image (same-looking concrete; noisy dark keypoints):
    the image-wide ratio test cannot tell the copies apart."""
    from jaxslam.pipeline._visual import KeyframeFeatures

    Xa = _tunnel_wall_points(rng, n)
    step = np.array([0.02, -0.01, 0.25])
    Xb = Xa - step
    base = rng.standard_normal((kinds, 64)).astype(np.float32)
    base /= np.linalg.norm(base, axis=1, keepdims=True)

    def feats(kf, X):
        xn = X[:, :2] / X[:, 2:]
        uv = xn * fe.K[0, 0] + fe.K[:2, 2]
        desc = base[np.arange(n) % kinds] + 0.01 * rng.standard_normal((n, 64)).astype(np.float32)
        return KeyframeFeatures(kf, float(kf), uv, xn, desc, np.ones(n), X.copy(), np.arange(n) + kf * n)

    T_cacb = np.eye(4)
    T_cacb[:3, 3] = step
    return feats(0, Xa), feats(1, Xb), fe.T_bc @ T_cacb @ fe.T_cb


def test_guided_matching_registers_a_repetitive_pair_only_near_the_prediction():
    """Image-wide matching finds nothing in a texture of repeated descriptors; matching
    within ``guided_radius_px`` of where the predicted motion projects the 3-D points recovers
    the pose (from the data: the prediction is 3 cm / 0.3 deg off); a prediction far off
    (20 deg of yaw) finds no consistent matches, and the option off keeps the old result."""
    from jaxslam.pipeline._visual import VisualFrontend, _projection_jacobian

    cfg = PipelineConfig()
    rng = np.random.default_rng(5)
    on = VisualFrontend(dataclasses.replace(cfg.vision, guided_radius_px=15.0), cfg.rig)
    off = VisualFrontend(dataclasses.replace(cfg.vision, guided_radius_px=0.0), cfg.rig)
    a, b, T_ab = _repeated_texture_pair(on, rng)
    assert off.relative(a, b, T_ab) is None
    guess = T_ab @ host.make_pose(host.so3_exp(np.radians([0.0, 0.0, 0.3])), np.array([0.03, 0.0, -0.02]))
    vm = on.relative(a, b, guess)
    assert vm is not None and vm.inliers >= 300, None if vm is None else vm.inliers
    err = host.se3_log(host.inverse(vm.T) @ T_ab)
    assert np.linalg.norm(err[3:]) < 1e-3 and np.linalg.norm(err[:3]) < 1e-4, err
    pairs = on.guided_pairs(a, b, on.T_cb @ host.inverse(guess) @ on.T_bc)
    assert len(np.unique(pairs[:, 1])) == len(pairs)  # each feature of b used once
    far = T_ab @ host.make_pose(host.so3_exp(np.radians([0.0, 0.0, 20.0])), np.zeros(3))
    assert on.relative(a, b, far) is None
    # the guided fit's information: its inliers' closed form times guided_information_scale
    assert on.guided_fits == 1 and off.guided_fits == 0
    T_cbca = on.T_cb @ host.inverse(vm.T) @ on.T_bc
    J = _projection_jacobian(host.transform_points(T_cbca, vm.X_i))
    H = np.einsum("nki,nkj->ij", J, J) / (cfg.vision.pixel_sigma / on.f) ** 2 * cfg.vision.information_scale
    A = host.adjoint(on.T_cb)
    scale = cfg.vision.guided_information_scale
    assert 0 < scale < 1
    np.testing.assert_allclose(vm.information, scale * (A.T @ H @ A), rtol=1e-9, atol=1e-6)


def test_motion_only_gate_follows_the_inlier_threshold():
    """``motion_only``: observations with 1.5 px Gaussian noise keep about
    ``1 - exp(-r^2 / 2 sigma^2)`` of the points within the gate ``r`` (2-D Rayleigh): ~59 % at
    2 px, ~93 % at 3.5 px (binomial bounds), and the pose error is within the noise's
    information (chi-square) either way."""
    from jaxslam.pipeline._visual import _projection_jacobian, motion_only

    rng = np.random.default_rng(11)
    f, n, sigma = 400.0, 400, 1.5
    X = _tunnel_wall_points(rng, n)
    T_ba = host.make_pose(host.so3_exp(np.radians([0.5, 8.0, 0.2])), np.array([0.01, 0.0, -0.25]))
    Xb = host.transform_points(T_ba, X)
    x = Xb[:, :2] / Xb[:, 2:] + sigma / f * rng.standard_normal((n, 2))
    start = T_ba @ host.se3_exp(np.r_[np.radians([0.2, -0.3, 0.1]), 0.02, 0.01, 0.03])
    for px in (2.0, 3.5):
        fit = motion_only(X, x, start, f, 15, inlier_px=px)
        assert fit is not None
        T, kept, e = fit
        p = 1 - np.exp(-(px**2) / (2 * sigma**2))
        assert abs(len(kept) - n * p) < 4 * np.sqrt(n * p * (1 - p)), (px, len(kept), n * p)
        assert np.all(e < px / f)
        # the pose error, whitened by the noise's information over the kept points: chi^2(6)
        J = _projection_jacobian(host.transform_points(T, X[kept]))
        H = np.einsum("nki,nkj->ij", J, J) / (sigma / f) ** 2
        err = host.se3_log(T_ba @ host.inverse(T))  # left perturbation, as the Jacobian's
        assert err @ H @ err < 22.5, (px, err @ H @ err)  # 99.9 % of chi^2(6)


def _noisy_sparse_pair(fe, rng, n=30, sigma_px=2.0):
    """Two keyframes 0.25 m apart with ``n`` distinct features whose pixels in b scatter by
    ``sigma_px`` (dark, motion-blurred keypoints) and a descriptor in a's set of 5 look-alikes
    (the image-wide ratio test rejects them; the guided window holds one)."""
    from jaxslam.pipeline._visual import KeyframeFeatures

    Xa = _tunnel_wall_points(rng, n)
    step = np.array([0.02, -0.01, 0.25])
    Xb = Xa - step
    base = rng.standard_normal((n // 5, 64)).astype(np.float32)

    def feats(kf, X, noise):
        xn = X[:, :2] / X[:, 2:] + noise
        uv = xn * fe.K[0, 0] + fe.K[:2, 2]
        desc = base[np.arange(n) % len(base)] + 0.01 * rng.standard_normal((n, 64)).astype(np.float32)
        return KeyframeFeatures(kf, float(kf), uv, xn, desc, np.ones(n), X.copy(), np.arange(n) + kf * n)

    T_cacb = np.eye(4)
    T_cacb[:3, 3] = step
    a = feats(0, Xa, np.zeros((n, 2)))
    b = feats(1, Xb, sigma_px / fe.K[0, 0] * rng.standard_normal((n, 2)))
    return a, b, fe.T_bc @ T_cacb @ fe.T_cb


def test_wide_gate_registers_scattered_keypoints_with_a_wider_sigma():
    """``vision.wide_inlier_px``: 30 guided pairs whose keypoints scatter by 2 px leave fewer
    than ``min_inliers`` within 2 px, so the pair was lost; the wide gate (3.5 px) registers it,
    counts it, and states its information for a pixel sigma 3.5 / 2 times wider (closed form
    over its inliers), under which its true error is a plausible chi-square. Off (2), the pair
    is lost."""
    from jaxslam.pipeline._visual import VisualFrontend, _projection_jacobian

    cfg = PipelineConfig()
    assert cfg.vision.wide_inlier_px > 2.0
    wide = VisualFrontend(cfg.vision, cfg.rig)
    off = VisualFrontend(dataclasses.replace(cfg.vision, wide_inlier_px=2.0), cfg.rig)
    a, b, T_ab = _noisy_sparse_pair(wide, np.random.default_rng(4))
    assert off.relative(a, b, T_ab) is None and off.wide_fits == 0
    vm = wide.relative(a, b, T_ab)
    assert vm is not None and wide.wide_fits == 1 and vm.inliers >= cfg.vision.min_inliers
    err = host.se3_log(host.inverse(vm.T) @ T_ab)  # the between factor's residual
    assert err @ vm.information @ err < 22.5, err @ vm.information @ err  # the stated sigma holds
    T_cbca = wide.T_cb @ host.inverse(vm.T) @ wide.T_bc
    J = _projection_jacobian(host.transform_points(T_cbca, vm.X_i))
    sigma = cfg.vision.pixel_sigma * cfg.vision.wide_inlier_px / 2.0 / wide.f
    H = np.einsum("nki,nkj->ij", J, J) / sigma**2 * cfg.vision.information_scale
    A = host.adjoint(wide.T_cb)
    np.testing.assert_allclose(vm.information, A.T @ H @ A, rtol=1e-9, atol=1e-6)


def test_zero_velocity_detector_takes_noise_only_intervals():
    """``ImuConfig.zupt``: an interval whose accelerometer spread is the sensor's white noise
    counts as standing still (whatever the gyro says: a turn on the spot keeps the IMU in place);
    the vibration of a moving robot, a short interval or ``zupt: false`` do not."""
    from jaxslam.pipeline import Estimator

    cfg = PipelineConfig()
    est = Estimator(cfg)
    rng = np.random.default_rng(0)
    rate = 200.0
    sigma = cfg.rig.accelerometer_noise_density * np.sqrt(rate)
    n = 100  # 0.5 s
    dt = np.full(n, 1.0 / rate)
    still = np.array([0.0, 0.0, 9.81]) + sigma * rng.standard_normal((n, 3))
    assert est._stationary(still, dt)
    t = np.arange(n) / rate
    shaking = still + 0.06 * np.sin(2 * np.pi * 7.0 * t)[:, None]  # 0.04 m/s^2 rms per axis
    assert not est._stationary(shaking, dt)
    assert not est._stationary(still[:30], dt[:30])  # 0.15 s: too short to tell
    off = Estimator(cfg.replace(imu={"zupt": False}))
    assert not off._stationary(still, dt)


def test_position_hold_pins_the_translation_and_leaves_the_rotation_free():
    """``ImuConfig.zupt_hold_sigma``: the hold costs ~0 for a turn on the spot of any angle, and
    1 sigma of translation costs 1 without a turn. With a turn by ``theta`` the residual is the
    SE(3) log's ``V(theta)^-1 t`` (closed form): still 1 along the turn's axis, and
    ``|V^-1 t|^2 = 1 + theta^2 / 12 + O(theta^4)`` across it (keyframes turn <= 10 deg)."""
    from jaxslam.pipeline._estimator import position_hold

    sigma = 0.002
    hold = position_hold(3, 4, sigma)
    assert [int(v.ids[0]) for v in hold.variables] == [3, 4]
    Ti = host.make_pose(host.so3_exp(np.array([0.1, -0.2, 0.3])), np.array([29.0, 0.4, 0.1]))

    def cost(T_ij):
        params = (host.matrix_to_params(Ti)[None], host.matrix_to_params(Ti @ T_ij)[None])
        r = hold.noise.whiten(hold.evaluate(tuple(jnp.asarray(p) for p in params)))
        return float(jnp.sum(r**2))

    for angle in (0.0, 0.3, 1.5, 3.0):
        turn = host.make_pose(host.so3_exp(np.array([0.0, 0.0, angle])), np.zeros(3))
        assert cost(turn) < 1e-5, (angle, cost(turn))  # ~1000 rad sigma on the rotation
        if angle > 0.3:
            continue
        for axis in np.eye(3):
            moved = turn @ host.make_pose(np.eye(3), sigma * axis)
            expected = 1.0 if axis[2] else 1.0 + angle**2 / 12
            assert abs(cost(moved) - expected) < 1e-4, (angle, axis, cost(moved), expected)


def test_visual_odometry_factor_kernel_and_scale_in_closed_form():
    """``vision.odometry_kernel`` / ``odometry_kernel_scale``: the factor's cost for keyframes
    off the measurement by a whitened distance ``x`` is ``x^2/2`` without a kernel,
    ``k^2/2 log(1 + x^2/k^2)`` under Cauchy and ``k x - k^2/2`` (beyond ``k``) under Huber;
    the scaled form is zero when the translation is the measured one times ``exp(lambda)``."""
    from jaxslam.core._factor import factor_cost
    from jaxslam.pipeline._estimator import visual_odometry_factor

    sigma = 0.01
    info = np.diag(np.r_[np.full(3, 1e4), np.full(3, sigma**-2.0)])
    T = host.make_pose(host.so3_exp(np.array([0.0, 0.02, 0.0])), np.array([0.3, 0.01, 0.0]))
    Ti = host.make_pose(host.so3_exp(np.array([0.1, -0.2, 0.3])), np.array([12.0, 0.4, 0.1]))

    def cost(factor, T_ij, lam=None):
        params = [host.matrix_to_params(Ti)[None], host.matrix_to_params(Ti @ T_ij)[None]]
        if lam is not None:
            params.append(np.array([[lam]]))
        return float(factor_cost(factor, tuple(jnp.asarray(p) for p in params))[0])

    x = 7.0  # whitened distance: 7 sigma along the track
    off = T @ host.make_pose(np.eye(3), np.array([x * sigma, 0.0, 0.0]))
    k = 3.0
    plain = visual_odometry_factor(2, 3, T, info, scaled=False)
    assert plain.robust is None
    assert abs(cost(plain, off) - x**2 / 2) < 1e-6
    cauchy = visual_odometry_factor(2, 3, T, info, scaled=False, kernel="cauchy", kernel_scale=k)
    assert abs(cost(cauchy, off) - k**2 / 2 * np.log1p(x**2 / k**2)) < 1e-6
    huber = visual_odometry_factor(2, 3, T, info, scaled=False, kernel="huber", kernel_scale=k)
    assert abs(cost(huber, off) - (k * x - k**2 / 2)) < 1e-6
    assert cost(cauchy, T) < 1e-12 and cost(huber, T) < 1e-12

    scaled = visual_odometry_factor(2, 3, T, info, scaled=True, kernel="cauchy", kernel_scale=k)
    assert [int(v.ids[0]) for v in scaled.variables] == [2, 3, 3]
    lam = np.log(1.02)
    stretched = T.copy()
    stretched[:3, 3] *= 1.02
    assert cost(scaled, stretched, lam) < 1e-12
    assert abs(cost(scaled, stretched, 0.0) - cost(cauchy, stretched)) < 1e-9


def test_long_lidar_pairs_span_at_most_the_configured_weak_scans():
    """``lidar.anchor_gap_scans``: ``weak_run`` is the longest run of consecutive axis-weak
    scans in a closed range; a long pair needs anchored ends and, between them, no weak scan
    (0, the rule before the option: the same as ``last_degenerate < first``) or runs of at
    most the gap."""
    from jaxslam.pipeline._lidar_frontend import LidarOdometry

    odo = LidarOdometry(PipelineConfig().lidar, np.eye(4))
    odo._weak = [3, 7, 8, 20, 21, 22, 23]
    assert [odo.weak_run(a, b) for a, b in [(0, 2), (0, 3), (4, 6), (0, 10), (7, 7), (9, 19), (0, 30), (22, 40)]] == [
        0,
        1,
        0,
        2,
        1,
        0,
        4,
        2,
    ]

    def anchored(gap, a, b):
        return odo.anchored_between(a, b, gap)

    last_weak = lambda b: max([w for w in odo._weak if w <= b], default=-1)  # noqa: E731
    for a, b in [(0, 2), (0, 5), (4, 6), (4, 9), (9, 19), (10, 30), (3, 5), (24, 30)]:
        assert anchored(0, a, b) == (last_weak(b) < a), (a, b)
    assert anchored(1, 0, 5) and not anchored(1, 0, 10) and anchored(2, 0, 10)
    assert not anchored(5, 3, 10) and not anchored(5, 0, 8)  # a weak end is never anchored
    assert not anchored(3, 10, 30) and anchored(4, 10, 30)


def _room_scan(rng: np.random.Generator, n: int = 4000) -> np.ndarray:
    """Points on the walls, floor and ceiling of a 12 x 8 x 4 m box around the sensor."""
    lo, hi = np.array([-5.0, -3.0, -1.5]), np.array([7.0, 5.0, 2.5])
    pts = rng.uniform(lo, hi, size=(n, 3))
    axis = rng.integers(0, 3, n)
    side = rng.integers(0, 2, n)
    pts[np.arange(n), axis] = np.where(side == 1, hi[axis], lo[axis])
    return pts


def test_failed_registrations_stay_out_of_the_local_map():
    """A scan whose registration failed has only its predicted pose: it is kept out of the
    local map (inserted, after a LiDAR dropout one 0.27 m off carried the error to every later
    scan) until ``lidar.map_after_failures`` fail in a row, then it goes in so the map follows
    the robot; a converged one resets the count."""
    from jaxslam.pipeline._lidar_frontend import LidarOdometry

    rng = np.random.default_rng(5)
    cfg = PipelineConfig().lidar
    odo = LidarOdometry(cfg, np.eye(4))
    motion = (np.array([0.0, 0.1]), np.stack([np.eye(4)] * 2))

    def scan(t: float, T_pred: np.ndarray):
        pts = _room_scan(rng)
        return odo.process(t, pts, np.full(len(pts), t), (motion[0] + t, motion[1]), T_pred)

    first = scan(0.0, np.eye(4))
    assert first.registration is None and len(odo.map) > 0
    size = len(odo.map)
    far = host.make_pose(np.eye(3), np.array([80.0, 0.0, 0.0]))  # nothing of the map within reach
    for k in range(1, cfg.map_after_failures):
        res = scan(0.1 * k, far)
        assert not res.registration.converged and len(odo.map) == size, k
    res = scan(0.1 * cfg.map_after_failures, far)
    assert not res.registration.converged and len(odo.map) > size  # the map follows the robot
    odo2 = LidarOdometry(cfg, np.eye(4))
    odo, rng = odo2, np.random.default_rng(5)
    scan(0.0, np.eye(4))
    scan(0.1, far)
    good = scan(0.2, host.make_pose(np.eye(3), np.array([0.05, -0.03, 0.02])))
    assert good.registration.converged and np.linalg.norm(good.T_odom[:3, 3]) < 0.01
    assert odo._failures == 0


def test_a_still_scan_keeps_the_last_pose_and_goes_into_the_map():
    """``lidar.hold_still``: a scan taken standing still is not registered; it keeps the last
    scan's pose exactly (not the prediction, which drifts with the estimated velocity), goes
    into the map there, is not counted as axis-weak (so long pairs across a standstill stay
    anchored) and is counted; the first scan (no map yet) and a moving one register as
    before."""
    from jaxslam.pipeline._lidar_frontend import LidarOdometry

    rng = np.random.default_rng(7)
    odo = LidarOdometry(PipelineConfig().lidar, np.eye(4))
    motion = (np.array([0.0, 0.1]), np.stack([np.eye(4)] * 2))

    def scan(t: float, T_pred: np.ndarray, still: bool):
        pts = _room_scan(rng)
        return odo.process(t, pts, np.full(len(pts), t), (motion[0] + t, motion[1]), T_pred, still=still)

    first = scan(0.0, np.eye(4), still=True)
    assert first.registration is None and not first.held and odo.held == 0
    size = len(odo.map)
    for k in range(1, 3):  # inserted on the usual schedule (every ``map_every``-th scan)
        drift = host.make_pose(np.eye(3), np.array([0.004 * k, 0.0, 0.0]))  # the IMU's, standing
        held = scan(0.1 * k, drift, still=True)
        assert held.held and held.registration is None and odo.held == k
        np.testing.assert_array_equal(held.T_odom, first.T_odom)
    assert len(odo.map) > size
    assert odo.weak_run(held.index, held.index) == 0 and held.last_degenerate == first.index
    moving = scan(0.3, host.make_pose(np.eye(3), np.array([0.05, -0.03, 0.02])), still=False)
    assert not moving.held and moving.registration.converged
    assert np.linalg.norm(moving.T_odom[:3, 3]) < 0.01


def test_factor_consistency_scores_each_front_end_against_ground_truth():
    """Closed form: LiDAR errors drawn at exactly their stated sigma give NEES ~1 and an axis
    z RMS ~1; visual errors twice their sigma give ~4 and ~2; the along-axis z uses the
    marginal sigma of a correlated information; a loop closure counts even without motion,
    a standing odometry pair does not."""
    from types import SimpleNamespace

    from jaxslam.pipeline._run import factor_consistency

    rng = np.random.default_rng(5)
    n = 400
    gt = np.stack([host.se3_exp(np.r_[0.05 * rng.normal(size=3), 0.3 * k, 0.02 * np.sin(k), 0.0]) for k in range(n)])
    gt[7] = gt[6]  # standing still: left out of the odometry
    sig = np.array([0.001, 0.001, 0.001, 0.01, 0.004, 0.004])
    info = np.diag(1 / sig**2)
    edges = []
    for k in range(1, n):
        T_true = host.inverse(gt[k - 1]) @ gt[k]
        for kind, f in (("lidar odometry", 1.0), ("visual odometry", 2.0)):
            e = f * sig * rng.normal(size=6)
            # measured = T_true Exp(-e): then Log(measured^-1 T_true) = e
            edges.append((kind, k - 1, k, T_true @ host.se3_exp(-e), info))
    # a correlated information: the x marginal is what the z divides by
    cov = np.diag(sig**2)
    cov[3, 4] = cov[4, 3] = 0.8 * sig[3] * sig[4]
    e = np.r_[0, 0, 0, 0.02, 0, 0]
    edges.append(("loop closure", 0, 0, host.se3_exp(-e), np.linalg.inv(cov)))
    out = factor_consistency(SimpleNamespace(edges=edges), gt)  # type: ignore[arg-type]
    assert set(out) == {"lidar odometry", "visual odometry", "loop closure"}
    # an estimator's accepted loops are also scored apart, LiDAR and visual
    loop_obj = SimpleNamespace(i=0, j=0, T=host.se3_exp(-e), information=np.linalg.inv(cov))
    from jaxslam.pipeline._config import PipelineConfig, config_from_dict

    def split_with(cfg):
        est = SimpleNamespace(edges=edges, loops=SimpleNamespace(accepted=[loop_obj]), visual_loops=None, cfg=cfg)
        return factor_consistency(est, gt)  # type: ignore[arg-type]

    split = split_with(PipelineConfig())
    assert split["lidar loop"] == split["loop closure"] and "visual loop" not in split
    # scored with the information the graph's loop factor has: the along-axis sigma scaled
    wider = split_with(config_from_dict({"loop": {"axis_sigma_scale": 2.0, "visual_axis_sigma_scale": 5.0}}))
    assert wider["lidar loop"]["axis_z_rms"] == pytest.approx(split["lidar loop"]["axis_z_rms"] / 2, rel=1e-9)
    lid, vis, loop = out["lidar odometry"], out["visual odometry"], out["loop closure"]
    assert lid["measurements"] == vis["measurements"] == n - 2  # the standing pair is left out
    assert lid["nees"] == pytest.approx(1.0, abs=0.1) and vis["nees"] == pytest.approx(4.0, abs=0.4)
    assert lid["axis_z_rms"] == pytest.approx(1.0, abs=0.1) and vis["axis_z_rms"] == pytest.approx(2.0, abs=0.2)
    assert lid["over_95"] == pytest.approx(0.05, abs=0.03) and vis["over_95"] > 0.5
    assert vis["axis_error_rms_m"] == pytest.approx(0.02, rel=0.15)
    assert loop["measurements"] == 1
    assert loop["axis_z_rms"] == pytest.approx(2.0, rel=1e-9)  # 0.02 m over the 0.01 m marginal
    assert loop["nees"] == pytest.approx(float(e @ np.linalg.inv(cov) @ e) / 6, rel=1e-9)


def test_odometry_length_ratio_compares_each_front_end_with_ground_truth():
    """Closed form: visual measurements 2 % short and LiDAR ones exact along a curved path
    give 0.98 and 1.0; a loop closure and a standing-still pair are left out."""
    from types import SimpleNamespace

    from jaxslam.pipeline._run import odometry_length_ratio

    rng = np.random.default_rng(3)
    n = 12
    gt = np.stack([host.se3_exp(np.r_[0.1 * rng.normal(size=3), k * 0.4, 0.1 * np.sin(k), 0.0]) for k in range(n)])
    gt[5] = gt[4]  # standing still from 4 to 5: no motion to compare
    edges = []
    for k in range(1, n):
        T = host.inverse(gt[k - 1]) @ gt[k]
        short = T.copy()
        short[:3, 3] *= 0.98
        edges.append(("lidar odometry", k - 1, k, T, np.eye(6)))
        edges.append(("visual odometry", k - 1, k, short, np.eye(6)))
    edges.append(("loop closure", 0, n - 1, np.eye(4), np.eye(6)))  # wrong on purpose: not counted
    edges.append(("lidar odometry", 0, 5, np.eye(4), np.eye(6)))  # not consecutive: not counted
    out = odometry_length_ratio(SimpleNamespace(edges=edges), gt)  # type: ignore[arg-type]
    assert set(out) == {"lidar odometry", "visual odometry"}
    moved = [k for k in range(1, n) if np.linalg.norm((host.inverse(gt[k - 1]) @ gt[k])[:3, 3]) >= 0.1]
    assert len(moved) < n - 1  # the still pair is left out
    for kind, want in (("lidar odometry", 1.0), ("visual odometry", 0.98)):
        assert out[kind]["pairs"] == len(moved)
        assert out[kind]["total"] == pytest.approx(want, abs=1e-12)
        assert out[kind]["median"] == pytest.approx(want, abs=1e-12)


def test_length_sigma_adds_variance_along_the_translation_only():
    """``vision.length_sigma_ratio``: the information equals the inverse of the covariance with
    ``(ratio |t|)^2`` added along ``t`` (closed form), the length's variance grows by exactly
    that much, and the information along any direction orthogonal to ``info @ u`` is kept."""
    from jaxslam.pipeline._visual import with_length_sigma

    rng = np.random.default_rng(7)
    A = rng.normal(size=(6, 6))
    info = A @ A.T + 0.1 * np.eye(6)
    t = np.array([0.25, -0.02, 0.01])
    out = with_length_sigma(info, t, 0.01)
    u = np.r_[np.zeros(3), t / np.linalg.norm(t)]
    cov = np.linalg.inv(info) + (0.01 * np.linalg.norm(t)) ** 2 * np.outer(u, u)
    np.testing.assert_allclose(out, np.linalg.inv(cov), rtol=1e-9, atol=1e-9)
    var_before, var_after = u @ np.linalg.inv(info) @ u, u @ np.linalg.inv(out) @ u
    assert var_after - var_before == pytest.approx((0.01 * np.linalg.norm(t)) ** 2, rel=1e-9)
    iu = info @ u
    z = rng.normal(size=6)
    z -= (z @ iu) / (iu @ iu) * iu  # orthogonal to info @ u
    assert z @ out @ z == pytest.approx(z @ info @ z, rel=1e-9)
    np.testing.assert_array_equal(with_length_sigma(info, np.zeros(3), 0.01), info)  # no motion: unchanged


def test_lidar_axis_sigma_adds_variance_along_body_x_only():
    """``lidar.min_sigma_axis``: the odometry factor's covariance is the registration's (through
    the extrinsic, scaled, regularised, floored) plus ``sigma^2`` on body-x translation and
    nothing else; the LiDAR loops' information (no ``axis_sigma``) is unchanged."""
    from jaxslam.pipeline._config import LidarConfig
    from jaxslam.pipeline._lidar_frontend import information_for_factor

    rng = np.random.default_rng(3)
    A = rng.normal(size=(6, 6))
    info_l = 1e4 * (A @ A.T) + np.eye(6)
    T_bl = host.se3_exp(np.array([0.02, -0.1, 0.3, 0.2, 0.0, 0.1]))
    cfg = LidarConfig()
    assert cfg.min_sigma_axis == 0.0  # off by default
    plain = information_for_factor(info_l, T_bl, cfg, 0.1)
    with_axis = information_for_factor(info_l, T_bl, cfg, 0.1, 0.015)
    diff = np.linalg.inv(with_axis) - np.linalg.inv(plain)
    expect = np.zeros((6, 6))
    expect[3, 3] = 0.015**2
    np.testing.assert_allclose(diff, expect, atol=1e-12)
    np.testing.assert_array_equal(information_for_factor(info_l, T_bl, cfg, 0.1, 0.0), plain)
    with pytest.raises(ConfigError, match="min_sigma_axis"):
        config_from_dict({"lidar": {"min_sigma_axis": -0.01}})
    with pytest.raises(ConfigError, match="scale_revert_to"):
        config_from_dict({"vision": {"scale_revert_to": "mean"}})


def test_axis_sigma_scale_multiplies_the_along_axis_sigma_only():
    """``{lidar,vision,loop}.axis_sigma_scale``: the factor's covariance becomes ``D C D`` with
    ``D = diag(1, 1, 1, s, 1, 1)`` (body-x sigma times s, its correlations kept, every other
    marginal unchanged), also for a rank-deficient information; off (1.0) by default."""
    from jaxslam.pipeline._config import PipelineConfig
    from jaxslam.pipeline._lidar_frontend import axis_sigma_scaled

    rng = np.random.default_rng(11)
    A = rng.normal(size=(6, 6))
    info = A @ A.T + 0.1 * np.eye(6)
    cov = np.linalg.inv(info)
    out_cov = np.linalg.inv(axis_sigma_scaled(info, 1.7))
    D = np.diag([1, 1, 1, 1.7, 1, 1])
    np.testing.assert_allclose(out_cov, D @ cov @ D, rtol=1e-9, atol=1e-12)
    assert np.sqrt(out_cov[3, 3] / cov[3, 3]) == pytest.approx(1.7, rel=1e-9)
    keep = [0, 1, 2, 4, 5]
    np.testing.assert_allclose(np.diag(out_cov)[keep], np.diag(cov)[keep], rtol=1e-9)
    # rank-deficient (a visual loop measures one direction): a vector in the null space stays there
    a = rng.normal(size=6)
    low = np.outer(a, a)
    scaled = axis_sigma_scaled(low, 2.0)
    assert np.linalg.matrix_rank(scaled) == 1
    b = a / np.array([1, 1, 1, 2.0, 1, 1])
    np.testing.assert_allclose(scaled, np.outer(b, b), rtol=1e-12)
    assert axis_sigma_scaled(info, 1.0) is info
    cfg = PipelineConfig()
    assert cfg.lidar.axis_sigma_scale == cfg.vision.axis_sigma_scale == cfg.loop.axis_sigma_scale == 1.0
    assert cfg.loop.visual_axis_sigma_scale == 1.0
    for section, field in (("lidar", "a"), ("vision", "a"), ("loop", "a"), ("loop", "visual_a")):
        field += "xis_sigma_scale"
        assert getattr(getattr(config_from_dict({section: {field: 1.4}}), section), field) == 1.4
        with pytest.raises(ConfigError, match=field):
            config_from_dict({section: {field: 0.0}})


def test_axis_sigma_calibration_pools_the_runs_z_and_undoes_it():
    """Closed form: two runs' along-axis z RMS pooled by measurement count, times the scale
    the runs were made with; a kind with too few measurements is left out; the result loads
    as a config."""
    from jaxslam.pipeline._run import axis_sigma_calibration

    def c(n, z):
        return {"measurements": n, "axis_z_rms": z}

    runs = [
        {"lidar odometry": c(100, 1.2), "lidar loop": c(5, 0.5)},
        {"lidar odometry": c(300, 1.6), "visual odometry": c(40, 2.0)},
        {"visual loop": c(50, 0.9), "loop closure": c(55, 3.0)},
        {},
    ]
    out = axis_sigma_calibration(runs)
    assert set(out) == {"lidar", "vision", "loop"}
    assert out["loop"] == {"visual_axis_sigma_scale": pytest.approx(0.9)}  # 5 LiDAR loops are too few
    assert out["lidar"]["axis_sigma_scale"] == pytest.approx(np.sqrt((100 * 1.44 + 300 * 2.56) / 400), rel=1e-12)
    assert out["vision"]["axis_sigma_scale"] == pytest.approx(2.0, rel=1e-12)
    base = config_from_dict({"lidar": {"axis_sigma_scale": 2.0}})
    again = axis_sigma_calibration(runs, base)
    assert again["lidar"]["axis_sigma_scale"] == pytest.approx(2 * out["lidar"]["axis_sigma_scale"], rel=1e-12)
    assert config_from_dict(out).vision.axis_sigma_scale == pytest.approx(2.0)
    assert axis_sigma_calibration(runs, min_measurements=1)["loop"]["axis_sigma_scale"] == pytest.approx(0.5)
    assert config_from_dict(out).loop.visual_axis_sigma_scale == pytest.approx(0.9)


def test_calibrate_axis_script_writes_a_config_and_refuses_bad_input(tmp_path):
    """``benchmarks/calibrate_axis.py``: benchmark rows in, a loadable config out; a file that
    is not JSON, or a run without ``factor_consistency``, is one line naming the file, exit 1."""
    import json
    import subprocess
    import sys
    from pathlib import Path

    from jaxslam.pipeline._config import load_config

    script = Path(__file__).resolve().parents[2] / "benchmarks" / "calibrate_axis.py"
    rows = [{"factor_consistency": {"lidar odometry": {"measurements": 400, "axis_z_rms": 1.5}}}]
    good = tmp_path / "runs.json"
    good.write_text(json.dumps(rows))
    out = tmp_path / "cal.yaml"

    def run(*files):
        return subprocess.run(
            [sys.executable, str(script), *map(str, files), "-o", str(out)], capture_output=True, text=True
        )

    ok = run(good)
    assert ok.returncode == 0, ok.stderr
    assert load_config(out).lidar.axis_sigma_scale == pytest.approx(1.5)
    bad = tmp_path / "bad.json"
    bad.write_text("{not json")
    empty = tmp_path / "empty.json"
    empty.write_text(json.dumps([{"ape_rmse_m": 0.01}]))
    for f, words in ((bad, "expected a JSON file"), (empty, "no factor_consistency"), (tmp_path / "gone.json", "gone")):
        r = run(good, f)
        assert r.returncode == 1 and str(f.name) in r.stderr and words in r.stderr, r.stderr
        assert len(r.stderr.strip().splitlines()) == 1 and "Traceback" not in r.stderr

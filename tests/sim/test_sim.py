"""The tunnel simulator: determinism, mutual consistency of ground truth / IMU / LiDAR,
lighting, and that its recordings open with rosbags and jaxslam's readers."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from jaxslam.cli import main
from jaxslam.io import open_recording
from jaxslam.measurements import Image, ImuSample, LidarScan, PositionFix
from jaxslam.sim import ImuConfig, Simulation, simulate_tunnel, synthesize_imu

from .conftest import tiny_config


@pytest.fixture(scope="module")
def sim(tiny):
    return Simulation.create(tiny)


def test_same_seed_same_recording_other_seed_differs(tmp_path):
    cfg = dataclasses.replace(tiny_config(seed=3), camera=dataclasses.replace(tiny_config().camera, rate=2.0))
    a = simulate_tunnel(cfg, tmp_path / "a", fmt="euroc")
    b = simulate_tunnel(cfg, tmp_path / "b", fmt="euroc")
    simulate_tunnel(dataclasses.replace(cfg, seed=4), tmp_path / "c", fmt="euroc")
    assert a["counts"] == b["counts"]
    for rel in ("mav0/imu0/data.csv", "mav0/total_station0/data.csv", "mav0/state_groundtruth_estimate0/data.csv"):
        assert (tmp_path / "a" / rel).read_bytes() == (tmp_path / "b" / rel).read_bytes()
    pngs = sorted((tmp_path / "a" / "mav0/cam0/data").iterdir())
    assert pngs and all(p.read_bytes() == (tmp_path / "b/mav0/cam0/data" / p.name).read_bytes() for p in pngs)
    scans = sorted((tmp_path / "a" / "mav0/lidar0/data").iterdir())
    assert all(np.array_equal(np.load(p), np.load(tmp_path / "b/mav0/lidar0/data" / p.name)) for p in scans[:5])
    assert (tmp_path / "a/mav0/imu0/data.csv").read_bytes() != (tmp_path / "c/mav0/imu0/data.csv").read_bytes()


def _quat_mul(a, b):
    w1, x1, y1, z1 = a
    w2, x2, y2, z2 = b
    return np.array(
        [
            w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2,
            w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
            w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
            w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2,
        ]
    )


def _quat_matrix(q):
    w, x, y, z = q / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def test_noise_free_imu_integrates_to_the_ground_truth(sim):
    """RK4 dead reckoning of exact IMU readings (sampled at 400 Hz: the odd samples are the
    RK4 midpoints of a 200 Hz integration) stays on the ground truth over the whole run."""
    from jaxslam.sim._trajectory import matrix_to_quaternion

    traj = sim.trajectory
    t = np.arange(0.0, traj.duration, 1 / 400)
    st = traj.state(t)
    imu = synthesize_imu(st, ImuConfig(noise=False))
    g = np.array([0.0, 0.0, -9.81])
    q = matrix_to_quaternion(st["R"][:1])[0]
    p, v = st["p"][0].copy(), st["v"][0].copy()
    h = 2 / 400

    def deriv(q, v, k):
        R = _quat_matrix(q)
        dq = 0.5 * _quat_mul(q, np.concatenate([[0.0], imu["gyro"][k]]))
        return dq, R @ imu["acc"][k] + g, v

    for k in range(0, len(t) - 2, 2):
        dq1, dv1, dp1 = deriv(q, v, k)
        dq2, dv2, dp2 = deriv(q + h / 2 * dq1, v + h / 2 * dv1, k + 1)
        dq3, dv3, dp3 = deriv(q + h / 2 * dq2, v + h / 2 * dv2, k + 1)
        dq4, dv4, dp4 = deriv(q + h * dq3, v + h * dv3, k + 2)
        q = q + h / 6 * (dq1 + 2 * dq2 + 2 * dq3 + dq4)
        q /= np.linalg.norm(q)
        p = p + h / 6 * (dp1 + 2 * dp2 + 2 * dp3 + dp4)
        v = v + h / 6 * (dv1 + 2 * dv2 + 2 * dv3 + dv4)
    last = len(t) - 1 - (len(t) - 1) % 2
    assert np.linalg.norm(p - st["p"][last]) < 2e-3
    assert np.linalg.norm(v - st["v"][last]) < 1e-3
    dR = _quat_matrix(q).T @ st["R"][last]
    assert np.arccos(np.clip((np.trace(dR) - 1) / 2, -1, 1)) < 1e-5


def test_jaxslam_preintegration_matches_ground_truth(sim):
    """The same check through jaxslam's own IMU preintegration, 1 s intervals, 200 Hz."""
    import jax.numpy as jnp

    from jaxslam.factors import PreintegrationParams, predict_imu_state, preintegrate
    from jaxslam.lie import SE3
    from jaxslam.sim._trajectory import matrix_to_quaternion

    traj = sim.trajectory
    t = np.arange(0.0, traj.duration, 1 / 200)
    st = traj.state(t)
    imu = synthesize_imu(st, ImuConfig(noise=False))
    n = 200
    starts = np.arange(0, len(t) - n - 1, n)
    acc = np.stack([imu["acc"][i : i + n] for i in starts])
    gyro = np.stack([imu["gyro"][i : i + n] for i in starts])
    params = PreintegrationParams.make_shared_u(9.81, accelerometer_noise_density=1e-3, gyroscope_noise_density=1e-4)
    pim = preintegrate(acc, gyro, np.full(acc.shape[:2], 1 / 200), params)
    pose_i = SE3(jnp.asarray(np.concatenate([matrix_to_quaternion(st["R"][starts]), st["p"][starts]], axis=1)))
    grav = jnp.broadcast_to(jnp.asarray(params.gravity), (len(starts), 3))
    pred, _ = predict_imu_state(
        pim.bias_corrected(np.zeros(6)), jnp.full(len(starts), 1.0), grav, pose_i, st["v"][starts]
    )
    err = np.linalg.norm(np.asarray(pred.translation) - st["p"][starts + n], axis=1)
    assert err.max() < 0.02, err.max()  # first-order sampling of 4-14 Hz vibration over 1 s


def test_lidar_points_lie_on_the_tunnel_surface(sim):
    traj, lidar = sim.trajectory, sim.lidar
    t_turn = traj.t_turn + sim.config.motion.turn / 2  # spinning at ~1 rad/s
    for t, cruise in ((traj.t_out + traj.t_leg / 2, True), (t_turn, False)):
        scan = lidar.scan(t, traj.state)
        assert len(scan["points"]) > 1000
        assert scan["point_times"].min() >= 0 and scan["point_times"].max() < 0.1
        st = traj.state(t + scan["point_times"])
        o = st["p"] + np.einsum("nij,j->ni", st["R"], lidar.t_bl)
        world = o + np.einsum("nij,nj->ni", st["R"], scan["points"])
        d = np.abs(sim.tunnel.signed_distance(world))
        # Gaussian range noise 2 cm: the distance to the surface is ~|noise| (x cos incidence)
        assert np.median(d) < 0.02 and np.quantile(d, 0.99) < 0.09, (np.median(d), np.quantile(d, 0.99))
        # without per-point poses (one pose for the whole frame) the turn smears the scan
        one = st["p"][0] + lidar.t_bl @ st["R"][0].T + scan["points"] @ st["R"][0].T
        d1 = np.abs(sim.tunnel.signed_distance(one))
        if not cruise:
            assert np.quantile(d1, 0.9) > 5 * np.quantile(d, 0.9)


def test_images_are_darker_in_dark_gaps_than_under_lamps(tiny):
    from jaxslam.sim import LightingConfig

    cfg = dataclasses.replace(tiny, tunnel=dataclasses.replace(tiny.tunnel, length=30.0))
    sim = Simulation.create(dataclasses.replace(cfg, lighting=LightingConfig(mode="dark")))
    lamps = sim.atlas.lamps
    lit = lamps[(lamps[:, 2] > 0) & (lamps[:, 0] > 2) & (lamps[:, 0] < 28)]
    gaps = np.arange(2.0, 28.0, 0.5)
    lux_at = [sim.atlas.irradiance_at(np.array([s]), np.array([sim.tunnel.config.width + 1.0]))[0] for s in gaps]
    dark_s = gaps[int(np.argmin(lux_at))]
    assert min(lux_at) < 30  # a dark gap below 30 lx exists

    def mean_image(s):
        sim.camera.exposure_gain = None
        R = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])  # facing the left wall
        p = sim.tunnel.to_world(np.array(s), np.array(-0.8), np.array(1.2))
        out = [sim.camera.render(0.0, R, p, np.zeros(3), np.zeros(3)) for _ in range(6)]
        return float(out[-1][0].mean()), out[-1][1]

    (dark, info), (bright, _) = mean_image(dark_s), mean_image(lit[0, 0])
    assert dark < 0.6 * bright
    # in the gap the auto-exposure runs out of exposure time and gain
    assert info["gain"] == pytest.approx(sim.camera.config.max_gain)


def test_recording_opens_with_rosbags_and_open_recording(tmp_path, tiny):
    from rosbags.highlevel import AnyReader

    cfg = dataclasses.replace(tiny, camera=dataclasses.replace(tiny.camera, rate=2.0))
    by_fmt = {}
    for fmt, name in (("bag", "r.bag"), ("bag2", "r2"), ("euroc", "re")):
        summary = simulate_tunnel(cfg, tmp_path / name, fmt=fmt)
        rec = open_recording(tmp_path / name)
        records = list(rec)
        assert not rec.skipped
        kinds = {type(r) for r in records}
        assert {ImuSample, Image, LidarScan} <= kinds
        n_img = sum(isinstance(r, Image) for r in records)
        assert n_img == summary["counts"]["images"]
        gt = rec.ground_truth()
        assert gt is not None and len(gt) == summary["counts"]["ground_truth"]
        by_fmt[fmt] = records
        assert (tmp_path / f"{name.split('.')[0]}.contact.png").is_file()
        assert json.loads((tmp_path / f"{name.split('.')[0]}.summary.json").read_text())["loop_gap_m"] < 1e-9
    assert PositionFix in {type(r) for r in by_fmt["euroc"]}
    with AnyReader([tmp_path / "r.bag"]) as reader:
        topics = {c.topic: c.msgtype for c in reader.connections}
    assert topics["/total_station/prism"] == "geometry_msgs/msg/PointStamped"
    assert topics["/lidar/points"] == "sensor_msgs/msg/PointCloud2"
    imu = {f: [r for r in by_fmt[f] if isinstance(r, ImuSample)] for f in by_fmt}
    for f in ("bag2", "euroc"):
        assert len(imu[f]) == len(imu["bag"])
        assert all(a.t == b.t and np.array_equal(a.acc, b.acc) for a, b in zip(imu["bag"], imu[f]))


def test_cli_smoke(tmp_path, capsys):
    out = tmp_path / "cli.bag"
    rc = main(
        [
            *("simulate", "-o", str(out), "--length", "1", "--width", "48", "--height", "32"),
            *("--decimation", "64", "--camera-rate", "2", "--lidar", "ring16", "-q"),
        ]
    )
    assert rc == 0 and out.is_file()
    assert "wrote" in capsys.readouterr().out
    summary = json.loads((tmp_path / "cli.summary.json").read_text())
    assert summary["counts"]["images"] > 10 and (tmp_path / "cli.contact.png").is_file()
    assert main(["simulate", "-o", str(out), "--length", "1", "-q"]) == 1  # refuses to overwrite


@pytest.mark.parametrize("section", ["rectangular", "horseshoe"])
@pytest.mark.parametrize("curvature", [0.0, 1 / 150])
def test_raycast_hits_the_analytic_surface(section, curvature):
    from jaxslam.sim import Tunnel, TunnelConfig

    tun = Tunnel(TunnelConfig(length=30.0, section=section, curvature=curvature, slope=0.02))
    rng = np.random.default_rng(0)
    d = rng.normal(size=(20000, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    o = tun.to_world(np.array(12.0), np.array(-0.4), np.array(0.8))
    hit = tun.raycast(np.broadcast_to(o, d.shape), d)
    err = np.abs(tun.signed_distance(hit["p"]))
    assert np.quantile(err, 0.999) < 1e-6
    assert np.all(hit["lam"] > 0) and set(np.unique(hit["wall"])) >= {0, 1, 2, 3}
    # perimeter coordinates invert
    on_wall = hit["wall"] <= 3
    u, v, _ = tun.surface_point(hit["s"][on_wall], hit["c"][on_wall])
    np.testing.assert_allclose(u, hit["u"][on_wall], atol=1e-6)
    np.testing.assert_allclose(v, hit["v"][on_wall], atol=1e-6)

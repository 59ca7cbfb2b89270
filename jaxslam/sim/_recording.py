"""``simulate_tunnel``: a whole synthetic recording, written through the ordinary writers.

The robot drives the out-and-back route (:mod:`._trajectory`) through the tunnel
(:mod:`._tunnel`, :mod:`._texture`) carrying an IMU (200 Hz), a camera (10 Hz), a LiDAR
(HAP or 16-ring, 10 Hz) and a total-station prism. Records go out in time order through
:func:`jaxslam.io.open_writer` (ROS1 bag, ROS2 mcap bag or EuRoC folder): IMU samples,
images, LiDAR scans, ground-truth poses of the body (= IMU) frame at ``gt_rate`` and prism
fixes at ``fix_rate``. Beside the recording go ``<name>.summary.json`` (figures and the
effective config), ``<name>.frames.csv`` (per-frame exposure and lighting labels),
``<name>.contact.png`` (a contact sheet of sample frames), ``<name>.gt.tum`` and
``<name>.map.ply`` (the noise-free LiDAR map, decimated) and ``<name>.rig.yaml`` (the rig's
calibration: intrinsics, distortion, extrinsics, IMU noise densities — what a calibration
step would give; ``jaxslam run`` reads it). Deterministic by ``seed``.
"""

from __future__ import annotations

import dataclasses
import json
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import jax.numpy as jnp
import numpy as np

from ..errors import ConfigError
from ..measurements import Image, ImuSample, LidarScan, PoseStamped, PositionFix
from ._camera import CameraConfig, CameraSimulator
from ._imu import ImuConfig, synthesize_imu
from ._lidar import LidarConfig, LidarSimulator
from ._texture import LightingConfig, SurfaceAtlas
from ._trajectory import MotionConfig, TunnelTrajectory, matrix_to_quaternion
from ._tunnel import Tunnel, TunnelConfig

T0_NS = 1_700_000_000_000_000_000
"""Start time of every simulated recording (ns since the epoch)."""


@dataclasses.dataclass(frozen=True)
class SimConfig:
    """Everything that defines a simulated recording (one sub-config per subsystem)."""

    seed: int = 0
    tunnel: TunnelConfig = dataclasses.field(default_factory=TunnelConfig)
    lighting: LightingConfig = dataclasses.field(default_factory=LightingConfig)
    motion: MotionConfig = dataclasses.field(default_factory=MotionConfig)
    camera: CameraConfig = dataclasses.field(default_factory=CameraConfig)
    lidar: LidarConfig = dataclasses.field(default_factory=LidarConfig)
    imu: ImuConfig = dataclasses.field(default_factory=ImuConfig)
    gt_rate: float = 100.0
    """Ground-truth pose rate (Hz)."""
    fix_rate: float = 5.0
    """Total-station rate (Hz)."""
    fix_sigma: float = 0.003
    """Total-station noise per axis (m)."""
    prism: tuple[float, float, float] = (0.0, 0.0, 0.55)
    """Prism lever arm in the body frame (m)."""
    map_every: int = 10
    """Keep every n-th LiDAR frame's noise-free points in the ground-truth map (0 = no map)."""

    def __post_init__(self) -> None:
        if not (self.gt_rate > 0 and self.fix_rate > 0 and self.fix_sigma > 0):
            raise ConfigError("gt_rate, fix_rate and fix_sigma must be positive")

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


@dataclasses.dataclass
class Simulation:
    """A simulation before writing: the world and the sensors (handy for tests)."""

    config: SimConfig
    tunnel: Tunnel
    atlas: SurfaceAtlas
    trajectory: TunnelTrajectory
    camera: CameraSimulator
    lidar: LidarSimulator

    @classmethod
    def create(cls, config: SimConfig) -> Simulation:
        tunnel = Tunnel(config.tunnel)
        atlas = SurfaceAtlas(tunnel, config.lighting, seed=config.seed)
        traj = TunnelTrajectory(tunnel, config.motion, seed=config.seed)
        cam = CameraSimulator(config.camera, tunnel, atlas, seed=config.seed)
        lidar = LidarSimulator(config.lidar, tunnel, atlas, seed=config.seed)
        return cls(config, tunnel, atlas, traj, cam, lidar)

    def times_ns(self, rate: float, offset: float = 0.0) -> np.ndarray:
        """Integer-ns stamps at ``rate`` over the run (relative times via :func:`rel`)."""
        n = int(np.floor((self.trajectory.duration - offset) * rate)) + 1
        return T0_NS + np.rint((offset + np.arange(n) / rate) * 1e9).astype(np.int64)

    def lux_and_region(self, R_wb: np.ndarray, p_wb: np.ndarray) -> tuple[float, str, float]:
        """Median irradiance (lux) of the surface the camera sees, the stretch label
        (``plain`` / ``structured``) and the route coordinate of the camera."""
        R_wc, p_wc = self.camera.pose(R_wb, p_wb)
        rays = self.camera.rays[::61]
        hit = self.tunnel.raycast(np.broadcast_to(p_wc, rays.shape), rays @ R_wc.T)
        ok = hit["c"] >= 0
        lux = float(np.median(self.atlas.irradiance_at(hit["s"][ok], hit["c"][ok]))) if ok.any() else 0.0
        s_cam = float(self.tunnel.to_tunnel(p_wc)[0])
        ahead = np.median(hit["s"][ok]) if ok.any() else s_cam
        cfg = self.config.tunnel
        plain = any(f0 * cfg.length <= ahead <= f1 * cfg.length for f0, f1 in cfg.plain)
        return lux, "plain" if plain else "structured", s_cam


def rel(ns: np.ndarray | int) -> np.ndarray:
    """Seconds since the start of the run of integer-ns stamps."""
    return (np.asarray(ns, dtype=np.int64) - T0_NS) / 1e9


def _contact_sheet(frames: list[tuple[np.ndarray, str]], path: Path, cols: int = 4) -> None:
    from PIL import Image as PILImage
    from PIL import ImageDraw

    if not frames:
        return
    h, w = frames[0][0].shape[:2]
    rows = int(np.ceil(len(frames) / cols))
    sheet = PILImage.new("RGB", (cols * w, rows * (h + 14)), (20, 20, 20))
    draw = ImageDraw.Draw(sheet)
    for k, (img, label) in enumerate(frames):
        r, c = divmod(k, cols)
        sheet.paste(PILImage.fromarray(img).convert("RGB"), (c * w, r * (h + 14) + 14))
        draw.text((c * w + 3, r * (h + 14) + 1), label, fill=(230, 230, 120))
    sheet.save(path)


def rig_calibration(config: SimConfig) -> dict[str, Any]:
    """The simulated rig's calibration in :class:`jaxslam.pipeline.RigConfig`'s keys."""
    from ..lie import host
    from ._camera import R_BODY_CAM

    cam, imu = config.camera, config.imu
    return {
        "camera_intrinsics": [float(v) for v in cam.intrinsics()],
        "camera_distortion": [float(v) for v in cam.distortion],
        "camera_size": [cam.width, cam.height],
        "body_T_camera": [float(v) for v in host.matrix_to_quat(R_BODY_CAM)] + [float(v) for v in cam.translation],
        "body_T_lidar": [1.0, 0.0, 0.0, 0.0] + [float(v) for v in config.lidar.translation],
        "lidar_model": config.lidar.model,
        "accelerometer_noise_density": imu.accelerometer_noise_density,
        "gyroscope_noise_density": imu.gyroscope_noise_density,
        "accelerometer_random_walk": imu.accelerometer_random_walk,
        "gyroscope_random_walk": imu.gyroscope_random_walk,
        "gravity": 9.81,
    }


def write_rig(config: SimConfig, path: str | Path) -> None:
    import yaml

    Path(path).write_text(
        "# jaxslam rig calibration (simulated rig)\n"
        + yaml.safe_dump({"rig": rig_calibration(config)}, sort_keys=False)
    )


def simulate_tunnel(
    config: SimConfig,
    output: str | Path,
    fmt: str = "bag",
    progress: Callable[[int, int], None] | None = None,
) -> dict[str, Any]:
    """Simulate a recording into ``output`` (a ``.bag`` file, a ROS2 bag folder or an EuRoC
    folder, by ``fmt``: ``bag``, ``bag2``, ``bag2-db3``, ``euroc``) and the side files (see the
    module docstring). ``progress(done, total)`` is called per camera frame. Returns the summary."""
    from ..io import open_writer, write_ply, write_tum
    from ..io._trajectory import Trajectory
    from ..lie import SE3

    t_start = time.perf_counter()
    out = Path(output)
    if out.exists():
        raise ConfigError(f"{out} exists; choose a new output path")
    out.parent.mkdir(parents=True, exist_ok=True)
    stem = out.parent / (out.stem if out.suffix else out.name)
    sim = Simulation.create(config)
    t_world = time.perf_counter() - t_start
    traj, cfg = sim.trajectory, config

    imu_ns = sim.times_ns(cfg.imu.rate)
    imu_state = traj.state(rel(imu_ns))
    imu = synthesize_imu(imu_state, cfg.imu, seed=cfg.seed)
    gt_ns = sim.times_ns(cfg.gt_rate)
    gt_state = traj.state(rel(gt_ns))
    gt_q = matrix_to_quaternion(gt_state["R"])
    gt_params = np.concatenate([gt_q, gt_state["p"]], axis=1)
    fix_ns = sim.times_ns(cfg.fix_rate)
    fs = traj.state(rel(fix_ns))
    rng = np.random.default_rng([cfg.seed, 17])
    prism = fs["p"] + np.einsum("nij,j->ni", fs["R"], np.asarray(cfg.prism))
    prism_noisy = prism + cfg.fix_sigma * rng.standard_normal(prism.shape)
    cam_ns = sim.times_ns(cfg.camera.rate, offset=0.5 / cfg.camera.rate)
    lidar_ns = sim.times_ns(cfg.lidar.rate)[:-1]  # every scan ends inside the run

    events: list[tuple[int, int, int]] = []  # (ns, kind, index); kinds: 0 imu 1 gt 2 fix 3 lidar 4 cam
    for kind, stamps in enumerate((imu_ns, gt_ns, fix_ns, lidar_ns, cam_ns)):
        events += [(int(s), kind, i) for i, s in enumerate(stamps)]
    events.sort()

    frame_rows: list[str] = ["t_ns,s_cam,region,lux,mean,exposure,gain,blur_px"]
    frame_info: list[dict[str, Any]] = []
    thumbs: dict[int, tuple[np.ndarray, str]] = {}
    sample_at = set(np.linspace(0, len(cam_ns) - 1, 12).astype(int).tolist())
    lidar_counts: list[int] = []
    map_pts: list[np.ndarray] = []
    t_cam = t_lidar = t_write = 0.0
    with open_writer(out, fmt) as writer:
        for ns, kind, i in events:
            t = ns / 1e9
            if kind == 0:
                writer.write(ImuSample(t, imu["acc"][i], imu["gyro"][i]))
            elif kind == 1:
                writer.write(PoseStamped(t, gt_params[i]))
            elif kind == 2:
                writer.write(PositionFix(t, prism_noisy[i], cfg.fix_sigma))
            elif kind == 3:
                t0 = time.perf_counter()
                scan = sim.lidar.scan(float(rel(ns)), traj.pose)
                t_lidar += time.perf_counter() - t0
                lidar_counts.append(len(scan["points"]))
                if cfg.map_every and i % cfg.map_every == 0:
                    map_pts.append(scan["world"][::4])
                t0 = time.perf_counter()
                ring = scan["ring"] if cfg.lidar.model == "ring16" else None
                writer.write(LidarScan(t, scan["points"], scan["intensity"], scan["point_times"], ring))
                t_write += time.perf_counter() - t0
            else:
                t0 = time.perf_counter()
                st = traj.state(np.array([rel(ns)]))
                R, p, v, w = st["R"][0], st["p"][0], st["v"][0], st["omega"][0]
                img, info = sim.camera.render(float(rel(ns)), R, p, v, w)
                lux, region, s_cam = sim.lux_and_region(R, p)
                t_cam += time.perf_counter() - t0
                t0 = time.perf_counter()
                writer.write(Image(t, img, camera="cam0"))
                t_write += time.perf_counter() - t0
                frame_rows.append(
                    f"{ns},{s_cam:.3f},{region},{lux:.3f},{info['mean']:.3f},{info['exposure']:.6f},"
                    f"{info['gain']:.4f},{info['blur_px']:.3f}"
                )
                frame_info.append({"lux": lux, "region": region, **info})
                if i in sample_at:
                    thumbs[i] = (img, f"t={rel(ns):.1f}s {region} {lux:.0f}lx mean {info['mean']:.0f}")
                if progress is not None:
                    progress(i + 1, len(cam_ns))
    t_total_sensors = time.perf_counter() - t_start

    gt = Trajectory(rel(gt_ns), SE3(jnp.asarray(np.asarray(gt_params))))
    write_tum(f"{stem}.gt.tum", gt)
    write_rig(config, f"{stem}.rig.yaml")
    if map_pts:
        write_ply(f"{stem}.map.ply", np.concatenate(map_pts))
    _contact_sheet([thumbs[k] for k in sorted(thumbs)], Path(f"{stem}.contact.png"))
    Path(f"{stem}.frames.csv").write_text("\n".join(frame_rows) + "\n")
    steps = np.linalg.norm(np.diff(gt_state["p"], axis=0), axis=1)
    frame_lux = np.array([f["lux"] for f in frame_info])
    means = np.array([f["mean"] for f in frame_info])
    summary = {
        "output": str(out),
        "format": fmt,
        "seed": cfg.seed,
        "duration_s": float(traj.duration),
        "path_length_m": float(steps.sum()),
        "loop_gap_m": float(np.linalg.norm(gt_state["p"][-1] - gt_state["p"][0])),
        "counts": {
            "imu": len(imu_ns),
            "images": len(cam_ns),
            "lidar": len(lidar_ns),
            "ground_truth": len(gt_ns),
            "total_station": len(fix_ns),
        },
        "lidar_points_per_frame": {
            "mean": float(np.mean(lidar_counts)) if lidar_counts else 0.0,
            "min": int(min(lidar_counts, default=0)),
            "max": int(max(lidar_counts, default=0)),
            "datasheet": cfg.lidar.points_per_second / cfg.lidar.rate,
            "decimation": cfg.lidar.decimation,
        },
        "images": {
            "mean_intensity": float(means.mean()) if len(means) else 0.0,
            "frames_below_30_lux": int((frame_lux < 30).sum()),
            "frames_plain": int(sum(f["region"] == "plain" for f in frame_info)),
            "lux_median": float(np.median(frame_lux)) if len(frame_lux) else 0.0,
        },
        "seconds": {
            "world": round(t_world, 2),
            "camera": round(t_cam, 2),
            "lidar": round(t_lidar, 2),
            "write": round(t_write, 2),
            "total": round(time.perf_counter() - t_start, 2),
            "sensors_and_write": round(t_total_sensors, 2),
        },
        "config": cfg.to_dict(),
    }
    Path(f"{stem}.summary.json").write_text(json.dumps(summary, indent=2, default=str) + "\n")
    return summary

"""How realistic is the simulated tunnel? Keypoints and brightness beside real low-light images.

Renders the default simulated camera (512x320 grey, "uneven" lighting unless --lighting)
along the outbound leg at 10 Hz (auto-exposure converges as in a recording), labels each
frame by the median irradiance of the surface it sees (dark < 30 lx) and by the stretch it
looks at (plain concrete or structured), and counts ORB (OpenCV, nfeatures=5000) and SIFT
keypoints (and SURF, jaxslam's own implementation with OpenCV's semantics, hessianThreshold
100, when ``jaxslam.vision.surf`` is importable) and the mean grey level per group. The same
figures for the real low-light images in ``../shared/data/lowlight`` (LIME, DICM; grey,
resized to the simulated 512x320 so counts compare) stand
beside them. LiDAR: points per frame of the HAP model at full datasheet rate (decimation 1)
and at the simulator's default decimation, against the datasheet's 452,000 pts/s / 10 Hz.
LiDAR intensity: the relative reflectivity (``jaxslam.lidar.relative_reflectivity``, as the
estimator computes it) of two consecutive simulated scans and of the real scan pair in
``../shared/data/lidar`` (aligned by its reference transform): the median difference at the
same surface spot (within 3 cm) against the spread of the pattern itself. Registration reads
the pattern; this ratio is its noise-to-signal, so the simulator should not make it smaller
than the real one.

Usage: python benchmarks/sim_realism.py [--json PATH] [--lighting uneven] [--frames 120]
(SURF is not in the PyPI OpenCV wheels, hence jaxslam's own.)
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path

import cv2
import jax
import numpy as np

jax.config.update("jax_enable_x64", True)

from jaxslam.sim import LidarConfig, LightingConfig, SimConfig, Simulation  # noqa: E402

DATA = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "lowlight"


try:
    from jaxslam.vision import surf as _surf
except ImportError:  # pragma: no cover - the vision layer is optional here
    _surf = None


def _counts(img: np.ndarray, orb, sift) -> tuple[int, int, int]:
    n_surf = -1
    if _surf is not None:
        n_surf = int(np.asarray(_surf(img, 100.0, max_keypoints=8000)[2]).sum())
    return len(orb.detect(img, None)), len(sift.detect(img, None)), n_surf


def _stats(rows: list[tuple[int, int, int, float]]) -> dict[str, float]:
    if not rows:
        return {"n": 0}
    a = np.asarray(rows, dtype=float)
    return {
        "n": len(rows),
        "orb_median": float(np.median(a[:, 0])),
        "sift_median": float(np.median(a[:, 1])),
        "surf_median": float(np.median(a[:, 2])) if a[0, 2] >= 0 else float("nan"),
        "mean_intensity": float(a[:, 3].mean()),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", help="write the figures as JSON")
    ap.add_argument("--lighting", default="uneven", choices=["dark", "uneven", "normal"])
    ap.add_argument("--frames", type=int, default=150, help="simulated frames (10 Hz, outbound leg)")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()

    orb, sift = cv2.ORB_create(nfeatures=5000), cv2.SIFT_create()
    cfg = SimConfig(seed=args.seed, lighting=LightingConfig(mode=args.lighting))
    t0 = time.perf_counter()
    sim = Simulation.create(cfg)
    traj = sim.trajectory
    times = traj.t_out + np.arange(args.frames) * max(0.1, traj.t_leg / args.frames)
    groups: dict[str, list[tuple[int, int, int, float]]] = {"dark": [], "lit": [], "plain": []}
    for t in times:
        st = traj.state(np.array([t]))
        img, info = sim.camera.render(float(t), st["R"][0], st["p"][0], st["v"][0], st["omega"][0])
        lux, region, _ = sim.lux_and_region(st["R"][0], st["p"][0])
        key = "plain" if region == "plain" else ("dark" if lux < 30 else "lit")
        groups[key].append((*_counts(img, orb, sift), info["mean"]))
    sim_s = time.perf_counter() - t0

    real: dict[str, list[tuple[int, int, int, float]]] = {}
    for name in ("LIME", "DICM"):
        rows = []
        for f in sorted((DATA / name).glob("*")):
            img = cv2.imread(str(f), cv2.IMREAD_GRAYSCALE)
            if img is None:
                continue
            img = cv2.resize(img, (512, 320), interpolation=cv2.INTER_AREA)
            rows.append((*_counts(img, orb, sift), float(img.mean())))
        real[name] = rows

    lidar = {}
    for dec in (1, LidarConfig().decimation):
        sim_l = Simulation.create(dataclasses.replace(cfg, lidar=LidarConfig(decimation=dec)))
        n = [len(sim_l.lidar.scan(float(t), traj.state)["points"]) for t in times[:: max(1, len(times) // 10)]]
        lidar[f"decimation_{dec}"] = float(np.mean(n))
    lidar["datasheet_per_frame"] = 45200.0
    reflect = _reflectivity_repeatability(cfg)

    out = {
        "lighting": args.lighting,
        "simulated": {k: _stats(v) for k, v in groups.items()},
        "real": {k: _stats(v) for k, v in real.items()},
        "lidar_points_per_frame": lidar,
        "lidar_reflectivity_repeatability": reflect,
        "seconds_simulating": round(sim_s, 1),
    }
    print(f"{'set':<16}{'n':>5}{'ORB med':>10}{'SIFT med':>10}{'SURF med':>10}{'mean grey':>11}")
    for label, st in [*((f"sim {k}", v) for k, v in out["simulated"].items()), *out["real"].items()]:
        if st["n"]:
            print(
                f"{label:<16}{st['n']:>5}{st['orb_median']:>10.0f}{st['sift_median']:>10.0f}"
                f"{st['surf_median']:>10.0f}{st['mean_intensity']:>11.1f}"
            )
    dec = LidarConfig().decimation
    print(
        f"LiDAR HAP points/frame: {lidar['decimation_1']:.0f} at full rate "
        f"({lidar['decimation_1'] / 45200:.0%} of the datasheet's 45,200; the rest: blind zone, dropouts, "
        f"grazing, open portal), {lidar[f'decimation_{dec}']:.0f} at the default decimation {dec}"
    )
    for k, v in reflect.items():
        print(
            f"LiDAR reflectivity, {k}: median change at the same spot {v['median_change']:.3f}, "
            f"pattern spread {v['pattern_std']:.3f}, ratio {v['ratio']:.2f} ({v['pairs']} spots)"
        )
    if args.json:
        Path(args.json).write_text(json.dumps(out, indent=2) + "\n")


def _repeatability(a, ai, b, bi, T_ba) -> dict[str, float]:
    from scipy.spatial import cKDTree

    from jaxslam.lidar import relative_reflectivity, voxel_downsample

    a10, a_i = voxel_downsample(a, 0.1, ai)
    b10, b_i = voxel_downsample(b, 0.1, bi)
    ra = relative_reflectivity(a10, a_i, smooth=0.2, max_range=12.0)
    rb = relative_reflectivity(b10, b_i, smooth=0.2, max_range=12.0)
    aw = a10 @ T_ba[:3, :3].T + T_ba[:3, 3]
    d, j = cKDTree(b10).query(aw, 1)
    m = (d < 0.03) & np.isfinite(ra) & np.isfinite(rb[j])
    change = float(np.median(np.abs(ra[m] - rb[j][m])))
    spread = float(np.std(rb[np.isfinite(rb)]))
    return {"median_change": change, "pattern_std": spread, "ratio": change / spread, "pairs": int(m.sum())}


def _reflectivity_repeatability(cfg: SimConfig) -> dict[str, dict[str, float]]:
    """Relative-reflectivity repeatability, simulated consecutive scans and the real pair."""
    from jaxslam.io import read_ply
    from jaxslam.lidar import deskew

    sim = Simulation.create(cfg)
    t_bl = np.asarray(cfg.lidar.translation)
    out = {}
    scans = []
    for t in (40.0, 40.1):  # mid outbound leg, consecutive frames, deskewed with the true motion
        sc = sim.lidar.scan(t, sim.trajectory.pose)
        tk = np.linspace(0.0, 0.1, 5)
        st = sim.trajectory.pose(t + tk)
        T = np.tile(np.eye(4), (len(tk), 1, 1))
        T[:, :3, :3] = st["R"]
        T[:, :3, 3] = st["p"] + np.einsum("nij,j->ni", st["R"], t_bl)
        pts = deskew(sc["points"], sc["point_times"], (T[:, :3, :3], T[:, :3, 3], tk))
        scans.append((pts, sc["intensity"], T[0]))
    (a, ai, Ta), (b, bi, Tb) = scans
    out["simulated"] = _repeatability(a, ai, b, bi, np.linalg.inv(Tb) @ Ta)
    real = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "lidar"
    if (real / "source.ply").exists():
        src, src_i = read_ply(real / "source.ply")
        tgt, tgt_i = read_ply(real / "target.ply")
        if src_i is not None and tgt_i is not None:
            ks, kt = np.linalg.norm(src, axis=1) > 0.1, np.linalg.norm(tgt, axis=1) > 0.1  # origin = no return
            T_ts = np.loadtxt(real / "T_target_source.txt")
            out["real pair"] = _repeatability(src[ks], src_i[ks], tgt[kt], tgt_i[kt], T_ts)
    return out


if __name__ == "__main__":
    main()

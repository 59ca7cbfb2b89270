"""LiDAR scan-to-map odometry on the simulated tunnel: jaxslam.lidar vs small_gicp, same scans.

    python benchmarks/lidar.py [--seconds N] [--start S] [--intensity] [--json PATH]

Over the default simulated run (``SimConfig(seed=0)``: Livox-HAP-like scans, 10 Hz, about
11k points each) from ``--start`` for ``--seconds``, every scan goes through:

1. crop (0.5..100 m), **deskew with a constant-velocity model** taken from the last two
   *estimated* poses (no IMU, no ground truth: ``twist = Log(T_{k-2}^-1 T_{k-1}) / dt``, with
   the velocity zeroed along weak directions that tilt, see ``Odometry.weak``),
   referenced to the **middle of the frame** (kiss-icp does the same: referenced to the frame
   start, a velocity error shifts the deskewed scan by half its motion over the frame, which
   feeds back into the next velocity and oscillates);
2. voxel downsampling (0.25 m source for registration, finer while it leaves fewer than 600
   points, as when the turn faces a wall 1-2 m away; 0.1 m for the map);
3. ``register`` against the ``VoxelMap`` from the constant-velocity prediction;
4. the map points added at the estimated pose.

The first scan is anchored at the ground-truth pose. Printed: per-scan time (steps 1-4,
p50/p95/max; the simulator's own time is excluded), relative-pose error per scan against
ground truth split into along-tunnel / lateral / vertical translation and rotation, the
drift at the end, and the share of scans flagged degenerate (and those whose weak
direction is the tunnel axis). If ``small_gicp`` is importable, its scan-to-model VGICP
odometry (its own Gaussian voxel map, same scans, same deskew model from its own poses) runs
in the same loop and the time and accuracy ratios ours / small_gicp are printed. With
``--intensity`` a third odometry, ``ours+reflectivity``, runs beside them: the same, with each
scan's relative reflectivity (``relative_reflectivity``, on a 0.1 m grid, within 6 m; the
estimator's settings) in the map and in the registration.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from jaxslam._machine import machine_info
from jaxslam.lidar import (
    IcpConfig,
    ScanContextDatabase,
    VoxelMap,
    crop_range,
    deskew,
    register,
    relative_reflectivity,
    scan_context,
    submap_points,
    voxel_downsample,
)
from jaxslam.lidar._se3 import make_pose, orthonormalize, se3_exp, se3_inverse, se3_log
from jaxslam.sim import SimConfig, Simulation

SOURCE_VOXEL, MAP_VOXEL = 0.25, 0.1
MIN_SOURCE = 600  # fewer source points than this: downsample finer
MID = 0.05  # deskew reference: mid-frame (s after the frame stamp)


class Odometry:
    """Scan-to-map odometry state: poses, the constant-velocity model."""

    def __init__(self, T0: np.ndarray, dt: float):
        self.poses = [T0]
        self.dt = dt
        self.hold = np.zeros((0, 6))  # tangent directions whose velocity is not extrapolated

    def prediction(self) -> tuple[np.ndarray, np.ndarray]:
        """(predicted pose, sensor twist) from the constant-velocity model."""
        if len(self.poses) < 2:
            return self.poses[-1], np.zeros(6)
        xi = se3_log(se3_inverse(self.poses[-2]) @ self.poses[-1])
        if len(self.hold):
            q, _ = np.linalg.qr(self.hold.T)
            xi = xi - q @ (q.T @ xi)
        return orthonormalize(self.poses[-1] @ se3_exp(xi)), xi / self.dt

    def weak(self, reg) -> None:
        """Velocity along a weak direction of the last registration is extrapolated only if the
        direction is a translation (the tunnel axis: the robot keeps its speed); weak directions
        that tilt (pitch + height near a wall) get zero velocity (it keeps its attitude):
        extrapolating them integrates noise into a runaway."""
        d = reg.weak_directions if reg is not None and reg.converged else np.zeros((0, 6))
        self.hold = d[np.linalg.norm(d[:, :3], axis=1) > 0.05] if len(d) else d


def ours_step(odo: Odometry, vmap: VoxelMap, points, times, cfg: IcpConfig, keep: list | None = None, intensity=None):
    pts, tau, inten = crop_range(points, 0.5, 100.0, times, np.zeros(len(points)) if intensity is None else intensity)
    pred, twist = odo.prediction()
    pts = deskew(pts, tau, twist, reference_time=MID)
    refl = np.full(len(pts), np.nan)
    if intensity is not None:  # the estimator's settings (pipeline LidarConfig)
        pts, inten = voxel_downsample(pts, 0.1, inten)
        refl = relative_reflectivity(pts, inten, radius=0.6, smooth=0.2, max_range=6.0)
    src, src_r = voxel_downsample(pts, SOURCE_VOXEL, refl)
    for voxel in (0.15, MAP_VOXEL):  # close to a wall (the turn) the scan covers little: keep >= 600 points
        if len(src) < MIN_SOURCE:
            src, src_r = voxel_downsample(pts, voxel, refl)
    dense, dense_r = voxel_downsample(pts, MAP_VOXEL, refl)
    if len(vmap) == 0:
        T, reg = odo.poses[-1], None
    else:
        reg = register(src, vmap, pred, cfg, source_intensity=None if intensity is None else src_r)
        T = reg.T if reg.converged else pred
        odo.poses.append(T)
        odo.weak(reg)
    vmap.add(dense @ T[:3, :3].T + T[:3, 3], T[:3, 3], intensity=None if intensity is None else dense_r)
    if keep is not None:
        keep.append(src)
    return reg


def gicp_step(odo: Odometry, state: dict, points, times, sg):
    pts, tau = crop_range(points, 0.5, 100.0, times)
    pred, twist = odo.prediction()
    pts = deskew(pts, tau, twist, reference_time=MID)
    cloud, _ = sg.preprocess_points(pts, downsampling_resolution=SOURCE_VOXEL, num_neighbors=10)
    if state.get("map") is None:
        state["map"] = sg.GaussianVoxelMap(1.0)
        state["map"].insert(cloud, odo.poses[-1])
        return
    res = sg.align(state["map"], cloud, pred, max_correspondence_distance=1.0, max_iterations=30)
    T = orthonormalize(res.T_target_source)
    odo.poses.append(T)
    state["map"].insert(cloud, T)


def errors(est: list[np.ndarray], gt: np.ndarray) -> dict[str, float]:
    """Per-scan relative pose errors (tunnel axes: world x along, y lateral, z vertical)."""
    E = np.stack(est)
    d_est = np.einsum("nij,njk->nik", se3_inverse(E[:-1]), E[1:])
    d_gt = np.einsum("nij,njk->nik", se3_inverse(gt[:-1]), gt[1:])
    err = np.einsum("nij,njk->nik", se3_inverse(d_gt), d_est)
    t_w = np.einsum("nij,nj->ni", gt[1:, :3, :3], err[:, :3, 3])
    rot = np.degrees(np.linalg.norm(se3_log(err)[:, :3], axis=1))
    drift = E[-1, :3, 3] - gt[-1, :3, 3]
    path = float(np.sum(np.linalg.norm(np.diff(gt[:, :3, 3], axis=0), axis=1)))
    rms = lambda x: float(np.sqrt(np.mean(x**2)))  # noqa: E731
    return {
        "rpe_along_mm": 1e3 * rms(t_w[:, 0]),
        "rpe_lateral_mm": 1e3 * rms(t_w[:, 1]),
        "rpe_vertical_mm": 1e3 * rms(t_w[:, 2]),
        "rpe_rotation_deg": rms(rot),
        "drift_along_m": float(drift[0]),
        "drift_lateral_m": float(drift[1]),
        "drift_vertical_m": float(drift[2]),
        "path_m": path,
        "drift_percent": 100 * float(np.linalg.norm(drift)) / max(path, 1e-9),
    }


def place_recognition(clouds: list[np.ndarray], est: list[np.ndarray], gt: np.ndarray) -> dict | None:
    """How distinctive Scan Context is in the tunnel: one descriptor per second from a submap
    of the last 6 s of scans (every 5th, estimated poses); return-leg keyframes (heading
    opposite to the first) query the database of the out-leg ones."""
    every, span = 10, 60
    keys = list(range(span, len(clouds), every))
    if len(keys) < 10:
        return None
    db = ScanContextDatabase(num_candidates=len(keys))
    descs, pos, heading = {}, gt[:, :3, 3], gt[:, 0, 0]
    for k in keys:
        idx = list(range(k - span, k + 1, 5))
        pts = submap_points([clouds[i] for i in idx], np.stack([est[i] for i in idx]), est[k])
        descs[k] = scan_context(pts)
    hits, n_query, d_true, d_best, d_far = 0, 0, [], [], []
    for k in keys:
        if heading[k] < 0:  # driving back: query the out-leg places
            n_query += 1
            res = db.query(descs[k], k=1)
            if res:
                top = res[0]
                ok_pos = np.linalg.norm(pos[top.id] - pos[k]) < 2.0
                hits += int(ok_pos and abs(abs(top.yaw) - np.pi) < np.radians(15))
                d_best.append(top.distance)
                out_keys = [j for j in keys if j < k and heading[j] > 0]
                j_true = min(out_keys, key=lambda j: np.linalg.norm(pos[j] - pos[k]))
                d_true.append(descs[k].distance(descs[j_true])[0])
                d_far.append(np.median([descs[k].distance(descs[j])[0] for j in out_keys]))
        if heading[k] > 0:
            db.add(k, descs[k])
    if not n_query:
        return {"keyframes": len(keys), "queries": 0}
    return {
        "keyframes": len(keys),
        "queries": n_query,
        "top1_correct_share": hits / n_query,
        "distance_to_true_place_median": float(np.median(d_true)),
        "distance_to_best_candidate_median": float(np.median(d_best)),
        "distance_to_other_places_median": float(np.median(d_far)),
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seconds", type=float, default=30.0, help="how much of the run (s); the full run is 138 s")
    ap.add_argument("--start", type=float, default=0.0, help="first scan time (s)")
    ap.add_argument("--intensity", action="store_true", help="also run ours with the reflectivity term")
    ap.add_argument("--json", type=Path, help="write the figures here")
    args = ap.parse_args(argv)
    try:
        import small_gicp as sg
    except ImportError:
        sg = None

    sim = Simulation.create(SimConfig(seed=0))
    dt = 1.0 / sim.config.lidar.rate
    tbl = np.asarray(sim.config.lidar.translation)
    times = np.arange(args.start, min(args.start + args.seconds, sim.trajectory.duration - dt), dt)
    st = sim.trajectory.pose(times + MID)
    gt = make_pose(st["R"], st["p"] + np.einsum("nij,j->ni", st["R"], tbl))

    cfg = IcpConfig()
    ours, vmap = Odometry(gt[0], dt), VoxelMap()
    theirs, gstate = Odometry(gt[0], dt), {}
    refl_odo, refl_map, t_refl, refl_regs = Odometry(gt[0], dt), VoxelMap(), [], []
    t_ours, t_theirs, regs, n_points, clouds = [], [], [], [], []
    for t in times:
        scan = sim.lidar.scan(float(t), sim.trajectory.pose)
        n_points.append(len(scan["points"]))
        t0 = time.perf_counter()
        reg = ours_step(ours, vmap, scan["points"], scan["point_times"], cfg, clouds)
        t_ours.append(time.perf_counter() - t0)
        if reg is not None:
            regs.append(reg)
        if sg is not None:
            t0 = time.perf_counter()
            gicp_step(theirs, gstate, scan["points"], scan["point_times"], sg)
            t_theirs.append(time.perf_counter() - t0)
        if args.intensity:
            t0 = time.perf_counter()
            r2 = ours_step(refl_odo, refl_map, scan["points"], scan["point_times"], cfg, intensity=scan["intensity"])
            t_refl.append(time.perf_counter() - t0)
            if r2 is not None:
                refl_regs.append(r2)

    ms = 1e3 * np.asarray(t_ours[1:])
    axis_gt = gt[1:, :3, :3].transpose(0, 2, 1)[:, :, 0]  # world x in each sensor frame
    axis_weak = [
        bool(r.degenerate and np.max(np.abs(r.weak_directions[:, 3:] @ a)) > 0.7) for r, a in zip(regs, axis_gt)
    ]
    out = {
        "machine": machine_info(),
        "scans": len(times),
        "seconds": [float(times[0]), float(times[-1])],
        "points_per_scan": float(np.mean(n_points)),
        "ours": {
            "ms_p50": float(np.percentile(ms, 50)),
            "ms_p95": float(np.percentile(ms, 95)),
            "ms_max": float(ms.max()),
            "degenerate_share": float(np.mean([r.degenerate for r in regs])),
            "axis_weak_share": float(np.mean(axis_weak)),
            "not_converged": int(sum(not r.converged for r in regs)),
            "min_eigenvalue_p50": float(np.median([r.eigenvalues[0] for r in regs])),
            "map_points": len(vmap),
            **errors(ours.poses, gt),
        },
    }
    if sg is not None:
        ms_g = 1e3 * np.asarray(t_theirs[1:])
        out["small_gicp"] = {
            "ms_p50": float(np.percentile(ms_g, 50)),
            "ms_p95": float(np.percentile(ms_g, 95)),
            **errors(theirs.poses, gt),
        }
        o, g = out["ours"], out["small_gicp"]
        out["ratio_ours_over_small_gicp"] = {
            k: o[k] / g[k] if g[k] else float("nan")
            for k in ("ms_p50", "ms_p95", "rpe_lateral_mm", "rpe_vertical_mm", "rpe_rotation_deg", "rpe_along_mm")
        }
    if args.intensity:
        ms_r = 1e3 * np.asarray(t_refl[1:])
        out["ours+reflectivity"] = {
            "ms_p50": float(np.percentile(ms_r, 50)),
            "ms_p95": float(np.percentile(ms_r, 95)),
            "degenerate_share": float(np.mean([r.degenerate for r in refl_regs])),
            **errors(refl_odo.poses, gt),
        }
    out["place_recognition"] = place_recognition(clouds, ours.poses, gt)
    _print(out)
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(out, indent=2))
    return 0


def _print(out: dict) -> None:
    print(
        f"{out['scans']} scans, t = {out['seconds'][0]:.1f}..{out['seconds'][1]:.1f} s, "
        f"{out['points_per_scan']:.0f} points per scan"
    )
    for name in ("ours", "ours+reflectivity", "small_gicp"):
        if name not in out:
            continue
        r = out[name]
        print(
            f"{name:>10}: {r['ms_p50']:.1f} / {r['ms_p95']:.1f} ms (p50/p95) | RPE rms along {r['rpe_along_mm']:.2f} "
            f"lateral {r['rpe_lateral_mm']:.2f} vertical {r['rpe_vertical_mm']:.2f} mm, rotation "
            f"{r['rpe_rotation_deg']:.4f} deg | drift along {r['drift_along_m']:+.3f} lateral "
            f"{r['drift_lateral_m']:+.3f} vertical {r['drift_vertical_m']:+.3f} m "
            f"({r['drift_percent']:.2f} % of {r['path_m']:.1f} m)"
        )
    o = out["ours"]
    print(
        f"degenerate scans {100 * o['degenerate_share']:.0f} % "
        f"(tunnel axis weak: {100 * o['axis_weak_share']:.0f} %), not converged {o['not_converged']}, "
        f"median smallest eigenvalue {o['min_eigenvalue_p50']:.2e}"
    )
    pr = out.get("place_recognition")
    if pr and pr.get("queries"):
        print(
            f"scan context (submaps, return leg vs out leg): top-1 right place {100 * pr['top1_correct_share']:.0f} % "
            f"of {pr['queries']}; distance to the true place {pr['distance_to_true_place_median']:.3f}, to the best "
            f"candidate {pr['distance_to_best_candidate_median']:.3f}, to other places "
            f"{pr['distance_to_other_places_median']:.3f} (medians)"
        )
    if "ratio_ours_over_small_gicp" in out:
        print("ratios ours / small_gicp:", {k: round(v, 3) for k, v in out["ratio_ours_over_small_gicp"].items()})


if __name__ == "__main__":
    raise SystemExit(main())

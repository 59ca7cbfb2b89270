"""``run_recording``: a recording in, a results folder out (the user's main job).

Outputs in ``outdir``: ``trajectory_tum.txt``, ``trajectory_kitti.txt`` (+ ``times.txt``),
``map.ply`` (deskewed keyframe scans at the optimised poses, grey from the camera where a
keyframe image sees the point), ``points.ply`` (the sparse visual map), ``metrics.json``,
``config.yaml`` (effective), and plots
``trajectory.png``, ``errors.png`` (when ground truth exists) and ``residuals.png``.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import jax.numpy as jnp
import numpy as np

from .._machine import compile_seconds, machine_info
from ..errors import ConfigError, InputFormatError
from ..io import open_recording, write_kitti, write_ply, write_tum
from ..io._reindex import reindex
from ..io._rosbag import _unindexed_ros1
from ..io._trajectory import Trajectory
from ..lie import SE3, host
from ._config import PipelineConfig, find_rig, load_rig, save_config
from ._estimator import Estimator
from ._lidar_frontend import axis_sigma_scaled
from ._mapping import SparseMap, build_sparse_map


def _trajectory(times: np.ndarray, poses: np.ndarray) -> Trajectory:
    return Trajectory(np.asarray(times, np.float64), SE3(jnp.asarray(host.matrix_to_params(poses))))


def mapping_statistics(est: Estimator, poses: np.ndarray) -> tuple[dict[str, Any], SparseMap | None]:
    """The paper's Table 10 quantities: keyframe images and how many the visual front end
    registered, and the sparse map of feature tracks triangulated at the final poses and
    refined by a structure-only bundle adjustment (:mod:`._mapping`)."""
    with_img = [kf for kf in est.keyframes if kf.features is not None]
    stats: dict[str, Any] = {
        "input_images": len(with_img),
        "registered_images": int(sum(kf.registered for kf in with_img)),
    }
    if est.visual is None:
        return {**stats, "reproj_rmse_px": float("nan")}, None
    sm = build_sparse_map(est.keyframes, poses, est.visual.T_bc, est.visual.f)
    return {**stats, **sm.statistics()}, sm


def factor_residuals(est: Estimator, poses: np.ndarray) -> dict[str, np.ndarray]:
    """Whitened residual norms per factor kind at the final poses (for ``residuals.png``)."""
    out: dict[str, list[float]] = {"lidar odometry": [], "visual odometry": [], "loop closure": []}
    for kind, i, j, T, info in est.edges:
        e = host.se3_log(host.inverse(T) @ host.inverse(poses[i]) @ poses[j])
        out[kind].append(float(np.sqrt(max(e @ info @ e, 0.0))))
    return {k: np.asarray(v) for k, v in out.items() if v}


def false_loops(
    est: Estimator, gt_poses: np.ndarray | None, trans_tol: float = 0.3, rot_tol_deg: float = 3.0
) -> int | None:
    """Accepted loops (LiDAR and visual) whose measurement disagrees with ground truth in the
    directions the loop constrains (the tunnel-axis direction a degenerate loop does not
    measure is ignored)."""
    if (est.loops is None and est.visual_loops is None) or gt_poses is None:
        return None
    bad = 0
    for lp in accepted_loops(est):
        T_gt = host.inverse(gt_poses[lp.i]) @ gt_poses[lp.j]
        e = host.se3_log(host.inverse(lp.T) @ T_gt)
        evals, evecs = np.linalg.eigh(lp.information)
        strong = evecs[:, evals > 1.0 / 0.05**2]  # directions the loop knows to better than 5 cm / rad
        e_s = strong @ (strong.T @ e)
        if np.linalg.norm(e_s[3:]) > trans_tol or np.degrees(np.linalg.norm(e_s[:3])) > rot_tol_deg:
            bad += 1
    return bad


def odometry_length_ratio(est: Estimator, gt_poses: np.ndarray, min_motion: float = 0.1) -> dict[str, Any]:
    """How long each odometry front end measures the motion against ground truth: per kind
    (``lidar odometry``, ``visual odometry``), over its factors between consecutive keyframes
    whose true motion is at least ``min_motion`` m, the median of measured / true translation
    length and the total measured over the total true length (1.0 = unbiased; 0.99 = the
    front end sees the path 1 % short). The measurements are the front ends' own, before the
    graph (and the visual length-scale variable) weighs them: a length biased along the
    tunnel axis shows here before it shows in the APE. ``gt_poses`` (K, 4, 4) at the
    keyframe times."""
    out: dict[str, Any] = {}
    for kind in ("visual odometry", "lidar odometry"):
        rows = [
            (float(np.linalg.norm(T[:3, 3])), float(np.linalg.norm((host.inverse(gt_poses[i]) @ gt_poses[j])[:3, 3])))
            for k, i, j, T, _ in est.edges
            if k == kind and j == i + 1
        ]
        m = np.array([r for r in rows if r[1] >= min_motion]).reshape(-1, 2)
        if len(m):
            out[kind] = {
                "pairs": len(m),
                "median": float(np.median(m[:, 0] / m[:, 1])),
                "total": float(m[:, 0].sum() / m[:, 1].sum()),
            }
    return out


#: chi-square(6) 95 % quantile: an honest 6-dof factor exceeds it 5 % of the time
_CHI2_6_95 = 12.591587243743977


def factor_consistency(est: Estimator, gt_poses: np.ndarray, min_motion: float = 0.1) -> dict[str, Any]:
    """Whether each front end's stated covariance is honest, against ground truth: per kind
    (``lidar odometry``, ``visual odometry``, ``loop closure``, and the accepted loops split
    into ``lidar loop`` / ``visual loop``), over its measurements (all baselines; odometry
    pairs whose true motion is below ``min_motion`` m are left out), the error
    ``e = Log(T_meas^-1 T_true)`` (tangent ``[rotation, translation]``, the between factor's)
    and its information ``I``:

    * ``nees``: mean of ``e^T I e / 6`` (1.0 = honest; 4 = the sigmas are half the errors);
    * ``over_95``: share of measurements with ``e^T I e`` above the chi-square(6) 95 % point
      (0.05 when honest; more = overconfident somewhere, even if the mean looks right);
    * ``axis_z_rms``: RMS of the along-axis translation error (body x, the direction of
      travel) over its marginal sigma ``sqrt((I^-1)_xx)``: the tunnel axis is where the
      LiDAR is weak and the camera measures short, so it gets its own figure;
    * ``axis_error_rms_m``: RMS of that error in metres.

    The measurements are the front ends' own (the visual ones before the graph's length
    scale; the loops before their robust kernel), as in :func:`odometry_length_ratio`.
    ``gt_poses`` (K, 4, 4) at the keyframe times."""
    groups: dict[str, list[tuple[int, int, np.ndarray, np.ndarray]]] = {}
    for kind, i, j, T, info in est.edges:
        groups.setdefault(kind, []).append((i, j, T, info))
    for kind, finder, field in (
        ("lidar loop", getattr(est, "loops", None), "axis_sigma_scale"),
        ("visual loop", getattr(est, "visual_loops", None), "visual_axis_sigma_scale"),
    ):
        if finder is not None and finder.accepted:
            scale = getattr(est.cfg.loop, field)  # as the graph's loop factor has it
            groups[kind] = [(lp.i, lp.j, lp.T, axis_sigma_scaled(lp.information, scale)) for lp in finder.accepted]
    out: dict[str, Any] = {}
    for kind in ("lidar odometry", "visual odometry", "loop closure", "lidar loop", "visual loop"):
        nees, zs, ex = [], [], []
        for i, j, T, info in groups.get(kind, []):
            T_true = host.inverse(gt_poses[i]) @ gt_poses[j]
            if "loop" not in kind and float(np.linalg.norm(T_true[:3, 3])) < min_motion:
                continue
            e = host.se3_log(host.inverse(T) @ T_true)
            info = np.asarray(info, dtype=np.float64)
            nees.append(float(e @ info @ e))
            var_x = float(np.linalg.pinv(info)[3, 3])
            zs.append(e[3] / np.sqrt(var_x) if var_x > 0 else np.nan)
            ex.append(e[3])
        if nees:
            n = np.asarray(nees)
            z = np.asarray(zs)
            out[kind] = {
                "measurements": len(n),
                "nees": float(np.mean(n) / 6.0),
                "over_95": float(np.mean(n > _CHI2_6_95)),
                "axis_z_rms": float(np.sqrt(np.nanmean(z * z))) if np.isfinite(z).any() else None,
                "axis_error_rms_m": float(np.sqrt(np.mean(np.square(ex)))),
            }
    return out


#: the factor kind of :func:`factor_consistency` whose along-axis sigma each (section, field) scales
AXIS_SCALE_KINDS = {
    ("lidar", "axis_sigma_scale"): "lidar odometry",
    ("vision", "axis_sigma_scale"): "visual odometry",
    ("loop", "axis_sigma_scale"): "lidar loop",
    ("loop", "visual_axis_sigma_scale"): "visual loop",
}


def axis_sigma_calibration(
    consistencies: list[dict[str, Any]], config: PipelineConfig | None = None, min_measurements: int = 30
) -> dict[str, dict[str, float]]:
    """The along-axis sigma scales (:data:`AXIS_SCALE_KINDS`) that make them honest on these
    runs (moment matching): each kind's along-axis z RMS pooled over the runs'
    :func:`factor_consistency` results (``sqrt(sum n z^2 / sum n)``), times the scale the runs
    were made with (``config``, default: the defaults). A kind with fewer than
    ``min_measurements`` measurements in all is left out. Returns config sections, e.g.
    ``{"lidar": {"axis_sigma_scale": 1.3}, "loop": {"axis_sigma_scale": 0.4,
    "visual_axis_sigma_scale": 1.0}, ...}``, for :func:`config_from_dict` / YAML.
    One step of a fixed point: the scales change the run, so measure again with them."""
    config = config or PipelineConfig()
    out: dict[str, dict[str, float]] = {}
    for (section, field), kind in AXIS_SCALE_KINDS.items():
        n = zz = 0.0
        for cons in consistencies:
            c = (cons or {}).get(kind)
            if c and c.get("axis_z_rms") is not None and np.isfinite(c["axis_z_rms"]):
                n += c["measurements"]
                zz += c["measurements"] * c["axis_z_rms"] ** 2
        if n >= min_measurements:
            old = getattr(getattr(config, section), field)
            out.setdefault(section, {})[field] = float(old * np.sqrt(zz / n))
    return out


def accepted_loops(est: Estimator) -> list[Any]:
    """Every accepted loop, LiDAR and visual (each has ``i``, ``j``, ``T``, ``information``)."""
    return [*(est.loops.accepted if est.loops else []), *(est.visual_loops.accepted if est.visual_loops else [])]


def run_recording(
    path: str | Path,
    outdir: str | Path,
    config: PipelineConfig | None = None,
    progress: Callable[[float, float], None] | None = None,
    plots: bool = True,
    max_seconds: float | None = None,
    on_finish: Callable[[Estimator, dict[str, Any], Trajectory | None], None] | None = None,
) -> dict[str, Any]:
    """Run the estimator over a recording and write the results folder; returns the metrics.
    ``on_finish(estimator, result, ground_truth)`` sees the finished estimator (its factor
    graph: ``jaxslam tune`` re-weights it)."""
    from .. import eval as ev

    t_start = time.perf_counter()
    compile_start = compile_seconds()
    config = config or PipelineConfig()
    out = Path(outdir)
    out.mkdir(parents=True, exist_ok=True)
    repaired: dict[str, int] = {}
    if _unindexed_ros1(Path(path)):  # cut short (power loss): rebuild the index from the chunks
        fixed = out / (Path(path).stem + ".reindexed.bag")
        fixed.unlink(missing_ok=True)
        repaired = reindex(path, fixed)
        rec = open_recording(fixed)
    else:
        rec = open_recording(path)
    rig_path = find_rig(path)
    if rig_path is not None and config.rig == PipelineConfig().rig:
        import dataclasses

        config = dataclasses.replace(config, rig=load_rig(rig_path))
    save_config(config, out / "config.yaml")
    streams = rec.streams()
    t0s = [s.t_start for s in streams if np.isfinite(s.t_start)]
    t1s = [s.t_end for s in streams if np.isfinite(s.t_end)]
    if not t0s:
        raise InputFormatError("the recording holds no readable stream", path)
    t_begin, t_end = min(t0s), max(t1s)
    est = Estimator(config)
    if repaired:
        dropped = sum(v for k, v in repaired.items() if k not in ("connections", "messages", "chunks"))
        kept = repaired.get("messages", 0)
        est.warnings[
            f"recording: bag without index (truncated?) reindexed: {kept} messages kept, {dropped} dropped"
        ] += 1
    n = 0
    try:
        for r in rec:
            if max_seconds is not None and r.t > t_begin + max_seconds:
                break
            est.feed(r)
            n += 1
            if progress is not None and n % 200 == 0:
                progress(r.t - t_begin, t_end - t_begin)
    except InputFormatError as e:  # a truncated / corrupt tail: keep what was read
        est.warnings[f"recording: read stopped early ({e})"] += 1
    for k, v in rec.skipped.items():
        est.warnings[f"recording: {k}"] += v
    res = est.finish()
    runtime = time.perf_counter() - t_start
    compile_s = compile_seconds() - compile_start  # JIT work inside the run, apart
    if not len(res["times"]):
        raise InputFormatError("no keyframe could be made (no IMU, or the recording is too short)", path)
    poses = res["poses"]
    traj = _trajectory(res["times"], poses)
    write_tum(out / "trajectory_tum.txt", traj)
    write_kitti(out / "trajectory_kitti.txt", traj, times_path=out / "times.txt")
    _write_map(est, poses, out / "map.ply")

    gt = rec.ground_truth()
    if gt is None and est.ground_truth:
        gt = Trajectory(
            np.array([p.t for p in est.ground_truth]), SE3(jnp.asarray(np.stack([p.pose for p in est.ground_truth])))
        )
    if on_finish is not None:
        on_finish(est, res, gt)
    stats, sparse = mapping_statistics(est, poses)
    reproj = sparse.residuals_px if sparse is not None else np.zeros(0)
    if sparse is not None and len(sparse.points):
        write_ply(out / "points.ply", sparse.points)
    lidar = est.lidar
    metrics: dict[str, Any] = {
        "recording": str(path),
        "keyframes": len(res["times"]),
        "registered_frames": stats["registered_images"],
        "total_frames": stats["input_images"],
        "reproj_rmse_px": stats["reproj_rmse_px"],
        "runtime_s": runtime,
        "compile_s": compile_s,
        "sequence_duration_s": float(min(t_end, est.t_last) - t_begin) if est.t_first is not None else 0.0,
        "degenerate_scans": lidar.degenerate if lidar else 0,
        "lidar_scans": lidar.processed if lidar else 0,
        "lidar_scans_held_still": lidar.held if lidar else 0,
        "loops_accepted": len(accepted_loops(est)),
        "loops_rejected": (len(est.loops.rejected) if est.loops else 0)
        + (len(est.visual_loops.rejected) if est.visual_loops else 0),
        "visual_loops_accepted": len(est.visual_loops.accepted) if est.visual_loops else 0,
        "visual_loops_blurred": sum(lp.blur_px > 0 for lp in est.visual_loops.accepted) if est.visual_loops else 0,
        "visual_loops_attempted": est.visual_loops.attempts if est.visual_loops else 0,
        "visual_loops_wide": (
            sum(lp.drift_per_m > est.visual_loops.cfg.visual_drift_per_m for lp in est.visual_loops.accepted)
            if est.visual_loops
            else 0
        ),
        "visual_loop_wide_searches": est.visual_loops.wide_searches if est.visual_loops else 0,
        "visual_loop_ladder_climbs": est.visual_loops.ladder_climbs if est.visual_loops else 0,
        "visual_scale": est._vo_scale,
        "zero_velocity_updates": est.zupt_count,
        "visual_lengths_softened": est.length_softened,
        "scale_free_visual_factors": est.direction_edges,
        "guided_visual_factors": est.visual.guided_fits if est.visual else 0,
        "wide_gate_visual_factors": est.visual.wide_fits if est.visual else 0,
        "patch_refined_visual_factors": est.visual.patch_refined if est.visual else 0,
        "patch_retried_visual_factors": est.visual.patch_retried if est.visual else 0,
        "mapping": stats,
        "timing_s": {k: round(v, 3) for k, v in est.timing.items()},
        "machine": machine_info(),
        "warnings": dict(est.warnings),
    }
    aligned: Any = traj
    if gt is not None:
        try:
            a = ev.ape(gt, traj, align="se3")
            g_at, e_at = ev.associate(gt, traj)
            aligned, _ = ev.align(g_at, e_at, "se3")  # the loop error needs the estimate in gt's frame
            try:
                rpe_rmse = ev.rpe(gt, traj, delta=1.0, unit="m", pose_relation="trans").stats["rmse"]  # per metre
            except ConfigError as e:  # a run shorter than the 1 m delta: no pair; the rest still holds
                rpe_rmse = None
                metrics["warnings"][f"eval: no RPE ({e})"] = 1
            metrics.update(
                ape_rmse_m=a.stats["rmse"],
                ape_mean_m=a.stats["mean"],
                ape_max_m=a.stats["max"],
                rpe_rmse=rpe_rmse,
                loop_error_m=ev.loop_error(aligned, g_at, associated=True),
                loop_error_ratio=ev.loop_error_ratio(aligned, g_at, associated=True),
                path_length_m=ev.path_length(gt),
            )
            gt_T = host.params_to_matrix(np.asarray(g_at.poses.params))  # type: ignore[union-attr]
            metrics["loops_false"] = None
            if len(gt_T) == len(poses):  # ground truth at every keyframe
                metrics["loops_false"] = false_loops(est, gt_T)
                metrics["odometry_length_ratio"] = odometry_length_ratio(est, gt_T)
                metrics["factor_consistency"] = factor_consistency(est, gt_T)
            if plots:
                ev.plot_ape_over_distance(out / "errors.png", a)
        except InputFormatError as e:
            metrics["ground_truth_error"] = str(e)
            gt = None
    else:
        metrics["path_length_m"] = ev.path_length(traj)
    if plots:
        shown = traj if gt is None else aligned  # against ground truth: SE(3)-aligned, as the APE
        title = Path(path).name + ("" if gt is None else " (estimate SE(3)-aligned to ground truth)")
        ev.plot_trajectory(out / "trajectory.png", shown, gt, title=title)
        resid = factor_residuals(est, poses)
        if len(reproj):
            resid = {"reprojection (px)": reproj, **resid}
        if resid:
            ev.plot_residual_histograms(out / "residuals.png", resid)
    (out / "metrics.json").write_text(json.dumps(metrics, indent=2, default=_json_default) + "\n")
    return metrics


def _json_default(x: Any) -> Any:
    if isinstance(x, np.generic):
        return x.item()
    if isinstance(x, np.ndarray):
        return x.tolist()
    return str(x)


def _write_map(est: Estimator, poses: np.ndarray, path: Path) -> None:
    pts, cols = [], []
    vis = est.visual
    for kf in est.keyframes:
        if kf.scan is None:
            continue
        P = kf.scan.points
        world = host.transform_points(poses[kf.index], P)
        grey = np.full(len(P), 128.0)
        if vis is not None and kf.image is not None:
            Xc = host.transform_points(vis.T_cb, P)
            front = Xc[:, 2] > 0.3
            uv = Xc[:, :2] / np.where(front, Xc[:, 2], 1.0)[:, None]
            u = vis.K[0, 0] * uv[:, 0] + vis.K[0, 2]
            v = vis.K[1, 1] * uv[:, 1] + vis.K[1, 2]
            h, w = kf.image.shape[:2]
            ok = front & (u >= 0) & (u < w - 1) & (v >= 0) & (v < h - 1)
            grey[ok] = kf.image[v[ok].astype(int), u[ok].astype(int)]
        pts.append(world)
        cols.append(grey)
    if not pts:
        return
    P = np.concatenate(pts)
    g = np.concatenate(cols)
    write_ply(path, P, colors=np.repeat(g[:, None], 3, axis=1))

"""``jaxslam vo IMAGES --calib CALIB -o OUTDIR``: monocular visual odometry on an image folder.

Writes ``trajectory_tum.txt`` (one row per input image, in input order), ``points.ply``,
``stats.json`` (the paper's Table 10 quantities, timings, and APE after Sim(3) alignment when
the folder has ``poses.txt``), ``residuals_hist.png`` and ``reprojection_hist.png``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add the ``vo`` subcommand to the ``jaxslam`` parser."""
    v = subparsers.add_parser("vo", help="monocular visual odometry on an image folder (KITTI-style or EuRoC)")
    v.add_argument("images", help="folder: KITTI-style (image_l/ or image_0/), EuRoC (mav0/cam0) or plain images")
    v.add_argument(
        "--calib", help="calibration: KITTI calib.txt (first P row), EuRoC sensor.yaml, K (9) or fx fy cx cy"
    )
    v.add_argument("-o", "--output", required=True, help="results folder")
    v.add_argument("--no-enhance", action="store_true", help="skip ABA-CLAHE enhancement")
    v.add_argument("--no-ransac", action="store_true", help="no RANSAC anywhere (the paper's ablation)")
    v.add_argument("--ransac", choices=["jax", "opencv"], default="jax", help="essential-matrix RANSAC (default jax)")
    v.add_argument("--detector", choices=["surf", "sift", "orb"], default="sift")
    v.add_argument("--max-features", type=int, default=2000)
    v.add_argument("--rate", type=float, default=10.0, help="frame rate for timestamps when the folder has none")
    v.add_argument("-q", "--quiet", action="store_true")
    v.set_defaults(func=cmd_vo)


def write_ply(path: Path, points: np.ndarray) -> None:
    """ASCII PLY with float64 ``x y z`` vertices."""
    header = (
        f"ply\nformat ascii 1.0\nelement vertex {len(points)}\n"
        "property double x\nproperty double y\nproperty double z\nend_header\n"
    )
    body = "".join(f"{x:.17g} {y:.17g} {z:.17g}\n" for x, y, z in np.asarray(points, np.float64))
    path.write_text(header + body, encoding="ascii")


def _histograms(out: Path, residuals: np.ndarray) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    for name, data, label in [
        ("residuals_hist.png", residuals.reshape(-1), "residual component (u or v), px"),
        ("reprojection_hist.png", np.linalg.norm(residuals, axis=1), "reprojection error |r|, px"),
    ]:
        fig, ax = plt.subplots(figsize=(6, 4))
        ax.hist(data, bins=60)
        ax.set_xlabel(label)
        ax.set_ylabel("observations")
        ax.set_title(f"{len(data)} values, RMS {np.sqrt(np.mean(data**2)):.3f} px")
        fig.tight_layout()
        fig.savefig(out / name, dpi=100)
        plt.close(fig)


def cmd_vo(args: argparse.Namespace) -> int:
    import jax.numpy as jnp

    from ..errors import ConfigError
    from ..io import Trajectory, write_tum
    from ..lie import SE3
    from ._vo import VoConfig, ape_sim3, load_sequence, run_vo

    if args.max_features < 8:
        raise ConfigError(f"--max-features must be at least 8, got {args.max_features}")
    t0 = time.perf_counter()
    seq = load_sequence(args.images, args.calib, rate_hz=args.rate)
    config = VoConfig(
        detector=args.detector,
        enhance=not args.no_enhance,
        ransac="none" if args.no_ransac else args.ransac,
        max_features=args.max_features,
    )

    def progress(stage: str, i: int, n: int) -> None:
        if not args.quiet:
            print(f"\r{stage}: {i}/{n}", end="" if i < n else "\n", file=sys.stderr)

    result = run_vo(seq, config, progress=progress)
    out = Path(args.output)
    out.mkdir(parents=True, exist_ok=True)
    write_tum(out / "trajectory_tum.txt", Trajectory(result.timestamps, SE3(jnp.asarray(result.poses))))
    write_ply(out / "points.ply", result.points)
    stats: dict[str, Any] = dict(result.stats())
    stats["runtime_s"] = time.perf_counter() - t0
    stats["timings_s"] = result.timings
    stats["config"] = dataclasses.asdict(config)
    if seq.ground_truth is not None:
        stats["ape_sim3"] = ape_sim3(result.poses[:, 4:], seq.ground_truth[:, :, 3])
    (out / "stats.json").write_text(json.dumps(stats, indent=2), encoding="utf-8")
    _histograms(out, result.residuals)
    line = (
        f"vo: registered {stats['registered_images']}/{stats['input_images']} images, {stats['points']} points, "
        f"reprojection RMSE {stats['reprojection_rmse_px']:.3f} px"
    )
    if "ape_sim3" in stats:
        ape = stats["ape_sim3"]
        line += f", APE (Sim3) {ape['rmse']:.3f} m = {ape['rmse_percent_of_path']:.2f} % of {ape['path_length']:.1f} m"
    print(line + f", {stats['runtime_s']:.1f} s -> {out}")
    return 0 if stats["registered_images"] == stats["input_images"] else 2

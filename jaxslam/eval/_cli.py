"""``jaxslam eval GT EST``: APE, RPE, loop-closure error and path length of an estimate."""

from __future__ import annotations

import argparse
import dataclasses
import json
from pathlib import Path


def register(subparsers) -> None:
    """Add the ``eval`` command to the ``jaxslam`` argument parser."""
    e = subparsers.add_parser(
        "eval",
        help="evaluate a trajectory against ground truth: APE, RPE, loop error (the numbers of evo_ape / evo_rpe)",
    )
    e.add_argument("gt", help="ground truth: TUM (8 columns), KITTI poses (12) or t x y z positions (4)")
    e.add_argument("est", help="estimate: TUM or KITTI poses (KITTI on either side: poses pair by index)")
    e.add_argument("--align", choices=["se3", "sim3", "none", "origin"], default="se3", help="default se3 (Umeyama)")
    e.add_argument("--delta", type=float, default=1.0, help="RPE pair spacing (default 1)")
    e.add_argument("--delta-unit", choices=["frames", "m"], default="frames", help="unit of --delta")
    e.add_argument(
        "--pose-relation",
        choices=["trans", "rot_deg", "rot_rad", "full", "point_distance", "point_vector"],
        help="RPE error kind (default trans; point_distance for position-only ground truth)",
    )
    e.add_argument("--max-diff", type=float, default=0.01, help="largest time difference to associate (s)")
    e.add_argument("--offset", type=float, default=0.0, help="added to the estimate's timestamps (s)")
    e.add_argument(
        "--lever-arm",
        type=float,
        nargs=3,
        metavar=("X", "Y", "Z"),
        help="body-frame offset (m) of the point the ground truth measured (prism); implies --gt-positions",
    )
    e.add_argument("--gt-positions", action="store_true", help="use only the ground truth's positions")
    e.add_argument("--json", metavar="PATH", help="write the results as JSON")
    e.add_argument("--plot", metavar="DIR", help="write trajectory.png and ape_over_distance.png here")
    e.set_defaults(func=cmd_eval)


def cmd_eval(args: argparse.Namespace) -> int:
    from ..errors import ConfigError
    from . import (
        PositionTrack,
        ape,
        associate,
        associate_by_index,
        loop_error,
        path_length,
        plot_ape_over_distance,
        plot_trajectory,
        read_track,
        rpe,
    )
    from ._align import apply_alignment

    if not args.max_diff >= 0:
        raise ConfigError(f"--max-diff must be >= 0, got {args.max_diff}")
    gt, gt_stamped = read_track(args.gt)
    est, est_stamped = read_track(args.est)
    lever = args.lever_arm
    if (lever is not None or args.gt_positions) and not isinstance(gt, PositionTrack):
        gt = PositionTrack.from_trajectory(gt)
    positions_only = isinstance(gt, PositionTrack) or isinstance(est, PositionTrack)
    relation = args.pose_relation or ("point_distance" if positions_only else "trans")
    if gt_stamped and est_stamped:
        ref, e = associate(gt, est, args.max_diff, args.offset)
        pairing = f"by time (max diff {args.max_diff:g} s)"
    else:
        ref, e = associate_by_index(gt, est)
        pairing = "by index (KITTI: no timestamps)"
    a = dataclasses.replace(ape(ref, e, args.align, lever, associated=True), ref_poses=len(gt), est_poses=len(est))
    r = rpe(
        ref,
        e,
        args.delta,
        args.delta_unit,
        relation,
        align=args.align,
        lever_arm=lever if relation.startswith("point_") else None,
        associated=True,
    )
    aligned = apply_alignment(e, a.alignment)
    arm = lever if not isinstance(aligned, PositionTrack) else None
    loop_gt = loop_error(aligned, ref, lever_arm=arm, associated=True)
    loop_est = loop_error(aligned, lever_arm=arm)
    length_gt, length_est = path_length(ref), path_length(aligned)
    ratio = loop_gt / length_gt if length_gt > 0 else float("nan")
    _print_table(args, a, r, pairing, loop_gt, loop_est, ratio, length_gt, length_est)
    result = {
        "gt": str(args.gt),
        "est": str(args.est),
        "association": pairing,
        "matched": a.matched,
        "ape": a.to_dict(),
        "rpe": r.to_dict(),
        "loop_error_m": loop_gt,
        "loop_error_ratio": ratio,
        "loop_error_est_only_m": loop_est,
        "path_length_m": {"gt": length_gt, "est": length_est},
    }
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps(result, indent=2) + "\n", encoding="utf-8")
    if args.plot:
        out = Path(args.plot)
        plot_trajectory(out / "trajectory.png", aligned, ref, title=f"{Path(args.est).name} ({args.align})")
        plot_ape_over_distance(out / "ape_over_distance.png", a)
    return 0


def _print_table(args, a, r, pairing, loop_gt, loop_est, ratio, length_gt, length_est) -> None:
    s, q = a.stats, r.stats
    unit = r.unit_label
    delta = f"{r.delta:g} {r.delta_unit}"
    lines = [
        f"matched {a.matched} poses ({a.ref_poses} gt, {a.est_poses} est) {pairing}; align {a.align}"
        + (f", scale {a.alignment.scale:.6f}" if a.align == "sim3" else ""),
        f"{'APE [m]':<22}rmse {s['rmse']:.6f}  mean {s['mean']:.6f}  median {s['median']:.6f}  "
        f"std {s['std']:.6f}  max {s['max']:.6f}",
        f"{'RPE ' + r.pose_relation + ' [' + unit + ']':<22}rmse {q['rmse']:.6f}  mean {q['mean']:.6f}  "
        f"max {q['max']:.6f}  ({len(r.errors)} pairs, delta {delta})",
        f"{'loop error [m]':<22}{loop_gt:.6f}  ratio {100 * ratio:.3f} %  (estimate alone: {loop_est:.6f})",
        f"{'path length [m]':<22}gt {length_gt:.3f}  est {length_est:.3f}",
    ]
    print("\n".join(lines))

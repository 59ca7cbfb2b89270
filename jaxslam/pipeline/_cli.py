"""``jaxslam run`` (the estimator on a recording) and ``jaxslam demo`` (simulate the default
tunnel, then run it)."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

# The paper's own figures (SPEC §5): its Table 8/9 rows, printed beside this run's.
PAPER_ROWS = [
    ("paper: R2LIVE", 0.1290, 0.0299, 0.121, 0.203),
    ("paper: LVI-SAM", 0.1188, 0.0208, 0.116, 0.185),
    ("paper: method", 0.0920, 0.0109, 0.096, 0.159),
    ("paper: w/o ABA-CLAHE", 0.1122, 0.0218, 0.110, 0.182),
    ("paper: w/o SURF-RANSAC", 0.0891, 0.0198, 0.168, 0.276),
]


def _add_ablation_flags(p: argparse.ArgumentParser) -> None:
    p.add_argument("--config", metavar="YAML", help="pipeline configuration (see config.yaml of any run)")
    p.add_argument("--rig", metavar="YAML", help="rig calibration (default: <recording>.rig.yaml beside it)")
    p.add_argument("--no-enhance", action="store_true", help="no ABA-CLAHE before features")
    p.add_argument("--no-ransac", action="store_true", help="no essential-matrix RANSAC on the matches")
    p.add_argument("--no-vision", action="store_true", help="no visual odometry")
    p.add_argument("--no-lidar", action="store_true", help="no LiDAR odometry (and no loops)")
    p.add_argument("--no-loop", action="store_true", help="no loop closure")
    p.add_argument("--solver", choices=["incremental", "batch"], help="incremental (default) or batch LM per keyframe")
    p.add_argument("--max-seconds", type=float, help="stop after this much of the recording")
    p.add_argument("--no-plots", action="store_true")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar")


def register(subparsers) -> None:
    r = subparsers.add_parser("run", help="run the fused estimator on a recording; writes a results folder")
    r.add_argument("recording", help="a ROS1 .bag, ROS2 bag (folder, .mcap, .db3), EuRoC or KITTI folder")
    r.add_argument("-o", "--output", required=True, help="results folder")
    _add_ablation_flags(r)
    r.set_defaults(func=cmd_run)

    d = subparsers.add_parser("demo", help="simulate the default low-light tunnel and run the estimator on it")
    d.add_argument("-o", "--output", default="runs/demo", help="results folder (default runs/demo)")
    d.add_argument("--seed", type=int, default=0)
    d.add_argument("--length", type=float, default=30.0, help="tunnel route length one way (m)")
    d.add_argument("--lighting", choices=["dark", "uneven", "normal"], default="uneven")
    _add_ablation_flags(d)
    d.set_defaults(func=cmd_demo)


def build_config(args: argparse.Namespace, recording: str | Path | None = None) -> Any:
    import dataclasses

    from ._config import PipelineConfig, find_rig, load_config, load_rig

    cfg = load_config(args.config) if args.config else PipelineConfig()
    rig = args.rig or (find_rig(recording) if recording is not None and not args.config else None)
    if rig:
        cfg = dataclasses.replace(cfg, rig=load_rig(rig))
    if args.no_enhance:
        cfg = cfg.replace(vision={"enhance": False})
    if args.no_ransac:
        cfg = cfg.replace(vision={"ransac": False})
    if args.no_vision:
        cfg = cfg.replace(vision={"enabled": False})
    if args.no_lidar:
        cfg = cfg.replace(lidar={"enabled": False}, loop={"enabled": False})
    if args.no_loop:
        cfg = cfg.replace(loop={"enabled": False})
    if args.solver:
        cfg = cfg.replace(solver={"mode": args.solver})
    return cfg


def _run(args: argparse.Namespace, recording: str | Path) -> dict[str, Any]:
    from tqdm import tqdm

    from ._run import run_recording

    cfg = build_config(args, recording)
    bar = tqdm(
        total=None,
        unit="s",
        disable=args.quiet,
        desc="run",
        # total is unknown (None) until the first progress report: the *_fmt fields show "?"
        bar_format="{l_bar}{bar}| {n_fmt}/{total_fmt} s [{elapsed}<{remaining}]",
    )

    def progress(done: float, total: float) -> None:
        bar.total = round(total)
        bar.n = round(done)
        bar.refresh()

    try:
        return run_recording(
            recording, args.output, cfg, progress=progress, plots=not args.no_plots, max_seconds=args.max_seconds
        )
    finally:
        bar.close()


def _fmt(x: Any, spec: str) -> str:
    return "n/a" if x is None or (isinstance(x, float) and x != x) else format(x, spec)


def print_summary(m: dict[str, Any], out: str | Path, paper: bool = False) -> None:
    print(f"results in {out}: trajectory_tum.txt, trajectory_kitti.txt, map.ply, metrics.json, config.yaml, plots")
    print(f"{'system':<26}{'APE RMSE m':>11}{'RPE RMSE':>10}{'loop err m':>11}{'ratio %':>9}")
    rows: list[tuple[str, Any, Any, Any, Any]] = list(PAPER_ROWS) if paper else []
    ratio = m.get("loop_error_ratio")
    rows.append(
        (
            "jaxslam (this run)",
            m.get("ape_rmse_m"),
            m.get("rpe_rmse"),
            m.get("loop_error_m"),
            None if ratio is None else 100 * ratio,
        )
    )
    for name, a, r, le, ratio_pct in rows:
        print(f"{name:<26}{_fmt(a, '.4f'):>11}{_fmt(r, '.4f'):>10}{_fmt(le, '.3f'):>11}{_fmt(ratio_pct, '.3f'):>9}")
    mp = m.get("mapping", {})
    print(
        f"mapping: {m['registered_frames']}/{m['total_frames']} keyframe images registered, "
        f"{mp.get('points', 0)} points, "
        f"{mp.get('residuals', 0)} residuals, track length {mp.get('track_length_min', 0)}/"
        f"{_fmt(mp.get('track_length_mean'), '.1f')}/{mp.get('track_length_max', 0)}, "
        f"reprojection RMSE {_fmt(m.get('reproj_rmse_px'), '.2f')} px" + (" (paper: 210/222, 1.10 px)" if paper else "")
    )
    print(
        f"LiDAR: {m['lidar_scans']} scans, {m['degenerate_scans']} degenerate; loops {m['loops_accepted']} accepted "
        f"({m.get('visual_loops_accepted', 0)} visual), {m['loops_rejected']} rejected"
        + (f", {m['loops_false']} false" if m.get("loops_false") is not None else "")
    )
    print(
        f"time: {m['runtime_s']:.1f} s for {m['sequence_duration_s']:.1f} s of recording "
        f"({m['runtime_s'] / max(m['sequence_duration_s'], 1e-9):.2f}x real time"
        + (f" on {m['machine']['cpu']}, {m['machine']['cpus']} CPUs" if "machine" in m else "")
        + (f"; JIT compilation in it: {m['compile_s']:.1f} s of CPU" if m.get("compile_s") is not None else "")
        + ")"
    )
    if m.get("warnings"):
        print("warnings: " + "; ".join(f"{k} x{v}" for k, v in m["warnings"].items()))


def cmd_run(args: argparse.Namespace) -> int:
    m = _run(args, args.recording)
    print_summary(m, args.output)
    return 0


def cmd_demo(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from ..sim import SimConfig, TunnelConfig, simulate_tunnel
    from ..sim._texture import LightingConfig

    out = Path(args.output)
    bag = out / "recording" / f"tunnel_seed{args.seed}_{args.lighting}_{args.length:g}m.bag"
    if not bag.exists():
        config = SimConfig(
            seed=args.seed, tunnel=TunnelConfig(length=args.length), lighting=LightingConfig(mode=args.lighting)
        )
        bar = tqdm(total=None, unit="frame", disable=args.quiet, desc="simulate")

        def progress(done: int, total: int) -> None:
            bar.total, bar.n = total, done
            bar.refresh()

        try:
            s = simulate_tunnel(config, bag, fmt="bag", progress=progress)
        finally:
            bar.close()
        print(
            f"simulated {bag}: {s['duration_s']:.0f} s, {s['path_length_m']:.1f} m out and back "
            f"(seed {args.seed}, {args.lighting} light)"
        )
    else:
        print(f"reusing {bag}")
    m = _run(args, bag)
    print_summary(m, out, paper=True)
    return 0

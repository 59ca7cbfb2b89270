"""``jaxslam tune RECORDING... -o weights.yaml [--holdout RECORDING...]``."""

from __future__ import annotations

import argparse
from pathlib import Path

from ..errors import ConfigError


def register(subparsers) -> None:
    t = subparsers.add_parser(
        "tune",
        help="learn the estimator's relative noise weights from recordings with surveyed ground truth",
        description=(
            "Runs the estimator on the training recordings, then learns one log-sigma multiplier per "
            "factor kind and axis group (IMU, bias walk, LiDAR/vision/loop rotation and translation) "
            "by gradients through the solver's optimum against the ground truth; repeats for --rounds. "
            "Writes a configuration for `jaxslam run --config`, a loss curve PNG and a JSON report."
        ),
    )
    t.add_argument("recordings", nargs="+", help="training recordings (with ground truth poses or prism fixes)")
    t.add_argument("-o", "--output", required=True, help="the learned configuration (YAML)")
    t.add_argument("--holdout", nargs="*", default=[], help="recordings to evaluate before/after (never trained on)")
    t.add_argument("--config", metavar="YAML", help="starting configuration (default: the built-in defaults)")
    t.add_argument("--rig", metavar="YAML", help="rig calibration (default: <first recording>.rig.yaml)")
    t.add_argument("--rounds", type=int, default=2, help="estimator runs per training recording (default 2)")
    t.add_argument("--steps", type=int, default=40, help="loss+gradient evaluations per round (L-BFGS-B; default 40)")
    t.add_argument(
        "--select",
        choices=["best", "last"],
        default="best",
        help="best (default): one more estimator run per training recording with the last round's weights, "
        "then keep the start's or a round's weights, whichever whole runs fit the truth best; last: the last round's",
    )
    t.add_argument(
        "--truth",
        choices=["auto", "poses", "positions"],
        default="auto",
        help="ground truth: full poses, total-station prism positions, or auto (poses when present)",
    )
    t.add_argument(
        "--lever-arm",
        nargs=3,
        type=float,
        metavar=("X", "Y", "Z"),
        default=(0.0, 0.0, 0.0),
        help="the prism's position in the body frame (m), with --truth positions",
    )
    t.add_argument(
        "--enhance",
        action="store_true",
        help="also learn ABA-CLAHE's alpha, beta and clip with the differentiable front-end objective "
        "(consecutive frames of the training recordings)",
    )
    t.add_argument("--enhance-steps", type=int, default=20, help="Adam steps for --enhance (default 20)")
    t.add_argument(
        "--devices",
        type=int,
        default=0,
        help="JAX devices to shard the training recordings' graphs across (default 0: all local devices; "
        "a CPU-only machine has one unless XLA_FLAGS=--xla_force_host_platform_device_count=N)",
    )
    t.add_argument("--workdir", help="where the estimator runs go (default: <output stem>_runs/)")
    t.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    t.set_defaults(func=cmd_tune)


def cmd_tune(args: argparse.Namespace) -> int:
    import dataclasses

    from tqdm import tqdm

    from ..pipeline._config import PipelineConfig, find_rig, load_config, load_rig, save_config
    from ._tune import TuneConfig, plot_loss, tune, weights_summary, write_report

    if args.rounds < 1 or args.steps < 0:
        raise ConfigError("--rounds must be >= 1 and --steps >= 0")
    import jax

    if not 0 <= args.devices <= len(jax.local_devices()):
        raise ConfigError(f"--devices must be 0 (all) to {len(jax.local_devices())} (the local JAX devices)")
    out = Path(args.output)
    if out.suffix.lower() not in (".yaml", ".yml"):
        raise ConfigError(f"--output must be a .yaml file, got {out}")
    for r in [*args.recordings, *args.holdout]:
        if not Path(r).exists():
            raise ConfigError(f"no such recording: {r}")
    cfg = load_config(args.config) if args.config else PipelineConfig()
    rig = args.rig or (find_rig(args.recordings[0]) if not args.config else None)
    if rig:
        cfg = dataclasses.replace(cfg, rig=load_rig(rig))
    tcfg = TuneConfig(
        steps=args.steps,
        rounds=args.rounds,
        truth=args.truth,
        lever_arm=tuple(args.lever_arm),
        devices=args.devices,
        select=args.select,
    )
    work = Path(args.workdir) if args.workdir else out.with_name(out.stem + "_runs")
    bar = None if args.quiet else (lambda **kw: tqdm(**kw))
    enhancement = None
    if args.enhance:
        from ._enhance_proxy import tune_enhancement
        from ._tune import sample_frame_pairs

        a, b = sample_frame_pairs(args.recordings)
        v = cfg.vision
        ebar = None if args.quiet else tqdm(total=args.enhance_steps + 1, desc="enhancement")

        def step(k: int, n: int, value: float) -> None:
            if ebar is not None:
                ebar.update(1)
                ebar.set_postfix(objective=f"{value:.4f}")

        try:
            enhancement = tune_enhancement(a, v.alpha, v.beta, v.clip, twins=b, steps=args.enhance_steps, progress=step)
        finally:
            if ebar is not None:
                ebar.close()
        cfg = cfg.replace(vision={"alpha": enhancement.alpha, "beta": enhancement.beta, "clip": enhancement.clip})
        print(
            f"enhancement: alpha {v.alpha:.3f} -> {enhancement.alpha:.3f}, "
            f"beta {v.beta:.3f} -> {enhancement.beta:.3f}, "
            f"clip {v.clip:.2f} -> {enhancement.clip:.2f} (objective {enhancement.history[0]:.4f} -> "
            f"{min(enhancement.history):.4f}, {len(a)} frame pairs)"
        )
    report = tune(args.recordings, cfg, tcfg, work, holdout=args.holdout, bar=bar)
    if enhancement is not None:
        report.enhancement = {
            "alpha": enhancement.alpha,
            "beta": enhancement.beta,
            "clip": enhancement.clip,
            "objective": enhancement.history,
        }
    out.parent.mkdir(parents=True, exist_ok=True)
    save_config(report.config, out)
    png = out.with_suffix(".loss.png")
    plot_loss(png, report, tcfg.steps)
    rep = out.with_suffix(".report.json")
    write_report(rep, report)
    if report.run_rmse_m:
        print(
            "whole runs on the training recordings (mean aligned RMSE): "
            + ", ".join(f"{k} {v:.4f} m" for k, v in report.run_rmse_m.items())
            + f"; kept: {report.selected}"
        )
    print(f"wrote {out} (use: jaxslam run REC -o DIR --config {out}), {png.name}, {rep.name}")
    for k, v in weights_summary(report.config).items():
        print(f"  {k}: {v}")
    print(f"{report.estimator_runs} estimator runs in {report.time_s:.0f} s")
    return 0

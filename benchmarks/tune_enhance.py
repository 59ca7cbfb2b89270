"""Tuning ABA-CLAHE's alpha, beta and clip through the differentiable front-end proxy, judged by
the discrete pipeline on held-out simulated frames (SPEC §3.1, §6).

    python benchmarks/tune_enhance.py [--json PATH] [--steps 25] [--frames 8]

1. Render short stretches of camera frames (10 Hz, 512x320, with ground-truth poses and a
   second sensor-noise realisation of every view) from the simulated tunnel: training seeds
   10, 11 ("uneven" lighting), held-out seeds 12, 13 ("uneven") and seed 12 ("dark"); three
   stretches per sequence (lit, dark-gap and mixed stretches of the route).
2. Tune (alpha, beta, clip) with :func:`jaxslam.tune._enhance_proxy.tune_enhancement` on the
   training frames only (every ``--tune-every``-th frame of each stretch and its noise twin),
   starting from a deliberately bad setting (alpha = beta = 1, clip 1: almost no
   enhancement).
3. Run the discrete front end (hard ABA-CLAHE → SURF → matching → essential RANSAC) on
   consecutive pairs of the held-out frames for the start, the tuned and the paper's defaults
   (0.25, 0.4, 2.0): registered pairs (>= 25 inliers), mean inliers, median RMS Sampson
   error (px) and median relative-rotation error (deg), plus the proxy's value on the
   held-out frames.

4. With ``--estimator SEED:LIGHTING ...``: the whole estimator (``jaxslam run``, vision
   inline so runs are deterministic) on held-out simulated recordings (``--length`` m, out
   and back; simulated into ``--workdir`` if missing) with each setting as
   ``vision.alpha/beta/clip``: registered frames, reprojection RMSE and APE, the figures the
   issue's goal names.

JSON (``--json``): ``{"train_seeds", "heldout", "start", "tuned", "defaults", "tuning"}``,
each setting with alpha, beta, clip, the proxy value and per held-out sequence and in total
the discrete metrics (and ``estimator``: per recording and setting, with ``--estimator``).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import jaxslam  # noqa: F401  (float64 on)
from jaxslam.tune._enhance_proxy import (
    FrameSet,
    enhancement_objective,
    evaluate_registration,
    simulate_frames,
    to_params,
    tune_enhancement,
)

TRAIN = [(10, "uneven"), (11, "uneven")]
HELDOUT = [(12, "uneven"), (13, "uneven"), (12, "dark")]
STARTS = {"uneven": (22.0, 26.0, 50.0), "dark": (12.0, 16.0, 20.0)}
START = (1.0, 1.0, 1.0)
DEFAULTS = (0.25, 0.4, 2.0)


def render(seqs: list[tuple[int, str]], frames: int) -> dict[str, list[FrameSet]]:
    out = {}
    for seed, light in seqs:
        out[f"{seed}-{light}"] = simulate_frames(seed, light, STARTS[light], frames)
    return out


def evaluate(setting: tuple[float, float, float], sets: dict[str, list[FrameSet]]) -> dict:
    per: dict[str, dict] = {}
    for name, stretches in sets.items():
        evs = [evaluate_registration(f.frames, f.poses, f.K, *setting, distortion=f.distortion) for f in stretches]
        pairs = sum(e["pairs"] for e in evs)
        any_reg = any(e["registered"] for e in evs)
        per[name] = {
            "pairs": pairs,
            "registered": sum(e["registered"] for e in evs),
            "mean_inliers": float(sum(e["mean_inliers"] * e["pairs"] for e in evs) / pairs),
            "mean_keypoints": float(np.mean([e["mean_keypoints"] for e in evs])),
            "sampson_px": float(np.nanmedian([e["sampson_px"] for e in evs])) if any_reg else None,
            "rot_err_deg": float(np.nanmedian([e["rot_err_deg"] for e in evs])) if any_reg else None,
        }
    pairs = sum(p["pairs"] for p in per.values())
    total = {
        "pairs": pairs,
        "registered": sum(p["registered"] for p in per.values()),
        "mean_inliers": float(sum(p["mean_inliers"] * p["pairs"] for p in per.values()) / pairs),
    }
    return {"per_sequence": per, "total": total}


def estimator_eval(args: argparse.Namespace, settings: dict[str, dict]) -> list[dict]:
    """The estimator on each ``--estimator`` recording with each setting's enhancement."""
    import dataclasses

    from jaxslam.cli import main as cli
    from jaxslam.pipeline import PipelineConfig, run_recording
    from jaxslam.pipeline._config import find_rig, load_rig

    rows = []
    for spec in args.estimator:
        seed, _, light = spec.partition(":")
        bag = args.workdir / (f"seed{seed}.bag" if light == "uneven" else f"seed{seed}_{light}.bag")
        if not bag.exists():
            args.workdir.mkdir(parents=True, exist_ok=True)
            cmd = ["simulate", "-o", str(bag), "--seed", seed, "--length", str(args.length), "--lighting", light, "-q"]
            if cli(cmd) != 0:
                raise SystemExit(f"simulation of {bag} failed")
        base = PipelineConfig().replace(vision={"threaded": False})
        rig = find_rig(bag)
        if rig is not None:
            base = dataclasses.replace(base, rig=load_rig(rig))
        row: dict = {"recording": bag.name}
        for name, st in settings.items():
            cfg = base.replace(vision={"alpha": st["alpha"], "beta": st["beta"], "clip": st["clip"]})
            m = run_recording(bag, args.workdir / "enhance_eval" / name / bag.stem, cfg, plots=False)
            row[name] = {
                "registered": m["registered_frames"],
                "frames": m["total_frames"],
                "reproj_rmse_px": m["reproj_rmse_px"],
                "ape_m": m.get("ape_rmse_m"),
            }
            print(
                f"estimator {bag.name:<20} {name:<9} registered {m['registered_frames']}/{m['total_frames']}, "
                f"reprojection {m['reproj_rmse_px']:.3f} px, APE {m.get('ape_rmse_m', float('nan')):.4f} m",
                flush=True,
            )
        rows.append(row)
    return rows


def proxy_batch(sets: dict[str, list[FrameSet]], every: int) -> tuple[np.ndarray, np.ndarray]:
    fs = [f for stretches in sets.values() for f in stretches]
    return np.concatenate([f.frames[::every] for f in fs]), np.concatenate([f.twins[::every] for f in fs])  # type: ignore[index]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--steps", type=int, default=25)
    ap.add_argument("--lr", type=float, default=0.2)
    ap.add_argument("--frames", type=int, default=8, help="frames per stretch (3 stretches per sequence)")
    ap.add_argument("--tune-every", type=int, default=8, help="tune on every n-th training frame (and its twin)")
    ap.add_argument(
        "--estimator",
        nargs="*",
        default=[],
        metavar="SEED:LIGHTING",
        help="also run the estimator on these held-out simulated recordings with each setting",
    )
    ap.add_argument("--length", type=float, default=25.0, help="tunnel length of --estimator recordings (m)")
    ap.add_argument("--workdir", type=Path, default=Path("runs/bench_tune"))
    args = ap.parse_args()
    for spec in args.estimator:
        seed, _, light = spec.partition(":")
        if not seed.isdigit() or light not in ("uneven", "dark", "normal"):
            ap.error(f"--estimator wants SEED:LIGHTING (lighting uneven, dark or normal), got {spec!r}")

    t0 = time.perf_counter()
    train = render(TRAIN, args.frames)
    held = render(HELDOUT, args.frames)
    t_render = time.perf_counter() - t0
    tf, tt = proxy_batch(train, args.tune_every)
    hf, ht = proxy_batch(held, args.tune_every)

    try:
        from tqdm import tqdm

        bar = tqdm(total=args.steps + 1, desc="tuning", unit="step", leave=False)

        def progress(k: int, n: int, value: float) -> None:
            bar.update(1)
            bar.set_postfix(objective=f"{value:.4f}")
    except ImportError:  # pragma: no cover - tqdm is a dependency
        bar = None
        progress = None  # type: ignore[assignment]

    res = tune_enhancement(tf, *START, twins=tt, steps=args.steps, lr=args.lr, progress=progress)
    if bar is not None:
        bar.close()
    tuned = (res.alpha, res.beta, res.clip)

    report: dict = {
        "train_seeds": [{"seed": s, "lighting": lt, "starts_s": list(STARTS[lt])} for s, lt in TRAIN],
        "heldout": [{"seed": s, "lighting": lt, "starts_s": list(STARTS[lt])} for s, lt in HELDOUT],
        "frames_per_stretch": args.frames,
        "render_s": round(t_render, 1),
        "tuning": {
            "steps": args.steps,
            "lr": args.lr,
            "train_images": len(tf),
            "seconds": round(res.seconds, 1),
            "history": res.history,
            "path": res.path,
        },
    }
    for name, setting in (("start", START), ("tuned", tuned), ("defaults", DEFAULTS)):
        t1 = time.perf_counter()
        ev = evaluate(setting, held)
        report[name] = {
            "alpha": setting[0],
            "beta": setting[1],
            "clip": setting[2],
            "proxy_train": float(enhancement_objective(to_params(*setting), tf, tt)),  # type: ignore[arg-type]
            "proxy_heldout": float(enhancement_objective(to_params(*setting), hf, ht)),  # type: ignore[arg-type]
            "heldout": ev,
            "eval_s": round(time.perf_counter() - t1, 1),
        }

    print(f"train {TRAIN}: {len(tf)} images + twins for tuning; held out {HELDOUT}: {args.frames} frames x 3 stretches")
    best = min(res.history)
    print(f"tuning: {args.steps} Adam steps, {res.seconds:.1f} s; objective {res.history[0]:.4f} -> {best:.4f}")
    head = f"{'setting':9s} {'alpha':>6s} {'beta':>6s} {'clip':>5s} {'proxy(ho)':>9s}"
    for name in held:
        head += f" | {name:>12s} reg  inl  samp  rot"
    head += " | total reg  inliers"
    print(head)
    for name in ("start", "tuned", "defaults"):
        r = report[name]
        line = f"{name:9s} {r['alpha']:6.3f} {r['beta']:6.3f} {r['clip']:5.2f} {r['proxy_heldout']:9.4f}"
        for seq in held:
            p = r["heldout"]["per_sequence"][seq]
            samp = "  -  " if p["sampson_px"] is None else f"{p['sampson_px']:.2f}"
            rot = "  -  " if p["rot_err_deg"] is None else f"{p['rot_err_deg']:.2f}"
            line += f" | {p['registered']:>3d}/{p['pairs']:<3d} {p['mean_inliers']:6.1f} {samp:>5s} {rot:>5s}"
        tot = r["heldout"]["total"]
        line += f" | {tot['registered']:>4d}/{tot['pairs']:<4d} {tot['mean_inliers']:6.1f}"
        print(line)
    if args.estimator:
        report["estimator"] = estimator_eval(args, {n: report[n] for n in ("start", "tuned", "defaults")})
    print(f"total {time.perf_counter() - t0:.0f} s (render {t_render:.0f} s)")
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(report, indent=1))


if __name__ == "__main__":
    main()

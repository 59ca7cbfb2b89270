"""Learning noise weights from wrong ones (issue 7): gradient tuning vs random search.

    python benchmarks/tune.py --json runs/tune.json
    python benchmarks/tune.py --truth positions --json runs/tune_positions.json   # prism + lever arm

Simulated tunnels (``--length`` m one way, out and back) are written once into ``--workdir``
(``jaxslam simulate``) and reused. The starting configuration is deliberately wrong in the
ways users report: LiDAR trusted ``--lidar-overtrust`` (30x) too much (its information
scale) and IMU noise densities ``--imu-factor`` (10x) too small. Then:

* **gradient**: ``jaxslam tune`` on the training recordings (``--train``, default seed 10 in
  uneven light and seed 11 dark; ``--rounds`` estimator runs per recording, ``--steps``
  bounded L-BFGS evaluations on adjoint gradients per round, then one more run per recording
  to keep the start's or a round's weights by whole-run fit: ``TuneConfig.select="best"``);
* **random search**, the baseline, with the same estimator runs, the same number of graph
  solves (``steps + 1`` log-uniform draws within 30x per round, best training loss kept;
  :class:`jaxslam.tune.TuneConfig` ``search="random"``) and the same selection;
* evaluation on held-out recordings that neither saw (``--heldout``, default seed 12 in
  uneven, dark and normal light; normal light is in no training recording): the estimator
  run with the wrong start, the tuned, the random-search and the hand-set default weights.

Prints a table; ``--json`` writes ``{"heldout_ape_before", "heldout_ape_after",
"heldout_ape_defaults", "random_search_ape", "train_seeds", "heldout_seeds",
"estimator_runs", ...}`` (APE in metres: mean over the held-out recordings, per recording
under ``heldout``). The defaults were hand-set while developing on seed 0 (another tunnel
length); every recording here is new to them.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
import types
from pathlib import Path
from typing import Any


def recording(work: Path, seed: int, lighting: str, length: float) -> Path:
    from jaxslam.cli import main as cli

    bag = work / (f"seed{seed}.bag" if lighting == "uneven" else f"seed{seed}_{lighting}.bag")
    if not bag.exists():
        work.mkdir(parents=True, exist_ok=True)
        args = ["simulate", "-o", str(bag), "--seed", str(seed), "--length", str(length), "--lighting", lighting, "-q"]
        if cli(args) != 0:
            raise SystemExit(f"simulation of {bag} failed")
    return bag


def parse_spec(spec: str) -> tuple[int, str]:
    """``SEED[:LIGHTING]`` -> (seed, lighting); the lighting defaults to uneven."""
    seed, _, light = spec.partition(":")
    if not seed.isdigit() or light not in ("", "uneven", "dark", "normal"):
        raise SystemExit(f"a recording is SEED[:uneven|dark|normal], got {spec!r}")
    return int(seed), light or "uneven"


def theta_total(rounds: list[dict[str, Any]], selected: str | None = None) -> Any:
    """Log-sigma multipliers of a tuned configuration relative to the start: the rounds'
    add up to the one whose weights were kept (``selected``: ``start``, ``round N``, or None
    for the last)."""
    import numpy as np

    from jaxslam.tune import GROUPS

    n = len(rounds) if not selected else 0 if selected == "start" else int(selected.split()[1])
    return np.sum([[rd["theta"][g] for g in GROUPS] for rd in rounds[:n]] or [[0.0] * len(GROUPS)], axis=0)


def graph_level(held: list[Path], start: Any, thetas: dict[str, Any], args: Any, work: Path) -> list[dict[str, Any]]:
    """Held-out APE with the front end held fixed: each held-out recording is run once with
    the starting configuration, its final graph kept, and re-solved with each configuration's
    weights (log-sigma multipliers relative to the start). Separates what the weights do
    from how the front end reacts to them (loop gates, predictions), which makes single
    estimator runs of different configurations differ chaotically."""
    import jax.numpy as jnp
    import numpy as np

    from jaxslam.pipeline import run_recording
    from jaxslam.sim import SimConfig
    from jaxslam.tune import DifferentiableSolver, TuneConfig, aligned_position_loss
    from jaxslam.tune._tune import capture, factor_fn_for

    rows = []
    tc = TuneConfig(truth=args.truth, lever_arm=tuple(SimConfig().prism))
    for bag in held:
        keep: list[Any] = []
        run_recording(
            bag,
            work / f"heldout_graph_{args.truth}" / bag.stem,
            start,
            plots=False,
            on_finish=lambda est, res, gt, b=bag, k=keep: k.append(capture(est, res, gt, tc, b.stem)),
        )
        cap = keep[0]
        ds = DifferentiableSolver(factor_fn_for(cap), cap.values, jnp.zeros(len(thetas["before"])))
        row: dict[str, Any] = {"recording": bag.name}
        for label, th in thetas.items():
            row[label] = float(np.sqrt(aligned_position_loss(ds.solve(jnp.asarray(th)), cap)))
        rows.append(row)
    return rows


def print_graph(rows: list[dict[str, Any]]) -> None:
    print("held-out APE with the front end fixed (start's graph re-solved with each configuration's weights):")
    for row in rows:
        print(f"  {row['recording']:<22}" + "".join(f" {k} {v:.4f}" for k, v in row.items() if k != "recording"))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument(
        "--train",
        nargs="+",
        default=["10:uneven", "11:dark"],
        help="training recordings as SEED[:LIGHTING] (default lighting: uneven)",
    )
    ap.add_argument(
        "--heldout",
        nargs="+",
        default=["12:uneven", "12:dark", "12:normal"],
        help="held-out recordings as SEED[:LIGHTING]",
    )
    ap.add_argument("--length", type=float, default=25.0)
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--steps", type=int, default=40)
    ap.add_argument("--lidar-overtrust", type=float, default=30.0)
    ap.add_argument("--imu-factor", type=float, default=0.1, help="multiplies the IMU noise densities")
    ap.add_argument("--truth", choices=["poses", "positions"], default="poses")
    ap.add_argument("--threaded", action="store_true", help="vision in its worker thread (faster, not deterministic)")
    ap.add_argument("--workdir", default="runs/bench_tune")
    ap.add_argument("--json", metavar="PATH")
    ap.add_argument(
        "--reuse-from",
        metavar="JSON",
        help="reuse an earlier run's random search and its held-out runs of the start, random and "
        "default weights (deterministic runs of unchanged configurations); rerun the gradient tuning",
    )
    ap.add_argument(
        "--graph-eval-from",
        metavar="JSON",
        help="only the fixed-front-end held-out evaluation, with the weights of an earlier run's JSON (updated)",
    )
    args = ap.parse_args()

    import numpy as np
    from tqdm import tqdm

    from jaxslam.pipeline import PipelineConfig, run_recording
    from jaxslam.pipeline._config import find_rig, load_config, load_rig, save_config
    from jaxslam.sim import SimConfig
    from jaxslam.tune import GROUPS, TuneConfig, tune, weights_summary
    from jaxslam.tune._tune import plot_loss

    work = Path(args.workdir)
    train = [recording(work, *parse_spec(spec), args.length) for spec in args.train]
    held = [recording(work, *parse_spec(spec), args.length) for spec in args.heldout]
    rig_path = find_rig(train[0])
    # the visual front end inline (not in its worker thread): runs are then deterministic, so
    # differences between configurations are not run-to-run noise (threaded runs of one
    # configuration differed by up to 0.03 m APE here)
    defaults = PipelineConfig().replace(vision={"threaded": args.threaded})
    if rig_path is not None:
        defaults = dataclasses.replace(defaults, rig=load_rig(rig_path))
    wrong = defaults.replace(
        lidar={"information_scale": defaults.lidar.information_scale * args.lidar_overtrust},
        imu={"noise_scale": defaults.imu.noise_scale * args.imu_factor},
    )
    lever = SimConfig().prism
    # the hand-set defaults as log-sigma multipliers relative to the wrong start
    theta_defaults = np.zeros(len(GROUPS))
    theta_defaults[GROUPS.index("imu")] = -np.log(args.imu_factor)
    for g_ in ("lidar.rotation", "lidar.translation"):
        theta_defaults[GROUPS.index(g_)] = 0.5 * np.log(args.lidar_overtrust)
    if args.graph_eval_from:
        prev = json.loads(Path(args.graph_eval_from).read_text())
        thetas = {
            "before": np.zeros(len(GROUPS)),
            "after": theta_total(prev["gradient_rounds"], prev.get("selected", {}).get("gradient")),
            "random": theta_total(prev["random_rounds"], prev.get("selected", {}).get("random")),
            "defaults": theta_defaults,
        }
        rows = graph_level(held, wrong, thetas, args, work)
        prev["heldout_graph"] = rows
        for label in thetas:
            prev[f"heldout_graph_ape_{label}"] = float(np.mean([r[label] for r in rows]))
        Path(args.graph_eval_from).write_text(json.dumps(prev, indent=2, default=str) + "\n")
        print_graph(rows)
        return
    t_all = time.perf_counter()
    results: dict[str, Any] = {}
    prev = json.loads(Path(args.reuse_from).read_text()) if args.reuse_from else None
    for search in ("gradient", "random"):
        if prev is not None and search == "random":  # unchanged code and deterministic runs: reuse
            results[search] = types.SimpleNamespace(
                config=load_config(work / f"weights_{args.truth}_random.yaml"),
                rounds=prev["random_rounds"],
                estimator_runs=prev["random_search_estimator_runs"],
            )
            print("random search: reused from", args.reuse_from)
            continue
        tc = TuneConfig(
            steps=args.steps, rounds=args.rounds, truth=args.truth, lever_arm=tuple(lever), search=search, seed=0
        )
        t0 = time.perf_counter()
        rep = tune(train, wrong, tc, work / f"tune_{args.truth}_{search}", bar=lambda **kw: tqdm(**kw))
        results[search] = rep
        save_config(rep.config, work / f"weights_{args.truth}_{search}.yaml")
        plot_loss(work / f"loss_{args.truth}_{search}.png", rep, args.steps)
        print(f"{search}: {rep.estimator_runs} estimator runs, {time.perf_counter() - t0:.0f} s", flush=True)
    configs = {
        "before": wrong,
        "after": results["gradient"].config,
        "random": results["random"].config,
        "defaults": defaults,
    }
    heldout_rows = []
    eval_runs = 0
    for bag in held:
        row: dict[str, Any] = {"recording": bag.name}
        for label, cfg in configs.items():
            if prev is not None and label != "after":
                row[label] = next(r for r in prev["heldout"] if r["recording"] == bag.name)[label]
                print(f"held out {bag.name:<22} {label:<9} APE {row[label]['ape_m']:.4f} m (reused)", flush=True)
                continue
            m = run_recording(bag, work / f"heldout_{args.truth}" / label / bag.stem, cfg, plots=False)
            eval_runs += 1
            row[label] = {
                "ape_m": m.get("ape_rmse_m"),
                "loop_error_m": m.get("loop_error_m"),
                "registered": f"{m['registered_frames']}/{m['total_frames']}",
            }
            print(f"held out {bag.name:<22} {label:<9} APE {m.get('ape_rmse_m'):.4f} m", flush=True)
        heldout_rows.append(row)

    def mean(label: str) -> float:
        return float(np.mean([r[label]["ape_m"] for r in heldout_rows]))

    g, r = results["gradient"], results["random"]
    thetas = {
        "before": np.zeros(len(GROUPS)),
        "after": theta_total(g.rounds, getattr(g, "selected", None)),
        "random": theta_total(r.rounds, getattr(r, "selected", None)),
        "defaults": theta_defaults,
    }
    graph_rows = graph_level(held, wrong, thetas, args, work)
    eval_runs += len(held)
    out = {
        "heldout_ape_before": mean("before"),
        "heldout_ape_after": mean("after"),
        "heldout_ape_defaults": mean("defaults"),
        "random_search_ape": mean("random"),
        "train_seeds": args.train,
        "heldout_seeds": args.heldout,
        "estimator_runs": g.estimator_runs,
        "random_search_estimator_runs": r.estimator_runs,
        "selected": {"gradient": getattr(g, "selected", None), "random": getattr(r, "selected", None)},
        "train_run_rmse_m": {"gradient": getattr(g, "run_rmse_m", None), "random": getattr(r, "run_rmse_m", None)},
        "evaluation_runs": eval_runs,
        "truth": args.truth,
        "lever_arm": list(lever) if args.truth == "positions" else None,
        "start": {"lidar_overtrust": args.lidar_overtrust, "imu_noise_factor": args.imu_factor},
        "heldout": heldout_rows,
        "heldout_graph": graph_rows,
        **{f"heldout_graph_ape_{k}": float(np.mean([row[k] for row in graph_rows])) for k in thetas},
        "weights": {k: weights_summary(c) for k, c in configs.items()},
        "gradient_rounds": g.rounds,
        "random_rounds": r.rounds,
        "time_s": time.perf_counter() - t_all,
        "reused_from": args.reuse_from,
    }
    print()
    print(f"{'held-out APE (mean m)':<34}{'value':>10}")
    for k in ("heldout_ape_before", "heldout_ape_after", "heldout_ape_defaults", "random_search_ape"):
        print(f"{k:<34}{out[k]:>10.4f}")
    imp = 1 - out["heldout_ape_after"] / out["heldout_ape_before"]
    print(f"improvement from the wrong start: {100 * imp:.1f} % (goal >= 30 %)")
    print(
        f"after vs defaults: {out['heldout_ape_after']:.4f} vs {out['heldout_ape_defaults']:.4f}; "
        f"vs random search: {out['random_search_ape']:.4f}"
    )
    for name, rep in (("gradient", g), ("random search", r)):
        if getattr(rep, "run_rmse_m", None):
            runs = ", ".join(f"{k} {v:.4f}" for k, v in rep.run_rmse_m.items())
            print(f"{name}: whole training runs, mean aligned RMSE (m): {runs}; kept {rep.selected}")
    for rr in g.rounds:
        print(
            f"gradient round: graph RMSE {rr['graph_rmse_before_m']:.4f} -> {rr['graph_rmse_after_m']:.4f} m, "
            f"forward {rr['forward_s']:.1f} s, backward {rr['backward_s']:.1f} s"
        )
    print_graph(graph_rows)
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps(out, indent=2, default=str) + "\n")
        print(f"wrote {args.json}")


if __name__ == "__main__":
    main()

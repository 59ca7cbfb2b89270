"""The ``jaxslam`` command. Thin over library functions; every subcommand is one function.

Known errors (:class:`~jaxslam.errors.JaxSlamError`, missing files) print one line on stderr
and exit with code 1; ``--debug`` shows the traceback instead.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path

from .errors import ConfigError, JaxSlamError


def _robust_kernel(spec: str | None):
    from .core import KERNELS

    if not spec:
        return None
    name, _, k = spec.partition(":")
    if name not in KERNELS:
        raise ConfigError(f"--robust: unknown kernel {name!r}; choose from {sorted(KERNELS)} (e.g. huber:1.345)")
    try:
        scale = float(k) if k else 1.0
    except ValueError as exc:
        raise ConfigError(f"--robust: scale must be a number, got {k!r}") from exc
    if not scale > 0:
        raise ConfigError(f"--robust: scale must be positive, got {scale}")
    return KERNELS[name](scale)


def initial_values_for(graph, init: str):
    """Initial values of a pose graph: as read (``file``) or by chordal relaxation."""
    import numpy as np

    from .core import Values
    from .solvers import chordal_initialize_se2, chordal_initialize_se3

    if init == "file":
        return graph.values
    if graph.num_edges == 0:
        return graph.values
    fn = chordal_initialize_se3 if graph.dim == 3 else chordal_initialize_se2
    ids = graph.vertex_ids
    anchor = np.asarray(graph.values.params(graph.var_type))[0]
    params = fn(ids, graph.edges_i, graph.edges_j, graph.measured, graph.information, anchor)
    return Values.create({graph.var_type(ids): params})


def cmd_optimize(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from .io import read_g2o, write_g2o
    from .solvers import Solver, SolverConfig

    robust = _robust_kernel(args.robust)  # check the options before any I/O
    t0 = time.perf_counter()
    graph = read_g2o(args.input)
    factors = list(graph.factors)
    if robust is not None:
        factors = [f.with_robust(robust) if len(f.variables) == 2 else f for f in factors]
    t_read = time.perf_counter() - t0
    t0 = time.perf_counter()
    values = initial_values_for(graph, args.init)
    t_init = time.perf_counter() - t0
    config = SolverConfig(
        method=args.solver,
        linear_solver=args.linear_solver,
        max_iterations=args.max_iterations,
        fix_gauge=True,
    )
    t0 = time.perf_counter()
    solver = Solver(factors, values, config)
    t_analyse = time.perf_counter() - t0
    with tqdm(
        total=args.max_iterations,
        desc=f"{args.solver.upper()}",
        unit="it",
        disable=args.quiet,
        file=sys.stderr,
        leave=False,
    ) as bar:

        def progress(it: int, cost: float) -> None:
            bar.n = it
            bar.set_postfix(cost=f"{cost:.6g}")
            bar.refresh()

        result = solver.solve(callback=progress)
    out_graph = graph.with_values(result.values)
    if args.output:
        write_g2o(args.output, out_graph, format="auto")  # .txt / .graph: GTSAM text format
    summary = {
        "input": str(args.input),
        "vertices": len(graph.vertex_ids),
        "edges": int(graph.num_edges),
        "init": args.init,
        "solver": args.solver,
        "linear_solver": solver.system.method,
        "status": result.status.value,
        "message": result.message,
        "initial_cost": result.initial_cost,
        "final_cost": result.final_cost,
        "iterations": result.iterations,
        "linear_solves": result.linear_solves,
        "time_s": {"read": t_read, "init": t_init, "analyse": t_analyse, "solve": result.time_s},
    }
    n_anchor = len(solver.anchors)
    gauge = "" if n_anchor == 0 else " (gauge fixed at the first vertex)"
    if n_anchor > 1:
        names = ", ".join(solver.problem.describe_block(b) for b in solver.problem.free_gauge_blocks()[:5])
        print(
            f"jaxslam optimize: warning: the graph has {n_anchor} disconnected components; each is held at "
            f"its first vertex ({names}{', ...' if n_anchor > 5 else ''}), so their relative placement is arbitrary",
            file=sys.stderr,
        )
        gauge = f" ({n_anchor} disconnected components, each anchored)"
    print(
        f"{Path(args.input).name}: {summary['vertices']} vertices, {summary['edges']} edges{gauge}\n"
        f"  initial cost {result.initial_cost:.10g}  (init: {args.init})\n"
        f"  final cost   {result.final_cost:.10g}  [{result.status.value}: {result.message}]\n"
        f"  {result.iterations} iterations, {result.linear_solves} linear solves ({solver.system.method}), "
        f"solve {result.time_s:.3f} s (first call includes JIT compilation), analysis {t_analyse:.3f} s, "
        f"read {t_read:.3f} s, init {t_init:.3f} s"
    )
    if args.output:
        print(f"  wrote {args.output}")
    if args.json:
        Path(args.json).write_text(json.dumps(summary, indent=2))
    return 0 if result.success else 2


def _ape_rmse(gt, est) -> float:
    """Translation RMSE without alignment (both trajectories start at the anchored pose)."""
    import numpy as np

    return float(np.sqrt(np.mean(np.sum((np.asarray(gt)[:, 4:] - np.asarray(est)[:, 4:]) ** 2, axis=1))))


def cmd_demo(args: argparse.Namespace) -> int:
    """A synthetic out-and-back tunnel pose graph with loop closures: chained odometry vs
    the optimised graph, against ground truth, written to OUTDIR with a plot."""
    import matplotlib

    matplotlib.use("Agg")
    import jax.numpy as jnp
    import matplotlib.pyplot as plt
    import numpy as np

    from .core import Gaussian, Pose3Var, Values
    from .factors import PriorFactor
    from .io import PoseGraph, Trajectory, chain_odometry, write_g2o, write_tum
    from .lie import SE3
    from .sim import tunnel_pose_graph
    from .solvers import Solver, SolverConfig

    out = Path(args.output)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    sim = tunnel_pose_graph(length=args.length, seed=args.seed)
    info = np.zeros((len(sim.sigmas), 6, 6))
    info[:, np.arange(6), np.arange(6)] = 1.0 / sim.sigmas**2
    ids, chained = chain_odometry(3, sim.edges_i[~sim.is_loop], sim.edges_j[~sim.is_loop], sim.measured[~sim.is_loop])
    # anchor: the first pose at its true value (a known start, as a surveyed entrance gives)
    chained = np.asarray((SE3(jnp.asarray(sim.ground_truth[:1])) @ SE3(jnp.asarray(chained))).params)
    graph = PoseGraph.from_arrays(
        3,
        Values.create({Pose3Var(ids): chained}),
        sim.edges_i,
        sim.edges_j,
        sim.measured,
        info,
        initialised_from="odometry",
    )
    first = Pose3Var(ids[:1])
    factors = [*graph.factors, PriorFactor.create(first, sim.ground_truth[:1], Gaussian.isotropic(6, 1e-6))]
    print(
        f"demo: synthetic tunnel {args.length:.0f} m out and back, {len(ids)} keyframes, "
        f"{int((~sim.is_loop).sum())} odometry + {int(sim.is_loop.sum())} loop-closure factors (seed {args.seed})"
    )
    solver = Solver(factors, graph.values, SolverConfig(method="lm"))
    result = solver.solve()
    opt = np.asarray(result.values.params(Pose3Var))
    t_total = time.perf_counter() - t0
    gt = sim.ground_truth
    path_len = float(np.sum(np.linalg.norm(np.diff(gt[:, 4:], axis=0), axis=1)))
    rows = {
        "chained odometry": (chained, _ape_rmse(gt, chained), float(np.linalg.norm(chained[-1, 4:] - gt[-1, 4:]))),
        "jaxslam LM": (opt, _ape_rmse(gt, opt), float(np.linalg.norm(opt[-1, 4:] - gt[-1, 4:]))),
    }
    print(f"{'estimate':<18}{'APE RMSE m':>12}{'end error m':>13}{'end err / path':>16}")
    for name, (_, ape, end) in rows.items():
        print(f"{name:<18}{ape:>12.4f}{end:>13.4f}{100 * end / path_len:>15.3f}%")
    print(
        f"cost {result.initial_cost:.6g} -> {result.final_cost:.6g} in {result.iterations} iterations "
        f"[{result.status.value}], {t_total:.2f} s total including JIT compilation"
    )
    stamps = sim.timestamps
    write_tum(out / "ground_truth_tum.txt", Trajectory(stamps, SE3(jnp.asarray(gt))))
    write_tum(out / "odometry_tum.txt", Trajectory(stamps, SE3(jnp.asarray(chained))))
    write_tum(out / "trajectory_tum.txt", Trajectory(stamps, SE3(jnp.asarray(opt))))
    write_g2o(out / "graph_optimised.g2o", graph.with_values(result.values))
    metrics = {
        "keyframes": len(ids),
        "odometry_factors": int((~sim.is_loop).sum()),
        "loop_factors": int(sim.is_loop.sum()),
        "path_length_m": path_len,
        "initial_cost": result.initial_cost,
        "final_cost": result.final_cost,
        "iterations": result.iterations,
        "status": result.status.value,
        "runtime_s": t_total,
        "ape_rmse_m": {k: v[1] for k, v in rows.items()},
        "end_error_m": {k: v[2] for k, v in rows.items()},
        "note": "APE without alignment: the first pose is anchored at ground truth",
    }
    (out / "metrics.json").write_text(json.dumps(metrics, indent=2))
    fig, ax = plt.subplots(2, 1, figsize=(11, 7), gridspec_kw={"height_ratios": [1, 1.3]})
    for name, arr, style in [
        ("ground truth", gt, "k-"),
        ("chained odometry", chained, "r--"),
        ("jaxslam LM", opt, "b-"),
    ]:
        ax[0].plot(arr[:, 4], arr[:, 5], style, label=name, lw=1.2)
    for i, j in zip(sim.edges_i[sim.is_loop], sim.edges_j[sim.is_loop]):
        ax[0].plot(gt[[i, j], 4], gt[[i, j], 5], color="0.7", lw=0.5)
    ax[0].set_aspect("equal")
    ax[0].set_xlabel("x m")
    ax[0].set_ylabel("y m")
    ax[0].set_title("top view (grey: loop closures)")
    ax[0].legend(loc="best", fontsize=8)
    dist = np.concatenate([[0], np.cumsum(np.linalg.norm(np.diff(gt[:, 4:], axis=0), axis=1))])
    for name, arr, style in [("chained odometry", chained, "r--"), ("jaxslam LM", opt, "b-")]:
        ax[1].plot(dist, np.linalg.norm(arr[:, 4:] - gt[:, 4:], axis=1), style, label=name)
    ax[1].set_xlabel("distance travelled m")
    ax[1].set_ylabel("position error m")
    ax[1].set_title("error along the path")
    ax[1].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(out / "trajectory.png", dpi=110)
    plt.close(fig)
    print(
        f"wrote {out}/: trajectory_tum.txt, odometry_tum.txt, ground_truth_tum.txt, graph_optimised.g2o, "
        "metrics.json, trajectory.png"
    )
    return 0 if result.success else 2


def build_parser() -> argparse.ArgumentParser:
    from . import __version__

    p = argparse.ArgumentParser(prog="jaxslam", description="JAX differentiable SLAM for low-light tunnels")
    p.add_argument("--version", action="version", version=f"jaxslam {__version__}")
    p.add_argument("--debug", action="store_true", help="show tracebacks instead of one-line errors")
    sub = p.add_subparsers(dest="command", required=True)

    o = sub.add_parser("optimize", help="optimise a pose graph file (g2o / GTSAM text) and write the result")
    o.add_argument("input", help="pose graph: .g2o, or GTSAM's .graph / EDGE3 .txt")
    o.add_argument(
        "-o",
        "--output",
        help="write the optimised graph at full float64 precision: GTSAM text format (VERTEX3/EDGE3 or "
        "VERTEX2/EDGE2) for a .txt or .graph name, else g2o",
    )
    o.add_argument("--solver", choices=["lm", "gn"], default="lm", help="Levenberg-Marquardt (default) or Gauss-Newton")
    o.add_argument(
        "--init",
        choices=["file", "chordal"],
        default="file",
        help="initial values: as in the file (or chained odometry), or chordal relaxation",
    )
    o.add_argument(
        "--robust",
        metavar="KERNEL[:K]",
        help="robust kernel on every edge: huber, cauchy, geman-mcclure, tukey (e.g. cauchy:1.0)",
    )
    o.add_argument("--linear-solver", default="auto", choices=["auto", "pardiso", "cholmod", "splu", "pcg"])
    o.add_argument("--max-iterations", type=int, default=100)
    o.add_argument("--json", metavar="PATH", help="also write the summary as JSON")
    o.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    o.set_defaults(func=cmd_optimize)

    d = sub.add_parser("demo-graph", help="a synthetic tunnel pose graph with loop closures, optimised and plotted")
    d.add_argument("-o", "--output", default="runs/demo-graph", help="results folder (default runs/demo-graph)")
    d.add_argument("--seed", type=int, default=0)
    d.add_argument("--length", type=float, default=60.0, help="path length in metres (out and back)")
    d.set_defaults(func=cmd_demo)

    e = sub.add_parser("enhance", help="enhance low-light images (ABA-CLAHE, CLAHE, HE, gamma); writes PNGs")
    e.add_argument("input", help="an image file or a folder of images")
    e.add_argument("-o", "--output", required=True, help="output PNG (file input) or folder (same-named PNGs)")
    e.add_argument("--method", choices=["aba-clahe", "clahe", "he", "gamma"], default="aba-clahe")
    e.add_argument("--alpha", type=float, default=0.25, help="ABA exponent for the mid-grey share (eq. 2)")
    e.add_argument("--beta", type=float, default=0.4, help="ABA exponent for the rest (eq. 2)")
    e.add_argument("--clip", type=float, default=2.0, help="CLAHE clip limit (OpenCV semantics)")
    e.add_argument("--gamma", type=float, default=0.5, help="exponent of --method gamma")
    e.set_defaults(func=cmd_enhance)
    __import__("jaxslam.sim._cli", fromlist=["register"]).register(sub)
    __import__("jaxslam.vision._features_cli", fromlist=["register"]).register(sub)
    __import__("jaxslam.vision._vo_cli", fromlist=["register"]).register(sub)
    __import__("jaxslam.eval._cli", fromlist=["register"]).register(sub)
    __import__("jaxslam.pipeline._cli", fromlist=["register"]).register(sub)
    __import__("jaxslam.tune._cli", fromlist=["register"]).register(sub)
    return p


def cmd_enhance(args: argparse.Namespace) -> int:
    """Enhance one image or every image of a folder (8-bit grey or RGB) and write PNGs."""
    import numpy as np
    from PIL import Image, UnidentifiedImageError

    from .errors import InputFormatError
    from .vision import aba_clahe, clahe, equalize_hist, gamma_correct

    methods = {
        "aba-clahe": lambda im: aba_clahe(im, args.alpha, args.beta, args.clip),
        "clahe": lambda im: clahe(im, args.clip),
        "he": equalize_hist,
        "gamma": lambda im: gamma_correct(im, args.gamma),
    }
    src, out = Path(args.input), Path(args.output)
    if src.is_dir():
        exts = {".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff"}
        pairs = [(f, out / (f.stem + ".png")) for f in sorted(src.iterdir()) if f.suffix.lower() in exts]
        if not pairs:
            raise InputFormatError("no images (.png .jpg .bmp .tif) in the folder", src)
        out.mkdir(parents=True, exist_ok=True)
    elif src.exists():
        pairs = [(src, out / (src.stem + ".png") if out.is_dir() else out)]
    else:
        raise InputFormatError("no such file or folder", src)
    failed = 0
    for f, dst in pairs:
        try:
            with Image.open(f) as im:
                arr = np.asarray(im.convert("L" if im.mode in ("L", "1", "I;16", "I", "F") else "RGB"))
            res = np.asarray(methods[args.method](arr))
            Image.fromarray(res).save(dst)
        except (UnidentifiedImageError, OSError, ValueError) as exc:
            print(f"jaxslam enhance: error: {f}: {exc}", file=sys.stderr)
            failed += 1
    print(f"enhanced {len(pairs) - failed}/{len(pairs)} image(s) with {args.method} -> {out}")
    return 1 if failed else 0


def enable_compilation_cache() -> str | None:
    """Keep JAX's compiled programs on disk between runs (``$JAXSLAM_CACHE_DIR``, default
    ``~/.cache/jaxslam/jax``; set it to an empty string to disable), so a second run of a
    command on a graph of the same size classes skips JIT compilation."""
    import os

    import jax

    path = os.environ.get("JAXSLAM_CACHE_DIR", str(Path.home() / ".cache" / "jaxslam" / "jax"))
    if not path:
        return None
    try:
        Path(path).mkdir(parents=True, exist_ok=True)
    except OSError:
        return None
    jax.config.update("jax_compilation_cache_dir", path)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    return path


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    enable_compilation_cache()
    func: Callable[[argparse.Namespace], int] = args.func
    if args.debug:
        return func(args)
    try:
        return func(args)
    except JaxSlamError as exc:
        print(f"jaxslam {args.command}: error: {exc}", file=sys.stderr)
        return 1
    except (OSError, ValueError) as exc:
        print(f"jaxslam {args.command}: error: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print(f"jaxslam {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())

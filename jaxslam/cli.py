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


def _robust_kernel(spec: str | None):  # noqa: ANN202
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


def initial_values_for(graph, init: str):  # noqa: ANN001, ANN201
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

    t0 = time.perf_counter()
    graph = read_g2o(args.input)
    robust = _robust_kernel(args.robust)
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
    with tqdm(total=args.max_iterations, desc=f"{args.solver.upper()}", unit="it", disable=args.quiet,
              file=sys.stderr, leave=False) as bar:

        def progress(it: int, cost: float) -> None:
            bar.n = it
            bar.set_postfix(cost=f"{cost:.6g}")
            bar.refresh()

        result = solver.solve(callback=progress)
    out_graph = graph.with_values(result.values)
    if args.output:
        write_g2o(args.output, out_graph)
    summary = {
        "input": str(args.input),
        "vertices": int(len(graph.vertex_ids)),
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
    gauge = "" if not solver.gauge_free and graph.fixed.size else " (gauge fixed at the first vertex)"
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


def build_parser() -> argparse.ArgumentParser:
    from . import __version__

    p = argparse.ArgumentParser(prog="jaxslam", description="JAX differentiable SLAM for low-light tunnels")
    p.add_argument("--version", action="version", version=f"jaxslam {__version__}")
    p.add_argument("--debug", action="store_true", help="show tracebacks instead of one-line errors")
    sub = p.add_subparsers(dest="command", required=True)

    o = sub.add_parser("optimize", help="optimise a pose graph file (g2o / GTSAM text) and write the result")
    o.add_argument("input", help="pose graph: .g2o, or GTSAM's .graph / EDGE3 .txt")
    o.add_argument("-o", "--output", help="write the optimised graph (g2o, full float64 precision)")
    o.add_argument("--solver", choices=["lm", "gn"], default="lm", help="Levenberg-Marquardt (default) or Gauss-Newton")
    o.add_argument("--init", choices=["file", "chordal"], default="file",
                   help="initial values: as in the file (or chained odometry), or chordal relaxation")
    o.add_argument("--robust", metavar="KERNEL[:K]",
                   help="robust kernel on every edge: huber, cauchy, geman-mcclure, tukey (e.g. cauchy:1.0)")
    o.add_argument("--linear-solver", default="auto", choices=["auto", "pardiso", "cholmod", "splu", "pcg"])
    o.add_argument("--max-iterations", type=int, default=100)
    o.add_argument("--json", metavar="PATH", help="also write the summary as JSON")
    o.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    o.set_defaults(func=cmd_optimize)
    return p


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
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

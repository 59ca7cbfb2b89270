"""Pose-graph optimisation, jaxslam vs GTSAM, same graphs, same process run.

    python benchmarks/pose_graph.py FILE... [--json PATH] [--repeat 3]

For every file: the graph is read once by jaxslam (g2o or GTSAM text; edges-only files are
initialised by chaining odometry), a prior (sigma 1e-6) holds the first vertex, and the
*identical* graph is handed to GTSAM through ``jaxslam.interop.gtsam``. Then:

* ours GN and LM, from the file's initial values: compile time (first call minus a steady
  run) reported apart from steady-state time (best of ``--repeat``);
* GTSAM GN and LM (default parameters, as users run them) from the same values;
* every final cost is GTSAM's ``graph.error`` of the returned values (ours re-evaluated by
  GTSAM, so the comparison uses one cost function);
* ours LM from the chordal initialisation (``ours_chordal``), with the initialisation time
  included in ``time_s``;
* the time of one Gauss-Newton iteration (linearise + factorise + solve + update) for both,
  measured as total GN time / iterations with a fixed iteration count.

JSON: a list, one object per file: ``{"file", "ours": {"gn": R, "lm": R}, "gtsam": {"gn": R,
"lm": R}, ...}`` with ``R = {"initial_cost", "final_cost", "iterations", "time_s",
"compile_s"}`` and extras (``ours_chordal``, ``gn_iteration_ms``, ratios).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import jaxslam
from jaxslam.cli import initial_values_for
from jaxslam.core import Gaussian
from jaxslam.factors import PriorFactor
from jaxslam.interop.gtsam import to_gtsam, values_to_gtsam
from jaxslam.io import read_g2o
from jaxslam.solvers import Solver, SolverConfig


def _resolve(name: str) -> str:
    if Path(name).exists():
        return name
    import gtsam

    return gtsam.findExampleDataFile(name)


def _anchor(graph) -> list:
    """The graph's factors plus a prior on the first vertex (if the file fixes none)."""
    factors = list(graph.factors)
    if graph.fixed.size == 0:
        vt = graph.var_type
        first = vt(graph.vertex_ids[:1])
        factors.append(PriorFactor.create(first, graph.values.get(first), Gaussian.isotropic(vt.tangent_dim, 1e-6)))
    return factors


def run_ours(factors, values, gt_graph, method: str, repeat: int, max_iterations: int, linear_solver: str) -> dict:
    cfg = SolverConfig(method=method, max_iterations=max_iterations, linear_solver=linear_solver)
    t0 = time.perf_counter()
    solver = Solver(factors, values, cfg)
    analyse = time.perf_counter() - t0
    t0 = time.perf_counter()
    first = solver.solve()
    t_first = time.perf_counter() - t0
    times = []
    res = first
    for _ in range(repeat):
        t0 = time.perf_counter()
        r = solver.solve()
        times.append(time.perf_counter() - t0)
        if times[-1] == min(times):
            res = r
    steady = min(times)
    final = gt_graph.error(values_to_gtsam(res.values))
    return {
        "initial_cost": float(gt_graph.error(values_to_gtsam(values))),
        "final_cost": float(final),
        "final_cost_ours": res.final_cost,
        "iterations": res.iterations,
        "linear_solves": res.linear_solves,
        "time_s": steady,
        "compile_s": max(t_first - steady, 0.0),
        "analysis_s": analyse,
        "status": res.status.value,
        "linear_solver": solver.system.method,
        "values": res.values,
        "solver": solver,
        "result": res,
    }


def run_gtsam(gt_graph, gt_initial, method: str, repeat: int, max_iterations: int | None = None) -> dict:
    import gtsam

    times = []
    for _ in range(repeat):
        if method == "gn":
            p = gtsam.GaussNewtonParams()
            if max_iterations:
                p.setMaxIterations(max_iterations)
            opt = gtsam.GaussNewtonOptimizer(gt_graph, gt_initial, p)
        else:
            p = gtsam.LevenbergMarquardtParams()
            if max_iterations:
                p.setMaxIterations(max_iterations)
            opt = gtsam.LevenbergMarquardtOptimizer(gt_graph, gt_initial, p)
        t0 = time.perf_counter()
        result = opt.optimize()
        times.append(time.perf_counter() - t0)
    return {
        "initial_cost": float(gt_graph.error(gt_initial)),
        "final_cost": float(gt_graph.error(result)),
        "iterations": int(opt.iterations()),
        "time_s": min(times),
        "compile_s": 0.0,
        "result": result,
    }


def gn_iteration_ms(solver: Solver, values, gt_graph, gt_initial, n: int, repeat: int) -> tuple[float, float]:
    """Time per GN iteration, both libraries, with exactly ``n`` iterations (no early stop)."""
    import dataclasses

    import gtsam

    s = Solver.__new__(Solver)
    s.__dict__.update(solver.__dict__)
    s.config = dataclasses.replace(
        solver.config, method="gn", max_iterations=n, relative_tol=0.0, absolute_tol=0.0, step_tol=0.0
    )
    s.solve(values)
    ours = min(_timed(lambda: s.solve(values)) for _ in range(repeat)) / n
    p = gtsam.GaussNewtonParams()
    p.setMaxIterations(n)
    p.setRelativeErrorTol(0.0)
    p.setAbsoluteErrorTol(0.0)
    p.setErrorTol(0.0)
    theirs = (
        min(_timed(lambda: gtsam.GaussNewtonOptimizer(gt_graph, gt_initial, p).optimize()) for _ in range(repeat)) / n
    )
    return ours * 1e3, theirs * 1e3


def _timed(fn) -> float:
    t0 = time.perf_counter()
    fn()
    return time.perf_counter() - t0


def _strip(r: dict) -> dict:
    return {k: v for k, v in r.items() if k not in ("values", "solver", "result")}


def bench_file(path: str, repeat: int, linear_solver: str, gn_iters: int) -> dict:
    graph = read_g2o(path)
    factors = _anchor(graph)
    values = graph.values
    gt_graph, gt_initial = to_gtsam(factors, values)
    out: dict = {
        "file": Path(path).name,
        "vertices": len(graph.vertex_ids),
        "edges": graph.num_edges,
        "dim": graph.dim,
        "initialised_from": graph.initialised_from,
    }
    gn = run_ours(factors, values, gt_graph, "gn", repeat, 100, linear_solver)
    lm = run_ours(factors, values, gt_graph, "lm", repeat, 200, linear_solver)
    g_gn = run_gtsam(gt_graph, gt_initial, "gn", repeat)
    g_lm = run_gtsam(gt_graph, gt_initial, "lm", repeat)
    out["ours"] = {"gn": _strip(gn), "lm": _strip(lm)}
    out["gtsam"] = {"gn": _strip(g_gn), "lm": _strip(g_lm)}

    # chordal initialisation + LM (init time included)
    t0 = time.perf_counter()
    v_ch = initial_values_for(graph, "chordal")
    t_init = time.perf_counter() - t0
    ch = run_ours(factors, v_ch, gt_graph, "lm", repeat, 200, linear_solver)
    ch["init_s"] = t_init
    ch["time_s"] += t_init
    out["ours_chordal"] = {"lm": _strip(ch)}

    ours_ms, gtsam_ms = gn_iteration_ms(gn["solver"], values, gt_graph, gt_initial, gn_iters, repeat)
    out["gn_iteration_ms"] = {"ours": ours_ms, "gtsam": gtsam_ms, "ratio": ours_ms / gtsam_ms}
    # Time to reach GTSAM LM's final cost, from each route's recorded cost history (the
    # chordal route includes its initialisation time).
    target = g_lm["final_cost"] * (1 + 1e-6)
    routes = {
        "lm": (lm["result"].time_to_reach(target), 0.0),
        "chordal+lm": (ch["result"].time_to_reach(target), t_init),
    }
    reached = {k: t + extra for k, (t, extra) in routes.items() if t is not None}
    best = min(reached, key=reached.get) if reached else None
    out["reach_gtsam_lm_cost"] = {
        "target": g_lm["final_cost"],
        "ours_route": best,
        "ours_time_s": reached.get(best) if best else None,
        "per_route_s": reached,
        "gtsam_lm_time_s": g_lm["time_s"],
        "ratio": reached[best] / g_lm["time_s"] if best else None,
    }
    ref = g_lm["final_cost"]
    out["lm_final_vs_gtsam_rel"] = (lm["final_cost"] - ref) / ref
    out["chordal_final_vs_gtsam_rel"] = (ch["final_cost"] - ref) / ref
    return out


def print_table(rows: list[dict]) -> None:
    hdr = (
        f"{'file':<22}{'solver':<16}{'initial':>14}{'final (GTSAM eval)':>20}{'iters':>7}{'time s':>9}{'compile s':>10}"
    )
    print(hdr)
    print("-" * len(hdr))
    for r in rows:
        entries = [
            ("ours GN", r["ours"]["gn"]),
            ("ours LM", r["ours"]["lm"]),
            ("ours chordal+LM", r["ours_chordal"]["lm"]),
            ("GTSAM GN", r["gtsam"]["gn"]),
            ("GTSAM LM", r["gtsam"]["lm"]),
        ]
        for name, e in entries:
            print(
                f"{r['file']:<22}{name:<16}{e['initial_cost']:>14.6g}{e['final_cost']:>20.10g}{e['iterations']:>7}"
                f"{e['time_s']:>9.3f}{e['compile_s']:>10.2f}"
            )
        g = r["gn_iteration_ms"]
        reach = r["reach_gtsam_lm_cost"]
        ratio = "not reached" if reach["ratio"] is None else f"{reach['ratio']:.3f} via {reach['ours_route']}"
        print(
            f"  GN iteration: ours {g['ours']:.1f} ms, GTSAM {g['gtsam']:.1f} ms, ratio {g['ratio']:.2f}; "
            f"time to GTSAM LM's final cost / GTSAM LM time: {ratio}; "
            f"LM final vs GTSAM LM: {r['lm_final_vs_gtsam_rel']:+.2e} rel, "
            f"chordal+LM: {r['chordal_final_vs_gtsam_rel']:+.2e} rel"
        )
        print()


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("files", nargs="+", help="pose-graph files (a bare name is looked up in GTSAM's Data/)")
    ap.add_argument("--json", help="write the results as JSON")
    ap.add_argument("--repeat", type=int, default=3, help="steady-state runs; the best is reported")
    ap.add_argument("--linear-solver", default="auto")
    ap.add_argument("--gn-iterations", type=int, default=5, help="fixed iteration count for the per-iteration time")
    args = ap.parse_args()
    rows = []
    for f in args.files:
        path = _resolve(f)
        print(f"# {path}", flush=True)
        rows.append(bench_file(path, args.repeat, args.linear_solver, args.gn_iterations))
    print()
    print(f"jaxslam {jaxslam.__version__}, {platform.processor() or platform.machine()}, {os.cpu_count()} CPUs")
    print_table(rows)
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=2))
        print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""The Gauss-Newton linear step, backend by backend, against GTSAM's elimination.

    python benchmarks/linear_solvers.py [FILE] [--json PATH] [--repeat 5]

One normal-equation system ``H delta = -g`` (the first GN step of FILE, default
``../shared/data/posegraph/sphere2500.g2o`` plus a prior on the first pose) is solved by every
available jaxslam backend with its symbolic analysis reused (numeric factorisation + solve,
best of ``--repeat``), and by GTSAM's ``GaussianFactorGraph.optimize()`` on the same
linearisation (ordering + elimination + back-substitution, as each GTSAM GN iteration does).
Also reports jaxslam's linearisation + assembly time and the steps' agreement. PARDISO uses
MKL's thread count; run with ``MKL_NUM_THREADS=1`` to measure one thread.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from pose_graph import _anchor, _resolve

from jaxslam.interop.gtsam import to_gtsam
from jaxslam.io import read_g2o
from jaxslam.solvers import Solver, SolverConfig, available_linear_solvers

DEFAULT = str(Path(__file__).resolve().parents[2] / "shared" / "data" / "posegraph" / "sphere2500.g2o")


def best(fn, repeat: int) -> float:
    fn()
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return min(times)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("file", nargs="?", default=DEFAULT)
    ap.add_argument("--json")
    ap.add_argument("--repeat", type=int, default=5)
    args = ap.parse_args()
    graph = read_g2o(_resolve(args.file))
    factors = _anchor(graph)
    out: dict = {"file": Path(args.file).name, "ms": {}}
    steps = {}
    for ls in available_linear_solvers():
        s = Solver(factors, graph.values, SolverConfig(linear_solver=ls))
        params = s.problem.pad_values(graph.values)
        h, g, _ = s.linearize(params)
        if ls == available_linear_solvers()[0]:
            out["ndof"], out["nnz_lower"] = s.problem.ndof, s.problem.nnz
            out["ms"]["linearize_assemble"] = 1e3 * best(lambda s=s, p=params: s.linearize(p), args.repeat)
        steps[ls] = s.system.solve(h, -g)
        reps = 1 if ls in ("splu", "pcg") else args.repeat
        out["ms"][ls] = 1e3 * best(lambda s=s, h=h, g=g: s.system.solve(h, -g), reps)
    ref = steps.get("splu")
    out["max_rel_step_diff"] = {
        k: float(np.abs(v - ref).max() / np.abs(ref).max())
        for k, v in steps.items()
        if ref is not None and v is not None
    }
    gt_graph, gt_values = to_gtsam(factors, graph.values)
    lin = gt_graph.linearize(gt_values)
    out["ms"]["gtsam_linearize"] = 1e3 * best(lambda: gt_graph.linearize(gt_values), args.repeat)
    out["ms"]["gtsam_eliminate_solve"] = 1e3 * best(lambda: lin.optimize(), args.repeat)
    print(f"{out['file']}: {out.get('ndof')} unknowns, {out.get('nnz_lower')} nonzeros in the lower triangle of H")
    for k, v in out["ms"].items():
        print(f"  {k:<24}{v:>10.1f} ms")
    print("  step agreement vs SuperLU:", {k: f"{v:.1e}" for k, v in out["max_rel_step_diff"].items()})
    if args.json:
        Path(args.json).write_text(json.dumps(out, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Gradients through the optimum (issue 7): backward cost vs forward solve, and accuracy.

    python benchmarks/implicit.py --json runs/implicit.json
    python benchmarks/implicit.py --poses 200 --fd            # quick, with the FD check

Synthetic tunnel pose graphs (``jaxslam.sim.tunnel_pose_graph``: odometry + loop closures,
Cauchy kernel on the loops) of several sizes. Parameters ``theta``: log-sigmas (rotation,
translation) of odometry and loops, and the Cauchy scale. Loss: mean squared position error
against ground truth. For each size, in one process:

* **forward (cold)**: Gauss-Newton from dead reckoning to tight tolerances (+ the Newton
  polish the adjoint needs), steady state (after compilation), median of ``--repeat``;
* **forward (warm)**: the same after a small change of ``theta`` (a learning step);
* **backward**: the adjoint, ``exact`` (CG on the exact Hessian, preconditioned by the
  Gauss-Newton Cholesky) and ``gauss-newton``; its CG iterations;
* **GTSAM (anchor)**: ``gtsam.LevenbergMarquardtOptimizer`` on the same graph from the same
  initial values, to place the forward time (GTSAM has no backward pass);
* JIT compile time (the first forward + backward) apart;
* ``--fd``: central finite differences of re-solved optima on every parameter.

Prints a table and the ratio backward / forward; ``--json`` writes the rows.
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from pathlib import Path
from typing import Any


def build(poses: int, seed: int = 0):
    import jax.numpy as jnp
    import numpy as np

    from jaxslam.core import Cauchy, Gaussian, Pose3Var, Values
    from jaxslam.factors import BetweenFactor, PriorFactor
    from jaxslam.lie import SE3
    from jaxslam.sim import tunnel_pose_graph

    g = tunnel_pose_graph(length=poses * 0.5, step=0.5, seed=seed)
    n = len(g.ground_truth)
    odo = ~g.is_loop

    def factor_fn(theta):
        prior = PriorFactor.create(
            Pose3Var(np.array([0])), SE3(jnp.asarray(g.ground_truth[:1])), Gaussian.diagonal(jnp.full(6, 1e-3))
        )
        fs = [prior]
        for mask, key in ((odo, "odo"), (g.is_loop, "loop")):
            ls = theta[key]
            sig = jnp.concatenate([jnp.full(3, jnp.exp(ls[0])), jnp.full(3, jnp.exp(ls[1]))])
            fs.append(
                BetweenFactor.create(
                    Pose3Var(g.edges_i[mask]),
                    Pose3Var(g.edges_j[mask]),
                    SE3(jnp.asarray(g.measured[mask])),
                    Gaussian.diagonal(sig, n=int(mask.sum())),
                    robust=Cauchy(theta["k"]) if key == "loop" else None,
                )
            )
        return fs

    theta = {"odo": jnp.log(jnp.array([0.004, 0.01])), "loop": jnp.log(jnp.array([0.01, 0.03])), "k": jnp.asarray(1.0)}
    init = [SE3(jnp.asarray(g.ground_truth[:1]))]
    for m in g.measured[odo]:
        init.append(init[-1].compose(SE3(jnp.asarray(m[None]))))
    values = Values.create({Pose3Var(np.arange(n)): SE3(jnp.concatenate([x.params for x in init]))})
    target = jnp.asarray(g.ground_truth[:, 4:])

    def loss_of(x):
        p = x.params(Pose3Var)[:, 4:]
        return jnp.mean(jnp.sum((p - target) ** 2, axis=1))

    return factor_fn, values, theta, loss_of, len(g.edges_i)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--poses", type=int, nargs="+", default=[200, 1000, 4000])
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--fd", action="store_true", help="finite-difference check (2 solves per parameter)")
    ap.add_argument("--json", metavar="PATH")
    args = ap.parse_args()

    import jax
    import jax.flatten_util
    import numpy as np

    from jaxslam.tune import DifferentiableSolver, ImplicitConfig

    rows: list[dict[str, Any]] = []
    for n in args.poses:
        factor_fn, values, theta, loss_of, edges = build(n)
        row: dict[str, Any] = {"poses": n, "edges": edges}
        for mode in ("exact", "gauss-newton"):
            ds = DifferentiableSolver(factor_fn, values, theta, ImplicitConfig(adjoint=mode))
            f = jax.value_and_grad(lambda th, d=ds, lf=loss_of: lf(d(th)))
            t0 = time.perf_counter()
            _, g0 = f(theta)
            compile_s = time.perf_counter() - t0
            cold, warm, back, cg = [], [], [], []
            for r in range(args.repeat):
                ds.reset()
                th = jax.tree_util.tree_map(lambda a, r=r: a * (1 + 1e-3 * r), theta)
                f(th)
                cold.append(ds.forward_time_s)
                back.append(ds.backward.time_s)
                cg.append(ds.backward.cg_iterations)
                th2 = jax.tree_util.tree_map(lambda a: a * (1 + 1e-2), th)  # a learning step
                f(th2)
                warm.append(ds.forward_time_s)
            row[mode] = {
                "compile_s": compile_s,
                "forward_cold_s": statistics.median(cold),
                "forward_warm_s": statistics.median(warm),
                "backward_s": statistics.median(back),
                "cg_iterations": statistics.median(cg),
                "backward_over_forward_cold": statistics.median(back) / statistics.median(cold),
                "backward_over_forward_warm": statistics.median(back) / statistics.median(warm),
            }
            if mode == "exact":
                grad_exact = np.asarray(jax.flatten_util.ravel_pytree(g0)[0])
            else:
                grad_gn = np.asarray(jax.flatten_util.ravel_pytree(g0)[0])
        row["gauss_newton_adjoint_rel_error"] = float(np.max(np.abs(grad_gn - grad_exact)) / np.max(np.abs(grad_exact)))
        try:
            import gtsam

            from jaxslam.interop.gtsam import to_gtsam

            graph, init = to_gtsam(factor_fn(theta), values)
            ts = []
            for _ in range(args.repeat):
                params = gtsam.LevenbergMarquardtParams()
                params.setRelativeErrorTol(1e-12)
                params.setAbsoluteErrorTol(1e-15)
                params.setMaxIterations(100)
                t0 = time.perf_counter()
                gtsam.LevenbergMarquardtOptimizer(graph, init, params).optimize()
                ts.append(time.perf_counter() - t0)
            row["gtsam_lm_forward_s"] = statistics.median(ts)
        except ImportError:
            row["gtsam_lm_forward_s"] = None
        if args.fd:
            ds = DifferentiableSolver(factor_fn, values, theta)
            flat, unravel = jax.flatten_util.ravel_pytree(theta)
            fd = np.zeros(len(flat))
            h = 1e-5
            for i in range(len(flat)):
                e = np.zeros(len(flat))
                e[i] = h
                lp = float(loss_of(ds.solve(unravel(flat + e))))
                lm = float(loss_of(ds.solve(unravel(flat - e))))
                fd[i] = (lp - lm) / (2 * h)
            row["fd_max_rel_error"] = float(np.max(np.abs(grad_exact - fd)) / np.max(np.abs(fd)))
        rows.append(row)
        e, gn = row["exact"], row["gauss-newton"]
        print(
            f"{n:>5} poses {edges:>5} edges | compile {e['compile_s']:6.1f} s | "
            f"forward cold {e['forward_cold_s']:.3f} s "
            f"warm {e['forward_warm_s']:.3f} s | backward exact {e['backward_s']:.3f} s ({e['cg_iterations']} CG) "
            f"GN {gn['backward_s']:.3f} s | backward/forward cold {e['backward_over_forward_cold']:.2f} "
            f"warm {e['backward_over_forward_warm']:.2f} | GTSAM LM {row['gtsam_lm_forward_s'] or float('nan'):.3f} s"
            + (f" | FD rel err {row['fd_max_rel_error']:.1e}" if args.fd else "")
            + f" | GN-adjoint rel err {row['gauss_newton_adjoint_rel_error']:.1e}",
            flush=True,
        )
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps(rows, indent=2) + "\n")
        print(f"wrote {args.json}")


if __name__ == "__main__":
    main()

"""Sharding the tuner's training sequences across JAX devices (issue 7).

    python benchmarks/tune_sharding.py [--host-devices 2] [--sequences 4] [--length 60] [--steps 8] [--json PATH]

``jaxslam.tune.tune_graphs`` evaluates the loss and its adjoint gradient on every training
graph at each step. With ``TuneConfig.devices`` > 1 the graphs are spread round-robin over
JAX devices, one host thread per device (:class:`jaxslam.tune.Shards`). This benchmark
times the same tuning on one device and on all of them, in one process, on graphs from
the simulator's tunnel (``jaxslam.tune.tunnel_capture``: odometry trusted 30x too much in
translation, position truth). With no accelerator, ``--host-devices N`` splits the CPU into
N XLA host devices (``XLA_FLAGS=--xla_force_host_platform_device_count``, set before JAX
starts); on a machine with GPUs, pass ``--host-devices 0`` to use them as they are.

The first evaluation of each configuration includes building the solvers and compiling
their kernels for its devices (reported apart); the steady state is the median time of the
evaluations after it (each a forward solve and an adjoint gradient on every graph). Checks that both give the same
loss history and weights (sums over sequences are taken in sequence order).
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--host-devices", type=int, default=2, help="XLA host (CPU) devices to create; 0: leave as is")
    ap.add_argument("--sequences", type=int, default=4, help="training graphs")
    ap.add_argument("--length", type=float, default=60.0, help="tunnel length (m, out and back)")
    ap.add_argument("--steps", type=int, default=8, help="L-BFGS-B evaluations after the first")
    ap.add_argument("--json", metavar="PATH")
    args = ap.parse_args()
    if args.host_devices:
        os.environ["XLA_FLAGS"] = (
            os.environ.get("XLA_FLAGS", "") + f" --xla_force_host_platform_device_count={args.host_devices}"
        )

    import jax
    import numpy as np

    import jaxslam  # noqa: F401  (float64)
    from jaxslam.tune import TuneConfig, tune_graphs, tunnel_capture

    devices = jax.local_devices()
    runs = [tunnel_capture(100 + s, 30.0, lever=(0.0, 0.0, 0.55), length=args.length) for s in range(args.sequences)]
    poses = [len(r.keyframes) for r in runs]
    print(f"{len(runs)} graphs of {poses} poses; JAX devices: {[str(d) for d in devices]}", flush=True)
    rows = {}
    for n in sorted({1, len(devices)}):
        stamps: list[float] = []
        t0 = time.perf_counter()
        cfg = TuneConfig(steps=args.steps, devices=n)
        res = tune_graphs(runs, cfg, lambda *_, s=stamps: s.append(time.perf_counter()))
        total = time.perf_counter() - t0
        steady = np.diff(stamps)  # evaluations after the first (which compiles the solvers' kernels)
        rows[n] = {
            "devices": n,
            "evaluations": len(res.history),
            "total_s": total,
            "first_evaluation_s": stamps[0] - t0,
            "evaluation_s_median": float(np.median(steady)),
            "evaluation_s_all": steady.tolist(),
            "history": res.history,
            "theta": res.theta.tolist(),
        }
        print(
            f"devices {n}: {len(res.history)} evaluations; steady state {1e3 * np.median(steady):.0f} ms each "
            f"(median), first {stamps[0] - t0:.1f} s (set-up + compile); "
            f"RMSE {np.sqrt(res.history[0]):.4f} -> {np.sqrt(min(res.history)):.4f} m",
            flush=True,
        )
    one, many = rows[1], rows[len(devices)]
    same = len(one["history"]) == len(many["history"]) and bool(
        np.allclose(one["history"], many["history"], rtol=1e-9, atol=0)
    )
    speedup = one["evaluation_s_median"] / many["evaluation_s_median"]
    print(f"speed-up with {len(devices)} devices: {speedup:.2f}x; same history and weights: {same}")
    if args.json:
        from jaxslam._machine import machine_info

        out = {
            "devices": [str(d) for d in devices],
            "host_devices": args.host_devices,
            "sequences": args.sequences,
            "poses": poses,
            "steps": args.steps,
            "runs": list(rows.values()),
            "speedup": speedup,
            "same_result": same,
            "machine": machine_info(),
        }
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps(out, indent=2) + "\n")
        print(f"wrote {args.json}")


if __name__ == "__main__":
    main()

"""IMU preintegration: jaxslam vs GTSAM 4.3.0 on the KITTI IMU stream shipped in the wheel.

    python benchmarks/imu_preintegration.py [--interval-s 0.1] [--repeats 20] [--json PATH]

The stream (``KittiEquivBiasedImu.txt``; noise sigmas from ``KittiEquivBiasedImu_metadata.txt``)
is cut into keyframe intervals of ``--interval-s`` seconds (each sample held until the next,
split at keyframes; :func:`jaxslam.factors.cut_imu_stream`). Both libraries integrate the same
(acc, gyro, dt) triples with the same non-zero bias estimate:

* accuracy: the largest relative difference over all intervals (``max|ours - gtsam| /
  max|gtsam|`` per interval and quantity) of dR, dv, dp, the bias Jacobians (GTSAM's, read
  through ``predict``, which is linear in the bias), the covariance ``preintMeasCov``, and the
  ImuFactor error vector and cost at random states with a perturbed bias;
* speed: samples per second of ``jaxslam.factors.preintegrate`` over all intervals at once
  (steady state; the first call's compile time is reported apart; a batch this large runs as
  equal parts on a thread pool, and the same batch in one call on one thread,
  ``parallel=False``, is timed beside it for reference) against
  ``PreintegratedImuMeasurements.integrateMeasurement`` in a Python loop (one PIM per interval,
  as GTSAM users write it), and their ratio. The two are timed in ``--rounds`` interleaved
  rounds (GTSAM's loop once, then ours ``--repeats / --rounds`` times), so that a machine
  whose speed drifts during the run (shared CPUs) slows both alike: the ratio reported is the
  median of the per-round ratios (ours: the round's median call), beside each side's median.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import gtsam
import jax

import jaxslam  # noqa: F401  (float64)
from jaxslam._machine import machine_info
from jaxslam.core import BiasVar, Pose3Var, VelocityVar, factor_cost
from jaxslam.factors import ImuFactor, PreintegrationParams, cut_imu_stream, preintegrate

TOLERANCE = 1e-9
GRAVITY = 9.81
BIAS_HAT = np.array([0.02, -0.03, 0.05, 1e-3, -2e-3, 5e-4])  # (acc m/s^2, gyro rad/s)


def load_kitti() -> tuple[np.ndarray, np.ndarray, np.ndarray, dict[str, float]]:
    """Time stamps (N,), acc (N, 3), gyro (N, 3) and the metadata sigmas. The first record
    is dropped: it lies 1.9 s before the second (a gap, not a sample period)."""
    data = np.loadtxt(gtsam.findExampleDataFile("KittiEquivBiasedImu.txt"), skiprows=1)
    meta_path = gtsam.findExampleDataFile("KittiEquivBiasedImu_metadata.txt")
    with open(meta_path, encoding="utf-8") as fh:
        names = fh.readline().split()
        values = [float(v) for v in fh.readline().split()]
    meta = dict(zip(names, values))
    return data[1:, 0], data[1:, 2:5], data[1:, 5:8], meta


def kitti_params(meta: dict[str, float]) -> PreintegrationParams:
    """jaxslam's parameters from the metadata sigmas (the same as :func:`gtsam_params`)."""
    return PreintegrationParams.from_gtsam_metadata(meta, GRAVITY)


def gtsam_params(meta: dict[str, float]) -> gtsam.PreintegrationParams:
    p = gtsam.PreintegrationParams.MakeSharedU(GRAVITY)
    p.setAccelerometerCovariance(np.eye(3) * meta["AccelerometerSigma"] ** 2)
    p.setGyroscopeCovariance(np.eye(3) * meta["GyroscopeSigma"] ** 2)
    p.setIntegrationCovariance(np.eye(3) * meta["IntegrationSigma"] ** 2)
    return p


def gtsam_loop(p: gtsam.PreintegrationParams, rows: list[tuple[list, list, list]]) -> list:
    bias = gtsam.imuBias.ConstantBias(BIAS_HAT[:3], BIAS_HAT[3:])
    pims = []
    for accs, gyros, dts in rows:
        pim = gtsam.PreintegratedImuMeasurements(p, bias)
        for a, w, d in zip(accs, gyros, dts):
            pim.integrateMeasurement(a, w, d)
        pims.append(pim)
    return pims


def gtsam_bias_jacobian(pim: gtsam.PreintegratedImuMeasurements, gravity: np.ndarray) -> np.ndarray:
    """GTSAM's d preintegrated / d bias (9x6). ``predict`` from the identity state returns
    the bias-corrected deltas plus gravity terms, and is affine in the bias, so unit bias
    steps give the columns exactly (up to rounding)."""
    dt = pim.deltaTij()

    def corrected(b: np.ndarray) -> np.ndarray:
        s = pim.predict(gtsam.NavState(), gtsam.imuBias.ConstantBias(b[:3], b[3:]))
        return np.concatenate(
            [gtsam.Rot3.Logmap(s.attitude()), s.position() - 0.5 * gravity * dt * dt, s.velocity() - gravity * dt]
        )

    base = corrected(BIAS_HAT)
    return np.stack([corrected(BIAS_HAT + np.eye(6)[j]) - base for j in range(6)], axis=1)


def rel_diff(ours: np.ndarray, ref: np.ndarray) -> float:
    """Largest over the leading axis of max|ours - ref| / max|ref|."""
    ours = np.asarray(ours).reshape(len(ref), -1)
    ref = np.asarray(ref).reshape(len(ref), -1)
    scale = np.maximum(np.abs(ref).max(axis=1), np.finfo(float).tiny)
    return float((np.abs(ours - ref).max(axis=1) / scale).max())


def random_states(rng: np.random.Generator, pims: list) -> tuple[list, np.ndarray, list, np.ndarray, np.ndarray]:
    """Random state i and bias; state j = GTSAM's prediction moved by a random error (0.3 rad,
    1 m, 1 m/s sigmas). Errors stay well below pi: near a rotation error of pi GTSAM's
    NavState::Logmap loses digits (1e-8 relative at pi - 8e-4 rad, against a 40-digit
    reference), while jaxslam's stays at 1e-15."""
    n = len(pims)
    poses_i = [gtsam.Pose3(gtsam.Rot3.Expmap(rng.normal(size=3)), rng.normal(size=3) * 5.0) for _ in range(n)]
    vel_i = rng.normal(size=(n, 3))
    bias_i = BIAS_HAT + 0.01 * rng.normal(size=(n, 6))
    poses_j, vel_j = [], []
    for k, pim in enumerate(pims):
        pred = pim.predict(
            gtsam.NavState(poses_i[k], vel_i[k]), gtsam.imuBias.ConstantBias(bias_i[k, :3], bias_i[k, 3:])
        )
        move = np.concatenate([0.3 * rng.normal(size=3), rng.normal(size=3)])
        poses_j.append(pred.pose().compose(gtsam.Pose3.Expmap(move)))
        vel_j.append(pred.velocity() + rng.normal(size=3))
    return poses_i, vel_i, poses_j, np.asarray(vel_j), bias_i


def pose_params(poses: list) -> np.ndarray:
    out = []
    for p in poses:
        q = p.rotation().toQuaternion()
        out.append([q.w(), q.x(), q.y(), q.z(), *p.translation()])
    return np.asarray(out)


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--interval-s", type=float, default=0.1, help="keyframe spacing, seconds")
    ap.add_argument("--repeats", type=int, default=20, help="timed calls of ours (after the first)")
    ap.add_argument("--rounds", type=int, default=5, help="interleaved rounds (one GTSAM loop each)")
    ap.add_argument("--json", type=Path, default=None, help="write the figures here")
    args = ap.parse_args(argv)

    t, acc, gyro, meta = load_kitti()
    kf = np.arange(t[0], t[-1], args.interval_s)
    t0 = time.perf_counter()
    iv = cut_imu_stream(t, acc, gyro, kf)
    cut_s = time.perf_counter() - t0
    n_int, n_samples = len(iv), iv.num_samples
    params = kitti_params(meta)

    # --- ours: compile, then steady state --------------------------------------------------
    t0 = time.perf_counter()
    ours = jax.block_until_ready(preintegrate(iv.acc, iv.gyro, iv.dt, params, bias_hat=BIAS_HAT, mask=iv.mask))
    first_s = time.perf_counter() - t0
    # --- GTSAM: the Python loop, interleaved with ours ------------------------------------------
    rows = []
    for k in range(n_int):
        m = iv.mask[k]
        rows.append((list(iv.acc[k][m]), list(iv.gyro[k][m]), iv.dt[k][m].tolist()))
    gp = gtsam_params(meta)
    gtsam_loop(gp, rows[:50])  # warm up
    rounds = max(1, args.rounds)
    per_round = max(1, -(-args.repeats // rounds))
    jax.block_until_ready(preintegrate(iv.acc, iv.gyro, iv.dt, params, BIAS_HAT, iv.mask, parallel=False))
    times, gtsam_times, round_ratios, one_call_t = [], [], [], []
    for _ in range(rounds):
        t0 = time.perf_counter()
        pims = gtsam_loop(gp, rows)
        gtsam_times.append(time.perf_counter() - t0)
        mine_t = []
        for _ in range(per_round):
            t0 = time.perf_counter()
            jax.block_until_ready(preintegrate(iv.acc, iv.gyro, iv.dt, params, bias_hat=BIAS_HAT, mask=iv.mask))
            mine_t.append(time.perf_counter() - t0)
            # the same batch kept in one call on this thread (parallel=False), for reference
            t0 = time.perf_counter()
            jax.block_until_ready(preintegrate(iv.acc, iv.gyro, iv.dt, params, BIAS_HAT, iv.mask, parallel=False))
            one_call_t.append(time.perf_counter() - t0)
        times += mine_t
        round_ratios.append(gtsam_times[-1] / float(np.median(mine_t)))
    ours_s = float(np.median(times))
    gtsam_s = float(np.median(gtsam_times))
    variant_is_tangent = bool(
        np.allclose(
            pims[0].preintMeasCov(),
            _first_with(gtsam.PreintegratedImuMeasurementsTangent, gp, rows[0]).preintMeasCov(),
            rtol=0,
            atol=0,
        )
    )

    # --- accuracy ------------------------------------------------------------------------------
    gravity = np.array([0.0, 0.0, -GRAVITY])
    ref = {
        "dR": np.stack([p.deltaRij().matrix() for p in pims]),
        "dv": np.stack([p.deltaVij() for p in pims]),
        "dp": np.stack([p.deltaPij() for p in pims]),
        "jacobians": np.stack([gtsam_bias_jacobian(p, gravity) for p in pims]),
        "covariance": np.stack([p.preintMeasCov() for p in pims]),
    }
    mine = {
        "dR": np.asarray(ours.delta_rotation.as_matrix()),
        "dv": np.asarray(ours.delta_velocity),
        "dp": np.asarray(ours.delta_position),
        "jacobians": np.asarray(ours.bias_jacobian),
        "covariance": np.asarray(ours.covariance),
    }
    diffs = {k: rel_diff(mine[k], ref[k]) for k in ref}

    rng = np.random.default_rng(0)
    pi, vi, pj, vj, bi = random_states(rng, pims)
    ids = np.arange(n_int)
    fac = ImuFactor.create(
        Pose3Var(ids), VelocityVar(ids), Pose3Var(ids + n_int), VelocityVar(ids + n_int), BiasVar(ids), ours, params
    )
    x = (pose_params(pi), vi, pose_params(pj), vj, bi)
    err = np.asarray(fac.evaluate(x))
    cost = np.asarray(factor_cost(fac, x))
    key_x, key_v, key_b = gtsam.symbol_shorthand.X, gtsam.symbol_shorthand.V, gtsam.symbol_shorthand.B
    g_err, g_cost = [], []
    for k, pim in enumerate(pims):
        f = gtsam.ImuFactor(key_x(0), key_v(0), key_x(1), key_v(1), key_b(0), pim)
        b = gtsam.imuBias.ConstantBias(bi[k, :3], bi[k, 3:])
        g_err.append(f.evaluateError(pi[k], vi[k], pj[k], vj[k], b))
        vals = gtsam.Values()
        vals.insert(key_x(0), pi[k])
        vals.insert(key_v(0), vi[k])
        vals.insert(key_x(1), pj[k])
        vals.insert(key_v(1), vj[k])
        vals.insert(key_b(0), b)
        g_cost.append([f.error(vals)])
    err_diff = rel_diff(err, np.stack(g_err))
    cost_diff = rel_diff(cost[:, None], np.asarray(g_cost))
    diffs["factor_error"] = max(err_diff, cost_diff)

    ours_rate = n_samples / ours_s
    gtsam_rate = n_samples / gtsam_s
    result = {
        "max_rel_diff": diffs,
        "ours_samples_per_s": ours_rate,
        "gtsam_samples_per_s": gtsam_rate,
        "ratio": float(np.median(round_ratios)),
        "ratio_of_medians": ours_rate / gtsam_rate,
        "round_ratios": round_ratios,
        "compile_s": first_s,
        "ours_steady_s": ours_s,
        "ours_steady_min_s": float(np.min(times)),
        "ours_one_call_s": float(np.median(one_call_t)),
        "gtsam_s": gtsam_s,
        "cut_s": cut_s,
        "factor_error_vector_rel_diff": err_diff,
        "factor_cost_rel_diff": cost_diff,
        "intervals": n_int,
        "samples": n_samples,
        "max_samples_per_interval": int(iv.dt.shape[1]),
        "interval_s": args.interval_s,
        "gtsam_variant": "tangent" if variant_is_tangent else "manifold?",
        "machine": machine_info(),
    }

    print(
        f"KITTI IMU: {n_samples} samples in {n_int} intervals of {args.interval_s} s "
        f"(max {iv.dt.shape[1]} per interval); GTSAM preintegration: {result['gtsam_variant']}"
    )
    print(f"{'quantity':<14}{'max rel diff':>14}{'tolerance':>12}  ok")
    for k, v in diffs.items():
        print(f"{k:<14}{v:>14.2e}{TOLERANCE:>12.0e}  {'yes' if v <= TOLERANCE else 'NO'}")
    print(f"{'':<14}{'samples/s':>14}{'time':>12}")
    print(f"{'jaxslam':<14}{ours_rate:>14.3e}{ours_s * 1e3:>10.2f}ms  (compile + first call {first_s:.2f} s)")
    one_s = result["ours_one_call_s"]
    print(f"{'  one call':<14}{n_samples / one_s:>14.3e}{one_s * 1e3:>10.2f}ms  (parallel=False: one thread)")
    print(f"{'gtsam loop':<14}{gtsam_rate:>14.3e}{gtsam_s * 1e3:>10.2f}ms")
    print(
        f"ratio jaxslam / gtsam: {result['ratio']:.1f}x (median of {rounds} interleaved rounds: "
        + ", ".join(f"{r:.1f}" for r in round_ratios)
        + f"; ratio of the medians {ours_rate / gtsam_rate:.1f}x)"
    )
    if args.json is not None:
        args.json.write_text(json.dumps(result, indent=2))
    return result


def _first_with(cls: type, p: gtsam.PreintegrationParams, row: tuple[list, list, list]):
    pim = cls(p, gtsam.imuBias.ConstantBias(BIAS_HAT[:3], BIAS_HAT[3:]))
    for a, w, d in zip(*row):
        pim.integrateMeasurement(a, w, d)
    return pim


if __name__ == "__main__":
    main()

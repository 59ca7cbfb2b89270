"""IMU preintegration on real data: EuRoC V1_01 against ground truth and against GTSAM.

    python benchmarks/euroc_imu.py [--windows 0.5 1 2] [--stride 1] [--json PATH] [--plot PATH]

Data (``../shared/data/euroc_V1_01``): the full 200 Hz IMU stream (``mav0/imu0/data.csv``) and
the ground-truth states of ``groundtruth_openvins/V1_01_easy.csv`` (20 Hz, at IMU stamps:
pose, velocity, gyro and accelerometer biases). Frames: ``mav0/imu0/sensor.yaml`` and
``mav0/state_groundtruth_estimate0/sensor.yaml`` both give ``T_BS = I``: the IMU frame *is*
the body frame and the ground-truth states are of that frame, in a z-up world (gravity
``(0, 0, -9.81)``); no extrinsic is applied (the script checks that both are the identity).

For windows of each length starting at every ``--stride``-th ground-truth row along the whole
run: start from the ground-truth state (pose, velocity, bias), preintegrate the IMU samples of
the window (each held until the next stamp; the windows start and end at IMU stamps) with the
ground-truth bias, predict the end state (:func:`jaxslam.factors.predict_imu_state`), and
compare with the ground truth there: position error (m), rotation error (deg, angle of
``R_gt^T R_pred``), velocity error (m/s). GTSAM's ``PreintegratedImuMeasurements`` +
``predict`` runs on the same windows in the same run; ours must equal it to ~1e-9.

``--original`` adds the same 1 s windows against ``V1_01_easy_original.txt`` (EuRoC's own
200 Hz ground truth, TUM format; velocity by central differences over +-50 ms, biases from the
csv). That file's attitude differs from the csv's by a nearly constant ~5.5 deg rotation on the
body side, and its gravity direction is what the IMU disagrees with (see the printed table).
"""

from __future__ import annotations

import argparse
import json
import re
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import jax
import jax.numpy as jnp

import jaxslam  # noqa: F401  (float64)
from jaxslam._machine import machine_info
from jaxslam.factors import PreintegrationParams, predict_imu_state, preintegrate
from jaxslam.lie import SE3, SO3

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "euroc_V1_01"
GRAVITY = 9.81
GT_PERIOD_NS = 50_000_000  # the csv's 20 Hz


# --------------------------------------------------------------------------------------------
# data
# --------------------------------------------------------------------------------------------


def _yaml_numbers(text: str, key: str) -> list[float]:
    m = re.search(rf"^\s*{key}\s*:\s*(\[[^\]]*\]|[-+0-9.eE]+)", text, re.MULTILINE)
    if m is None:
        raise SystemExit(f"no {key} in the sensor yaml")
    return [float(v) for v in re.findall(r"[-+]?[0-9.]+(?:[eE][-+]?[0-9]+)?", m.group(1))]


def _t_bs(path: Path) -> np.ndarray:
    text = path.read_text(encoding="utf-8")
    block = re.search(r"T_BS:.*?data:\s*(\[[^\]]*\])", text, re.DOTALL)
    if block is None:
        raise SystemExit(f"{path}: no T_BS")
    return np.array([float(v) for v in re.findall(r"[-+]?[0-9.]+(?:[eE][-+]?[0-9]+)?", block.group(1))]).reshape(4, 4)


def load_euroc(root: Path = DATA) -> dict[str, Any]:
    """IMU (ns stamps, acc, gyro), ground-truth rows (ns, pose params (qw qx qy qz x y z),
    velocity, bias (acc, gyro)), noise densities, and the two extrinsics (must be I)."""
    imu = np.loadtxt(root / "mav0/imu0/data.csv", delimiter=",", comments="#")
    imu_ns = np.loadtxt(root / "mav0/imu0/data.csv", delimiter=",", comments="#", usecols=0, dtype=np.int64)
    gt = np.loadtxt(root / "groundtruth_openvins/V1_01_easy.csv", delimiter=",", comments="#")
    gt_ns = np.loadtxt(
        root / "groundtruth_openvins/V1_01_easy.csv", delimiter=",", comments="#", usecols=0, dtype=np.int64
    )
    imu_yaml = (root / "mav0/imu0/sensor.yaml").read_text(encoding="utf-8")
    extrinsics = {
        "imu0": _t_bs(root / "mav0/imu0/sensor.yaml"),
        "state_groundtruth_estimate0": _t_bs(root / "mav0/state_groundtruth_estimate0/sensor.yaml"),
    }
    for name, t in extrinsics.items():
        if not np.allclose(t, np.eye(4)):
            raise SystemExit(f"{name} T_BS is not the identity: the frames need an extrinsic here\n{t}")
    noise = {
        k: _yaml_numbers(imu_yaml, k)[0]
        for k in (
            "gyroscope_noise_density",
            "gyroscope_random_walk",
            "accelerometer_noise_density",
            "accelerometer_random_walk",
        )
    }
    pose = gt[:, [4, 5, 6, 7, 1, 2, 3]]
    pose[:, :4] /= np.linalg.norm(pose[:, :4], axis=1, keepdims=True)  # printed to 6 digits: not unit
    return {
        "imu_ns": imu_ns,
        "gyro": imu[:, 1:4],
        "acc": imu[:, 4:7],
        "gt_ns": gt_ns,
        "pose": pose,
        "vel": gt[:, 8:11],
        "bias": np.concatenate([gt[:, 14:17], gt[:, 11:14]], axis=1),
        "noise": noise,
        "extrinsics": {k: v.tolist() for k, v in extrinsics.items()},
    }


def load_original(root: Path = DATA) -> tuple[np.ndarray, np.ndarray]:
    """EuRoC's own 200 Hz ground truth (TUM: t x y z qx qy qz qw): times (s), pose params."""
    o = np.loadtxt(root / "groundtruth_openvins/V1_01_easy_original.txt", comments="#")
    pose = o[:, [7, 4, 5, 6, 1, 2, 3]]
    pose[:, :4] /= np.linalg.norm(pose[:, :4], axis=1, keepdims=True)
    return o[:, 0], pose


def params_from(noise: dict[str, float]) -> PreintegrationParams:
    return PreintegrationParams.make_shared_u(
        GRAVITY,
        accelerometer_noise_density=noise["accelerometer_noise_density"],
        gyroscope_noise_density=noise["gyroscope_noise_density"],
        accelerometer_random_walk=noise["accelerometer_random_walk"],
        gyroscope_random_walk=noise["gyroscope_random_walk"],
    )


# --------------------------------------------------------------------------------------------
# windows
# --------------------------------------------------------------------------------------------


def _nearest(imu_ns: np.ndarray, ns: np.ndarray) -> np.ndarray:
    """Index of the IMU stamp of each ground-truth stamp (they differ by up to 256 ns of
    rounding in the files; more than 1 us is an error)."""
    j = np.clip(np.searchsorted(imu_ns, ns), 1, len(imu_ns) - 1)
    j = np.where(np.abs(imu_ns[j - 1] - ns) < np.abs(imu_ns[j] - ns), j - 1, j)
    if np.any(np.abs(imu_ns[j] - ns) > 1000):
        raise SystemExit("ground-truth stamps are not IMU stamps")
    return j


def windows(d: dict[str, Any], length_s: float, stride: int = 1, limit: int | None = None) -> dict[str, np.ndarray]:
    """Ground-truth rows ``a`` (start) and ``b`` (end, ``length_s`` later) and the padded IMU
    samples between them: ``acc``/``gyro`` (K, M, 3), ``dt`` (K, M), ``mask`` (K, M)."""
    steps = round(length_s * 1e9 / GT_PERIOD_NS)
    gt_ns, imu_ns = d["gt_ns"], d["imu_ns"]
    a = np.arange(0, len(gt_ns) - steps, stride)
    b = a + steps
    ok = np.abs(gt_ns[b] - gt_ns[a] - steps * GT_PERIOD_NS) < 1_000_000  # no gap in the ground truth
    a, b = a[ok], b[ok]
    if limit is not None:
        a, b = a[:limit], b[:limit]
    ia, ib = _nearest(imu_ns, gt_ns[a]), _nearest(imu_ns, gt_ns[b])
    count = ib - ia
    m = int(count.max())
    slot = np.arange(m)[None, :]
    mask = slot < count[:, None]
    idx = np.where(mask, ia[:, None] + slot, 0)
    t = imu_ns.astype(np.float64) * 1e-9
    dt = np.where(mask, (imu_ns[np.minimum(idx + 1, len(t) - 1)] - imu_ns[idx]) * 1e-9, 0.0)
    zeros = np.zeros(3)
    return {
        "a": a,
        "b": b,
        "t_start": t[ia],
        "acc": np.where(mask[..., None], d["acc"][idx], zeros),
        "gyro": np.where(mask[..., None], d["gyro"][idx], zeros),
        "dt": dt,
        "mask": mask,
    }


def predict_ours(
    w: dict[str, np.ndarray], pose0: np.ndarray, vel0: np.ndarray, bias0: np.ndarray, params: PreintegrationParams
) -> tuple[np.ndarray, np.ndarray]:
    """Predicted end pose params (K, 7) and velocity (K, 3)."""
    pim = preintegrate(w["acc"], w["gyro"], w["dt"], params, bias_hat=bias0, mask=w["mask"])
    k = len(w["a"])
    grav = jnp.broadcast_to(params.gravity, (k, 3))
    pose, vel = predict_imu_state(pim.preintegrated, pim.delta_time, grav, SE3(jnp.asarray(pose0)), jnp.asarray(vel0))
    return np.asarray(pose.params), np.asarray(vel)


def gtsam_params(noise: dict[str, float]) -> Any:
    import gtsam

    p = gtsam.PreintegrationParams.MakeSharedU(GRAVITY)
    p.setAccelerometerCovariance(np.eye(3) * noise["accelerometer_noise_density"] ** 2)
    p.setGyroscopeCovariance(np.eye(3) * noise["gyroscope_noise_density"] ** 2)
    p.setIntegrationCovariance(np.zeros((3, 3)))
    return p


def predict_gtsam(
    w: dict[str, np.ndarray], pose0: np.ndarray, vel0: np.ndarray, bias0: np.ndarray, gp: Any
) -> tuple[np.ndarray, np.ndarray]:
    import gtsam

    poses, vels = [], []
    for k in range(len(w["a"])):
        bias = gtsam.imuBias.ConstantBias(bias0[k, :3], bias0[k, 3:])
        pim = gtsam.PreintegratedImuMeasurements(gp, bias)
        m = w["mask"][k]
        for acc, gyro, dt in zip(w["acc"][k][m], w["gyro"][k][m], w["dt"][k][m]):
            pim.integrateMeasurement(acc, gyro, dt)
        p = pose0[k]
        s = pim.predict(gtsam.NavState(gtsam.Pose3(gtsam.Rot3.Quaternion(*p[:4]), p[4:7]), vel0[k]), bias)
        q = s.attitude().toQuaternion()
        poses.append([q.w(), q.x(), q.y(), q.z(), *s.position()])
        vels.append(s.velocity())
    return np.asarray(poses), np.asarray(vels)


def errors(pose: np.ndarray, vel: np.ndarray, pose_ref: np.ndarray, vel_ref: np.ndarray) -> dict[str, np.ndarray]:
    """Per window: position (m), rotation (rad, angle of R_ref^T R), velocity (m/s) errors."""
    r = SO3(jnp.asarray(pose_ref[:, :4])).inverse() @ SO3(jnp.asarray(pose[:, :4]))
    return {
        "position": np.linalg.norm(pose[:, 4:7] - pose_ref[:, 4:7], axis=1),
        "rotation": np.linalg.norm(np.asarray(r.log()), axis=1),
        "velocity": np.linalg.norm(vel - vel_ref, axis=1),
    }


def summary(x: np.ndarray) -> dict[str, float]:
    return {"median": float(np.median(x)), "p95": float(np.percentile(x, 95)), "max": float(np.max(x))}


def original_states(d: dict[str, Any], t_o: np.ndarray, pose_o: np.ndarray, ns: np.ndarray) -> tuple:
    """Pose, velocity (central difference over +-10 samples = +-50 ms) of EuRoC's own ground
    truth at the stamps ``ns`` (nearest row, must be within 0.1 ms); ``ok`` marks stamps it
    covers."""
    t = ns.astype(np.float64) * 1e-9
    j = np.clip(np.searchsorted(t_o, t), 1, len(t_o) - 1)
    j = np.where(np.abs(t_o[j - 1] - t) < np.abs(t_o[j] - t), j - 1, j)
    ok = (np.abs(t_o[j] - t) < 1e-4) & (j >= 10) & (j < len(t_o) - 10)
    j = np.clip(j, 10, len(t_o) - 11)
    vel = (pose_o[j + 10, 4:7] - pose_o[j - 10, 4:7]) / (t_o[j + 10] - t_o[j - 10])[:, None]
    return pose_o[j], vel, ok


# --------------------------------------------------------------------------------------------
# main
# --------------------------------------------------------------------------------------------


def run_length(
    d: dict[str, Any], length: float, stride: int, params: PreintegrationParams, gp: Any, repeats: int = 5
) -> dict[str, Any]:
    """All windows of one length: ours (steady time = median of ``repeats`` calls after the
    compiling one) and GTSAM's loop, errors to the ground truth and to each other."""
    w = windows(d, length, stride)
    a, b = w["a"], w["b"]
    pose0, vel0, bias0 = d["pose"][a], d["vel"][a], d["bias"][a]
    t0 = time.perf_counter()
    jax.block_until_ready(predict_ours(w, pose0, vel0, bias0, params))
    first_s = time.perf_counter() - t0
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        pose, vel = predict_ours(w, pose0, vel0, bias0, params)
        times.append(time.perf_counter() - t0)
    ours_s = float(np.median(times))
    t0 = time.perf_counter()
    gpose, gvel = predict_gtsam(w, pose0, vel0, bias0, gp)
    gtsam_s = time.perf_counter() - t0
    parity = errors(pose, vel, gpose, gvel)
    err = errors(pose, vel, d["pose"][b], d["vel"][b])
    gerr = errors(gpose, gvel, d["pose"][b], d["vel"][b])
    return {
        "length_s": length,
        "windows": len(a),
        "samples": int(w["mask"].sum()),
        "t_start": w["t_start"],
        "errors": err,
        "gtsam_errors": gerr,
        "max_diff_to_gtsam": {k: float(v.max()) for k, v in parity.items()},
        "max_error_diff_to_gtsam": {k: float(np.abs(err[k] - gerr[k]).max()) for k in err},
        "ours_s": ours_s,
        "ours_first_s": first_s,
        "gtsam_s": gtsam_s,
    }


def run_original(d: dict[str, Any], length: float, stride: int, params: PreintegrationParams) -> dict[str, Any]:
    t_o, pose_o = load_original()
    w = windows(d, length, stride)
    pa, va, ok_a = original_states(d, t_o, pose_o, d["gt_ns"][w["a"]])
    pb, vb, ok_b = original_states(d, t_o, pose_o, d["gt_ns"][w["b"]])
    ok = ok_a & ok_b
    sub = {k: v[ok] for k, v in w.items()}
    pose, vel = predict_ours(sub, pa[ok], va[ok], d["bias"][w["a"]][ok], params)
    err = errors(pose, vel, pb[ok], vb[ok])
    # the attitude offset between the two ground truths, body side: R_orig^T R_csv
    off = SO3(jnp.asarray(pa[ok][:, :4])).inverse() @ SO3(jnp.asarray(d["pose"][w["a"]][ok][:, :4]))
    off_v = np.asarray(off.log())
    return {
        "length_s": length,
        "windows": int(ok.sum()),
        "errors": err,
        "attitude_offset_deg": {
            "mean_rotvec": np.degrees(off_v.mean(axis=0)).tolist(),
            "angle_median": float(np.degrees(np.median(np.linalg.norm(off_v, axis=1)))),
            "angle_std": float(np.degrees(np.std(np.linalg.norm(off_v, axis=1)))),
        },
        "position_offset_median_m": float(
            np.median(np.linalg.norm(pa[ok][:, 4:7] - d["pose"][w["a"]][ok][:, 4:7], axis=1))
        ),
    }


def _row(name: str, err: dict[str, np.ndarray], n: int) -> str:
    p, r, v = summary(err["position"]), summary(np.degrees(err["rotation"])), summary(err["velocity"])
    return (
        f"{name:<10}{n:>6}  {p['median']:>7.4f} {p['p95']:>7.4f} {p['max']:>7.4f}  "
        f"{r['median']:>6.3f} {r['p95']:>6.3f} {r['max']:>6.3f}  {v['median']:>7.4f} {v['p95']:>7.4f} {v['max']:>7.4f}"
    )


def plot(path: Path, rows: list[dict[str, Any]]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(3, 1, figsize=(11, 9), sharex=True)
    labels = (("position", "position error [m]", 1.0), ("rotation", "rotation error [deg]", 180 / np.pi))
    labels += (("velocity", "velocity error [m/s]", 1.0),)
    t0 = min(r["t_start"][0] for r in rows)
    for ax, (key, label, scale) in zip(axes, labels):
        for r in sorted(rows, key=lambda r: -r["length_s"]):
            ax.plot(r["t_start"] - t0, r["errors"][key] * scale, lw=0.8, label=f"{r['length_s']:g} s windows")
        ax.set_ylabel(label)
        ax.set_yscale("log")
        ax.grid(alpha=0.3)
    axes[0].legend(loc="upper right")
    axes[0].set_title("EuRoC V1_01: IMU prediction from the ground-truth state vs ground truth (jaxslam = GTSAM)")
    axes[-1].set_xlabel("window start [s]")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--windows", type=float, nargs="+", default=[0.5, 1.0, 2.0], help="window lengths, s")
    ap.add_argument("--stride", type=int, default=1, help="start a window every N ground-truth rows (20 Hz)")
    ap.add_argument("--original", action="store_true", help="also score 1 s windows against EuRoC's own ground truth")
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--plot", type=Path, default=None, help="PNG: error vs time")
    args = ap.parse_args(argv)

    d = load_euroc()
    params = params_from(d["noise"])
    gp = gtsam_params(d["noise"])
    dur = (d["imu_ns"][-1] - d["imu_ns"][0]) * 1e-9
    print(
        f"EuRoC V1_01: {len(d['imu_ns'])} IMU samples ({dur:.0f} s), {len(d['gt_ns'])} ground-truth states; "
        "T_BS(imu0) = T_BS(ground truth) = I",
        flush=True,
    )
    rows = [run_length(d, length, args.stride, params, gp) for length in args.windows]
    orig = run_original(d, 1.0, args.stride, params) if args.original else None

    head = (
        f"{'window':<10}{'n':>6}  {'position error m':^23}  {'rotation error deg':^20}  {'velocity error m/s':^23}\n"
        f"{'':<16}  {'median':>7} {'95%':>7} {'max':>7}  {'median':>6} {'95%':>6} {'max':>6}  "
        f"{'median':>7} {'95%':>7} {'max':>7}"
    )
    print("\nprediction from the ground-truth state vs ground truth (V1_01_easy.csv)")
    print(head)
    for r in rows:
        print(_row(f"{r['length_s']:g} s", r["errors"], r["windows"]))
    if orig is not None:
        print(_row("1 s orig.", orig["errors"], orig["windows"]) + "   <- EuRoC's own ground truth")
        ao = orig["attitude_offset_deg"]
        print(
            f"  EuRoC's own vs csv attitude (body side): {ao['angle_median']:.2f} deg (std {ao['angle_std']:.2f}), "
            f"mean rotation vector {np.round(ao['mean_rotvec'], 2).tolist()} deg; position offset "
            f"{orig['position_offset_median_m']:.3f} m"
        )
    print("\njaxslam vs GTSAM on the same windows (max over windows)")
    print(
        f"{'window':<10}{'|dp| m':>10}{'angle rad':>11}{'|dv| m/s':>10}   "
        f"{'ours ms':>8}{'compile s':>10}{'gtsam ms':>10}{'ratio':>7}"
    )
    for r in rows:
        m = r["max_diff_to_gtsam"]
        print(
            f"{r['length_s']:<10g}{m['position']:>10.1e}{m['rotation']:>11.1e}{m['velocity']:>10.1e}   "
            f"{r['ours_s'] * 1e3:>8.1f}{r['ours_first_s']:>10.2f}{r['gtsam_s'] * 1e3:>10.0f}"
            f"{r['gtsam_s'] / r['ours_s']:>6.0f}x"
        )
    result = {
        "windows": [
            {
                "length_s": r["length_s"],
                "count": r["windows"],
                "samples": r["samples"],
                "position_m": summary(r["errors"]["position"]),
                "rotation_deg": summary(np.degrees(r["errors"]["rotation"])),
                "velocity_mps": summary(r["errors"]["velocity"]),
                "max_diff_to_gtsam": r["max_diff_to_gtsam"],
                "max_error_diff_to_gtsam": r["max_error_diff_to_gtsam"],
                "ours_ms": r["ours_s"] * 1e3,
                "ours_compile_s": r["ours_first_s"],
                "gtsam_ms": r["gtsam_s"] * 1e3,
            }
            for r in rows
        ],
        "stride_rows": args.stride,
        "noise": d["noise"],
        "extrinsics_T_BS": d["extrinsics"],
        "gravity": GRAVITY,
        "machine": machine_info(),
    }
    if orig is not None:
        result["euroc_original_1s"] = {
            "count": orig["windows"],
            "position_m": summary(orig["errors"]["position"]),
            "rotation_deg": summary(np.degrees(orig["errors"]["rotation"])),
            "velocity_mps": summary(orig["errors"]["velocity"]),
            "attitude_offset_deg": orig["attitude_offset_deg"],
            "position_offset_median_m": orig["position_offset_median_m"],
        }
    if args.json is not None:
        args.json.write_text(json.dumps(result, indent=2))
        print(f"wrote {args.json}")
    if args.plot is not None:
        plot(args.plot, rows)
        print(f"wrote {args.plot}")
    return result


if __name__ == "__main__":
    main()

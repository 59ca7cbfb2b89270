"""Visual odometry's translation length against ground truth with exact depth (issue 6).

    python benchmarks/vo_scale.py [--seed 2] [--t0 8 --t1 62 --step 0.5] [--json PATH]

Renders frames of a simulated 30 m tunnel at ground-truth poses ``--step`` s apart (0.25 m at
the default 0.5 m/s), gives every feature its exact depth from the renderer's depth map, and
runs the estimator's visual front end (``VisualFrontend.relative``) on consecutive pairs: the
ratio of its translation length to the true one, over all pairs and per 6 m of the tunnel.
Twice: with the simulator's renderer (one radiance sample per pixel) and with 2x2 supersampled
radiance (the mean of four rays per pixel), to tell a bias of the features themselves from
texture aliasing. The estimator's own depth (LiDAR) is not used here: see
``vision.scale_depth`` for that part.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import tempfile
import time
from pathlib import Path

import numpy as np
import yaml
from scipy import ndimage

from jaxslam.lie import host
from jaxslam.pipeline import PipelineConfig, load_rig
from jaxslam.pipeline._visual import VisualFrontend
from jaxslam.sim import SimConfig, TunnelConfig
from jaxslam.sim._camera import CameraSimulator
from jaxslam.sim._recording import Simulation, rig_calibration
from jaxslam.sim._texture import LightingConfig


def supersampled(cam: CameraSimulator):
    """A radiance function for ``cam`` that averages 2x2 rays per pixel (same depth map)."""
    fx, fy, cx, cy = cam.K
    big = dataclasses.replace(
        cam.config,
        width=2 * cam.config.width,
        height=2 * cam.config.height,
        fx=2 * fx,
        fy=2 * fy,
        cx=2 * cx + 0.5,  # sub-pixel centres at -1/4 and +1/4 of a pixel
        cy=2 * cy + 0.5,
    )
    cam2 = CameraSimulator(big, cam.tunnel, cam.atlas)
    plain = cam.radiance

    def radiance(R_wc, p_wc):
        L2, _ = cam2.radiance(R_wc, p_wc)
        L = L2.reshape(L2.shape[0] // 2, 2, L2.shape[1] // 2, 2).mean((1, 3)).astype(np.float32)
        return L, plain(R_wc, p_wc)[1]

    return radiance


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seed", type=int, default=2)
    ap.add_argument("--lighting", default="uneven", choices=["uneven", "dark", "normal"])
    ap.add_argument("--t0", type=float, default=8.0, help="first frame, s (the outbound leg: 8-62 s)")
    ap.add_argument("--t1", type=float, default=62.0)
    ap.add_argument("--step", type=float, default=0.5, help="seconds between the frames of a pair")
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()

    cfg = SimConfig(seed=args.seed, tunnel=TunnelConfig(length=30.0), lighting=LightingConfig(mode=args.lighting))
    sim = Simulation.create(cfg)
    cam = sim.camera
    plain = cam.radiance
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "rig.yaml"
        path.write_text(yaml.safe_dump(rig_calibration(cfg)))
        rig = load_rig(path)
    vcfg = PipelineConfig(rig=rig).vision
    times = np.arange(args.t0, args.t1, args.step)
    out: dict = {"seed": args.seed, "lighting": args.lighting, "pairs": len(times) - 1}
    for name, radiance in (("plain", plain), ("supersampled", supersampled(cam))):
        fe = VisualFrontend(vcfg, rig)
        cam.radiance = radiance
        cam.exposure_gain = None
        t_start = time.perf_counter()
        feats, poses = [], []
        for k, t in enumerate(times):
            st = sim.trajectory.state(np.array([t]))
            R, p = st["R"][0], st["p"][0]
            img, _ = cam.render(float(t), R, p, st["v"][0], st["omega"][0])
            depth = plain(*cam.pose(R, p))[1]
            f = fe.features(k, float(t), img, None)
            z = ndimage.map_coordinates(depth, [f.uv[:, 1], f.uv[:, 0]], order=1, mode="nearest")
            f.X[:] = np.c_[f.xn * z[:, None], z]
            f.X[z > vcfg.max_depth] = np.nan
            T = np.eye(4)
            T[:3, :3], T[:3, 3] = R, p
            feats.append(f)
            poses.append(T)
        ratio, where = [], []
        for k in range(len(times) - 1):
            T_true = host.inverse(poses[k]) @ poses[k + 1]
            vm = fe.relative(feats[k], feats[k + 1], T_true)
            if vm is not None and hasattr(vm, "information"):
                ratio.append(np.linalg.norm(vm.T[:3, 3]) / np.linalg.norm(T_true[:3, 3]))
                where.append(poses[k][0, 3])
        r, x = np.array(ratio), np.array(where)
        per = {}
        for lo in range(-6, 36, 6):
            s = (x >= lo) & (x < lo + 6)
            if s.any():
                per[f"{lo}..{lo + 6} m"] = {"pairs": int(s.sum()), "median": float(np.median(r[s]))}
        out[name] = {"pairs": len(r), "mean": float(r.mean()), "median": float(np.median(r)), "per_6m": per}
        print(
            f"{name:<13} {len(r)} pairs: length ratio mean {r.mean():.4f}, median {np.median(r):.4f} "
            f"({time.perf_counter() - t_start:.0f} s)"
        )
        for k, v in per.items():
            print(f"    x {k:>10}: {v['pairs']:3d} pairs, median {v['median']:.4f}")
    if args.json:
        args.json.write_text(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()

"""SURF (jaxslam, JAX) vs OpenCV SIFT and ORB, with and without enhancement (issue 4, item 5).

    python benchmarks/features.py ../shared/data [--json PATH] [--repeats 15] [--timing-only]

DIR is the shared data folder (``kitti_mono/``, ``lowlight/sice``, ``lowlight/LIME``). Measures,
in one run:

* time per image of detect + describe on a 1241x376 KITTI frame (JAX compile time apart),
  every method once per round over ``--repeats`` interleaved rounds: medians, quartiles and
  the same-run ratio SURF / SIFT (``--timing-only`` stops there);
* under known homographies (rotations, scalings, a brightness change) of real 512x512 images
  (SICE mid exposures, LIME and DICM crops): repeatability (a keypoint mapped into the other
  image has one within 2.5 px), match accuracy after the ratio test (0.8; correct = mapped
  within 3 px) and after ``cv2.findHomography`` RANSAC (share of inliers among ratio matches,
  and share of correct among the inliers);
* the same on SICE exposure pairs (darkest vs mid exposure of a tripod scene: identity map).

Methods: ``surf``, ``sift``, ``orb`` on the grey image, and ``+aba`` (ABA-CLAHE), ``+clahe``,
``+he`` variants. Matching is OpenCV's ``BFMatcher`` (L2; Hamming for ORB). JSON:
``{"methods": {name: {"keypoints", "ms_per_image", "repeatability", "match_accuracy",
"ransac_inlier_ratio", ...}}, "timing": {...}}``.
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import cv2
import jax
import numpy as np
from PIL import Image

jax.config.update("jax_enable_x64", True)

from jaxslam.vision import aba_clahe, clahe, equalize_hist, surf  # noqa: E402

MAXK = 4096
ENHANCE = {
    "": lambda g: g,
    "+aba": lambda g: np.asarray(aba_clahe(g)),
    "+clahe": lambda g: np.asarray(clahe(g)),
    "+he": lambda g: np.asarray(equalize_hist(g)),
}
_SIFT = cv2.SIFT_create()
_ORB = cv2.ORB_create(nfeatures=5000)


def gray(path: Path) -> np.ndarray:
    with Image.open(path) as im:
        return np.asarray(im.convert("L"))


def run_detector(name: str, g: np.ndarray):
    """Keypoint xy ``(N, 2)``, descriptors, and whether they are binary."""
    if name == "surf":
        kp, desc, valid = surf(g, 100.0, max_keypoints=MAXK)
        jax.block_until_ready(desc)
        v = np.asarray(valid)
        return np.asarray(kp)[v, :2].astype(np.float64), np.asarray(desc)[v], False
    det = _SIFT if name == "sift" else _ORB
    kps, desc = det.detectAndCompute(g, None)
    xy = np.array([k.pt for k in kps], np.float64).reshape(-1, 2)
    if desc is None:
        desc = np.zeros((0, 128 if name == "sift" else 32), np.float32 if name == "sift" else np.uint8)
    return xy, desc, name == "orb"


def apply_affine(M: np.ndarray, xy: np.ndarray) -> np.ndarray:
    return np.c_[xy, np.ones(len(xy))] @ M[:2].T


def evaluate_pair(a, b, M, shape_b, margin=16):
    """Repeatability, ratio-test accuracy, RANSAC inlier ratio and RANSAC accuracy of a pair."""
    (xa, da, binary), (xb, db, _) = a, b
    h, w = shape_b
    if len(xa) < 2 or len(xb) < 2:
        return dict(repeatability=0.0, match_accuracy=0.0, ransac_inlier_ratio=0.0, ransac_accuracy=0.0, matches=0)
    pa = apply_affine(M, xa)
    inside = (pa[:, 0] > margin) & (pa[:, 0] < w - margin) & (pa[:, 1] > margin) & (pa[:, 1] < h - margin)
    from scipy.spatial import cKDTree

    d, _ = cKDTree(xb).query(pa[inside]) if inside.any() else (np.zeros(0), None)
    rep = float(np.mean(d <= 2.5)) if len(d) else 0.0
    bf = cv2.BFMatcher(cv2.NORM_HAMMING if binary else cv2.NORM_L2)
    knn = bf.knnMatch(da, db, k=2)
    good = [m[0] for m in knn if len(m) == 2 and m[0].distance < 0.8 * m[1].distance]
    if len(good) < 4:
        return dict(
            repeatability=rep, match_accuracy=0.0, ransac_inlier_ratio=0.0, ransac_accuracy=0.0, matches=len(good)
        )
    ia = np.array([m.queryIdx for m in good])
    ib = np.array([m.trainIdx for m in good])
    correct = np.linalg.norm(pa[ia] - xb[ib], axis=1) <= 3.0
    _, mask = cv2.findHomography(xa[ia], xb[ib], cv2.RANSAC, 3.0)
    inl = mask.ravel().astype(bool) if mask is not None else np.zeros(len(good), bool)
    return dict(
        repeatability=rep,
        match_accuracy=float(correct.mean()),
        ransac_inlier_ratio=float(inl.mean()),
        ransac_accuracy=float(correct[inl].mean()) if inl.any() else 0.0,
        matches=len(good),
    )


def synthetic_pairs(images):
    """(source, warped, 3x3 map) for rotations, scalings and a brightness change."""
    out = []
    for g in images:
        h, w = g.shape
        c = ((w - 1) / 2, (h - 1) / 2)
        for angle, scale, gain in ((15, 1.0, 1.0), (30, 1.0, 1.0), (0, 0.8, 1.0), (0, 1.25, 1.0), (0, 1.0, 0.5)):
            M = np.vstack([cv2.getRotationMatrix2D(c, angle, scale), [0, 0, 1]])
            wimg = cv2.warpAffine(g, M[:2], (w, h), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT_101)
            if gain != 1.0:
                wimg = np.clip(np.rint(wimg.astype(np.float64) * gain), 0, 255).astype(np.uint8)
            out.append((g, wimg, M))
    return out


def crop512(g):
    h, w = g.shape
    if h < 512 or w < 512:
        return None
    y, x = (h - 512) // 2, (w - 512) // 2
    return np.ascontiguousarray(g[y : y + 512, x : x + 512])


def _stats(ms: list[float]) -> dict:
    q = np.percentile(ms, [0, 25, 50, 75, 100])
    return {"median": float(q[2]), "min": float(q[0]), "q1": float(q[1]), "q3": float(q[3]), "max": float(q[4])}


def timing(frame: np.ndarray, methods, repeats: int) -> dict:
    """Per-image ms of every method on ``frame``, interleaved over ``repeats`` rounds (one
    call of each per round, so that machine load hits all alike); medians and spread.
    JAX compile time (first call) apart."""
    from jaxslam.vision._surf import surf_u8

    res: dict = {}
    t0 = time.perf_counter()
    run_detector("surf", frame)
    res["surf_first_call_s"] = time.perf_counter() - t0
    img = jax.numpy.asarray(frame)

    def detect_orient():
        jax.block_until_ready(surf_u8(img, 100.0, max_keypoints=MAXK, descriptors=False))

    t0 = time.perf_counter()
    detect_orient()
    res["surf_detect_orient_first_call_s"] = time.perf_counter() - t0

    def surf_one_call():  # parallel=False: the descriptors in one call, for reference
        jax.block_until_ready(surf(frame, 100.0, max_keypoints=MAXK, parallel=False))

    surf_one_call()
    calls = {"surf_detect_orient": detect_orient, "surf_one_call": surf_one_call}
    for m in methods:
        det, enh = m.split("+")[0], ("+" + m.split("+")[1]) if "+" in m else ""
        calls[m] = lambda det=det, enh=enh: run_detector(det, ENHANCE[enh](frame))
        calls[m]()  # compile the enhancement
    times: dict[str, list[float]] = {k: [] for k in calls}
    for _ in range(repeats):
        for k, f in calls.items():
            t = time.perf_counter()
            f()
            times[k].append(1e3 * (time.perf_counter() - t))
    res["stats_ms"] = {k: _stats(v) for k, v in times.items()}
    res["ratio_surf_over_sift_per_round"] = _stats([a / b for a, b in zip(times["surf"], times["sift"])])
    for k, v in res["stats_ms"].items():
        res[k if k != "surf_detect_orient" else "surf_detect_orient_ms"] = v["median"]
    return res


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("data", type=Path, help="the shared data folder (../shared/data)")
    ap.add_argument("--json", type=Path, help="write the results here")
    ap.add_argument("--repeats", type=int, default=15, help="interleaved timing rounds")
    ap.add_argument("--quick", action="store_true", help="fewer images (smoke test)")
    ap.add_argument("--timing-only", action="store_true", help="only the timing of SURF, SIFT and ORB")
    args = ap.parse_args()
    detectors = ["surf", "sift", "orb"]
    methods = [d + e for d in detectors for e in ENHANCE]

    frame = gray(args.data / "kitti_mono/image_l/000000.png")
    timed = ["surf", "sift", "orb"] if args.timing_only else methods
    size = f"{frame.shape[1]}x{frame.shape[0]}"
    print(f"timing on a {size} KITTI frame ({args.repeats} interleaved rounds) ...", flush=True)
    tm = timing(frame, timed, args.repeats)
    print(f"  SURF first call (JAX compile + run): {tm['surf_first_call_s']:.1f} s")
    st = tm["stats_ms"]
    for k in ("surf", "sift", "orb", "surf_detect_orient", "surf_one_call"):
        v = st[k]
        spread = f"quartiles {v['q1']:.1f}-{v['q3']:.1f}, min {v['min']:.1f}, max {v['max']:.1f}"
        print(f"  {k:<20} median {v['median']:7.1f} ms  ({spread})")
    ratio = tm["surf"] / tm["sift"]
    rr = tm["ratio_surf_over_sift_per_round"]
    per_round = f"median {rr['median']:.2f}, quartiles {rr['q1']:.2f}-{rr['q3']:.2f}"
    print(f"  SURF/SIFT = {ratio:.2f} (ratio of medians); per round: {per_round}")
    print(f"  load average {os.getloadavg()[0]:.2f} on {os.cpu_count()} CPUs")
    timing_json = {
        "frame": "kitti_mono/image_l/000000.png (1241x376)",
        "surf_first_call_s": tm["surf_first_call_s"],
        "surf_over_sift": ratio,
        "surf_over_sift_per_round": rr,
        "surf_detect_orient_ms": tm["surf_detect_orient_ms"],
        "sift_ms": tm["sift"],
        "surf_ms": tm["surf"],
        "surf_one_call_ms": st["surf_one_call"]["median"],
        "stats_ms": st,
        "repeats": args.repeats,
        "load": os.getloadavg(),
        "device": str(jax.devices()[0]),
    }
    if args.timing_only:
        if args.json:
            args.json.write_text(json.dumps({"timing": timing_json}, indent=1))
            print(f"wrote {args.json}")
        return

    sice = sorted((args.data / "lowlight/sice").iterdir())
    if args.quick:
        sice = sice[:2]
    mids, exposure_pairs = [], []
    for scene in sice:
        files = sorted(scene.glob("*.jpg"), key=lambda p: int(p.stem))
        mid = gray(files[len(files) // 2])
        mids.append(mid)
        exposure_pairs.append((gray(files[0]), mid, np.eye(3)))
    others = [crop512(gray(p)) for p in sorted((args.data / "lowlight/LIME").glob("*"))[:4]]
    others += [crop512(gray(p)) for p in sorted((args.data / "lowlight/DICM").glob("*"))[:4]]
    images = mids[:4] + [g for g in others if g is not None]
    if args.quick:
        images = images[:2]
    synth = synthetic_pairs(images)
    print(
        f"{len(synth)} synthetic pairs from {len(images)} real images; {len(exposure_pairs)} SICE exposure pairs",
        flush=True,
    )

    results = {}
    for m in methods:
        det, enh = m.split("+")[0], ("+" + m.split("+")[1]) if "+" in m else ""
        f = ENHANCE[enh]
        row = {}
        for label, pairs in (("synthetic", synth), ("exposure", exposure_pairs)):
            stats, nkp, cache = [], [], {}
            for a, b, M in pairs:
                ka = cache.get(id(a))
                if ka is None:
                    ka = cache[id(a)] = run_detector(det, f(a))
                kb = run_detector(det, f(b))
                nkp += [len(ka[0]), len(kb[0])]
                stats.append(evaluate_pair(ka, kb, M, b.shape))
            row[label] = {k: float(np.mean([s[k] for s in stats])) for k in stats[0]}
            row[label]["keypoints"] = float(np.mean(nkp))
        results[m] = {
            "keypoints": row["synthetic"]["keypoints"],
            "ms_per_image": tm[m],
            "repeatability": row["synthetic"]["repeatability"],
            "match_accuracy": row["synthetic"]["match_accuracy"],
            "ransac_inlier_ratio": row["synthetic"]["ransac_inlier_ratio"],
            "ransac_accuracy": row["synthetic"]["ransac_accuracy"],
            "exposure": row["exposure"],
        }
        e = row["exposure"]
        r = results[m]
        print(
            f"{m:10s} kp {r['keypoints']:7.0f}  {tm[m]:7.1f} ms | synthetic: rep {r['repeatability']:.3f} "
            f"acc {r['match_accuracy']:.3f} ransac-inl {r['ransac_inlier_ratio']:.3f} | "
            f"exposure: kp {e['keypoints']:.0f} rep {e['repeatability']:.3f} acc {e['match_accuracy']:.3f} "
            f"ransac-inl {e['ransac_inlier_ratio']:.3f}",
            flush=True,
        )
    out = {"methods": results, "timing": timing_json}
    print(f"same-run time ratio SURF/SIFT on 1241x376: {ratio:.2f}")
    if args.json:
        args.json.write_text(json.dumps(out, indent=1))
        print(f"wrote {args.json}")


if __name__ == "__main__":
    main()

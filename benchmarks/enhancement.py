"""Low-light enhancement: jaxslam (ABA-CLAHE, CLAHE, HE, gamma) vs OpenCV CLAHE, same run.

    python benchmarks/enhancement.py DIR... [--json PATH] [--repeat 100]

For every image under the folders (recursively; read with OpenCV, BGR → RGB, 8-bit):

* SPEC Table 1 metrics of each method's output against the original image: PSNR, SSIM
  (Wang et al. 2004: 11x11 Gaussian window, sigma 1.5, on the grey image), entropy (bits,
  256 bins) and STD of the grey output; averaged over the images;
* for ``sice`` scenes (sub-folders of a folder named ``sice``): PSNR/SSIM of each method's
  output of the darkest exposure against a mid exposure (the ``len // 2``-th by file number);
* hard-mode agreement with ``cv2.createCLAHE(2.0, (8, 8)).apply``: fraction of pixels within
  ±1 grey level, on the grey image and on V = max(R, G, B), min and mean over the images;
* time per image on the first KITTI-sized (1241x376) grey frame found (else the first
  image): ours steady state (median of ``--repeat`` interleaved runs after a warm-up),
  compile time (first call minus steady) apart, and OpenCV CLAHE in the same loop.

JSON: ``{"clahe_agreement", "ms_per_image": {"aba-clahe", "clahe", "opencv_clahe", ...},
"metrics": {method: {"psnr", "ssim", "entropy", "std"}}, "sice_pairs", ...}``.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import cv2
import numpy as np
from scipy.ndimage import gaussian_filter

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import jax

import jaxslam  # noqa: F401  (float64 on)
from jaxslam._machine import machine_info
from jaxslam.vision import aba_clahe, clahe, equalize_hist, gamma_correct

EXTS = {".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff"}
METHODS = {
    "aba-clahe": lambda im: aba_clahe(im, 0.25, 0.4, 2.0),
    "clahe": lambda im: clahe(im, 2.0),
    "he": equalize_hist,
    "gamma": lambda im: gamma_correct(im, 0.5),
}


def grey(rgb: np.ndarray) -> np.ndarray:
    return rgb if rgb.ndim == 2 else cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = np.mean((a.astype(float) - b.astype(float)) ** 2)
    return float("inf") if mse == 0 else float(10 * np.log10(255.0**2 / mse))


def ssim(a: np.ndarray, b: np.ndarray) -> float:
    """Mean SSIM (Wang et al. 2004), Gaussian window sigma 1.5 truncated at 11x11, L = 255."""
    x, y = a.astype(float), b.astype(float)
    f = lambda z: gaussian_filter(z, 1.5, truncate=3.5)  # noqa: E731
    mx, my = f(x), f(y)
    sxx, syy, sxy = f(x * x) - mx * mx, f(y * y) - my * my, f(x * y) - mx * my
    c1, c2 = (0.01 * 255) ** 2, (0.03 * 255) ** 2
    s = ((2 * mx * my + c1) * (2 * sxy + c2)) / ((mx * mx + my * my + c1) * (sxx + syy + c2))
    return float(s[5:-5, 5:-5].mean())


def entropy(g: np.ndarray) -> float:
    p = np.bincount(g.ravel(), minlength=256) / g.size
    p = p[p > 0]
    return float(-(p * np.log2(p)).sum())


def read(path: Path) -> np.ndarray | None:
    bgr = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if bgr is None:
        return None
    if bgr.dtype != np.uint8:
        bgr = cv2.convertScaleAbs(bgr, alpha=255.0 / max(1, int(bgr.max())))
    if bgr.ndim == 3:
        return np.ascontiguousarray(cv2.cvtColor(bgr[..., :3], cv2.COLOR_BGR2RGB))
    return bgr


def images_in(folder: Path) -> list[Path]:
    return sorted(p for p in folder.rglob("*") if p.suffix.lower() in EXTS)


def _num(p: Path) -> float:
    try:
        return float(p.stem)
    except ValueError:
        return float("inf")


def _finite_mean(v: list[float]) -> float | None:
    """Mean of the finite values (PSNR of an unchanged image is inf); None when there are none."""
    f = [x for x in v if np.isfinite(x)]
    return float(np.mean(f)) if f else None


def time_frame(frame: np.ndarray, repeat: int) -> dict:
    """Steady-state ms (median, interleaved) and compile s for ours vs OpenCV CLAHE."""
    cv = cv2.createCLAHE(2.0, (8, 8))
    fns = {
        "aba-clahe": lambda: aba_clahe(frame).block_until_ready(),
        "clahe": lambda: clahe(frame).block_until_ready(),
        "he": lambda: equalize_hist(frame).block_until_ready(),
        "gamma": lambda: gamma_correct(frame).block_until_ready(),
        "opencv_clahe": lambda: cv.apply(frame),
    }
    jframe = jax.device_put(frame)
    fns_dev = {k: fns[k] for k in fns}
    fns_dev["aba-clahe (device array)"] = lambda: aba_clahe(jframe).block_until_ready()
    jax.clear_caches()  # so that the first call below includes compilation
    first = {}
    for k, f in fns_dev.items():
        t = time.perf_counter()
        f()
        first[k] = time.perf_counter() - t
    times: dict[str, list[float]] = {k: [] for k in fns_dev}
    for _ in range(repeat):
        for k, f in fns_dev.items():
            t = time.perf_counter()
            f()
            times[k].append(time.perf_counter() - t)
    ms = {k: 1e3 * float(np.median(v)) for k, v in times.items()}
    ms_min = {k: 1e3 * float(np.min(v)) for k, v in times.items()}
    compile_s = {k: max(0.0, first[k] - ms[k] / 1e3) for k in fns if k != "opencv_clahe"}
    return {"ms_per_image": ms, "ms_min": ms_min, "compile_s": compile_s}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("dirs", nargs="+", type=Path)
    ap.add_argument("--json", type=Path)
    ap.add_argument("--repeat", type=int, default=100)
    args = ap.parse_args(argv)
    cv = cv2.createCLAHE(2.0, (8, 8))
    sums: dict[str, dict[str, list[float]]] = {m: {"psnr": [], "ssim": [], "entropy": [], "std": []} for m in METHODS}
    sums["input"] = {"psnr": [], "ssim": [], "entropy": [], "std": []}
    agree: dict[str, list[float]] = {}
    sice: dict[str, dict[str, list[float]]] = {m: {"psnr": [], "ssim": []} for m in [*METHODS, "input"]}
    frame = None
    n_img = 0
    t_total = {m: 0.0 for m in METHODS}
    for d in args.dirs:
        files = images_in(d)
        for path in files:
            rgb = read(path)
            if rgb is None:
                print(f"skip unreadable {path}", file=sys.stderr)
                continue
            n_img += 1
            g = grey(rgb)
            if frame is None or (g.shape == (376, 1241) and frame.shape != (376, 1241)):
                frame = g
            for name, src in (("grey", g), ("value", rgb.max(axis=-1) if rgb.ndim == 3 else g)):
                d_ = np.abs(np.asarray(clahe(src)).astype(int) - cv.apply(src).astype(int))
                agree.setdefault(f"{d.name}/{name}", []).append(float(np.mean(d_ <= 1)))
            for m, fn in {**METHODS, "input": lambda im: im}.items():
                t = time.perf_counter()
                out = np.asarray(fn(rgb))
                if m in t_total:
                    t_total[m] += time.perf_counter() - t
                og = grey(out)
                sums[m]["psnr"].append(psnr(og, g))
                sums[m]["ssim"].append(ssim(og, g))
                sums[m]["entropy"].append(entropy(og))
                sums[m]["std"].append(float(og.std()))
        if d.name == "sice":
            for scene in sorted(p for p in d.iterdir() if p.is_dir()):
                exp = sorted(images_in(scene), key=_num)
                if len(exp) < 3:
                    continue
                dark, mid = read(exp[0]), read(exp[len(exp) // 2])
                if dark is None or mid is None:
                    continue
                for m, fn in {**METHODS, "input": lambda im: im}.items():
                    og = grey(np.asarray(fn(dark)))
                    sice[m]["psnr"].append(psnr(og, grey(mid)))
                    sice[m]["ssim"].append(ssim(og, grey(mid)))
    if frame is None:
        print("no images found", file=sys.stderr)
        return 1
    metrics = {m: {k: _finite_mean(v) for k, v in s.items()} for m, s in sums.items()}
    sice_pairs = {m: {k: float(np.mean(v)) if v else None for k, v in s.items()} for m, s in sice.items()}
    agreement = {k: {"min": float(np.min(v)), "mean": float(np.mean(v)), "images": len(v)} for k, v in agree.items()}
    timing = time_frame(frame, args.repeat)
    ms = timing["ms_per_image"]
    result = {
        "clahe_agreement": float(min(v["min"] for v in agreement.values())),
        "clahe_agreement_detail": agreement,
        "ms_per_image": ms,
        "ms_min": timing["ms_min"],
        "compile_s": timing["compile_s"],
        "timed_frame_shape": list(frame.shape),
        "ratio_to_opencv": {k: ms[k] / ms["opencv_clahe"] for k in ms},
        "metrics": metrics,
        "sice_pairs": sice_pairs,
        "images": n_img,
        "machine": machine_info(),
    }
    print(f"{n_img} images; hard CLAHE vs OpenCV, fraction within ±1 grey level (min / mean per image):")
    for k, v in agreement.items():
        print(f"  {k:<22} {v['min']:.5f} / {v['mean']:.5f}  ({v['images']} images)")
    print(f"{'method':<10}{'PSNR dB':>9}{'SSIM':>8}{'entropy':>9}{'STD':>8}   vs original (mean over images)")
    for m, r in metrics.items():
        ps = "inf" if r["psnr"] is None else f"{r['psnr']:.2f}"
        print(f"{m:<10}{ps:>9}{r['ssim']:>8.4f}{r['entropy']:>9.4f}{r['std']:>8.2f}")
    if sice_pairs["input"]["psnr"] is not None:
        print("SICE darkest exposure vs a mid exposure:")
        for m, r in sice_pairs.items():
            print(f"  {m:<10}{r['psnr']:>9.2f} dB {r['ssim']:>8.4f}")
    print(f"time per {frame.shape[1]}x{frame.shape[0]} grey frame (median of {args.repeat}, same run):")
    for k, v in ms.items():
        c = timing["compile_s"].get(k)
        extra = f", compile {c:.2f} s" if c is not None else ""
        print(f"  {k:<26}{v:>8.3f} ms  ({v / ms['opencv_clahe']:.2f}x OpenCV CLAHE{extra})")
    print(f"load average {os.getloadavg()[0]:.2f} on {os.cpu_count()} CPUs")
    if args.json:
        args.json.write_text(json.dumps(result, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""``jaxslam features IMAGE... --detector surf|sift|orb -o OUTDIR``: one ``.npz`` per image
with ``keypoints`` (x, y, size, angle°, response, octave, Laplacian sign) and ``descriptors``."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from ..errors import InputFormatError

_EXTS = {".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".pgm", ".ppm"}


def register(subparsers) -> argparse.ArgumentParser:
    """Add the ``features`` subcommand to the ``jaxslam`` parser."""
    f = subparsers.add_parser(
        "features",
        help="detect and describe local features (SURF in JAX; OpenCV SIFT/ORB); one .npz per image",
    )
    f.add_argument("images", nargs="+", help="image files or folders of images")
    f.add_argument("-o", "--output", required=True, help="output folder (IMAGE_STEM.npz per image)")
    f.add_argument("--detector", choices=["surf", "sift", "orb"], default="surf")
    f.add_argument("--hessian-threshold", type=float, default=100.0, help="SURF threshold (OpenCV units)")
    f.add_argument("--upright", action="store_true", help="SURF without orientation (U-SURF)")
    f.add_argument("--max-keypoints", type=int, default=4096, help="keep at most N (best responses)")
    f.set_defaults(func=cmd_features)
    return f


def _inputs(paths: list[str]) -> list[Path]:
    files: list[Path] = []
    for p in map(Path, paths):
        if p.is_dir():
            found = [f for f in sorted(p.iterdir()) if f.suffix.lower() in _EXTS]
            if not found:
                raise InputFormatError("no images in the folder", p)
            files += found
        elif p.exists():
            files.append(p)
        else:
            raise InputFormatError("no such file or folder", p)
    return files


def cmd_features(args: argparse.Namespace) -> int:
    import numpy as np
    from PIL import Image, UnidentifiedImageError

    from ._features import detect_and_describe

    if args.max_keypoints < 1:
        raise InputFormatError(f"--max-keypoints must be >= 1, got {args.max_keypoints}")
    files = _inputs(args.images)
    out = Path(args.output)
    out.mkdir(parents=True, exist_ok=True)
    failed = 0
    for f in files:
        try:
            with Image.open(f) as im:
                gray = np.asarray(im.convert("L"))
            kp, desc = detect_and_describe(
                gray,
                args.detector,
                hessian_threshold=args.hessian_threshold,
                max_keypoints=args.max_keypoints,
                upright=args.upright,
            )
            np.savez(out / (f.stem + ".npz"), keypoints=kp, descriptors=desc, image_shape=np.array(gray.shape))
            print(f"{f}: {len(kp)} keypoints")
        except (UnidentifiedImageError, OSError, ValueError) as exc:
            print(f"jaxslam features: error: {f}: {exc}", file=sys.stderr)
            failed += 1
    print(f"described {len(files) - failed}/{len(files)} image(s) with {args.detector} -> {out}")
    return 1 if failed else 0

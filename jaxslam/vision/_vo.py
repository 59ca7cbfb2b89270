"""Monocular visual odometry on an image folder (SPEC §3, issue 4 item 4).

Pipeline: read the images (KITTI-style folder, EuRoC ``mav0/cam0`` or a plain folder),
optionally enhance them (ABA-CLAHE), detect and describe features, then

1. **initialise** from the first frame and the first later frame with enough parallax:
   essential matrix (RANSAC), relative pose with cheirality, DLT triangulation, two-view BA;
   the first baseline has length 1 (monocular scale, SPEC §3.3: never from ground truth);
2. **track** every frame against the local map (descriptor matching to the map points of the
   last keyframes, ``cv2.solvePnPRansac`` + LM refinement);
3. make a **keyframe** when the parallax to the last keyframe or the share of tracked points
   says so; triangulate new points from matches with the previous keyframe (epipolar check,
   cheirality, reprojection and parallax-angle gates); run a **windowed BA** (Huber kernel,
   :func:`~jaxslam.vision.bundle_adjust`) over the last keyframes;
4. a **final BA** over every keyframe and point, outlier observations removed and solved
   again, then every non-keyframe re-localised against the final map.

Poses are ``world_T_camera`` with the first camera at the origin. Results: one pose per input
image (in input order), the sparse map, and Table-10 statistics (:class:`VoResult`).
"""

from __future__ import annotations

import dataclasses
import re
from pathlib import Path

import numpy as np

from ..errors import ConfigError, InputFormatError, JaxSlamError
from ._geometry import (
    bundle_adjust,
    relative_pose,
    reprojection_residuals,
    triangulate_points,
)
from ._matching import match_descriptors

IMAGE_EXTENSIONS = {".png", ".jpg", ".jpeg", ".bmp", ".pgm", ".ppm", ".tif", ".tiff"}


class VoError(JaxSlamError, RuntimeError):
    """Visual odometry could not run on the given images (too few features or matches)."""


# --- input -------------------------------------------------------------------------------------


@dataclasses.dataclass
class ImageSequence:
    """Images of one camera: ``paths`` in order, ``timestamps`` (s), intrinsics ``K`` (3x3),
    optional radial-tangential ``distortion`` (k1, k2, p1, p2[, k3]) and ground truth
    ``poses`` ``(N, 3, 4)`` (KITTI ``poses.txt``) when the folder has them."""

    paths: list[Path]
    timestamps: np.ndarray
    K: np.ndarray
    distortion: np.ndarray | None = None
    ground_truth: np.ndarray | None = None


def _images_in(folder: Path) -> list[Path]:
    return sorted(p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_EXTENSIONS)


def read_calibration(path: str | Path) -> tuple[np.ndarray, np.ndarray | None]:
    """Intrinsics ``K`` (and distortion, EuRoC only) from a KITTI ``calib.txt`` (first
    projection matrix, ``P0:`` label optional, 12 numbers), an EuRoC ``sensor.yaml``
    (``intrinsics: [fu, fv, cu, cv]``, ``distortion_coefficients``), a 3x3 matrix (9 numbers)
    or ``fx fy cx cy``. Raises :class:`InputFormatError` naming the file otherwise."""
    path = Path(path)
    if not path.is_file():
        raise InputFormatError("calibration file not found", path)
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise InputFormatError(f"cannot read the calibration: {exc}", path) from exc
    if "intrinsics" in text:
        m = re.search(r"intrinsics:\s*\[([^\]]*)\]", text)
        vals = _floats(m.group(1) if m else "", path, 1)
        if len(vals) != 4:
            raise InputFormatError(f"intrinsics need 4 numbers [fu, fv, cu, cv], found {len(vals)}", path)
        K = np.array([[vals[0], 0, vals[2]], [0, vals[1], vals[3]], [0, 0, 1.0]])
        d = re.search(r"distortion_coefficients:\s*\[([^\]]*)\]", text)
        dist = np.array(_floats(d.group(1), path, 1)) if d else None
        return _check_K(K, path), dist
    for lineno, line in enumerate(text.splitlines(), 1):
        body = line.split("#")[0].strip()
        if not body:
            continue
        if ":" in body:
            body = body.split(":", 1)[1]
        vals = _floats(body, path, lineno)
        if len(vals) == 12:
            return _check_K(np.array(vals).reshape(3, 4)[:, :3], path), None
        if len(vals) == 9:
            return _check_K(np.array(vals).reshape(3, 3), path), None
        if len(vals) == 4:
            return _check_K(np.array([[vals[0], 0, vals[2]], [0, vals[1], vals[3]], [0, 0, 1.0]]), path), None
        raise InputFormatError(
            f"a calibration line needs 12 numbers (KITTI P0), 9 (K) or 4 (fx fy cx cy), found {len(vals)}",
            path,
            lineno,
        )
    raise InputFormatError("no calibration found (empty file)", path)


def _floats(text: str, path: Path, line: int) -> list[float]:
    try:
        return [float(v) for v in text.replace(",", " ").split()]
    except ValueError as exc:
        raise InputFormatError(f"expected numbers: {exc}", path, line) from exc


def _check_K(K: np.ndarray, path: Path) -> np.ndarray:
    if not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0 or abs(K[2, 2] - 1.0) > 1e-9:
        raise InputFormatError(f"not a camera matrix (fx, fy > 0, K[2,2] = 1): {K.tolist()}", path)
    return K


def load_sequence(images: str | Path, calib: str | Path | None = None, rate_hz: float = 10.0) -> ImageSequence:
    """Find the images, timestamps, calibration and (optional) ground truth of ``images``: a
    KITTI-style folder (``image_l/`` or ``image_0/``, ``calib.txt``, optional ``times.txt``
    and ``poses.txt``), an EuRoC folder (``mav0/cam0/data`` + ``data.csv`` + ``sensor.yaml``)
    or a plain folder of images (timestamps = index / ``rate_hz``). ``calib`` overrides the
    folder's own calibration file."""
    root = Path(images)
    if not root.exists():
        raise InputFormatError("no such folder", root)
    if not root.is_dir():
        raise InputFormatError("IMAGES must be a folder of images (KITTI-style, EuRoC or plain)", root)
    gt = None
    times = None
    cam0 = next((c for c in (root / "mav0" / "cam0", root / "cam0") if (c / "data").is_dir()), None)
    if cam0 is not None:
        paths = _images_in(cam0 / "data")
        stamps = {p.stem: int(p.stem) * 1e-9 for p in paths if p.stem.isdigit()}
        times = np.array([stamps.get(p.stem, np.nan) for p in paths])
        default_calib = cam0 / "sensor.yaml"
    else:
        sub = next((root / s for s in ("image_l", "image_0") if (root / s).is_dir()), root)
        paths = _images_in(sub)
        default_calib = root / "calib.txt"
        if (root / "times.txt").is_file():
            times = np.array(_floats((root / "times.txt").read_text(), root / "times.txt", 1))
        if (root / "poses.txt").is_file():
            lines = (root / "poses.txt").read_text(encoding="utf-8").splitlines()
            rows = [_floats(ln, root / "poses.txt", i + 1) for i, ln in enumerate(lines) if ln.strip()]
            if all(len(r) == 12 for r in rows):
                gt = np.array(rows).reshape(-1, 3, 4)
    if not paths:
        raise InputFormatError(f"no images ({' '.join(sorted(IMAGE_EXTENSIONS))}) found", root)
    if times is None or len(times) != len(paths) or not np.all(np.isfinite(times)):
        times = np.arange(len(paths)) / rate_hz
    K, dist = read_calibration(calib if calib is not None else default_calib)
    if gt is not None and len(gt) != len(paths):
        gt = None
    return ImageSequence(paths, np.asarray(times, np.float64), K, dist, gt)


def read_gray(path: Path) -> np.ndarray:
    """An 8-bit grey image; :class:`InputFormatError` when the file cannot be decoded."""
    import cv2

    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None or img.size == 0:
        raise InputFormatError("cannot read the image (missing, truncated or not an image)", path)
    if img.ndim == 3:
        img = cv2.cvtColor(img[..., :3], cv2.COLOR_BGR2GRAY)
    if img.dtype != np.uint8:
        lo, hi = float(np.nanmin(img)), float(np.nanmax(img))
        img = np.nan_to_num((img.astype(np.float64) - lo) * (255.0 / max(hi - lo, 1e-12))).astype(np.uint8)
    return img


# --- features ----------------------------------------------------------------------------------


def detect(image: np.ndarray, detector: str = "sift", max_features: int = 2000) -> tuple[np.ndarray, np.ndarray]:
    """Keypoints ``(N, 7)`` (x, y, size, angle°, response, octave, Laplacian sign) and
    descriptors from :func:`jaxslam.vision.detect_and_describe` (SURF in JAX, OpenCV SIFT/ORB)."""
    from ._features import detect_and_describe

    if detector not in ("surf", "sift", "orb"):
        raise ConfigError(f"detector must be surf, sift or orb, got {detector!r}")
    kps, desc = detect_and_describe(image, detector=detector, max_keypoints=max_features)  # type: ignore[arg-type]
    return np.asarray(kps, np.float64), np.asarray(desc)


@dataclasses.dataclass
class VoConfig:
    """Options of :func:`run_vo`."""

    detector: str = "sift"
    """Feature detector: ``surf`` (JAX), ``sift`` or ``orb``."""
    enhance: bool = True
    """ABA-CLAHE on every image before detection (SPEC §3.1)."""
    ransac: str = "jax"
    """Outlier rejection for two-view geometry: ``jax`` (our vectorised RANSAC), ``opencv``
    (``findEssentialMat``) or ``none`` (no RANSAC anywhere: the paper's ablation)."""
    max_features: int = 2000
    ratio: float = 0.8
    """Lowe ratio for matching."""
    threshold_px: float = 1.0
    """Sampson threshold of the essential-matrix RANSAC, pixels."""
    pnp_threshold_px: float = 2.0
    init_parallax_px: float = 12.0
    """Median flow (pixels) the initial pair needs."""
    keyframe_parallax_px: float = 12.0
    """A frame whose median flow to the last keyframe exceeds this becomes a keyframe."""
    keyframe_track_ratio: float = 0.5
    """... or one that tracks fewer than this share of the last keyframe's map points."""
    min_parallax_deg: float = 0.5
    """Smallest ray angle for a new point."""
    max_reprojection_px: float = 2.0
    """Observations with a larger error are dropped (after each BA and at triangulation)."""
    window: int = 5
    """Keyframes optimised by each windowed BA."""
    window_ba_every: int = 3
    """Run the windowed BA every this many keyframes (0: never)."""
    local_keyframes: int = 3
    """Map points of the last this many keyframes are matched when tracking."""
    huber_px: float = 2.0
    final_ba_iterations: int = 50


@dataclasses.dataclass
class VoResult:
    """Output of :func:`run_vo`: ``poses`` ``(N, 7)`` world_T_camera for every input image
    (SE3 params; rows of unregistered images repeat the nearest registered pose),
    ``registered`` ``(N,)``, ``keyframes`` (indices), ``points`` ``(P, 3)``,
    ``residuals`` ``(O, 2)`` (pixels, final BA) and ``track_lengths`` ``(P,)``."""

    timestamps: np.ndarray
    poses: np.ndarray
    registered: np.ndarray
    keyframes: list[int]
    points: np.ndarray
    residuals: np.ndarray
    track_lengths: np.ndarray
    timings: dict[str, float]

    def stats(self) -> dict[str, float | int]:
        """The paper's Table 10 quantities."""
        err = np.linalg.norm(self.residuals, axis=1)
        tl = self.track_lengths
        return {
            "input_images": len(self.registered),
            "registered_images": int(self.registered.sum()),
            "keyframes": len(self.keyframes),
            "points": len(self.points),
            "residuals": len(self.residuals),
            "track_length_min": int(tl.min()) if len(tl) else 0,
            "track_length_mean": float(tl.mean()) if len(tl) else 0.0,
            "track_length_max": int(tl.max()) if len(tl) else 0,
            "reprojection_rmse_px": float(np.sqrt(np.mean(err**2))) if len(err) else float("nan"),
            "residuals_below_1px": float(np.mean(np.abs(self.residuals) < 1.0)) if len(err) else float("nan"),
        }


# --- small pose helpers (numpy; 4x4 camera_T_world matrices) -----------------------------------


def _quat_from_matrix(R: np.ndarray) -> np.ndarray:
    """Unit quaternions (w, x, y, z) of rotation matrices ``(N, 3, 3)`` (Shepperd's method)."""
    R = np.asarray(R, np.float64)
    tr = np.trace(R, axis1=-2, axis2=-1)
    cands = np.stack(
        [
            np.stack([1 + tr, R[:, 2, 1] - R[:, 1, 2], R[:, 0, 2] - R[:, 2, 0], R[:, 1, 0] - R[:, 0, 1]], -1),
            np.stack(
                [R[:, 2, 1] - R[:, 1, 2], 1 + 2 * R[:, 0, 0] - tr, R[:, 0, 1] + R[:, 1, 0], R[:, 0, 2] + R[:, 2, 0]], -1
            ),
            np.stack(
                [R[:, 0, 2] - R[:, 2, 0], R[:, 0, 1] + R[:, 1, 0], 1 + 2 * R[:, 1, 1] - tr, R[:, 1, 2] + R[:, 2, 1]], -1
            ),
            np.stack(
                [R[:, 1, 0] - R[:, 0, 1], R[:, 0, 2] + R[:, 2, 0], R[:, 1, 2] + R[:, 2, 1], 1 + 2 * R[:, 2, 2] - tr], -1
            ),
        ],
        1,
    )
    k = np.argmax(np.stack([tr, R[:, 0, 0], R[:, 1, 1], R[:, 2, 2]], -1), axis=-1)
    q = cands[np.arange(len(R)), k]
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    return q * np.where(q[:, :1] < 0, -1.0, 1.0)


def _to_params(T_cw: np.ndarray) -> np.ndarray:
    """SE3 params (qw qx qy qz x y z) of world_T_camera from camera_T_world matrices (N, 4, 4)."""
    T_wc = np.linalg.inv(T_cw)
    return np.concatenate([_quat_from_matrix(T_wc[:, :3, :3]), T_wc[:, :3, 3]], axis=-1)


def _from_params(params: np.ndarray) -> np.ndarray:
    """camera_T_world matrices (N, 4, 4) from world_T_camera SE3 params (N, 7)."""
    q = np.asarray(params, np.float64)[:, :4]
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    w, x, y, z = q.T
    R = np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
            np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
            np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
        ],
        -2,
    )
    T = np.tile(np.eye(4), (len(q), 1, 1))
    T[:, :3, :3] = R
    T[:, :3, 3] = params[:, 4:]
    return np.linalg.inv(T)


def _rt(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = np.ravel(t)
    return T


def _project(T_cw: np.ndarray, X: np.ndarray, K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    Xc = X @ T_cw[:3, :3].T + T_cw[:3, 3]
    z = Xc[:, 2]
    zs = np.where(z > 1e-9, z, 1.0)
    uv = np.stack([Xc[:, 0] / zs, Xc[:, 1] / zs], 1) @ K[:2, :2].T + K[:2, 2]
    return uv, z > 1e-9


def _normalize(uv: np.ndarray, K: np.ndarray) -> np.ndarray:
    return (uv - K[:2, 2]) @ np.linalg.inv(K[:2, :2]).T


def _sampson_np(R: np.ndarray, t: np.ndarray, x1: np.ndarray, x2: np.ndarray) -> np.ndarray:
    """NumPy twin of :func:`~jaxslam.vision.sampson_error` for one pose (driver-side gate)."""
    tx = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
    E = tx @ R
    h1 = np.c_[x1, np.ones(len(x1))]
    h2 = np.c_[x2, np.ones(len(x2))]
    ex1, etx2 = h1 @ E.T, h2 @ E
    num = np.sum(h2 * ex1, 1) ** 2
    return num / np.maximum(ex1[:, 0] ** 2 + ex1[:, 1] ** 2 + etx2[:, 0] ** 2 + etx2[:, 1] ** 2, 1e-300)


@dataclasses.dataclass
class _Frame:
    uv: np.ndarray
    desc: np.ndarray
    sign: np.ndarray | None


class _Vo:
    """The state of one run (frames, map, observations); see the module doc."""

    def __init__(self, frames: list[_Frame], K: np.ndarray, config: VoConfig):
        self.f = frames
        self.K = K
        self.c = config
        n = len(frames)
        self.T = np.full((n, 4, 4), np.nan)  # camera_T_world per frame
        self.kfs: list[int] = []
        self.kf_pt: dict[int, np.ndarray] = {}  # keyframe -> point id per keypoint (-1: none)
        self.X = np.zeros((0, 3))
        self.pdesc = np.zeros((0, *frames[0].desc.shape[1:]), frames[0].desc.dtype)
        self.psign = np.zeros(0)
        self.palive = np.zeros(0, bool)
        self.o_cam: list[int] = []
        self.o_pt: list[int] = []
        self.o_kp: list[int] = []
        self.o_ok: list[bool] = []
        self.track: dict[int, tuple[np.ndarray, np.ndarray]] = {}  # frame -> (kp idx, pt id)
        self.kf_since_ba = 0
        self.scale_pair: tuple[int, int] | None = None

    # -- matching and geometry helpers --
    def _match(self, d1, d2, s1=None, s2=None) -> np.ndarray:
        gate = self.c.detector == "surf" and s1 is not None and s2 is not None
        pairs, _ = match_descriptors(
            d1, d2, ratio=self.c.ratio, cross_check=True, sign1=s1 if gate else None, sign2=s2 if gate else None
        )
        return pairs

    def _add_points(self, X: np.ndarray, desc: np.ndarray, sign: np.ndarray | None) -> np.ndarray:
        ids = np.arange(len(self.X), len(self.X) + len(X))
        self.X = np.concatenate([self.X, X])
        self.pdesc = np.concatenate([self.pdesc, desc])
        self.psign = np.concatenate([self.psign, np.zeros(len(X)) if sign is None else sign])
        self.palive = np.concatenate([self.palive, np.ones(len(X), bool)])
        return ids

    def _observe(self, kf: int, kp: np.ndarray, pt: np.ndarray) -> None:
        kp = np.asarray(kp, np.int64)
        pt = np.asarray(pt, np.int64)
        self.kf_pt[kf][kp] = pt
        self.o_cam += [kf] * len(kp)
        self.o_pt += pt.tolist()
        self.o_kp += kp.tolist()
        self.o_ok += [True] * len(kp)

    def _obs_arrays(self):
        cam = np.asarray(self.o_cam, np.int64)
        kp = np.asarray(self.o_kp, np.int64)
        uv = np.zeros((len(cam), 2))
        for k in np.unique(cam):
            m = cam == k
            uv[m] = self.f[k].uv[kp[m]]
        return cam, np.asarray(self.o_pt, np.int64), kp, uv, np.asarray(self.o_ok, bool)

    def _triangulate(self, a: int, b: int, uva: np.ndarray, uvb: np.ndarray):
        """Points from pixel pairs in frames a, b with known poses; returns (X, ok)."""
        xa, xb = _normalize(uva, self.K), _normalize(uvb, self.K)
        X, ok = triangulate_points(self.T[a][:3], self.T[b][:3], xa, xb)
        for k, uv in ((a, uva), (b, uvb)):
            proj, front = _project(self.T[k], X, self.K)
            ok &= front & (np.linalg.norm(proj - uv, axis=1) < self.c.max_reprojection_px)
        ca = -self.T[a][:3, :3].T @ self.T[a][:3, 3]
        cb = -self.T[b][:3, :3].T @ self.T[b][:3, 3]
        ra, rb = X - ca, X - cb
        cos = np.sum(ra * rb, 1) / np.maximum(np.linalg.norm(ra, axis=1) * np.linalg.norm(rb, axis=1), 1e-300)
        ok &= cos < np.cos(np.radians(self.c.min_parallax_deg))
        return X, ok

    # -- initialisation --
    def initialise(self) -> bool:
        c, f0 = self.c, self.f[0]
        for j in range(1, len(self.f)):
            pairs = self._match(f0.desc, self.f[j].desc, f0.sign, self.f[j].sign)
            if len(pairs) < 30:
                continue
            uv0, uvj = f0.uv[pairs[:, 0]], self.f[j].uv[pairs[:, 1]]
            R, t, inl = relative_pose(uv0, uvj, self.K, method=c.ransac, threshold_px=c.threshold_px)
            flow = np.median(np.linalg.norm(uvj[inl] - uv0[inl], axis=1)) if inl.sum() else 0.0
            if inl.sum() < 50 or flow < c.init_parallax_px:
                continue
            self.T[0] = np.eye(4)
            self.T[j] = _rt(R, t)
            X, ok = self._triangulate(0, j, uv0, uvj)
            ok &= inl
            if ok.sum() < 30:
                continue
            for k in (0, j):
                self.kfs.append(k)
                self.kf_pt[k] = np.full(len(self.f[k].uv), -1, np.int64)
            sign_j = self.f[j].sign
            ids = self._add_points(
                X[ok], self.f[j].desc[pairs[ok, 1]], None if sign_j is None else sign_j[pairs[ok, 1]]
            )
            self._observe(0, pairs[ok, 0], ids)
            self._observe(j, pairs[ok, 1], ids)
            self.scale_pair = (0, j)
            self.bundle(self.kfs, fixed=[0], scale_pair=(0, j))
            return True
        return False

    # -- tracking --
    def track_frame(self, i: int, candidates: np.ndarray | None = None) -> int:
        """PnP of frame i against map points (``candidates``: point ids; default the local
        map). Sets ``T[i]`` and ``track[i]``; returns the number of inliers (0: failed)."""
        import cv2

        if candidates is None:
            cam, pt, _, _, ok = self._obs_arrays()
            recent = np.isin(cam, self.kfs[-self.c.local_keyframes :]) & ok
            candidates = np.unique(pt[recent])
        candidates = candidates[self.palive[candidates]]
        if len(candidates) < 6:
            return 0
        fr = self.f[i]
        pairs = self._match(
            fr.desc, self.pdesc[candidates], fr.sign, self.psign[candidates] if fr.sign is not None else None
        )
        if len(pairs) < 6:
            return 0
        kp, pt = pairs[:, 0], candidates[pairs[:, 1]]
        obj, img = self.X[pt].astype(np.float64), fr.uv[kp].astype(np.float64)
        prev = self.T[i - 1] if i > 0 and np.isfinite(self.T[i - 1]).all() else None
        if self.c.ransac == "none":
            if prev is None:
                ok_, rvec, tvec = cv2.solvePnP(obj, img, self.K, None, flags=cv2.SOLVEPNP_EPNP)
            else:
                rvec0, tvec0 = cv2.Rodrigues(prev[:3, :3])[0], prev[:3, 3].reshape(3, 1).copy()
                ok_, rvec, tvec = cv2.solvePnP(obj, img, self.K, None, rvec0, tvec0, True, cv2.SOLVEPNP_ITERATIVE)
            inl: np.ndarray = np.arange(len(kp))
        else:
            ok_, rvec, tvec, inl = cv2.solvePnPRansac(
                obj,
                img,
                self.K,
                None,
                iterationsCount=300,
                reprojectionError=self.c.pnp_threshold_px,
                confidence=0.999,
                flags=cv2.SOLVEPNP_EPNP,
            )
            if not ok_ or inl is None or len(inl) < 10:
                return 0
            inl = inl[:, 0]
            rvec, tvec = cv2.solvePnPRefineLM(obj[inl], img[inl], self.K, None, rvec, tvec)
            proj = cv2.projectPoints(obj, rvec, tvec, self.K, None)[0][:, 0]
            inl = np.nonzero(np.linalg.norm(proj - img, axis=1) < self.c.pnp_threshold_px)[0]
        if not ok_ or len(inl) < 10:
            return 0
        self.T[i] = _rt(cv2.Rodrigues(rvec)[0], tvec)
        self.track[i] = (kp[inl], pt[inl])
        return len(inl)

    # -- keyframes --
    def is_keyframe(self, i: int, n_tracked: int) -> bool:
        last = self.kfs[-1]
        kp, pt = self.track[i]
        kf_kp = np.full(len(self.X), -1)
        has = self.kf_pt[last] >= 0
        kf_kp[self.kf_pt[last][has]] = np.nonzero(has)[0]
        common = kf_kp[pt] >= 0
        if common.sum() == 0:
            return True
        flow = np.median(np.linalg.norm(self.f[i].uv[kp[common]] - self.f[last].uv[kf_kp[pt[common]]], axis=1))
        return bool(flow > self.c.keyframe_parallax_px or n_tracked < self.c.keyframe_track_ratio * has.sum())

    def add_keyframe(self, i: int) -> None:
        prev = self.kfs[-1]
        self.kfs.append(i)
        self.kf_pt[i] = np.full(len(self.f[i].uv), -1, np.int64)
        kp, pt = self.track[i]
        self._observe(i, kp, pt)
        fi, fp = self.f[i], self.f[prev]
        pairs = self._match(fp.desc, fi.desc, fp.sign, fi.sign)
        pairs = pairs[self.kf_pt[i][pairs[:, 1]] < 0]
        existing = self.kf_pt[prev][pairs[:, 0]]
        # matches to points the previous keyframe sees: extend the track if it reprojects
        ext = pairs[existing >= 0]
        if len(ext):
            ept = existing[existing >= 0]
            ok = self.palive[ept] & ~np.isin(ept, self.kf_pt[i])
            proj, front = _project(self.T[i], self.X[ept], self.K)
            ok &= front & (np.linalg.norm(proj - fi.uv[ext[:, 1]], axis=1) < self.c.max_reprojection_px)
            _, first = np.unique(ept, return_index=True)
            keep = np.zeros(len(ept), bool)
            keep[first] = True
            ok &= keep
            self._observe(i, ext[ok, 1], ept[ok])
        # new points from the other matches: epipolar gate, then triangulation gates
        new = pairs[existing < 0]
        if len(new) == 0:
            return
        uvp, uvi = fp.uv[new[:, 0]], fi.uv[new[:, 1]]
        T_ip = self.T[i] @ np.linalg.inv(self.T[prev])
        t = T_ip[:3, 3] / max(np.linalg.norm(T_ip[:3, 3]), 1e-12)
        f = 0.5 * (self.K[0, 0] + self.K[1, 1])
        samp = _sampson_np(T_ip[:3, :3], t, _normalize(uvp, self.K), _normalize(uvi, self.K)) * f * f
        X, ok = self._triangulate(prev, i, uvp, uvi)
        ok &= samp < (2.0 * self.c.threshold_px) ** 2
        if ok.sum() == 0:
            return
        ids = self._add_points(X[ok], fi.desc[new[ok, 1]], None if fi.sign is None else fi.sign[new[ok, 1]])
        self._observe(prev, new[ok, 0], ids)
        self._observe(i, new[ok, 1], ids)

    # -- bundle adjustment --
    def bundle(self, window: list[int], fixed: list[int] | None = None, scale_pair=None, iterations: int = 20):
        cam, pt, _, uv, ok = self._obs_arrays()
        sel_pts = np.unique(pt[ok & np.isin(cam, window)])
        sel_pts = sel_pts[self.palive[sel_pts]]
        m = ok & np.isin(pt, sel_pts)
        if m.sum() == 0:
            return None
        cams = np.unique(cam[m])
        if fixed is None:
            fixed = [k for k in cams if k not in window]
            if len(fixed) < 2:  # gauge and scale: hold the oldest keyframe, the next one's distance
                fixed = [int(cams[0])]
                scale_pair = (int(cams[0]), int(cams[1])) if len(cams) > 1 else None
        poses = np.zeros((len(self.f), 7))
        poses[:, 0] = 1.0
        poses[cams] = _to_params(self.T[cams])
        res = bundle_adjust(
            poses,
            self.X,
            cam[m],
            pt[m],
            uv[m],
            self.K,
            fixed_cameras=fixed,
            scale_prior=scale_pair,
            huber_px=self.c.huber_px,
            max_iterations=iterations,
        )
        self.T[cams] = _from_params(res.poses[cams])
        self.X[sel_pts] = res.points[sel_pts]
        self.cull(np.nonzero(m)[0])
        return res

    def cull(self, obs_idx: np.ndarray) -> None:
        """Drop observations (among ``obs_idx``) that reproject worse than the gate, then points
        seen by fewer than two keyframes."""
        cam, pt, kp, uv, ok = self._obs_arrays()
        err = np.full(len(obs_idx), np.inf)
        for k in np.unique(cam[obs_idx]):
            m = cam[obs_idx] == k
            proj, front = _project(self.T[k], self.X[pt[obs_idx][m]], self.K)
            err[m] = np.where(front, np.linalg.norm(proj - uv[obs_idx][m], axis=1), np.inf)
        bad = obs_idx[~(err < self.c.max_reprojection_px)]
        for o in bad:
            self.o_ok[o] = False
            self.kf_pt[cam[o]][kp[o]] = -1
        ok = np.asarray(self.o_ok, bool)
        counts = np.bincount(pt[ok], minlength=len(self.X))
        dead = np.nonzero(self.palive & (counts < 2))[0]
        self.palive[dead] = False
        kill = ok & np.isin(pt, dead)
        for o in np.nonzero(kill)[0]:
            self.o_ok[o] = False
            self.kf_pt[cam[o]][kp[o]] = -1

    # -- the whole run --
    def run(self) -> None:
        if not self.initialise():
            raise VoError("initialisation failed: no frame pair with enough matches and parallax")
        start = self.kfs[-1] + 1
        for i in range(start, len(self.f)):
            n = self.track_frame(i)
            if n == 0:
                continue
            if self.is_keyframe(i, n) or i == len(self.f) - 1:
                self.add_keyframe(i)
                self.kf_since_ba += 1
                if self.c.window_ba_every and self.kf_since_ba >= self.c.window_ba_every:
                    self.bundle(self.kfs[-self.c.window :])
                    self.kf_since_ba = 0

    def final(self) -> None:
        for _ in range(2):
            self.bundle(
                self.kfs, fixed=[self.kfs[0]], scale_pair=self.scale_pair, iterations=self.c.final_ba_iterations
            )
        # re-localise every non-keyframe against the final map (all alive points)
        alive = np.nonzero(self.palive)[0]
        for i in range(len(self.f)):
            if i in self.kf_pt:
                continue
            self.T[i] = np.nan
            self.track.pop(i, None)
            self.track_frame(i, candidates=alive)


def run_vo(sequence: ImageSequence, config: VoConfig | None = None, progress=None) -> VoResult:
    """Monocular VO over ``sequence``; see the module doc. ``progress(stage, i, n)`` is called
    while images are read."""
    import time

    import cv2

    config = config or VoConfig()
    if config.detector not in ("surf", "sift", "orb"):
        raise ConfigError(f"detector must be surf, sift or orb, got {config.detector!r}")
    if config.ransac not in ("jax", "opencv", "none"):
        raise ConfigError(f"ransac must be jax, opencv or none, got {config.ransac!r}")
    n = len(sequence.paths)
    if n < 2:
        raise InputFormatError(f"visual odometry needs at least 2 images, found {n}", sequence.paths[0] if n else None)
    timings: dict[str, float] = {}
    t0 = time.perf_counter()
    frames: list[_Frame] = []
    shape = None
    for i, path in enumerate(sequence.paths):
        img = read_gray(path)
        if shape is None:
            shape = img.shape
        elif img.shape != shape:
            raise InputFormatError(f"image size {img.shape[::-1]} differs from the first image's {shape[::-1]}", path)
        if config.enhance:
            from ._enhance import aba_clahe

            img = np.asarray(aba_clahe(img))
        kps, desc = detect(img, config.detector, config.max_features)
        uv = kps[:, :2].astype(np.float64)
        if sequence.distortion is not None and len(uv):
            uv = cv2.undistortPoints(uv[:, None], sequence.K, sequence.distortion, P=sequence.K)[:, 0].astype(
                np.float64
            )
        sign = kps[:, 6].astype(np.int8) if config.detector == "surf" else None
        frames.append(_Frame(uv, desc, sign))
        if progress is not None:
            progress("features", i + 1, n)
    timings["features_s"] = time.perf_counter() - t0
    if sum(len(f.uv) for f in frames) == 0:
        raise VoError("no features found in any image")
    t0 = time.perf_counter()
    vo = _Vo(frames, sequence.K, config)
    vo.run()
    timings["tracking_s"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    vo.final()
    timings["final_ba_s"] = time.perf_counter() - t0
    registered = np.all(np.isfinite(vo.T.reshape(n, -1)), axis=1)
    T = vo.T.copy()
    reg_idx = np.nonzero(registered)[0]
    for k in np.nonzero(~registered)[0]:  # one row per image: hold the nearest registered pose
        T[k] = T[reg_idx[int(np.argmin(np.abs(reg_idx - k)))]]
    poses = _to_params(T)
    cam, pt, _, uv, ok = vo._obs_arrays()
    ok &= vo.palive[pt]
    keep = np.nonzero(vo.palive)[0]
    remap = np.full(len(vo.X), -1)
    remap[keep] = np.arange(len(keep))
    res = reprojection_residuals(poses, vo.X, cam[ok], pt[ok], uv[ok], sequence.K)
    tracks = np.bincount(remap[pt[ok]], minlength=len(keep))
    return VoResult(sequence.timestamps, poses, registered, list(vo.kfs), vo.X[keep], res, tracks, timings)


# --- evaluation against ground truth -----------------------------------------------------------


def umeyama_alignment(
    src: np.ndarray, dst: np.ndarray, with_scale: bool = True
) -> tuple[float, np.ndarray, np.ndarray]:
    """``(s, R, t)`` minimising ``sum |dst_i - (s R src_i + t)|^2`` for point sets ``(N, 3)``
    (Umeyama, "Least-squares estimation of transformation parameters between two point
    patterns", PAMI 1991; the alignment ``evo_ape -as`` uses)."""
    src = np.asarray(src, np.float64)
    dst = np.asarray(dst, np.float64)
    if src.shape != dst.shape or src.ndim != 2 or src.shape[1] != 3 or len(src) < 3:
        raise ValueError(f"umeyama_alignment needs two (N, 3) arrays with N >= 3, got {src.shape}, {dst.shape}")
    mu_s, mu_d = src.mean(0), dst.mean(0)
    xs, xd = src - mu_s, dst - mu_d
    cov = xd.T @ xs / len(src)
    u, d, vt = np.linalg.svd(cov)
    S = np.eye(3)
    if np.linalg.det(u) * np.linalg.det(vt) < 0:
        S[2, 2] = -1.0
    R = u @ S @ vt
    var_s = np.mean(np.sum(xs**2, axis=1))
    s = float(np.trace(np.diag(d) @ S) / var_s) if with_scale else 1.0
    t = mu_d - s * R @ mu_s
    return s, R, t


def ape_sim3(estimate: np.ndarray, reference: np.ndarray) -> dict[str, float]:
    """Absolute position error after Sim(3) alignment of ``estimate`` to ``reference``
    (positions ``(N, 3)``): RMSE, mean, max (in the reference's units), the path length of
    the reference and the RMSE as a percentage of it."""
    s, R, t = umeyama_alignment(estimate, reference, with_scale=True)
    aligned = s * np.asarray(estimate) @ R.T + t
    err = np.linalg.norm(aligned - reference, axis=1)
    length = float(np.sum(np.linalg.norm(np.diff(reference, axis=0), axis=1)))
    rmse = float(np.sqrt(np.mean(err**2)))
    return {
        "rmse": rmse,
        "mean": float(err.mean()),
        "max": float(err.max()),
        "scale": s,
        "path_length": length,
        "rmse_percent_of_path": 100.0 * rmse / length if length > 0 else float("nan"),
    }

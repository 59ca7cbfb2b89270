"""Visual odometry between keyframes with metric scale from LiDAR depth (SPEC §3.3).

Per keyframe image: ABA-CLAHE (optional), features (SURF by default), undistorted normalised
coordinates, and depth for the features that LiDAR points land near: the deskewed scan at the
keyframe time is projected into the image and a plane fitted to the points within a few pixels
of a feature; the feature's ray meets that plane (unbiased on walls, unlike the nearest
point's depth). Between consecutive keyframes: descriptor matching (ratio test, cross-check,
Laplacian-sign gate), essential-matrix RANSAC (jaxslam's JAX MSAC; ``ransac=False`` keeps every
match), then a motion-only Gauss-Newton (Huber) of the previous keyframe's 3-D points
reprojected into the current image: a metric relative pose and its information
(``J^T J / sigma_px^2``), expressed for the body frame's between factor. Scale never comes
from ground truth.
"""

from __future__ import annotations

import dataclasses

import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree

from ..lie import host
from ..vision import aba_clahe, detect_and_describe, find_essential, match_descriptors
from ._config import RigConfig, VisionConfig

INLIER_PX = 2.0
"""The motion-only fit's inlier threshold (px); ``vision.wide_inlier_px`` widens it."""


def undistort_normalized(uv: np.ndarray, K: np.ndarray, dist: tuple[float, ...], iters: int = 20) -> np.ndarray:
    """Normalised undistorted coordinates (N, 2) of distorted pixels (N, 2) (radtan, inverted
    by fixed-point iteration)."""
    xd = (uv[:, 0] - K[0, 2]) / K[0, 0]
    yd = (uv[:, 1] - K[1, 2]) / K[1, 1]
    if not any(dist):
        return np.stack([xd, yd], 1)
    k1, k2, p1, p2 = [*list(dist), 0, 0, 0, 0][:4]
    x, y = xd.copy(), yd.copy()
    for _ in range(iters):
        r2 = x * x + y * y
        radial = 1 + k1 * r2 + k2 * r2 * r2
        dx = 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
        dy = p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
        x = (xd - dx) / radial
        y = (yd - dy) / radial
    return np.stack([x, y], 1)


def distort_normalized(xn: np.ndarray, dist: tuple[float, ...]) -> np.ndarray:
    """Radial-tangential distortion (``k1, k2, p1, p2``) of normalised coordinates (..., 2):
    the forward model :func:`undistort_normalized` inverts."""
    x, y = xn[..., 0], xn[..., 1]
    if not any(dist):
        return np.stack([x, y], -1)
    k1, k2, p1, p2 = [*list(dist), 0, 0, 0, 0][:4]
    r2 = x * x + y * y
    radial = 1 + k1 * r2 + k2 * r2 * r2
    return np.stack(
        [x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x), y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y], -1
    )


@dataclasses.dataclass
class KeyframeFeatures:
    kf: int
    t: float
    uv: np.ndarray
    """Measured pixels (N, 2)."""
    xn: np.ndarray
    """Undistorted normalised coordinates (N, 2)."""
    desc: np.ndarray
    sign: np.ndarray
    X: np.ndarray
    """Camera-frame 3-D points from LiDAR depth (N, 3), NaN where there is none."""
    track: np.ndarray
    """Track id per feature (N,)."""
    X_scan: np.ndarray | None = None
    """Camera-frame 3-D points from the keyframe's own scan only (N, 3), NaN where none."""
    normal: np.ndarray | None = None
    """Unit normals (camera frame, facing it) of the LiDAR planes behind ``X`` (N, 3)."""
    image: np.ndarray | None = None
    """The grey image the features came from, before enhancement (H, W) uint8: the patches
    :func:`align_patches` compares."""


@dataclasses.dataclass
class VisualMeasurement:
    """A metric relative pose between two keyframes' bodies (``T_i^-1 T_j``)."""

    i: int
    j: int
    T: np.ndarray
    information: np.ndarray
    """(6, 6) for the between factor (body tangent, [rotation, translation])."""
    inliers: int
    matches: int
    X_i: np.ndarray
    """Inlier 3-D points in camera i (M, 3) and their normalised observations in j (M, 2)."""
    xn_j: np.ndarray
    rmse_px: float
    refined: bool = False
    """Its keypoints in ``j`` were replaced by aligned patches (``vision.patch_refine``)."""


@dataclasses.dataclass
class DirectionMeasurement:
    """A scale-free relative pose (no metric depth): camera j's rotation ``R`` and unit
    position ``u`` in camera i, from the essential matrix (RANSAC inliers)."""

    i: int
    j: int
    R: np.ndarray
    u: np.ndarray
    inliers: int


def plane_depth(
    xn: np.ndarray,
    pts_c: np.ndarray,
    radius: float,
    min_points: int = 5,
    max_rms: float = 0.03,
    k: int = 10,
    normals: bool = False,
) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
    """3-D points (N, 3) where each normalised ray ``(x, y, 1)`` meets the plane fitted to the
    camera-frame LiDAR points ``pts_c`` projecting within ``radius`` (normalised units); NaN
    where fewer than ``min_points`` are near or the fit is not planar (RMS above ``max_rms`` m).
    With ``normals``, also the planes' unit normals (N, 3), facing the camera."""
    out = np.full((len(xn), 3), np.nan)
    nrm = np.full((len(xn), 3), np.nan)
    if len(pts_c) < min_points or not len(xn):
        return (out, nrm) if normals else out
    proj = pts_c[:, :2] / pts_c[:, 2:3]
    tree = cKDTree(proj, balanced_tree=False, compact_nodes=False)  # a faster build, exact queries
    d, idx = tree.query(xn, k=k, distance_upper_bound=radius)
    ok = np.isfinite(d)
    cnt = ok.sum(1)
    sel = np.nonzero(cnt >= min_points)[0]
    if not len(sel):
        return (out, nrm) if normals else out
    idx_s = np.where(ok[sel], idx[sel], 0)
    w = ok[sel].astype(np.float64)
    P = pts_c[idx_s]  # (S, k, 3)
    c = (P * w[..., None]).sum(1) / w.sum(1, keepdims=True)
    Q = (P - c[:, None]) * w[..., None]
    C = np.einsum("ski,skj->sij", Q, Q) / w.sum(1)[:, None, None]
    evals, evecs = np.linalg.eigh(C)
    n = evecs[:, :, 0]
    rms = np.sqrt(np.maximum(evals[:, 0], 0))
    rays = np.concatenate([xn[sel], np.ones((len(sel), 1))], 1)
    denom = np.einsum("si,si->s", n, rays)
    lam = np.einsum("si,si->s", n, c) / np.where(np.abs(denom) < 1e-9, np.nan, denom)
    good = (rms < max_rms) & np.isfinite(lam) & (lam > 0.3)
    # the hit must lie near the fitted points (no extrapolation across a depth edge)
    X = rays * lam[:, None]
    spread = np.sqrt(np.maximum(evals[:, 2], 0)) + 0.05
    good &= np.linalg.norm(X - c, axis=1) < 3 * spread
    out[sel[good]] = X[good]
    if not normals:
        return out
    n = n * -np.sign(np.einsum("si,si->s", n, rays))[:, None]  # facing the camera
    nrm[sel[good]] = n[good]
    return out, nrm


class VisualFrontend:
    """Keyframe features and metric relative poses (see the module docstring)."""

    def __init__(self, config: VisionConfig, rig: RigConfig):
        self.cfg, self.rig = config, rig
        self.K = rig.K()
        self.f = 0.5 * (self.K[0, 0] + self.K[1, 1])
        self.T_bc = host.params_to_matrix(np.asarray(rig.body_T_camera))
        self.T_cb = host.inverse(self.T_bc)
        self._next_track = 0
        self.guided_fits = 0
        """Relative poses fitted on guided pairs at 2 px (``vision.guided_information_scale``)."""
        self.wide_fits = 0
        """Relative poses fitted at ``vision.wide_inlier_px`` (the 2 px fit had failed)."""
        self.patch_refined = 0
        """Relative poses fitted on patch-aligned points (``vision.patch_refine``)."""
        self.patch_retried = 0
        """Of those, the ones aligned by the retry (``vision.patch_retry_half``)."""

    def features(
        self,
        kf: int,
        t: float,
        image: np.ndarray,
        points_body: np.ndarray | None,
        scan_body: np.ndarray | None = None,
    ) -> KeyframeFeatures:
        """Features of one keyframe image, with depth from ``points_body`` (the local map in
        the body frame) and, separately, from ``scan_body`` (its own scan) when given."""
        cfg = self.cfg
        img = np.asarray(image)
        if img.ndim == 3:
            img = img.max(axis=2) if img.dtype == np.uint8 else img
        if img.dtype != np.uint8:
            img = np.clip(np.asarray(img, np.float64) * (255.0 if img.max() <= 1.0 else 1.0), 0, 255).astype(np.uint8)
        grey = img
        if cfg.enhance:
            img = np.asarray(aba_clahe(img, cfg.alpha, cfg.beta, cfg.clip))
        # one call (parallel=False): the estimator already runs vision on one core beside
        # the LiDAR front end on the other
        kp, desc = detect_and_describe(
            img,
            cfg.detector,  # type: ignore[arg-type]
            cfg.hessian_threshold,
            cfg.max_keypoints,
            parallel=False,
        )
        uv = kp[:, :2].astype(np.float64)
        xn = undistort_normalized(uv, self.K, self.rig.camera_distortion)
        X, normal = self._depth(xn, points_body)
        X_scan = self._depth(xn, scan_body)[0] if scan_body is not None else None
        track = np.arange(self._next_track, self._next_track + len(uv))
        self._next_track += len(uv)
        sign = kp[:, 6].astype(np.float64)
        return KeyframeFeatures(kf, t, uv, xn, desc, sign, X, track, X_scan, normal, grey)

    def _depth(self, xn: np.ndarray, points_body: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
        """Camera-frame points of the features ``xn`` from LiDAR points in the body frame, and
        the normals of the planes they lie on (NaN where none)."""
        if points_body is None or not len(points_body):
            return np.full((len(xn), 3), np.nan), np.full((len(xn), 3), np.nan)
        pc = host.transform_points(self.T_cb, points_body)
        pc = pc[(pc[:, 2] > 0.3) & (pc[:, 2] < self.cfg.max_depth)]
        return plane_depth(xn, pc, self.cfg.depth_radius_px / self.f, normals=True)  # type: ignore[return-value]

    def relative(
        self, a: KeyframeFeatures, b: KeyframeFeatures, T_ab_guess: np.ndarray
    ) -> VisualMeasurement | DirectionMeasurement | None:
        """Relative body pose ``T_a^-1 T_b`` from keyframe ``a`` to ``b`` (``T_ab_guess`` from
        the IMU/LiDAR estimate seeds the refinement); None when too few inliers survive."""
        cfg = self.cfg
        if len(a.uv) < 8 or len(b.uv) < 8:
            return None
        T_cacb = self.T_cb @ T_ab_guess @ self.T_bc  # camera a <- camera b
        signs = (a.sign, b.sign) if cfg.detector == "surf" else (None, None)
        pairs, _ = match_descriptors(a.desc, b.desc, ratio=cfg.ratio, cross_check=True, sign1=signs[0], sign2=signs[1])
        fit = None
        if len(pairs) >= max(8, cfg.min_inliers):
            ia, ib = pairs[:, 0], pairs[:, 1]
            res = None
            if cfg.ransac:
                res = find_essential(a.xn[ia], b.xn[ib], cfg.ransac_threshold_px / self.f)
                keep = np.asarray(res.inliers)
                ia, ib = ia[keep], ib[keep]
            has = np.isfinite(a.X[ia, 0])
            if has.sum() >= cfg.min_inliers:
                ia, ib = ia[has], ib[has]
                fit = motion_only(a.X[ia], b.xn[ib], host.inverse(T_cacb), self.f, cfg.min_inliers)
            elif (
                cfg.direction_fallback
                and res is not None
                and len(ia) >= cfg.min_inliers
                and float(np.linalg.norm(T_ab_guess[:3, 3])) > cfg.direction_min_motion
            ):
                # no metric depth (no LiDAR map there): the scale-free two-view pose
                R, t = np.asarray(res.R), np.asarray(res.t)  # camera b from camera a: X_b = R X_a + t
                u = -R.T @ t
                if np.all(np.isfinite(u)) and np.linalg.norm(u) > 1e-9:
                    return DirectionMeasurement(a.kf, b.kf, R.T, u / np.linalg.norm(u), len(ia))
        n_pairs = len(pairs)
        pixel_sigma = cfg.pixel_sigma
        info_scale = cfg.information_scale
        if fit is None and cfg.guided_radius_px > 0:
            # too few global matches (dark, noisy keypoints; a turn on the spot): match again
            # where the predicted motion puts a's 3-D points, then the same robust fit
            gp = self.guided_pairs(a, b, host.inverse(T_cacb))
            if len(gp) >= cfg.min_inliers:
                ia, ib = gp[:, 0], gp[:, 1]
                fit = motion_only(a.X[ia], b.xn[ib], host.inverse(T_cacb), self.f, cfg.min_inliers)
                n_pairs = len(gp)
                if fit is not None:  # pairs chosen near the prediction lean towards it
                    info_scale *= cfg.guided_information_scale
                    self.guided_fits += 1
                if fit is None and cfg.wide_inlier_px > INLIER_PX:
                    # dark, motion-blurred keypoints scatter past the gate: a wider one, and a
                    # pixel sigma widened by as much so the pose weighs less
                    fit = motion_only(
                        a.X[ia], b.xn[ib], host.inverse(T_cacb), self.f, cfg.min_inliers, inlier_px=cfg.wide_inlier_px
                    )
                    if fit is not None:
                        pixel_sigma *= cfg.wide_inlier_px / INLIER_PX
                        self.wide_fits += 1
        if fit is None:
            return None
        T_cbca, keep, e = fit
        X, x, ia, ib = a.X[ia][keep], b.xn[ib][keep], ia[keep], ib[keep]
        Xb = b.X[ib]
        refined = None
        if cfg.patch_refine:
            refined = self._refine_by_patches(a, b, ia, ib, T_cbca)
            if refined is not None:
                T_cbca, ia, ib, x, Xb, e = refined
                X = a.X[ia]
                self.patch_refined += 1
        if cfg.depth_scale:
            scaled = None
            if cfg.scale_depth == "scan" and a.X_scan is not None and b.X_scan is not None:
                scaled = self._scale_from_depth(T_cbca, a.X_scan[ia], b.X_scan[ib])
            if scaled is None:
                scaled = self._scale_from_depth(T_cbca, X, Xb)
            T_cbca = scaled if scaled is not None else T_cbca
        J = _projection_jacobian(host.transform_points(T_cbca, X))
        sigma = pixel_sigma / self.f
        H = np.einsum("nki,nkj->ij", J, J) / sigma**2 * info_scale
        # left perturbation of T_cb<-ca == (minus) right perturbation of T_ca<-cb; to the body:
        A = host.adjoint(self.T_cb)  # xi_cam = Ad(T_cb) xi_body
        info_body = A.T @ H @ A
        T_ab = self.T_bc @ host.inverse(T_cbca) @ self.T_cb
        b.track[ib] = a.track[ia]
        return VisualMeasurement(
            a.kf,
            b.kf,
            T_ab,
            0.5 * (info_body + info_body.T),
            len(ia),
            n_pairs,
            X,
            x,
            float(np.sqrt(np.mean((e * self.f) ** 2))),
            refined is not None,
        )

    def _refine_by_patches(
        self, a: KeyframeFeatures, b: KeyframeFeatures, ia: np.ndarray, ib: np.ndarray, T_cbca: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None:
        """Replace b's detected keypoints by where a's patches (laid on their LiDAR planes) are
        found in b's image (:func:`align_patches`), then fit the motion again on those. Returns
        ``(T_cbca, ia, ib, x_b, X_b, e)``: the pose, the surviving pairs, b's refined normalised
        points, b's 3-D points moved along the refined rays onto b's own LiDAR planes, and the
        fit's errors; None (keep the detections) where images or planes are missing or fewer
        than ``min_inliers`` patches, or ``patch_min_fraction`` of them, align (and the retry
        with ``patch_retry_half`` / ``patch_retry_min_ncc`` / ``patch_retry_min_fraction``, when
        on, fails too)."""
        cfg = self.cfg
        if a.image is None or b.image is None or a.normal is None or b.normal is None:
            return None
        usable = np.isfinite(a.normal[ia, 0]) & np.isfinite(b.normal[ib, 0]) & np.isfinite(b.X[ib, 0])
        if usable.sum() < cfg.min_inliers:
            return None
        ia, ib = ia[usable], ib[usable]
        dist = self.rig.camera_distortion
        args = (a.image, b.image, a.uv[ia], a.X[ia], a.normal[ia], T_cbca, self.K, dist)
        uv, ok = align_patches(*args, cfg.patch_half, min_ncc=cfg.patch_min_ncc)
        if ok.sum() < max(cfg.min_inliers, cfg.patch_min_fraction * len(ok)):
            if cfg.patch_retry_half <= 0:
                return None
            # too few align (sensor noise caps the NCC in the dark): larger patches, lower bar
            uv, ok = align_patches(*args, cfg.patch_retry_half, min_ncc=cfg.patch_retry_min_ncc)
            if ok.sum() < max(cfg.min_inliers, cfg.patch_retry_min_fraction * len(ok)):
                return None
            self.patch_retried += 1
        ia, ib = ia[ok], ib[ok]
        x = undistort_normalized(uv[ok], self.K, dist)
        fit = motion_only(a.X[ia], x, T_cbca, self.f, cfg.min_inliers)
        if fit is None:
            return None
        T, keep, e = fit
        ia, ib, x = ia[keep], ib[keep], x[keep]
        rays = np.concatenate([x, np.ones((len(x), 1))], 1)
        nb = b.normal[ib]
        with np.errstate(divide="ignore", invalid="ignore"):
            depth = np.einsum("ni,ni->n", nb, b.X[ib]) / np.einsum("ni,ni->n", nb, rays)
        Xb = rays * np.where(depth > 0.1, depth, np.nan)[:, None]  # NaN: no depth (edge-on plane)
        return T, ia, ib, x, Xb, e

    def guided_pairs(self, a: KeyframeFeatures, b: KeyframeFeatures, T_cbca: np.ndarray) -> np.ndarray:
        """Matches ``(M, 2)`` of a's features with depth to b's features near where the
        motion ``T_cbca`` (camera b <- camera a, a prediction) projects them: within
        ``guided_radius_px``, same Laplacian sign (SURF), the nearest descriptor passing the
        ratio test against the other candidates in the window (``guided_ratio``), each of b's
        features used once (the closest descriptor wins). A window holds a few candidates
        instead of the whole image, so noisy dark keypoints that fail the global ratio test
        can still be matched; the motion-only fit then rejects what the prediction let in."""
        cfg = self.cfg
        ia = np.nonzero(np.isfinite(a.X[:, 0]))[0]
        if ia.size == 0 or len(b.xn) == 0:
            return np.zeros((0, 2), np.int64)
        Xb = host.transform_points(T_cbca, a.X[ia])
        front = Xb[:, 2] > 0.1
        ia, Xb = ia[front], Xb[front]
        cand = cKDTree(b.xn).query_ball_point(Xb[:, :2] / Xb[:, 2:3], cfg.guided_radius_px / self.f)
        lens = np.fromiter((len(c) for c in cand), np.int64, len(cand))
        if lens.sum() == 0:
            return np.zeros((0, 2), np.int64)
        pa = np.repeat(ia, lens)
        pb = np.fromiter((j for c in cand for j in c), np.int64, int(lens.sum()))
        if cfg.detector == "surf":
            same = a.sign[pa] == b.sign[pb]
            pa, pb = pa[same], pb[same]
        d = np.linalg.norm(a.desc[pa].astype(np.float64) - b.desc[pb].astype(np.float64), axis=1)
        order = np.lexsort((d, pa))  # by feature of a, nearest descriptor first
        pa, pb, d = pa[order], pb[order], d[order]
        first = np.r_[True, pa[1:] != pa[:-1]]
        start = np.nonzero(first)[0]
        second = np.full(len(start), np.inf)
        has2 = np.r_[start[1:], len(pa)] - start > 1
        second[has2] = d[start[has2] + 1]
        ok = d[start] < cfg.guided_ratio * second
        pa, pb, d = pa[start[ok]], pb[start[ok]], d[start[ok]]
        order = np.lexsort((d, pb))  # one feature of b per match: the closest descriptor
        pa, pb = pa[order], pb[order]
        keep = np.r_[True, pb[1:] != pb[:-1]]
        return np.stack([pa[keep], pb[keep]], axis=1)

    @staticmethod
    def _scale_from_depth(T_ba: np.ndarray, Xa: np.ndarray, Xb: np.ndarray) -> np.ndarray | None:
        """Replace the translation's length along its direction by the one the LiDAR depths of
        *both* keyframes give (``Xb - R Xa``, a robust mean): reprojecting noisy 3-D points of
        one frame into the other is an errors-in-variables fit whose length comes out biased
        short (measured ~1 % on the simulated tunnel); the 3-D-3-D difference is linear in the
        depths, so their noise averages out. Needs 10 points with depth in both frames (else
        None)."""
        ok = np.isfinite(Xa[:, 0]) & np.isfinite(Xb[:, 0])
        t = T_ba[:3, 3]
        n = np.linalg.norm(t)
        if ok.sum() < 10 or n < 1e-3:
            return None
        d = Xb[ok] - Xa[ok] @ T_ba[:3, :3].T  # per-point translation estimates
        u = t / n
        proj = d @ u
        med = np.median(proj)
        mad = 1.4826 * np.median(np.abs(proj - med)) + 1e-4
        w = np.abs(proj - med) < 3 * mad
        length = float(np.mean(proj[w])) if w.sum() >= 5 else float(med)
        out = T_ba.copy()
        out[:3, 3] = t + (length - float(t @ u)) * u
        return out


def with_length_sigma(info: np.ndarray, t: np.ndarray, ratio: float) -> np.ndarray:
    """The information (6, 6) of a relative pose (body tangent, [rotation, translation]) with
    a variance ``(ratio |t|)^2`` added along the translation ``t``: ``(I^-1 + s^2 u u^T)^-1``
    by the Sherman-Morrison formula (no inverse of a possibly ill-conditioned ``I``)."""
    n = float(np.linalg.norm(t))
    if n < 1e-9:
        return info
    u = np.zeros(6)
    u[3:] = t / n
    s2 = (ratio * n) ** 2
    iu = info @ u
    return info - s2 * np.outer(iu, iu) / (1.0 + s2 * float(u @ iu))


def _bilinear(img: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """``img`` sampled at pixel positions ``pts`` (..., 2) (x, y), bilinear, edges clamped."""
    flat = pts.reshape(-1, 2)
    out = ndimage.map_coordinates(img, [flat[:, 1], flat[:, 0]], order=1, mode="nearest")
    return out.reshape(pts.shape[:-1])


def align_patches(
    img_a: np.ndarray,
    img_b: np.ndarray,
    uv_a: np.ndarray,
    X_a: np.ndarray,
    n_a: np.ndarray,
    T_ba: np.ndarray,
    K: np.ndarray,
    dist: tuple[float, ...],
    half: int = 6,
    iterations: int = 10,
    max_shift_px: float = 2.5,
    min_ncc: float = 0.7,
) -> tuple[np.ndarray, np.ndarray]:
    """Where the surface seen at pixels ``uv_a`` (M, 2) of image a appears in image b.

    Each ``(2 half + 1)^2`` patch around ``uv_a`` is laid on its plane (through ``X_a`` with
    normal ``n_a``, camera a), moved by ``T_ba`` (camera b <- a) and projected into b (with the
    lens distortion ``dist``), then shifted in b by Gauss-Newton on the zero-mean, unit-norm
    grey values (so exposure and gain changes do not matter) until it fits. Returns b's pixels
    (M, 2) and which patches aligned: NCC above ``min_ncc``, within ``max_shift_px`` of the
    projection. A detector finds a blob's centre a little differently at another scale and
    under another light; on the simulated tunnel (exact depth) keypoints coming home towards
    the bright portal sat 0.09 px inwards of their true position in the median, which made
    the visual lengths 0.8 % short; aligned patches, 0.01 px and 0.02 %."""
    m = len(uv_a)
    o = np.arange(-half, half + 1, dtype=np.float64)
    offsets = np.stack(np.meshgrid(o, o), -1).reshape(-1, 2)
    pa = uv_a[:, None, :] + offsets[None]
    rays = np.concatenate(
        [undistort_normalized(pa.reshape(-1, 2), K, dist).reshape(m, -1, 2), np.ones((m, len(offsets), 1))], -1
    )
    depth = np.einsum("mi,mi->m", n_a, X_a)[:, None] / np.einsum("mi,mpi->mp", n_a, rays)
    Xb = (rays * depth[..., None]) @ T_ba[:3, :3].T + T_ba[:3, 3]
    # a patch must lie in front of both cameras (a plane seen edge-on gives no depth)
    valid = np.all(np.isfinite(Xb) & (depth[..., None] > 0.1) & (Xb[..., 2:3] > 0.1), axis=(1, 2))
    Xb[~valid] = [0.0, 0.0, 1.0]
    xb = distort_normalized(Xb[..., :2] / Xb[..., 2:3], dist)
    qb = xb * np.array([K[0, 0], K[1, 1]]) + np.array([K[0, 2], K[1, 2]])
    ta = _bilinear(np.asarray(img_a, np.float64), pa)
    ta -= ta.mean(1, keepdims=True)
    ta /= np.linalg.norm(ta, axis=1, keepdims=True) + 1e-9
    b = np.asarray(img_b, np.float64)
    gy, gx = (np.asarray(g) for g in np.gradient(b))
    shift = np.zeros((m, 2))
    ncc = np.zeros(m)
    for _ in range(iterations):
        q = qb + shift[:, None, :]
        tb = _bilinear(b, q)
        tb -= tb.mean(1, keepdims=True)
        norm = np.linalg.norm(tb, axis=1, keepdims=True) + 1e-9
        tb /= norm
        ncc = np.einsum("mp,mp->m", tb, ta)
        J = np.stack([_bilinear(gx, q), _bilinear(gy, q)], -1) / norm[..., None]
        J -= J.mean(1, keepdims=True)
        H = np.einsum("mpi,mpj->mij", J, J)
        g = np.einsum("mpi,mp->mi", J, tb - ta)
        det = H[:, 0, 0] * H[:, 1, 1] - H[:, 0, 1] * H[:, 1, 0]
        valid &= det > 1e-12  # a flat patch (no texture, saturated) cannot be aligned
        inv_det = np.where(valid, 1.0 / np.where(valid, det, 1.0), 0.0)
        step = (
            -np.stack([H[:, 1, 1] * g[:, 0] - H[:, 0, 1] * g[:, 1], H[:, 0, 0] * g[:, 1] - H[:, 1, 0] * g[:, 0]], -1)
            * inv_det[:, None]
        )
        step = np.clip(np.nan_to_num(step), -1.0, 1.0)
        shift += step
        if np.max(np.abs(step), initial=0.0) < 1e-3:
            break
    centre = qb[:, len(offsets) // 2, :]
    ok = valid & (ncc > min_ncc) & (np.linalg.norm(shift, axis=1) < max_shift_px)
    return centre + shift, ok


def motion_only(
    X: np.ndarray,
    x: np.ndarray,
    T_ba: np.ndarray,
    f: float,
    min_inliers: int,
    iterations: int = 12,
    inlier_px: float = INLIER_PX,
) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """Motion-only Gauss-Newton (Huber at ``inlier_px``) of camera b's pose: points ``X``
    (N, 3) in camera a, their normalised observations ``x`` (N, 2) in camera b, ``T_ba``
    (b <- a) the start. Gross outliers (1.5 ``inlier_px``) are dropped once the pose has
    settled; returns ``(T_ba, kept, e)``, the indices of the final inliers (``inlier_px``) and
    their errors (normalised units), or None when fewer than ``min_inliers`` remain or the
    system is singular."""
    idx = np.arange(len(X))
    delta = inlier_px / f  # Huber threshold
    T = T_ba
    for it in range(iterations):
        Xc = host.transform_points(T, X)
        z = Xc[:, 2]
        ok = z > 0.1
        r = (Xc[:, :2] / np.where(ok, z, 1.0)[:, None] - x) * ok[:, None]
        e = np.linalg.norm(r, axis=1)
        w = np.where(e <= delta, 1.0, delta / np.maximum(e, 1e-12)) * ok
        J = _projection_jacobian(Xc)
        H = np.einsum("n,nki,nkj->ij", w, J, J)
        g = np.einsum("n,nki,nk->i", w, J, r)
        try:
            step = -np.linalg.solve(H + 1e-9 * np.eye(6), g)
        except np.linalg.LinAlgError:
            return None
        T = host.se3_exp(step) @ T
        if np.max(np.abs(step)) < 1e-9:
            break
        if it == 5:  # drop gross outliers once the pose has settled
            Xc = host.transform_points(T, X)
            e = np.linalg.norm(Xc[:, :2] / Xc[:, 2:3] - x, axis=1)
            inl = e < 1.5 * delta
            if inl.sum() < min_inliers:
                return None
            X, x, idx = X[inl], x[inl], idx[inl]
    Xc = host.transform_points(T, X)
    e = np.linalg.norm(Xc[:, :2] / np.where(Xc[:, 2:3] > 0.1, Xc[:, 2:3], np.nan) - x, axis=1)
    inl = e < delta
    if inl.sum() < min_inliers:
        return None
    return T, idx[inl], e[inl]


def _projection_jacobian(Xc: np.ndarray) -> np.ndarray:
    """d(x/z, y/z) / d(left perturbation [rot, trans]) (N, 2, 6)."""
    x, y, z = Xc[:, 0], Xc[:, 1], Xc[:, 2]
    iz = 1.0 / z
    dp = np.zeros((len(Xc), 2, 3))
    dp[:, 0, 0] = iz
    dp[:, 0, 2] = -x * iz * iz
    dp[:, 1, 1] = iz
    dp[:, 1, 2] = -y * iz * iz
    dX = np.concatenate([-host.skew(Xc), np.broadcast_to(np.eye(3), (len(Xc), 3, 3))], axis=2)
    return dp @ dX

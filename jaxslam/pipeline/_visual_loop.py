"""Visual loop closure by projection: a place seen again, from any heading, pins the tunnel axis.

In a straight tunnel the LiDAR sees only walls parallel to the axis wherever the end wall is
out of view, and LiDAR loops there say nothing along the axis (:mod:`._loop`). An out-and-back
run passes every wall patch twice, the second time facing the other way; a planar patch seen
from the mirrored position (the same distance ahead, the opposite heading) looks much the same
to the camera: the same side faces it, the same foreshortening, the same lamps. So features
of an old keyframe, which carry 3-D points from LiDAR depth, can be found again in the current
image and measure where along the axis the current camera is.

Appearance alone cannot find them (a repetitive wall matches everywhere; measured on the
simulated tunnel: ~10 % of guided SURF matches right across headings), so the search is guided
by the estimate and photometric:

1. candidates: old keyframes (``min_gap_s`` older, within ``visual_radius``) whose 3-D points
   project into the current camera at the predicted pose, in front of it and at a similar
   distance (``visual_min_depth`` .. ``visual_max_depth``, within 2x of the old one), best
   ``visual_candidates`` by count;
2. search along the track: each point's ``visual_patch`` square patch is laid on its LiDAR
   plane (the plane fit that gave the feature its depth gives the normal), sampled in the old
   image and compared by NCC with the current one while the current camera slides along its
   direction of travel (``visual_shift_step`` steps, within three times the drift expected
   since the old keyframe, clamped to ``visual_min_shift`` .. ``visual_max_shift``, plus
   ``visual_alias_margin``: a drift just past three times the expected would put the true
   peak at the range's edge, where it cannot show as a peak, and leave a periodic alias
   inside to win unopposed; where too few patches align, or two hypotheses tie
   (``visual_widen_ambiguous``), the search and the gate are done once more at
   ``visual_wide_drift_per_m``, clamped at ``visual_wide_max_shift``: in a dark stretch the
   visual odometry can run 10 % short while the LiDAR is blind along the axis, and once
   the estimate is off by more than the first range only aliases lie inside it; the first
   search's hypotheses compete in the wide one too); both
   images are undistorted (OpenCV ``remap``) and blurred by ``visual_blur_px`` so a few
   centimetres of lateral error do not hide the peak;
3. hypotheses: up to ``visual_hypotheses`` local peaks of the mean (clipped) NCC over the
   shifts; each is refined by a direct alignment (Gauss-Newton on the patches' normalised
   grey values, translation only, blurred then sharp images, rotation held at the
   prediction); the one with the most patches above ``visual_min_ncc`` wins. When none
   aligns ``visual_min_inliers`` patches on the sharp images (a dark stretch, where the
   sensor noise caps a true patch's NCC), all are aligned again on images blurred by
   ``visual_dim_blur_px`` (and, with ``visual_dim_blur_rungs`` above 1, by twice, three
   times that, each rung only where the one before still aligned too few, and only where
   both images' mean grey level is below ``visual_dim_ladder_max_grey``);
4. acceptance: at least ``visual_min_inliers`` such patches, no runner-up hypothesis with
   more than ``visual_peak_ratio`` of the winner's (a periodic structure: tray rungs,
   brackets),
   a move across the track below ``visual_max_cross`` (the LiDAR pins lateral and vertical),
   an along-track sigma below ``visual_max_sigma``, and the same chi^2 consistency gate
   against the estimate as LiDAR loops.

The factor measures the translation along the track only (sigma from the aligned patch
centres' reprojection Hessian times ``visual_information_scale``; with
``visual_blur_noise_px`` set, a loop aligned on blurred images gets a larger variance), with
the rotation and the other translations loose (``visual_rotation_sigma_deg``,
``visual_loose_sigma``): the rotation was held, and a few tenths of a degree of rotation
error move the lateral estimate by centimetres but not the along-track one. Loop factors
carry a Cauchy kernel in the graph. Everything here is numpy / OpenCV on the host; it runs in
the vision worker beside the keyframe's own features.
"""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np

from ..lie import host
from ._config import LoopConfig
from ._lidar_frontend import axis_weighted
from ._loop import drift_gate
from ._visual import KeyframeFeatures, distort_normalized


@dataclasses.dataclass
class VisualLoop:
    """A relative body pose ``T_i^-1 T_j`` from matching keyframe j's image to keyframe i's
    3-D points (i older)."""

    i: int
    j: int
    T: np.ndarray
    information: np.ndarray
    inliers: int
    candidates: int
    ncc: float
    """Mean NCC of the aligned patches."""
    mahalanobis2: float
    blur_px: float = 0.0
    """Blur of the images its patches were aligned on (0: sharp; ``visual_dim_blur_px``)."""
    drift_per_m: float = 0.0
    """The drift per metre its search range and gate assumed (``visual_drift_per_m``, or
    ``visual_wide_drift_per_m`` when the first search aligned too few patches)."""


@dataclasses.dataclass
class LoopQuery:
    """What the vision worker needs to look for visual loops from keyframe ``k``: the pose
    estimates of all keyframes (K, 4, 4), the newest (``k``) at its prediction, and the
    distance travelled up to each keyframe (K,)."""

    k: int
    t: float
    poses: np.ndarray
    travelled: np.ndarray
    times: np.ndarray


class VisualLoopCloser:
    """See the module docstring. ``T_bc`` body <- camera; ``f`` focal length (px)."""

    def __init__(
        self,
        cfg: LoopConfig,
        T_bc: np.ndarray,
        f: float,
        image_size: tuple[int, int],
        K: np.ndarray,
        dist: tuple[float, ...] = (0.0, 0.0, 0.0, 0.0),
    ):
        self.cfg = cfg
        self.T_bc = T_bc
        self.T_cb = host.inverse(T_bc)
        self.f = f
        w, h = image_size
        self.K = K
        self.dist = tuple(dist)
        self._maps: tuple[np.ndarray, np.ndarray] | None = None
        self._rectified: dict[tuple[int, float], np.ndarray] | None = None  # during detect()
        # the image's extent in normalised coordinates (undistorted corners, loosely)
        self.bounds = np.array(
            [-K[0, 2] / K[0, 0], (w - K[0, 2]) / K[0, 0], -K[1, 2] / K[1, 1], (h - K[1, 2]) / K[1, 1]]
        )
        self.accepted: list[VisualLoop] = []
        self.pending: list[VisualLoop] = []
        """Loops found but not yet confirmed by a later query (``visual_confirm_m``)."""
        self.rejected: list[tuple[int, int, str]] = []
        self.attempts = 0
        self.wide_searches = 0
        """Candidates searched again at ``visual_wide_drift_per_m``."""
        self.ladder_climbs = 0
        """Alignments on a blur rung above the first (``visual_dim_blur_rungs``)."""
        self.last_hypotheses: list[tuple[int, float]] = []
        """The last verification's aligned hypotheses: (patches aligned, shift in m), best first."""

    def due(self, k: int) -> bool:
        return k > 0 and self.cfg.enabled and self.cfg.visual and k % max(self.cfg.visual_every, 1) == 0

    def detect(
        self,
        q: LoopQuery,
        image: np.ndarray,
        features: dict[int, KeyframeFeatures],
        images: dict[int, np.ndarray],
    ) -> list[VisualLoop]:
        """Loops from keyframe ``q.k`` (its grey ``image``) to older keyframes (their
        ``features`` and grey ``images``)."""
        self._rectified = {}
        try:
            return self.confirm(q, self._detect(q, image, features, images))
        finally:
            self._rectified = None

    def confirm(self, q: LoopQuery, found: list[VisualLoop]) -> list[VisualLoop]:
        """The loops that join the graph now: those of ``found`` that agree with a pending or
        accepted loop of an earlier query within ``visual_confirm_m`` metres, and the pending
        ones they agree with (oldest first). Agreement: where the two loops put their current
        keyframes along the track, relative to the estimate ``q.poses``, differs by at most
        ``visual_confirm_tol`` plus ``visual_confirm_drift_per_m`` per metre between them (the
        odometry's drift). A loop of ``found`` that agrees with none waits; pending loops
        farther back than ``visual_confirm_m`` are dropped (``rejected``, "unconfirmed")."""
        cfg = self.cfg
        if cfg.visual_confirm_m <= 0:
            self.accepted += found
            return found
        here = q.travelled[q.k]
        axis = q.poses[q.k][:3, 0]  # the direction of travel (body x) in the world

        def along(lp: VisualLoop) -> float:  # where the loop puts keyframe j, ahead of its estimate
            return float(((q.poses[lp.i] @ lp.T)[:3, 3] - q.poses[lp.j][:3, 3]) @ axis)

        def near(lp: VisualLoop) -> bool:
            return here - q.travelled[lp.j] <= cfg.visual_confirm_m

        for lp in self.pending:
            if not near(lp):
                self.rejected.append((lp.i, lp.j, "unconfirmed by a later loop"))
        self.pending = [lp for lp in self.pending if near(lp)]
        earlier = [lp for lp in self.pending + self.accepted if lp.j < q.k and near(lp)]
        confirmed: set[int] = set()
        out: list[VisualLoop] = []
        for lp in found:
            agree = [
                o
                for o in earlier
                if abs(along(lp) - along(o))
                <= cfg.visual_confirm_tol + cfg.visual_confirm_drift_per_m * abs(here - q.travelled[o.j])
            ]
            confirmed |= {id(o) for o in agree}
            (out if agree else self.pending).append(lp)
        now = [lp for lp in self.pending if id(lp) in confirmed] + out
        self.pending = [lp for lp in self.pending if id(lp) not in confirmed]
        self.accepted += now
        return now

    def close(self) -> None:
        """End of the recording: loops still waiting for confirmation are dropped."""
        self.rejected += [(lp.i, lp.j, "unconfirmed at the end") for lp in self.pending]
        self.pending = []

    def _detect(
        self,
        q: LoopQuery,
        image: np.ndarray,
        features: dict[int, KeyframeFeatures],
        images: dict[int, np.ndarray],
    ) -> list[VisualLoop]:
        cfg = self.cfg
        old = np.nonzero(q.times < q.t - cfg.min_gap_s)[0]
        d = np.linalg.norm(q.poses[old, :3, 3] - q.poses[q.k, :3, 3], axis=1)
        old = old[d < cfg.visual_radius]
        T_wck = q.poses[q.k] @ self.T_bc
        scored = []
        for i in old.tolist():
            fi = features.get(i)
            if fi is None or i not in images:
                continue
            has = np.isfinite(fi.X[:, 0])
            if has.sum() < cfg.visual_min_inliers:
                continue
            T_ki = host.inverse(T_wck) @ q.poses[i] @ self.T_bc  # camera k <- camera i (predicted)
            n = int(self._visible(fi.X[has], T_ki).sum())
            if n >= 2 * cfg.visual_min_inliers:
                scored.append((n, i, T_ki))
        scored.sort(key=lambda s: -s[0])
        out = []
        for _, i, T_ki in scored[: cfg.visual_candidates]:
            self.attempts += 1
            travelled = abs(float(q.travelled[q.k] - q.travelled[i]))
            loop = self._verify(i, q.k, features[i], (images[i], image), T_ki, travelled, q.poses)
            if loop is not None:
                out.append(loop)
        return out

    def _visible(self, X: np.ndarray, T_ki: np.ndarray) -> np.ndarray:
        """Points (camera i) in front of camera k, inside its image, at a distance within 2x
        of the one they were seen at."""
        cfg = self.cfg
        Xk = host.transform_points(T_ki, X)
        z = Xk[:, 2]
        ok = (z > cfg.visual_min_depth) & (z < cfg.visual_max_depth)
        xy = Xk[:, :2] / np.where(ok, z, 1.0)[:, None]
        b = self.bounds
        ok &= (xy[:, 0] > b[0]) & (xy[:, 0] < b[1]) & (xy[:, 1] > b[2]) & (xy[:, 1] < b[3])
        ratio = np.linalg.norm(Xk, axis=1) / np.maximum(np.linalg.norm(X, axis=1), 1e-9)
        return ok & (ratio > 0.5) & (ratio < 2.0)

    def patches(self, fi: KeyframeFeatures, pts: np.ndarray, spacing: float) -> tuple[np.ndarray, np.ndarray]:
        """Square grids (P, G, 3) on the LiDAR planes of fi's points ``pts`` (camera i frame),
        ``visual_patch`` samples a side, spaced ``spacing`` px apart in image i (as if facing
        it), and the indices of the points that got one (those with a normal)."""
        cfg = self.cfg
        if fi.normal is not None:
            pts = pts[np.isfinite(fi.normal[pts, 0])]
        if fi.normal is None or not len(pts):
            return np.zeros((0, cfg.visual_patch**2, 3)), pts[:0]
        X, n = fi.X[pts], fi.normal[pts]
        # in-plane axes: t1 horizontal in the camera (across image y), t2 = n x t1
        t1 = np.cross(n, np.array([0.0, 1.0, 0.0]))
        flat = np.linalg.norm(t1, axis=1) < 0.3  # the plane faces up or down (floor, ceiling)
        t1[flat] = np.cross(n[flat], np.array([1.0, 0.0, 0.0]))
        t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
        t2 = np.cross(n, t1)
        g = (np.arange(cfg.visual_patch) - (cfg.visual_patch - 1) / 2.0)[None, :] * (spacing * X[:, 2:3] / self.f)
        grid = (
            X[:, None, None, :]
            + g[:, :, None, None] * t1[:, None, None, :]
            + g[:, None, :, None] * t2[:, None, None, :]
        )
        return grid.reshape(len(pts), -1, 3), pts

    def _pixels(self, Xc: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Pixel coordinates ``u, v`` in the rectified (pinhole) image of camera-frame points
        (..., 3), and whether each is in front of the camera."""
        z = Xc[..., 2]
        front = z > 0.2
        iz = 1.0 / np.where(front, z, 1.0)
        return self.K[0, 0] * Xc[..., 0] * iz + self.K[0, 2], self.K[1, 1] * Xc[..., 1] * iz + self.K[1, 2], front

    def rectified(self, image: np.ndarray, blur: float) -> np.ndarray:
        """The grey image resampled to the pinhole camera of the same ``K`` (distortion
        removed) as float32, Gaussian-blurred by ``blur`` px (0: none); kept for the rest of
        the :meth:`detect` call (the search and every alignment reuse the same images)."""
        key = (id(image), blur)
        if self._rectified is not None and key in self._rectified:
            return self._rectified[key]
        img = np.asarray(image, np.float32)
        if img.ndim == 3:
            img = img.max(axis=2)
        if self._maps is None:
            h, w = img.shape
            v, u = np.mgrid[0:h, 0:w].astype(np.float64)
            xn = np.stack([(u - self.K[0, 2]) / self.K[0, 0], (v - self.K[1, 2]) / self.K[1, 1]], -1)
            xd = distort_normalized(xn, self.dist)
            self._maps = (
                (self.K[0, 0] * xd[..., 0] + self.K[0, 2]).astype(np.float32),
                (self.K[1, 1] * xd[..., 1] + self.K[1, 2]).astype(np.float32),
            )
        out = cv2.remap(img, *self._maps, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=np.nan)
        out = cv2.GaussianBlur(out, (0, 0), blur) if blur > 0 else out
        if self._rectified is not None:
            self._rectified[key] = out
        return out

    @staticmethod
    def _bilinear(image: np.ndarray, u: np.ndarray, v: np.ndarray, ok: np.ndarray) -> np.ndarray:
        """Bilinear values of a float32 image at (u, v) (any shape); NaN where not ``ok``,
        outside the image or next to a NaN pixel."""
        shape = u.shape
        n = int(np.prod(shape))
        if n == 0:
            return np.zeros(shape)
        cols = 1024
        rows = -(-n // cols)
        mu = np.full(rows * cols, -10.0, np.float32)
        mv = np.full(rows * cols, -10.0, np.float32)
        mu[:n] = np.where(ok, u, -10.0).ravel()
        mv[:n] = np.where(ok, v, -10.0).ravel()
        val = cv2.remap(
            image,
            mu.reshape(rows, cols),
            mv.reshape(rows, cols),
            cv2.INTER_LINEAR,
            borderMode=cv2.BORDER_CONSTANT,
            borderValue=np.nan,
        )
        return val.ravel()[:n].reshape(shape).astype(np.float64)

    @staticmethod
    def _ncc(ref: np.ndarray, cur: np.ndarray) -> np.ndarray:
        """NCC over the last axis of zero-mean ``ref`` and any ``cur`` (broadcast); -1 where
        undefined."""
        cur = cur - cur.mean(axis=-1, keepdims=True)
        num = np.mean(cur * ref, axis=-1)
        den = np.sqrt(np.mean(cur * cur, axis=-1) * np.mean(ref * ref, axis=-1)) + 1e-9
        out = num / den
        return np.where(np.isfinite(out), out, -1.0)

    def along_track(
        self,
        fi: KeyframeFeatures,
        images: tuple[np.ndarray, np.ndarray],
        T_ki: np.ndarray,
        max_shift: float,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Photometric search of fi's textured 3-D points along the drift line: for shifts
        ``s`` of the current camera along the body's direction of travel (x), the NCC of each
        point's plane patch in image i with the same patch seen from camera k. The images are
        blurred and the patch samples spaced ``visual_search_spacing_px``, so a pixel or two
        of error across the line (the prediction's other directions) does not hide the peak.
        Returns the shifts (S,), the NCC (S, P) and the point indices (P,)."""
        cfg = self.cfg
        shifts = np.arange(-max_shift, max_shift + 1e-9, cfg.visual_shift_step)
        pts = np.nonzero(np.isfinite(fi.X[:, 0]))[0]
        grid, pts = self.patches(fi, pts[self._visible(fi.X[pts], T_ki)], self.cfg.visual_search_spacing_px)
        if not len(pts):
            return shifts, np.zeros((len(shifts), 0)), pts
        blur_i, blur_k = (self.rectified(im, cfg.visual_blur_px) for im in images)
        ref = self._bilinear(blur_i, *self._pixels(grid))  # (P, G)
        ref = ref - ref.mean(axis=1, keepdims=True)
        sd = np.sqrt(np.mean(ref * ref, axis=1))
        keep = np.isfinite(sd) & (sd > cfg.visual_min_contrast)
        top = np.nonzero(keep)[0][np.argsort(-sd[keep])][: cfg.visual_max_points]  # the most contrasted
        ref, grid, pts = ref[top], grid[top], pts[top]
        if not len(pts):
            return shifts, np.zeros((len(shifts), 0)), pts
        a = self.T_cb[:3, :3] @ np.array([1.0, 0.0, 0.0])  # travel direction in camera k
        Xk = grid @ T_ki[:3, :3].T + T_ki[:3, 3]  # (P, G, 3) at the prediction
        # camera k displaced by s a: the points move by -s a (S, P, G), one coordinate at a time
        z = Xk[None, ..., 2] - shifts[:, None, None] * a[2]
        front = z > 0.2
        iz = 1.0 / np.where(front, z, 1.0)
        u = self.K[0, 0] * (Xk[None, ..., 0] - shifts[:, None, None] * a[0]) * iz + self.K[0, 2]
        v = self.K[1, 1] * (Xk[None, ..., 1] - shifts[:, None, None] * a[1]) * iz + self.K[1, 2]
        cur = self._bilinear(blur_k, u, v, front)  # (S, P, G)
        return shifts, self._ncc(ref[None], cur), pts

    def hypotheses(self, shifts: np.ndarray, ncc: np.ndarray) -> list[float]:
        """Candidate shifts: the highest local peaks of the patches' mean NCC (negative values
        as 0) along the track, at least three shift tolerances apart, each refined by a
        parabola; at most ``visual_hypotheses``. On blurred images a periodic structure (tray
        rungs every 0.3 m, brackets every 1.5 m) peaks at its aliases too: the alignment on
        sharp images decides between them (:meth:`_verify`)."""
        cfg = self.cfg
        if not ncc.shape[1] or len(shifts) < 5:
            return []
        score = np.clip(ncc, 0.0, None).mean(axis=1)
        peaks = [j for j in range(1, len(shifts) - 1) if score[j] >= score[j - 1] and score[j] > score[j + 1]]
        out: list[float] = []
        for j in sorted(peaks, key=lambda j: -score[j]):
            if j < 2 or j > len(shifts) - 3:  # at the range's edge: the true peak may lie beyond
                continue
            lo, mid, hi = score[j - 1], score[j], score[j + 1]
            den = lo - 2 * mid + hi
            sh = float(
                shifts[j] + np.clip(0.5 * (lo - hi) / den if den < -1e-12 else 0.0, -0.5, 0.5) * cfg.visual_shift_step
            )
            if all(abs(sh - o) > 3 * cfg.visual_shift_tol for o in out):
                out.append(sh)
            if len(out) == cfg.visual_hypotheses:
                break
        return out

    def align(
        self,
        fi: KeyframeFeatures,
        pts: np.ndarray,
        images: tuple[np.ndarray, np.ndarray],
        T_ki: np.ndarray,
        blur: float,
        iterations: int = 6,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Direct alignment of ``T_ki`` (camera k <- camera i) on the plane patches of ``pts``:
        Gauss-Newton on the difference of the per-patch normalised grey values (zero mean,
        unit variance: exposure-free) of image k and image i over a left perturbation of the
        translation (the rotation is held), Jacobian by central differences,
        patches weighted by a Huber kernel on their residual. Returns the refined pose and each
        patch's final NCC."""
        grid, kept = self.patches(fi, pts, 1.5)
        ncc_out = np.full(len(pts), -1.0)
        if not len(kept):
            return T_ki, ncc_out
        img_i, img_k = (self.rectified(im, blur) for im in images)

        def normalised(vals: np.ndarray) -> np.ndarray:
            vals = vals - vals.mean(axis=-1, keepdims=True)
            return vals / (np.sqrt(np.mean(vals * vals, axis=-1, keepdims=True)) + 1e-9)

        ref = normalised(self._bilinear(img_i, *self._pixels(grid)))  # (P, G)
        dims = np.arange(3, 6)  # the translation's tangent coordinates
        h = np.full(3, 1e-2)  # m

        def residual(T: np.ndarray, d: np.ndarray | None = None) -> np.ndarray:
            if d is not None:
                T = host.se3_exp(d) @ T
            cur = normalised(self._bilinear(img_k, *self._pixels(grid @ T[:3, :3].T + T[:3, 3])))
            return cur - ref  # NaN where a sample left the image

        T = T_ki.copy()
        eye = np.eye(6)
        for _ in range(iterations):
            r = residual(T)
            J = np.stack(
                [(residual(T, hj * eye[j]) - residual(T, -hj * eye[j])) / (2 * hj) for j, hj in zip(dims, h)], axis=-1
            )
            ok = np.all(np.isfinite(r), axis=1) & np.all(np.isfinite(J), axis=(1, 2))
            if ok.sum() < 3:
                break
            e = np.sqrt(np.mean(r[ok] ** 2, axis=1))  # per-patch RMS (normalised units)
            w = np.where(e <= 0.5, 1.0, 0.5 / np.maximum(e, 1e-12))
            Jo, ro = J[ok], r[ok]
            H = np.einsum("p,pgi,pgj->ij", w, Jo, Jo)
            g = np.einsum("p,pgi,pg->i", w, Jo, ro)
            if np.linalg.cond(H) > 1e10:
                break
            step = -np.linalg.solve(H, g)
            step = step * min(1.0, float(np.min(5 * h / np.maximum(np.abs(step), 1e-12))))  # <= 5 cm
            d = np.zeros(6)
            d[dims] = step
            T = host.se3_exp(d) @ T
            if np.all(np.abs(step) < 0.01 * h):
                break
        r = residual(T)
        ncc = 1.0 - 0.5 * np.mean(r * r, axis=1)  # of unit-variance vectors: NCC = 1 - |a - b|^2 / 2G
        ncc_out[np.searchsorted(pts, kept)] = np.where(np.isfinite(ncc), ncc, -1.0)
        return T, ncc_out

    def _align_hypotheses(
        self,
        fi: KeyframeFeatures,
        pts: np.ndarray,
        images: tuple[np.ndarray, np.ndarray],
        T_ki: np.ndarray,
        hyps: list[float],
        reach: float,
        blur: float,
    ) -> list[tuple[int, float, np.ndarray, np.ndarray, np.ndarray, np.ndarray]]:
        """Each shift hypothesis aligned (blurred search images, then images blurred by
        ``blur`` px, then again on the patches that passed), as ``(patches above
        visual_min_ncc, shift converged to, T, patches used, which passed, their NCC)``, the
        most patches first; hypotheses converging beyond ``reach`` or onto an earlier one
        are dropped."""
        cfg = self.cfg
        a = self.T_cb[:3, :3] @ np.array([1.0, 0.0, 0.0])  # travel direction in camera k
        tried: list[tuple[int, float, np.ndarray, np.ndarray, np.ndarray, np.ndarray]] = []
        for shift in hyps:
            step = np.eye(4)
            step[:3, 3] = -shift * a
            T, ncc_pts = self.align(fi, pts, images, step @ T_ki, cfg.visual_blur_px)
            T, ncc_pts = self.align(fi, pts, images, T, blur)
            use = pts
            good = ncc_pts > cfg.visual_min_ncc
            if good.sum() >= cfg.visual_min_inliers and not good.all():
                T, ncc_pts = self.align(fi, pts[good], images, T, blur)
                use = pts[good]
                good = ncc_pts > cfg.visual_min_ncc
            moved = float(-(T[:3, 3] - T_ki[:3, 3]) @ a)  # the shift it converged to
            if abs(moved) <= reach and not any(abs(moved - m) < cfg.visual_shift_tol for _, m, *_ in tried):
                tried.append((int(good.sum()), moved, T, use, good, ncc_pts))
        tried.sort(key=lambda h: -h[0])
        return tried

    def search_range(self, drift_per_m: float, travelled: float, wide: bool = False) -> float:
        """How far (m) the search along the track reaches either side of the prediction:
        three times the drift expected over ``travelled`` metres, clamped to
        [``visual_min_shift``, ``visual_max_shift``] (``visual_wide_max_shift`` for the wide
        search), plus ``visual_alias_margin``."""
        cfg = self.cfg
        drift = max(drift_per_m * travelled, 0.02)
        top = max(cfg.visual_wide_max_shift, cfg.visual_max_shift) if wide else cfg.visual_max_shift
        return min(max(3.0 * drift, cfg.visual_min_shift), top) + cfg.visual_alias_margin

    def _verify(
        self,
        i: int,
        k: int,
        fi: KeyframeFeatures,
        images: tuple[np.ndarray, np.ndarray],
        T_ki: np.ndarray,
        travelled: float,
        poses: np.ndarray,
    ) -> VisualLoop | None:
        """Search and verify at the expected drift; where too few patches align there, once
        more at ``visual_wide_drift_per_m`` (a wider range and a looser gate), when that
        reaches further. Only the last search's refusal is kept in ``rejected``."""
        cfg = self.cfg
        narrow, wide = cfg.visual_drift_per_m, cfg.visual_wide_drift_per_m
        n_rej = len(self.rejected)
        loop, why = self._verify_at(i, k, fi, images, T_ki, travelled, poses, narrow)
        if (
            loop is None
            and (why == "too few" or (why == "ambiguous" and cfg.visual_widen_ambiguous))
            and wide > narrow
            and self.search_range(wide, travelled, True) > self.search_range(narrow, travelled) + cfg.visual_shift_step
        ):
            del self.rejected[n_rej:]
            self.wide_searches += 1
            # the first search's hypotheses compete in the wide one too: a wider range has
            # more peaks than ``visual_hypotheses``, and an alias that tied inside the first
            # range must not drop out of the comparison (measured: a prediction 1.5 m off
            # gave a tie of two rung aliases at -0.3 / +0.3 m; searched wide without them the
            # -0.3 m alias won alone, a false loop 1.2 m off)
            first = tuple(moved for _, moved in self.last_hypotheses)
            loop, _ = self._verify_at(i, k, fi, images, T_ki, travelled, poses, wide, True, first)
            if loop is None and len(self.rejected) > n_rej:
                a, b, why = self.rejected[-1]
                self.rejected[-1] = (a, b, f"wide search: {why}")
        return loop

    def _verify_at(
        self,
        i: int,
        k: int,
        fi: KeyframeFeatures,
        images: tuple[np.ndarray, np.ndarray],
        T_ki: np.ndarray,
        travelled: float,
        poses: np.ndarray,
        drift_per_m: float,
        wide: bool = False,
        extra: tuple[float, ...] = (),
    ) -> tuple[VisualLoop | None, str]:
        """One search and verification assuming ``drift_per_m`` (``wide``: the wide search's
        clamp), with the shifts ``extra`` aligned as hypotheses too: (the loop or None, why
        it was refused: ``"too few"`` patches aligned, ``"ambiguous"``, another reason, or
        ``""``)."""
        cfg = self.cfg
        reach = self.search_range(drift_per_m, travelled, wide)  # competitors are looked for this far
        shifts, ncc, pts = self.along_track(fi, images, T_ki, reach)
        a = self.T_cb[:3, :3] @ np.array([1.0, 0.0, 0.0])  # travel direction in camera k
        pts = np.sort(pts)
        hyps = self.hypotheses(shifts, ncc)
        for sh in extra:
            if hyps and all(abs(sh - o) > 3 * cfg.visual_shift_tol for o in hyps):
                hyps.append(float(sh))
        tried = self._align_hypotheses(fi, pts, images, T_ki, hyps, reach, 0.0)
        blur = 0.0
        rungs = cfg.visual_dim_blur_rungs
        if rungs > 1 and max(float(np.mean(im)) for im in images) >= cfg.visual_dim_ladder_max_grey:
            rungs = 1  # not dark enough for the ladder: its blur lets aliases align too
        for rung in range(1, rungs + 1):
            if (tried and tried[0][0] >= cfg.visual_min_inliers) or cfg.visual_dim_blur_px <= 0 or not hyps:
                break
            self.ladder_climbs += rung > 1
            # too few patches align on the sharp images: in a dark stretch the sensor noise
            # (a few grey levels at full gain) caps a true patch's NCC well below the
            # threshold, so the alignment is tried again on blurred images, more each rung
            blur = rung * cfg.visual_dim_blur_px
            tried = self._align_hypotheses(fi, pts, images, T_ki, hyps, reach, blur)
        self.last_hypotheses = [(n, moved) for n, moved, *_ in tried]  # (patches aligned, shift m), best first
        if not tried or tried[0][0] < cfg.visual_min_inliers:
            n = tried[0][0] if tried else 0
            self.rejected.append((i, k, f"{n} patches align (of {ncc.shape[1]})"))
            return None, "too few"
        best = tried[0]
        if len(tried) > 1 and tried[1][0] > cfg.visual_peak_ratio * best[0]:
            self.rejected.append(
                (i, k, f"ambiguous: {best[0]} and {tried[1][0]} patches align at {best[1]:+.2f}, {tried[1][1]:+.2f} m")
            )
            return None, "ambiguous"
        _, _, T, pts, good, ncc_pts = best
        # the prediction's lateral and vertical come from the LiDAR (the walls, floor, ceiling
        # pin them to a centimetre or two): an alignment that needed to move them far
        # compensated a rotation error (right after a turn on the spot) or matched the wrong
        # thing, and its along-track shift cannot be trusted either
        d = T[:3, 3] - T_ki[:3, 3]
        cross = float(np.linalg.norm(d - (d @ a) * a))
        if cross > cfg.visual_max_cross:
            self.rejected.append((i, k, f"moved {cross:.3f} m across the track"))
            return None, "other"
        Xc = host.transform_points(T, fi.X[pts[good]])
        x = Xc[:, :2] / Xc[:, 2:3]  # where the aligned patches' centres are
        fit = translation_only(fi.X[pts[good]], x, T, self.f)
        if fit is None:
            self.rejected.append((i, k, "singular"))
            return None, "other"
        T, keep, _, H_t = fit
        # information along the track only: the rotation was held at the prediction, and a
        # rotation error of a few tenths of a degree biases the lateral translation by
        # centimetres but leaves the along-track one (measured: 1 cm RMS at 0.1 and 0.5 deg of
        # yaw error); LiDAR measures the other directions better anyway
        try:
            var = float(a @ np.linalg.solve(H_t, a)) / (self.f**2 * cfg.visual_information_scale)
            if cfg.visual_blur_noise_px > 0:  # a blurred NCC peak is wider: its centre less sure
                var *= 1.0 + (blur / cfg.visual_blur_noise_px) ** 2
        except np.linalg.LinAlgError:
            self.rejected.append((i, k, "singular"))
            return None, "other"
        if var > cfg.visual_max_sigma**2:  # too few or badly placed patches to be worth the risk
            self.rejected.append((i, k, f"along-track sigma {np.sqrt(var):.3f} m"))
            return None, "other"
        info = np.diag(
            [1.0 / np.radians(cfg.visual_rotation_sigma_deg) ** 2] * 3 + [1.0 / cfg.visual_loose_sigma**2] * 3
        )
        info[3, 3] += 1.0 / var  # body x of keyframe k: the between factor's tangent frame
        # the learned loop weights (jaxslam tune), as for LiDAR loops: the tuner re-weights every
        # factor tagged "loop" in its graph, visual loops included
        info = axis_weighted(info, cfg.axis_weights)
        T_ik = self.T_bc @ host.inverse(T) @ self.T_cb  # body i <- body k
        T_est = host.inverse(poses[i]) @ poses[k]
        ok, m2 = drift_gate(T_ik, info, T_est, travelled, dataclasses.replace(cfg, drift_per_m=drift_per_m))
        if not ok:
            self.rejected.append((i, k, f"inconsistent with odometry (chi2 {m2:.1f})"))
            return None, "other"
        return VisualLoop(
            i, k, T_ik, info, len(keep), ncc.shape[1], float(np.mean(ncc_pts[good])), m2, blur, drift_per_m
        ), ""


def translation_only(
    X: np.ndarray, x: np.ndarray, T: np.ndarray, f: float, iterations: int = 10
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None:
    """Gauss-Newton (Huber, 2 px) of the translation of ``T`` (camera b <- a) with its rotation
    held: points ``X`` (N, 3) in camera a, normalised observations ``x`` (N, 2) in b. Returns
    ``(T, inliers (2 px), their errors, H)`` with ``H`` the 3x3 Gauss-Newton matrix of the
    translation over the inliers (normalised units), or None when singular."""
    delta = 2.0 / f
    T = T.copy()

    def linearise(T: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        Xc = host.transform_points(T, X)
        front = Xc[:, 2] > 0.1
        z = np.where(front, Xc[:, 2], 1.0)
        r = Xc[:, :2] / z[:, None] - x
        J = np.zeros((len(X), 2, 3))
        J[:, 0, 0] = J[:, 1, 1] = 1.0 / z
        J[:, 0, 2] = -Xc[:, 0] / z**2
        J[:, 1, 2] = -Xc[:, 1] / z**2
        return r, J, front

    for _ in range(iterations):
        r, J, front = linearise(T)
        e = np.linalg.norm(r, axis=1)
        w = np.where(e <= delta, 1.0, delta / np.maximum(e, 1e-12)) * front
        H = np.einsum("n,nki,nkj->ij", w, J, J)
        g = np.einsum("n,nki,nk->i", w, J, r)
        if np.linalg.cond(H) > 1e12:
            return None
        step = -np.linalg.solve(H, g)
        T[:3, 3] += step
        if np.max(np.abs(step)) < 1e-7:
            break
    r, J, front = linearise(T)
    e = np.linalg.norm(r, axis=1)
    inl = np.nonzero(front & (e < delta))[0]
    return T, inl, e[inl], np.einsum("nki,nkj->ij", J[inl], J[inl])

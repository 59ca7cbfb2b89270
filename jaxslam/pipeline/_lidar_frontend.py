"""LiDAR odometry for the estimator: deskew with IMU-propagated motion, downsample, register to
a local voxel map in the odometry frame (scan-to-map, kiss-icp style), and turn the
registration Hessian into the information of an odometry factor with degenerate directions
(the tunnel axis) down-weighted. With ``lidar.intensity`` the return intensity, made a relative
reflectivity per scan, joins the registration and the map, so the surface pattern observes the
axis where the geometry is degenerate."""

from __future__ import annotations

import bisect
import dataclasses

import numpy as np

from ..lidar import (
    IcpConfig,
    Registration,
    VoxelMap,
    VoxelMapConfig,
    crop_range,
    deskew,
    register,
    relative_reflectivity,
    voxel_downsample,
)
from ..lie import host
from ._config import LidarConfig


@dataclasses.dataclass
class ScanResult:
    t: float
    """Reference time of the deskewed scan (s)."""
    T_odom: np.ndarray
    """Body pose in the odometry frame at ``t`` (4x4)."""
    registration: Registration | None
    points: np.ndarray
    """Deskewed, downsampled points in the body frame at ``t`` (N, 3)."""
    degenerate: bool
    condition: float
    index: int = 0
    """Scan number (0, 1, ...) in the odometry."""
    last_degenerate: int = -1
    """Number of the latest scan up to this one whose registration did not observe the
    direction of travel (weak along body x, or unregistered): the odometry is anchored
    (drift-free along the axis too) over the scans after it."""
    reflectivity: np.ndarray | None = None
    """Relative reflectivity of ``points`` (N,), NaN where none; None without intensity."""
    held: bool = False
    """Not registered: the vehicle stood still and the scan kept the last scan's pose
    (``LidarConfig.hold_still``)."""


def information_for_factor(
    info_lidar: np.ndarray, T_bl: np.ndarray, cfg: LidarConfig, scale: float, axis_sigma: float = 0.0
) -> np.ndarray:
    """Registration information (LiDAR tangent) -> body-tangent information for a between
    factor: conjugated by the extrinsic, scaled, regularised so a direction the scan does not
    see gets sigma ``cfg.degenerate_sigma``, and capped by the sigma floors. Callers pass
    ``Registration.strong_information()``: along a degenerate direction ICP held the
    prediction, which is not a measurement, so the factor says (almost) nothing there."""
    A = host.adjoint(host.inverse(T_bl))  # xi_lidar = Ad(T_lb) xi_body
    info = scale * (A.T @ info_lidar @ A)
    info = 0.5 * (info + info.T) + np.eye(6) / cfg.degenerate_sigma**2
    cov = np.linalg.inv(info)
    floor = np.array([cfg.min_sigma_rot] * 3 + [cfg.min_sigma_trans] * 3) ** 2
    cov = cov + np.diag(floor)
    if axis_sigma > 0:  # body x: the direction of travel
        cov[3, 3] += axis_sigma**2
    out = np.linalg.inv(cov)
    return 0.5 * (out + out.T)


def axis_weighted(info: np.ndarray, weights: tuple[float, float]) -> np.ndarray:
    """Information of a relative pose (tangent ``[rotation, translation]``) with its rotation
    and translation blocks re-weighted: ``S info S``, ``S = diag(sqrt(w_rot) I, sqrt(w_trans) I)``
    (each group's sigmas divided by ``sqrt(w)``). Learned by ``jaxslam tune``."""
    if tuple(weights) == (1.0, 1.0):
        return info
    s = np.sqrt(np.repeat(np.asarray(weights, dtype=np.float64), 3))
    return info * s[:, None] * s[None, :]


def axis_sigma_scaled(info: np.ndarray, scale: float) -> np.ndarray:
    """Information of a relative pose (tangent ``[rotation, translation]``) whose along-axis
    (body x translation) sigma is multiplied by ``scale``, correlations kept: ``D^-1 info D^-1``
    with ``D = diag(1, 1, 1, scale, 1, 1)``, i.e. the covariance ``D C D``. Exact for a
    rank-deficient information too (no inverse taken)."""
    if scale == 1.0:
        return info
    d = np.ones(6)
    d[3] = 1.0 / scale
    return info * d[:, None] * d[None, :]


class LidarOdometry:
    """Scan-to-map odometry (see the module docstring)."""

    def __init__(self, cfg: LidarConfig, T_bl: np.ndarray):
        self.cfg = cfg
        self.T_bl = T_bl
        self.T_lb = host.inverse(T_bl)
        self.map = VoxelMap(
            VoxelMapConfig(
                voxel_size=cfg.map_voxel, max_points_per_voxel=cfg.map_points_per_voxel, max_distance=cfg.map_radius
            )
        )
        self.icp = IcpConfig(intensity_weight=cfg.intensity_weight if cfg.intensity else 0.0)
        self.last: ScanResult | None = None
        self.degenerate = 0
        self.processed = 0
        self._last_degenerate = -1
        self.continued = 0  # registrations given a second run of iterations
        self._failures = 0  # consecutive failed registrations
        self._weak: list[int] = []  # numbers of the axis-weak scans, ascending
        self.held = 0  # scans kept at the last scan's pose while standing still

    def weak_run(self, first: int, last: int) -> int:
        """Longest run of consecutive axis-weak scans numbered ``first`` to ``last``
        (inclusive): 0 when the odometry kept the axis on every one of them."""
        lo = bisect.bisect_left(self._weak, first)
        hi = bisect.bisect_right(self._weak, last)
        run = best = 0
        prev = None
        for i in self._weak[lo:hi]:
            run = run + 1 if prev is not None and i == prev + 1 else 1
            best = max(best, run)
            prev = i
        return best

    def anchored_between(self, first: int, last: int, gap: int) -> bool:
        """Whether scans ``first`` and ``last`` both kept the axis and no more than ``gap``
        consecutive scans between them lost it (``lidar.anchor_gap_scans``)."""
        ends = self.weak_run(first, first) + self.weak_run(last, last)
        return ends == 0 and self.weak_run(first, last) <= gap

    def process(
        self,
        t_ref: float,
        points: np.ndarray,
        point_times: np.ndarray,
        body_motion,
        T_odom_pred: np.ndarray,
        intensity: np.ndarray | None = None,
        still: bool = False,
    ) -> ScanResult:
        """``body_motion``: (times (K,), poses (K, 4, 4)) of the body in any fixed frame over
        the scan (IMU-propagated); ``point_times`` absolute (s); ``T_odom_pred`` the predicted
        body pose at ``t_ref`` in the odometry frame; ``intensity`` (N,) the raw returns;
        ``still``: the vehicle stands still, so the scan keeps the last scan's pose,
        unregistered (once a map exists)."""
        cfg = self.cfg
        times, poses = body_motion
        lid = poses @ self.T_bl
        pts = deskew(points, point_times, (lid[:, :3, :3], lid[:, :3, 3], times), reference_time=t_ref, tolerance=0.02)
        use_i = cfg.intensity and intensity is not None
        if use_i:
            pts, inten = crop_range(pts, cfg.min_range, cfg.max_range, np.asarray(intensity, dtype=np.float64))
            # reflectivity on a 10 cm grid: fine enough for its 0.2 m smoothing, ~4x fewer points
            pts, inten = voxel_downsample(pts, 0.1, inten)
            refl = relative_reflectivity(
                pts, inten, radius=cfg.intensity_radius, smooth=cfg.intensity_smooth, max_range=cfg.intensity_max_range
            )
        else:
            pts = np.asarray(crop_range(pts, cfg.min_range, cfg.max_range))
            refl = np.full(len(pts), np.nan)
        src, src_r = voxel_downsample(pts, cfg.voxel, refl)
        T_init = T_odom_pred @ self.T_bl
        reg: Registration | None = None
        last = self.last
        held = still and len(self.map) > 0 and last is not None
        if held and last is not None:  # no motion: the last scan's pose (the IMU's prediction drifts)
            T_l = last.T_odom @ self.T_bl
            self.held += 1
        elif len(self.map) == 0:
            T_l = T_init
        else:
            reg = register(src, self.map, T_init, self.icp, source_intensity=src_r if use_i else None)
            if not reg.converged and reg.iterations >= self.icp.max_iterations:
                # out of iterations, still moving (a poor prediction, as after a dropout, slides
                # slowly along the tunnel): go on once from where it stopped
                self.continued += 1
                reg = register(src, self.map, reg.T, self.icp, source_intensity=src_r if use_i else None)
            T_l = reg.T if reg.converged else T_init
        self._failures = 0 if reg is None or reg.converged else self._failures + 1
        insert = self._failures == 0 or self._failures >= cfg.map_after_failures
        if insert and (self.processed % cfg.map_every == 0 or len(self.map) == 0 or self._failures):
            m_pts, m_r = voxel_downsample(pts, cfg.map_voxel, refl)
            self.map.add(host.transform_points(T_l, m_pts), T_l[:3, 3], intensity=m_r if use_i else None)
        T_b = T_l @ self.T_lb
        deg = bool(reg is not None and reg.degenerate)
        self.degenerate += int(deg)
        # the odometry loses its anchoring along the axis (body x, the direction of travel)
        # when a weak direction has a large x-translation component (a weak pitch + height
        # combination near a wall does not)
        # (a held scan's pose is the last one's: standing still keeps the axis as it was)
        axis_weak = not held and (reg is None or not reg.converged or any(abs(w[3]) > 0.5 for w in reg.weak_directions))
        if axis_weak:
            self._last_degenerate = self.processed
            self._weak.append(self.processed)
        self.processed += 1
        body_p, body_r = voxel_downsample(pts, 0.1, refl)
        body_pts = host.transform_points(self.T_bl, body_p)
        res = ScanResult(
            t_ref,
            T_b,
            reg,
            body_pts,
            deg,
            float(reg.condition_number) if reg is not None else np.nan,
            self.processed - 1,
            self._last_degenerate,
            body_r if use_i else None,
            held,
        )
        self.last = res
        return res

"""The camera: pinhole + radial-tangential distortion, exposure, noise, blur and glare.

Per frame: every pixel's ray (undistorted once at start) is cast into the tunnel and the
radiance atlas sampled (vectorised numpy, no per-pixel loops). Then, in this order: motion
blur along each pixel's image velocity over the exposure (from the true twist and the depth),
bloom around saturated light sources, vignetting, the sensor (electrons = radiance x exposure
x sensitivity; Poisson shot noise as a Gaussian of variance = electrons; read noise; gain;
8-bit quantisation and saturation). Auto-exposure meters each frame and adapts with a lag,
preferring exposure time up to ``max_exposure`` and then gain, so dark gaps stay dark and
noisy and lamp glare saturates, as in a real low-light tunnel.
"""

from __future__ import annotations

import dataclasses

import numpy as np
from scipy import ndimage

from ..errors import ConfigError
from ._texture import SurfaceAtlas
from ._tunnel import Tunnel

R_BODY_CAM = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
"""Camera axes (x right, y down, z forward) in the body frame (x forward, y left, z up)."""


@dataclasses.dataclass(frozen=True)
class CameraConfig:
    """Camera intrinsics, exposure control and sensor noise."""

    width: int = 512
    height: int = 320
    fx: float | None = None
    """Focal length (px); default ``0.55 * width`` (~85 degrees horizontal field of view)."""
    fy: float | None = None
    cx: float | None = None
    cy: float | None = None
    distortion: tuple[float, float, float, float] = (-0.25, 0.06, 2e-4, -1e-4)
    """Radial-tangential (k1, k2, p1, p2), OpenCV / Kalibr ``radtan``."""
    rate: float = 10.0
    """Frames per second."""
    colour: bool = False
    """RGB frames (warm lamp tint) instead of grey."""
    translation: tuple[float, float, float] = (0.2, 0.0, 0.3)
    """Camera centre in the body frame (m)."""
    max_exposure: float = 0.02
    min_exposure: float = 5e-5
    max_gain: float = 4.0
    target: float = 100.0
    """Auto-exposure target mean grey level."""
    ae_lag: float = 0.5
    """Auto-exposure smoothing per frame (0 = instant, 1 = frozen)."""
    sensitivity: float = 1.0e4
    """Electrons per (cd/m^2 * s) at the image centre."""
    dn_per_electron: float = 0.1
    """Grey levels per electron at gain 1 (full well ~2550 e-)."""
    read_noise: float = 4.0
    """Read noise (electrons)."""
    vignetting: float = 0.35
    """Brightness lost at the image corners (fraction)."""
    blur: bool = True
    """Motion blur from the true motion during the exposure."""
    bloom: float = 0.6
    """Strength of the glare halo around saturated lights."""
    flicker: float = 0.0
    """Relative amplitude of lamp flicker seen as frame-to-frame exposure beat (0 = none)."""

    def __post_init__(self) -> None:
        if self.width < 16 or self.height < 16:
            raise ConfigError(f"camera resolution must be at least 16x16, got {self.width}x{self.height}")
        if not self.rate > 0:
            raise ConfigError("camera rate must be positive")

    def intrinsics(self) -> tuple[float, float, float, float]:
        fx = self.fx if self.fx is not None else 0.55 * self.width
        fy = self.fy if self.fy is not None else fx
        cx = self.cx if self.cx is not None else (self.width - 1) / 2
        cy = self.cy if self.cy is not None else (self.height - 1) / 2
        return fx, fy, cx, cy


def distort(xn: np.ndarray, yn: np.ndarray, dist) -> tuple[np.ndarray, np.ndarray]:
    """Radial-tangential distortion of normalised coordinates."""
    k1, k2, p1, p2 = dist
    r2 = xn * xn + yn * yn
    radial = 1 + k1 * r2 + k2 * r2 * r2
    xd = xn * radial + 2 * p1 * xn * yn + p2 * (r2 + 2 * xn * xn)
    yd = yn * radial + p1 * (r2 + 2 * yn * yn) + 2 * p2 * xn * yn
    return xd, yd


def undistort(xd: np.ndarray, yd: np.ndarray, dist, iters: int = 30) -> tuple[np.ndarray, np.ndarray]:
    """Invert :func:`distort` by fixed-point iteration."""
    xn, yn = xd.copy(), yd.copy()
    for _ in range(iters):
        x2, y2 = distort(xn, yn, dist)
        xn, yn = xn - (x2 - xd), yn - (y2 - yd)
    return xn, yn


class CameraSimulator:
    """Renders frames of one camera in one tunnel (holds the auto-exposure state)."""

    def __init__(self, config: CameraConfig, tunnel: Tunnel, atlas: SurfaceAtlas, seed: int = 0):
        self.config, self.tunnel, self.atlas = config, tunnel, atlas
        self.rng = np.random.default_rng([seed, 3])
        fx, fy, cx, cy = config.intrinsics()
        self.K = (fx, fy, cx, cy)
        j, i = np.meshgrid(np.arange(config.width, dtype=np.float64), np.arange(config.height, dtype=np.float64))
        xn, yn = undistort((j - cx) / fx, (i - cy) / fy, config.distortion)
        self.xn, self.yn = xn, yn
        rays = np.stack([xn, yn, np.ones_like(xn)], axis=-1)
        self.rays = (rays / np.linalg.norm(rays, axis=-1, keepdims=True)).reshape(-1, 3)
        r2 = ((j - cx) / (config.width / 2)) ** 2 + ((i - cy) / (config.height / 2)) ** 2
        self.vignette = (1 - config.vignetting * np.clip(r2 / 2, 0, 1)).astype(np.float32)
        self._ii, self._jj = (
            a.astype(np.float32) for a in np.meshgrid(np.arange(config.height), np.arange(config.width), indexing="ij")
        )
        self.exposure_gain: float | None = None  # exposure * gain, the auto-exposure state
        self.t_bc = np.asarray(config.translation, dtype=np.float64)

    def pose(self, R_wb: np.ndarray, p_wb: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """World-from-camera rotation and centre."""
        return R_wb @ R_BODY_CAM, p_wb + R_wb @ self.t_bc

    def radiance(self, R_wc: np.ndarray, p_wc: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Scene radiance (H, W) float32 (cd/m^2) and depth along the optical axis (H, W)."""
        cfg, tun = self.config, self.tunnel
        r = self.rays
        d = r[:, 0:1] * R_wc[:, 0] + r[:, 1:2] * R_wc[:, 1] + r[:, 2:3] * R_wc[:, 2]
        hit = tun.raycast(np.broadcast_to(p_wc, d.shape), d)
        L = self.atlas.sample(hit["s"], hit["c"])
        ends = hit["c"] < 0
        L = np.where(ends, 0.35 * self.atlas.lighting.ambient * 3 / np.pi, L)
        L = np.where(hit["sky"], self.atlas.lighting.sky, L).astype(np.float32)
        depth = hit["lam"] * self.rays[:, 2]
        return L.reshape(cfg.height, cfg.width), depth.reshape(cfg.height, cfg.width)

    def _blur(self, L, depth, R_wb, v_w, omega_b, exposure):
        """Average ``L`` along each pixel's image motion during the exposure."""
        fx, fy, _, _ = self.K
        w_c = R_BODY_CAM.T @ omega_b
        v_c = R_BODY_CAM.T @ (R_wb.T @ v_w + np.cross(omega_b, self.t_bc))
        # image velocity of a static point at depth z: rotation part + translation part / z
        x, y = self.xn, self.yn
        inv_z = 1.0 / depth
        # d(x, y)/dt for normalised coordinates (Longuet-Higgins & Prazdny)
        tx, ty, tz = v_c
        wx, wy, wz = w_c
        dx = (-tx + x * tz) * inv_z + x * y * wx - (1 + x * x) * wy + y * wz
        dy = (-ty + y * tz) * inv_z + (1 + y * y) * wx - x * y * wy - x * wz
        du, dv = (fx * exposure) * dx, (fy * exposure) * dy
        length = float(np.percentile(np.hypot(du[::7, ::7], dv[::7, ::7]), 99))
        if length < 0.3:
            return L, length
        taps = int(min(5, max(2, np.ceil(length))))
        acc = np.zeros_like(L)
        for f in np.linspace(-0.5, 0.5, taps):
            coords = [
                self._ii + np.float32(f) * dv.astype(np.float32),
                self._jj + np.float32(f) * du.astype(np.float32),
            ]
            acc += ndimage.map_coordinates(L, coords, order=1, mode="nearest")
        return acc / taps, length

    def render(self, t: float, R_wb, p_wb, v_w, omega_b) -> tuple[np.ndarray, dict[str, float]]:
        """One frame at time ``t`` (mid-exposure) from the body state; returns the uint8 image
        (H, W) or (H, W, 3) and its exposure figures."""
        cfg = self.config
        R_wc, p_wc = self.pose(R_wb, p_wb)
        L, depth = self.radiance(R_wc, p_wc)
        metered = float(np.mean(np.minimum(L, 200.0) * self.vignette))
        want = cfg.target / (cfg.dn_per_electron * cfg.sensitivity * max(metered, 1e-6))
        if self.exposure_gain is None:
            self.exposure_gain = want
        else:
            self.exposure_gain = float(
                np.exp(cfg.ae_lag * np.log(self.exposure_gain) + (1 - cfg.ae_lag) * np.log(want))
            )
        eg = float(np.clip(self.exposure_gain, cfg.min_exposure, cfg.max_exposure * cfg.max_gain))
        self.exposure_gain = eg
        exposure = min(eg, cfg.max_exposure)
        gain = max(1.0, eg / exposure)
        if cfg.flicker:
            L = L * np.float32(1 + cfg.flicker * np.sin(2 * np.pi * 100.3 * t))
        blur = 0.0
        if cfg.blur:
            L, blur = self._blur(L, depth, R_wb, v_w, omega_b, exposure)
        electrons = L * self.vignette * np.float32(exposure * cfg.sensitivity)
        full = 255.0 / (cfg.dn_per_electron * gain)
        if cfg.bloom:
            # glare: a halo around saturated sources, bounded (a lens spreads a few % of it)
            excess = np.minimum(np.maximum(electrons[::4, ::4] - full, 0), 4 * full)
            if excess.any():
                halo = ndimage.gaussian_filter(excess, 2.5, mode="constant")
                halo = np.repeat(np.repeat(halo, 4, axis=0), 4, axis=1)[: L.shape[0], : L.shape[1]]
                pad = ((0, L.shape[0] - halo.shape[0]), (0, L.shape[1] - halo.shape[1]))
                electrons = electrons + np.float32(cfg.bloom * 0.25) * np.pad(halo, pad)
        channels = [np.float32(1.0)]
        if cfg.colour:
            channels = [np.float32(1.0), np.float32(0.86), np.float32(0.66)]
        out = []
        for tint in channels:
            e = np.minimum(electrons * tint, 4 * full)
            noisy = e + np.sqrt(e) * self.rng.standard_normal(e.shape, dtype=np.float32)
            noisy += cfg.read_noise * self.rng.standard_normal(e.shape, dtype=np.float32)
            dn = noisy * np.float32(cfg.dn_per_electron * gain)
            out.append(np.clip(np.rint(dn), 0, 255).astype(np.uint8))
        img = out[0] if len(out) == 1 else np.stack(out, axis=-1)
        info = {"exposure": exposure, "gain": gain, "blur_px": blur, "mean": float(img.mean())}
        return img, info

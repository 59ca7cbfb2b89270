"""The LiDAR: a Livox HAP-like non-repetitive scan or a 16-ring spinning scanner.

Every point has its own emission time inside the frame; the sensor pose is evaluated at that
time (so a moving sensor's frame is motion-distorted exactly as a real one) and the ray cast
into the tunnel. Points are returned in the LiDAR frame at their own time, with
``point_times`` relative to the frame stamp (the frame start), as drivers publish them.

- ``hap``: 120 x 25 degrees, 452,000 points/s (datasheet) at 10 Hz = 45,200 per frame
  before ``decimation``. The pattern is an approximation (Livox does not publish it): six
  channels sweep azimuth with a triangle wave while their elevations wobble at an
  incommensurate frequency and precess with absolute time, so successive frames cover
  different points (non-repetitive; coverage grows with integration time). Blind zone 0.5 m.
- ``ring16``: 16 rings at -15..+15 degrees, 0.2 degree azimuth steps, 360 degrees per frame
  (28,800 points per frame before ``decimation``), time by azimuth; ``ring`` ids are kept.

Range noise is Gaussian; dropouts are random plus grazing-angle returns; intensity is
albedo x (0.3 + 0.7 cos(incidence)) scaled to 0..255 with multiplicative noise
(``intensity_noise``) and rounded to whole counts, as a sensor reports it; beyond
``max_range`` nothing returns.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from ..errors import ConfigError
from ._texture import SurfaceAtlas
from ._tunnel import Tunnel


@dataclasses.dataclass(frozen=True)
class LidarConfig:
    """LiDAR model, noise and mounting."""

    model: str = "hap"
    """``"hap"`` (Livox HAP pattern) or ``"ring16"``."""
    rate: float = 10.0
    """Frames per second."""
    decimation: int = 4
    """Keep every n-th point of the datasheet rate (1 = the full 45,200 / 28,800 per frame)."""
    range_noise: float = 0.02
    """Range standard deviation (m)."""
    dropout: float = 0.02
    """Fraction of returns lost at random."""
    max_range: float = 150.0
    min_range: float = 0.5
    intensity_noise: float = 0.08
    """Relative standard deviation of each return's intensity. 0.08 makes the scan-to-scan
    repeatability of the relative reflectivity, against the pattern's own spread, what the
    real scan pair in ``shared/data/lidar`` shows (``benchmarks/sim_realism.py``)."""
    translation: tuple[float, float, float] = (0.25, 0.0, 0.45)
    """LiDAR origin in the body frame (m); axes as the body's (x forward, y left, z up)."""

    def __post_init__(self) -> None:
        if self.model not in ("hap", "ring16"):
            raise ConfigError(f"lidar model must be 'hap' or 'ring16', got {self.model!r}")
        if self.decimation < 1 or not self.rate > 0:
            raise ConfigError("lidar decimation must be >= 1 and rate > 0")
        if not self.intensity_noise >= 0:
            raise ConfigError("lidar intensity_noise must be >= 0")

    @property
    def points_per_second(self) -> float:
        return 452_000.0 if self.model == "hap" else 288_000.0


def scan_pattern(config: LidarConfig, t_frame: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Unit directions (N, 3) in the LiDAR frame, time offsets (N,) s and ring/line ids (N,)."""
    period = 1.0 / config.rate
    if config.model == "hap":
        n = round(config.points_per_second * period)
        k = np.arange(0, n, config.decimation)
        tau = k / config.points_per_second
        line = k % 6
        ta = t_frame + tau  # absolute time: the pattern never repeats between frames
        phase = 83.7 * ta + line / 6.0
        tri = 2 * np.abs(2 * (phase - np.floor(phase + 0.5))) - 1
        az = np.deg2rad(60.0) * tri
        wob = np.sin(2 * np.pi * 17.31 * ta + 1.7 * line) + 0.5 * np.sin(2 * np.pi * 0.613 * ta + line)
        el = np.deg2rad(12.5) * np.clip((line - 2.5) / 3.0 + 0.1 * wob, -1, 1)
    else:
        cols = round(360 / 0.2)
        col = np.arange(cols)
        ring = np.arange(16)
        grid_c, grid_r = np.meshgrid(col, ring, indexing="ij")
        C, Rg = grid_c.reshape(-1)[:: config.decimation], grid_r.reshape(-1)[:: config.decimation]
        tau = C / cols * period
        az = -np.pi + 2 * np.pi * C / cols
        el = np.deg2rad(-15.0 + 2.0 * Rg)
        line = Rg
    d = np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], axis=-1)
    return d, tau, line


class LidarSimulator:
    """Produces motion-distorted LiDAR frames from a trajectory."""

    def __init__(self, config: LidarConfig, tunnel: Tunnel, atlas: SurfaceAtlas, seed: int = 0):
        self.config, self.tunnel, self.atlas = config, tunnel, atlas
        self.rng = np.random.default_rng([seed, 5])
        self.seed = seed
        self.t_bl = np.asarray(config.translation, dtype=np.float64)

    def scan(self, t: float, state_at) -> dict[str, np.ndarray]:
        """One frame starting at ``t``; ``state_at(times)`` returns the body ``R``, ``p``.

        Returns ``points`` (N, 3) LiDAR frame, ``intensity``, ``point_times`` (s from t),
        ``ring`` (line / ring id) and, for tests, ``world`` (N, 3) noise-free hit points."""
        cfg = self.config
        d_l, tau, line = scan_pattern(cfg, t)
        st = state_at(t + tau)
        R, p = st["R"], st["p"]
        o = p + np.einsum("nij,j->ni", R, self.t_bl)
        d_w = np.einsum("nij,nj->ni", R, d_l)
        hit = self.tunnel.raycast(o, d_w)
        rng = hit["lam"]
        ns_, nu, nv = self.tunnel.normal_uv(hit["wall"], hit["u"], hit["v"])
        n_w = self.tunnel.frame_to_world(self.tunnel.k * hit["s"], ns_, nu, nv)
        cos_inc = np.abs(np.einsum("ni,ni->n", n_w, d_w))
        albedo = np.where(hit["c"] >= 0, self.atlas.sample(hit["s"], hit["c"], self.atlas.albedo), 0.4)
        keep = (rng > cfg.min_range) & (rng < cfg.max_range) & ~hit["sky"]
        keep &= self.rng.random(len(rng)) >= cfg.dropout
        keep &= self.rng.random(len(rng)) >= np.clip((0.12 - cos_inc) / 0.12, 0, 1)  # grazing returns fade
        noisy = rng + cfg.range_noise * self.rng.standard_normal(len(rng))
        pts = d_l * noisy[:, None]
        inten = 255 * albedo * (0.3 + 0.7 * cos_inc)
        if cfg.intensity_noise:
            # its own stream, keyed by the frame time: the range noise and dropouts are unchanged
            irng = np.random.default_rng([self.seed, 29, round(float(t) * 1e4)])
            inten = np.rint(inten * (1 + cfg.intensity_noise * irng.standard_normal(len(inten))))
        inten = np.clip(inten, 0, 255)
        return {
            "points": pts[keep],
            "intensity": inten[keep],
            "point_times": tau[keep],
            "ring": line[keep],
            "world": hit["p"][keep],
        }

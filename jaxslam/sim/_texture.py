"""Surface appearance: a procedural albedo atlas and baked lamp lighting over ``(s, c)``.

The tunnel surface is unrolled into an atlas: rows along ``s`` (from ``s_min``), columns
round the perimeter ``c``, one texel per ``texel`` metres. Albedo (reflectance 0..1) holds
concrete grain, stains and segment joints everywhere; outside the plain stretches the walls
carry pipes with flanges and brackets, cable trays with rungs and cables, conduits, signs,
bolts and cracks (the corners and blobs feature detectors find). Irradiance (lux) from the
lamps (point sources on the ceiling, ``I cos(theta)`` downwards), a little inter-reflection
and daylight from the entrance is computed on a coarse grid and multiplied in, giving the
radiance atlas (cd/m^2) the camera samples. Lamp faces are emissive (the glare).
"""

from __future__ import annotations

import dataclasses

import numpy as np
from scipy import ndimage

from ..errors import ConfigError
from ._tunnel import WALL_CEIL, WALL_FLOOR, WALL_LEFT, WALL_RIGHT, Tunnel

LIGHTING: dict[str, tuple[float, float, float, float, float]] = {
    # spacing m, candela, dead-lamp fraction, intensity spread, entrance daylight lux
    "normal": (5.0, 1500.0, 0.0, 0.1, 3000.0),
    "uneven": (7.0, 900.0, 0.25, 0.35, 2000.0),
    "dark": (12.0, 250.0, 0.4, 0.4, 800.0),
}


@dataclasses.dataclass(frozen=True)
class LightingConfig:
    """Lamps and daylight."""

    mode: str = "uneven"
    """``"normal"`` (bright, regular), ``"uneven"`` (dead lamps, dark gaps), ``"dark"``."""
    ambient: float = 0.4
    """Ambient irradiance (lux) everywhere (inter-reflection floor)."""
    sky: float = 4000.0
    """Luminance (cd/m^2) seen through the open entrance."""
    lamp_luminance: float = 6000.0
    """Luminance of a lit lamp face (cd/m^2): saturates the camera and blooms."""

    def __post_init__(self) -> None:
        if self.mode not in LIGHTING:
            raise ConfigError(f"lighting must be one of {sorted(LIGHTING)}, got {self.mode!r}")


def _noise(shape: tuple[int, int], cells: tuple[float, float], rng: np.random.Generator, order: int = 1) -> np.ndarray:
    """Smooth value noise in [0, 1] of ``shape`` with ``cells`` lattice cells per axis."""
    lat = rng.random((max(2, int(cells[0]) + 2), max(2, int(cells[1]) + 2))).astype(np.float32)
    zoom = (shape[0] / (lat.shape[0] - 1), shape[1] / (lat.shape[1] - 1))
    out = ndimage.zoom(lat, zoom, order=order, mode="nearest", grid_mode=False)
    return out[: shape[0], : shape[1]]


class SurfaceAtlas:
    """The radiance atlas of a tunnel (built once per recording, deterministic by seed)."""

    def __init__(self, tunnel: Tunnel, lighting: LightingConfig, seed: int = 0):
        self.tunnel, self.lighting = tunnel, lighting
        cfg = tunnel.config
        self.texel = cfg.texel
        self.ns = int(np.ceil((cfg.s_max - cfg.s_min) / cfg.texel)) + 1
        self.nc = int(np.ceil(cfg.perimeter / cfg.texel)) + 1
        rng = np.random.default_rng([seed, 7])
        self.lamps = self._lamps(rng)
        self.albedo, emissive = self._albedo(rng)
        irr = self._irradiance()
        self.radiance = (self.albedo * irr / np.pi + emissive).astype(np.float32)

    # --- lamps -----------------------------------------------------------------------------------

    def _lamps(self, rng: np.random.Generator) -> np.ndarray:
        """``(L, 3)``: s, intensity (cd, 0 when dead), on (1/0)."""
        cfg = self.tunnel.config
        spacing, cd, dead, spread, _ = LIGHTING[self.lighting.mode]
        s = np.arange(cfg.s_min + spacing / 2, cfg.s_max, spacing)
        on = rng.random(len(s)) >= dead
        inten = cd * np.clip(1 + spread * rng.standard_normal(len(s)), 0.3, 2.0) * on
        return np.stack([s, inten, on.astype(float)], axis=1)

    def lamp_positions(self) -> np.ndarray:
        cfg = self.tunnel.config
        s = self.lamps[:, 0]
        return self.tunnel.to_world(s, 0.0 * s, np.full_like(s, cfg.height - 0.08))

    # --- albedo ----------------------------------------------------------------------------------

    def _grid(self) -> tuple[np.ndarray, np.ndarray]:
        cfg = self.tunnel.config
        s = (cfg.s_min + np.arange(self.ns) * self.texel).astype(np.float32)
        c = (np.arange(self.nc) * self.texel).astype(np.float32)
        return s, c

    def _albedo(self, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        cfg, tx = self.tunnel.config, self.texel
        shape = (self.ns, self.nc)
        s, c = self._grid()
        S = s[:, None]
        L, P = cfg.s_max - cfg.s_min, cfg.perimeter
        u, v, wall = self.tunnel.surface_point(c.astype(np.float64), c.astype(np.float64))
        u, v, wall = u.astype(np.float32)[None, :], v.astype(np.float32)[None, :], wall[None, :]
        # concrete: low-frequency tone, grain, stains
        a = 0.42 + 0.10 * (_noise(shape, (L / 1.5, P / 1.5), rng, order=3) - 0.5)
        a += 0.02 * (_noise(shape, (L / 0.05, P / 0.05), rng) - 0.5)
        a += 0.01 * (rng.random(shape, dtype=np.float32) - 0.5)
        stain = _noise(shape, (L / 0.8, P / 0.8), rng, order=3)
        a *= 1 - 0.45 * np.clip((stain - 0.62) * 5, 0, 1)
        a = np.where(wall == WALL_FLOOR, a * 0.8, a)
        # segment joints every 6 m (everywhere)
        a = np.where(np.abs(np.mod(S + 1.0, 6.0) - 0.01) < 0.012, a * 0.35, a)
        structured = np.ones((self.ns, 1), dtype=bool)
        for f0, f1 in cfg.plain:
            structured &= ~((f0 * cfg.length <= S) & (f1 * cfg.length >= S))
        a = self._structure(a, S, u, v, wall, structured, rng)
        emissive = np.zeros(shape, dtype=np.float32)
        ceil = wall == WALL_CEIL
        for ls, inten, on in self.lamps:
            i0, i1 = int((ls - 0.6 - cfg.s_min) / tx), int((ls + 0.6 - cfg.s_min) / tx)
            i0, i1 = max(i0, 0), min(i1, self.ns)
            if i1 <= i0:
                continue
            box = (ceil & (np.abs(u) < 0.12)).repeat(i1 - i0, axis=0)
            frame = (ceil & (np.abs(u) < 0.17)).repeat(i1 - i0, axis=0)
            box[:8], box[-8:] = False, False
            a[i0:i1] = np.where(frame, 0.12, a[i0:i1])
            a[i0:i1] = np.where(box, 0.8, a[i0:i1])
            if on:
                lum = self.lighting.lamp_luminance * min(1.5, inten / LIGHTING[self.lighting.mode][1])
                inner = box.copy()
                inner[:4], inner[-4:] = False, False
                emissive[i0:i1] = np.where(inner, lum, 0.0)
        return np.clip(a, 0.02, 0.95).astype(np.float32), emissive

    def _structure(self, a, S, u, v, wall, structured, rng):
        """Pipes, brackets, cable trays, conduits, signs, bolts and cracks."""
        cfg = self.tunnel.config
        shape = a.shape
        L, P = cfg.s_max - cfg.s_min, cfg.perimeter
        left, right, ceil = wall == WALL_LEFT, wall == WALL_RIGHT, wall == WALL_CEIL
        st = structured
        # pipes on the left wall (shaded cylinders), flanges every 3 m, brackets every 1.5 m
        for hc, r, tone in ((1.55, 0.09, 0.7), (1.95, 0.06, 0.3)):
            d = (v - hc) / r
            on = left & (np.abs(d) < 1) & st
            shade = tone * (0.55 + 0.45 * np.sqrt(np.clip(1 - d * d, 0, 1)))
            a = np.where(on, shade, a)
            flange = on & (np.abs(np.mod(S, 3.0) - 1.5) < 0.04)
            a = np.where(flange, tone * 0.5 + 0.2, a)
        bracket = left & st & (np.abs(np.mod(S, 1.5) - 0.75) < 0.035) & (v > 1.35) & (v < 2.1)
        a = np.where(bracket, 0.1, a)
        bolt = bracket & (np.abs(np.mod(S, 1.5) - 0.75) < 0.012) & (np.abs(np.mod(v, 0.25) - 0.125) < 0.012)
        a = np.where(bolt, 0.85, a)
        # cable trays on the right wall: edges, cables, rungs every 0.3 m
        for h0 in (1.1, 1.9):
            tray = right & st & (v > h0) & (v < h0 + 0.22)
            cable = np.mod((v - h0) * 40.0, 1.0)
            a = np.where(tray, 0.25 + 0.35 * (cable > 0.5), a)
            rung = tray & (np.abs(np.mod(S, 0.3) - 0.15) < 0.02)
            a = np.where(rung, 0.8, a)
            edge = right & st & ((np.abs(v - h0) < 0.015) | (np.abs(v - h0 - 0.22) < 0.015))
            a = np.where(edge, 0.85, a)
            hanger = right & st & (np.abs(np.mod(S, 1.2) - 0.6) < 0.03) & (v > h0 - 0.1) & (v < h0 + 0.3)
            a = np.where(hanger, 0.08, a)
        # conduit along the ceiling, clamps every 1 m
        cond = ceil & st & (np.abs(u - 0.6) < 0.03)
        a = np.where(cond, 0.75, a)
        a = np.where(cond & (np.abs(np.mod(S, 1.0) - 0.5) < 0.02), 0.15, a)
        # signs every 10 m (both walls): a dark plate with a light pictogram-like pattern
        for w, hs in ((left, 1.0), (right, 0.7)):
            sign = w & st & (np.abs(np.mod(S - 4.0, 10.0) - 5.0) < 0.2) & (np.abs(v - hs) < 0.15)
            pat = (np.abs(np.mod(S * 12, 2.0) - 1) < 0.5) ^ (np.abs(np.mod(v * 12, 2.0) - 1) < 0.5)
            a = np.where(sign, np.where(pat, 0.85, 0.12), a)
        # cracks: thin iso-lines of a noise field, gated by a sparse mask (more on structured walls)
        n = _noise(shape, (L / 0.4, P / 0.4), rng, order=3)
        gate = _noise(shape, (L / 2.0, P / 2.0), rng, order=1)
        crack = (np.abs(n - 0.5) < 0.012) & (gate > np.where(st, 0.55, 0.8)) & (wall != WALL_FLOOR)
        a = np.where(crack, a * 0.3, a)
        # spalls/patches: blobs in the structured zone
        patch = (_noise(shape, (L / 0.25, P / 0.25), rng) > 0.86) & st & (gate > 0.4)
        a = np.where(patch, a * 0.55, a)
        return a

    # --- lighting --------------------------------------------------------------------------------

    def _irradiance(self) -> np.ndarray:
        """Irradiance (lux) on the fine atlas grid, computed on a 5 cm grid and interpolated."""
        cfg, tun = self.tunnel.config, self.tunnel
        step = 0.05
        s = cfg.s_min + np.arange(int(np.ceil((cfg.s_max - cfg.s_min) / step)) + 1) * step
        c = np.arange(int(np.ceil(cfg.perimeter / step)) + 1) * step
        u, v, wall = tun.surface_point(c, c)
        S = s[:, None] + 0 * c[None, :]
        U, V, W = (np.broadcast_to(x[None, :], S.shape) for x in (u, v, wall))
        X = tun.to_world(S, U, V)
        ns_, nu, nv = tun.normal_uv(W, U, V)
        N = tun.frame_to_world(tun.k * S, ns_, nu, nv)
        E: np.ndarray = np.full(S.shape, self.lighting.ambient)
        lamp_xyz = self.lamp_positions()
        for (_, inten, on), lp in zip(self.lamps, lamp_xyz):
            if not on:
                continue
            D = lp - X
            d2 = np.einsum("...i,...i->...", D, D)
            dist = np.sqrt(d2)
            cos_surf = np.clip(np.einsum("...i,...i->...", N, D) / dist, 0, None)
            cos_lamp = np.clip(-D[..., 2] / dist, 0, None)  # lamp emits downwards
            direct = inten * cos_lamp * cos_surf / np.maximum(d2, 0.05)
            E += direct + 0.08 * inten / np.maximum(d2, 1.0)  # + inter-reflection
        if cfg.entrance:
            E += LIGHTING[self.lighting.mode][4] * np.exp(-(S - cfg.s_min) / 2.5)
        zoom = (self.ns / E.shape[0], self.nc / E.shape[1])
        fine = ndimage.zoom(E.astype(np.float32), zoom, order=1, mode="nearest", grid_mode=True)
        fine = fine[: self.ns, : self.nc]
        if fine.shape != (self.ns, self.nc):
            fine = np.pad(fine, ((0, self.ns - fine.shape[0]), (0, self.nc - fine.shape[1])), mode="edge")
        return fine

    def irradiance_at(self, s: np.ndarray, c: np.ndarray) -> np.ndarray:
        """Irradiance (lux) at surface points (for lighting statistics)."""
        alb = self.sample(s, c, self.albedo)
        rad = self.sample(s, c, self.radiance)
        return rad * np.pi / np.maximum(alb, 1e-3)

    def sample(self, s: np.ndarray, c: np.ndarray, atlas: np.ndarray | None = None) -> np.ndarray:
        """Bilinear lookup of ``atlas`` (default: radiance) at surface coordinates."""
        atlas = self.radiance if atlas is None else atlas
        cfg = self.tunnel.config
        fi = np.clip((s - cfg.s_min) / self.texel, 0, self.ns - 1.001)
        fj = np.clip(np.mod(c, cfg.perimeter) / self.texel, 0, self.nc - 1.001)
        i0, j0 = fi.astype(np.int64), fj.astype(np.int64)
        ws, wc = (fi - i0).astype(np.float32), (fj - j0).astype(np.float32)
        flat = atlas.reshape(-1)
        base = i0 * self.nc + j0
        a00, a01 = flat[base], flat[base + 1]
        a10, a11 = flat[base + self.nc], flat[base + self.nc + 1]
        return (a00 * (1 - wc) + a01 * wc) * (1 - ws) + (a10 * (1 - wc) + a11 * wc) * ws

"""Tunnel geometry: an analytic enclosed corridor, its surface coordinates and a ray caster.

Frames: world is Z-up (gravity ``(0, 0, -9.81)``), the route starts at the origin heading +x.
The centreline is a circular arc of ``curvature`` (1/m, 0 = straight, > 0 turns left) that
rises ``slope`` m per m. A point has tunnel coordinates ``(s, u, v)``: ``s`` arc length along
the centreline, ``u`` lateral (left positive), ``v`` height above the floor (vertical). The
cross-section in ``(u, v)`` is a rectangle ``|u| < width/2, 0 < v < height`` or a horseshoe
(vertical walls up to the springline ``height - width/2``, a half-circle arch above). The
tunnel runs from ``s_min`` (the entrance portal: open to daylight or closed) to ``s_max``
(a closed end wall).

Surface coordinates ``(s, c)``: ``c`` runs round the perimeter, floor first (right to left),
then the left wall, ceiling/arch, right wall. Walls are numbered (see ``WALL_*``) so callers
can look up normals and textures. Everything is numpy, vectorised over rays, float64.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from ..errors import ConfigError

WALL_FLOOR, WALL_LEFT, WALL_CEIL, WALL_RIGHT, WALL_START, WALL_END = range(6)
"""Wall ids: floor, left wall, ceiling (or arch), right wall, entrance (s_min), end (s_max)."""


@dataclasses.dataclass(frozen=True)
class TunnelConfig:
    """The corridor's shape and surface structure."""

    length: float = 30.0
    """Route length one way (m) along the centreline; the robot drives out and back."""
    section: str = "rectangular"
    """``"rectangular"`` or ``"horseshoe"``."""
    width: float = 3.0
    """Inner width (m)."""
    height: float = 3.0
    """Ceiling height (m); for the horseshoe the crown height (springline at height - width/2)."""
    curvature: float = 0.0
    """Centreline curvature (1/m), 0 for straight (fast closed-form ray casting); > 0 turns
    left (e.g. 1/300: rays are then bracketed and bisected, ~5x slower)."""
    slope: float = 0.01
    """Rise per metre along the route."""
    margin_start: float = 6.0
    """Tunnel length behind the start (m): the entrance portal is at ``s = -margin_start``."""
    margin_end: float = 6.0
    """Tunnel beyond the far end of the route (m), closed by an end wall."""
    entrance: bool = True
    """The portal at ``s_min`` is open to daylight (else a closed wall)."""
    plain: tuple[tuple[float, float], ...] = ((0.3, 0.62),)
    """Stretches of plain concrete (no wall structure), as fractions of ``length``."""
    texel: float = 0.006
    """Texture resolution on the surface (m)."""

    def __post_init__(self) -> None:
        if self.section not in ("rectangular", "horseshoe"):
            raise ConfigError(f"section must be 'rectangular' or 'horseshoe', got {self.section!r}")
        if not (self.length > 0 and self.width > 0.5 and self.height > 0.5 and self.texel > 0):
            raise ConfigError("tunnel length, width, height and texel must be positive (width, height > 0.5 m)")
        if self.section == "horseshoe" and self.height <= self.width / 2:
            raise ConfigError("horseshoe needs height > width / 2 (the springline above the floor)")
        if abs(self.curvature) * (self.width / 2) >= 0.2:
            raise ConfigError(f"curvature {self.curvature} 1/m is too sharp for a {self.width} m wide tunnel")

    @property
    def s_min(self) -> float:
        return -self.margin_start

    @property
    def s_max(self) -> float:
        return self.length + self.margin_end

    @property
    def springline(self) -> float:
        """Height where the walls meet the arch (horseshoe) or the ceiling (rectangular)."""
        return self.height - self.width / 2 if self.section == "horseshoe" else self.height

    @property
    def perimeter(self) -> float:
        w, h = self.width, self.height
        if self.section == "rectangular":
            return 2 * w + 2 * h
        return w + 2 * self.springline + np.pi * w / 2


class Tunnel:
    """Geometry of one :class:`TunnelConfig` (coordinates, frames, distances, ray casting)."""

    def __init__(self, config: TunnelConfig):
        self.config = config
        self.k = float(config.curvature)

    # --- coordinates ---------------------------------------------------------------------------

    def centreline(self, s: np.ndarray, xp=np) -> tuple:
        """Centreline point ``(x, y, z)`` and heading ``phi`` at arc length ``s`` (xp: np or jnp)."""
        k, slope = self.k, self.config.slope
        phi = k * s
        if k == 0.0:
            x, y = s, 0.0 * s
        else:
            x, y = xp.sin(phi) / k, (1 - xp.cos(phi)) / k
        return x, y, slope * s, phi

    def to_world(self, s, u, v, xp=np):
        """World ``(..., 3)`` point of tunnel coordinates (``xp``: np or jax.numpy)."""
        x, y, z, phi = self.centreline(s, xp)
        return xp.stack([x - u * xp.sin(phi), y + u * xp.cos(phi), z + v], axis=-1)

    def to_tunnel(self, p: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """``(s, u, v, phi)`` of world points ``(..., 3)``."""
        px, py, pz = p[..., 0], p[..., 1], p[..., 2]
        k = self.k
        if k == 0.0:
            s, u = px, py
        else:
            r = 1.0 / k
            sg = np.sign(r)
            phi = np.arctan2(px * sg, (r - py) * sg)
            s = phi * r
            u = r - sg * np.hypot(px, r - py)
        v = pz - self.config.slope * s
        return s, u, v, k * s

    # --- the inside as constraints g_i >= 0 ------------------------------------------------------

    def constraints(self, p: np.ndarray) -> tuple[np.ndarray, tuple[np.ndarray, np.ndarray, np.ndarray]]:
        """``g`` (..., 6): per wall, the distance inside it (>= 0 inside), and ``(s, u, v)``."""
        c = self.config
        s, u, v, _ = self.to_tunnel(p)
        w2 = c.width / 2
        big = np.full_like(s, 1e9)
        if c.section == "rectangular":
            ceil = c.height - v
        else:
            h = c.springline
            ceil = np.where(v > h, w2 - np.hypot(u, v - h), big)
        g = np.stack([v, w2 - u, ceil, w2 + u, s - c.s_min, c.s_max - s], axis=-1)
        return g, (s, u, v)

    def signed_distance(self, p: np.ndarray) -> np.ndarray:
        """Distance from the surface (> 0 inside, approximate near edges), for tests."""
        g, _ = self.constraints(p)
        return g.min(axis=-1)

    def inside_portal(self, p: np.ndarray) -> np.ndarray:
        """True where a point has left the tunnel through the open entrance (``s < s_min``)."""
        s, _, _, _ = self.to_tunnel(p)
        return s < self.config.s_min

    # --- surface coordinates and normals -------------------------------------------------------

    def surface_c(self, wall: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        """Perimeter coordinate ``c`` of a surface point on ``wall`` (see the module docstring)."""
        c = self.config
        w2, h = c.width / 2, c.springline
        if c.section == "rectangular":
            ceil = c.width + c.height + (w2 - u)
        else:
            alpha = np.arctan2(np.clip(v - h, 0, None), u)
            ceil = c.width + h + w2 * alpha
        if c.section == "rectangular":
            right = 2 * c.width + c.height + (c.height - v)
        else:
            right = c.width + h + np.pi * w2 + (h - v)
        return np.select(
            [wall == WALL_FLOOR, wall == WALL_LEFT, wall == WALL_CEIL, wall == WALL_RIGHT],
            [u + w2, c.width + v, ceil, right],
            default=-1.0,
        )

    def surface_point(self, s: np.ndarray, cc: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Inverse of :meth:`surface_c`: ``(u, v, wall)`` of perimeter coordinate ``cc``."""
        c = self.config
        w, w2, h = c.width, c.width / 2, c.springline
        cc = np.mod(cc, c.perimeter)
        if c.section == "rectangular":
            edges = [w, w + h, 2 * w + h]
            ceil_u, ceil_v = w2 - (cc - w - h), np.full_like(cc, h)
            right_v = h - (cc - 2 * w - h)
        else:
            edges = [w, w + h, w + h + np.pi * w2]
            a = (cc - w - h) / w2
            ceil_u, ceil_v = w2 * np.cos(a), h + w2 * np.sin(a)
            right_v = h - (cc - edges[2])
        wall = np.searchsorted(np.asarray(edges), cc, side="right")
        u = np.select([wall == 0, wall == 1, wall == 2], [cc - w2, np.full_like(cc, w2), ceil_u], -w2)
        v = np.select([wall == 0, wall == 1, wall == 2], [np.zeros_like(cc), cc - w, ceil_v], right_v)
        return u, v, wall

    def normal_uv(self, wall: np.ndarray, u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Inward unit normal ``(n_s, n_u, n_v)`` in the tunnel frame (tangent, left, up)."""
        c = self.config
        zero = np.zeros_like(u)
        nu = np.select([wall == WALL_LEFT, wall == WALL_RIGHT], [-1.0 + zero, 1.0 + zero], zero)
        nv = np.select([wall == WALL_FLOOR], [1.0 + zero], zero)
        ns = np.select([wall == WALL_START, wall == WALL_END], [1.0 + zero, -1.0 + zero], zero)
        if c.section == "rectangular":
            nv = np.where(wall == WALL_CEIL, -1.0, nv)
        else:
            du, dv = -u, -(v - c.springline)
            r = np.maximum(np.hypot(du, dv), 1e-9)
            nu = np.where(wall == WALL_CEIL, du / r, nu)
            nv = np.where(wall == WALL_CEIL, dv / r, nv)
        return ns, nu, nv

    def frame_to_world(self, phi: np.ndarray, vec_s, vec_u, vec_v) -> np.ndarray:
        """World vectors ``(..., 3)`` of tunnel-frame components (tangent, left, up; horizontal
        tangent: the small slope is ignored for directions)."""
        cp, sp = np.cos(phi), np.sin(phi)
        return np.stack([vec_s * cp - vec_u * sp, vec_s * sp + vec_u * cp, vec_v], axis=-1)

    # --- ray casting -----------------------------------------------------------------------------

    def _grad(self, p: np.ndarray, wall: np.ndarray, s, u, v) -> np.ndarray:
        """World gradient of constraint ``wall`` at points ``p`` (..., 3)."""
        c = self.config
        k = self.k
        if k == 0.0:
            gs = np.zeros_like(p)
            gs[..., 0] = 1.0
            gu = np.zeros_like(p)
            gu[..., 1] = 1.0
        else:
            r = 1.0 / k
            sg = np.sign(r)
            px, py = p[..., 0], p[..., 1]
            rho2 = px**2 + (r - py) ** 2
            rho = np.sqrt(rho2)
            gs = np.stack([r * (r - py) / rho2, r * px / rho2, np.zeros_like(px)], axis=-1)
            gu = -sg * np.stack([px / rho, -(r - py) / rho, np.zeros_like(px)], axis=-1)
        gv = -c.slope * gs
        gv[..., 2] += 1.0
        if c.section == "rectangular":
            gceil = -gv
        else:
            dv = v - c.springline
            rho = np.maximum(np.hypot(u, dv), 1e-9)
            gceil = -(u[..., None] * gu + dv[..., None] * gv) / rho[..., None]
        grads = np.stack([gv, -gu, gceil, gu, gs, -gs], axis=-2)
        return np.take_along_axis(grads, wall[..., None, None], axis=-2)[..., 0, :]

    def _straight_exit(self, o: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Exit distance and wall in the straight tangent tunnel at each origin (first guess)."""
        c = self.config
        s0, u0, v0, phi = self.to_tunnel(o)
        cp, sp = np.cos(phi), np.sin(phi)
        ds = d[..., 0] * cp + d[..., 1] * sp
        du = -d[..., 0] * sp + d[..., 1] * cp
        dv = d[..., 2] - c.slope * ds
        w2 = c.width / 2
        inf = np.inf

        def exit_plane(pos, rate, limit, upper):
            # distance until coordinate `pos` moving at `rate` reaches `limit` from below/above
            with np.errstate(divide="ignore", invalid="ignore"):
                t = (limit - pos) / rate
            ok = (rate > 1e-12) if upper else (rate < -1e-12)
            return np.where(ok, np.maximum(t, 0.0), inf)

        cands = [
            exit_plane(v0, dv, 0.0, False),
            exit_plane(u0, du, w2, True),
            exit_plane(v0, dv, c.height, True),
            exit_plane(u0, du, -w2, False),
            exit_plane(s0, ds, c.s_min, False),
            exit_plane(s0, ds, c.s_max, True),
        ]
        if c.section == "horseshoe":
            h = c.springline
            a = du**2 + dv**2
            b = 2 * (u0 * du + (v0 - h) * dv)
            cq = u0**2 + (v0 - h) ** 2 - w2**2
            disc = np.maximum(b * b - 4 * a * cq, 0.0)
            with np.errstate(divide="ignore", invalid="ignore"):
                t = (-b + np.sqrt(disc)) / (2 * a)
            vh = v0 + t * dv
            cands[WALL_CEIL] = np.where((a > 1e-12) & (vh >= h), np.maximum(t, 0.0), inf)
        lam = np.stack(cands, axis=-1)
        wall = np.argmin(lam, axis=-1)
        return np.take_along_axis(lam, wall[..., None], axis=-1)[..., 0], wall

    def _refine(self, o, d, lam, iters=3):
        for _ in range(iters):
            p = o + lam[..., None] * d
            g, (s, u, v) = self.constraints(p)
            wall = np.argmin(g, axis=-1)
            gv = np.take_along_axis(g, wall[..., None], axis=-1)[..., 0]
            slope = np.einsum("...i,...i->...", self._grad(p, wall, s, u, v), d)
            step = np.where(slope < -1e-6, gv / np.where(slope < -1e-6, -slope, 1.0), 0.0)
            lam = np.maximum(lam + np.clip(step, -1.0, 1.0), 1e-3)
        return lam

    def raycast(self, o: np.ndarray, d: np.ndarray) -> dict[str, np.ndarray]:
        """Cast rays from origins ``o`` (..., 3) (inside the tunnel) along unit directions ``d``.

        Returns ``lam`` (distance), ``p`` (hit point), ``wall``, ``s``, ``u``, ``v``, ``c``
        (perimeter coordinate; -1 on end walls) and ``sky`` (the ray left through the open
        entrance; its ``p`` is on the portal plane)."""
        o, d = np.broadcast_arrays(np.asarray(o, dtype=np.float64), np.asarray(d, dtype=np.float64))
        lam0, _ = self._straight_exit(o, d)
        lam = lam0
        if self.k != 0.0:
            lam = self._refine(o, d, lam0)
            # long rays: the curve bends the walls towards them; bracket the first crossing
            # by sampling, then bisect (the inside is not convex on a curve)
            flat_lam = lam.reshape(-1).copy()
            far = np.nonzero(flat_lam > 3.0)[0]
            if far.size:
                of, df, lf = o.reshape(-1, 3)[far], d.reshape(-1, 3)[far], flat_lam[far]
                span = 1.6 * np.maximum(lf, lam0.reshape(-1)[far])
                lo, hi = np.zeros_like(lf), np.full_like(lf, np.nan)
                for frac in np.linspace(0.0625, 1.0, 16):
                    t = span * frac
                    neg = (self.signed_distance(of + t[:, None] * df) < 0) & np.isnan(hi)
                    hi = np.where(neg, t, hi)
                    lo = np.where(np.isnan(hi), t, lo)
                ok = ~np.isnan(hi)
                a, b, oo, dd = lo[ok], hi[ok], of[ok], df[ok]
                for _ in range(45):
                    m = 0.5 * (a + b)
                    inside = self.signed_distance(oo + m[:, None] * dd) >= 0
                    a, b = np.where(inside, m, a), np.where(inside, b, m)
                lf[ok] = 0.5 * (a + b)
                flat_lam[far] = lf
                lam = flat_lam.reshape(lam.shape)
        p = o + lam[..., None] * d
        g, (s, u, v) = self.constraints(p)
        wall = np.argmin(g, axis=-1)
        sky = (s <= self.config.s_min + 1e-6) & self.config.entrance
        wall = np.where(sky, WALL_START, wall)
        c = np.where(wall <= WALL_RIGHT, self.surface_c(wall, u, v), -1.0)
        return {"lam": lam, "p": p, "wall": wall, "s": s, "u": u, "v": v, "c": c, "sky": sky}

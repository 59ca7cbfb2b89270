"""Timestamp association and rigid / similarity alignment of trajectories (host numpy).

Frames: every trajectory holds ``T_world_body`` poses; the estimate and the reference may
live in different world frames. An alignment ``(R, t, s)`` maps the estimate's world frame
into the reference's: ``p_ref ≈ s R p_est + t``, orientations ``R_ref ≈ R R_est``.

Association follows evo's ``associate_trajectories`` (nearest time, evo 1.38) so that the
same pairs are compared:

- the trajectory with *fewer* poses drives (the estimate when the counts are equal); each of
  its stamps is matched to the nearest stamp of the other within ``max_diff`` seconds (a tie
  goes to the earlier stamp); stamps outside the other's range ± ``max_diff`` are skipped;
- ``offset`` is added to the estimate's stamps (as evo's ``offset_2``);
- matching is one-to-one whenever the driving trajectory's stamps are more than
  ``2 * max_diff`` apart (the usual case); closer stamps may share a partner, as in evo.

Position-only ground truth (a total station's prism fixes) is a :class:`PositionTrack`:
timestamps and ``(N, 3)`` positions. Read one with :func:`read_track` from a file of
``t x y z`` rows, or take the positions of a TUM trajectory with
:meth:`PositionTrack.from_trajectory` (e.g. when its quaternions are all identity).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Literal, NamedTuple

import jax.numpy as jnp
import numpy as np

from .. import _config  # noqa: F401  (float64 in JAX)
from ..errors import InputFormatError
from ..io import Trajectory, read_trajectory
from ..io._parse import check_field_count, parse_floats, read_data_lines
from ..lie import SE3, SO3
from ..lie.host import quat_to_matrix

AlignMode = Literal["se3", "sim3", "none", "origin"]
ALIGN_MODES: tuple[str, ...] = ("se3", "sim3", "none", "origin")


@dataclasses.dataclass(frozen=True, eq=False)
class PositionTrack:
    """Position-only trajectory: ``timestamps`` ``(N,)`` s (strictly increasing) and
    ``positions`` ``(N, 3)`` m in the world frame (e.g. total-station prism fixes)."""

    timestamps: np.ndarray
    positions: np.ndarray

    def __post_init__(self) -> None:
        t = np.asarray(self.timestamps, dtype=np.float64)
        p = np.asarray(self.positions, dtype=np.float64)
        if t.ndim != 1 or p.shape != (len(t), 3):
            raise ValueError(f"PositionTrack needs timestamps (N,) and positions (N, 3), got {t.shape} and {p.shape}")
        if not (np.isfinite(t).all() and np.isfinite(p).all()):
            raise ValueError("PositionTrack timestamps and positions must be finite")
        if np.any(np.diff(t) <= 0):
            raise ValueError("PositionTrack timestamps must increase strictly")
        object.__setattr__(self, "timestamps", t)
        object.__setattr__(self, "positions", p)

    def __len__(self) -> int:
        return int(self.timestamps.shape[0])

    @classmethod
    def from_trajectory(cls, trajectory: Trajectory) -> PositionTrack:
        """The positions of ``trajectory`` (its orientations are dropped)."""
        return cls(trajectory.timestamps, np.asarray(trajectory.positions, dtype=np.float64))


Track = Trajectory | PositionTrack


class Alignment(NamedTuple):
    """``p_ref ≈ scale * rotation @ p_est + translation``; unpacks as ``(R, t, s)``."""

    rotation: np.ndarray
    translation: np.ndarray
    scale: float

    @classmethod
    def identity(cls) -> Alignment:
        return cls(np.eye(3), np.zeros(3), 1.0)

    def apply(self, points: np.ndarray) -> np.ndarray:
        """Map ``(N, 3)`` estimate-frame points into the reference frame."""
        return (self.scale * np.asarray(points)) @ self.rotation.T + self.translation

    def to_dict(self) -> dict:
        return {"rotation": self.rotation.tolist(), "translation": self.translation.tolist(), "scale": self.scale}


# --- host arrays -------------------------------------------------------------------------------


def positions_of(track: Track) -> np.ndarray:
    """``(N, 3)`` float64 positions of a trajectory or position track."""
    if isinstance(track, PositionTrack):
        return track.positions
    return np.asarray(track.positions, dtype=np.float64)


def rotations_of(track: Track, what: str = "trajectory") -> np.ndarray:
    """``(N, 3, 3)`` rotation matrices ``R_world_body`` of a trajectory (ValueError for a
    position-only track)."""
    if isinstance(track, PositionTrack):
        raise ValueError(f"{what} is position-only (PositionTrack); this needs orientations")
    return quat_to_matrix(np.asarray(track.poses.params, dtype=np.float64)[:, :4])


def _quat_mul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product ``a ⊗ b`` (wxyz), broadcasting."""
    aw, ax, ay, az = np.moveaxis(a, -1, 0)
    bw, bx, by, bz = np.moveaxis(b, -1, 0)
    return np.stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ],
        axis=-1,
    )


def _subset(track: Track, index: np.ndarray, timestamps: np.ndarray | None = None) -> Track:
    t = track.timestamps[index] if timestamps is None else timestamps
    if isinstance(track, PositionTrack):
        return PositionTrack(t, track.positions[index])
    return Trajectory(t, SE3(jnp.asarray(np.asarray(track.poses.params)[index])))


# --- association -------------------------------------------------------------------------------


def _nearest(short: np.ndarray, long: np.ndarray, max_diff: float) -> tuple[np.ndarray, np.ndarray]:
    """For each stamp of ``short`` the nearest of sorted ``long`` within ``max_diff``."""
    k = np.minimum(np.searchsorted(long, short, side="right"), len(long) - 1)
    after = long[k] - short
    before = np.where(k > 0, short - long[k - 1], np.inf)
    in_range = ~((short < long[0] - max_diff) | (short > long[-1] + max_diff))
    take_after = (after <= max_diff) & (after < before)
    take_before = ~take_after & (before <= max_diff) & (before <= after)
    keep = in_range & (take_after | take_before)
    return np.flatnonzero(keep), np.where(take_after, k, k - 1)[keep]


def match_indices(
    ref_stamps: np.ndarray, est_stamps: np.ndarray, max_diff: float = 0.01, offset: float = 0.0
) -> tuple[np.ndarray, np.ndarray]:
    """Indices ``(i_ref, i_est)`` of associated stamps (see the module docstring); ``offset``
    (s) is added to the estimate's stamps. May be empty."""
    ref_t = np.asarray(ref_stamps, dtype=np.float64)
    est_t = np.asarray(est_stamps, dtype=np.float64)
    if not max_diff >= 0:
        raise ValueError(f"max_diff must be >= 0, got {max_diff}")
    if len(est_t) > len(ref_t):
        i_ref, i_est = _nearest(ref_t, est_t + offset, max_diff)
    else:
        i_est, i_ref = _nearest(est_t, ref_t - offset, max_diff)
    return i_ref, i_est


def associate(ref: Track, est: Track, max_diff: float = 0.01, offset: float = 0.0) -> tuple[Track, Track]:
    """The associated poses of ``ref`` and ``est``: two tracks of equal length, each keeping
    its own timestamps, ordered by the driving trajectory's time (see the module docstring).

    ``max_diff`` (s): largest accepted time difference; ``offset`` (s): added to the
    estimate's stamps before matching. Raises InputFormatError naming both time ranges when
    no stamp matches.
    """
    i_ref, i_est = match_indices(ref.timestamps, est.timestamps, max_diff, offset)
    if i_ref.size == 0:
        rt, et = ref.timestamps, est.timestamps
        raise InputFormatError(
            f"no matching timestamps within max_diff = {max_diff:g} s (offset {offset:g} s): reference spans "
            f"[{rt[0]:.6f}, {rt[-1]:.6f}] s ({len(rt)} poses), estimate [{et[0]:.6f}, {et[-1]:.6f}] s "
            f"({len(et)} poses)"
        )
    return _subset(ref, i_ref), _subset(est, i_est)


def associate_by_index(ref: Track, est: Track) -> tuple[Track, Track]:
    """Pair pose k with pose k (KITTI files carry no timestamps); both get the stamps
    ``0, 1, ...``. The counts must be equal (InputFormatError otherwise, as evo requires)."""
    if len(ref) != len(est):
        raise InputFormatError(
            f"cannot associate by index: the reference has {len(ref)} poses and the estimate {len(est)} "
            "(KITTI files have no timestamps, so the counts must be equal)"
        )
    idx = np.arange(len(ref))
    stamps = idx.astype(np.float64)
    return _subset(ref, idx, stamps), _subset(est, idx, stamps)


# --- alignment ---------------------------------------------------------------------------------


def umeyama(src_xyz: np.ndarray, dst_xyz: np.ndarray, with_scale: bool = False) -> Alignment:
    """Least-squares ``(R, t, s)`` with ``dst ≈ s R src + t`` for ``(N, 3)`` point sets.

    Umeyama, "Least-squares estimation of transformation parameters between two point
    patterns", IEEE PAMI 13(4), 1991, eqs. 34–43 (with the reflection fix ``S``). ``s`` is 1
    unless ``with_scale``. Raises InputFormatError when the points are degenerate (covariance
    rank < 2: fewer than 3 poses, or all on one line), as evo does.
    """
    x = np.asarray(src_xyz, dtype=np.float64)
    y = np.asarray(dst_xyz, dtype=np.float64)
    if x.ndim != 2 or x.shape[1] != 3 or x.shape != y.shape:
        raise ValueError(f"umeyama needs two (N, 3) arrays of equal shape, got {x.shape} and {y.shape}")
    n = x.shape[0]
    mx, my = x.mean(axis=0), y.mean(axis=0)
    xc, yc = x - mx, y - my
    var_x = np.sum(xc * xc) / n
    cov = (yc.T @ xc) / n
    u, d, vt = np.linalg.svd(cov)
    # rank with numpy's (and evo's) tolerance, relative to the largest singular value: an
    # absolute eps let rounding noise (~1e-15 on a 10 m line) count as a second direction
    if np.count_nonzero(d > d[0] * max(cov.shape) * np.finfo(np.float64).eps) < 2:
        raise InputFormatError(
            f"cannot align: the {n} matched positions are degenerate (all on one line, or fewer than 3); "
            "use align 'none' or 'origin'"
        )
    s = np.ones(3)
    if np.linalg.det(u) * np.linalg.det(vt) < 0:
        s[2] = -1.0
    r = (u * s) @ vt
    c = float(np.sum(d * s) / var_x) if with_scale else 1.0
    return Alignment(r, my - c * (r @ mx), c)


def lever_points(track: Track, lever_arm: np.ndarray | None) -> np.ndarray:
    """World positions of the point at ``lever_arm`` (body frame, m) on each pose:
    ``p + R @ lever_arm`` (plain positions when ``lever_arm`` is None)."""
    p = positions_of(track)
    if lever_arm is None:
        return p
    arm = np.asarray(lever_arm, dtype=np.float64)
    if arm.shape != (3,) or not np.isfinite(arm).all():
        raise ValueError(f"lever_arm must be 3 finite numbers, got {arm!r}")
    return p + rotations_of(track, "the estimate (for a lever arm)") @ arm


def fit_alignment(
    ref: Track, est: Track, mode: str = "se3", lever_arm: np.ndarray | None = None
) -> tuple[Alignment, np.ndarray]:
    """The alignment of associated ``est`` onto ``ref`` and the estimate's (lever-arm) points
    mapped by it, ``(N, 3)``. Umeyama fits ``lever_points(est)`` to the reference positions."""
    if mode not in ALIGN_MODES:
        raise ValueError(f"align mode must be one of {ALIGN_MODES}, got {mode!r}")
    if len(ref) != len(est):
        raise ValueError(f"align needs associated tracks of equal length, got {len(ref)} and {len(est)}")
    pts = lever_points(est, lever_arm)
    if mode == "none":
        a = Alignment.identity()
    elif mode == "origin":
        r_ref0 = rotations_of(ref, "the reference (for origin alignment)")[0]
        rot = r_ref0 @ rotations_of(est, "the estimate (for origin alignment)")[0].T
        a = Alignment(rot, positions_of(ref)[0] - rot @ positions_of(est)[0], 1.0)
    else:
        a = umeyama(pts, positions_of(ref), with_scale=mode == "sim3")
    return a, a.apply(pts)


def apply_alignment(est: Track, alignment: Alignment) -> Track:
    """``est`` mapped into the reference frame: positions ``s R p + t``, orientations
    ``R R_est``."""
    p = alignment.apply(positions_of(est))
    if isinstance(est, PositionTrack):
        return PositionTrack(est.timestamps, p)
    q_a = np.asarray(SO3.from_matrix(jnp.asarray(alignment.rotation)).params, dtype=np.float64)
    q = _quat_mul(q_a, np.asarray(est.poses.params, dtype=np.float64)[:, :4])
    return Trajectory(est.timestamps, SE3(jnp.asarray(np.concatenate([q, p], axis=-1))))


def align(ref: Track, est: Track, mode: str = "se3") -> tuple[Track, Alignment]:
    """Align associated ``est`` to ``ref`` (equal lengths, pose k with pose k).

    ``mode``: ``"se3"`` (Umeyama, rotation + translation), ``"sim3"`` (and scale), ``"none"``
    (identity) or ``"origin"`` (the first estimate pose onto the first reference pose:
    ``T = T_ref[0] T_est[0]^-1``; needs orientations). Returns the aligned estimate and the
    :class:`Alignment` ``(R, t, s)``, the same as evo's ``traj.align`` / ``align_origin``.
    """
    a, _ = fit_alignment(ref, est, mode)
    return apply_alignment(est, a), a


# --- files -------------------------------------------------------------------------------------


def read_track(path: str | Path) -> tuple[Track, bool]:
    """Read a trajectory file, telling the format from the first data line's field count:
    4 (``t x y z``: a :class:`PositionTrack`), 8 (TUM) or 12 (KITTI). Returns the track and
    whether it has real timestamps (False for KITTI: stamps are the frame indices)."""
    rows = read_data_lines(path)
    n = len(rows.tokens[0])
    if n == 4:
        check_field_count(rows, "position row", 4)
        v = parse_floats(rows, "position row", ("timestamp", "x", "y", "z"))
        bad = np.flatnonzero(~(np.diff(v[:, 0]) > 0))
        if bad.size:
            k = int(bad[0]) + 1
            raise InputFormatError("timestamps must increase strictly", rows.path, int(rows.lines[k]))
        return PositionTrack(v[:, 0], v[:, 1:]), True
    if n not in (8, 12):
        raise InputFormatError(
            f"cannot tell the trajectory format: {n} fields (t x y z has 4, TUM 8, KITTI 12)",
            rows.path,
            int(rows.lines[0]),
        )
    return read_trajectory(path), n == 8

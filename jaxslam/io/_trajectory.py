"""Trajectories (timestamped SE(3) poses) in the TUM and KITTI text formats, as evo reads them.

TUM (TUM RGB-D benchmark; evo's ``tum`` format), one pose per line::

    timestamp tx ty tz qx qy qz qw

seconds, then the body's pose in the world frame (``T_world_body``) with a Hamilton unit
quaternion in xyzw order. Blank lines and ``#`` comments are skipped.

KITTI odometry poses (evo's ``kitti`` format), one pose per line: the top three rows of the
4x4 matrix ``T_world_cam`` row-major, 12 numbers::

    r11 r12 r13 tx r21 r22 r23 ty r31 r32 r33 tz

The format has no timestamps; they come from a separate file with one number per line
(KITTI's ``times.txt``), an array, or default to the frame index 0, 1, 2, ...

Decisions (each tested):

- Timestamps must increase strictly; a repeated or earlier one raises InputFormatError naming
  the line (a trajectory must be a function of time for association and interpolation).
- A quaternion whose norm is within :data:`QUATERNION_NORM_TOLERANCE` (1e-2) of 1 is normalised
  (files round to ~6 digits); one further off raises InputFormatError naming the line.
- A KITTI rotation block must be orthonormal to :data:`ROTATION_TOLERANCE` (max entry of
  ``R^T R - I``) with determinant > 0, or InputFormatError names the line; it is then
  projected onto the nearest rotation (SVD), since KITTI files keep ~7 digits.
- Writers print the shortest decimal that reads back to the same float64. TUM write -> read is
  exact; KITTI goes through a rotation matrix and back (rotations within a few 1e-15).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Literal

import jax.numpy as jnp
import numpy as np
from jax import Array

from ..errors import InputFormatError
from ..lie import SE3, SO3
from ._parse import (
    DataLines,
    check_field_count,
    format_rows,
    normalize_quaternions,
    parse_floats,
    read_data_lines,
    require_finite,
)

ROTATION_TOLERANCE = 1e-3
"""Largest entry of ``|R^T R - I|`` accepted in a KITTI rotation block before projection."""

TUM_HEADER = "# timestamp tx ty tz qx qy qz qw"
_TUM_NAMES = ("timestamp", "tx", "ty", "tz", "qx", "qy", "qz", "qw")
_KITTI_NAMES = tuple(["r11", "r12", "r13", "tx", "r21", "r22", "r23", "ty", "r31", "r32", "r33", "tz"])


@dataclasses.dataclass(frozen=True, eq=False)
class Trajectory:
    """``timestamps`` ``(N,)`` float64 seconds and ``poses``, an :class:`SE3` with batch ``(N,)``
    (``T_world_body``; params ``(qw, qx, qy, qz, x, y, z)``)."""

    timestamps: np.ndarray
    poses: SE3

    def __post_init__(self) -> None:
        t = np.asarray(self.timestamps, dtype=np.float64)
        if t.ndim != 1:
            raise ValueError(f"Trajectory timestamps must be 1-D, got shape {t.shape}")
        if not isinstance(self.poses, SE3) or tuple(self.poses.params.shape) != (len(t), 7):
            raise ValueError(f"Trajectory poses must be an SE3 of batch ({len(t)},), got {self.poses!r}")
        object.__setattr__(self, "timestamps", t)

    def __len__(self) -> int:
        return int(self.timestamps.shape[0])

    @property
    def positions(self) -> Array:
        """``(N, 3)`` positions of the body in the world frame."""
        return self.poses.translation

    @classmethod
    def from_matrices(cls, timestamps: np.ndarray, matrices: np.ndarray) -> Trajectory:
        """From ``(N, 4, 4)`` or ``(N, 3, 4)`` homogeneous matrices."""
        return cls(np.asarray(timestamps, dtype=np.float64), SE3.from_matrix(jnp.asarray(matrices, jnp.float64)))


# --- TUM ---------------------------------------------------------------------------------------


def read_tum(path: str | Path) -> Trajectory:
    """Read a TUM trajectory (``timestamp tx ty tz qx qy qz qw`` per line, ``#`` comments).

    Raises InputFormatError naming the file and line for a wrong field count, a field that is
    not a finite number, a timestamp that does not increase, or a non-unit quaternion (beyond
    the tolerance; within it the quaternion is normalised).
    """
    return _tum_from_rows(read_data_lines(path))


def _tum_from_rows(rows: DataLines) -> Trajectory:
    check_field_count(rows, "TUM row", 8)
    numbers = parse_floats(rows, "TUM row", _TUM_NAMES)
    _check_increasing(numbers[:, 0], rows)
    q = normalize_quaternions(numbers[:, [7, 4, 5, 6]], rows, "TUM row")
    params = np.concatenate([q, numbers[:, 1:4]], axis=-1)
    return Trajectory(numbers[:, 0], SE3(jnp.asarray(params)))


def write_tum(path: str | Path, trajectory: Trajectory, header: bool = True) -> None:
    """Write ``trajectory`` as TUM lines at full precision (a ``# timestamp ...`` comment line
    first unless ``header=False``)."""
    p = np.asarray(trajectory.poses.params, dtype=np.float64)
    require_finite("write_tum", np.concatenate([trajectory.timestamps[:, None], p], axis=-1))
    numbers = np.concatenate([trajectory.timestamps[:, None], p[:, 4:7], p[:, 1:4], p[:, :1]], axis=-1)
    lines = ([TUM_HEADER] if header else []) + format_rows("", np.zeros((len(p), 0)), numbers)
    Path(path).write_text("\n".join(lines) + "\n", encoding="utf-8")


# --- KITTI -------------------------------------------------------------------------------------


def read_kitti(path: str | Path, times: str | Path | np.ndarray | None = None) -> Trajectory:
    """Read KITTI odometry poses (12 numbers per line: 3x4 ``[R | t]`` row-major).

    ``times``: a file with one timestamp per line (KITTI's ``times.txt``), an array of
    timestamps, or None for the frame indices ``0, 1, ..., N-1``. Raises InputFormatError
    naming the file and line for a wrong field count, a bad number, a rotation block that is
    not a rotation (see :data:`ROTATION_TOLERANCE`), a times file whose length differs from the
    pose count, or timestamps that do not increase.
    """
    return _kitti_from_rows(read_data_lines(path), times)


def _kitti_from_rows(rows: DataLines, times: str | Path | np.ndarray | None) -> Trajectory:
    check_field_count(rows, "KITTI row", 12)
    m = parse_floats(rows, "KITTI row", _KITTI_NAMES).reshape(-1, 3, 4)
    rot = _nearest_rotations(m[:, :, :3], rows)
    q = SO3.from_matrix(jnp.asarray(rot)).params
    poses = SE3(jnp.concatenate([q, jnp.asarray(m[:, :, 3])], axis=-1))
    return Trajectory(_kitti_times(times, len(rows), rows.path), poses)


def _nearest_rotations(r: np.ndarray, rows: DataLines) -> np.ndarray:
    with np.errstate(all="ignore"):
        err = np.abs(np.swapaxes(r, 1, 2) @ r - np.eye(3)).max(axis=(1, 2))
        det = np.linalg.det(r)
    bad = np.flatnonzero(~((err <= ROTATION_TOLERANCE) & (det > 0)))
    if bad.size:
        k = int(bad[0])
        raise InputFormatError(
            f"KITTI row's 3x3 block is not a rotation (max |R^T R - I| = {err[k]:.3g}, det = {det[k]:.3g}; "
            f"expected orthonormal within {ROTATION_TOLERANCE:g} and det > 0)",
            rows.path,
            int(rows.lines[k]),
        )
    u, _, vt = np.linalg.svd(r)
    return u @ vt


def _kitti_times(times: str | Path | np.ndarray | None, n: int, poses_path: str) -> np.ndarray:
    if times is None:
        return np.arange(n, dtype=np.float64)
    if isinstance(times, (str, Path)):
        rows = read_data_lines(times)
        check_field_count(rows, "times row", 1)
        t = parse_floats(rows, "times row", ("timestamp",))[:, 0]
        if len(t) != n:
            raise InputFormatError(f"has {len(t)} timestamps but {poses_path} has {n} poses", rows.path)
        _check_increasing(t, rows)
        return t
    t = np.asarray(times, dtype=np.float64)
    if t.shape != (n,):
        raise ValueError(f"times must have shape ({n},) to match the poses, got {t.shape}")
    _check_increasing(t, None)
    return t


def write_kitti(path: str | Path, trajectory: Trajectory, times_path: str | Path | None = None) -> None:
    """Write KITTI pose lines at full precision; the timestamps go to ``times_path`` (one per
    line) if given, since the format itself has none."""
    rot = np.asarray(trajectory.poses.rotation.as_matrix(), dtype=np.float64)
    t = np.asarray(trajectory.poses.translation, dtype=np.float64)
    numbers = np.concatenate([rot, t[:, :, None]], axis=-1).reshape(-1, 12)
    require_finite("write_kitti", np.concatenate([numbers, trajectory.timestamps[:, None]], axis=-1))
    no_ids = np.zeros((len(numbers), 0))
    Path(path).write_text("\n".join(format_rows("", no_ids, numbers)) + "\n", encoding="utf-8")
    if times_path is not None:
        stamps = format_rows("", no_ids, trajectory.timestamps[:, None])
        Path(times_path).write_text("\n".join(stamps) + "\n", encoding="utf-8")


# --- shared ------------------------------------------------------------------------------------


def read_trajectory(
    path: str | Path, fmt: Literal["tum", "kitti"] | None = None, times: str | Path | np.ndarray | None = None
) -> Trajectory:
    """Read a TUM or KITTI trajectory; with ``fmt=None`` the format is told from the first data
    line (8 fields: TUM, 12: KITTI). ``times`` is used for KITTI only."""
    rows = read_data_lines(path)
    if fmt is None:
        n = len(rows.tokens[0])
        if n not in (8, 12):
            raise InputFormatError(
                f"cannot tell the trajectory format: {n} fields (TUM has 8, KITTI 12)", rows.path, int(rows.lines[0])
            )
        fmt = "tum" if n == 8 else "kitti"
    if fmt == "tum":
        return _tum_from_rows(rows)
    if fmt == "kitti":
        return _kitti_from_rows(rows, times)
    raise ValueError(f"fmt must be 'tum', 'kitti' or None, got {fmt!r}")


def _check_increasing(t: np.ndarray, rows: DataLines | None) -> None:
    bad = np.flatnonzero(~(np.diff(t) > 0))
    if not bad.size:
        return
    k = int(bad[0]) + 1
    now, before = float(t[k]), float(t[k - 1])
    if rows is None:
        raise ValueError(f"timestamps must increase strictly: times[{k}] = {now!r} after {before!r}")
    raise InputFormatError(
        f"timestamp {now!r} is not after {before!r} on line {int(rows.lines[k - 1])}; timestamps must "
        "increase strictly",
        rows.path,
        int(rows.lines[k]),
    )

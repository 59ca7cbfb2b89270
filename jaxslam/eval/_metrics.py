"""Trajectory error metrics on host arrays: APE, RPE, loop-closure error, path length.

Definitions (the same numbers as evo 1.38's ``evo_ape`` / ``evo_rpe``, tested against it):

- **APE** (translation part): associate, align (``se3`` default), then per pose
  ``e_k = ‖p_est,k − p_ref,k‖`` in the reference frame (metres).
- **RPE**: for pose pairs ``(i, j)`` of the associated trajectories,
  ``E = (Q_i^-1 Q_j)^-1 (P_i^-1 P_j)`` with ``Q`` reference and ``P`` estimate poses
  (``T_world_body``). ``"trans"``: ``‖t(E)‖`` m; ``"rot_deg"`` / ``"rot_rad"``: the rotation
  angle of ``E``; ``"full"``: ``‖E − I₄‖_F``.
  Pairs come from the estimate (after alignment) as evo's default: ``unit="frames"``: indices
  ``0, δ, 2δ, ...`` consecutive; ``unit="m"``: walk along the estimate adding step lengths and
  close a pair whenever the travelled distance reaches ``delta`` metres (then restart at 0).
- **Point-distance RPE** (position-only ground truth, evo's ``point_distance``):
  ``|‖p_ref,j − p_ref,i‖ − ‖p_est,j − p_est,i‖|`` — compares travelled chord lengths, free of
  any frame. ``"point_vector"`` (not in evo) is ``‖(p_ref,j − p_ref,i) − (p_est,j − p_est,i)‖``
  in the reference frame after alignment, which also sees heading drift.
- **Statistics**: rmse, mean, median, std (population), min, max, sse of the error array.

Lever arm (total-station ground truth): the estimate is compared at the prism,
``p + R_world_body @ lever_arm`` (``lever_arm`` in the body frame, m); Umeyama then fits
those points to the surveyed positions. With ``sim3`` the lever arm is scaled with the
estimate (the alignment is applied to the prism points it was fitted to).
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import numpy as np

from ..errors import ConfigError, InputFormatError
from ._align import (
    Alignment,
    Track,
    associate,
    fit_alignment,
    positions_of,
    rotations_of,
)

POSE_RELATIONS: tuple[str, ...] = ("trans", "rot_deg", "rot_rad", "full", "point_distance", "point_vector")
DELTA_UNITS: tuple[str, ...] = ("frames", "m")


def error_stats(errors: np.ndarray) -> dict[str, float]:
    """rmse, mean, median, std (ddof 0), min, max and sse (sum of squares) of ``errors``."""
    e = np.asarray(errors, dtype=np.float64)
    if e.size == 0:
        raise ValueError("no errors to summarise")
    sq = e * e
    return {
        "rmse": math.sqrt(float(np.mean(sq))),
        "mean": float(np.mean(e)),
        "median": float(np.median(e)),
        "std": float(np.std(e)),
        "min": float(np.min(e)),
        "max": float(np.max(e)),
        "sse": float(np.sum(sq)),
    }


def accumulated_distances(points: np.ndarray) -> np.ndarray:
    """``(N,)`` distance travelled from the first point along the polyline ``(N, 3)``."""
    p = np.asarray(points, dtype=np.float64)
    return np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(p, axis=0), axis=1))])


def path_length(traj: Track) -> float:
    """Length (m) of the polyline through the positions of ``traj``."""
    return float(accumulated_distances(positions_of(traj))[-1])


@dataclasses.dataclass(frozen=True, eq=False)
class ApeResult:
    """Absolute (translation) pose error of associated, aligned poses.

    ``errors`` ``(M,)`` m; ``timestamps`` ``(M,)`` the estimate's matched stamps;
    ``distances`` ``(M,)`` m travelled along the matched reference; ``stats`` see
    :func:`error_stats`; ``alignment`` the fitted ``(R, t, s)``.
    """

    errors: np.ndarray
    timestamps: np.ndarray
    distances: np.ndarray
    stats: dict[str, float]
    alignment: Alignment
    align: str
    matched: int
    ref_poses: int
    est_poses: int
    lever_arm: tuple[float, float, float] | None = None

    def to_dict(self, arrays: bool = False) -> dict[str, Any]:
        """JSON-ready summary (per-pose arrays too when ``arrays``)."""
        d: dict[str, Any] = {
            "stats": dict(self.stats),
            "unit": "m",
            "align": self.align,
            "alignment": self.alignment.to_dict(),
            "matched": self.matched,
            "ref_poses": self.ref_poses,
            "est_poses": self.est_poses,
            "lever_arm": None if self.lever_arm is None else list(self.lever_arm),
        }
        if arrays:
            d |= {k: getattr(self, k).tolist() for k in ("errors", "timestamps", "distances")}
        return d


@dataclasses.dataclass(frozen=True, eq=False)
class RpeResult:
    """Relative pose error over pose pairs ``pairs`` ``(K, 2)`` (indices into the associated
    trajectories); ``errors`` ``(K,)`` in ``unit_label`` (m, deg, rad or none)."""

    errors: np.ndarray
    pairs: np.ndarray
    timestamps: np.ndarray
    stats: dict[str, float]
    delta: float
    delta_unit: str
    pose_relation: str
    unit_label: str
    align: str
    matched: int

    def to_dict(self, arrays: bool = False) -> dict[str, Any]:
        """JSON-ready summary (per-pair arrays too when ``arrays``)."""
        d: dict[str, Any] = {
            "stats": dict(self.stats),
            "unit": self.unit_label,
            "delta": self.delta,
            "delta_unit": self.delta_unit,
            "pose_relation": self.pose_relation,
            "align": self.align,
            "pairs": len(self.errors),
            "matched": self.matched,
        }
        if arrays:
            d |= {"errors": self.errors.tolist(), "pair_ids": self.pairs.tolist()}
        return d


def _lever_tuple(lever_arm: Any) -> tuple[float, float, float] | None:
    if lever_arm is None:
        return None
    a = np.asarray(lever_arm, dtype=np.float64).reshape(-1)
    if a.shape != (3,):
        raise ValueError(f"lever_arm must have 3 components, got {a.shape}")
    return float(a[0]), float(a[1]), float(a[2])


def ape(
    ref: Track,
    est: Track,
    align: str = "se3",
    lever_arm: Any = None,
    *,
    max_diff: float = 0.01,
    offset: float = 0.0,
    associated: bool = False,
) -> ApeResult:
    """Translation APE of ``est`` against ``ref`` (see the module docstring).

    ``ref``: a :class:`~jaxslam.io.Trajectory` or, for position-only ground truth, a
    :class:`PositionTrack`. ``align``: ``"se3" | "sim3" | "none" | "origin"``.
    ``lever_arm`` ``(3,)`` body-frame offset of the point the reference measured (prism).
    ``max_diff`` / ``offset``: timestamp association (s); ``associated=True`` skips it
    (pose k pairs with pose k). Equals ``evo_ape tum REF EST [-a | -as]`` (translation part).
    """
    arm = _lever_tuple(lever_arm)
    r, e = (ref, est) if associated else associate(ref, est, max_diff, offset)
    alignment, pts = fit_alignment(r, e, align, None if arm is None else np.asarray(arm))
    ref_p = positions_of(r)
    errors = np.linalg.norm(pts - ref_p, axis=1)
    return ApeResult(
        errors=errors,
        timestamps=e.timestamps.copy(),
        distances=accumulated_distances(ref_p),
        stats=error_stats(errors),
        alignment=alignment,
        align=align,
        matched=len(r),
        ref_poses=len(ref),
        est_poses=len(est),
        lever_arm=arm,
    )


def pairs_by_frames(n: int, delta: int) -> np.ndarray:
    """Consecutive index pairs ``(0, δ), (δ, 2δ), ...`` among ``n`` poses, ``(K, 2)``."""
    ids = np.arange(0, n, delta)
    return np.stack([ids[:-1], ids[1:]], axis=-1)


def pairs_by_path(points: np.ndarray, delta: float) -> np.ndarray:
    """Consecutive index pairs whose travelled distance first reaches ``delta`` m, ``(K, 2)``:
    steps are summed from the last pair's end, and the sum restarts at 0 after each pair."""
    steps = np.linalg.norm(np.diff(np.asarray(points, dtype=np.float64), axis=0), axis=1).tolist()
    ids = [0]
    travelled = 0.0
    for k, step in enumerate(steps, start=1):
        travelled += step
        if travelled >= delta:
            ids.append(k)
            travelled = 0.0
    a = np.asarray(ids, dtype=np.int64)
    return np.stack([a[:-1], a[1:]], axis=-1)


def _rotation_angle(r: np.ndarray) -> np.ndarray:
    """Angles (rad, [0, π]) of rotation matrices ``(K, 3, 3)``: ``atan2(|ω|, (tr − 1) / 2)``
    with ``2 sin θ ω̂ = vee(R − Rᵀ)``; accurate near 0 and π alike."""
    v = np.stack([r[:, 2, 1] - r[:, 1, 2], r[:, 0, 2] - r[:, 2, 0], r[:, 1, 0] - r[:, 0, 1]], axis=-1)
    return np.arctan2(0.5 * np.linalg.norm(v, axis=-1), 0.5 * (np.trace(r, axis1=1, axis2=2) - 1.0))


def _relative_errors(
    ref: Track, est_rot: np.ndarray, est_p: np.ndarray, pairs: np.ndarray, relation: str
) -> np.ndarray:
    i, j = pairs[:, 0], pairs[:, 1]
    ref_p = positions_of(ref)
    if relation in ("point_distance", "point_vector"):
        d_ref, d_est = ref_p[j] - ref_p[i], est_p[j] - est_p[i]
        if relation == "point_vector":
            return np.linalg.norm(d_ref - d_est, axis=1)
        return np.abs(np.linalg.norm(d_ref, axis=1) - np.linalg.norm(d_est, axis=1))
    ref_rot = rotations_of(ref, f"the reference (RPE {relation!r}; use 'point_distance')")
    # Q_rel = Q_i^-1 Q_j, P_rel = P_i^-1 P_j; E = Q_rel^-1 P_rel
    q_r = np.swapaxes(ref_rot[i], 1, 2) @ ref_rot[j]
    q_t = np.einsum("kba,kb->ka", ref_rot[i], ref_p[j] - ref_p[i])
    p_r = np.swapaxes(est_rot[i], 1, 2) @ est_rot[j]
    p_t = np.einsum("kba,kb->ka", est_rot[i], est_p[j] - est_p[i])
    e_r = np.swapaxes(q_r, 1, 2) @ p_r
    e_t = np.einsum("kba,kb->ka", q_r, p_t - q_t)
    if relation == "trans":
        return np.linalg.norm(e_t, axis=1)
    if relation == "rot_rad":
        return _rotation_angle(e_r)
    if relation == "rot_deg":
        return np.rad2deg(_rotation_angle(e_r))
    # full: ‖E − I‖_F of the 4x4 matrix
    return np.sqrt(np.sum((e_r - np.eye(3)) ** 2, axis=(1, 2)) + np.sum(e_t * e_t, axis=1))


_UNIT_LABELS = {"trans": "m", "rot_deg": "deg", "rot_rad": "rad", "full": "none", "point_distance": "m"}


def rpe(
    ref: Track,
    est: Track,
    delta: float = 1,
    unit: str = "frames",
    pose_relation: str = "trans",
    *,
    align: str = "none",
    lever_arm: Any = None,
    max_diff: float = 0.01,
    offset: float = 0.0,
    associated: bool = False,
) -> RpeResult:
    """Relative pose error (see the module docstring for the definitions).

    ``delta``: an integer number of frames (``unit="frames"``) or metres travelled along the
    estimate (``unit="m"``). ``pose_relation``: ``"trans" | "rot_deg" | "rot_rad" | "full"``
    (need reference orientations) or ``"point_distance" | "point_vector"`` (positions only;
    use these with a :class:`PositionTrack` reference). ``align`` as in :func:`ape` (it
    changes RPE only through ``sim3``'s scale and the ``point_vector`` frame). ``lever_arm``
    (body frame, m) moves the estimate's points to the prism; only with the point relations.
    Equals ``evo_rpe tum REF EST -r trans_part|angle_deg|full|point_distance -d δ -u f|m``.
    Raises ConfigError when ``delta`` yields no pair.
    """
    if pose_relation not in POSE_RELATIONS:
        raise ValueError(f"pose_relation must be one of {POSE_RELATIONS}, got {pose_relation!r}")
    if unit not in DELTA_UNITS:
        raise ValueError(f"unit must be one of {DELTA_UNITS}, got {unit!r}")
    point_relation = pose_relation.startswith("point_")
    if lever_arm is not None and not point_relation:
        raise ValueError("lever_arm needs pose_relation 'point_distance' or 'point_vector'")
    if unit == "frames" and not (float(delta).is_integer() and delta >= 1):
        raise ConfigError(f"RPE delta must be a whole number of frames >= 1, got {delta}")
    if unit == "m" and not delta > 0:
        raise ConfigError(f"RPE delta must be a positive distance in metres, got {delta}")
    arm = _lever_tuple(lever_arm)
    r, e = (ref, est) if associated else associate(ref, est, max_diff, offset)
    alignment, pts = fit_alignment(r, e, align, None if arm is None else np.asarray(arm))
    est_rot = None if point_relation else alignment.rotation @ rotations_of(e, "the estimate")
    pairs = pairs_by_frames(len(e), int(delta)) if unit == "frames" else pairs_by_path(pts, float(delta))
    if len(pairs) == 0:
        raise ConfigError(
            f"RPE delta = {delta:g} {unit} yields no pose pair among {len(e)} matched poses "
            f"({accumulated_distances(pts)[-1]:.3f} m travelled); use a smaller delta"
        )
    errors = _relative_errors(r, est_rot, pts, pairs, pose_relation)  # type: ignore[arg-type]
    return RpeResult(
        errors=errors,
        pairs=pairs,
        timestamps=e.timestamps[pairs[:, 1]],
        stats=error_stats(errors),
        delta=float(delta) if unit == "m" else int(delta),
        delta_unit=unit,
        pose_relation=pose_relation,
        unit_label=_UNIT_LABELS.get(pose_relation, "m"),
        align=align,
        matched=len(r),
    )


def _displacement(track: Track, lever_arm: Any) -> np.ndarray:
    p = positions_of(track)
    if lever_arm is None:
        return p[-1] - p[0]
    r = rotations_of(track, "the estimate (for a lever arm)")
    arm = np.asarray(lever_arm, dtype=np.float64)
    return (p[-1] + r[-1] @ arm) - (p[0] + r[0] @ arm)


def loop_error(
    est: Track,
    gt: Track | None = None,
    *,
    lever_arm: Any = None,
    max_diff: float = 0.01,
    offset: float = 0.0,
    associated: bool = False,
) -> float:
    """Loop-closure error (m) of a path meant to return to its start.

    Without ``gt``: ``‖p_end − p_start‖`` of ``est``. With ``gt`` (the true path need not
    close exactly): both are associated first, and the error is
    ``‖(p_end − p_start)_est − (p_end − p_start)_gt‖`` over the first and last matched poses,
    which needs ``est`` in ``gt``'s frame (pass the aligned estimate: :func:`align`).
    ``lever_arm`` (body frame, m) compares the estimate at the prism of a position-only
    ``gt``. ``associated=True``: ``est`` and ``gt`` are already paired pose by pose.
    """
    if gt is None:
        return float(np.linalg.norm(_displacement(est, lever_arm)))
    g, e = (gt, est) if associated else associate(gt, est, max_diff, offset)
    return float(np.linalg.norm(_displacement(e, lever_arm) - _displacement(g, None)))


def loop_error_ratio(
    est: Track,
    gt: Track | None = None,
    *,
    lever_arm: Any = None,
    max_diff: float = 0.01,
    offset: float = 0.0,
    associated: bool = False,
) -> float:
    """:func:`loop_error` divided by the path length: of the matched ``gt`` when given, else
    of ``est`` (a fraction; multiply by 100 for percent)."""
    err = loop_error(est, gt, lever_arm=lever_arm, max_diff=max_diff, offset=offset, associated=associated)
    if gt is None:
        length = path_length(est)
    else:
        length = path_length(gt if associated else associate(gt, est, max_diff, offset)[0])
    if not length > 0:
        raise InputFormatError("loop error ratio: the path has zero length")
    return err / length

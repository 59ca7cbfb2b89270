"""Bridge to GTSAM (optional dependency ``gtsam==4.3.0``): the same graph on both sides.

``to_gtsam(factors, values)`` builds a ``gtsam.NonlinearFactorGraph`` and ``gtsam.Values`` from
jaxslam factors (prior and between on Pose3/Pose2/Rot3/Point3, with their noise models and
robust kernels), so one graph can be solved by both libraries and either optimum can be
evaluated by GTSAM's ``graph.error``. ``values_to_gtsam`` / ``values_from_gtsam`` convert
estimates. Keys are the jaxslam ids, offset per variable type (``KEY_BASE``), so ids of
different types never collide; a graph with a single type uses the ids unchanged.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from ..core import Cauchy, Factor, GemanMcClure, Huber, Point3Var, Pose2Var, Pose3Var, Rot3Var, Tukey, Values
from ..errors import JaxSlamError

KEY_BASE = {Pose3Var: 0, Pose2Var: 0, Rot3Var: 10**12, Point3Var: 2 * 10**12}


def _gtsam() -> Any:
    try:
        import gtsam
    except ImportError as exc:  # pragma: no cover
        raise JaxSlamError("the GTSAM bridge needs the gtsam wheel: pip install 'jaxslam[bench]'") from exc
    return gtsam


def _to_object(gtsam: Any, vtype: type, p: np.ndarray) -> Any:
    if vtype is Pose3Var:
        return gtsam.Pose3(gtsam.Rot3.Quaternion(*p[:4]), p[4:7])
    if vtype is Pose2Var:
        return gtsam.Pose2(p[2], p[3], float(np.arctan2(p[1], p[0])))
    if vtype is Rot3Var:
        return gtsam.Rot3.Quaternion(*p[:4])
    if vtype is Point3Var:
        return np.asarray(p, dtype=float)
    raise JaxSlamError(f"no GTSAM type for {vtype.__name__}")


def _from_object(vtype: type, obj: Any) -> np.ndarray:
    if vtype is Pose3Var:
        q = obj.rotation().toQuaternion()
        return np.array([q.w(), q.x(), q.y(), q.z(), *obj.translation()])
    if vtype is Pose2Var:
        return np.array([np.cos(obj.theta()), np.sin(obj.theta()), obj.x(), obj.y()])
    if vtype is Rot3Var:
        q = obj.toQuaternion()
        return np.array([q.w(), q.x(), q.y(), q.z()])
    return np.asarray(obj, dtype=float)


def _at(gtsam_values: Any, vtype: type, key: int) -> Any:
    if vtype is Pose3Var:
        return gtsam_values.atPose3(key)
    if vtype is Pose2Var:
        return gtsam_values.atPose2(key)
    if vtype is Rot3Var:
        return gtsam_values.atRot3(key)
    return gtsam_values.atPoint3(key)


def values_to_gtsam(values: Values) -> Any:
    gtsam = _gtsam()
    out = gtsam.Values()
    for t in values.types():
        params = np.asarray(values.params(t))
        for i, p in zip(values.ids(t), params):
            out.insert(int(i) + KEY_BASE[t], _to_object(gtsam, t, p))
    return out


def values_from_gtsam(gtsam_values: Any, like: Values) -> Values:
    """Read back the variables of ``like`` (same types and ids) from GTSAM values."""
    entries = {}
    for t in like.types():
        ids = like.ids(t)
        entries[t(ids)] = np.stack([_from_object(t, _at(gtsam_values, t, int(i) + KEY_BASE[t])) for i in ids])
    return Values.create(entries)


# jaxslam Pose2 tangent is [theta, x, y]; GTSAM Pose2's is [x, y, theta].
_POSE2_PERM = np.array([1, 2, 0])


def _noise(gtsam: Any, factor: Factor, k: int, vtype: type) -> Any:
    r = np.asarray(factor.noise.sqrt_info[k])
    if vtype is Pose2Var:
        r = r[np.ix_(_POSE2_PERM, _POSE2_PERM)]
    model = gtsam.noiseModel.Gaussian.SqrtInformation(r)
    if factor.robust is not None:
        kk_all = np.asarray(factor.robust.k)  # shared (scalar) or per constraint (N,)
        kk = float(kk_all if kk_all.ndim == 0 else kk_all[k])
        est = {
            Huber: gtsam.noiseModel.mEstimator.Huber,
            Cauchy: gtsam.noiseModel.mEstimator.Cauchy,
            GemanMcClure: gtsam.noiseModel.mEstimator.GemanMcClure,
            Tukey: gtsam.noiseModel.mEstimator.Tukey,
        }[type(factor.robust)].Create(kk)
        model = gtsam.noiseModel.Robust.Create(est, model)
    return model


def to_gtsam(factors: Sequence[Factor], values: Values) -> tuple[Any, Any]:
    """``(gtsam.NonlinearFactorGraph, gtsam.Values)`` equivalent to jaxslam's graph."""
    from ..factors import BetweenFactor, PriorFactor

    gtsam = _gtsam()
    names = {Pose3Var: "Pose3", Pose2Var: "Pose2", Rot3Var: "Rot3", Point3Var: "Point3"}
    graph = gtsam.NonlinearFactorGraph()
    for f in factors:
        vtype = type(f.variables[0])
        if vtype not in names or not isinstance(f, (BetweenFactor, PriorFactor)):
            raise JaxSlamError(f"to_gtsam supports prior/between factors on {list(names)}, not {type(f).__name__}")
        cls_name = ("BetweenFactor" if isinstance(f, BetweenFactor) else "PriorFactor") + names[vtype]
        ctor = getattr(gtsam, cls_name)
        measured = np.asarray(f.measured)
        ids = [np.asarray(v.ids) for v in f.variables]
        for k in range(f.num_constraints):
            keys = [int(i[k]) + KEY_BASE[vtype] for i in ids]
            graph.add(ctor(*keys, _to_object(gtsam, vtype, measured[k]), _noise(gtsam, f, k, vtype)))
    return graph, values_to_gtsam(values)

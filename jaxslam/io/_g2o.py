"""Pose graphs in g2o format and in GTSAM's older text formats (TORO-style ``.graph``).

Lines are ``TAG field field ...``; blank lines and ``#`` comments are skipped. Tags read:

====================  ==================================================  ====================
tag                   fields after the tag                                information order
====================  ==================================================  ====================
``VERTEX_SE2``        ``id x y theta``
``VERTEX2``           same as VERTEX_SE2 (GTSAM / TORO)
``VERTEX_SE3:QUAT``   ``id x y z qx qy qz qw``
``VERTEX3``           ``id x y z roll pitch yaw`` (R = Rz(yaw) Ry(pitch) Rx(roll))
``EDGE_SE2``          ``i j dx dy dtheta I11 I12 I13 I22 I23 I33``        [x, y, theta]
``EDGE2``             same fields; the 6 numbers in g2o or TORO order       see ``noise_format``
``EDGE_SE3:QUAT``     ``i j x y z qx qy qz qw`` + 21 upper-triangular       [translation, rotation]
``EDGE3``             ``i j x y z roll pitch yaw`` + 21 upper-triangular    taken as [rotation,
                                                                           translation] (GTSAM)
``FIX``               ``id [id ...]``: vertices held fixed (a tight prior)
====================  ==================================================  ====================

Information matrices are converted to jaxslam's tangent order ([theta, x, y] in 2-D,
[rotation, translation] in 3-D) exactly as GTSAM 4.3's ``readG2o`` / ``load2D`` / ``load3D``
interpret them (checked against the gtsam wheel in the tests):

- ``EDGE_SE2``: upper triangle in [x, y, theta] order, permuted to [theta, x, y].
- ``EDGE2``: ``noise_format="g2o"`` reads ``I11 I12 I13 I22 I23 I33``; ``"toro"`` reads TORO's
  ``I11 I12 I22 I33 I13 I23``; ``"auto"`` (default) uses g2o order unless that gives a matrix
  that is not positive definite while TORO order gives one (``w10000.graph`` writes the
  identity as ``1 0 1 1 0 0``). GTSAM's ``load2D`` guesses from the same zero patterns but
  then reads the numbers as a *covariance*; for the unit matrices of its example files that
  is the same thing.
- ``EDGE_SE3:QUAT``: [translation, rotation] permuted symmetrically to [rotation, translation].
  (g2o's rotation error is the quaternion's vector part, about half the angle; GTSAM ignores
  that factor of 4 in the information and so does jaxslam.)
- ``EDGE3``: GTSAM uses the 6x6 matrix as given, i.e. as [rotation, translation]; jaxslam does
  the same so both solve the same problem. Note that the g2o version of sphere2500 puts the
  entries that are 10 in ``sphere2500.txt`` on the translation instead.

Quaternions are normalised (norm within 1e-2 of 1, else an error). Files with edges but no
vertex lines (``manhattan.g2o``, ``sphere2500.txt``) are initialised by chaining odometry (see
:func:`chain_odometry`); GTSAM returns no initial values for them.

Deliberate differences from GTSAM's readers, which skip unknown tags silently and stop reading
edges at a ``FIX`` or ``#`` line: unknown tags raise :class:`InputFormatError` naming them
(pass ``ignore=`` to skip them); ``EQUIV`` (TORO vertex equivalences, ignored by GTSAM too)
and ``PARAMS_SE2OFFSET`` / ``PARAMS_SE3OFFSET`` (sensor offsets of landmark edges) are skipped
and counted in ``PoseGraph.skipped``; ``FIX`` becomes a prior.

:func:`write_g2o` writes every float at full precision (shortest round-trip decimal), so a
write followed by a read gives the same numbers (GTSAM's ``writeG2o`` keeps 6 digits). With
``format="g2o"`` (default) it writes ``VERTEX_SE2``/``EDGE_SE2`` or ``VERTEX_SE3:QUAT``/
``EDGE_SE3:QUAT``; with ``format="gtsam"`` GTSAM's text format, ``VERTEX2``/``EDGE2`` (the
information in g2o's order ``I11 I12 I13 I22 I23 I33`` over [x, y, theta], which the reader's
``"auto"`` and GTSAM's ``readG2o`` and ``load2D(noiseFormat=NoiseFormatG2O)`` read; GTSAM's
``load2D`` default guesses a *covariance* from the zero pattern) or ``VERTEX3``/``EDGE3``
(roll, pitch, yaw from :func:`rpy_from_quaternion`; the 21 information numbers as
[rotation, translation], which GTSAM's ``load3D`` and ``readG2o`` both read); ``format="auto"``
picks GTSAM's for a ``.txt`` or ``.graph`` path and g2o for any other.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Literal

import jax.numpy as jnp
import numpy as np

from ..core import Factor, Pose2Var, Pose3Var, Values, Variable, information_is_valid
from ..errors import GraphError, InputFormatError
from ..factors import BetweenFactor, PriorFactor
from ._parse import (
    DataLines,
    check_field_count,
    format_rows,
    normalize_quaternions,
    parse_floats,
    parse_ids,
    read_data_lines,
    require_finite,
)
from ._posegraph import FIX_SIGMA, PoseGraph, chain_odometry

NoiseFormat = Literal["auto", "g2o", "toro"]
WriteFormat = Literal["g2o", "gtsam", "auto"]

GTSAM_SUFFIXES = frozenset({".txt", ".graph"})
"""Suffixes that ``write_g2o(..., format="auto")`` writes in GTSAM's text format."""

IGNORED_TAGS = frozenset({"EQUIV", "PARAMS_SE2OFFSET", "PARAMS_SE3OFFSET"})
"""Tags skipped without error (counted in ``PoseGraph.skipped``)."""

_G2O_TO_JAX = {2: np.array([2, 0, 1]), 3: np.array([3, 4, 5, 0, 1, 2])}
"""Index into the file's tangent order for each jaxslam tangent coordinate."""
_JAX_TO_G2O = {d: np.argsort(p) for d, p in _G2O_TO_JAX.items()}


def _upper_names(n: int) -> tuple[str, ...]:
    return tuple(f"I{r + 1}{c + 1}" for r in range(n) for c in range(r, n))


@dataclasses.dataclass(frozen=True)
class _Tag:
    name: str
    dim: int
    pose: tuple[str, ...]
    info_dim: int = 0  # 0 for vertices

    @property
    def is_edge(self) -> bool:
        return self.info_dim > 0

    @property
    def names(self) -> tuple[str, ...]:
        ids = ("i", "j") if self.is_edge else ("id",)
        return ids + self.pose + (_upper_names(self.info_dim) if self.is_edge else ())


_SE2 = ("x", "y", "theta")
_QUAT = ("x", "y", "z", "qx", "qy", "qz", "qw")
_RPY = ("x", "y", "z", "roll", "pitch", "yaw")
TAGS: dict[str, _Tag] = {
    t.name: t
    for t in (
        _Tag("VERTEX_SE2", 2, _SE2),
        _Tag("VERTEX2", 2, _SE2),
        _Tag("VERTEX_SE3:QUAT", 3, _QUAT),
        _Tag("VERTEX3", 3, _RPY),
        _Tag("EDGE_SE2", 2, ("dx", "dy", "dtheta"), 3),
        _Tag("EDGE2", 2, ("dx", "dy", "dtheta"), 3),
        _Tag("EDGE_SE3:QUAT", 3, _QUAT, 6),
        _Tag("EDGE3", 3, _RPY, 6),
    )
}


@dataclasses.dataclass
class _Parsed:
    """Vertex, edge and FIX rows of one file, each with its line numbers."""

    v_ids: list[np.ndarray] = dataclasses.field(default_factory=list)
    v_params: list[np.ndarray] = dataclasses.field(default_factory=list)
    v_lines: list[np.ndarray] = dataclasses.field(default_factory=list)
    e_ids: list[np.ndarray] = dataclasses.field(default_factory=list)
    e_params: list[np.ndarray] = dataclasses.field(default_factory=list)
    e_info: list[np.ndarray] = dataclasses.field(default_factory=list)
    e_lines: list[np.ndarray] = dataclasses.field(default_factory=list)
    fix_ids: list[int] = dataclasses.field(default_factory=list)
    fix_lines: list[int] = dataclasses.field(default_factory=list)


# --- reading ---------------------------------------------------------------------------------


def read_g2o(
    path: str | Path,
    *,
    noise_format: NoiseFormat = "auto",
    ignore: Iterable[str] = (),
    fix_sigma: float = FIX_SIGMA,
) -> PoseGraph:
    """Read a 2-D or 3-D pose graph (g2o, or GTSAM's ``.graph`` / ``EDGE3`` text formats).

    Args:
        path: the file.
        noise_format: how to read the 6 noise numbers of ``EDGE2`` lines (see module doc).
        ignore: more tags to skip (e.g. landmark tags such as ``"VERTEX_XY"``).
        fix_sigma: standard deviation of the prior that holds each ``FIX`` vertex.

    Returns a :class:`PoseGraph`. Raises :class:`InputFormatError` (file, line and what was
    expected) for unreadable files, unknown tags, wrong field counts, bad numbers and
    information matrices that are not positive definite; :class:`GraphError` (also naming
    the line) for repeated vertex ids, self-loops, edges to undefined vertices, and vertices
    that odometry chaining cannot reach.
    """
    if noise_format not in ("auto", "g2o", "toro"):
        raise ValueError(f"noise_format must be 'auto', 'g2o' or 'toro', got {noise_format!r}")
    rows = read_data_lines(path)
    groups, skipped = _group_by_tag(rows, IGNORED_TAGS | frozenset(ignore))
    dim = _check_one_dimension(rows, groups)
    parsed = _Parsed()
    for tag, index in groups.items():
        _parse_group(parsed, tag, rows.select(index), noise_format)
    return _build_graph(parsed, dim, rows.path, fix_sigma, skipped)


def _group_by_tag(rows: DataLines, ignored: frozenset[str]) -> tuple[dict[str, list[int]], dict[str, int]]:
    groups: dict[str, list[int]] = {}
    skipped: dict[str, int] = {}
    for k, tokens in enumerate(rows.tokens):
        tag = tokens[0]
        if tag in TAGS or tag == "FIX":
            groups.setdefault(tag, []).append(k)
        elif tag in ignored:
            skipped[tag] = skipped.get(tag, 0) + 1
        else:
            known = ", ".join([*TAGS, "FIX"])
            raise InputFormatError(
                f"unknown tag {tag[:40]!r}; expected one of {known} (pass ignore=[{tag[:40]!r}] to skip such lines)",
                rows.path,
                int(rows.lines[k]),
            )
    return groups, skipped


def _check_one_dimension(rows: DataLines, groups: dict[str, list[int]]) -> int:
    """The graph's dimension; a 2-D tag and a 3-D tag in one file raise InputFormatError."""
    firsts = sorted((index[0], tag) for tag, index in groups.items() if tag in TAGS)
    if not firsts:
        raise InputFormatError("no VERTEX or EDGE lines", rows.path)
    first_k, first_tag = firsts[0]
    dim = TAGS[first_tag].dim
    for tag, index in groups.items():
        if tag in TAGS and TAGS[tag].dim != dim:
            raise InputFormatError(
                f"{tag} is a {TAGS[tag].dim}-D tag but line {int(rows.lines[first_k])} has the "
                f"{dim}-D tag {first_tag}; a file holds one kind of pose",
                rows.path,
                int(rows.lines[index[0]]),
            )
    return dim


def _parse_group(out: _Parsed, tag: str, rows: DataLines, noise_format: NoiseFormat) -> None:
    if tag == "FIX":
        _parse_fix(out, rows)
        return
    spec = TAGS[tag]
    check_field_count(rows, tag, len(spec.names), skip=1)
    n_ids = 2 if spec.is_edge else 1
    ids = parse_ids(rows, tag, spec.names[:n_ids], start=1)
    numbers = parse_floats(rows, tag, spec.names[n_ids:], start=1 + n_ids)
    params = _pose_params(spec, numbers[:, : len(spec.pose)], rows)
    if spec.is_edge:
        out.e_ids.append(ids)
        out.e_params.append(params)
        out.e_info.append(_information(spec, numbers[:, len(spec.pose) :], rows, noise_format))
        out.e_lines.append(rows.lines)
    else:
        out.v_ids.append(ids[:, 0])
        out.v_params.append(params)
        out.v_lines.append(rows.lines)


def _parse_fix(out: _Parsed, rows: DataLines) -> None:
    for k, tokens in enumerate(rows.tokens):
        if len(tokens) < 2:
            raise InputFormatError("FIX needs at least 1 field (a vertex id), found 0", rows.path, int(rows.lines[k]))
        one = DataLines(rows.path, [tokens], rows.lines[k : k + 1])
        ids = parse_ids(one, "FIX", [f"id{n + 1}" for n in range(len(tokens) - 1)], start=1)[0]
        out.fix_ids.extend(ids.tolist())
        out.fix_lines.extend([int(rows.lines[k])] * len(ids))


# --- numbers to jaxslam layouts ----------------------------------------------------------------


def _pose_params(spec: _Tag, pose: np.ndarray, rows: DataLines) -> np.ndarray:
    if spec.dim == 2:
        theta = pose[:, 2]
        return np.stack([np.cos(theta), np.sin(theta), pose[:, 0], pose[:, 1]], axis=-1)
    if spec.pose == _QUAT:
        q = normalize_quaternions(pose[:, [6, 3, 4, 5]], rows, spec.name)
    else:
        q = quaternion_from_rpy(pose[:, 3], pose[:, 4], pose[:, 5])
    return np.concatenate([q, pose[:, :3]], axis=-1)


def quaternion_from_rpy(roll: np.ndarray, pitch: np.ndarray, yaw: np.ndarray) -> np.ndarray:
    """``(N, 4)`` wxyz quaternions of ``Rz(yaw) Ry(pitch) Rx(roll)`` (GTSAM's ``Rot3::Ypr``)."""
    cr, sr = np.cos(roll / 2), np.sin(roll / 2)
    cp, sp = np.cos(pitch / 2), np.sin(pitch / 2)
    cy, sy = np.cos(yaw / 2), np.sin(yaw / 2)
    return np.stack(
        [
            cy * cp * cr + sy * sp * sr,
            cy * cp * sr - sy * sp * cr,
            cy * sp * cr + sy * cp * sr,
            sy * cp * cr - cy * sp * sr,
        ],
        axis=-1,
    )


def rpy_from_quaternion(q: np.ndarray) -> np.ndarray:
    """``(N, 3)`` roll, pitch, yaw of ``(N, 4)`` wxyz unit quaternions: the inverse of
    :func:`quaternion_from_rpy` (``R = Rz(yaw) Ry(pitch) Rx(roll)``).

    Pitch is in ``[-pi/2, pi/2]``, roll and yaw in ``[-pi, pi]``. Uses the half-angle identities
    ``w + y = k+ cos((yaw - roll)/2)``, ``z - x = k+ sin((yaw - roll)/2)``, ``w - y = k- cos((yaw +
    roll)/2)``, ``z + x = k- sin((yaw + roll)/2)`` with ``k+ = sqrt(1 + sin pitch)`` and ``k- =
    sqrt(1 - sin pitch)``: every angle comes from an ``atan2``, so it is accurate to rounding
    everywhere. At gimbal lock (pitch = +-pi/2) one of ``k+-`` is zero and only ``yaw - roll``
    or ``yaw + roll`` is defined; the ``atan2(0, 0) = 0`` used for the other gives a valid split
    and never NaN. Either sign of ``q`` gives the same rotation back.
    """
    q = np.asarray(q, dtype=np.float64)
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    half_diff = np.arctan2(z - x, w + y)  # (yaw - roll) / 2
    half_sum = np.arctan2(z + x, w - y)  # (yaw + roll) / 2
    pitch = 2.0 * np.arctan2(np.hypot(w + y, z - x), np.hypot(w - y, z + x)) - np.pi / 2
    return np.stack([_wrap(half_sum - half_diff), pitch, _wrap(half_sum + half_diff)], axis=-1)


def _wrap(angle: np.ndarray) -> np.ndarray:
    """Angles in ``(-2pi, 2pi]`` moved into ``[-pi, pi]`` by adding or subtracting ``2pi``."""
    return np.where(angle > np.pi, angle - 2 * np.pi, np.where(angle < -np.pi, angle + 2 * np.pi, angle))


def _symmetric(upper: np.ndarray, n: int, order: Sequence[int] | None = None) -> np.ndarray:
    """``(N, n, n)`` symmetric matrices from ``(N, n(n+1)/2)`` entries. By default the entries
    are the upper triangle row by row; ``order`` lists, for each such position, which column
    of ``upper`` holds it (TORO's 2-D order)."""
    if order is not None:
        upper = upper[:, order]
    r, c = np.triu_indices(n)
    m = np.zeros((upper.shape[0], n, n))
    m[:, r, c] = upper
    m[:, c, r] = upper
    return m


_TORO_ORDER = [0, 1, 4, 2, 5, 3]
"""TORO writes I11 I12 I22 I33 I13 I23; g2o position (I11 I12 I13 I22 I23 I33) -> TORO column."""


def _information(spec: _Tag, upper: np.ndarray, rows: DataLines, noise_format: NoiseFormat) -> np.ndarray:
    n = 2 * spec.dim if spec.dim == 3 else 3
    info = _symmetric(upper, n)
    if spec.name == "EDGE2" and noise_format != "g2o":
        toro = _symmetric(upper, n, _TORO_ORDER)
        use_toro = np.ones(len(info), bool) if noise_format == "toro" else _prefer_toro(info, toro)
        info = np.where(use_toro[:, None, None], toro, info)
    if spec.name != "EDGE3":  # GTSAM takes EDGE3's matrix as [rotation, translation] already
        p = _G2O_TO_JAX[spec.dim]
        info = info[:, p][:, :, p]
    _check_information(info, rows, spec.name)
    return info


def _prefer_toro(g2o: np.ndarray, toro: np.ndarray) -> np.ndarray:
    with np.errstate(all="ignore"):
        return ~information_is_valid(g2o) & information_is_valid(toro)


def _check_information(info: np.ndarray, rows: DataLines, tag: str) -> None:
    """Every matrix must be finite, symmetric, positive definite and have a finite Cholesky
    factor; the first that is not raises InputFormatError naming its line."""
    with np.errstate(all="ignore"):
        ok = information_is_valid(info)
        ok[ok] = _cholesky_ok(info[ok])
    if not ok.all():
        k = int(np.flatnonzero(~ok)[0])
        raise InputFormatError(
            f"{tag} information matrix is not symmetric positive definite "
            f"(fields {_upper_names(info.shape[-1])[0]}..{_upper_names(info.shape[-1])[-1]})",
            rows.path,
            int(rows.lines[k]),
        )


def _cholesky_ok(info: np.ndarray) -> np.ndarray:
    try:
        return np.all(np.isfinite(np.linalg.cholesky(info)), axis=(1, 2))
    except np.linalg.LinAlgError:  # some matrix failed: find which, one by one
        if len(info) == 1:
            return np.array([False])
        return np.concatenate([_cholesky_ok(m[None]) for m in info])


# --- graph assembly ----------------------------------------------------------------------------


def _where(path: str, line: int) -> str:
    return f"{path}:{line}"


def _build_graph(p: _Parsed, dim: int, path: str, fix_sigma: float, skipped: dict[str, int]) -> PoseGraph:
    pdim = 4 if dim == 2 else 7
    tdim = 3 if dim == 2 else 6
    e_lines = np.concatenate(p.e_lines) if p.e_lines else np.zeros(0, np.int64)
    order = np.argsort(e_lines, kind="stable")
    e_lines = e_lines[order]
    e_ids = np.concatenate(p.e_ids)[order] if p.e_ids else np.zeros((0, 2), np.int64)
    measured = np.concatenate(p.e_params)[order] if p.e_params else np.zeros((0, pdim))
    info = np.concatenate(p.e_info)[order] if p.e_info else np.zeros((0, tdim, tdim))
    _check_self_loops(e_ids, e_lines, path)
    if p.v_ids:
        ids, params = _vertices(p, path)
        _check_defined(ids, e_ids.ravel(), np.repeat(e_lines, 2), path, "an edge")
        source = "vertices"
    else:
        ids, params = chain_odometry(dim, e_ids[:, 0], e_ids[:, 1], measured, source=path)
        source = "odometry"
    fixed = np.unique(np.asarray(p.fix_ids, dtype=np.int64))
    _check_defined(ids, np.asarray(p.fix_ids, np.int64), np.asarray(p.fix_lines, np.int64), path, "FIX")
    vtype = Pose2Var if dim == 2 else Pose3Var
    values = Values({vtype: ids}, {vtype: jnp.asarray(params)})  # ids sorted and unique
    return PoseGraph.from_arrays(
        dim,
        values,
        e_ids[:, 0],
        e_ids[:, 1],
        measured,
        info,
        fixed,
        fix_sigma,
        initialised_from=source,
        skipped=skipped,
        path=path,
    )


def _vertices(p: _Parsed, path: str) -> tuple[np.ndarray, np.ndarray]:
    ids = np.concatenate(p.v_ids)
    lines = np.concatenate(p.v_lines)
    order = np.lexsort((lines, ids))
    ids, lines = ids[order], lines[order]
    dup = np.flatnonzero(ids[1:] == ids[:-1])
    if dup.size:
        k = int(dup[np.argmin(lines[dup + 1])])
        raise GraphError(
            f"{_where(path, int(lines[k + 1]))}: vertex {int(ids[k])} is defined again (first on line {int(lines[k])})"
        )
    return ids, np.concatenate(p.v_params)[order]


def _check_self_loops(e_ids: np.ndarray, lines: np.ndarray, path: str) -> None:
    loops = np.flatnonzero(e_ids[:, 0] == e_ids[:, 1])
    if loops.size:
        k = int(loops[0])
        raise GraphError(f"{_where(path, int(lines[k]))}: edge connects vertex {int(e_ids[k, 0])} to itself")


def _check_defined(ids: np.ndarray, used: np.ndarray, lines: np.ndarray, path: str, what: str) -> None:
    rows = np.minimum(np.searchsorted(ids, used), len(ids) - 1)
    missing = np.flatnonzero(ids[rows] != used)
    if missing.size:
        k = int(missing[np.argmin(lines[missing])])
        raise GraphError(f"{_where(path, int(lines[k]))}: {what} refers to vertex {int(used[k])}, which is not defined")


# --- writing -----------------------------------------------------------------------------------


def write_g2o(
    path: str | Path,
    graph: PoseGraph | Values,
    factors: Sequence[Factor] | None = None,
    *,
    format: WriteFormat = "g2o",
) -> None:
    """Write a pose graph in g2o format, or GTSAM's text format, at full float64 precision.

    Either ``write_g2o(path, graph)`` with a :class:`PoseGraph` (``graph.with_values(opt)``
    writes an optimised estimate with the original edges), or ``write_g2o(path, values,
    factors)`` with Values of one pose type and a list of :class:`BetweenFactor` (their noise
    written as information ``R^T R``) and :class:`PriorFactor` (written as ``FIX`` lines: the
    prior's measurement and noise are not kept). Robust kernels are not written.

    Args:
        path: the file to write.
        graph: a PoseGraph, or Values (then pass ``factors``).
        factors: the factors to write with ``Values``.
        format: ``"g2o"`` (``VERTEX_SE2``/``EDGE_SE2``, ``VERTEX_SE3:QUAT``/``EDGE_SE3:QUAT``),
            ``"gtsam"`` (``VERTEX2``/``EDGE2``, ``VERTEX3``/``EDGE3`` with roll, pitch, yaw; see
            the module doc for the information order), or ``"auto"``: ``"gtsam"`` when
            ``path`` ends in ``.txt`` or ``.graph`` (any case), else ``"g2o"``.

    Raises ValueError for an unknown format or for NaN / infinite poses or information.
    """
    if format not in ("g2o", "gtsam", "auto"):
        raise ValueError(f"format must be 'g2o', 'gtsam' or 'auto', got {format!r}")
    gtsam = format == "gtsam" or (format == "auto" and Path(path).suffix.lower() in GTSAM_SUFFIXES)
    g = _as_pose_graph(graph, factors)
    require_finite("write_g2o vertices", np.asarray(g.values.params(g.var_type)))
    require_finite("write_g2o measured", g.measured)
    require_finite("write_g2o information", g.information)
    lines = _vertex_lines(g, gtsam) + _edge_lines(g, gtsam) + [f"FIX {k}" for k in g.fixed.tolist()]
    Path(path).write_text("\n".join(lines) + "\n", encoding="utf-8")


def _as_pose_graph(graph: PoseGraph | Values, factors: Sequence[Factor] | None) -> PoseGraph:
    if isinstance(graph, PoseGraph):
        if factors is not None:
            raise TypeError("write_g2o: pass factors only with a Values, not with a PoseGraph")
        return graph
    if not isinstance(graph, Values) or factors is None:
        raise TypeError("write_g2o expects a PoseGraph, or a Values and a list of factors")
    types = [t for t in graph.types() if t in (Pose2Var, Pose3Var)]
    if len(types) != 1 or len(graph.types()) != 1:
        raise ValueError(f"g2o holds one pose type; these values hold {[t.__name__ for t in graph.types()]}")
    return _graph_from_factors(graph, types[0], factors)


def _graph_from_factors(values: Values, vtype: type[Variable], factors: Sequence[Factor]) -> PoseGraph:
    dim = 2 if vtype is Pose2Var else 3
    ii, jj, meas, info, fixed = [], [], [], [], []
    for f in factors:
        if any(type(v) is not vtype for v in f.variables):
            raise ValueError(f"write_g2o: a {type(f).__name__} on {f.variable_types()} in a graph of {vtype.__name__}")
        if isinstance(f, BetweenFactor):
            ii.append(np.asarray(f.variables[0].ids))
            jj.append(np.asarray(f.variables[1].ids))
            meas.append(np.asarray(f.measured))
            r = np.asarray(f.noise.sqrt_info)
            info.append(np.swapaxes(r, -1, -2) @ r)
        elif isinstance(f, PriorFactor):
            fixed.append(np.asarray(f.variables[0].ids))
        else:
            raise TypeError(f"write_g2o writes BetweenFactor and PriorFactor only, got {type(f).__name__}")
    edges_i, edges_j = _cat(ii, (0,)).astype(np.int64), _cat(jj, (0,)).astype(np.int64)
    fixed_ids = np.unique(_cat(fixed, (0,)).astype(np.int64))
    for ids in (edges_i, edges_j, fixed_ids):
        values.rows(vtype(ids))  # GraphError for ids without a value
    t = vtype.tangent_dim
    info_all = _cat(info, (0, t, t))
    measured = _cat(meas, (0, vtype.param_dim))
    return PoseGraph(dim, values, list(factors), edges_i, edges_j, measured, info_all, fixed_ids)


def _cat(arrays: list[np.ndarray], empty_shape: tuple[int, ...]) -> np.ndarray:
    return np.concatenate(arrays) if arrays else np.zeros(empty_shape)


def _file_pose(dim: int, params: np.ndarray, gtsam: bool = False) -> np.ndarray:
    """jaxslam params to g2o's ``x y theta`` or ``x y z qx qy qz qw``, or (``gtsam``) to
    ``x y z roll pitch yaw`` in 3-D."""
    if dim == 2:
        return np.stack([params[:, 2], params[:, 3], _angles(params[:, 0], params[:, 1])], axis=-1)
    if gtsam:
        return np.concatenate([params[:, 4:7], rpy_from_quaternion(params[:, :4])], axis=-1)
    return params[:, [4, 5, 6, 1, 2, 3, 0]]


def _angles(c: np.ndarray, s: np.ndarray, ulps: int = 4) -> np.ndarray:
    """``atan2(s, c)``, moved by up to ``ulps`` units in the last place to an angle whose
    ``cos`` and ``sin`` give back ``c`` and ``s`` exactly where there is one (always so for
    poses read from a file), so that write -> read reproduces SE2 params bit for bit."""
    theta = np.arctan2(s, c)
    found = (np.cos(theta) == c) & (np.sin(theta) == s)
    up, down = theta, theta
    for _ in range(ulps):
        up, down = np.nextafter(up, np.inf), np.nextafter(down, -np.inf)
        for cand in (up, down):
            hit = ~found & (np.cos(cand) == c) & (np.sin(cand) == s)
            theta = np.where(hit, cand, theta)
            found |= hit
    return theta


_WRITE_TAGS = {
    (2, False): ("VERTEX_SE2", "EDGE_SE2"),
    (3, False): ("VERTEX_SE3:QUAT", "EDGE_SE3:QUAT"),
    (2, True): ("VERTEX2", "EDGE2"),
    (3, True): ("VERTEX3", "EDGE3"),
}


def _vertex_lines(g: PoseGraph, gtsam: bool) -> list[str]:
    tag = _WRITE_TAGS[g.dim, gtsam][0]
    params = np.asarray(g.values.params(g.var_type), dtype=np.float64)
    return format_rows(tag, g.vertex_ids[:, None], _file_pose(g.dim, params, gtsam))


def _edge_lines(g: PoseGraph, gtsam: bool) -> list[str]:
    tag = _WRITE_TAGS[g.dim, gtsam][1]
    info = g.information
    if not (gtsam and g.dim == 3):  # EDGE3 holds jaxslam's [rotation, translation] order as is
        q = _JAX_TO_G2O[g.dim]
        info = info[:, q][:, :, q]
    r, c = np.triu_indices(info.shape[-1])
    numbers = np.concatenate([_file_pose(g.dim, g.measured, gtsam), info[:, r, c]], axis=-1)
    return format_rows(tag, np.stack([g.edges_i, g.edges_j], axis=-1), numbers)

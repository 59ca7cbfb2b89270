"""g2o / GTSAM text pose-graph I/O: GTSAM is the oracle for every real file; round trips are
exact; every kind of bad input raises a JaxSlamError that names the file and line."""

from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from jaxslam.core import Pose2Var, Pose3Var, Values
from jaxslam.errors import GraphError, InputFormatError, JaxSlamError
from jaxslam.factors import BetweenFactor, PriorFactor
from jaxslam.io import PoseGraph, chain_odometry, read_g2o, write_g2o

DATA = Path(__file__).resolve().parents[2] / ".." / "shared" / "data" / "posegraph"
G2O_FILES = ["sphere2500", "parking-garage", "smallGrid3D", "tinyGrid3D", "intel", "city10000", "manhattan"]
GTSAM_TO_JAX = {2: np.array([2, 0, 1]), 3: np.arange(6)}  # GTSAM tangent index per jaxslam index


def data_file(name: str) -> Path:
    path = DATA / f"{name}.g2o"
    if not path.exists():
        pytest.skip(f"{path} is not available")
    return path


def write(tmp_path: Path, text: str, name: str = "g.g2o") -> Path:
    path = tmp_path / name
    path.write_text(text)
    return path


# --- helpers: our layout vs GTSAM's objects ----------------------------------------------------


def pose_matrix(dim: int, p: np.ndarray) -> np.ndarray:
    if dim == 2:
        c, s, x, y = p
        return np.array([[c, -s, x], [s, c, y], [0, 0, 1.0]])
    w, a, b, c, x, y, z = p
    r = np.array(
        [
            [1 - 2 * (b * b + c * c), 2 * (a * b - c * w), 2 * (a * c + b * w)],
            [2 * (a * b + c * w), 1 - 2 * (a * a + c * c), 2 * (b * c - a * w)],
            [2 * (a * c - b * w), 2 * (b * c + a * w), 1 - 2 * (a * a + b * b)],
        ]
    )
    m = np.eye(4)
    m[:3, :3], m[:3, 3] = r, (x, y, z)
    return m


def factor_information(graph: PoseGraph) -> np.ndarray:
    """``R^T R`` of the vectorised BetweenFactor's noise model."""
    between = graph.factors[0]
    assert isinstance(between, BetweenFactor)
    r = np.asarray(between.noise.sqrt_info)
    return np.swapaxes(r, -1, -2) @ r


def assert_matches_gtsam(graph: PoseGraph, factors, gvalues=None) -> None:
    """Keys, measured poses (1e-12), information (1e-9 relative), and vertex values (1e-12)."""
    assert factors.size() == graph.num_edges
    p = GTSAM_TO_JAX[graph.dim]
    between = graph.factors[0]
    assert isinstance(between, BetweenFactor)
    np.testing.assert_array_equal(np.asarray(between.variables[0].ids), graph.edges_i)
    np.testing.assert_array_equal(np.asarray(between.variables[1].ids), graph.edges_j)
    gf = [factors.at(k) for k in range(factors.size())]
    keys = np.array([f.keys() for f in gf], dtype=np.int64).reshape(-1, 2)
    np.testing.assert_array_equal(keys, np.stack([graph.edges_i, graph.edges_j], axis=-1))
    measured = np.stack([pose_matrix(graph.dim, m) for m in np.asarray(between.measured)])
    np.testing.assert_allclose(measured, np.stack([f.measured().matrix() for f in gf]), 0, 1e-12)
    rg = np.stack([f.noiseModel().R() for f in gf])
    gtsam_info = (np.swapaxes(rg, 1, 2) @ rg)[:, p][:, :, p]
    scale = np.abs(gtsam_info).max(axis=(1, 2), keepdims=True)
    for info in (factor_information(graph), graph.information):
        np.testing.assert_allclose(info / scale, gtsam_info / scale, 0, 1e-9)
    if gvalues is not None and gvalues.size():
        assert_values_close(graph, gvalues, 1e-12)


def assert_values_close(graph: PoseGraph, gvalues, atol: float) -> None:
    vt = graph.var_type
    ids = graph.values.ids(vt)
    assert gvalues.size() == len(ids)
    ours = np.stack([pose_matrix(graph.dim, p) for p in np.asarray(graph.values.params(vt))])
    at = gvalues.atPose2 if graph.dim == 2 else gvalues.atPose3
    np.testing.assert_allclose(ours, np.stack([at(i).matrix() for i in ids.tolist()]), 0, atol)


# --- GTSAM oracle on every real file -----------------------------------------------------------


@pytest.mark.gtsam
@pytest.mark.parametrize("name", G2O_FILES)
def test_g2o_files_match_gtsam_readg2o(name: str, gtsam) -> None:
    path = data_file(name)
    graph = read_g2o(path)
    factors, values = gtsam.readG2o(str(path), graph.dim == 3)
    assert_matches_gtsam(graph, factors, values)
    assert graph.initialised_from == ("odometry" if name == "manhattan" else "vertices")
    if name == "manhattan":  # GTSAM also chains odometry for a 2-D file without vertices
        assert_values_close(graph, values, 1e-9)


@pytest.mark.gtsam
def test_sphere2500_txt_matches_gtsam_load3d(gtsam) -> None:
    path = gtsam.findExampleDataFile("sphere2500.txt")
    graph = read_g2o(path)
    for factors, _ in (gtsam.load3D(path), gtsam.readG2o(path, True)):
        assert_matches_gtsam(graph, factors)
    assert graph.dim == 3 and graph.initialised_from == "odometry" and len(graph.values) == 2500
    # GTSAM returns no values here: compare the chain with GTSAM's own composition.
    factors, _ = gtsam.load3D(path)
    pose = gtsam.Pose3()
    chained = {0: pose}
    for k in range(factors.size()):
        f = factors.at(k)
        i, j = f.keys()
        if j == i + 1 and j not in chained:
            chained[j] = chained[i].compose(f.measured())
    expect = gtsam.Values()
    for key, value in chained.items():
        expect.insert(key, value)
    assert_values_close(graph, expect, 1e-9)


@pytest.mark.gtsam
def test_w10000_graph_matches_gtsam_load2d(gtsam) -> None:
    path = gtsam.findExampleDataFile("w10000.graph")
    graph = read_g2o(path)
    factors, values = gtsam.load2D(path)
    assert_matches_gtsam(graph, factors, values)
    assert graph.skipped == {"EQUIV": 5875}  # TORO vertex equivalences, ignored like GTSAM does


@pytest.mark.gtsam
def test_full_information_matrices_match_gtsam(tmp_path: Path, gtsam) -> None:
    """Off-diagonal entries, where an ordering mistake would show (the files above are block
    diagonal): EDGE_SE3:QUAT, EDGE3, EDGE_SE2, and EDGE2 in TORO order."""
    upper6 = " ".join(str(1000.0 + r if r == c else 10 * (r + 1) + c + 1) for r in range(6) for c in range(r, 6))
    v3 = "VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1\nVERTEX_SE3:QUAT 1 1 0 0 0 0 0 1\n"
    quat = write(tmp_path, v3 + f"EDGE_SE3:QUAT 0 1 1 2 3 0.1 0.2 0.3 0.9273618495495704 {upper6}\n", "q.g2o")
    assert_matches_gtsam(read_g2o(quat), gtsam.readG2o(str(quat), True)[0])
    edge3 = write(tmp_path, f"EDGE3 0 1 1 2 3 0.1 0.2 0.3 {upper6}\n", "e3.txt")
    assert_matches_gtsam(read_g2o(edge3), gtsam.load3D(str(edge3))[0])
    v2 = "VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 1 0 0\n"
    se2 = write(tmp_path, v2 + "EDGE_SE2 0 1 1 2 0.3 100 11 12 200 23 300\n", "s.g2o")
    assert_matches_gtsam(read_g2o(se2), gtsam.readG2o(str(se2), False)[0])
    toro = write(tmp_path, v2 + "EDGE2 0 1 1 2 0.3 100 11 200 300 12 23\n", "t.graph")
    expect = gtsam.load2D(str(toro), noiseFormat=gtsam.NoiseFormat.NoiseFormatTORO)[0]
    assert_matches_gtsam(read_g2o(toro, noise_format="toro"), expect)
    offdiag = gtsam.findExampleDataFile("pose3example-offdiagonal.txt")
    assert_matches_gtsam(read_g2o(offdiag), gtsam.readG2o(offdiag, True)[0])


def test_information_orders_are_explicit(tmp_path: Path) -> None:
    """The conventions without GTSAM: g2o [x, y, theta] -> [theta, x, y]; [t, r] -> [r, t]."""
    v2 = "VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 1 0 0\n"
    g = read_g2o(write(tmp_path, v2 + "EDGE_SE2 0 1 1 2 0.3 10 2 3 20 5 30\n"))
    expect = np.array([[30.0, 3, 5], [3, 10, 2], [5, 2, 20]])  # theta first
    np.testing.assert_array_equal(g.information[0], expect)
    diag6 = " ".join("1" if r == c else "0" for r in range(6) for c in range(r, 6)).split()
    diag6[0] = "7"  # I11: translation x in g2o order
    v3 = "VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1\nVERTEX_SE3:QUAT 1 1 0 0 0 0 0 1\n"
    g = read_g2o(write(tmp_path, v3 + f"EDGE_SE3:QUAT 0 1 1 0 0 0 0 0 1 {' '.join(diag6)}\n"))
    np.testing.assert_array_equal(np.diag(g.information[0]), [1, 1, 1, 7, 1, 1])


# --- layout and structure ----------------------------------------------------------------------


def test_pose_graph_layout() -> None:
    graph = read_g2o(data_file("parking-garage"))
    assert graph.dim == 3 and graph.var_type is Pose3Var
    assert graph.edges_i.dtype == np.int64 and graph.measured.shape == (6275, 7)
    assert graph.information.shape == (6275, 6, 6)
    assert len(graph.factors) == 1 and len(graph.factors[0]) == 6275
    np.testing.assert_array_equal(graph.vertex_ids, np.arange(1661))
    np.testing.assert_allclose(np.linalg.norm(graph.measured[:, :4], axis=1), 1.0, 0, 1e-15)
    r = graph.sqrt_information()
    np.testing.assert_allclose(np.swapaxes(r, 1, 2) @ r, graph.information, 1e-12)


def test_vertex_ids_as_given(tmp_path: Path) -> None:
    text = "VERTEX_SE2 7 0 0 0\nVERTEX_SE2 3 1 2 0.5\nEDGE_SE2 7 3 1 0 0 1 0 0 1 0 1\n"
    graph = read_g2o(write(tmp_path, text))
    np.testing.assert_array_equal(graph.vertex_ids, [3, 7])
    np.testing.assert_allclose(np.asarray(graph.values.params(Pose2Var))[0], [np.cos(0.5), np.sin(0.5), 1, 2])


def test_vertex3_and_edge3_use_roll_pitch_yaw(tmp_path: Path) -> None:
    text = "VERTEX3 0 1 2 3 0 0 0.5\nVERTEX3 1 0 0 0 0.5 0 0\n"
    graph = read_g2o(write(tmp_path, text, "v.graph"))
    p = np.asarray(graph.values.params(Pose3Var))
    np.testing.assert_allclose(p[0], [np.cos(0.25), 0, 0, np.sin(0.25), 1, 2, 3], 0, 1e-15)
    np.testing.assert_allclose(p[1], [np.cos(0.25), np.sin(0.25), 0, 0, 0, 0, 0], 0, 1e-15)
    assert graph.factors == []


def test_fix_becomes_prior_and_is_written(tmp_path: Path) -> None:
    text = "VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 1 0 0.5\nVERTEX_SE2 2 2 0 0.5\nFIX 0 2\nEDGE_SE2 0 1 1 0 0.5 1 0 0 1 0 1\n"
    graph = read_g2o(write(tmp_path, text), fix_sigma=1e-4)
    np.testing.assert_array_equal(graph.fixed, [0, 2])
    prior = graph.factors[1]
    assert isinstance(prior, PriorFactor)
    np.testing.assert_array_equal(prior.variables[0].ids, [0, 2])
    np.testing.assert_allclose(np.asarray(prior.noise.sqrt_info)[0], 1e4 * np.eye(3))
    np.testing.assert_allclose(prior.measured, np.asarray(graph.values.params(Pose2Var))[[0, 2]])
    out = tmp_path / "out.g2o"
    write_g2o(out, graph)
    assert "FIX 0\nFIX 2\n" in out.read_text()
    np.testing.assert_array_equal(read_g2o(out).fixed, [0, 2])


def test_ignored_and_extra_ignored_tags(tmp_path: Path) -> None:
    text = "VERTEX_SE2 0 0 0 0\nEQUIV 0 1\nPARAMS_SE2OFFSET 0 0 0 0\nVERTEX_XY 5 1 2\nVERTEX_SE2 1 1 0 0\n"
    with pytest.raises(InputFormatError, match=r"g\.g2o:4: unknown tag 'VERTEX_XY'"):
        read_g2o(write(tmp_path, text))
    graph = read_g2o(write(tmp_path, text), ignore=["VERTEX_XY"])
    assert graph.skipped == {"EQUIV": 1, "PARAMS_SE2OFFSET": 1, "VERTEX_XY": 1}


def test_comments_and_blank_lines_are_skipped(tmp_path: Path) -> None:
    text = "# header\n\nVERTEX_SE2 0 0 0 0  # origin\n   \nVERTEX_SE2 1 1 0 0\n# mid\nEDGE_SE2 0 1 1 0 0 1 0 0 1 0 1\n"
    assert read_g2o(write(tmp_path, text)).num_edges == 1  # GTSAM would stop reading edges at '# mid'


def test_utf8_byte_order_mark_is_dropped(tmp_path: Path) -> None:
    path = tmp_path / "bom.g2o"
    path.write_bytes(b"\xef\xbb\xbf" + V2.encode())
    assert len(read_g2o(path).values) == 2


def test_edge2_noise_format_auto(tmp_path: Path) -> None:
    """EDGE2 numbers that only make sense in TORO order are read in TORO order."""
    v = "VERTEX2 0 0 0 0\nVERTEX2 1 1 0 0\n"
    text = v + "EDGE2 0 1 1 0 0 2 0 3 5 0 0\nEDGE2 1 0 1 0 0 2 0 0 3 0 5\n"
    graph = read_g2o(write(tmp_path, text, "x.graph"))
    np.testing.assert_array_equal(graph.information, np.broadcast_to(np.diag([5.0, 2, 3]), (2, 3, 3)))
    with pytest.raises(InputFormatError, match=r"x\.graph:3: EDGE2 information"):
        read_g2o(write(tmp_path, text, "x.graph"), noise_format="g2o")
    with pytest.raises(ValueError, match="noise_format"):
        read_g2o(write(tmp_path, text, "x.graph"), noise_format="cov")  # type: ignore[arg-type]


# --- odometry chaining -------------------------------------------------------------------------


def test_chain_uses_forward_then_inverted_backward_edges() -> None:
    z = np.array([np.cos(0.5), np.sin(0.5), 1.0, 0.0])
    ids, params = chain_odometry(2, np.array([4, 6, 5]), np.array([5, 5, 4]), np.stack([z, z, 2 * z]))
    np.testing.assert_array_equal(ids, [4, 5, 6])
    np.testing.assert_array_equal(params[0], [1, 0, 0, 0])  # the first vertex at the identity
    np.testing.assert_allclose(params[1], z, 0, 1e-15)  # 4 -> 5: the forward edge, not 5 -> 4
    np.testing.assert_allclose(params[2], [1, 0, 0, 0], 0, 1e-15)  # 6 = 5 * (6 -> 5)^-1 = z z^-1


def test_chain_unreachable_vertex_is_named(tmp_path: Path) -> None:
    text = "EDGE_SE2 0 1 1 0 0 1 0 0 1 0 1\nEDGE_SE2 1 2 1 0 0 1 0 0 1 0 1\nEDGE_SE2 2 5 1 0 0 1 0 0 1 0 1\n"
    with pytest.raises(GraphError, match="cannot initialise vertex 5 by chaining odometry"):
        read_g2o(write(tmp_path, text))


# --- writing -----------------------------------------------------------------------------------


@pytest.mark.parametrize("name", ["sphere2500", "intel", "manhattan"])
def test_write_read_round_trip_is_exact(tmp_path: Path, name: str) -> None:
    """Numbers that came from a file come back bit for bit (quaternions are stored as written;
    SE2 angles are written so that cos/sin read back exactly). Chained values (manhattan) are
    not cos/sin of any float angle: they come back within rounding, then stay fixed."""
    graph = read_g2o(data_file(name))
    write_g2o(tmp_path / "a.g2o", graph)
    back = read_g2o(tmp_path / "a.g2o")
    vt = graph.var_type
    for field in ("edges_i", "edges_j", "measured", "information", "vertex_ids", "fixed"):
        np.testing.assert_array_equal(getattr(back, field), getattr(graph, field))
    if graph.initialised_from == "vertices":
        np.testing.assert_array_equal(back.values.params(vt), graph.values.params(vt))
    else:
        np.testing.assert_allclose(back.values.params(vt), graph.values.params(vt), 1e-15, 1e-15)
    write_g2o(tmp_path / "b.g2o", back)
    again = read_g2o(tmp_path / "b.g2o")
    np.testing.assert_array_equal(again.values.params(vt), back.values.params(vt))
    np.testing.assert_array_equal(again.measured, back.measured)


def test_write_optimised_values_with_original_edges(tmp_path: Path, rng: np.random.Generator) -> None:
    graph = read_g2o(data_file("tinyGrid3D"))
    params = np.asarray(graph.values.params(Pose3Var)).copy()
    params[:, 4:] += rng.normal(size=(len(params), 3))
    moved = Values({Pose3Var: graph.vertex_ids}, {Pose3Var: params})
    for args in ((graph.with_values(moved),), (moved, graph.factors)):
        out = tmp_path / "opt.g2o"
        write_g2o(out, *args)
        back = read_g2o(out)
        np.testing.assert_array_equal(back.values.params(Pose3Var), params)
        np.testing.assert_array_equal(back.measured, graph.measured)
        np.testing.assert_allclose(back.information, graph.information, 1e-13)


@pytest.mark.gtsam
def test_gtsam_reads_what_we_write(tmp_path: Path, gtsam) -> None:
    for name in ("smallGrid3D", "intel"):
        graph = read_g2o(data_file(name))
        out = tmp_path / f"{name}.g2o"
        write_g2o(out, graph)
        factors, values = gtsam.readG2o(str(out), graph.dim == 3)
        assert_matches_gtsam(graph, factors, values)


def test_write_rejects_wrong_inputs(tmp_path: Path) -> None:
    graph = read_g2o(data_file("tinyGrid3D"))
    with pytest.raises(TypeError):
        write_g2o(tmp_path / "x.g2o", graph, graph.factors)
    with pytest.raises(TypeError):
        write_g2o(tmp_path / "x.g2o", graph.values)
    missing = Values({Pose3Var: graph.vertex_ids[:3]}, {Pose3Var: graph.values.params(Pose3Var)[:3]})
    with pytest.raises(GraphError):
        write_g2o(tmp_path / "x.g2o", missing, graph.factors)


def test_write_refuses_non_finite_values(tmp_path: Path) -> None:
    graph = read_g2o(data_file("tinyGrid3D"))
    params = np.asarray(graph.values.params(Pose3Var)).copy()
    params[3, 5] = np.nan
    broken = Values({Pose3Var: graph.vertex_ids}, {Pose3Var: params})
    with pytest.raises(ValueError, match="row 3 is not finite"):
        write_g2o(tmp_path / "x.g2o", graph.with_values(broken))
    assert not (tmp_path / "x.g2o").exists()


def test_from_arrays_builds_and_validates() -> None:
    values = Values({Pose2Var: np.array([0, 1])}, {Pose2Var: np.array([[1.0, 0, 0, 0], [1.0, 0, 1, 0]])})
    z = np.array([[1.0, 0, 1, 0]])
    graph = PoseGraph.from_arrays(2, values, np.array([0]), np.array([1]), z, np.eye(3)[None], fixed=[0])
    assert [type(f) for f in graph.factors] == [BetweenFactor, PriorFactor]
    with pytest.raises(ValueError, match=r"measured must have shape \(1, 4\)"):
        PoseGraph.from_arrays(2, values, np.array([0]), np.array([1]), z[:, :3], np.eye(3)[None])
    with pytest.raises(ValueError, match=r"information\[0\] is not symmetric positive definite"):
        PoseGraph.from_arrays(2, values, np.array([0]), np.array([1]), z, -np.eye(3)[None])
    with pytest.raises(GraphError):
        PoseGraph.from_arrays(2, values, np.array([0]), np.array([5]), z, np.eye(3)[None])


# --- bad input: each raises a JaxSlamError naming the file and line -----------------------------

V2 = "VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 1 0 0\n"
E2 = "EDGE_SE2 0 1 1 0 0 1 0 0 1 0 1\n"
V3 = "VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1\nVERTEX_SE3:QUAT 1 1 0 0 0 0 0 1\n"
INFO6 = " ".join("1" if r == c else "0" for r in range(6) for c in range(r, 6))


@pytest.mark.parametrize(
    ("text", "error", "pattern"),
    [
        (
            V2 + "EDGE_SE2 0 1 1 0 0 1 0 0 1x 0 1\n",
            InputFormatError,
            r":3: EDGE_SE2 field I22 is '1x', expected a number",
        ),
        (V2 + "EDGE_SE2 0 1 1 0 0 1 0 0 1 0\n", InputFormatError, r":3: EDGE_SE2 needs 11 fields, found 10"),
        (
            V3 + f"EDGE_SE3:QUAT 0 1 1 0 0 0 0 0 1 {INFO6[:-2]}\n",
            InputFormatError,
            r":3: EDGE_SE3:QUAT needs 30 fields, found 29",
        ),
        (V2 + "VERTEX_SE2 2 0 0\n", InputFormatError, r":3: VERTEX_SE2 needs 4 fields, found 3"),
        (V2 + "EDGE_SE2_XY 0 1 1 0 1 0 1\n", InputFormatError, r":3: unknown tag 'EDGE_SE2_XY'"),
        (V2 + "EDGE_SE2 0 1 nan 0 0 1 0 0 1 0 1\n", InputFormatError, r":3: EDGE_SE2 field dx is 'nan'; NaN"),
        ("VERTEX_SE2 0 0 inf 0\n", InputFormatError, r":1: VERTEX_SE2 field y is 'inf'"),
        (V2 + "EDGE_SE2 0 1 1 0 0 1 0 0 1e999 0 1\n", InputFormatError, r":3: EDGE_SE2 field I22 is '1e999'"),
        (V2 + "EDGE_SE2 0 1 1 0 0 1 0 0 -1 0 1\n", InputFormatError, r":3: EDGE_SE2 information matrix is not"),
        (V2 + "EDGE_SE2 0 1 1 0 0 1 2 0 1 0 1\n", InputFormatError, r":3: EDGE_SE2 information matrix is not"),
        (V2 + "EDGE_SE2 0 1 1 0 0 0 0 0 0 0 0\n", InputFormatError, r":3: EDGE_SE2 information matrix is not"),
        (V2 + "VERTEX_SE2 0 5 5 5\n", GraphError, r":3: vertex 0 is defined again \(first on line 1\)"),
        (V2 + "EDGE_SE2 0 7 1 0 0 1 0 0 1 0 1\n", GraphError, r":3: an edge refers to vertex 7, which is not defined"),
        (V2 + "EDGE_SE2 1 1 1 0 0 1 0 0 1 0 1\n", GraphError, r":3: edge connects vertex 1 to itself"),
        (V2 + "FIX 9\n", GraphError, r":3: FIX refers to vertex 9"),
        (V2 + "FIX\n", InputFormatError, r":3: FIX needs at least 1 field"),
        (V2 + E2 + V3, InputFormatError, r":4: VERTEX_SE3:QUAT is a 3-D tag but line 1 has the 2-D tag VERTEX_SE2"),
        ("VERTEX_SE2 -1 0 0 0\n", InputFormatError, r":1: VERTEX_SE2 field id is '-1', expected a non-negative"),
        ("VERTEX_SE2 1.5 0 0 0\n", InputFormatError, r":1: VERTEX_SE2 field id is '1.5', expected an integer"),
        ("VERTEX_SE3:QUAT 0 0 0 0 0 0 0 2\n", InputFormatError, r":1: VERTEX_SE3:QUAT quaternion has norm 2"),
        ("VERTEX_SE3:QUAT 0 0 0 0 0 0 0 0\n", InputFormatError, r":1: VERTEX_SE3:QUAT quaternion has norm 0"),
        ("", InputFormatError, r"g\.g2o: file is empty"),
        ("# only a comment\n\n   \n", InputFormatError, r"g\.g2o: file is empty"),
        ("FIX 0\nEQUIV 1 2\n", InputFormatError, r"g\.g2o: no VERTEX or EDGE lines"),
    ],
)
def test_bad_input(tmp_path: Path, text: str, error: type[Exception], pattern: str) -> None:
    with pytest.raises(error, match=r"g\.g2o" + pattern if not pattern.startswith("g") else pattern):
        read_g2o(write(tmp_path, text))


def test_bad_input_carries_path_and_line(tmp_path: Path) -> None:
    path = write(tmp_path, V2 + "EDGE_SE2 0 1 1 0 0 1 0 0 1 0\n")
    with pytest.raises(InputFormatError) as info:
        read_g2o(path)
    assert info.value.path == str(path) and info.value.line == 3


def test_missing_file_and_directory(tmp_path: Path) -> None:
    with pytest.raises(InputFormatError, match=r"nope\.g2o: file not found"):
        read_g2o(tmp_path / "nope.g2o")
    with pytest.raises(InputFormatError, match="is a directory"):
        read_g2o(tmp_path)


def test_binary_and_non_utf8_files(tmp_path: Path, rng: np.random.Generator) -> None:
    binary = tmp_path / "b.g2o"
    binary.write_bytes(b"VERTEX_SE2 0 0 0 0\n" + rng.integers(0, 256, 500, dtype=np.uint8).tobytes() + b"\x00")
    with pytest.raises(InputFormatError, match="not a text file"):
        read_g2o(binary)
    latin = tmp_path / "l.g2o"
    latin.write_bytes(b"VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 \xe9 0 0\n")
    with pytest.raises(InputFormatError, match=r"l\.g2o:2: not UTF-8 text"):
        read_g2o(latin)


# --- fuzz: nothing but JaxSlamError escapes ----------------------------------------------------

_GOOD_LINES = [
    "VERTEX_SE2 0 0 0 0",
    "VERTEX_SE2 1 1 0 0.5",
    "EDGE_SE2 0 1 1 0 0.5 1 0 0 1 0 1",
    "EDGE2 1 0 -1 0 0 1 0 1 1 0 0",
    "VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1",
    "VERTEX_SE3:QUAT 1 1 0 0 0 0 0.1 0.995",
    f"EDGE_SE3:QUAT 0 1 1 0 0 0 0 0 1 {INFO6}",
    f"EDGE3 0 1 1 0 0 0 0 0.1 {INFO6}",
    "FIX 0",
    "EQUIV 0 1",
    "# comment",
]
_TOKENS = st.one_of(
    st.sampled_from(["0", "1", "2", "-1", "nan", "inf", "1e308", "-1e308", "0.5", "x", "", "FIX", "VERTEX_SE2"]),
    st.sampled_from(["EDGE_SE2", "EDGE_SE3:QUAT", "99999999999999999999", "1e-320", "#", "\t", "\x00", "\xe9"]),
    st.text(max_size=4),
)


@st.composite
def _mutated_line(draw: st.DrawFn) -> str:
    tokens = draw(st.sampled_from(_GOOD_LINES)).split(" ")
    for _ in range(draw(st.integers(0, 3))):
        action = draw(st.sampled_from(["drop", "replace", "insert"]))
        k = draw(st.integers(0, max(len(tokens) - 1, 0)))
        if action == "drop" and tokens:
            tokens.pop(k)
        elif action == "replace" and tokens:
            tokens[k] = draw(_TOKENS)
        else:
            tokens.insert(k, draw(_TOKENS))
    return " ".join(tokens)


@settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    lines=st.lists(st.one_of(_mutated_line(), st.sampled_from(_GOOD_LINES), st.text(max_size=30)), max_size=8),
    raw=st.one_of(st.none(), st.none(), st.none(), st.binary(max_size=64)),  # mostly text
)
def test_fuzz_only_jaxslam_errors_escape(lines: list[str], raw: bytes | None) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "fuzz.g2o"
        data = raw if raw is not None else "\n".join(lines).encode("utf-8", "surrogatepass")
        path.write_bytes(data)
        try:
            graph = read_g2o(path)
        except JaxSlamError:
            return
        assert isinstance(graph, PoseGraph) and graph.dim in (2, 3)
        out = Path(tmp) / "out.g2o"
        write_g2o(out, graph)
        assert read_g2o(out).num_edges == graph.num_edges

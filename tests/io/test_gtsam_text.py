"""Writing GTSAM's text formats (``VERTEX3``/``EDGE3``, ``VERTEX2``/``EDGE2``): write -> read
gives the same graph, GTSAM's own readers get the same factors as from the original file,
roll/pitch/yaw survive gimbal lock, and ``jaxslam optimize -o OUT.txt`` writes this format."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from jaxslam.cli import main
from jaxslam.core import Pose2Var, Pose3Var, Values
from jaxslam.io import PoseGraph, quaternion_from_rpy, read_g2o, rpy_from_quaternion, write_g2o

DATA = Path(__file__).resolve().parents[2] / ".." / "shared" / "data" / "posegraph"


def data_file(name: str) -> Path:
    path = DATA / f"{name}.g2o"
    if not path.exists():
        pytest.skip(f"{path} is not available")
    return path


def sphere2500_txt() -> Path:
    gtsam = pytest.importorskip("gtsam")
    return Path(gtsam.findExampleDataFile("sphere2500.txt"))


def source(name: str) -> Path:
    return sphere2500_txt() if name == "sphere2500.txt" else data_file(name)


def pose_matrix(dim: int, p: np.ndarray) -> np.ndarray:
    """``(N, 3, 3)`` / ``(N, 4, 4)`` homogeneous matrices of jaxslam params."""
    p = np.asarray(p, dtype=np.float64)
    n = len(p)
    if dim == 2:
        c, s, x, y = p.T
        m = np.zeros((n, 3, 3))
        m[:, 0, 0], m[:, 0, 1], m[:, 1, 0], m[:, 1, 1] = c, -s, s, c
        m[:, 0, 2], m[:, 1, 2], m[:, 2, 2] = x, y, 1.0
        return m
    w, a, b, c = p[:, :4].T
    m = np.zeros((n, 4, 4))
    m[:, 0] = np.stack([1 - 2 * (b * b + c * c), 2 * (a * b - c * w), 2 * (a * c + b * w), p[:, 4]], -1)
    m[:, 1] = np.stack([2 * (a * b + c * w), 1 - 2 * (a * a + c * c), 2 * (b * c - a * w), p[:, 5]], -1)
    m[:, 2] = np.stack([2 * (a * c - b * w), 2 * (b * c + a * w), 1 - 2 * (a * a + b * b), p[:, 6]], -1)
    m[:, 3, 3] = 1.0
    return m


def assert_same_graph(back: PoseGraph, graph: PoseGraph) -> None:
    """Edges and fixed ids equal; measured poses and vertices within 1e-12 (as matrices);
    information within 1e-9 relative to each matrix's largest entry."""
    assert back.dim == graph.dim
    for field in ("edges_i", "edges_j", "vertex_ids", "fixed"):
        np.testing.assert_array_equal(getattr(back, field), getattr(graph, field))
    np.testing.assert_allclose(pose_matrix(back.dim, back.measured), pose_matrix(graph.dim, graph.measured), 0, 1e-12)
    scale = np.abs(graph.information).max(axis=(1, 2), keepdims=True)
    np.testing.assert_allclose(back.information / scale, graph.information / scale, 0, 1e-9)
    vt = graph.var_type
    ours, theirs = back.values.params(vt), graph.values.params(vt)
    np.testing.assert_allclose(pose_matrix(back.dim, ours), pose_matrix(graph.dim, theirs), 0, 1e-12)


def tags(path: Path) -> set[str]:
    return {line.split()[0] for line in path.read_text().splitlines() if line.strip()}


# --- roll, pitch, yaw --------------------------------------------------------------------------


def test_rpy_from_quaternion_inverts_quaternion_from_rpy(rng: np.random.Generator) -> None:
    q = rng.normal(size=(20000, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    rpy = rpy_from_quaternion(q)
    assert np.all(np.abs(rpy[:, 1]) <= np.pi / 2) and np.all(np.abs(rpy[:, [0, 2]]) <= np.pi)
    back = quaternion_from_rpy(*rpy.T)
    np.testing.assert_allclose(np.abs(np.sum(q * back, axis=1)), 1.0, 0, 1e-15)  # same rotation, either sign
    for other in (rpy_from_quaternion(-q), rpy_from_quaternion(back)):  # same angles (mod 2 pi)
        np.testing.assert_allclose(np.angle(np.exp(1j * (other - rpy))), 0.0, 0, 1e-13)


@pytest.mark.gtsam
def test_rpy_matches_gtsam_rot3(rng: np.random.Generator, gtsam) -> None:
    q = rng.normal(size=(200, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    expect = np.stack([gtsam.Rot3.Quaternion(*row).rpy() for row in q])
    np.testing.assert_allclose(rpy_from_quaternion(q), expect, 0, 1e-12)


def gimbal_rpy(rng: np.random.Generator) -> np.ndarray:
    """Pitch at and next to +-pi/2 with any roll and yaw (including roll = yaw = 0)."""
    pitches = [np.pi / 2, -np.pi / 2, np.nextafter(np.pi / 2, 0), np.pi / 2 - 1e-9, -np.pi / 2 + 1e-12]
    rpy = rng.uniform(-np.pi, np.pi, size=(5 * len(pitches), 3))
    rpy[:, 1] = np.repeat(pitches, 5)
    rpy[::5, 0] = rpy[::5, 2] = 0.0
    return rpy


def test_gimbal_lock_has_no_nan_and_round_trips(rng: np.random.Generator) -> None:
    rpy = gimbal_rpy(rng)
    q = quaternion_from_rpy(*rpy.T)
    for sign in (1.0, -1.0):
        got = rpy_from_quaternion(sign * q)
        assert np.all(np.isfinite(got))
        np.testing.assert_allclose(np.abs(np.sum(quaternion_from_rpy(*got.T) * q, axis=1)), 1.0, 0, 1e-15)


def gimbal_graph(rng: np.random.Generator) -> PoseGraph:
    """Vertices and edges whose rotations sit at or next to gimbal lock."""
    rpy = gimbal_rpy(rng)
    n = len(rpy)
    params = np.concatenate([quaternion_from_rpy(*rpy.T), rng.normal(size=(n, 3))], axis=1)
    params[1::2, :4] *= -1.0  # both quaternion signs
    values = Values({Pose3Var: np.arange(n)}, {Pose3Var: params})
    info = np.broadcast_to(np.diag([1e4, 2e4, 3e4, 10.0, 20.0, 30.0]), (n - 1, 6, 6))
    return PoseGraph.from_arrays(3, values, np.arange(n - 1), np.arange(1, n), params[1:], info, [0])


def test_gimbal_lock_graph_writes_and_reads_back(tmp_path: Path, rng: np.random.Generator) -> None:
    graph = gimbal_graph(rng)
    out = tmp_path / "gimbal.txt"
    write_g2o(out, graph, format="gtsam")
    assert "nan" not in out.read_text().lower()
    assert tags(out) == {"VERTEX3", "EDGE3", "FIX"}
    assert_same_graph(read_g2o(out), graph)


@pytest.mark.gtsam
def test_gtsam_reads_gimbal_lock_poses(tmp_path: Path, rng: np.random.Generator, gtsam) -> None:
    graph = gimbal_graph(rng)
    out = tmp_path / "gimbal.txt"
    write_g2o(out, graph, format="gtsam")
    factors, values = gtsam.load3D(str(out))
    params = np.asarray(graph.values.params(Pose3Var))
    np.testing.assert_allclose(
        np.stack([values.atPose3(int(i)).matrix() for i in graph.vertex_ids]), pose_matrix(3, params), 0, 1e-12
    )
    measured = np.stack([factors.at(k).measured().matrix() for k in range(factors.size())])
    np.testing.assert_allclose(measured, pose_matrix(3, graph.measured), 0, 1e-12)


# --- round trips on real files -----------------------------------------------------------------


@pytest.mark.parametrize(("name", "suffix"), [("smallGrid3D", ".txt"), ("sphere2500.txt", ".txt"), ("intel", ".graph")])
def test_write_read_round_trip(tmp_path: Path, name: str, suffix: str) -> None:
    graph = read_g2o(source(name))
    out = tmp_path / f"out{suffix}"
    write_g2o(out, graph, format="gtsam")
    expect_tags = {"VERTEX3", "EDGE3"} if graph.dim == 3 else {"VERTEX2", "EDGE2"}
    assert tags(out) == expect_tags | ({"FIX"} if len(graph.fixed) else set())
    back = read_g2o(out)
    assert back.initialised_from == "vertices"
    assert_same_graph(back, graph)
    if graph.dim == 2:  # the same angle and information layout as g2o: bit for bit
        np.testing.assert_array_equal(back.measured, graph.measured)
        np.testing.assert_array_equal(back.information, graph.information)
        np.testing.assert_array_equal(back.values.params(Pose2Var), graph.values.params(Pose2Var))
    again = tmp_path / f"again{suffix}"
    write_g2o(again, back, format="gtsam")
    assert_same_graph(read_g2o(again), back)


def gtsam_factor_arrays(dim: int, factors) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Keys ``(M, 2)``, measured matrices and information ``R^T R`` of GTSAM BetweenFactors."""
    gf = [factors.at(k) for k in range(factors.size())]
    keys = np.array([f.keys() for f in gf], dtype=np.int64).reshape(-1, 2)
    measured = np.stack([f.measured().matrix() for f in gf])
    r = np.stack([f.noiseModel().R() for f in gf])
    return keys, measured, np.swapaxes(r, 1, 2) @ r


def assert_same_gtsam_factors(dim: int, got, expect) -> None:
    keys, measured, info = gtsam_factor_arrays(dim, got)
    keys0, measured0, info0 = gtsam_factor_arrays(dim, expect)
    np.testing.assert_array_equal(keys, keys0)
    np.testing.assert_allclose(measured, measured0, 0, 1e-12)
    scale = np.abs(info0).max(axis=(1, 2), keepdims=True)
    np.testing.assert_allclose(info / scale, info0 / scale, 0, 1e-9)


@pytest.mark.gtsam
@pytest.mark.parametrize("name", ["smallGrid3D", "sphere2500.txt"])
def test_gtsam_load3d_reads_our_3d_file(tmp_path: Path, name: str, gtsam) -> None:
    path = source(name)
    graph = read_g2o(path)
    out = tmp_path / "out.txt"
    write_g2o(out, graph, format="gtsam")
    original = gtsam.load3D(str(path))[0] if path.suffix == ".txt" else gtsam.readG2o(str(path), True)[0]
    for factors, values in (gtsam.load3D(str(out)), gtsam.readG2o(str(out), True)):
        assert_same_gtsam_factors(3, factors, original)
        assert values.size() == len(graph.vertex_ids)
        ours = pose_matrix(3, graph.values.params(Pose3Var))
        theirs = np.stack([values.atPose3(int(i)).matrix() for i in graph.vertex_ids])
        np.testing.assert_allclose(theirs, ours, 0, 1e-12)


@pytest.mark.gtsam
def test_gtsam_reads_our_2d_file(tmp_path: Path, gtsam) -> None:
    """GTSAM's ``load2D`` needs ``NoiseFormatG2O`` (its default guesses a covariance from the
    zero pattern); ``readG2o`` reads EDGE2 as g2o information anyway."""
    path = data_file("intel")
    graph = read_g2o(path)
    out = tmp_path / "out.graph"
    write_g2o(out, graph, format="gtsam")
    original, original_values = gtsam.readG2o(str(path), False)
    for factors, values in (
        gtsam.load2D(str(out), noiseFormat=gtsam.NoiseFormat.NoiseFormatG2O),
        gtsam.readG2o(str(out), False),
    ):
        assert_same_gtsam_factors(2, factors, original)
        ids = graph.vertex_ids.tolist()
        theirs = np.stack([values.atPose2(i).matrix() for i in ids])
        np.testing.assert_allclose(theirs, np.stack([original_values.atPose2(i).matrix() for i in ids]), 0, 1e-12)


# --- format selection and refusals -------------------------------------------------------------


def test_format_auto_by_suffix(tmp_path: Path) -> None:
    graph = read_g2o(data_file("tinyGrid3D"))
    quat = "VERTEX_SE3:QUAT"
    for name, expect in [("a.txt", "VERTEX3"), ("a.GRAPH", "VERTEX3"), ("a.g2o", quat), ("a", quat)]:
        write_g2o(tmp_path / name, graph, format="auto")
        assert (tmp_path / name).read_text().split()[0] == expect
    write_g2o(tmp_path / "plain.txt", graph)  # the default stays g2o whatever the suffix
    assert (tmp_path / "plain.txt").read_text().split()[0] == "VERTEX_SE3:QUAT"
    with pytest.raises(ValueError, match="format must be"):
        write_g2o(tmp_path / "x.txt", graph, format="toro")  # type: ignore[arg-type]


def test_values_and_factors_in_gtsam_format(tmp_path: Path) -> None:
    graph = read_g2o(data_file("tinyGrid3D"))
    out = tmp_path / "vf.txt"
    write_g2o(out, graph.values, graph.factors, format="gtsam")
    assert_same_graph(read_g2o(out), graph)


@pytest.mark.parametrize("dim", [2, 3])
def test_nan_poses_are_refused(tmp_path: Path, dim: int) -> None:
    graph = read_g2o(data_file("intel" if dim == 2 else "tinyGrid3D"))
    vt = graph.var_type
    params = np.asarray(graph.values.params(vt)).copy()
    params[3, 0] = np.nan
    bad = graph.with_values(Values({vt: graph.vertex_ids}, {vt: params}))
    out = tmp_path / "bad.txt"
    with pytest.raises(ValueError, match="row 3 is not finite"):
        write_g2o(out, bad, format="gtsam")
    assert not out.exists()
    measured = graph.measured.copy()
    measured[1, -1] = np.inf
    bad_edge = PoseGraph.from_arrays(dim, graph.values, graph.edges_i, graph.edges_j, measured, graph.information)
    with pytest.raises(ValueError, match="measured: row 1 is not finite"):
        write_g2o(out, bad_edge, format="gtsam")


# --- the command line --------------------------------------------------------------------------


@pytest.mark.gtsam
def test_cli_writes_gtsam_text_for_txt(tmp_path: Path, gtsam) -> None:
    out = tmp_path / "opt.txt"
    assert main(["optimize", str(data_file("smallGrid3D")), "-o", str(out), "-q"]) == 0
    assert tags(out) <= {"VERTEX3", "EDGE3", "FIX"} and "EDGE3" in tags(out)
    ours = read_g2o(out)
    factors, values = gtsam.load3D(str(out))
    assert factors.size() == ours.num_edges == read_g2o(data_file("smallGrid3D")).num_edges
    theirs = np.stack([values.atPose3(int(i)).matrix() for i in ours.vertex_ids])
    np.testing.assert_allclose(theirs, pose_matrix(3, ours.values.params(Pose3Var)), 0, 1e-12)


def test_cli_writes_graph_suffix_as_vertex2(tmp_path: Path) -> None:
    src = tmp_path / "square.g2o"
    src.write_text(
        "VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 1.1 0 1.5\nVERTEX_SE2 2 1 1 3.1\nVERTEX_SE2 3 0 0.9 -1.6\n"
        + "".join(f"EDGE_SE2 {i} {(i + 1) % 4} 1 0 1.5707963267948966 100 0 0 100 0 400\n" for i in range(4))
        + "FIX 0\n"
    )
    out = tmp_path / "opt.graph"
    assert main(["optimize", str(src), "-o", str(out), "-q"]) == 0
    assert tags(out) == {"VERTEX2", "EDGE2", "FIX"}
    back = read_g2o(out)
    assert back.num_edges == 4
    np.testing.assert_allclose(back.values.params(Pose2Var)[2], [-1.0, 0.0, 1.0, 1.0], 0, 1e-6)

"""TUM / KITTI trajectory I/O: evo's column conventions, real files, exact round trips and
bad input that names the file and line."""

from __future__ import annotations

import tempfile
from pathlib import Path

import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from jaxslam.errors import InputFormatError, JaxSlamError
from jaxslam.io import Trajectory, read_kitti, read_trajectory, read_tum, write_kitti, write_tum
from jaxslam.lie import SE3, SO3

DATA = Path(__file__).resolve().parents[2] / ".." / "shared" / "data"
EUROC_TUM = DATA / "euroc_V1_01" / "groundtruth_openvins" / "V1_01_easy_original.txt"
KITTI_POSES = DATA / "kitti_mono" / "poses.txt"


def needs(path: Path) -> Path:
    if not path.exists():
        pytest.skip(f"{path} is not available")
    return path


def write(tmp_path: Path, text: str, name: str = "t.txt") -> Path:
    path = tmp_path / name
    path.write_text(text)
    return path


def random_trajectory(rng: np.random.Generator, n: int) -> Trajectory:
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    params = np.concatenate([q, rng.normal(size=(n, 3)) * 10], axis=1)
    t = 1.4e9 + np.cumsum(rng.uniform(0.001, 0.1, n))
    return Trajectory(t, SE3(jnp.asarray(params)))


# --- real files --------------------------------------------------------------------------------


def test_read_tum_euroc_ground_truth() -> None:
    path = needs(EUROC_TUM)
    traj = read_tum(path)
    raw = np.loadtxt(path, comments="#")
    assert len(traj) == raw.shape[0] == 28712
    np.testing.assert_array_equal(traj.timestamps, raw[:, 0])
    np.testing.assert_array_equal(np.asarray(traj.positions), raw[:, 1:4])
    q_wxyz = raw[:, [7, 4, 5, 6]] / np.linalg.norm(raw[:, 4:8], axis=1, keepdims=True)
    np.testing.assert_allclose(np.asarray(traj.poses.params[:, :4]), q_wxyz, 0, 1e-15)
    assert np.all(np.diff(traj.timestamps) > 0)


def test_read_kitti_poses() -> None:
    path = needs(KITTI_POSES)
    traj = read_kitti(path)
    raw = np.loadtxt(path).reshape(-1, 3, 4)
    assert len(traj) == 51
    np.testing.assert_array_equal(traj.timestamps, np.arange(51.0))
    np.testing.assert_array_equal(np.asarray(traj.positions), raw[:, :, 3])
    # The file keeps 7 digits: rotations are the nearest rotation to what is written.
    np.testing.assert_allclose(np.asarray(traj.poses.rotation.as_matrix()), raw[:, :, :3], 0, 1e-6)


def test_read_trajectory_guesses_the_format(tmp_path: Path) -> None:
    assert len(read_trajectory(needs(KITTI_POSES))) == 51
    tum = write(tmp_path, "1 0 0 0 0 0 0 1\n2 1 0 0 0 0 0 1\n")
    assert len(read_trajectory(tum)) == 2
    with pytest.raises(InputFormatError, match=r"t\.txt:1: cannot tell the trajectory format: 3 fields"):
        read_trajectory(write(tmp_path, "1 2 3\n"))


# --- conventions (evo / TUM / KITTI) -----------------------------------------------------------


def test_tum_columns_are_t_xyz_then_quaternion_xyzw(tmp_path: Path) -> None:
    s = float(np.sin(np.pi / 4))
    traj = read_tum(write(tmp_path, f"# timestamp tx ty tz qx qy qz qw\n10.5 1 2 3 0 0 {s!r} {s!r}\n"))
    np.testing.assert_allclose(np.asarray(traj.poses.params[0]), [s, 0, 0, s, 1, 2, 3], 0, 1e-15)
    np.testing.assert_allclose(np.asarray(traj.poses.act(jnp.array([1.0, 0, 0])))[0], [1, 3, 3], 0, 1e-15)
    assert traj.timestamps[0] == 10.5


def test_kitti_rows_are_3x4_row_major(tmp_path: Path) -> None:
    traj = read_kitti(write(tmp_path, "0 -1 0 1 1 0 0 2 0 0 1 3\n"))
    s = np.sin(np.pi / 4)
    np.testing.assert_allclose(np.asarray(traj.poses.params[0]), [s, 0, 0, s, 1, 2, 3], 0, 1e-15)


# --- round trips -------------------------------------------------------------------------------


def test_tum_round_trip_is_exact(tmp_path: Path, rng: np.random.Generator) -> None:
    traj = random_trajectory(rng, 200)
    out = tmp_path / "a.tum"
    write_tum(out, traj)
    assert out.read_text().startswith("# timestamp tx ty tz qx qy qz qw\n")
    back = read_tum(out)
    np.testing.assert_array_equal(back.timestamps, traj.timestamps)
    np.testing.assert_array_equal(np.asarray(back.poses.params), np.asarray(traj.poses.params))
    write_tum(tmp_path / "b.tum", back, header=False)
    np.testing.assert_array_equal(read_tum(tmp_path / "b.tum").timestamps, traj.timestamps)


def test_tum_round_trip_of_real_file(tmp_path: Path) -> None:
    traj = read_tum(needs(EUROC_TUM))
    write_tum(tmp_path / "e.tum", traj)
    back = read_tum(tmp_path / "e.tum")
    np.testing.assert_array_equal(back.timestamps, traj.timestamps)
    np.testing.assert_array_equal(np.asarray(back.poses.params), np.asarray(traj.poses.params))


def test_kitti_round_trip_with_times(tmp_path: Path, rng: np.random.Generator) -> None:
    traj = random_trajectory(rng, 100)
    write_kitti(tmp_path / "p.txt", traj, tmp_path / "times.txt")
    back = read_kitti(tmp_path / "p.txt", tmp_path / "times.txt")
    np.testing.assert_array_equal(back.timestamps, traj.timestamps)
    np.testing.assert_array_equal(np.asarray(back.positions), np.asarray(traj.positions))
    np.testing.assert_allclose(
        np.asarray(back.poses.rotation.as_matrix()), np.asarray(traj.poses.rotation.as_matrix()), 0, 5e-15
    )
    again = read_kitti(tmp_path / "p.txt", back.timestamps)  # times as an array
    np.testing.assert_array_equal(again.timestamps, traj.timestamps)


def test_trajectory_constructors() -> None:
    m = np.broadcast_to(np.eye(4), (3, 4, 4))
    traj = Trajectory.from_matrices(np.arange(3.0), m)
    np.testing.assert_allclose(np.asarray(traj.poses.params), np.asarray(SE3.identity((3,)).params))
    with pytest.raises(ValueError, match="batch"):
        Trajectory(np.arange(2.0), traj.poses)
    with pytest.raises(ValueError, match="1-D"):
        Trajectory(np.zeros((3, 1)), traj.poses)


def test_writers_refuse_non_finite(tmp_path: Path, rng: np.random.Generator) -> None:
    traj = random_trajectory(rng, 5)
    bad = Trajectory(traj.timestamps, SE3(traj.poses.params.at[2, 5].set(jnp.inf)))
    with pytest.raises(ValueError, match="row 2 is not finite"):
        write_tum(tmp_path / "a.tum", bad)
    with pytest.raises(ValueError, match="row 2 is not finite"):
        write_kitti(tmp_path / "a.txt", bad)


# --- decisions: quaternion norm, monotonic time ------------------------------------------------


def test_near_unit_quaternion_is_normalised(tmp_path: Path) -> None:
    traj = read_tum(write(tmp_path, "0 0 0 0 0 0 0 1.004\n1 0 0 0 0.1 0 0 1\n"))
    np.testing.assert_allclose(np.linalg.norm(np.asarray(traj.poses.params[:, :4]), axis=1), 1.0, 0, 1e-15)
    np.testing.assert_allclose(np.asarray(traj.poses.params[1, :2]), np.array([1, 0.1]) / np.hypot(1, 0.1))


@pytest.mark.parametrize(
    ("text", "pattern"),
    [
        ("0 0 0 0 0 0 0 1\n1 0 0 0 0 0 0 1.5\n", r":2: TUM row quaternion has norm 1.5"),
        ("0 0 0 0 0 0 0 0\n", r":1: TUM row quaternion has norm 0"),
        ("0 0 0 0 0 0 0 1\n# c\n1 0 0 0 0 0 1\n", r":3: TUM row needs 8 fields, found 7"),
        ("0 0 0 0 0 0 0 1 5\n", r":1: TUM row needs 8 fields, found 9"),
        ("0 0 0 0 0 0 0 1\n1 0 0 x 0 0 0 1\n", r":2: TUM row field tz is 'x', expected a number"),
        ("0 0 nan 0 0 0 0 1\n", r":1: TUM row field ty is 'nan'; NaN"),
        ("0 0 0 0 0 0 0 1\n2 0 0 0 0 0 0 1\n1 0 0 0 0 0 0 1\n", r":3: timestamp 1.0 is not after 2.0 on line 2"),
        ("0 0 0 0 0 0 0 1\n0 0 0 0 0 0 0 1\n", r":2: timestamp 0.0 is not after 0.0 on line 1"),
        ("", r": file is empty"),
    ],
)
def test_tum_bad_input(tmp_path: Path, text: str, pattern: str) -> None:
    with pytest.raises(InputFormatError, match=r"t\.txt" + pattern):
        read_tum(write(tmp_path, text))


@pytest.mark.parametrize(
    ("text", "pattern"),
    [
        ("1 0 0 0 0 1 0 0 0 0 1\n", r":1: KITTI row needs 12 fields, found 11"),
        ("1 0 0 0 0 1 0 0 0 0 1 0\n2 0 0 0 0 1 0 0 0 0 1 0\n", r":2: KITTI row's 3x3 block is not a rotation"),
        ("1 0 0 0 0 1 0 0 0 0 -1 0\n", r":1: KITTI row's 3x3 block is not a rotation"),
        ("1 0 0 0 0 1 0 0 0 0 1 inf\n", r":1: KITTI row field tz is 'inf'"),
    ],
)
def test_kitti_bad_input(tmp_path: Path, text: str, pattern: str) -> None:
    with pytest.raises(InputFormatError, match=r"t\.txt" + pattern):
        read_kitti(write(tmp_path, text))


def test_kitti_bad_times(tmp_path: Path) -> None:
    poses = write(tmp_path, "1 0 0 0 0 1 0 0 0 0 1 0\n" * 3, "p.txt")
    with pytest.raises(InputFormatError, match=r"times\.txt: has 2 timestamps but .*p\.txt has 3 poses"):
        read_kitti(poses, write(tmp_path, "0\n1\n", "times.txt"))
    with pytest.raises(InputFormatError, match=r"times\.txt:3: timestamp 0.5 is not after 1.0"):
        read_kitti(poses, write(tmp_path, "0\n1\n0.5\n", "times.txt"))
    with pytest.raises(InputFormatError, match=r"times\.txt:2: times row needs 1 fields, found 2"):
        read_kitti(poses, write(tmp_path, "0\n1 2\n3\n", "times.txt"))
    with pytest.raises(ValueError, match="increase strictly"):
        read_kitti(poses, np.array([0.0, 2.0, 1.0]))
    with pytest.raises(ValueError, match="shape"):
        read_kitti(poses, np.array([0.0, 2.0]))


def test_missing_and_binary_files(tmp_path: Path) -> None:
    with pytest.raises(InputFormatError, match="file not found"):
        read_tum(tmp_path / "none.txt")
    binary = tmp_path / "b.txt"
    binary.write_bytes(bytes(range(256)))
    with pytest.raises(InputFormatError, match="not a text file"):
        read_kitti(binary)


def test_rotation_round_trip_helper_agrees_with_so3() -> None:
    r = np.asarray(SO3.exp(jnp.array([[0.1, -0.2, 0.3]])).as_matrix())
    traj = Trajectory.from_matrices(np.zeros(1), np.concatenate([r, np.zeros((1, 3, 1))], axis=2))
    np.testing.assert_allclose(np.asarray(traj.poses.rotation.as_matrix()), r, 0, 1e-15)


# --- fuzz --------------------------------------------------------------------------------------

_NUMBER = st.one_of(
    st.sampled_from(["0", "1", "-1", "0.5", "nan", "inf", "1e308", "x", "#", ""]),
    st.floats(allow_nan=True).map(repr),
    st.text(max_size=3),
)


@settings(max_examples=100, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(rows=st.lists(st.lists(_NUMBER, min_size=6, max_size=13), max_size=5), kitti=st.booleans())
def test_fuzz_only_jaxslam_errors_escape(rows: list[list[str]], kitti: bool) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "fuzz.txt"
        path.write_bytes("\n".join(" ".join(r) for r in rows).encode("utf-8", "surrogatepass"))
        try:
            traj = read_kitti(path) if kitti else read_tum(path)
        except JaxSlamError:
            return
        assert np.all(np.isfinite(np.asarray(traj.poses.params)))

"""The recording registry and the EuRoC/ASL reader, on the real EuRoC V1_01 excerpt."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest

from jaxslam.errors import InputFormatError
from jaxslam.io import EurocRecording, Trajectory, open_recording, recording_formats
from jaxslam.measurements import Image, ImuSample

DATA = Path(__file__).resolve().parents[2] / ".." / "shared" / "data"
EUROC = DATA / "euroc_V1_01"
GT_TUM = EUROC / "groundtruth_openvins" / "V1_01_easy_original.txt"
ROSBAG = DATA / "rosbag"

needs_euroc = pytest.mark.skipif(not EUROC.is_dir(), reason="shared EuRoC data not present")


@pytest.fixture(scope="module")
def euroc_records():
    rec = open_recording(EUROC, ground_truth=GT_TUM)
    return rec, list(rec)


@needs_euroc
def test_euroc_is_guessed_and_lists_streams(euroc_records):
    rec, _ = euroc_records
    assert isinstance(rec, EurocRecording)
    streams = {s.kind: s for s in rec.streams()}
    assert streams["imu"].count == 29120 and streams["image"].count == 20
    assert streams["imu"].t_start == pytest.approx(1403715273.262142976, abs=1e-6)
    assert streams["imu"].t_end == pytest.approx(1403715418.857143, abs=1e-5)
    assert set(rec.topics()) == {"imu0", "cam0"}
    # cam0/data.csv lists 95 frames, only 20 PNGs ship: the rest are counted, not raised
    assert rec.skipped["cam0: image file missing"] == 75


@needs_euroc
def test_euroc_records_counts_order_and_units(euroc_records):
    _, records = euroc_records
    imu = [r for r in records if isinstance(r, ImuSample)]
    images = [r for r in records if isinstance(r, Image)]
    assert len(imu) == 29120 and len(images) == 20
    t = np.array([r.t for r in records])
    assert np.all(np.diff(t) >= 0)
    assert imu[0].t == pytest.approx(1403715273.262142976, abs=1e-6)
    assert imu[-1].t == pytest.approx(1403715418.857143, abs=1e-5)
    assert images[0].t == pytest.approx(1403715273.262142976, abs=1e-6)
    assert images[-1].t == pytest.approx(1403715274.2121432, abs=1e-6)
    # first csv row: gyro in rad/s, acc in m/s^2, standing still -> |acc| ~ g
    np.testing.assert_allclose(imu[0].gyro, [-0.0020943951023931952, 0.017453292519943295, 0.07749261878854824])
    np.testing.assert_allclose(imu[0].acc, [9.0874956666666655, 0.13075533333333333, -3.6938381666666662])
    acc = np.stack([r.acc for r in imu[:200]])
    assert np.linalg.norm(acc, axis=1).mean() == pytest.approx(9.81, abs=0.2)
    assert np.abs(np.stack([r.gyro for r in imu])).max() < 10.0
    assert images[0].data.shape == (480, 752) and images[0].data.dtype == np.uint8
    assert images[0].camera == "cam0"


@needs_euroc
def test_euroc_ground_truth_from_tum_option(euroc_records):
    rec, _ = euroc_records
    gt = rec.ground_truth()
    assert isinstance(gt, Trajectory)
    assert len(gt) == 28712 and np.all(np.diff(gt.timestamps) > 0)
    assert open_recording(EUROC).ground_truth() is None


def _tiny_euroc(tmp_path: Path, imu_rows: list[str], gt: bool = False) -> Path:
    root = tmp_path / "seq" / "mav0"
    (root / "imu0").mkdir(parents=True)
    header = "#timestamp [ns],w_RS_S_x [rad s^-1],w_RS_S_y,w_RS_S_z,a_RS_S_x [m s^-2],a_RS_S_y,a_RS_S_z\n"
    (root / "imu0" / "data.csv").write_text(header + "\n".join(imu_rows) + "\n")
    if gt:
        (root / "state_groundtruth_estimate0").mkdir()
        rows = ["#timestamp,p_x,p_y,p_z,q_w,q_x,q_y,q_z,v_x,v_y,v_z"]
        rows += [f"{1000 + i},{i},0,0,1,0,0,0,0,0,0" for i in range(3)]
        (root / "state_groundtruth_estimate0" / "data.csv").write_text("\n".join(rows) + "\n")
    return tmp_path / "seq"


def test_euroc_nan_and_backwards_rows_are_skipped_and_counted(tmp_path):
    rows = [
        "1000000000,0,0,0,0,0,9.81",
        "1005000000,nan,0,0,0,0,9.81",
        "1010000000,0,0,0,0,0,9.81",
        "1002000000,0,0,0,0,0,9.81",
        "1015000000,0.1,0,0,0,0,9.81",
    ]
    rec = open_recording(_tiny_euroc(tmp_path, rows))
    got = list(rec)
    assert [r.t for r in got] == [1.0, 1.01, 1.015]
    assert rec.skipped == {"imu0: invalid (NaN or shape)": 1, "imu0: time not increasing": 1}
    assert len(list(rec)) == 3 and sum(rec.skipped.values()) == 2  # iterating again recounts


def test_euroc_ground_truth_from_state_csv(tmp_path):
    rec = open_recording(_tiny_euroc(tmp_path, ["1000,0,0,0,0,0,9.81"], gt=True))
    gt = rec.ground_truth()
    assert gt is not None and len(gt) == 3
    np.testing.assert_allclose(np.asarray(gt.positions)[:, 0], [0, 1, 2])
    np.testing.assert_allclose(gt.timestamps, [1e-6, 1.001e-6, 1.002e-6])


def test_euroc_bad_csv_names_file_and_line(tmp_path):
    path = _tiny_euroc(tmp_path, ["1000,0,0,0,0,0,9.81", "2000,0,0"])
    with pytest.raises(InputFormatError, match=r"imu0/data.csv:3: .*7 fields"):
        open_recording(path)


def test_euroc_missing_camera_lists_available(tmp_path):
    path = _tiny_euroc(tmp_path, ["1000,0,0,0,0,0,9.81"])
    with pytest.raises(InputFormatError, match=r"no camera \['cam1'\]; available: \[\]"):
        open_recording(path, cameras=["cam1"])


def test_registry_guesses_and_rejects(tmp_path):
    assert recording_formats() == ["ros1", "ros2", "euroc", "kitti"]
    (tmp_path / "notes.txt").write_text("hello")
    with pytest.raises(InputFormatError, match=r"notes.txt: not a known recording; formats: ros1"):
        open_recording(tmp_path / "notes.txt")
    with pytest.raises(InputFormatError, match="no such file"):
        open_recording(tmp_path / "missing.bag")
    with pytest.raises(InputFormatError, match="unknown recording format 'tum'"):
        open_recording(tmp_path, fmt="tum")
    with pytest.raises(InputFormatError, match="formats: ros1"):
        open_recording(tmp_path)  # an empty folder


@pytest.mark.skipif(not ROSBAG.is_dir(), reason="shared rosbag data not present")
def test_registry_guesses_each_bag_kind(tmp_path):
    from jaxslam.io import RosbagRecording

    for name in ("ROS_example.bag", "tf_example_ros2", "nav2_turtlebot.mcap", "tf_example_ros2/tf_example.db3"):
        assert isinstance(open_recording(ROSBAG / name), RosbagRecording), name
    shutil.copytree(EUROC / "mav0" / "imu0", tmp_path / "mav0" / "imu0")
    assert isinstance(open_recording(tmp_path / "mav0"), EurocRecording)

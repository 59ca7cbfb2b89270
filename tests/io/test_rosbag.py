"""The rosbag reader: the real evo fixture bags, round trips through bags written with
rosbags' writer (ROS1 and ROS2), and bad input (not a bag, truncated, NaN, time reversal,
missing topics)."""

from __future__ import annotations

import io
import shutil
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from rosbags.rosbag1 import Writer as Writer1
from rosbags.rosbag2 import StoragePlugin
from rosbags.rosbag2 import Writer as Writer2

from jaxslam.errors import InputFormatError
from jaxslam.io import RosbagRecording, Trajectory, open_recording
from jaxslam.io._rosbag import default_typestore
from jaxslam.measurements import Image, ImuSample, LidarScan, PoseStamped

ROSBAG = Path(__file__).resolve().parents[2] / ".." / "shared" / "data" / "rosbag"
needs_data = pytest.mark.skipif(not ROSBAG.is_dir(), reason="shared rosbag data not present")

T0 = 1_700_000_000_000_000_000  # ns


# --- the real fixture bags ----------------------------------------------------------------------


@needs_data
@pytest.mark.parametrize(
    ("name", "options", "kinds", "count"),
    [
        ("ROS_example.bag", {}, {"pose"}, 12765),
        ("tf_example.bag", {}, set(), 0),
        ("tf_example.bag", {"tf": ("odom", "base_footprint")}, {"pose"}, 517),
        ("tf_example_ros2", {}, set(), 0),
        ("tf_example_ros2", {"tf": ("/odom", "base_footprint")}, {"pose"}, 517),
        ("nav2_turtlebot.mcap", {}, {"pose"}, 2639),
    ],
)
def test_real_bags_list_streams_and_iterate(name, options, kinds, count):
    rec = open_recording(ROSBAG / name, **options)
    streams = rec.streams()
    assert {s.kind for s in streams} == kinds
    records = list(rec)
    assert len(records) == count and not rec.skipped
    assert all(isinstance(r, PoseStamped) for r in records)
    assert np.all(np.diff([r.t for r in records]) >= 0)
    if streams:
        assert streams[0].count == count
        assert streams[0].t_start <= streams[0].t_end


@needs_data
def test_ros_example_guesses_groundtruth_and_says_so():
    rec = open_recording(ROSBAG / "ROS_example.bag")
    (s,) = rec.streams()
    assert s.topic == "groundtruth" and s.msgtype == "geometry_msgs/msg/PoseStamped"
    assert "guessed among ['ORB-SLAM', 'S-PTAM', 'groundtruth']" in s.note
    gt = rec.ground_truth()
    assert isinstance(gt, Trajectory) and len(gt) == 12765
    assert np.all(np.diff(gt.timestamps) > 0)
    q = np.asarray(gt.poses.params)[:, :4]
    np.testing.assert_allclose(np.linalg.norm(q, axis=1), 1.0, atol=1e-12)
    orb = open_recording(ROSBAG / "ROS_example.bag", topics={"pose": "ORB-SLAM"})
    assert orb.streams()[0].note == "chosen by option" and len(list(orb)) == 8362


@needs_data
def test_nav2_odometry_and_no_ground_truth():
    rec = open_recording(ROSBAG / "nav2_turtlebot.mcap", topics={"pose": "/amcl_pose"})
    assert len(list(rec)) == 135
    assert rec.ground_truth() is None
    assert len(open_recording(ROSBAG / "nav2_turtlebot.mcap", ground_truth="/odom").ground_truth()) == 2639


@needs_data
def test_receive_time_option():
    rec = open_recording(ROSBAG / "ROS_example.bag", time="receive")
    t = [r.t for r in rec]
    assert len(t) == 12765 and t[0] == pytest.approx(rec.streams()[0].t_start)


@needs_data
def test_missing_topic_lists_available():
    with pytest.raises(InputFormatError, match=r"no topic '/imu' for imu; topics: ORB-SLAM \(geometry_msgs"):
        open_recording(ROSBAG / "ROS_example.bag", topics={"imu": "/imu"})
    with pytest.raises(InputFormatError, match="not a imu type"):
        open_recording(ROSBAG / "ROS_example.bag", topics={"imu": "groundtruth"})
    with pytest.raises(ValueError, match="topics keys"):
        open_recording(ROSBAG / "ROS_example.bag", topics={"gps": "groundtruth"})
    with pytest.raises(InputFormatError, match="no TF topic"):
        open_recording(ROSBAG / "ROS_example.bag", tf=("map", "base"))


# --- bad files --------------------------------------------------------------------------------


def test_not_a_bag(tmp_path):
    for name in ("junk.bag", "junk.mcap", "junk.db3"):
        (tmp_path / name).write_bytes(b"this is not a bag at all\n" * 10)
        with pytest.raises(InputFormatError, match=rf"{name}: cannot read bag"):
            open_recording(tmp_path / name)


@needs_data
def test_truncated_ros1_bag_names_file(tmp_path):
    data = (ROSBAG / "ROS_example.bag").read_bytes()
    (tmp_path / "cut.bag").write_bytes(data[: len(data) // 2])
    # cut short, its index position points past the end: named as unindexed, with the repair
    with pytest.raises(InputFormatError, match=r"cut.bag: ROS1 bag has no index.*reindex"):
        list(open_recording(tmp_path / "cut.bag"))


@needs_data
def test_truncated_mcap_names_file(tmp_path):
    # rosbags needs the MCAP footer/summary, so a cut file is refused rather than recovered
    data = (ROSBAG / "nav2_turtlebot.mcap").read_bytes()
    (tmp_path / "cut.mcap").write_bytes(data[: len(data) // 2])
    with pytest.raises(InputFormatError, match=r"cut.mcap: cannot read bag"):
        list(open_recording(tmp_path / "cut.mcap"))


@needs_data
def test_read_error_mid_bag_keeps_earlier_records_with_a_warning(monkeypatch):
    from rosbags.highlevel import AnyReader, AnyReaderError

    real = AnyReader.messages

    def failing(self, *args, **kwargs):
        for k, item in enumerate(real(self, *args, **kwargs)):
            if k == 100:
                raise AnyReaderError("chunk 7 is damaged")
            yield item

    rec = open_recording(ROSBAG / "ROS_example.bag")
    monkeypatch.setattr(AnyReader, "messages", failing)
    with pytest.warns(UserWarning, match=r"ROS_example.bag: read stopped after 100 messages: chunk 7"):
        records = list(rec)
    assert len(records) == 100 and rec.skipped == {"bag: unreadable remainder": 1}


# --- round trips through written bags -----------------------------------------------------------


class _Bag:
    """Write messages into a ROS1 or ROS2 bag with rosbags' writer (test helper)."""

    def __init__(self, path: Path, ros1: bool):
        self.ros1 = ros1
        self.store = default_typestore(ros1)
        self.w: Any = Writer1(path) if ros1 else Writer2(path, version=9, storage_plugin=StoragePlugin.MCAP)
        self.w.open()
        self.conns: dict[str, Any] = {}

    def T(self, name: str) -> Any:
        return self.store.types[name]

    def header(self, ns: int) -> Any:
        stamp = self.T("builtin_interfaces/msg/Time")(sec=ns // 10**9, nanosec=ns % 10**9)
        H = self.T("std_msgs/msg/Header")
        return H(seq=0, stamp=stamp, frame_id="f") if self.ros1 else H(stamp=stamp, frame_id="f")

    def write(self, topic: str, msgtype: str, msg: Any, t_recv: int) -> None:
        if topic not in self.conns:
            self.conns[topic] = self.w.add_connection(topic, msgtype, typestore=self.store)
        ser = self.store.serialize_ros1 if self.ros1 else self.store.serialize_cdr
        self.w.write(self.conns[topic], t_recv, ser(msg, msgtype))

    def close(self) -> None:
        self.w.close()

    # message builders
    def imu(self, ns: int, acc, gyro) -> Any:
        V = self.T("geometry_msgs/msg/Vector3")
        Q = self.T("geometry_msgs/msg/Quaternion")
        z9 = np.zeros(9)
        return self.T("sensor_msgs/msg/Imu")(
            header=self.header(ns),
            orientation=Q(x=0.0, y=0.0, z=0.0, w=1.0),
            orientation_covariance=z9,
            angular_velocity=V(x=gyro[0], y=gyro[1], z=gyro[2]),
            angular_velocity_covariance=z9,
            linear_acceleration=V(x=acc[0], y=acc[1], z=acc[2]),
            linear_acceleration_covariance=z9,
        )

    def image(self, ns: int, px: np.ndarray, encoding: str) -> Any:
        h, w = px.shape[:2]
        data = np.ascontiguousarray(px).view(np.uint8).reshape(-1)
        return self.T("sensor_msgs/msg/Image")(
            header=self.header(ns),
            height=h,
            width=w,
            encoding=encoding,
            is_bigendian=0,
            step=data.size // h,
            data=data,
        )

    def compressed(self, ns: int, png: bytes, fmt: str = "png") -> Any:
        return self.T("sensor_msgs/msg/CompressedImage")(
            header=self.header(ns), format=fmt, data=np.frombuffer(png, dtype=np.uint8)
        )

    def cloud(self, ns: int, arr: np.ndarray) -> Any:
        F = self.T("sensor_msgs/msg/PointField")
        codes = {"f4": 7, "f8": 8, "u4": 6, "u2": 4}
        fields = [
            F(name=n, offset=arr.dtype.fields[n][1], datatype=codes[arr.dtype.fields[n][0].str[1:]], count=1)
            for n in arr.dtype.names
        ]
        return self.T("sensor_msgs/msg/PointCloud2")(
            header=self.header(ns),
            height=1,
            width=len(arr),
            fields=fields,
            is_bigendian=False,
            point_step=arr.dtype.itemsize,
            row_step=arr.dtype.itemsize * len(arr),
            data=arr.view(np.uint8).reshape(-1).copy(),
            is_dense=True,
        )

    def livox(self, ns: int, pts: np.ndarray, refl: np.ndarray, off: np.ndarray) -> Any:
        P = self.T("livox_ros_driver2/msg/CustomPoint")
        points = [
            P(offset_time=int(o), x=float(p[0]), y=float(p[1]), z=float(p[2]), reflectivity=int(r), tag=0, line=0)
            for p, r, o in zip(pts, refl, off)
        ]
        return self.T("livox_ros_driver2/msg/CustomMsg")(
            header=self.header(ns),
            timebase=ns,
            point_num=len(points),
            lidar_id=0,
            rsvd=np.zeros(3, dtype=np.uint8),
            points=points,
        )


def _png(px: np.ndarray) -> bytes:
    from PIL import Image as PILImage

    buf = io.BytesIO()
    PILImage.fromarray(px).save(buf, format="PNG")
    return buf.getvalue()


@pytest.mark.parametrize("ros1", [True, False], ids=["ros1", "ros2-mcap"])
def test_round_trip_imu_image_cloud_livox(tmp_path, ros1):
    rng = np.random.default_rng(0)
    path = tmp_path / ("r.bag" if ros1 else "r2")
    bag = _Bag(path, ros1)
    acc, gyro = rng.normal(size=(5, 3)), rng.normal(size=(5, 3))
    for i in range(5):  # 100 Hz IMU
        ns = T0 + i * 10_000_000
        bag.write("/imu", "sensor_msgs/msg/Imu", bag.imu(ns, acc[i], gyro[i]), ns + 1000)
    grey = rng.integers(0, 255, (4, 6), dtype=np.uint8)
    rgb = rng.integers(0, 255, (4, 6, 3), dtype=np.uint8)
    mono16 = rng.integers(0, 65535, (4, 6), dtype=np.uint16)
    frames = [(grey, "mono8"), (rgb, "rgb8"), (rgb[..., ::-1], "bgr8"), (mono16, "mono16")]
    for k, (px, enc) in enumerate(frames):
        ns = T0 + 5_000_000 + k * 10_000_000
        bag.write("/cam", "sensor_msgs/msg/Image", bag.image(ns, px, enc), ns + 2000)
    bag.write("/cam/compressed", "sensor_msgs/msg/CompressedImage", bag.compressed(T0, _png(rgb)), T0)
    dt = np.dtype({"names": ["x", "y", "z", "intensity", "t"], "formats": ["f4", "f4", "f4", "f4", "u4"]})
    cloud = np.zeros(7, dtype=dt)
    for n in ("x", "y", "z", "intensity"):
        cloud[n] = rng.normal(size=7)
    cloud["t"] = np.arange(7) * 1_000_000
    bag.write("/points", "sensor_msgs/msg/PointCloud2", bag.cloud(T0 + 1_000_000, cloud), T0 + 9_000_000)
    lpts = rng.normal(size=(6, 3)).astype(np.float32)
    refl, off = np.arange(6, dtype=np.uint8) * 10, np.arange(6) * 500_000
    bag.write("/livox", "livox_ros_driver2/msg/CustomMsg", bag.livox(T0 + 2_000_000, lpts, refl, off), T0 + 3_000_000)
    bag.close()

    rec = open_recording(path)
    assert isinstance(rec, RosbagRecording)
    streams = {s.kind: s for s in rec.streams()}
    assert streams["imu"].topic == "/imu" and streams["imu"].count == 5
    assert streams["image"].topic == "/cam"  # the topic with more messages
    assert "guessed among ['/cam', '/cam/compressed']" in streams["image"].note
    assert streams["lidar"].topic in ("/livox", "/points")
    records = list(rec)
    assert not rec.skipped
    assert np.all(np.diff([r.t for r in records]) >= 0)
    imu = [r for r in records if isinstance(r, ImuSample)]
    np.testing.assert_array_equal(np.stack([r.acc for r in imu]), acc)
    np.testing.assert_array_equal(np.stack([r.gyro for r in imu]), gyro)
    assert [r.t for r in imu] == [(T0 + i * 10_000_000) / 1e9 for i in range(5)]
    images = [r for r in records if isinstance(r, Image)]
    np.testing.assert_array_equal(images[0].data, grey)
    np.testing.assert_array_equal(images[1].data, rgb)
    np.testing.assert_array_equal(images[2].data, rgb)  # bgr8 -> RGB
    np.testing.assert_allclose(images[3].data, mono16 / 65535.0, rtol=1e-6)
    assert images[3].data.dtype == np.float32 and images[0].camera == "/cam"

    comp = list(open_recording(path, topics={"image": "/cam/compressed"}))
    np.testing.assert_array_equal(next(r.data for r in comp if isinstance(r, Image)), rgb)

    (scan,) = [r for r in open_recording(path, topics={"lidar": "/points"}) if isinstance(r, LidarScan)]
    assert scan.t == (T0 + 1_000_000) / 1e9
    np.testing.assert_array_equal(scan.points, np.stack([cloud["x"], cloud["y"], cloud["z"]], axis=1))
    np.testing.assert_array_equal(scan.intensity, cloud["intensity"])
    np.testing.assert_allclose(scan.point_times, np.arange(7) * 1e-3)

    (lv,) = [r for r in open_recording(path, topics={"lidar": "/livox"}) if isinstance(r, LidarScan)]
    assert lv.t == (T0 + 2_000_000) / 1e9
    np.testing.assert_array_equal(lv.points, lpts)
    np.testing.assert_array_equal(lv.intensity, refl)
    np.testing.assert_allclose(lv.point_times, off / 1e9)


def test_cloud_time_fields_units_and_nan_points(tmp_path):
    path = tmp_path / "c.bag"
    bag = _Bag(path, ros1=True)
    dt = np.dtype({"names": ["x", "y", "z", "time", "ring"], "formats": ["f4", "f4", "f4", "f4", "u2"]})
    arr = np.zeros(4, dtype=dt)
    arr["x"] = [1, np.nan, 3, 4]
    arr["time"] = [0.0, 0.01, 0.02, 0.03]  # Velodyne: float seconds
    arr["ring"] = [0, 1, 2, 3]
    bag.write("/velodyne_points", "sensor_msgs/msg/PointCloud2", bag.cloud(T0, arr), T0)
    dt2 = np.dtype({"names": ["x", "y", "z", "timestamp"], "formats": ["f4", "f4", "f4", "f8"]})
    arr2 = np.zeros(2, dtype=dt2)
    arr2["timestamp"] = [T0 / 1e9 + 1.0, T0 / 1e9 + 1.05]  # Hesai: absolute seconds
    bag.write("/hesai", "sensor_msgs/msg/PointCloud2", bag.cloud(T0 + 10**9, arr2), T0 + 10**9)
    bag.close()
    (v,) = list(open_recording(path, topics={"lidar": "/velodyne_points"}))
    assert isinstance(v, LidarScan) and v.points.shape == (3, 3)  # the NaN point is dropped
    np.testing.assert_allclose(v.point_times, [0.0, 0.02, 0.03], atol=1e-7)
    np.testing.assert_array_equal(v.ring, [0, 2, 3])
    np.testing.assert_array_equal(v.intensity, [0, 0, 0])
    (h,) = list(open_recording(path, topics={"lidar": "/hesai"}))
    np.testing.assert_allclose(h.point_times, [0.0, 0.05], atol=1e-6)


def test_nan_backwards_and_bad_encoding_are_skipped_and_counted(tmp_path):
    path = tmp_path / "bad.bag"
    bag = _Bag(path, ros1=True)
    stamps = [T0, T0 + 10**7, T0 + 2 * 10**7, T0 + 10**6, T0 + 3 * 10**7]  # 4th goes back
    for i, ns in enumerate(stamps):
        acc = [np.nan, 0, 0] if i == 1 else [0, 0, 9.81]
        bag.write("/imu", "sensor_msgs/msg/Imu", bag.imu(ns, acc, [0, 0, 0]), T0 + i * 10**7)
    # beyond the 1 s reorder window: a sample stamped 4 s before one already passed on
    bag.write("/imu", "sensor_msgs/msg/Imu", bag.imu(T0 + 5 * 10**9, [0, 0, 9.81], [0, 0, 0]), T0 + 10 * 10**9)
    bag.write("/imu", "sensor_msgs/msg/Imu", bag.imu(T0 + 10**9, [0, 0, 9.81], [0, 0, 0]), T0 + 11 * 10**9)
    bag.write("/cam", "sensor_msgs/msg/Image", bag.image(T0, np.zeros((2, 2, 4), np.uint8), "rgba8"), T0)
    bag.write("/cam", "sensor_msgs/msg/Image", bag.image(T0, np.zeros((2, 2), np.uint8), "mono8"), T0)
    bag.write("/cam/compressed", "sensor_msgs/msg/CompressedImage", bag.compressed(T0, b"not a png"), T0)
    short = bag.cloud(T0, np.zeros(4, dtype=np.dtype({"names": ["x", "y", "z"], "formats": ["f4"] * 3})))
    short.width = 40  # says 40 points, carries 4
    bag.write("/points", "sensor_msgs/msg/PointCloud2", short, T0)
    bag.close()

    rec = open_recording(path)
    records = list(rec)
    imu_t = [r.t for r in records if isinstance(r, ImuSample)]
    # the sample stamped T0 + 1 ms arrives 30 ms late but within the window: re-ordered, kept
    assert imu_t == [s / 1e9 for s in (T0, T0 + 10**6, T0 + 2 * 10**7, T0 + 3 * 10**7, T0 + 5 * 10**9)]
    assert rec.skipped == {
        "/imu: invalid (NaN or shape)": 1,
        "/imu: time not increasing": 1,
        "/cam: unsupported image encoding": 1,
        "/points: malformed message": 1,
    }
    rec2 = open_recording(path, topics={"image": "/cam/compressed"})
    assert not [r for r in rec2 if isinstance(r, Image)]
    assert rec2.skipped["/cam/compressed: unsupported image encoding"] == 1


def test_ros2_sqlite_written_bag_and_folder_guess(tmp_path):
    path = tmp_path / "sq"
    bag = _Bag.__new__(_Bag)
    bag.ros1, bag.store, bag.conns = False, default_typestore(False), {}
    bag.w = Writer2(path, version=9, storage_plugin=StoragePlugin.SQLITE3)
    bag.w.open()
    for i in range(3):
        ns = T0 + i * 5_000_000
        bag.write("/imu", "sensor_msgs/msg/Imu", bag.imu(ns, [0, 0, 9.81], [0.1, 0, 0]), ns)
    bag.close()
    rec = open_recording(path)
    assert [s.kind for s in rec.streams()] == ["imu"] and len(list(rec)) == 3
    db3 = next(path.glob("*.db3"))
    shutil.copy(db3, tmp_path / "alone.db3")
    assert len(list(open_recording(tmp_path / "alone.db3"))) == 3

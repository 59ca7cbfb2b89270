"""Total-station fixes in bags: geometry_msgs/PointStamped (sigma in frame_id) -> PositionFix,
written by the writers (ROS1, ROS2 mcap and sqlite3) and read back equal; topic choice,
bad sigma, and the hint for an unindexed (killed) ROS1 bag."""

from __future__ import annotations

import numpy as np
import pytest
from rosbags.rosbag1 import Writer as Writer1

from jaxslam.errors import InputFormatError
from jaxslam.io import RosbagRecording, open_recording, open_writer
from jaxslam.io._rosbag import DEFAULT_FIX_SIGMA, default_typestore, fix_sigma
from jaxslam.measurements import ImuSample, PositionFix

T0_NS = 1_700_000_000_000_000_000


def _fixes(n: int = 12) -> list[PositionFix]:
    rng = np.random.default_rng(5)
    return [
        PositionFix((T0_NS + k * 250_000_000) / 1e9, rng.normal(size=3) * 10, float(rng.uniform(0.001, 0.01)))
        for k in range(n)
    ]


@pytest.mark.parametrize(("fmt", "name"), [("bag", "r.bag"), ("bag2", "r2"), ("bag2-db3", "r3")])
def test_position_fixes_round_trip(tmp_path, fmt, name):
    fixes = _fixes()
    imu = [ImuSample((T0_NS + k * 100_000_000) / 1e9, np.ones(3) * k, np.zeros(3)) for k in range(30)]
    with open_writer(tmp_path / name, fmt) as w:
        w.write_all(sorted([*fixes, *imu], key=lambda r: r.t))
    rec = open_recording(tmp_path / name)
    streams = {s.kind: s for s in rec.streams()}
    assert streams["position"].topic == "/total_station/prism"
    assert streams["position"].msgtype == "geometry_msgs/msg/PointStamped" and streams["position"].count == 12
    back = [r for r in rec if isinstance(r, PositionFix)]
    assert not rec.skipped and len(back) == len(fixes)
    for a, b in zip(fixes, back):
        assert a.t == b.t and a.sigma == b.sigma
        np.testing.assert_array_equal(a.xyz, b.xyz)
        b.validate()


def _point_bag(path, topics: dict[str, list[tuple[int, str]]]) -> None:
    """A ROS1 bag with PointStamped messages: topic -> [(ns, frame_id)]."""
    store = default_typestore(ros1=True)
    T = store.types
    with Writer1(path) as w:
        for topic, msgs in topics.items():
            conn = w.add_connection(topic, "geometry_msgs/msg/PointStamped", typestore=store)
            for k, (ns, frame) in enumerate(msgs):
                header = T["std_msgs/msg/Header"](
                    seq=k, stamp=T["builtin_interfaces/msg/Time"](sec=ns // 10**9, nanosec=ns % 10**9), frame_id=frame
                )
                msg = T["geometry_msgs/msg/PointStamped"](
                    header=header, point=T["geometry_msgs/msg/Point"](x=1.0 * k, y=2.0, z=3.0)
                )
                w.write(conn, ns, store.serialize_ros1(msg, "geometry_msgs/msg/PointStamped"))


def test_sigma_parsing_and_bad_sigma_counted(tmp_path):
    assert fix_sigma("world;sigma=0.004") == 0.004
    assert fix_sigma("sigma=2e-3") == 0.002
    assert fix_sigma("world") == DEFAULT_FIX_SIGMA == 0.005
    for bad in ("world;sigma=abc", "sigma=-1", "sigma=nan", "sigma=0", "sigma="):
        with pytest.raises(InputFormatError, match="sigma"):
            fix_sigma(bad)
    frames = ["world;sigma=0.002", "world", "world;sigma=oops", "world;sigma=-3", "prism;sigma=0.01"]
    _point_bag(tmp_path / "p.bag", {"/total_station/prism": [(T0_NS + k * 10**8, f) for k, f in enumerate(frames)]})
    rec = open_recording(tmp_path / "p.bag")
    back = list(rec)
    assert [r.sigma for r in back] == [0.002, 0.005, 0.01]
    assert [r.xyz[0] for r in back] == [0.0, 1.0, 4.0]
    assert rec.skipped["/total_station/prism: bad sigma in frame_id"] == 2


def test_position_topic_guessed_by_name_then_chosen_by_option(tmp_path):
    many = [(T0_NS + k * 10**8, "map") for k in range(5)]
    few = [(T0_NS + k * 10**8, "world;sigma=0.003") for k in range(2)]
    _point_bag(tmp_path / "g.bag", {"/clicked_point": many, "/survey/prism": few})
    rec = open_recording(tmp_path / "g.bag")
    (s,) = rec.streams()
    assert s.topic == "/survey/prism" and "total-station name" in s.note
    assert len(list(rec)) == 2
    rec2 = RosbagRecording(tmp_path / "g.bag", topics={"position": "/clicked_point"})
    assert rec2.streams()[0].note == "chosen by option" and len(list(rec2)) == 5
    with pytest.raises(InputFormatError, match="not a imu type"):
        RosbagRecording(tmp_path / "g.bag", topics={"imu": "/survey/prism"})
    with pytest.raises(InputFormatError, match="no topic '/nope' for position"):
        RosbagRecording(tmp_path / "g.bag", topics={"position": "/nope"})


def test_unindexed_ros1_bag_says_how_to_repair(tmp_path):
    store = default_typestore(ros1=True)
    w = Writer1(tmp_path / "killed.bag")
    w.open()
    conn = w.add_connection("/imu/data", "std_msgs/msg/String", typestore=store)
    w.write(conn, T0_NS, store.serialize_ros1(store.types["std_msgs/msg/String"](data="x"), "std_msgs/msg/String"))
    w.write_chunk(w.chunks[-1])
    w.abort()  # no index written: what SIGKILL leaves
    with pytest.raises(InputFormatError, match=r"no index .* drivers\.record reindex"):
        open_recording(tmp_path / "killed.bag")

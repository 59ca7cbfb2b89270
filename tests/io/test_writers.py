"""Writers: records -> ROS1 bag, ROS2 bag (mcap, sqlite3), EuRoC folder -> open_recording gives
the same records back; PLY/PCD point maps round-trip."""

from __future__ import annotations

import numpy as np
import pytest

from jaxslam.errors import InputFormatError
from jaxslam.io import open_recording, open_writer, read_pcd, read_ply, write_pcd, write_ply
from jaxslam.measurements import Image, ImuSample, LidarScan, PoseStamped, PositionFix

T0_NS = 1_700_000_000_000_000_000
T0 = T0_NS / 1e9


def _t(offset_s: float) -> float:
    """A stamp that is exactly an integer number of ns (as every reader returns)."""
    return (T0_NS + round(offset_s * 1e9)) / 1e9


def _records(ring: bool):
    rng = np.random.default_rng(1)
    recs = []
    for i in range(20):  # 100 Hz IMU
        recs.append(ImuSample(_t(i * 0.01), rng.normal(size=3), rng.normal(size=3)))
    for i in range(3):
        t0 = 0.005 + i * 0.05
        t = _t(t0)
        recs.append(Image(t, rng.integers(0, 255, (6, 8), dtype=np.uint8), camera="cam0"))
        n = 50
        pts = rng.normal(size=(n, 3)).astype(np.float32).astype(np.float64)
        inten = rng.integers(0, 255, n).astype(np.float64)
        times = np.sort(rng.integers(0, 100_000_000, n)) / 1e9
        recs.append(LidarScan(_t(t0 + 0.001), pts, inten, times, np.arange(n) % 16 if ring else None))
        q = rng.normal(size=4)
        recs.append(PoseStamped(_t(t0 + 0.002), np.concatenate([q / np.linalg.norm(q), rng.normal(size=3)])))
        recs.append(PositionFix(_t(t0 + 0.003), rng.normal(size=3), 0.004))
    return sorted(recs, key=lambda r: r.t)


def _equal(a, b) -> None:
    assert type(a) is type(b) and a.t == b.t
    if isinstance(a, ImuSample):
        np.testing.assert_array_equal(a.acc, b.acc)
        np.testing.assert_array_equal(a.gyro, b.gyro)
    elif isinstance(a, Image):
        np.testing.assert_array_equal(a.data, b.data)
    elif isinstance(a, LidarScan):
        np.testing.assert_array_equal(a.points, b.points)
        np.testing.assert_array_equal(a.intensity, b.intensity)
        np.testing.assert_allclose(a.point_times, b.point_times, atol=1e-9)
        assert (a.ring is None) == (b.ring is None)
        if a.ring is not None:
            np.testing.assert_array_equal(a.ring, b.ring)
    elif isinstance(a, PoseStamped):
        np.testing.assert_array_equal(a.pose, b.pose)
    else:
        np.testing.assert_array_equal(a.xyz, b.xyz)
        assert a.sigma == b.sigma


@pytest.mark.parametrize("ring", [False, True], ids=["hap", "ring"])
@pytest.mark.parametrize(("fmt", "name"), [("bag", "r.bag"), ("bag2", "r2"), ("bag2-db3", "r3"), ("euroc", "re")])
def test_write_then_read_gives_equal_records(tmp_path, fmt, name, ring):
    recs = _records(ring)
    with open_writer(tmp_path / name, fmt) as w:
        w.write_all(recs)
    rec = open_recording(tmp_path / name)
    back = list(rec)
    assert not rec.skipped
    if fmt == "euroc":  # ground truth via ground_truth(), fixes as records
        want = [r for r in recs if not isinstance(r, PoseStamped)]
        poses = [r for r in recs if isinstance(r, PoseStamped)]
        gt = rec.ground_truth()
        np.testing.assert_array_equal(gt.timestamps, [p.t for p in poses])
        np.testing.assert_allclose(np.asarray(gt.poses.params), np.stack([p.pose for p in poses]), atol=1e-15)
    else:  # bags: every record, fixes included (PointStamped -> PositionFix)
        want = recs
    assert len(back) == len(want)
    for a, b in zip(want, back):
        _equal(a, b)
    if fmt != "euroc":
        from rosbags.highlevel import AnyReader

        with AnyReader([tmp_path / name]) as reader:
            conns = [c for c in reader.connections if c.topic == "/total_station/prism"]
            msgs = [reader.deserialize(raw, c.msgtype) for c, _, raw in reader.messages(connections=conns)]
        fixes = [r for r in recs if isinstance(r, PositionFix)]
        assert len(msgs) == len(fixes)
        for m, f in zip(msgs, fixes):
            np.testing.assert_array_equal([m.point.x, m.point.y, m.point.z], f.xyz)
            assert m.header.frame_id.endswith(f"sigma={f.sigma!r}")


def test_bag_writer_refuses_to_overwrite_and_unknown_format(tmp_path):
    (tmp_path / "x.bag").write_bytes(b"")
    with pytest.raises(InputFormatError, match="overwrite"):
        open_writer(tmp_path / "x.bag", "bag")
    with pytest.raises(ValueError, match="format must be"):
        open_writer(tmp_path / "y", "zip")


def test_mono16_and_rgb_images_round_trip(tmp_path):
    rng = np.random.default_rng(2)
    rgb = rng.integers(0, 255, (4, 5, 3), dtype=np.uint8)
    grey16 = (rng.integers(0, 65535, (4, 5)) / 65535.0).astype(np.float32)
    for fmt, ext in (("bag", ".bag"), ("euroc", "")):
        for k, px in enumerate((rgb, grey16)):  # the bag reader takes one image topic
            name = f"{fmt}{k}{ext}"
            with open_writer(tmp_path / name, fmt) as w:
                w.write(ImuSample(T0, np.zeros(3), np.zeros(3)))
                w.write(Image(T0 + 0.1, px, camera="cam0"))
            (img,) = [r.data for r in open_recording(tmp_path / name) if isinstance(r, Image)]
            if px.dtype == np.uint8:
                np.testing.assert_array_equal(img, px)
            else:
                np.testing.assert_allclose(img, px, atol=1e-6)


@pytest.mark.parametrize("binary", [True, False])
@pytest.mark.parametrize("with_intensity", [True, False])
def test_point_maps_round_trip(tmp_path, binary, with_intensity):
    rng = np.random.default_rng(3)
    pts = rng.normal(size=(100, 3)) * 10
    inten = rng.random(100).astype(np.float32).astype(np.float64) if with_intensity else None
    for write, read, ext in ((write_ply, read_ply, "ply"), (write_pcd, read_pcd, "pcd")):
        path = tmp_path / f"m.{ext}"
        write(path, pts, inten, binary=binary)
        p2, i2 = read(path)
        np.testing.assert_array_equal(p2, pts)
        if with_intensity:
            np.testing.assert_array_equal(i2, inten)
        else:
            assert i2 is None


def test_ply_from_another_tool_keeps_its_intensity():
    """CloudCompare names the field ``scalar_intensity`` (the real scan pair in shared/data)."""
    from pathlib import Path

    path = Path(__file__).resolve().parents[2] / ".." / "shared" / "data" / "lidar" / "source.ply"
    if not path.exists():
        pytest.skip("shared/data/lidar is not beside the checkout")
    assert b"scalar_intensity" in path.read_bytes()[:1000]
    pts, inten = read_ply(path)
    assert inten is not None and inten.shape == (len(pts),) and inten.min() >= 0 and inten.max() <= 255
    assert len(np.unique(inten)) > 50


def test_point_map_readers_reject_bad_files(tmp_path):
    (tmp_path / "bad.ply").write_bytes(b"not a ply")
    with pytest.raises(InputFormatError, match="not a PLY"):
        read_ply(tmp_path / "bad.ply")
    write_ply(tmp_path / "cut.ply", np.zeros((10, 3)))
    data = (tmp_path / "cut.ply").read_bytes()
    (tmp_path / "cut.ply").write_bytes(data[:-20])
    with pytest.raises(InputFormatError, match="of 10 vertices"):
        read_ply(tmp_path / "cut.ply")
    (tmp_path / "bad.pcd").write_bytes(b"VERSION 0.7\n")
    with pytest.raises(InputFormatError, match="DATA"):
        read_pcd(tmp_path / "bad.pcd")
    with pytest.raises(ValueError, match=r"shape \(N, 3\)"):
        write_ply(tmp_path / "x.ply", np.zeros((3, 2)))

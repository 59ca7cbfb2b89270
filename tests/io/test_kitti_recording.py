"""KITTI odometry folders as recordings: the real kitti_mono frames, a synthetic sequence with
velodyne scans and times.txt, and bad input."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from PIL import Image as PILImage

from jaxslam.errors import InputFormatError
from jaxslam.io import KittiRecording, open_recording, read_kitti
from jaxslam.measurements import Image, LidarScan

KITTI = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "kitti_mono"


def test_reads_the_shared_kitti_frames_and_ground_truth() -> None:
    rec = open_recording(KITTI)
    assert isinstance(rec, KittiRecording)
    (cam,) = rec.streams()
    n = len(list((KITTI / "image_l").glob("*.png")))
    assert cam.kind == "image" and cam.count == n and cam.note == "frame / 10 Hz"
    images = list(rec)
    assert len(images) == n and all(isinstance(r, Image) for r in images)
    assert images[0].data.shape == (376, 1241) and images[0].data.dtype == np.uint8
    np.testing.assert_allclose([r.t for r in images], np.arange(n) / 10.0)
    first = np.asarray(PILImage.open(sorted((KITTI / "image_l").glob("*.png"))[0]))
    np.testing.assert_array_equal(images[0].data, first)
    gt = rec.ground_truth()
    ref = read_kitti(KITTI / "poses.txt")
    np.testing.assert_allclose(np.asarray(gt.poses.params), np.asarray(ref.poses.params))
    np.testing.assert_allclose(gt.timestamps, np.arange(len(ref.timestamps)) / 10.0)


def _sequence(root: Path, frames: int = 3) -> np.ndarray:
    rng = np.random.default_rng(0)
    (root / "image_0").mkdir(parents=True)
    (root / "velodyne").mkdir()
    for k in range(frames):
        PILImage.fromarray(rng.integers(0, 255, (8, 10), dtype=np.uint8)).save(root / "image_0" / f"{k:06d}.png")
        rng.normal(size=(5 + k, 4)).astype(np.float32).tofile(root / "velodyne" / f"{k:06d}.bin")
    times = np.array([0.0, 0.1037, 0.2075, 0.31])[:frames]
    np.savetxt(root / "times.txt", times)
    return times


def test_synthetic_sequence_with_velodyne_and_times(tmp_path: Path) -> None:
    times = _sequence(tmp_path)
    rec = open_recording(tmp_path)
    kinds = {s.topic: s for s in rec.streams()}
    assert kinds["cam0"].count == 3 and kinds["velodyne"].count == 3 and kinds["velodyne"].note == "times.txt"
    recs = list(rec)
    scans = [r for r in recs if isinstance(r, LidarScan)]
    assert [s.points.shape[0] for s in scans] == [5, 6, 7]
    raw = np.fromfile(tmp_path / "velodyne" / "000001.bin", dtype=np.float32).reshape(-1, 4)
    np.testing.assert_array_equal(scans[1].points, raw[:, :3].astype(np.float64))
    np.testing.assert_array_equal(scans[1].intensity, raw[:, 3].astype(np.float64))
    np.testing.assert_allclose([s.t for s in scans], times)
    assert rec.ground_truth() is None


def test_bad_kitti_input(tmp_path: Path) -> None:
    _sequence(tmp_path)
    # a truncated scan and an unreadable image are skipped and counted
    (tmp_path / "velodyne" / "000002.bin").write_bytes(b"\x00" * 6)
    (tmp_path / "image_0" / "000001.png").write_bytes(b"not a png")
    rec = open_recording(tmp_path)
    recs = list(rec)
    assert len(recs) == 4
    assert rec.skipped["velodyne: scan size not a multiple of 4 floats"] == 1
    assert rec.skipped["cam0: unreadable image"] == 1
    (tmp_path / "times.txt").write_text("0.0\n0.1\n")
    with pytest.raises(InputFormatError, match="2 lines for 3 frames"):
        KittiRecording(tmp_path)
    (tmp_path / "times.txt").write_text("0.0\nabc\n0.2\n")
    with pytest.raises(InputFormatError, match=r"times\.txt"):
        KittiRecording(tmp_path)
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(InputFormatError, match="no image_0"):
        KittiRecording(empty)

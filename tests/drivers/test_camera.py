"""Camera source without a camera: a folder of PNGs (exact pixels), a generated video file
(cv2.VideoWriter, lossy), pacing, bad files counted, missing sources raise DriverError."""

from __future__ import annotations

import time

import numpy as np
import pytest

cv2 = pytest.importorskip("cv2")

from drivers import DriverError  # noqa: E402
from drivers.camera import CameraSource  # noqa: E402
from jaxslam.errors import ConfigError, JaxSlamError  # noqa: E402
from jaxslam.measurements import Image  # noqa: E402


def _frames(n: int, h: int = 48, w: int = 64) -> list[np.ndarray]:
    """RGB frames with a block that moves and a per-frame colour (video-codec friendly)."""
    out = []
    for k in range(n):
        f = np.full((h, w, 3), (20, 40, 60), np.uint8)
        f[8:24, 4 * k : 4 * k + 16] = (200, 100 + 10 * k, 50)
        out.append(f)
    return out


def test_folder_of_pngs_exact_rgb_and_grey(tmp_path):
    frames = _frames(6)
    for k, f in enumerate(frames):
        cv2.imwrite(str(tmp_path / f"{k:04d}.png"), f[:, :, ::-1])  # OpenCV writes BGR
    (tmp_path / "0002b.png").write_bytes(b"not a png")  # counted, skipped
    (tmp_path / "notes.txt").write_text("ignored")
    clock = iter(range(100, 200))
    with CameraSource(tmp_path, camera="cam1", fps=0, clock=lambda: float(next(clock))) as cam:
        recs = list(cam.frames())
    assert len(recs) == 6 and cam.counters["bad_frames"] == 1 and cam.counters["frames"] == 6
    for rec, f in zip(recs, frames):
        assert isinstance(rec, Image) and rec.camera == "cam1"
        np.testing.assert_array_equal(rec.data, f)
        rec.validate()
    assert np.all(np.diff([r.t for r in recs]) > 0)
    grey = list(CameraSource(tmp_path, grey=True, fps=0).frames(max_frames=2))
    assert grey[0].data.shape == (48, 64) and grey[0].data.dtype == np.uint8
    np.testing.assert_array_equal(grey[0].data, cv2.cvtColor(frames[0][:, :, ::-1], cv2.COLOR_BGR2GRAY))


def test_sixteen_bit_png_is_float(tmp_path):
    px = (np.arange(12, dtype=np.uint16).reshape(3, 4) * 5000).astype(np.uint16)
    cv2.imwrite(str(tmp_path / "a.png"), px)
    (rec,) = CameraSource(tmp_path, fps=0).frames()
    assert rec.data.dtype == np.float32
    np.testing.assert_allclose(rec.data, px / 65535.0, rtol=1e-6)


def test_video_file_frames_and_pacing(tmp_path):
    frames = _frames(10)
    path = tmp_path / "v.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 20.0, (64, 48))
    assert writer.isOpened()
    for f in frames:
        writer.write(f[:, :, ::-1])
    writer.release()
    with CameraSource(path, fps=0) as cam:
        recs = list(cam.frames())
    assert len(recs) == 10
    for rec, f in zip(recs, frames):
        assert rec.data.shape == (48, 64, 3) and rec.data.dtype == np.uint8
        assert np.abs(rec.data.astype(int) - f).mean() < 6  # MJPG is lossy
    # Replayed at the file's rate (20 Hz): 10 frames take ~0.45 s; loop=True keeps going.
    t0 = time.monotonic()
    with CameraSource(path) as cam:
        assert cam.fps == pytest.approx(20.0)
        paced = list(cam.frames())
    assert len(paced) == 10 and 0.35 < time.monotonic() - t0 < 3.0
    with CameraSource(path, fps=0, loop=True) as cam:
        assert len(list(cam.frames(max_frames=25))) == 25
    with CameraSource(path, fps=100) as cam:
        assert 1 <= len(list(cam.frames(duration=0.05))) <= 8


def test_missing_sources_raise_driver_error(tmp_path):
    with pytest.raises(DriverError, match="no image files"):
        CameraSource(tmp_path)
    with pytest.raises(DriverError, match="not a device index"):
        CameraSource(tmp_path / "nope")
    (tmp_path / "junk.avi").write_bytes(b"\x00" * 100)
    with pytest.raises(DriverError, match="cannot open"):
        CameraSource(tmp_path / "junk.avi")
    with pytest.raises(DriverError, match="cannot open"):
        CameraSource(97)  # no /dev/video97
    with pytest.raises(ConfigError):
        CameraSource(tmp_path / "junk.avi", fps=-1)
    assert issubclass(DriverError, JaxSlamError)

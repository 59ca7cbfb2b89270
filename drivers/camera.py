"""Camera sources: an OpenCV ``VideoCapture`` device, a video file or a folder of images ->
:class:`jaxslam.measurements.Image` records with host timestamps.

``CameraSource(source)`` picks the kind from ``source``:

- an ``int`` or a string of digits: a capture device index (``/dev/videoN`` on Linux);
  any other string that is not an existing path is passed to ``VideoCapture`` as is (a
  GStreamer pipeline, an RTSP URL, a ``/dev/video*`` path);
- a folder: its ``*.png``, ``*.jpg``, ``*.jpeg``, ``*.bmp``, ``*.tif(f)`` files in name order
  (files that do not decode are counted as ``bad_frames`` and skipped);
- a file: a video decoded by ``VideoCapture`` (whatever the OpenCV build's backends read).

Records: ``data`` is ``(H, W, 3)`` RGB uint8 (OpenCV's BGR converted), or ``(H, W)`` grey with
``grey=True`` (a 16-bit image file gives float32 in [0, 1], as the readers do); ``camera`` is
the ``camera`` name. ``t`` is the host time (:func:`drivers._common.host_time`) right after
the frame was grabbed: it includes the exposure, transfer and driver latency (not
compensated: pass ``latency`` if measured). Folder and video sources replay at ``fps``
(default: the video's own rate, 10 Hz for a folder; ``fps=0`` as fast as possible).

GenICam / USB3 Vision cameras (the rig's Hikvision) need the vendor SDK or ``harvesters``: not
built here; such a camera that exposes a V4L2/UVC device works as a device index.

Opening a source that does not exist or cannot be opened raises
:class:`~drivers._common.DriverError`; bad arguments :class:`~jaxslam.errors.ConfigError`.
"""

from __future__ import annotations

import math
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from jaxslam.errors import ConfigError
from jaxslam.measurements import Image

from ._common import Counters, DriverError, HostClock, host_time

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")
FOLDER_FPS = 10.0


def _cv2() -> Any:
    try:
        import cv2
    except ImportError as exc:  # pragma: no cover - opencv is a dev dependency
        raise ConfigError("the camera source needs OpenCV: pip install opencv-python-headless") from exc
    return cv2


class CameraSource:
    """A camera device, video file or image folder (see the module docstring).

    ``counters``: ``frames`` (yielded), ``bad_frames`` (undecodable files, invalid images),
    ``read_failures`` (a device read that returned no frame).
    """

    def __init__(
        self,
        source: int | str | Path,
        *,
        camera: str = "cam0",
        grey: bool = False,
        fps: float | None = None,
        latency: float = 0.0,
        clock: HostClock = host_time,
        loop: bool = False,
    ):
        self.cv2 = _cv2()
        self.camera, self.grey, self.latency, self.clock, self.loop = camera, grey, float(latency), clock, loop
        self.counters = Counters("frames", "bad_frames", "read_failures")
        self.files: list[Path] | None = None
        self.cap: Any = None
        self.live = False
        if fps is not None and not (math.isfinite(fps) and fps >= 0):
            raise ConfigError(f"fps must be >= 0, got {fps}")
        path = None if isinstance(source, int) else Path(source)
        if path is not None and path.is_dir():
            self.kind = "folder"
            self.files = sorted(p for p in path.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
            if not self.files:
                raise DriverError(f"camera folder {path} holds no image files ({', '.join(IMAGE_SUFFIXES)})")
            self.fps = FOLDER_FPS if fps is None else float(fps)
        else:
            if isinstance(source, int) or str(source).isdigit():
                self.kind, target, self.live = "device", int(source), True
            elif path is not None and path.is_file():
                self.kind, target = "video", str(path)
            elif str(source).startswith(("/dev/", "rtsp:", "http:", "https:")) or "!" in str(source):
                self.kind, target, self.live = "device", str(source), True
            else:
                raise DriverError(f"camera source {source!r} is not a device index, a folder or a file")
            self.cap = self.cv2.VideoCapture(target)
            if not self.cap.isOpened():
                self.cap.release()
                raise DriverError(f"cannot open camera {self.kind} {source!r} with OpenCV VideoCapture")
            native = float(self.cap.get(self.cv2.CAP_PROP_FPS) or 0.0)
            self.fps = 0.0 if self.live else (float(fps) if fps is not None else (native if native > 0 else 0.0))
        self.source = source

    def _convert(self, bgr: np.ndarray) -> np.ndarray:
        cv2 = self.cv2
        if bgr.dtype == np.uint16:
            grey16 = bgr if bgr.ndim == 2 else cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY)
            return grey16.astype(np.float32) / np.float32(65535.0)
        if bgr.ndim == 2:
            return bgr if self.grey else np.ascontiguousarray(np.repeat(bgr[:, :, None], 3, axis=2))
        if bgr.shape[2] == 4:
            bgr = cv2.cvtColor(bgr, cv2.COLOR_BGRA2BGR)
        return cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY if self.grey else cv2.COLOR_BGR2RGB)

    def _grab(self, index: int) -> np.ndarray | None:
        """The next raw frame (None: a frame to skip); raises StopIteration at the end."""
        if self.files is not None:
            if index >= len(self.files):
                if not self.loop:
                    raise StopIteration
                index %= len(self.files)
            img = self.cv2.imread(str(self.files[index]), self.cv2.IMREAD_UNCHANGED)
            if img is None:
                self.counters.add("bad_frames")
            return img
        ok, img = self.cap.read()
        if not ok or img is None:
            if self.live:
                self.counters.add("read_failures")
                if self.counters["read_failures"] > 50 and self.counters["frames"] == 0:
                    raise DriverError(f"camera {self.source!r} returns no frames")
                return None
            if self.loop and self.counters["frames"]:
                self.cap.set(self.cv2.CAP_PROP_POS_FRAMES, 0)
                return None
            raise StopIteration
        return img

    def frames(self, max_frames: int | None = None, duration: float | None = None) -> Iterator[Image]:
        """Yield :class:`Image` records until ``max_frames``, ``duration`` seconds or the end
        of a folder/video (``loop=True`` replays it)."""
        deadline = None if duration is None else time.monotonic() + duration
        period = 1.0 / self.fps if self.fps > 0 else 0.0
        next_due = time.monotonic()
        emitted = index = 0
        while max_frames is None or emitted < max_frames:
            if deadline is not None and time.monotonic() >= deadline:
                return
            if period:
                wait = next_due - time.monotonic()
                if wait > 0:
                    time.sleep(wait if deadline is None else min(wait, max(0.0, deadline - time.monotonic())))
                    if deadline is not None and time.monotonic() >= deadline:
                        return
                next_due = max(next_due + period, time.monotonic() - period)
            try:
                raw = self._grab(index)
            except StopIteration:
                return
            index += 1
            t = self.clock() - self.latency
            if raw is None:
                continue
            rec = Image(t, self._convert(raw), camera=self.camera)
            try:
                rec.validate(f"camera {self.camera}")
            except ValueError:
                self.counters.add("bad_frames")
                continue
            self.counters.add("frames")
            emitted += 1
            yield rec

    def close(self) -> None:
        if self.cap is not None:
            self.cap.release()
            self.cap = None

    def __enter__(self) -> CameraSource:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

"""KITTI odometry sequence folders as recordings.

Layout (the odometry benchmark's, one sequence)::

    SEQ/image_0/000000.png ...   left grey camera (``image_l/`` is accepted too), -> "cam0"
    SEQ/image_1/ ...              right grey camera, when present                -> "cam1"
    SEQ/velodyne/000000.bin ...   float32 (x, y, z, reflectance) per point      -> LidarScan
    SEQ/times.txt                 one timestamp [s] per frame (else frame / rate)
    SEQ/poses.txt                 ground truth, 12 numbers per line (optional; or the
                                  benchmark's ``poses/NN.txt`` passed as ``ground_truth=``)
    SEQ/calib.txt                 projection matrices (read by the VO, not needed here)

Frames are numbered by file name; a frame whose image or scan is missing or unreadable is
skipped and counted. Velodyne scans carry no per-point times in KITTI (they are already
motion-compensated): ``point_times`` is zero.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np

from ..errors import InputFormatError
from ..measurements import Image, LidarScan, Measurement
from ._recording import Recording, StreamInfo, read_image_file, register_format
from ._trajectory import Trajectory, read_kitti

_CAMERAS = (("image_0", "cam0"), ("image_l", "cam0"), ("image_1", "cam1"), ("image_r", "cam1"))
_IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp")


def _frame_number(p: Path) -> int | None:
    return int(p.stem) if p.stem.isdigit() else None


class KittiRecording(Recording):
    """A KITTI odometry sequence folder (see the module docstring). ``rate`` (Hz) gives the
    timestamps when there is no ``times.txt`` (KITTI's cameras run at ~10 Hz)."""

    def __init__(self, path: str | Path, ground_truth: str | Path | None = None, rate: float = 10.0):
        super().__init__(path)
        if not self.path.is_dir():
            raise InputFormatError("KITTI sequence must be a folder", self.path)
        if not rate > 0:
            raise InputFormatError(f"rate must be positive, got {rate}", self.path)
        self._gt_path = Path(ground_truth) if ground_truth is not None else None
        self._cams: dict[str, dict[int, Path]] = {}
        for folder, name in _CAMERAS:
            d = self.path / folder
            if name in self._cams or not d.is_dir():
                continue
            frames = {}
            for f in sorted(d.iterdir()):
                k = _frame_number(f)
                if k is not None and f.suffix.lower() in _IMAGE_SUFFIXES:
                    frames[k] = f
            self._cams[name] = frames
        self._scans: dict[int, Path] = {}
        if (self.path / "velodyne").is_dir():
            for f in sorted((self.path / "velodyne").glob("*.bin")):
                k = _frame_number(f)
                if k is not None:
                    self._scans[k] = f
        if not self._cams and not self._scans:
            raise InputFormatError("KITTI sequence has no image_0/ (image_l/) or velodyne/ frames", self.path)
        n = 1 + max([max(d) for d in self._cams.values() if d] + [max(self._scans, default=-1), -1])
        times_file = self.path / "times.txt"
        if times_file.is_file():
            try:
                times = np.loadtxt(times_file, dtype=np.float64, ndmin=1)
            except ValueError as err:
                raise InputFormatError(f"times.txt is not one number per line ({err})", times_file) from None
            if len(times) < n:
                raise InputFormatError(f"times.txt has {len(times)} lines for {n} frames", times_file)
            if not np.all(np.isfinite(times)):
                raise InputFormatError("times.txt holds a non-finite timestamp", times_file)
            self._times = times
            self._time_note = "times.txt"
        else:
            self._times = np.arange(max(n, 0), dtype=np.float64) / rate
            self._time_note = f"frame / {rate:g} Hz"

    def streams(self) -> list[StreamInfo]:
        def info(kind: str, topic: str, msgtype: str, frames: dict[int, Path]) -> StreamInfo:
            ks = sorted(frames)
            span = (self._times[ks[0]], self._times[ks[-1]]) if ks else (np.nan, np.nan)
            return StreamInfo(kind, topic, msgtype, len(ks), float(span[0]), float(span[1]), self._time_note)

        out = [info("image", name, "kitti/png", frames) for name, frames in self._cams.items()]
        if self._scans:
            out.append(info("lidar", "velodyne", "kitti/bin", self._scans))
        return out

    def _records(self) -> Iterator[tuple[str, Measurement]]:
        frames = sorted(set().union(*[set(d) for d in self._cams.values()], set(self._scans)))
        for k in frames:
            t = float(self._times[k])
            for name, files in self._cams.items():
                f = files.get(k)
                if f is None:
                    continue
                try:
                    data = read_image_file(f)
                except InputFormatError:
                    self.skipped[f"{name}: unreadable image"] += 1
                    continue
                yield name, Image(t, data, camera=name)
            f = self._scans.get(k)
            if f is not None:
                raw = np.fromfile(f, dtype=np.float32)
                if raw.size % 4:
                    self.skipped["velodyne: scan size not a multiple of 4 floats"] += 1
                    continue
                pts = raw.reshape(-1, 4).astype(np.float64)
                yield "velodyne", LidarScan(t, pts[:, :3], pts[:, 3], np.zeros(len(pts)))

    def ground_truth(self) -> Trajectory | None:
        """``ground_truth=`` or ``poses.txt`` (camera-0 poses), timed like the frames."""
        path = self._gt_path or (self.path / "poses.txt")
        if not path.is_file():
            return None
        traj = read_kitti(path)
        n = len(traj.timestamps)
        if n > len(self._times):
            raise InputFormatError(f"{n} poses but only {len(self._times)} frame times", path)
        return Trajectory(self._times[:n].copy(), traj.poses)


def _is_kitti(p: Path) -> bool:
    return (
        p.is_dir()
        and (any((p / folder).is_dir() for folder, _ in _CAMERAS) or (p / "velodyne").is_dir())
        and not (p / "mav0").is_dir()
    )


register_format("kitti", _is_kitti, KittiRecording)

"""Recorded sensor data behind one registry: :func:`open_recording` guesses the format from
the path and returns a :class:`Recording` that yields measurement records
(:mod:`jaxslam.measurements`) in time order, exactly as a live driver would.

Formats (guessed in this order; ``fmt=`` forces one):

- ``ros1``: a ``.bag`` file.
- ``ros2``: a folder holding ``metadata.yaml`` and a ``.db3`` or ``.mcap`` file, or a ``.mcap``
  / ``.db3`` file.
- ``euroc``: an EuRoC/ASL folder, one that contains ``mav0/`` (or is ``mav0`` itself).

Decisions (each tested):

- Records come out in non-decreasing ``t``, merged across streams. A record whose time goes
  backwards within its stream (or, for bags, beyond the reorder window) and a record whose
  ``validate()`` fails (NaN, wrong shape) are skipped and counted in
  :attr:`Recording.skipped` (``"<stream>: <reason>" -> count``), never raised.
- A file that cannot be read at all raises :class:`~jaxslam.errors.InputFormatError` naming it.
"""

from __future__ import annotations

import csv
import dataclasses
import heapq
import io
from collections import Counter
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path
from typing import Any

import jax.numpy as jnp
import numpy as np

from ..errors import InputFormatError
from ..lie import SE3
from ..measurements import Image, ImuSample, LidarScan, Measurement, PositionFix
from ._trajectory import Trajectory, read_tum


@dataclasses.dataclass(frozen=True)
class StreamInfo:
    """One stream of a recording: record ``kind`` (``"imu"``, ``"image"``, ``"lidar"``,
    ``"pose"``), its ``topic`` (bag topic or EuRoC sensor folder), the source ``msgtype``,
    ``count`` messages and the time span ``t_start``..``t_end`` in seconds (``nan`` when empty);
    ``note`` says how the stream was chosen when it was guessed among several."""

    kind: str
    topic: str
    msgtype: str
    count: int
    t_start: float
    t_end: float
    note: str = ""


class Recording:
    """A recording: iterate it for records in time order.

    Subclasses implement :meth:`streams`, :meth:`_records` and :meth:`ground_truth`.
    ``skipped`` counts records dropped while iterating, by ``"<stream>: <reason>"``.
    """

    path: Path
    skipped: Counter[str]

    def __init__(self, path: str | Path):
        self.path = Path(path)
        self.skipped = Counter()
        self._skipped_at_open: Counter[str] = Counter()

    def streams(self) -> list[StreamInfo]:
        """The streams this recording yields records for."""
        raise NotImplementedError

    def topics(self) -> dict[str, StreamInfo]:
        """The streams keyed by topic."""
        return {s.topic: s for s in self.streams()}

    def ground_truth(self) -> Trajectory | None:
        """The ground-truth trajectory, or ``None`` when the recording has none."""
        return None

    def _records(self) -> Iterator[tuple[str, Measurement]]:
        """Yield ``(stream name, record)`` roughly in time order (before the checks)."""
        raise NotImplementedError

    def __iter__(self) -> Iterator[Measurement]:
        """Yield valid records in non-decreasing time; count and skip the others."""
        self.skipped.clear()
        self.skipped.update(self._skipped_at_open)
        last_stream: dict[str, float] = {}
        last = -np.inf
        for stream, record in self._records():
            try:
                record.validate(f"{self.path}: {stream}")
            except InputFormatError:
                self.skipped[f"{stream}: invalid (NaN or shape)"] += 1
                continue
            t = float(record.t)
            if t <= last_stream.get(stream, -np.inf) or t < last:
                self.skipped[f"{stream}: time not increasing"] += 1
                continue
            last_stream[stream] = t
            last = t
            yield record


# --- registry ------------------------------------------------------------------------------------

Detector = Callable[[Path], bool]
Opener = Callable[..., Recording]
_FORMATS: dict[str, tuple[Detector, Opener]] = {}


def register_format(name: str, detect: Detector, opener: Opener) -> None:
    """Add a recording format: ``detect(path)`` says whether a path is one, ``opener(path,
    **options)`` opens it. Later registrations are tried after earlier ones."""
    _FORMATS[name] = (detect, opener)


def recording_formats() -> list[str]:
    """The names of the registered recording formats."""
    return list(_FORMATS)


def open_recording(path: str | Path, fmt: str | None = None, **options: Any) -> Recording:
    """Open a recording, guessing its format from the path (or ``fmt=``); ``options`` go to
    the format's reader (see :class:`EurocRecording` and ``RosbagRecording``).

    Raises InputFormatError when the path is missing or no format matches, listing the formats.
    """
    p = Path(path)
    if not p.exists():
        raise InputFormatError("no such file or folder", p)
    if fmt is not None:
        if fmt not in _FORMATS:
            raise InputFormatError(f"unknown recording format {fmt!r}; formats: {', '.join(_FORMATS)}", p)
        return _FORMATS[fmt][1](p, **options)
    for detect, opener in _FORMATS.values():
        if detect(p):
            return opener(p, **options)
    raise InputFormatError(
        "not a known recording; formats: ros1 (a .bag file), ros2 (a folder with metadata.yaml and "
        ".db3/.mcap, or a .mcap/.db3 file), euroc (a folder with mav0/)",
        p,
    )


def _is_ros1(p: Path) -> bool:
    return p.is_file() and p.suffix == ".bag"


def _is_ros2(p: Path) -> bool:
    if p.is_file():
        return p.suffix in (".mcap", ".db3")
    return p.is_dir() and (p / "metadata.yaml").is_file() and (any(p.glob("*.db3")) or any(p.glob("*.mcap")))


def _is_euroc(p: Path) -> bool:
    return p.is_dir() and ((p / "mav0").is_dir() or (p.name == "mav0" and (p / "imu0").is_dir()))


def _open_rosbag(path: Path, **options: Any) -> Recording:
    from ._rosbag import RosbagRecording

    return RosbagRecording(path, **options)


# --- EuRoC / ASL ---------------------------------------------------------------------------------


def _read_csv(path: Path, ncols: int) -> tuple[np.ndarray, list[list[str]]]:
    """Rows of an ASL csv (``#`` header skipped): int64 ns timestamps and the string fields."""
    times: list[int] = []
    rows: list[list[str]] = []
    lineno = 0
    try:
        with open(path, newline="", encoding="utf-8") as f:
            for lineno, row in enumerate(csv.reader(f), start=1):
                if not row or row[0].lstrip().startswith("#"):
                    continue
                if len(row) < ncols:
                    raise InputFormatError(f"ASL rows need {ncols} fields, found {len(row)}", path, lineno)
                try:
                    t = int(row[0])
                except ValueError:
                    raise InputFormatError(f"timestamp {row[0]!r} is not an integer (ns)", path, lineno) from None
                if not -(2**63) <= t < 2**63:
                    raise InputFormatError(f"timestamp {row[0]!r} does not fit int64 ns", path, lineno)
                times.append(t)
                rows.append([x.strip() for x in row[1:ncols]])
    except UnicodeDecodeError as err:
        raise InputFormatError(f"not UTF-8 text: {err.reason} at byte {err.start}", path, lineno + 1) from None
    except csv.Error as err:
        raise InputFormatError(f"malformed csv: {err}", path, lineno + 1) from None
    return np.asarray(times, dtype=np.int64), rows


def _floats(rows: list[list[str]], n: int, path: Path, blank_nan: bool = False) -> np.ndarray:
    """The first ``n`` fields of each row as float64 (InputFormatError naming a bad field)."""
    try:
        vals = [[float(x) if (x or not blank_nan) else np.nan for x in r[:n]] for r in rows]
    except ValueError as err:
        raise InputFormatError(f"a field is not a number ({err})", path) from None
    return np.array(vals, dtype=np.float64).reshape(-1, n)


def read_image_file(path: str | Path | bytes) -> np.ndarray:
    """Read an image file (or its bytes) to ``(H, W)`` grey or ``(H, W, 3)`` RGB: uint8 for
    8-bit images, float32 in [0, 1] for 16-bit grey. Decoded with Pillow (a dependency of
    matplotlib, itself a core dependency)."""
    from PIL import Image as PILImage

    try:
        with PILImage.open(io.BytesIO(path) if isinstance(path, bytes) else path) as im:
            if im.mode in ("I;16", "I;16B", "I;16L", "I"):
                return np.asarray(im, dtype=np.float32) / np.float32(65535.0)
            pixels = im if im.mode in ("L", "RGB") else im.convert("RGB")
            return np.ascontiguousarray(np.asarray(pixels))
    except (OSError, ValueError) as err:
        where = "<bytes>" if isinstance(path, bytes) else path
        raise InputFormatError(f"cannot decode image: {err}", where) from None


class EurocRecording(Recording):
    """An EuRoC MAV / ASL folder: ``mav0/imu0/data.csv`` (``#timestamp [ns], w_RS_S_x..z
    [rad/s], a_RS_S_x..z [m/s^2]``) -> :class:`ImuSample` and ``mav0/camN/data.csv`` +
    ``data/<file>`` -> :class:`Image` (``camera="camN"``; PNGs decoded on demand, uint8 grey;
    csv rows whose file is missing are left out and counted in ``skipped``).
    Times are the csv nanoseconds / 1e9 (float64 s).

    Ground truth: ``mav0/state_groundtruth_estimate0/data.csv`` (``p_RS_R``, ``q_RS`` wxyz) when
    present; ``ground_truth=<TUM file>`` overrides it. ``cameras=("cam0",)`` picks cameras
    (default: every ``cam*`` folder with a ``data.csv``).

    When present (the layout :class:`~jaxslam.io.EurocWriter` writes): ``mav0/lidar0/data.csv``
    + ``data/<file>.npy`` (float32 ``(N, 5)`` x y z intensity time-offset, or ``(N, 6)`` with
    ring) -> :class:`LidarScan`, and ``mav0/total_station0/data.csv`` (``p x y z [m], sigma``)
    -> :class:`PositionFix`.
    """

    def __init__(
        self,
        path: str | Path,
        ground_truth: str | Path | None = None,
        cameras: Iterable[str] | None = None,
    ):
        super().__init__(path)
        root = self.path if self.path.name == "mav0" else self.path / "mav0"
        self.root = root
        self._gt_path = None if ground_truth is None else Path(ground_truth)
        imu_csv = root / "imu0" / "data.csv"
        if not imu_csv.is_file():
            raise InputFormatError("EuRoC folder has no mav0/imu0/data.csv", self.path)
        t, rows = _read_csv(imu_csv, 7)
        vals = _floats(rows, 6, imu_csv, blank_nan=True)
        self._imu_t, self._imu = t, vals
        names = sorted(d.name for d in root.glob("cam*") if (d / "data.csv").is_file())
        if cameras is not None:
            missing = [c for c in cameras if c not in names]
            if missing:
                raise InputFormatError(f"no camera {missing}; available: {names}", self.path)
            names = list(cameras)
        self._cams: dict[str, tuple[np.ndarray, list[Path]]] = {}
        for name in names:
            ct, crows = _read_csv(root / name / "data.csv", 2)
            files = [root / name / "data" / r[0] for r in crows]
            there = np.array([f.is_file() for f in files], dtype=bool)
            if not there.all():
                self._skipped_at_open[f"{name}: image file missing"] += int((~there).sum())
            self._cams[name] = (ct[there], [f for f, ok in zip(files, there) if ok])
        self._lidar: tuple[np.ndarray, list[Path]] | None = None
        if (root / "lidar0" / "data.csv").is_file():
            lt, lrows = _read_csv(root / "lidar0" / "data.csv", 2)
            self._lidar = (lt, [root / "lidar0" / "data" / r[0] for r in lrows])
        self._fixes: tuple[np.ndarray, np.ndarray] | None = None
        if (root / "total_station0" / "data.csv").is_file():
            ft, frows = _read_csv(root / "total_station0" / "data.csv", 5)
            fv = _floats(frows, 4, root / "total_station0" / "data.csv")
            self._fixes = (ft, fv)
        self.skipped.update(self._skipped_at_open)

    def streams(self) -> list[StreamInfo]:
        def info(kind: str, topic: str, msgtype: str, t: np.ndarray) -> StreamInfo:
            span = (t[0] / 1e9, t[-1] / 1e9) if len(t) else (np.nan, np.nan)
            return StreamInfo(kind, topic, msgtype, len(t), float(span[0]), float(span[1]))

        out = [info("imu", "imu0", "euroc/imu csv", self._imu_t)]
        out += [info("image", c, "euroc/png", t) for c, (t, _) in self._cams.items()]
        if self._lidar is not None:
            out.append(info("lidar", "lidar0", "euroc/npy", self._lidar[0]))
        if self._fixes is not None:
            out.append(info("position", "total_station0", "euroc/position csv", self._fixes[0]))
        return out

    def _lidar_records(self) -> Iterator[tuple[int, str, Measurement]]:
        assert self._lidar is not None
        for ns, f in zip(self._lidar[0].tolist(), self._lidar[1]):
            try:
                a = np.load(f, allow_pickle=False)
                if a.ndim != 2 or a.shape[1] not in (5, 6):
                    raise ValueError(f"shape {a.shape}")
            except (OSError, ValueError):
                self.skipped["lidar0: unreadable scan"] += 1
                continue
            a64 = a.astype(np.float64)
            ring = a[:, 5].astype(np.int64) if a.shape[1] == 6 else None
            yield ns, "lidar0", LidarScan(ns / 1e9, a64[:, 0:3], a64[:, 3], a64[:, 4], ring)

    def _fix_records(self) -> Iterator[tuple[int, str, Measurement]]:
        assert self._fixes is not None
        for ns, v in zip(self._fixes[0].tolist(), self._fixes[1]):
            yield ns, "total_station0", PositionFix(ns / 1e9, v[0:3].copy(), float(v[3]))

    def _imu_records(self) -> Iterator[tuple[int, str, Measurement]]:
        for ns, v in zip(self._imu_t.tolist(), self._imu):
            yield ns, "imu0", ImuSample(ns / 1e9, acc=v[3:6].copy(), gyro=v[0:3].copy())

    def _cam_records(self, name: str) -> Iterator[tuple[int, str, Measurement]]:
        times, files = self._cams[name]
        for ns, f in zip(times.tolist(), files):
            try:
                data = read_image_file(f)
            except InputFormatError:
                self.skipped[f"{name}: unreadable image"] += 1
                continue
            yield ns, name, Image(ns / 1e9, data, camera=name)

    def _records(self) -> Iterator[tuple[str, Measurement]]:
        gens = [self._imu_records()] + [self._cam_records(c) for c in self._cams]
        gens += [self._lidar_records()] if self._lidar is not None else []
        gens += [self._fix_records()] if self._fixes is not None else []
        for _, stream, record in heapq.merge(*gens, key=lambda x: x[0]):
            yield stream, record

    def ground_truth(self) -> Trajectory | None:
        """The ground truth: the ``ground_truth=`` TUM file, else the ASL state csv, else None."""
        if self._gt_path is not None:
            return read_tum(self._gt_path)
        gt = self.root / "state_groundtruth_estimate0" / "data.csv"
        if not gt.is_file():
            return None
        t, rows = _read_csv(gt, 8)
        v = _floats(rows, 7, gt)
        q = v[:, 3:7] / np.linalg.norm(v[:, 3:7], axis=1, keepdims=True)
        return Trajectory(t / 1e9, SE3(jnp.asarray(np.concatenate([q, v[:, :3]], axis=1))))


register_format("ros1", _is_ros1, _open_rosbag)
register_format("ros2", _is_ros2, _open_rosbag)
register_format("euroc", _is_euroc, EurocRecording)

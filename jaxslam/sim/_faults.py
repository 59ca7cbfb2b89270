"""Fault injection: turn a clean record stream into a bad recording, for robustness tests.

:func:`inject_faults` wraps a time-ordered iterator of measurement records
(:mod:`jaxslam.measurements`) and applies fault specs, small frozen dataclasses:

=========================================  =====================================================
fault                                      effect
=========================================  =====================================================
``CameraDark(start, duration)``            images in the window become almost black
                                           (``data * gain`` plus Gaussian read noise, dtype
                                           kept): a dead lamp stretch
``SensorDropout(kind, start, duration)``   records of ``kind`` in the window are removed
``NanSamples(kind, every)``                every n-th record of ``kind`` gets NaN values: one
                                           acc and one gyro component (IMU), a fraction of the
                                           points' coordinates (LiDAR), a fraction of the pixels
                                           of a float copy in [0, 1] (image)
``TimeJump(kind, at, back, count=3)``      the first ``count`` records of ``kind`` at or after
                                           ``at`` come with ``t - back``; later stamps are normal
``Truncate(at)``                           the stream ends before the first record at ``at``
=========================================  =====================================================

Times ``start``/``at`` are seconds relative to the **first record's** time (whatever its
kind), compared with the records' original stamps; windows are half-open
``[start, start + duration)``. ``kind`` is a record's ``kind`` (``"imu"``, ``"image"``,
``"lidar"``, ``"position"``, ``"pose"``). The n-th record of a kind is counted over the input
stream (1-based: ``every=3`` hits the 3rd, 6th, ...), so a dropped record still counts.
Faults apply in list order to each record. Noise and the NaN positions come from
``numpy.random.default_rng([seed, fault index, record index])``: the same input, faults and
seed give the same output.

Recordings (:func:`write_faulty`, :func:`truncate_file`). What survives a write + read round
trip through :func:`jaxslam.io.open_writer` / :func:`jaxslam.io.open_recording`:

- dark images and dropouts, truncation: exactly (they are ordinary records);
- NaN IMU samples: written (a float NaN encodes in both bags and EuRoC csv), then skipped by
  the reader and counted in ``Recording.skipped`` (``"<topic>: invalid (NaN or shape)"``);
- NaN LiDAR points: bags keep the scan and the reader drops the NaN points (organised-cloud
  convention), so the scan comes back with fewer points; EuRoC keeps them in the ``.npy``
  and the reader skips the whole scan as invalid (counted);
- NaN images: no image encoding (``mono8``/``mono16``/PNG) holds NaN -- the writers would
  cast NaN to an arbitrary grey level -- so :func:`write_faulty` leaves them out and counts
  them (``"image: NaN not encodable"``);
- time jumps: the writers accept any stamp order. A ROS1/ROS2 bag is read back in stamp
  order (rosbags sorts by time), so a jumped record comes back *moved earlier*, not
  rejected, unless it lands more than the reader's ``reorder_window`` behind records
  already emitted (then it is counted as ``"time not increasing"``); an EuRoC csv keeps file
  order and the reader skips each jumped record as ``"time not increasing"``.

So NaN and time-jump faults test the estimator only when the faulted records go straight
into it; through a file they test the readers.

A ROS1 bag cut by a power loss (:func:`truncate_file`): the header's ``index_pos`` still
points at the index that was never completely written (beyond the end of the cut file), so
``open_recording`` raises :class:`~jaxslam.errors.InputFormatError` ("cannot read bag: ...");
``python -m drivers.record reindex CUT.bag`` rebuilds a readable bag from the chunks that are
complete (``reindex`` counts the cut one as ``truncated_records``). A bag written by a
recorder that never closed it (``index_pos = 0``) is named as such by the reader.
"""

from __future__ import annotations

import dataclasses
import shutil
from collections import Counter
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import ConfigError
from ..measurements import Image, ImuSample, LidarScan, Measurement

KINDS = ("imu", "image", "lidar", "position", "pose")
"""Record kinds a fault can name (``Measurement.kind``)."""


def _check_kind(kind: str) -> None:
    if kind not in KINDS:
        raise ConfigError(f"fault kind must be one of {', '.join(KINDS)}, got {kind!r}")


def _check_window(start: float, duration: float) -> None:
    if not (np.isfinite(start) and np.isfinite(duration) and duration >= 0):
        raise ConfigError(f"fault window needs finite start and duration >= 0, got {start}, {duration}")


@dataclasses.dataclass(frozen=True)
class CameraDark:
    """Images with ``start <= t - t0 < start + duration`` become ``data * gain`` plus
    Gaussian read noise of ``read_noise`` grey levels (of 255; float images in [0, 1] get
    ``read_noise / 255``), rounded and clipped for uint8; ``camera`` limits it to one camera."""

    start: float
    duration: float
    gain: float = 0.02
    read_noise: float = 1.0
    camera: str | None = None

    def __post_init__(self) -> None:
        _check_window(self.start, self.duration)
        if not (0 <= self.gain <= 1 and self.read_noise >= 0):
            raise ConfigError(
                f"CameraDark needs 0 <= gain <= 1 and read_noise >= 0, got {self.gain}, {self.read_noise}"
            )


@dataclasses.dataclass(frozen=True)
class SensorDropout:
    """Records of ``kind`` with ``start <= t - t0 < start + duration`` are removed."""

    kind: str
    start: float
    duration: float

    def __post_init__(self) -> None:
        _check_kind(self.kind)
        _check_window(self.start, self.duration)


@dataclasses.dataclass(frozen=True)
class NanSamples:
    """Every ``every``-th record of ``kind`` (1-based over the input) gets NaN values;
    ``fraction`` of the LiDAR points / image pixels (at least one)."""

    kind: str
    every: int
    fraction: float = 0.1

    def __post_init__(self) -> None:
        if self.kind not in ("imu", "image", "lidar"):
            raise ConfigError(f"NanSamples kind must be imu, image or lidar, got {self.kind!r}")
        if not (isinstance(self.every, int) and self.every >= 1):
            raise ConfigError(f"NanSamples.every must be an integer >= 1, got {self.every!r}")
        if not 0 < self.fraction <= 1:
            raise ConfigError(f"NanSamples.fraction must be in (0, 1], got {self.fraction}")


@dataclasses.dataclass(frozen=True)
class TimeJump:
    """The first ``count`` records of ``kind`` with ``t - t0 >= at`` get ``t - back``."""

    kind: str
    at: float
    back: float
    count: int = 3

    def __post_init__(self) -> None:
        _check_kind(self.kind)
        if not (np.isfinite(self.at) and np.isfinite(self.back) and isinstance(self.count, int) and self.count >= 1):
            raise ConfigError(
                f"TimeJump needs finite at, back and count >= 1, got {self.at}, {self.back}, {self.count}"
            )


@dataclasses.dataclass(frozen=True)
class Truncate:
    """The stream ends before the first record with ``t - t0 >= at``."""

    at: float

    def __post_init__(self) -> None:
        if not np.isfinite(self.at):
            raise ConfigError(f"Truncate.at must be finite, got {self.at}")


Fault = CameraDark | SensorDropout | NanSamples | TimeJump | Truncate


def _in(rel: float, start: float, duration: float) -> bool:
    return start <= rel < start + duration


def _dark(img: Image, f: CameraDark, rng: np.random.Generator) -> Image:
    d = np.asarray(img.data)
    if d.dtype.kind == "f":
        out = np.clip(d * f.gain + rng.normal(0.0, f.read_noise / 255.0, d.shape), 0.0, 1.0).astype(d.dtype)
    else:
        info = np.iinfo(d.dtype)
        vals = np.rint(d.astype(np.float64) * f.gain + rng.normal(0.0, f.read_noise, d.shape))
        out = np.clip(vals, info.min, info.max).astype(d.dtype)
    return dataclasses.replace(img, data=out)


def _some(n: int, fraction: float, rng: np.random.Generator) -> np.ndarray:
    """Indices of ``max(1, round(fraction * n))`` of ``n`` items (sorted)."""
    k = min(n, max(1, round(fraction * n)))
    return np.sort(rng.choice(n, size=k, replace=False))


def _nan(rec: Measurement, f: NanSamples, rng: np.random.Generator) -> Measurement:
    if isinstance(rec, ImuSample):
        acc = np.array(rec.acc, dtype=np.float64)
        gyro = np.array(rec.gyro, dtype=np.float64)
        acc[rng.integers(3)] = np.nan
        gyro[rng.integers(3)] = np.nan
        return dataclasses.replace(rec, acc=acc, gyro=gyro)
    if isinstance(rec, LidarScan):
        pts = np.array(rec.points, dtype=np.float64)
        if len(pts):
            pts[_some(len(pts), f.fraction, rng)] = np.nan
        return dataclasses.replace(rec, points=pts)
    if isinstance(rec, Image):
        d = np.asarray(rec.data)
        data = d.astype(np.float64) / 255.0 if d.dtype.kind in "ui" else d.astype(np.float64)
        flat = data.reshape(d.shape[0] * d.shape[1], -1)
        flat[_some(len(flat), f.fraction, rng)] = np.nan
        return dataclasses.replace(rec, data=flat.reshape(d.shape))
    return rec


def inject_faults(records: Iterable[Measurement], faults: Iterable[Fault], seed: int = 0) -> Iterator[Measurement]:
    """Yield ``records`` with ``faults`` applied (see the module docstring); lazy, so a
    :class:`Truncate` stops reading the input at the cut."""
    faults = list(faults)
    for f in faults:
        if not isinstance(f, CameraDark | SensorDropout | NanSamples | TimeJump | Truncate):
            raise TypeError(f"not a fault spec: {f!r}")
    t0: float | None = None
    seen: Counter[str] = Counter()  # input records per kind
    jumped: Counter[int] = Counter()  # records shifted so far per TimeJump (by index)
    for i, rec in enumerate(records):
        if t0 is None:
            t0 = float(rec.t)
        rel = float(rec.t) - t0
        seen[rec.kind] += 1
        if any(isinstance(f, Truncate) and rel >= f.at for f in faults):
            return
        out: Measurement | None = rec
        for j, f in enumerate(faults):
            if isinstance(f, SensorDropout) and rec.kind == f.kind and _in(rel, f.start, f.duration):
                out = None
                break
            if (
                isinstance(f, CameraDark)
                and isinstance(out, Image)
                and (f.camera is None or f.camera == out.camera)
                and _in(rel, f.start, f.duration)
            ):
                out = _dark(out, f, np.random.default_rng([seed, j, i]))
            elif isinstance(f, NanSamples) and out is not None and rec.kind == f.kind and seen[rec.kind] % f.every == 0:
                out = _nan(out, f, np.random.default_rng([seed, j, i]))
            elif (
                isinstance(f, TimeJump)
                and out is not None
                and rec.kind == f.kind
                and rel >= f.at
                and jumped[j] < f.count
            ):
                jumped[j] += 1
                out = dataclasses.replace(out, t=float(out.t) - f.back)
        if out is not None:
            yield out


def _encodable(rec: Measurement) -> bool:
    """Whether a writer can store the record faithfully (NaN pixels have no encoding)."""
    if isinstance(rec, Image):
        d = np.asarray(rec.data)
        return not (d.dtype.kind == "f" and not np.all(np.isfinite(d)))
    return True


def write_faulty(
    src_path: str | Path, dst_path: str | Path, faults: Iterable[Fault], fmt: str = "bag", seed: int = 0, **options: Any
) -> Counter[str]:
    """Read the recording ``src_path`` (:func:`jaxslam.io.open_recording`, ``options`` go to
    it), apply ``faults`` and write the result to ``dst_path`` with
    :func:`jaxslam.io.open_writer` (``fmt``: ``bag``, ``bag2``, ``bag2-db3``, ``euroc``).

    Returns counts: ``"<kind>: written"`` per kind and ``"image: NaN not encodable"`` for the
    NaN images left out (see the module docstring for what survives reading it back).
    """
    from ..io import open_recording, open_writer

    counts: Counter[str] = Counter()
    rec_in = open_recording(src_path, **options)
    with open_writer(dst_path, fmt) as w:
        for rec in inject_faults(rec_in, faults, seed=seed):
            if not _encodable(rec):
                counts[f"{rec.kind}: NaN not encodable"] += 1
                continue
            w.write(rec)
            counts[f"{rec.kind}: written"] += 1
    return counts


def truncate_file(src: str | Path, dst: str | Path, fraction: float) -> int:
    """Copy the first ``fraction`` of the bytes of ``src`` to ``dst`` (a recording cut by a
    power loss mid-write); returns the bytes written. ``dst`` must not exist."""
    if not 0 <= fraction <= 1:
        raise ConfigError(f"fraction must be in [0, 1], got {fraction}")
    src, dst = Path(src), Path(dst)
    if dst.exists():
        raise ConfigError(f"{dst} exists; not overwriting")
    n = int(src.stat().st_size * fraction)
    with open(src, "rb") as fi, open(dst, "wb") as fo:
        shutil.copyfileobj(_Limited(fi, n), fo)
    return n


class _Limited:
    """A read-only file view of the first ``n`` bytes (for ``shutil.copyfileobj``)."""

    def __init__(self, f: Any, n: int):
        self.f, self.left = f, n

    def read(self, size: int = -1) -> bytes:
        size = self.left if size < 0 else min(size, self.left)
        data = self.f.read(size)
        self.left -= len(data)
        return data

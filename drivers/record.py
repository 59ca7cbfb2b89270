"""Record the rig's sensors to a ROS1 bag as it goes; rebuild the index of a bag whose
recorder was killed.

Usage::

    python -m drivers.record --imu /dev/ttyUSB0 [--imu-baud 115200] \\
        [--lidar-port 57000 --lidar-imu-port 58000 --lidar-host 0.0.0.0] \\
        [--camera 0|FOLDER|VIDEO --camera-fps 10] -o run.bag [--duration S] [--flush 0.5]
    python -m drivers.record reindex run.bag [-o fixed.bag]

Topics and messages (the layout ``jaxslam.io``'s writers use, so ``open_recording`` reads a
recording like any bag): WitMotion IMU -> ``sensor_msgs/Imu`` on ``/imu/data`` (host clock);
Livox frames -> ``sensor_msgs/PointCloud2`` on ``/lidar/points`` (float32 ``x y z intensity``,
uint32 ``t`` ns after the stamp, uint16 ``ring``) and Livox IMU -> ``/livox/imu`` (sensor
clock: PTP/GPS time when synchronised, time since power-on otherwise, see
:mod:`drivers.livox`); camera -> ``sensor_msgs/Image`` (``rgb8``/``mono8``, ``mono16`` for
float images) on ``/<camera>/image_raw`` (host clock). Header stamps are the records' times;
the bag's receive time is the host time at which the record was written, so
``open_recording(bag, time="receive")`` puts every stream on the host clock.

**Crash safety.** rosbags' ROS1 writer keeps the open chunk in memory and writes the index
(connection and chunk-info records, and ``index_pos`` in the bag header) only on close. The
recorder therefore closes the open chunk every ``--flush`` seconds (default 0.5 s) and flushes
it to the operating system, so a recorder killed by anything (SIGKILL, power loss after the
kernel wrote the pages) leaves every chunk but the open one on disk: all but the last
~0.5-1 s. Such a bag has no index; ``jaxslam.io.open_recording`` says so and names the repair::

    python -m drivers.record reindex run.bag      # run.bag rebuilt, the original kept as run.orig.bag

``reindex`` reads the chunks in file order (connection and message records; a truncated
last record is dropped and counted) and writes a new, indexed bag with the same connections
and messages. SIGINT/SIGTERM stop the recorder cleanly (index written, no repair needed).

Layer rule: this module imports only ``jaxslam.measurements`` and ``jaxslam.errors`` from
jaxslam (the message building below duplicates a few lines of ``jaxslam.io``'s writer).
"""

from __future__ import annotations

import argparse
import contextlib
import queue
import signal
import sys
import threading
import time
from collections import Counter
from pathlib import Path
from typing import Any

import numpy as np
from rosbags.rosbag1 import Writer
from rosbags.typesys import Stores, get_typestore

from jaxslam.errors import ConfigError, JaxSlamError
from jaxslam.measurements import Image, ImuSample, LidarScan

from ._common import DriverError

TOPICS = {"imu": "/imu/data", "lidar": "/lidar/points", "lidar_imu": "/livox/imu"}
"""Bag topics of the recorder's streams (images: ``/<camera>/image_raw``)."""

FLUSH_INTERVAL = 0.5
"""Seconds between chunk flushes: the most a killed recorder loses (plus the queue)."""


# ----------------------------------------------------------------------------- bag writing


class BagRecorder:
    """A ROS1 bag written as it goes: ``write(topic, record, t_recv)``; the open chunk is
    written to the file and flushed every ``flush_interval`` seconds (and at 1 MiB)."""

    def __init__(self, path: str | Path, flush_interval: float = FLUSH_INTERVAL):
        self.path = Path(path)
        if self.path.exists():
            raise ConfigError(f"{self.path} exists; not overwriting a recording")
        self.store = get_typestore(Stores.ROS1_NOETIC)
        self.T = self.store.types
        self.writer = Writer(self.path)
        try:
            self.writer.open()
        except OSError as exc:
            raise DriverError(f"cannot create bag {self.path}: {exc}") from exc
        self.flush_interval = float(flush_interval)
        self.conns: dict[str, Any] = {}
        self.seq: Counter[str] = Counter()
        self.counts: Counter[str] = Counter()
        self._last_flush = time.monotonic()

    def _header(self, topic: str, t: float, frame: str) -> Any:
        ns = round(t * 1e9)
        self.seq[topic] += 1
        stamp = self.T["builtin_interfaces/msg/Time"](sec=ns // 10**9, nanosec=ns % 10**9)
        return self.T["std_msgs/msg/Header"](seq=self.seq[topic] - 1, stamp=stamp, frame_id=frame)

    def message(self, topic: str, record: Any) -> tuple[str, Any]:
        """``(msgtype, message)`` for a record (the writers' layout)."""
        T = self.T
        if isinstance(record, ImuSample):
            V = T["geometry_msgs/msg/Vector3"]
            a, g = np.asarray(record.acc, np.float64), np.asarray(record.gyro, np.float64)
            return "sensor_msgs/msg/Imu", T["sensor_msgs/msg/Imu"](
                header=self._header(topic, record.t, "imu"),
                orientation=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0),
                orientation_covariance=np.array([-1.0] + [0.0] * 8),
                angular_velocity=V(x=float(g[0]), y=float(g[1]), z=float(g[2])),
                angular_velocity_covariance=np.zeros(9),
                linear_acceleration=V(x=float(a[0]), y=float(a[1]), z=float(a[2])),
                linear_acceleration_covariance=np.zeros(9),
            )
        if isinstance(record, Image):
            px = np.asarray(record.data)
            if px.dtype.kind == "f":
                px, enc = np.rint(np.clip(px, 0, 1) * 65535).astype("<u2"), "mono16"
            else:
                px, enc = px.astype(np.uint8, copy=False), "mono8" if px.ndim == 2 else "rgb8"
            h, w = px.shape[:2]
            data = np.ascontiguousarray(px).view(np.uint8).reshape(-1)
            return "sensor_msgs/msg/Image", T["sensor_msgs/msg/Image"](
                header=self._header(topic, record.t, record.camera),
                height=h,
                width=w,
                encoding=enc,
                is_bigendian=0,
                step=data.size // h,
                data=data,
            )
        if isinstance(record, LidarScan):
            pts = np.asarray(record.points)
            names, fmts = ["x", "y", "z", "intensity", "t"], ["<f4", "<f4", "<f4", "<f4", "<u4"]
            if record.ring is not None:
                names, fmts = [*names, "ring"], [*fmts, "<u2"]
            arr = np.zeros(len(pts), dtype=np.dtype({"names": names, "formats": fmts}))
            arr["x"], arr["y"], arr["z"] = pts[:, 0], pts[:, 1], pts[:, 2]
            arr["intensity"] = record.intensity
            arr["t"] = np.rint(np.clip(np.asarray(record.point_times, np.float64), 0, None) * 1e9)
            if record.ring is not None:
                arr["ring"] = record.ring
            codes = {"<f4": 7, "<u4": 6, "<u2": 4}
            F = T["sensor_msgs/msg/PointField"]
            fields = [F(name=n, offset=arr.dtype.fields[n][1], datatype=codes[f], count=1) for n, f in zip(names, fmts)]
            return "sensor_msgs/msg/PointCloud2", T["sensor_msgs/msg/PointCloud2"](
                header=self._header(topic, record.t, "lidar"),
                height=1,
                width=len(arr),
                fields=fields,
                is_bigendian=False,
                point_step=arr.dtype.itemsize,
                row_step=arr.dtype.itemsize * len(arr),
                data=arr.view(np.uint8).reshape(-1).copy(),
                is_dense=True,
            )
        raise TypeError(f"the recorder cannot write {type(record).__name__}")

    def write(self, topic: str, record: Any, t_recv: float | None = None) -> None:
        msgtype, msg = self.message(topic, record)
        if topic not in self.conns:
            self.conns[topic] = self.writer.add_connection(topic, msgtype, typestore=self.store)
        ns = round((record.t if t_recv is None else t_recv) * 1e9)
        try:
            self.writer.write(self.conns[topic], ns, self.store.serialize_ros1(msg, msgtype))
        except OSError as exc:
            raise DriverError(f"writing bag {self.path} failed: {exc}") from exc
        self.counts[topic] += 1
        if time.monotonic() - self._last_flush >= self.flush_interval:
            self.flush()

    def flush(self) -> None:
        """Write the open chunk to the file and hand it to the operating system."""
        self._last_flush = time.monotonic()
        w = self.writer
        if w.bio is None:
            return
        try:
            w.write_chunk(w.chunks[-1])
            w.bio.flush()
        except OSError as exc:
            raise DriverError(f"writing bag {self.path} failed: {exc}") from exc

    def close(self) -> None:
        if self.writer.bio is not None:
            self.writer.close()

    def __enter__(self) -> BagRecorder:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


# ----------------------------------------------------------------------------- reindex
# (lives in jaxslam.io so that `jaxslam run` can repair a cut bag itself; re-exported here)
from jaxslam.io._reindex import reindex  # noqa: E402

# ----------------------------------------------------------------------------- recorder


def _pump(name: str, gen: Any, q: queue.Queue, stop: threading.Event) -> None:
    """Run a source's record generator in a thread, putting ``(name, record, t_recv)``."""
    try:
        for rec in gen:
            while True:  # never block forever on a full queue once the recorder stops
                try:
                    q.put((name, rec, time.time()), timeout=0.2)
                    break
                except queue.Full:
                    if stop.is_set():
                        return
            if stop.is_set():
                break
    except JaxSlamError as exc:
        q.put((name, exc, time.time()))
    except Exception as exc:  # a bug or an unexpected device error: report, do not hang
        q.put((name, DriverError(f"{name}: {type(exc).__name__}: {exc}"), time.time()))


def record(args: argparse.Namespace) -> dict[str, int]:
    """Open the sources, record until ``--duration`` or a signal; return the message counts."""
    sources: list[tuple[str, Any, Any]] = []  # (name, generator, closer)
    stop = threading.Event()
    try:
        if args.imu:
            from .witmotion import WitMotionSerial

            imu = WitMotionSerial(args.imu, args.imu_baud, timeout=0.05, latency=args.imu_latency)
            sources.append(("imu", imu.read_samples(), imu))
        if args.lidar_port is not None:
            from .livox import LivoxUDP

            lidar = LivoxUDP(args.lidar_host, args.lidar_port, args.lidar_imu_port, timeout=0.05)
            sources.append(("lidar", lidar.recv(), lidar))
        if args.camera is not None:
            from .camera import CameraSource

            src = int(args.camera) if args.camera.isdigit() else args.camera
            cam = CameraSource(src, camera=args.camera_name, fps=args.camera_fps, loop=args.camera_loop)
            sources.append(("camera", cam.frames(), cam))
        if not sources:
            raise ConfigError("nothing to record: pass --imu, --lidar-port and/or --camera")
        bag = BagRecorder(args.output, args.flush)
    except BaseException:
        for _, _, closer in sources:
            closer.close()
        raise
    q: queue.Queue = queue.Queue(maxsize=10000)
    threads = [threading.Thread(target=_pump, args=(n, gen, q, stop), daemon=True, name=n) for n, gen, _ in sources]
    for th in threads:
        th.start()

    def on_signal(signum: int, _frame: Any) -> None:
        stop.set()

    signal.signal(signal.SIGTERM, on_signal)
    signal.signal(signal.SIGINT, on_signal)
    print(f"recording {', '.join(n for n, _, _ in sources)} to {bag.path}", file=sys.stderr, flush=True)
    deadline = None if args.duration is None else time.monotonic() + args.duration
    error: BaseException | None = None
    try:
        while not stop.is_set() and (deadline is None or time.monotonic() < deadline):
            try:
                name, rec, t_recv = q.get(timeout=0.05)
            except queue.Empty:
                if time.monotonic() - bag._last_flush >= bag.flush_interval:
                    bag.flush()
                continue
            if isinstance(rec, BaseException):
                error = rec
                break
            if name == "imu":
                topic = TOPICS["imu"]
            elif name == "lidar":
                topic = TOPICS["lidar_imu"] if isinstance(rec, ImuSample) else TOPICS["lidar"]
            else:
                topic = rec.camera if rec.camera.startswith("/") else f"/{rec.camera}/image_raw"
            bag.write(topic, rec, t_recv)
    finally:
        stop.set()
        bag.close()
        # Let the source threads leave their C calls (OpenCV, sockets) before the
        # interpreter exits: a daemon thread killed inside OpenCV aborts the process.
        for th in threads:
            th.join(timeout=2.0)
        for _, _, closer in sources:
            with contextlib.suppress(Exception):
                closer.close()
    counts = dict(bag.counts)
    print(f"wrote {bag.path}: {counts}", file=sys.stderr, flush=True)
    if error is not None:
        raise error
    return counts


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m drivers.record", description=__doc__.split("\n\n")[0])
    p.add_argument("--imu", metavar="PORT", help="WitMotion serial port (/dev/ttyUSB0)")
    p.add_argument("--imu-baud", type=int, default=115200, help="the sensor's baud rate (factory default 9600)")
    p.add_argument("--imu-latency", type=float, default=0.0, help="constant subtracted from IMU host stamps (s)")
    p.add_argument("--lidar-port", type=int, help="Livox point-cloud UDP port (57000)")
    p.add_argument("--lidar-imu-port", type=lambda s: None if s == "none" else int(s), default=None,
                   help="Livox IMU UDP port (58000); default none")  # fmt: skip
    p.add_argument("--lidar-host", default="0.0.0.0", help="address to bind the Livox ports on")
    p.add_argument("--camera", metavar="SRC", help="device index, image folder or video file")
    p.add_argument("--camera-name", default="cam0", help="topic /<name>/image_raw")
    p.add_argument("--camera-fps", type=float, default=None, help="replay rate of a folder/video (0: fast)")
    p.add_argument("--camera-loop", action="store_true", help="replay a folder/video in a loop")
    p.add_argument("-o", "--output", required=True, help="the ROS1 bag to create (must not exist)")
    p.add_argument("--duration", type=float, help="seconds to record (default: until Ctrl-C)")
    p.add_argument("--flush", type=float, default=FLUSH_INTERVAL, help="seconds between chunk flushes")
    return p


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    try:
        if argv[:1] == ["reindex"]:
            p = argparse.ArgumentParser(prog="python -m drivers.record reindex", description=reindex.__doc__)
            p.add_argument("bag")
            p.add_argument("-o", "--output", help="write here instead of repairing in place")
            a = p.parse_args(argv[1:])
            stats = reindex(a.bag, a.output)
            print(f"reindexed {a.bag}: {stats}")
            return 0
        record(_parser().parse_args(argv))
        return 0
    except JaxSlamError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())

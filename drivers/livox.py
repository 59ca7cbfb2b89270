"""Livox HAP (SDK2 protocol) point-cloud and IMU UDP packets: parser, frame assembler, receiver.

Every data datagram (points on host port 57000, IMU on 58000 by FIELD-NOTES; both
configurable) is a 36-byte header then ``dot_num`` records, all little-endian::

    offset  size  field          use here
    0       1     version        must be 0
    1       2     length         bytes of the whole datagram, header included: must match
    3       2     time_interval  0.1 µs units: time spanned by the packet's points
    5       2     dot_num        number of records: must match the payload size
    7       2     udp_cnt        per-stream packet counter: gaps counted as ``lost_packets``
    9       1     frame_cnt      not used (frames are cut by time, see below)
    10      1     data_type      0 IMU, 1 Cartesian high, 2 Cartesian low (3 spherical and
                                 0x11 dual echo: counted as ``unsupported_type``)
    11      1     time_type      0 no sync (time since power-on), 1 PTP/gPTP, 2 GPS
    12      1     pack_info      not used (Mid-360 puts a tag type here; HAP: reserved)
    13      11    reserved
    24      4     crc32          checked only with ``check_crc=True``, see below
    28      8     timestamp      uint64 ns of the first point, clock per ``time_type``
    36      ...   data

Records: Cartesian high (1): ``int32 x, y, z`` (mm), ``uint8 reflectivity``, ``uint8 tag``
(14 bytes); Cartesian low (2): ``int16 x, y, z`` (cm), reflectivity, tag (8 bytes); IMU (0):
``float32 gyro_x, gyro_y, gyro_z`` (rad/s), ``float32 acc_x, acc_y, acc_z`` (g), 24 bytes,
``dot_num`` = 1.

Source: the ``LivoxLidarEthernetPacket``, ``LivoxLidarCartesianHighRawPoint``,
``...LowRawPoint`` and ``LivoxLidarImuRawPoint`` structs and the data-type enum in Livox-SDK2's
``include/livox_lidar_def.h`` (there ``pack_info`` is the first of 12 reserved bytes; the
Mid-360 protocol page names it). **Unsure**: (a) the CRC: the protocol pages say crc32 covers
"timestamp + data"; we check ``zlib.crc32(datagram[28:length])`` (CRC-32/ISO-HDLC), not
confirmed on a HAP, so it is off by default; (b) per-point times: the header only gives the
packet's ``time_interval``; point ``i`` gets ``timestamp + i * time_interval * 100 ns /
dot_num``, as livox_ros_driver2 spreads them; (c) ``ring``: livox_ros_driver2 numbers HAP
"lines" as point index modulo 6 (``lines=6`` here; ``None`` leaves ``ring`` unset); (d) the
``udp_cnt`` semantics (one counter per stream, +1 per datagram). Units of the IMU (rad/s,
g) follow livox_ros_driver2, which publishes them unscaled as ROS ``Imu`` (acc then in g).

**Frames.** Points are cut into :class:`LidarScan` frames of ``frame_period`` (0.1 s, the HAP's
10 Hz) of *sensor* time. A frame's ``t`` is the timestamp of its first packet (the next
frame's is the previous ``t + frame_period``, or its first point's time after a gap of more
than one period); ``point_times`` are relative to ``t``, in [0, frame_period). A point at or
after ``t + frame_period`` closes the frame (a packet straddling the boundary is split). A
frame is emitted when the next frame's first point arrives, or by :meth:`LivoxStream.flush`.
Points at exactly (0, 0, 0) (no return) are dropped and counted. A packet up to one period
older than the open frame is dropped (``late_packets``); a larger jump back (clock reset, sync
acquired) closes the frame and restarts (``time_resets``).

**Time.** Stamps are the sensor's clock. Without gPTP (``time_type`` 0, counted as
``unsynced_packets``) that is time since power-on, unrelated to the host clock: unlike the ROS
driver we never substitute host arrival time silently; the caller decides.

The receiver sends no control commands: point/IMU streaming and the host IP/ports are
configured beforehand (Livox Viewer 2 or the SDK2 control protocol on port 56000).
"""

from __future__ import annotations

import dataclasses
import math
import select
import socket
import struct
import time
import zlib
from collections.abc import Iterator

import numpy as np

from jaxslam.errors import ConfigError, InputFormatError
from jaxslam.measurements import ImuSample, LidarScan

from ._common import Counters, DriverError, G

HEADER = struct.Struct("<BHHHHBBBB11sIQ")
HEADER_SIZE = HEADER.size  # 36
POINT_PORT, IMU_PORT, COMMAND_PORT = 57000, 58000, 56000

IMU_DATA, CARTESIAN_HIGH, CARTESIAN_LOW, SPHERICAL, DUAL_ECHO = 0x00, 0x01, 0x02, 0x03, 0x11
TIME_TYPES = {0: "none", 1: "ptp", 2: "gps"}

HIGH_POINT = np.dtype([("x", "<i4"), ("y", "<i4"), ("z", "<i4"), ("reflectivity", "u1"), ("tag", "u1")])
LOW_POINT = np.dtype([("x", "<i2"), ("y", "<i2"), ("z", "<i2"), ("reflectivity", "u1"), ("tag", "u1")])
IMU_RECORD = np.dtype([("gyro", "<f4", (3,)), ("acc", "<f4", (3,))])
RECORD_SIZE = {IMU_DATA: IMU_RECORD.itemsize, CARTESIAN_HIGH: HIGH_POINT.itemsize, CARTESIAN_LOW: LOW_POINT.itemsize}
POINT_SCALE = {CARTESIAN_HIGH: 1e-3, CARTESIAN_LOW: 1e-2}  # m per unit (mm, cm)


class PacketError(InputFormatError):
    """A datagram that is not a valid Livox data packet; ``reason`` names the counter."""

    def __init__(self, reason: str, message: str):
        self.reason = reason
        super().__init__(message, "livox")


@dataclasses.dataclass(frozen=True)
class LivoxPacket:
    """One parsed datagram.

    Header fields as named in the module table (``timestamp_ns`` is the 8-byte timestamp).
    Point packets: ``points`` (N, 3) m, ``reflectivity`` and ``tag`` (N,) uint8,
    ``offsets_ns`` (N,) int64 time of each point after ``timestamp_ns``. IMU packets:
    ``gyro`` (3,) rad/s and ``acc`` (3,) m/s^2 (converted from g); point arrays empty.
    """

    version: int
    length: int
    time_interval: int
    dot_num: int
    udp_cnt: int
    frame_cnt: int
    data_type: int
    time_type: int
    pack_info: int
    crc32: int
    timestamp_ns: int
    points: np.ndarray
    reflectivity: np.ndarray
    tag: np.ndarray
    offsets_ns: np.ndarray
    gyro: np.ndarray | None = None
    acc: np.ndarray | None = None

    @property
    def is_imu(self) -> bool:
        return self.data_type == IMU_DATA


def build_packet(
    data_type: int,
    payload: bytes,
    dot_num: int,
    *,
    timestamp_ns: int = 0,
    time_interval: int = 0,
    udp_cnt: int = 0,
    frame_cnt: int = 0,
    time_type: int = 1,
    version: int = 0,
    length: int | None = None,
) -> bytes:
    """A datagram with a correct ``crc32`` (as checked here) around ``payload`` (tests, simulators)."""
    n = HEADER_SIZE + len(payload) if length is None else length
    head = HEADER.pack(version, n, time_interval, dot_num, udp_cnt, frame_cnt, data_type, time_type, 0, bytes(11), 0, 0)
    tail = struct.pack("<Q", timestamp_ns) + payload
    crc = zlib.crc32(tail) & 0xFFFFFFFF
    return head[:24] + struct.pack("<I", crc) + tail


def _points_payload(dtype: np.dtype, xyz: np.ndarray, reflectivity: np.ndarray | None, tag: np.ndarray | None) -> bytes:
    xyz = np.asarray(xyz)
    rec = np.zeros(len(xyz), dtype)
    rec["x"], rec["y"], rec["z"] = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    rec["reflectivity"] = 0 if reflectivity is None else reflectivity
    rec["tag"] = 0 if tag is None else tag
    return rec.tobytes()


def high_points_payload(
    xyz_mm: np.ndarray, reflectivity: np.ndarray | None = None, tag: np.ndarray | None = None
) -> bytes:
    """Cartesian-high records (14 bytes each) from (N, 3) int millimetres."""
    return _points_payload(HIGH_POINT, xyz_mm, reflectivity, tag)


def low_points_payload(
    xyz_cm: np.ndarray, reflectivity: np.ndarray | None = None, tag: np.ndarray | None = None
) -> bytes:
    """Cartesian-low records (8 bytes each) from (N, 3) int centimetres."""
    return _points_payload(LOW_POINT, xyz_cm, reflectivity, tag)


def imu_payload(gyro: np.ndarray, acc_g: np.ndarray) -> bytes:
    """One IMU record: gyro (rad/s) then acc (g), six float32."""
    return struct.pack("<6f", *np.asarray(gyro, dtype=float), *np.asarray(acc_g, dtype=float))


_EMPTY_F = np.zeros((0, 3))
_EMPTY_U8 = np.zeros(0, np.uint8)
_EMPTY_I64 = np.zeros(0, np.int64)


def parse_packet(data: bytes | bytearray | memoryview, *, check_crc: bool = False) -> LivoxPacket:
    """Parse one datagram; raise :class:`PacketError` (an ``InputFormatError``) if malformed."""
    n = len(data)
    if n < HEADER_SIZE:
        raise PacketError("too_short", f"datagram of {n} bytes is shorter than the 36-byte header")
    (version, length, interval, dot_num, udp_cnt, frame_cnt, dtype, time_type, pack_info, _, crc, ts) = (
        HEADER.unpack_from(data, 0)
    )
    if version != 0:
        raise PacketError("bad_version", f"protocol version {version}, expected 0")
    if length != n:
        raise PacketError("bad_length", f"header length {length} != datagram size {n}")
    if dtype not in RECORD_SIZE:
        if dtype in (SPHERICAL, DUAL_ECHO):
            raise PacketError("unsupported_type", f"data type {dtype:#x} (spherical/dual echo) is not supported")
        raise PacketError("unknown_type", f"unknown data type {dtype:#x}")
    size = RECORD_SIZE[dtype]
    if n - HEADER_SIZE != dot_num * size:
        raise PacketError(
            "bad_dot_num", f"dot_num {dot_num} x {size} bytes != payload of {n - HEADER_SIZE} bytes (type {dtype})"
        )
    if check_crc and zlib.crc32(bytes(data[28:n])) & 0xFFFFFFFF != crc:
        raise PacketError("bad_crc", "crc32 of timestamp + data does not match")
    common = dict(
        version=version,
        length=length,
        time_interval=interval,
        dot_num=dot_num,
        udp_cnt=udp_cnt,
        frame_cnt=frame_cnt,
        data_type=dtype,
        time_type=time_type,
        pack_info=pack_info,
        crc32=crc,
        timestamp_ns=ts,
    )
    if dtype == IMU_DATA:
        if dot_num != 1:
            raise PacketError("bad_dot_num", f"IMU packet with dot_num {dot_num}, expected 1")
        rec = np.frombuffer(data, IMU_RECORD, count=1, offset=HEADER_SIZE)[0]
        with np.errstate(all="ignore"):  # a signalling NaN warns on the cast: reject it below
            gyro = rec["gyro"].astype(np.float64)
            acc = rec["acc"].astype(np.float64) * G
        if not (np.all(np.isfinite(gyro)) and np.all(np.isfinite(acc))):
            raise PacketError("invalid_imu", "IMU packet holds NaN or inf")
        return LivoxPacket(
            **common,
            points=_EMPTY_F,
            reflectivity=_EMPTY_U8,
            tag=_EMPTY_U8,
            offsets_ns=_EMPTY_I64,
            gyro=gyro,
            acc=acc,
        )
    rec = np.frombuffer(data, HIGH_POINT if dtype == CARTESIAN_HIGH else LOW_POINT, count=dot_num, offset=HEADER_SIZE)
    scale = POINT_SCALE[dtype]
    points = np.stack([rec["x"], rec["y"], rec["z"]], axis=1).astype(np.float64) * scale
    offsets = (np.arange(dot_num, dtype=np.int64) * (interval * 100)) // max(dot_num, 1)
    return LivoxPacket(
        **common,
        points=points,
        reflectivity=rec["reflectivity"].copy(),
        tag=rec["tag"].copy(),
        offsets_ns=offsets,
    )


_COUNTERS = (
    "datagrams",
    "point_packets",
    "imu_packets",
    "points",
    "zero_points",
    "frames",
    "imu_samples",
    "too_short",
    "bad_version",
    "bad_length",
    "unknown_type",
    "unsupported_type",
    "bad_dot_num",
    "bad_crc",
    "invalid_imu",
    "invalid_frames",
    "late_packets",
    "late_points",
    "time_resets",
    "lost_packets",
    "unsynced_packets",
)


class LivoxStream:
    """Datagrams in, :class:`LidarScan` frames and :class:`ImuSample` records out.

    Args:
        frame_period: frame length (s) of sensor time; 0.1 for the HAP's 10 Hz.
        lines: ``ring`` = point index in its packet modulo ``lines`` (6 for the HAP, as
            livox_ros_driver2); ``None``: no ring.
        drop_zero: drop points at exactly (0, 0, 0) (no return).
        check_crc: verify ``crc32`` (see the module notes: unconfirmed on hardware).
        max_points: a frame reaching this many points is emitted early.

    ``counters`` counts every datagram's fate (module docstring); :meth:`feed` never raises
    on bad input.
    """

    def __init__(
        self,
        frame_period: float = 0.1,
        *,
        lines: int | None = 6,
        drop_zero: bool = True,
        check_crc: bool = False,
        max_points: int = 2_000_000,
    ):
        if not (math.isfinite(frame_period) and frame_period > 0):
            raise ConfigError(f"frame_period must be positive, got {frame_period}")
        self.period_ns = round(frame_period * 1e9)
        self.lines = lines
        self.drop_zero = drop_zero
        self.check_crc = check_crc
        self.max_points = max_points
        self.counters = Counters(*_COUNTERS)
        self.time_type: int | None = None
        self._start: int | None = None  # frame start, sensor ns
        self._parts: list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray | None]] = []
        self._npoints = 0
        self._last_cnt: dict[bool, int] = {}

    def feed(self, datagram: bytes | bytearray | memoryview) -> list[LidarScan | ImuSample]:
        """Parse one datagram; return the frames it closed and the IMU sample it carried."""
        self.counters.add("datagrams")
        try:
            pkt = parse_packet(datagram, check_crc=self.check_crc)
        except PacketError as exc:
            self.counters.add(exc.reason)
            return []
        self._count_gap(pkt)
        self.time_type = pkt.time_type
        if pkt.time_type == 0:
            self.counters.add("unsynced_packets")
        if pkt.acc is not None and pkt.gyro is not None:  # an IMU packet
            self.counters.add("imu_packets")
            sample = ImuSample(t=pkt.timestamp_ns * 1e-9, acc=pkt.acc, gyro=pkt.gyro)
            self.counters.add("imu_samples")
            return [sample]
        self.counters.add("point_packets")
        return [*self._add_points(pkt)]

    def flush(self) -> list[LidarScan]:
        """Emit the open frame (end of stream)."""
        out = self._emit()
        self._start = None
        return out

    def _count_gap(self, pkt: LivoxPacket) -> None:
        last = self._last_cnt.get(pkt.is_imu)
        if last is not None:
            gap = (pkt.udp_cnt - last - 1) % 65536
            if 0 < gap < 32768:
                self.counters.add("lost_packets", gap)
        self._last_cnt[pkt.is_imu] = pkt.udp_cnt

    def _add_points(self, pkt: LivoxPacket) -> list[LidarScan]:
        pts, refl, offsets = pkt.points, pkt.reflectivity, pkt.offsets_ns
        ring = None if self.lines is None else (np.arange(len(pts)) % self.lines).astype(np.uint16)
        if self.drop_zero:
            keep = np.any(pts != 0.0, axis=1)
            if not np.all(keep):
                self.counters.add("zero_points", int(np.count_nonzero(~keep)))
                pts, refl, offsets = pts[keep], refl[keep], offsets[keep]
                ring = None if ring is None else ring[keep]
        if len(pts) == 0:
            return []
        ts = pkt.timestamp_ns
        out: list[LidarScan] = []
        if self._start is None:
            self._start = ts
        rel0 = ts - self._start
        if rel0 < 0:
            if rel0 >= -self.period_ns:
                self.counters.add("late_packets")
                self.counters.add("late_points", len(pts))
                return out
            self.counters.add("time_resets")
            out += self._emit()
            self._start = ts
            rel0 = 0
        self.counters.add("points", len(pts))
        while len(pts):
            if rel0 >= self.period_ns:
                k = 0
            elif rel0 + int(offsets[-1]) < self.period_ns:
                k = len(pts)
            else:
                k = int(np.searchsorted(offsets, self.period_ns - rel0, side="left"))
            if k:
                times = rel0 + offsets[:k]
                self._parts.append((pts[:k], refl[:k], times, None if ring is None else ring[:k]))
                self._npoints += k
            if k == len(pts):
                if self._npoints >= self.max_points:
                    out += self._emit()
                    self._start = None
                break
            out += self._emit()
            first = rel0 + int(offsets[k])  # the first point of the next frame, rel. to the old start
            if first < 2 * self.period_ns:
                self._start += self.period_ns
            else:
                self._start = ts + int(offsets[k])
            rel0 = ts - self._start
            pts, refl, offsets = pts[k:], refl[k:], offsets[k:]
            ring = None if ring is None else ring[k:]
        return out

    def _emit(self) -> list[LidarScan]:
        if not self._parts or self._start is None:
            self._parts, self._npoints = [], 0
            return []
        parts, self._parts, self._npoints = self._parts, [], 0
        scan = LidarScan(
            t=self._start * 1e-9,
            points=np.concatenate([p[0] for p in parts]),
            intensity=np.concatenate([p[1] for p in parts]).astype(np.float64),
            point_times=np.concatenate([p[2] for p in parts]).astype(np.float64) * 1e-9,
            ring=None if parts[0][3] is None else np.concatenate([p[3] for p in parts]),
        )
        try:
            scan.validate("livox")
        except InputFormatError:  # pragma: no cover - integer points are always finite
            self.counters.add("invalid_frames")
            return []
        self.counters.add("frames")
        return [scan]


class LivoxUDP:
    """Receive a Livox's point and IMU datagrams on UDP ports and assemble records.

    Binds ``host`` (``"0.0.0.0"`` for all interfaces; tests use ``"127.0.0.1"``) on
    ``point_port`` and ``imu_port`` (``None``: points only; port 0 picks a free port, read
    back from ``ports``). ``timeout`` (s) bounds each wait in :meth:`recv`. Other keyword
    arguments go to :class:`LivoxStream`. Bind/receive failures raise
    :class:`~drivers._common.DriverError`. Usable as a context manager.
    """

    def __init__(
        self,
        host: str = "0.0.0.0",
        point_port: int = POINT_PORT,
        imu_port: int | None = IMU_PORT,
        *,
        timeout: float = 0.1,
        rcvbuf: int = 8 << 20,
        **stream_options,
    ):
        self.stream = LivoxStream(**stream_options)
        self.timeout = timeout
        self.timeouts = 0
        self._pending: list[LidarScan | ImuSample] = []
        self.sockets: list[socket.socket] = []
        try:
            for port in (point_port, imu_port):
                if port is None:
                    continue
                sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
                self.sockets.append(sock)
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, rcvbuf)  # the kernel caps it (rmem_max)
                sock.bind((host, port))
                sock.setblocking(False)
        except OSError as exc:
            self.close()
            raise DriverError(f"cannot bind Livox UDP {host}:{point_port}/{imu_port}: {exc}") from exc

    @property
    def ports(self) -> list[int]:
        """The bound port numbers (points first)."""
        return [s.getsockname()[1] for s in self.sockets]

    @property
    def counters(self) -> Counters:
        return self.stream.counters

    def poll(self, timeout: float | None = 0.0) -> list[LidarScan | ImuSample]:
        """Wait up to ``timeout`` s for datagrams, then parse every queued one."""
        try:
            ready, _, _ = select.select(self.sockets, [], [], timeout)
        except (OSError, ValueError) as exc:
            raise DriverError(f"waiting on Livox UDP sockets failed: {exc}") from exc
        out: list[LidarScan | ImuSample] = []
        for sock in ready:
            while True:
                try:
                    data = sock.recv(65535)
                except BlockingIOError:
                    break
                except OSError as exc:
                    raise DriverError(f"receiving Livox UDP failed: {exc}") from exc
                out += self.stream.feed(data)
        return out

    def recv(
        self, duration: float | None = None, max_records: int | None = None, *, flush: bool = True
    ) -> Iterator[LidarScan | ImuSample]:
        """Yield frames and IMU samples until ``duration`` s passed or ``max_records`` were
        yielded (both ``None``: forever); waits time out every ``timeout`` s (counted in
        ``timeouts``). Records received beyond ``max_records`` are kept for the next call.
        When ``duration`` ends the loop, ``flush`` also yields the open frame."""
        deadline = None if duration is None else time.monotonic() + duration
        emitted = 0
        while max_records is None or emitted < max_records:
            if not self._pending:
                wait = self.timeout
                if deadline is not None:
                    left = deadline - time.monotonic()
                    if left <= 0:
                        if flush:
                            yield from self.stream.flush()
                        return
                    wait = min(wait, left)
                self._pending += self.poll(wait)
                if not self._pending:
                    self.timeouts += 1
                    continue
            yield self._pending.pop(0)
            emitted += 1

    def close(self) -> None:
        for sock in self.sockets:
            sock.close()

    def __enter__(self) -> LivoxUDP:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

"""ROS1 (``.bag``) and ROS2 (sqlite ``.db3``, ``.mcap``) recordings via ``rosbags``' AnyReader.

Messages -> records:

- ``sensor_msgs/Imu`` -> :class:`ImuSample` (``linear_acceleration`` m/s^2, ``angular_velocity``
  rad/s).
- ``sensor_msgs/Image`` (``mono8``, ``rgb8``, ``bgr8`` -> uint8; ``mono16`` -> float32 in [0, 1])
  and ``sensor_msgs/CompressedImage`` (png/jpeg, decoded with Pillow) -> :class:`Image` with
  ``camera=<topic>``. Other encodings or undecodable data are skipped and counted.
- ``sensor_msgs/PointCloud2`` -> :class:`LidarScan`: fields ``x y z`` (m), ``intensity`` (zeros
  when absent), ``ring`` when present, and a per-point time field, the first of ``t``,
  ``time``, ``timestamp``, ``offset_time``. Units: an integer field is nanoseconds (Ouster
  ``t``, Livox ``offset_time``), a float field seconds (Velodyne ``time``, Hesai
  ``timestamp``); values above 1e6 s are absolute and made relative to the scan time. No
  time field -> zeros. Points with a non-finite coordinate are dropped (organised clouds
  mark missing returns with NaN).
- ``livox_ros_driver2/CustomMsg`` (definition registered here from :data:`LIVOX_CUSTOM_MSG`)
  -> :class:`LidarScan`: ``x y z``, ``reflectivity`` as intensity, point times
  ``timebase + offset_time`` (ns) relative to the scan time.
- ``geometry_msgs/PoseStamped``, ``PoseWithCovarianceStamped``, ``nav_msgs/Odometry``,
  ``TransformStamped`` -> :class:`PoseStamped` (qw qx qy qz x y z); ``tf2_msgs/TFMessage`` on
  ``/tf`` only with ``tf=(parent, child)`` (that one transform, leading ``/`` ignored).
- ``geometry_msgs/PointStamped`` -> :class:`PositionFix` (total-station prism fixes, as the
  writers and the simulator put them on ``/total_station/prism``): ``point`` (m) and the
  standard deviation from ``sigma=<m>`` in ``header.frame_id`` (``world;sigma=0.004``); without
  one the fix gets :data:`DEFAULT_FIX_SIGMA`; a ``sigma=`` that is not a positive number skips
  the message (counted).

A message that cannot be decoded or converted (a cloud whose buffer is shorter than its
fields say, an unsupported encoding) is skipped and counted; a read error part-way through a
bag ends the iteration with a warning naming the file and the number of messages read.

Times: the header stamp (sensor time) by default; ``time="receive"`` uses the bag's receive
time instead (for drivers that leave stamps at zero). Bags are stored in receive order, so
records are re-ordered within ``reorder_window`` seconds (default 1.0); a record later than
that is counted as "time not increasing" and skipped.

Topics: ``topics={"imu": "/imu", "image": "/cam0/image_raw", ...}`` chooses one topic per kind
(a missing one raises InputFormatError listing the topics). Otherwise each kind is guessed by
message type: among several candidates the topic with the most messages wins (for ``pose``, a
topic whose name contains ``groundtruth``/``ground_truth``/``gt`` wins first; for
``position``, one whose name contains ``total_station``/``prism``); the stream's ``note`` says so.

A ROS1 bag whose header has no index (a recorder killed before it closed the bag) raises
InputFormatError saying so; ``python -m drivers.record reindex BAG`` rebuilds the index from
the chunks that reached the disk.
"""

from __future__ import annotations

import contextlib
import heapq
import itertools
import re
import struct
import warnings
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import jax.numpy as jnp
import numpy as np
from rosbags.highlevel import AnyReader, AnyReaderError
from rosbags.rosbag1 import ReaderError as Rosbag1ReaderError
from rosbags.rosbag2 import ReaderError as Rosbag2ReaderError
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from ..errors import InputFormatError
from ..lie import SE3
from ..measurements import Image, ImuSample, LidarScan, Measurement, PoseStamped, PositionFix
from ._recording import Recording, StreamInfo, read_image_file
from ._trajectory import Trajectory, read_tum

LIVOX_CUSTOM_POINT = """uint32 offset_time
float32 x
float32 y
float32 z
uint8 reflectivity
uint8 tag
uint8 line
"""
"""``livox_ros_driver2/msg/CustomPoint``: ``offset_time`` ns from the message's ``timebase``."""

LIVOX_CUSTOM_MSG = """std_msgs/Header header
uint64 timebase
uint32 point_num
uint8 lidar_id
uint8[3] rsvd
CustomPoint[] points
"""
"""``livox_ros_driver2/msg/CustomMsg`` (Livox ROS driver 2): ``timebase`` ns, the scan start."""

KINDS: dict[str, tuple[str, ...]] = {
    "imu": ("sensor_msgs/msg/Imu",),
    "image": ("sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage"),
    "lidar": ("sensor_msgs/msg/PointCloud2", "livox_ros_driver2/msg/CustomMsg"),
    "pose": (
        "geometry_msgs/msg/PoseStamped",
        "geometry_msgs/msg/PoseWithCovarianceStamped",
        "nav_msgs/msg/Odometry",
        "geometry_msgs/msg/TransformStamped",
    ),
    "position": ("geometry_msgs/msg/PointStamped",),
}
"""Message types read as each record kind."""

DEFAULT_FIX_SIGMA = PositionFix.sigma
"""Standard deviation (m) of a PointStamped fix whose ``frame_id`` carries no ``sigma=``."""

_SIGMA = re.compile(r"(?:^|[;,\s])sigma=([^;,\s]*)")


def fix_sigma(frame_id: str) -> float:
    """The ``sigma=<m>`` of a PointStamped ``frame_id`` (:data:`DEFAULT_FIX_SIGMA` when absent);
    raises InputFormatError when it is not a positive finite number."""
    m = _SIGMA.search(frame_id)
    if m is None:
        return float(DEFAULT_FIX_SIGMA)
    try:
        sigma = float(m.group(1))
    except ValueError:
        raise InputFormatError(f"frame_id {frame_id!r}: sigma is not a number") from None
    if not (np.isfinite(sigma) and sigma > 0):
        raise InputFormatError(f"frame_id {frame_id!r}: sigma must be positive and finite")
    return sigma


_GT_NAME = re.compile(r"ground_?truth|(^|[/_])gt($|[/_])", re.IGNORECASE)
_FIX_NAME = re.compile(r"total_?station|prism", re.IGNORECASE)
_READ_ERRORS = (
    AnyReaderError,
    Rosbag1ReaderError,
    Rosbag2ReaderError,
    OSError,
    ValueError,
    KeyError,
    IndexError,
    EOFError,
    struct.error,
    OverflowError,
    AssertionError,  # rosbags asserts on some inconsistent records
    MemoryError,  # a corrupt length field asking for an impossible allocation
    TypeError,  # a truncated connection header (ord('') in rosbags' header parser)
    SyntaxError,  # a corrupt message definition: rosbags compiles definitions into code
)
"""What rosbags raises on a corrupt file (found by benchmarks/fuzz.py): turned into
InputFormatError at open, a counted skip per message, or a warning ending the iteration."""


_CONVERT_ERRORS = (InputFormatError, ValueError, TypeError, AttributeError, IndexError, OverflowError, MemoryError)
"""What converting a decoded but inconsistent message raises: the message is skipped and counted."""


def _describe(err: BaseException) -> str:
    if isinstance(err, MemoryError):
        return "a record declares an impossible size (corrupt file)"
    return str(err) or type(err).__name__


def _unindexed_ros1(path: Path) -> bool:
    """Whether a file is a ROS1 v2.0 bag without a usable index: its header says
    ``index_pos=0`` (never closed) or points past the end of the file (truncated)."""
    try:
        with open(path, "rb") as f:
            head = f.read(4096)
    except OSError:
        return False
    key = b"index_pos="
    i = head.find(key)
    if not head.startswith(b"#ROSBAG V2.0\n") or i < 0 or len(head) < i + len(key) + 8:
        return False
    index_pos = int.from_bytes(head[i + len(key) : i + len(key) + 8], "little")
    if index_pos == 0:
        return True
    try:  # an index position past the end of the file: cut short (power loss) after closing began
        return index_pos >= path.stat().st_size
    except OSError:
        return False


def livox_types() -> dict[str, Any]:
    """rosbags type definitions for the Livox ``CustomPoint`` / ``CustomMsg`` messages."""
    typs = dict(get_types_from_msg(LIVOX_CUSTOM_POINT, "livox_ros_driver2/msg/CustomPoint"))
    typs.update(get_types_from_msg(LIVOX_CUSTOM_MSG, "livox_ros_driver2/msg/CustomMsg"))
    return typs


def default_typestore(ros1: bool = False) -> Any:
    """The typestore used when a bag carries no message definitions: ROS2 Humble (or ROS1
    Noetic) plus the Livox messages."""
    store = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
    store.register(livox_types())
    return store


def _stamp(header: Any) -> int:
    return int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)


def _pose_params(position: Any, orientation: Any) -> np.ndarray:
    o, p = orientation, position
    return np.array([o.w, o.x, o.y, o.z, p.x, p.y, p.z], dtype=np.float64)


def _vec(v: Any) -> np.ndarray:
    return np.array([v.x, v.y, v.z], dtype=np.float64)


_PC2_TYPES = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 8: "f8"}
_TIME_FIELDS = ("t", "time", "timestamp", "offset_time")


def pointcloud2_arrays(msg: Any, t_ns: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray | None]:
    """``points`` (N, 3), ``intensity`` (N,), ``point_times`` (N,) s relative to ``t_ns`` and
    ``ring`` (N,) or None from a PointCloud2 message (units: see the module docstring)."""
    fields = {f.name: f for f in msg.fields}
    if not all(k in fields for k in "xyz"):
        raise InputFormatError(f"PointCloud2 needs fields x y z, has {sorted(fields)}")
    order = ">" if msg.is_bigendian else "<"
    names = [n for n in ("x", "y", "z", "intensity", "ring", *_TIME_FIELDS) if n in fields]
    unknown = [n for n in names if fields[n].datatype not in _PC2_TYPES]
    if unknown:
        raise InputFormatError(f"PointCloud2 field {unknown[0]!r} has unknown datatype")
    dtype = np.dtype(
        {
            "names": names,
            "formats": [order + _PC2_TYPES[fields[n].datatype] for n in names],
            "offsets": [fields[n].offset for n in names],
            "itemsize": msg.point_step,
        }
    )
    n = int(msg.width) * int(msg.height)
    raw = np.frombuffer(np.asarray(msg.data, dtype=np.uint8).tobytes(), dtype=np.uint8)
    rows = raw[: msg.row_step * msg.height].reshape(msg.height, msg.row_step)[:, : msg.point_step * msg.width]
    arr = np.frombuffer(np.ascontiguousarray(rows).tobytes(), dtype=dtype, count=n)
    pts = np.stack([arr["x"], arr["y"], arr["z"]], axis=1).astype(np.float64)
    inten = arr["intensity"].astype(np.float64) if "intensity" in names else np.zeros(n)
    ring = arr["ring"].astype(np.int64) if "ring" in names else None
    times = np.zeros(n)
    tname = next((k for k in _TIME_FIELDS if k in names), None)
    if tname is not None:
        raw_t = arr[tname]
        times = raw_t.astype(np.float64) / (1e9 if raw_t.dtype.kind in "iu" else 1.0)
        if n and np.nanmax(np.abs(times)) > 1e6:
            times = times - t_ns / 1e9
    keep = np.all(np.isfinite(pts), axis=1)
    return pts[keep], inten[keep], times[keep], None if ring is None else ring[keep]


def image_array(msg: Any, msgtype: str) -> np.ndarray | None:
    """The pixels of an Image / CompressedImage message, or None for an unsupported encoding."""
    if msgtype.endswith("CompressedImage"):
        return read_image_file(np.asarray(msg.data, dtype=np.uint8).tobytes())
    enc, h, w, step = msg.encoding.lower(), int(msg.height), int(msg.width), int(msg.step)
    channels = {"mono8": (1, "u1"), "rgb8": (3, "u1"), "bgr8": (3, "u1"), "mono16": (1, "u2")}
    if enc not in channels:
        return None
    c, kind = channels[enc]
    dt = np.dtype((">" if msg.is_bigendian else "<") + kind)
    raw = np.asarray(msg.data, dtype=np.uint8)[: h * step].reshape(h, step)[:, : w * c * dt.itemsize]
    px = np.frombuffer(np.ascontiguousarray(raw).tobytes(), dtype=dt).reshape(h, w, c)
    if enc == "mono16":
        return (px[..., 0].astype(np.float32) / np.float32(65535.0)).astype(np.float32)
    if enc == "bgr8":
        px = px[..., ::-1]
    return np.ascontiguousarray(px[..., 0] if c == 1 else px)


class RosbagRecording(Recording):
    """A ROS1 or ROS2 bag (see the module docstring for the mapping and the options).

    Options: ``topics`` (kind -> topic), ``time`` (``"header"`` or ``"receive"``), ``tf``
    (``(parent_frame, child_frame)``: read that transform from ``/tf`` as the pose stream),
    ``ground_truth`` (a pose topic or a TUM file), ``reorder_window`` (s).
    """

    def __init__(
        self,
        path: str | Path,
        topics: dict[str, str] | None = None,
        time: str = "header",
        tf: tuple[str, str] | None = None,
        ground_truth: str | Path | None = None,
        reorder_window: float = 1.0,
    ):
        super().__init__(path)
        if time not in ("header", "receive"):
            raise ValueError(f"time must be 'header' or 'receive', got {time!r}")
        unknown = set(topics or {}) - set(KINDS)
        if unknown:
            raise ValueError(f"topics keys must be among {sorted(KINDS)}, got {sorted(unknown)}")
        self.time, self.tf, self.reorder_window = time, tf, float(reorder_window)
        self._gt = ground_truth
        with self._reader() as reader:
            self._all = {name: (info.msgtype or "", info.msgcount) for name, info in reader.topics.items()}
        self._chosen = self._choose(topics or {})
        self._streams: list[StreamInfo] | None = None

    @contextlib.contextmanager
    def _reader(self) -> Iterator[AnyReader]:
        """An open AnyReader; a bag that cannot be opened raises InputFormatError naming it."""
        ros1 = self.path.suffix == ".bag"
        try:
            reader = AnyReader([self.path], default_typestore=default_typestore(ros1))
            reader.open()
        except _READ_ERRORS as err:
            if ros1 and _unindexed_ros1(self.path):
                raise InputFormatError(
                    "ROS1 bag has no index (the recorder was stopped before closing it); "
                    f"rebuild it with: python -m drivers.record reindex {self.path}",
                    self.path,
                ) from None
            raise InputFormatError(f"cannot read bag: {_describe(err)}", self.path) from None
        try:
            yield reader
        finally:
            reader.close()

    def _choose(self, wanted: dict[str, str]) -> dict[str, tuple[str, str]]:
        """kind -> (topic, note)."""
        chosen: dict[str, tuple[str, str]] = {}
        listing = ", ".join(f"{t} ({m})" for t, (m, _) in sorted(self._all.items()))
        for kind, topic in wanted.items():
            if topic not in self._all:
                raise InputFormatError(f"no topic {topic!r} for {kind}; topics: {listing}", self.path)
            if self._all[topic][0] not in KINDS[kind]:
                raise InputFormatError(f"topic {topic!r} is {self._all[topic][0]}, not a {kind} type", self.path)
            chosen[kind] = (topic, "chosen by option")
        for kind, types in KINDS.items():
            if kind in chosen or (kind == "pose" and self.tf is not None):
                continue
            cands = [t for t, (m, _) in self._all.items() if m in types]
            if not cands:
                continue

            def rank(t: str, kind: str = kind) -> tuple[bool, int, str]:
                named = (kind == "pose" and bool(_GT_NAME.search(t))) or (
                    kind == "position" and bool(_FIX_NAME.search(t))
                )
                return (named, self._all[t][1], t)

            best = max(cands, key=rank)
            note = ""
            if len(cands) > 1:
                rule = {"pose": "a ground-truth name, then ", "position": "a total-station name, then "}.get(kind, "")
                note = f"guessed among {sorted(cands)} by {rule}most messages; pass topics= to choose"
            chosen[kind] = (best, note)
        if self.tf is not None and "pose" not in chosen:
            tf_topics = [t for t, (m, _) in self._all.items() if m == "tf2_msgs/msg/TFMessage"]
            if not tf_topics:
                raise InputFormatError(f"tf={self.tf} asked but the bag has no TF topic; topics: {listing}", self.path)
            chosen["pose"] = ("/tf" if "/tf" in tf_topics else tf_topics[0], f"tf {self.tf[0]} -> {self.tf[1]}")
        return chosen

    def streams(self) -> list[StreamInfo]:
        """The chosen streams; counts and the time span are from the bag index (receive time)."""
        if self._streams is None:
            out = []
            with self._reader() as reader:
                for kind, (topic, note) in self._chosen.items():
                    conns = [c for c in reader.connections if c.topic == topic]
                    ts = [t for _, t, _ in self._safe(reader.messages(connections=conns))]
                    span = (ts[0] / 1e9, ts[-1] / 1e9) if ts else (np.nan, np.nan)
                    out.append(StreamInfo(kind, topic, self._all[topic][0], len(ts), span[0], span[1], note))
            self._streams = out
        return self._streams

    def _safe(self, gen: Iterator[tuple[Any, int, bytes]]) -> Iterator[tuple[Any, int, bytes]]:
        """Yield from a message generator; a read error ends it with a warning and a count."""
        n = 0
        try:
            for item in gen:
                n += 1
                yield item
        except _READ_ERRORS as err:
            self.skipped["bag: unreadable remainder"] += 1
            warnings.warn(f"{self.path}: read stopped after {n} messages: {_describe(err)}", stacklevel=3)

    def _records(self) -> Iterator[tuple[str, Measurement]]:
        by_topic = {topic: kind for kind, (topic, _) in self._chosen.items()}
        heap: list[tuple[float, int, str, Measurement]] = []
        seq = itertools.count()
        with self._reader() as reader:
            conns = [c for c in reader.connections if c.topic in by_topic]
            for conn, t_recv, raw in self._safe(reader.messages(connections=conns)):
                try:
                    msg = reader.deserialize(raw, conn.msgtype)
                except _READ_ERRORS:
                    self.skipped[f"{conn.topic}: undecodable"] += 1
                    continue
                try:
                    recs = self._convert(conn.topic, conn.msgtype, msg, t_recv)
                except _CONVERT_ERRORS:
                    self.skipped[f"{conn.topic}: malformed message"] += 1
                    continue
                for rec in recs:
                    heapq.heappush(heap, (rec.t, next(seq), conn.topic, rec))
                horizon = t_recv / 1e9 - self.reorder_window
                while heap and (self.time == "receive" or heap[0][0] < horizon):
                    _, _, topic, rec = heapq.heappop(heap)
                    yield topic, rec
        while heap:
            _, _, topic, rec = heapq.heappop(heap)
            yield topic, rec

    def _convert(self, topic: str, msgtype: str, msg: Any, t_recv: int) -> list[Measurement]:
        recv = self.time == "receive"
        if msgtype == "tf2_msgs/msg/TFMessage":
            if self.tf is None:
                return []
            out: list[Measurement] = []
            for tr in msg.transforms:
                if (tr.header.frame_id.lstrip("/"), tr.child_frame_id.lstrip("/")) == tuple(
                    f.lstrip("/") for f in self.tf
                ):
                    tr_ns = t_recv if recv else _stamp(tr.header)
                    out.append(PoseStamped(tr_ns / 1e9, _pose_params(tr.transform.translation, tr.transform.rotation)))
            return out
        t_ns = t_recv if recv else _stamp(msg.header)
        t = t_ns / 1e9
        if msgtype == "sensor_msgs/msg/Imu":
            return [ImuSample(t, acc=_vec(msg.linear_acceleration), gyro=_vec(msg.angular_velocity))]
        if msgtype in KINDS["image"]:
            try:
                px = image_array(msg, msgtype)
            except InputFormatError:
                px = None
            if px is None:
                self.skipped[f"{topic}: unsupported image encoding"] += 1
                return []
            return [Image(t, px, camera=topic)]
        if msgtype == "sensor_msgs/msg/PointCloud2":
            try:
                pts, inten, times, ring = pointcloud2_arrays(msg, t_ns)
            except InputFormatError:
                self.skipped[f"{topic}: unsupported point layout"] += 1
                return []
            return [LidarScan(t, pts, inten, times, ring)]
        if msgtype == "livox_ros_driver2/msg/CustomMsg":
            p = msg.points
            pts = np.array([[q.x, q.y, q.z] for q in p], dtype=np.float64).reshape(-1, 3)
            inten = np.array([q.reflectivity for q in p], dtype=np.float64)
            off = np.array([q.offset_time for q in p], dtype=np.int64)
            base = int(msg.timebase) if msg.timebase else t_ns
            return [LidarScan(t, pts, inten, ((base - t_ns) + off) / 1e9)]
        if msgtype == "geometry_msgs/msg/PoseStamped":
            return [PoseStamped(t, _pose_params(msg.pose.position, msg.pose.orientation))]
        if msgtype in ("geometry_msgs/msg/PoseWithCovarianceStamped", "nav_msgs/msg/Odometry"):
            return [PoseStamped(t, _pose_params(msg.pose.pose.position, msg.pose.pose.orientation))]
        if msgtype == "geometry_msgs/msg/TransformStamped":
            return [PoseStamped(t, _pose_params(msg.transform.translation, msg.transform.rotation))]
        if msgtype == "geometry_msgs/msg/PointStamped":
            try:
                sigma = fix_sigma(msg.header.frame_id)
            except InputFormatError:
                self.skipped[f"{topic}: bad sigma in frame_id"] += 1
                return []
            return [PositionFix(t, _vec(msg.point), sigma)]
        return []

    def ground_truth(self) -> Trajectory | None:
        """``ground_truth=`` (a TUM file or a pose topic), else a pose topic whose name says
        ground truth, else None. Poses with NaN or non-increasing times are dropped; quaternions
        are normalised."""
        if self._gt is not None and Path(self._gt).is_file():
            return read_tum(self._gt)
        topic = None if self._gt is None else str(self._gt)
        if topic is None:
            names = [t for t, (m, _) in self._all.items() if m in KINDS["pose"] and _GT_NAME.search(t)]
            if not names:
                return None
            topic = sorted(names)[0]
        sub = RosbagRecording(self.path, topics={"pose": topic}, time=self.time, reorder_window=self.reorder_window)
        poses = [r for r in sub if isinstance(r, PoseStamped)]
        self.skipped.update(sub.skipped)
        if not poses:
            return None
        t = np.array([p.t for p in poses])
        params = np.stack([p.pose for p in poses])
        params[:, :4] /= np.linalg.norm(params[:, :4], axis=1, keepdims=True)
        return Trajectory(t, SE3(jnp.asarray(params)))

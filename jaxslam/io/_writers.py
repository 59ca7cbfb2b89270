"""Writers: measurement records to ROS1/ROS2 bags and EuRoC/ASL folders; point maps to PLY/PCD.

Every recording writer takes records (:mod:`jaxslam.measurements`) one at a time, in any
order within a stream's time, and is a context manager; what it writes reads back through
:func:`~jaxslam.io.open_recording` as equal records (tested per format).

Bags (``rosbags``): ``ImuSample`` -> ``sensor_msgs/Imu`` on ``/imu/data``; ``Image`` ->
``sensor_msgs/Image`` (``mono8`` / ``rgb8``; float images as ``mono16``) on
``/<camera>/image_raw``; ``LidarScan`` -> ``sensor_msgs/PointCloud2`` on ``/lidar/points``
with float32 ``x y z intensity``, uint32 ``t`` (ns after the header stamp; float64 ``time``
seconds when an offset is negative) and uint16 ``ring`` when known; ``PoseStamped`` ->
``geometry_msgs/PoseStamped`` on ``/groundtruth/pose`` (the readers guess it as ground
truth by name); ``PositionFix`` -> ``geometry_msgs/PointStamped`` on
``/total_station/prism`` (``frame_id`` carries ``sigma=<m>``). Header stamps are the record
times in integer nanoseconds; the bag's receive time equals the stamp.

EuRoC/ASL: ``mav0/imu0/data.csv``, ``mav0/<camera>/data.csv`` + ``data/<ns>.png``,
``mav0/lidar0/data.csv`` + ``data/<ns>.npy`` (float32 ``(N, 5)`` x y z intensity time, or
``(N, 6)`` with ring), ``mav0/total_station0/data.csv`` (``p x y z [m], sigma [m]``) and
``mav0/state_groundtruth_estimate0/data.csv`` (``p_RS_R``, ``q_RS`` wxyz). Floats are
written with ``repr`` (full float64 precision).
"""

from __future__ import annotations

import io
from pathlib import Path
from typing import Any, ClassVar

import numpy as np

from ..errors import InputFormatError
from ..measurements import Image, ImuSample, LidarScan, Measurement, PoseStamped, PositionFix

TOPICS = {
    "imu": "/imu/data",
    "lidar": "/lidar/points",
    "pose": "/groundtruth/pose",
    "position": "/total_station/prism",
}
"""Default bag topics per record kind (images: ``/<camera>/image_raw``)."""


def _ns(t: float) -> int:
    return round(float(t) * 1e9)


def image_topic(camera: str) -> str:
    """The bag topic of a camera name (a name starting with ``/`` is used as is)."""
    return camera if camera.startswith("/") else f"/{camera}/image_raw"


class RecordingWriter:
    """Base class: ``write(record)`` then ``close()`` (or use ``with``)."""

    def __enter__(self) -> RecordingWriter:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    def write(self, record: Measurement) -> None:
        raise NotImplementedError

    def write_all(self, records) -> None:
        for r in records:
            self.write(r)

    def close(self) -> None:
        raise NotImplementedError


# --- bags ----------------------------------------------------------------------------------------


class RosbagWriter(RecordingWriter):
    """A ROS1 ``.bag`` (``ros2=False``) or a ROS2 bag folder (``storage="mcap"`` or ``"sqlite3"``).

    ``topics`` overrides :data:`TOPICS` per kind. The path must not exist yet.
    """

    def __init__(
        self, path: str | Path, ros2: bool = False, storage: str = "mcap", topics: dict[str, str] | None = None
    ):
        from ._rosbag import default_typestore

        self.path = Path(path)
        if self.path.exists():
            raise InputFormatError("refusing to overwrite an existing bag", self.path)
        self.ros1 = not ros2
        self.store = default_typestore(self.ros1)
        self.topics = {**TOPICS, **(topics or {})}
        if self.ros1:
            from rosbags.rosbag1 import Writer as Writer1

            self.w: Any = Writer1(self.path)
        else:
            from rosbags.rosbag2 import StoragePlugin
            from rosbags.rosbag2 import Writer as Writer2

            plugins = {"mcap": StoragePlugin.MCAP, "sqlite3": StoragePlugin.SQLITE3}
            if storage not in plugins:
                raise ValueError(f"storage must be 'mcap' or 'sqlite3', got {storage!r}")
            self.w = Writer2(self.path, version=9, storage_plugin=plugins[storage])
        self.w.open()
        self.conns: dict[str, Any] = {}
        self.seq: dict[str, int] = {}
        self.T = self.store.types

    def _header(self, topic: str, ns: int, frame: str) -> Any:
        stamp = self.T["builtin_interfaces/msg/Time"](sec=ns // 10**9, nanosec=ns % 10**9)
        H = self.T["std_msgs/msg/Header"]
        if self.ros1:
            self.seq[topic] = self.seq.get(topic, -1) + 1
            return H(seq=self.seq[topic], stamp=stamp, frame_id=frame)
        return H(stamp=stamp, frame_id=frame)

    def _put(self, topic: str, msgtype: str, msg: Any, ns: int) -> None:
        if topic not in self.conns:
            self.conns[topic] = self.w.add_connection(topic, msgtype, typestore=self.store)
        ser = self.store.serialize_ros1 if self.ros1 else self.store.serialize_cdr
        self.w.write(self.conns[topic], ns, ser(msg, msgtype))

    def write(self, record: Measurement) -> None:
        ns = _ns(record.t)
        T = self.T
        if isinstance(record, ImuSample):
            topic = self.topics["imu"]
            V, Q, z9 = T["geometry_msgs/msg/Vector3"], T["geometry_msgs/msg/Quaternion"], np.zeros(9)
            a, g = np.asarray(record.acc, dtype=np.float64), np.asarray(record.gyro, dtype=np.float64)
            msg = T["sensor_msgs/msg/Imu"](
                header=self._header(topic, ns, "imu"),
                orientation=Q(x=0.0, y=0.0, z=0.0, w=1.0),
                orientation_covariance=np.array([-1.0] + [0.0] * 8),
                angular_velocity=V(x=float(g[0]), y=float(g[1]), z=float(g[2])),
                angular_velocity_covariance=z9,
                linear_acceleration=V(x=float(a[0]), y=float(a[1]), z=float(a[2])),
                linear_acceleration_covariance=z9,
            )
            self._put(topic, "sensor_msgs/msg/Imu", msg, ns)
        elif isinstance(record, Image):
            topic = image_topic(record.camera)
            px = np.asarray(record.data)
            if px.dtype.kind == "f":
                px, enc = np.rint(np.clip(px, 0, 1) * 65535).astype("<u2"), "mono16"
                if px.ndim == 3:
                    raise InputFormatError("float colour images cannot be written (convert to uint8)", self.path)
            elif px.dtype != np.uint8:
                raise InputFormatError(f"images must be uint8 or float, got {px.dtype}", self.path)
            else:
                enc = "mono8" if px.ndim == 2 else "rgb8"
            h, w = px.shape[:2]
            data = np.ascontiguousarray(px).view(np.uint8).reshape(-1)
            msg = T["sensor_msgs/msg/Image"](
                header=self._header(topic, ns, record.camera.strip("/")),
                height=h,
                width=w,
                encoding=enc,
                is_bigendian=0,
                step=data.size // h,
                data=data,
            )
            self._put(topic, "sensor_msgs/msg/Image", msg, ns)
        elif isinstance(record, LidarScan):
            topic = self.topics["lidar"]
            self._put(topic, "sensor_msgs/msg/PointCloud2", self._cloud(topic, ns, record), ns)
        elif isinstance(record, PoseStamped):
            topic = self.topics["pose"]
            q = np.asarray(record.pose, dtype=np.float64)
            P, Q = T["geometry_msgs/msg/Point"], T["geometry_msgs/msg/Quaternion"]
            pose = T["geometry_msgs/msg/Pose"](
                position=P(x=float(q[4]), y=float(q[5]), z=float(q[6])),
                orientation=Q(x=float(q[1]), y=float(q[2]), z=float(q[3]), w=float(q[0])),
            )
            msg = T["geometry_msgs/msg/PoseStamped"](header=self._header(topic, ns, "world"), pose=pose)
            self._put(topic, "geometry_msgs/msg/PoseStamped", msg, ns)
        elif isinstance(record, PositionFix):
            topic = self.topics["position"]
            x = np.asarray(record.xyz, dtype=np.float64)
            P = T["geometry_msgs/msg/Point"]
            msg = T["geometry_msgs/msg/PointStamped"](
                header=self._header(topic, ns, f"world;sigma={float(record.sigma)!r}"),
                point=P(x=float(x[0]), y=float(x[1]), z=float(x[2])),
            )
            self._put(topic, "geometry_msgs/msg/PointStamped", msg, ns)
        else:
            raise TypeError(f"cannot write {type(record).__name__} to a bag")

    def _cloud(self, topic: str, ns: int, scan: LidarScan) -> Any:
        pts = np.asarray(scan.points)
        times = np.asarray(scan.point_times, dtype=np.float64)
        names = ["x", "y", "z", "intensity"]
        fmts = ["<f4"] * 4
        signed = len(times) and times.min() < 0
        names.append("time" if signed else "t")
        fmts.append("<f8" if signed else "<u4")
        if scan.ring is not None:
            names.append("ring")
            fmts.append("<u2")
        arr = np.zeros(len(pts), dtype=np.dtype({"names": names, "formats": fmts}))
        arr["x"], arr["y"], arr["z"] = pts[:, 0], pts[:, 1], pts[:, 2]
        arr["intensity"] = scan.intensity
        arr[names[4]] = times if signed else np.rint(times * 1e9)
        if scan.ring is not None:
            arr["ring"] = scan.ring
        codes = {"<f4": 7, "<f8": 8, "<u4": 6, "<u2": 4}
        F = self.T["sensor_msgs/msg/PointField"]
        layout: dict[str, Any] = dict(arr.dtype.fields or {})
        fields = [F(name=n, offset=layout[n][1], datatype=codes[f], count=1) for n, f in zip(names, fmts)]
        return self.T["sensor_msgs/msg/PointCloud2"](
            header=self._header(topic, ns, "lidar"),
            height=1,
            width=len(arr),
            fields=fields,
            is_bigendian=False,
            point_step=arr.dtype.itemsize,
            row_step=arr.dtype.itemsize * len(arr),
            data=arr.view(np.uint8).reshape(-1).copy(),
            is_dense=True,
        )

    def close(self) -> None:
        self.w.close()


# --- EuRoC / ASL ---------------------------------------------------------------------------------


class EurocWriter(RecordingWriter):
    """An EuRoC/ASL folder (``<path>/mav0/...``); see the module docstring for the layout."""

    HEADERS: ClassVar[dict[str, str]] = {
        "imu0": "#timestamp [ns],w_RS_S_x [rad s^-1],w_RS_S_y [rad s^-1],w_RS_S_z [rad s^-1],"
        "a_RS_S_x [m s^-2],a_RS_S_y [m s^-2],a_RS_S_z [m s^-2]",
        "lidar0": "#timestamp [ns],filename",
        "total_station0": "#timestamp [ns],p_x [m],p_y [m],p_z [m],sigma [m]",
        "state_groundtruth_estimate0": "#timestamp,p_RS_R_x [m],p_RS_R_y [m],p_RS_R_z [m],"
        "q_RS_w [],q_RS_x [],q_RS_y [],q_RS_z []",
    }

    def __init__(self, path: str | Path, png_compression: int = 1):
        self.path = Path(path)
        self.root = self.path / "mav0"
        self.root.mkdir(parents=True, exist_ok=True)
        self.png_compression = int(png_compression)
        self.files: dict[str, Any] = {}

    def _csv(self, name: str, header: str | None = None) -> Any:
        if name not in self.files:
            folder = self.root / name
            folder.mkdir(parents=True, exist_ok=True)
            f = open(folder / "data.csv", "w", newline="")  # noqa: SIM115 - closed in close()
            f.write((header or self.HEADERS.get(name, "#timestamp [ns],filename")) + "\n")
            self.files[name] = f
        return self.files[name]

    def write(self, record: Measurement) -> None:
        ns = _ns(record.t)
        if isinstance(record, ImuSample):
            vals = list(np.asarray(record.gyro, dtype=np.float64)) + list(np.asarray(record.acc, dtype=np.float64))
            self._csv("imu0").write(f"{ns}," + ",".join(repr(float(v)) for v in vals) + "\n")
        elif isinstance(record, Image):
            from PIL import Image as PILImage

            name = record.camera.strip("/").replace("/", "_") or "cam0"
            f = self._csv(name)
            (self.root / name / "data").mkdir(exist_ok=True)
            px = np.asarray(record.data)
            if px.dtype.kind == "f":
                im = PILImage.fromarray(np.rint(np.clip(px, 0, 1) * 65535).astype(np.uint16))
            else:
                im = PILImage.fromarray(px)
            im.save(self.root / name / "data" / f"{ns}.png", compress_level=self.png_compression)
            f.write(f"{ns},{ns}.png\n")
        elif isinstance(record, LidarScan):
            f = self._csv("lidar0")
            (self.root / "lidar0" / "data").mkdir(exist_ok=True)
            cols = [np.asarray(record.points), np.asarray(record.intensity)[:, None]]
            cols.append(np.asarray(record.point_times)[:, None])
            if record.ring is not None:
                cols.append(np.asarray(record.ring)[:, None])
            np.save(self.root / "lidar0" / "data" / f"{ns}.npy", np.concatenate(cols, axis=1).astype(np.float32))
            f.write(f"{ns},{ns}.npy\n")
        elif isinstance(record, PositionFix):
            x = np.asarray(record.xyz, dtype=np.float64)
            vals = [*x.tolist(), float(record.sigma)]
            self._csv("total_station0").write(f"{ns}," + ",".join(repr(v) for v in vals) + "\n")
        elif isinstance(record, PoseStamped):
            q = np.asarray(record.pose, dtype=np.float64)
            vals = [*q[4:7].tolist(), *q[0:4].tolist()]
            self._csv("state_groundtruth_estimate0").write(f"{ns}," + ",".join(repr(v) for v in vals) + "\n")
        else:
            raise TypeError(f"cannot write {type(record).__name__} to an EuRoC folder")

    def close(self) -> None:
        for f in self.files.values():
            f.close()
        self.files.clear()


def open_writer(path: str | Path, fmt: str) -> RecordingWriter:
    """A writer by format name: ``bag`` (ROS1), ``bag2`` (ROS2 mcap), ``bag2-db3`` (ROS2 sqlite),
    ``euroc``."""
    if fmt == "bag":
        return RosbagWriter(path)
    if fmt == "bag2":
        return RosbagWriter(path, ros2=True)
    if fmt == "bag2-db3":
        return RosbagWriter(path, ros2=True, storage="sqlite3")
    if fmt == "euroc":
        return EurocWriter(path)
    raise ValueError(f"format must be bag, bag2, bag2-db3 or euroc, got {fmt!r}")


# --- point maps ----------------------------------------------------------------------------------


def _map_arrays(points: Any, intensity: Any) -> tuple[np.ndarray, np.ndarray | None]:
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"points must have shape (N, 3), got {pts.shape}")
    if intensity is None:
        return pts, None
    inten = np.asarray(intensity, dtype=np.float64)
    if inten.shape != (len(pts),):
        raise ValueError(f"intensity must have shape ({len(pts)},), got {inten.shape}")
    return pts, inten


def write_ply(path: str | Path, points: Any, intensity: Any = None, binary: bool = True, colors: Any = None) -> None:
    """A PLY point map: float64 ``x y z`` (+ float32 ``intensity``) (+ uchar ``red green blue``
    from ``colors`` (N, 3) uint8), binary little-endian or ASCII."""
    pts, inten = _map_arrays(points, intensity)
    rgb = None if colors is None else np.asarray(colors)
    if rgb is not None and (rgb.shape != (len(pts), 3)):
        raise ValueError(f"colors must have shape ({len(pts)}, 3), got {rgb.shape}")
    props = ["property double x", "property double y", "property double z"]
    if inten is not None:
        props.append("property float intensity")
    if rgb is not None:
        rgb = np.clip(rgb, 0, 255).astype(np.uint8)
        props += ["property uchar red", "property uchar green", "property uchar blue"]
    fmt = "binary_little_endian" if binary else "ascii"
    header = "\n".join(["ply", f"format {fmt} 1.0", f"element vertex {len(pts)}", *props, "end_header"]) + "\n"
    with open(path, "wb") as f:
        f.write(header.encode("ascii"))
        if binary:
            dt = [("x", "<f8"), ("y", "<f8"), ("z", "<f8")] + ([("intensity", "<f4")] if inten is not None else [])
            dt += [("red", "u1"), ("green", "u1"), ("blue", "u1")] if rgb is not None else []
            arr = np.zeros(len(pts), dtype=dt)
            arr["x"], arr["y"], arr["z"] = pts.T
            if inten is not None:
                arr["intensity"] = inten
            if rgb is not None:
                arr["red"], arr["green"], arr["blue"] = rgb.T
            f.write(arr.tobytes())
        else:
            buf = io.StringIO()
            for k in range(len(pts)):
                row = [repr(float(v)) for v in pts[k]] + (
                    [repr(float(np.float32(inten[k])))] if inten is not None else []
                )
                row += [str(int(c)) for c in rgb[k]] if rgb is not None else []
                buf.write(" ".join(row) + "\n")
            f.write(buf.getvalue().encode("ascii"))


def read_ply(path: str | Path) -> tuple[np.ndarray, np.ndarray | None]:
    """Read a PLY point map (vertex x y z [intensity]): :func:`write_ply`'s, or another tool's
    (the intensity also as ``scalar_intensity``, ``reflectivity`` or ``remission``)."""
    data = Path(path).read_bytes()
    end = data.find(b"end_header\n")
    if not data.startswith(b"ply") or end < 0:
        raise InputFormatError("not a PLY file (no 'ply' magic or 'end_header')", path)
    lines = data[:end].decode("ascii", "replace").splitlines()
    fmt = next((ln.split()[1] for ln in lines if ln.startswith("format")), "")
    count = next((int(ln.split()[2]) for ln in lines if ln.startswith("element vertex")), 0)
    props = [(ln.split()[1], ln.split()[2]) for ln in lines if ln.startswith("property")]
    types = {"double": "<f8", "float": "<f4", "uchar": "u1", "int": "<i4", "uint": "<u4", "ushort": "<u2"}
    try:
        dt = np.dtype([(name, types[typ]) for typ, name in props])
    except KeyError as err:
        raise InputFormatError(f"unsupported PLY property type {err}", path) from None
    body = data[end + len(b"end_header\n") :]
    if fmt == "binary_little_endian":
        if len(body) < count * dt.itemsize:
            raise InputFormatError(f"PLY body holds {len(body) // dt.itemsize} of {count} vertices", path)
        arr = np.frombuffer(body, dtype=dt, count=count)
        cols = {n: arr[n].astype(np.float64) for n in dt.names or ()}
    elif fmt == "ascii":
        vals = np.loadtxt(io.StringIO(body.decode("ascii")), ndmin=2).reshape(-1, len(props))
        cols = {n: vals[:, i] for i, (_, n) in enumerate(props)}
    else:
        raise InputFormatError(f"unsupported PLY format {fmt!r}", path)
    pts = np.stack([cols["x"], cols["y"], cols["z"]], axis=1)
    # the intensity under the names tools give it (CloudCompare: "scalar_<field>")
    lower = {n.lower(): n for n in cols}
    name = next((lower[k] for k in _INTENSITY_NAMES if k in lower), None)
    return pts, cols[name] if name is not None else None


_INTENSITY_NAMES = ("intensity", "scalar_intensity", "reflectivity", "scalar_reflectivity", "remission")


def write_pcd(path: str | Path, points: Any, intensity: Any = None, binary: bool = True) -> None:
    """A PCD v0.7 point map (PCL): float64 ``x y z`` (+ float32 ``intensity``)."""
    pts, inten = _map_arrays(points, intensity)
    fields, sizes, types = ["x", "y", "z"], ["8", "8", "8"], ["F", "F", "F"]
    if inten is not None:
        fields, sizes, types = [*fields, "intensity"], [*sizes, "4"], [*types, "F"]
    n = len(pts)
    header = (
        "# .PCD v0.7 - Point Cloud Data file format\nVERSION 0.7\n"
        f"FIELDS {' '.join(fields)}\nSIZE {' '.join(sizes)}\nTYPE {' '.join(types)}\n"
        f"COUNT {' '.join('1' for _ in fields)}\nWIDTH {n}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\n"
        f"POINTS {n}\nDATA {'binary' if binary else 'ascii'}\n"
    )
    with open(path, "wb") as f:
        f.write(header.encode("ascii"))
        if binary:
            dt = [("x", "<f8"), ("y", "<f8"), ("z", "<f8")] + ([("intensity", "<f4")] if inten is not None else [])
            arr = np.zeros(n, dtype=dt)
            arr["x"], arr["y"], arr["z"] = pts.T
            if inten is not None:
                arr["intensity"] = inten
            f.write(arr.tobytes())
        else:
            for k in range(n):
                row = [repr(float(v)) for v in pts[k]] + (
                    [repr(float(np.float32(inten[k])))] if inten is not None else []
                )
                f.write((" ".join(row) + "\n").encode("ascii"))


def read_pcd(path: str | Path) -> tuple[np.ndarray, np.ndarray | None]:
    """Read an uncompressed PCD point map (ascii or binary; F/U/I fields, COUNT 1)."""
    data = Path(path).read_bytes()
    head: dict[str, list[str]] = {}
    pos = 0
    while True:
        nl = data.find(b"\n", pos)
        if nl < 0:
            raise InputFormatError("PCD header has no DATA line", path)
        line = data[pos:nl].decode("ascii", "replace").strip()
        pos = nl + 1
        if line and not line.startswith("#"):
            key, *vals = line.split()
            head[key.upper()] = vals
            if key.upper() == "DATA":
                break
    try:
        fields, sizes, types = head["FIELDS"], [int(x) for x in head["SIZE"]], head["TYPE"]
        n = int(head["POINTS"][0])
    except (KeyError, ValueError, IndexError):
        raise InputFormatError("PCD header needs FIELDS, SIZE, TYPE and POINTS", path) from None
    kinds = {"F": "f", "U": "u", "I": "i"}
    dt = np.dtype([(f, f"<{kinds[t]}{s}") for f, s, t in zip(fields, sizes, types)])
    mode = head["DATA"][0]
    if mode == "binary":
        body = data[pos:]
        if len(body) < n * dt.itemsize:
            raise InputFormatError(f"PCD body holds {len(body) // dt.itemsize} of {n} points", path)
        arr = np.frombuffer(body, dtype=dt, count=n)
        cols = {f: arr[f].astype(np.float64) for f in fields}
    elif mode == "ascii":
        table = np.loadtxt(io.StringIO(data[pos:].decode("ascii")), ndmin=2).reshape(-1, len(fields))
        cols = {f: table[:, i] for i, f in enumerate(fields)}
    else:
        raise InputFormatError(f"unsupported PCD DATA {mode!r} (binary or ascii)", path)
    return np.stack([cols["x"], cols["y"], cols["z"]], axis=1), cols.get("intensity")

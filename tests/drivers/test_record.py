"""The recorder: records -> ROS1 bag -> open_recording gives them back; a bag left unclosed is
repaired by ``reindex``; and the real thing: ``python -m drivers.record`` fed by a
pseudo-terminal (WitMotion packet bytes), loopback Livox UDP and an image folder, killed with
SIGKILL, then reindexed: every record up to ~1 s before the kill is there."""

from __future__ import annotations

import os
import select
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from drivers.livox import CARTESIAN_HIGH, high_points_payload
from drivers.livox import build_packet as livox_packet
from drivers.record import BagRecorder, main, reindex
from drivers.witmotion import ACCEL, ANGLE, GYRO, build_packet
from jaxslam.errors import ConfigError, InputFormatError
from jaxslam.io import open_recording
from jaxslam.measurements import Image, ImuSample, LidarScan

ROOT = Path(__file__).resolve().parents[2]
G = 9.80665
T0 = 1_700_000_000.0


def _records(n_imu: int = 50, t0: float = T0) -> list:
    rng = np.random.default_rng(4)
    recs: list = [ImuSample(t0 + k * 0.005, rng.normal(size=3), rng.normal(size=3)) for k in range(n_imu)]
    for k in range(3):
        t = t0 + 0.0021 + k * 0.08
        recs.append(Image(t, rng.integers(0, 255, (6, 8, 3), dtype=np.uint8), camera="cam0"))
        n = 40
        pts = rng.normal(size=(n, 3)).astype(np.float32).astype(np.float64)
        times = np.arange(n) * 1e-3
        recs.append(LidarScan(t + 0.001, pts, rng.integers(0, 255, n).astype(np.float64), times, np.arange(n) % 6))
    return sorted(recs, key=lambda r: r.t)


def _same(a, b) -> None:
    assert type(a) is type(b) and abs(a.t - b.t) < 1e-6
    if isinstance(a, ImuSample):
        np.testing.assert_array_equal(a.acc, b.acc)
        np.testing.assert_array_equal(a.gyro, b.gyro)
    elif isinstance(a, Image):
        np.testing.assert_array_equal(a.data, b.data)
    else:
        np.testing.assert_array_equal(a.points, b.points)
        np.testing.assert_array_equal(a.intensity, b.intensity)
        np.testing.assert_allclose(a.point_times, b.point_times, atol=1e-9)
        np.testing.assert_array_equal(a.ring, b.ring)


def _topic(r) -> str:
    return {ImuSample: "/imu/data", LidarScan: "/lidar/points"}.get(type(r), "/cam0/image_raw")


def test_bag_recorder_round_trip(tmp_path):
    recs = _records()
    with BagRecorder(tmp_path / "r.bag", flush_interval=0.0) as bag:  # a chunk per message
        for r in recs:
            bag.write(_topic(r), r)
    rec = open_recording(tmp_path / "r.bag")
    back = list(rec)
    assert not rec.skipped and len(back) == len(recs)
    for a, b in zip(recs, back):
        _same(a, b)
    with pytest.raises(ConfigError, match="exists"):
        BagRecorder(tmp_path / "r.bag")


def test_reindex_an_unclosed_bag_and_a_truncated_tail(tmp_path):
    recs = _records()
    bag = BagRecorder(tmp_path / "k.bag", flush_interval=1e9)
    for r in recs[:30]:
        bag.write(_topic(r), r)
    bag.flush()
    for r in recs[30:]:
        bag.write(_topic(r), r)  # still in the open chunk: lost
    bag.writer.abort()  # what SIGKILL leaves: chunks, no index
    with pytest.raises(InputFormatError, match="no index"):
        open_recording(tmp_path / "k.bag")
    data = (tmp_path / "k.bag").read_bytes()
    (tmp_path / "cut.bag").write_bytes(data[:-10])  # the last chunk's index data cut short
    stats = reindex(tmp_path / "k.bag")
    assert stats["messages"] == 30 and stats["chunks"] == 1 and stats["connections"] == 3
    assert (tmp_path / "k.orig.bag").read_bytes() == data
    back = list(open_recording(tmp_path / "k.bag"))
    assert len(back) == 30
    for a, b in zip(recs[:30], back):
        _same(a, b)
    assert main(["reindex", str(tmp_path / "cut.bag"), "-o", str(tmp_path / "cut2.bag")]) == 0
    assert len(list(open_recording(tmp_path / "cut2.bag"))) == 30
    # a closed bag reindexes to the same records; a non-bag is refused with a clear error
    stats = reindex(tmp_path / "k.bag", tmp_path / "again.bag")
    assert stats["messages"] == 30 and len(list(open_recording(tmp_path / "again.bag"))) == 30
    (tmp_path / "x.bag").write_bytes(b"hello")
    with pytest.raises(InputFormatError, match="not a ROS1"):
        reindex(tmp_path / "x.bag", tmp_path / "y.bag")
    assert not (tmp_path / "y.bag").exists()
    assert main(["reindex", str(tmp_path / "x.bag"), "-o", str(tmp_path / "y.bag")]) == 1


# ----------------------------------------------------------------------------- subprocess


def _env() -> dict[str, str]:
    env = dict(os.environ)
    env["PYTHONPATH"] = str(ROOT) + os.pathsep + env.get("PYTHONPATH", "")
    return env


def _wait_for_line(proc: subprocess.Popen, word: bytes, timeout: float = 60.0) -> bytes:
    deadline, got = time.monotonic() + timeout, b""
    while time.monotonic() < deadline:
        ready, _, _ = select.select([proc.stderr], [], [], 0.2)
        if ready:
            line = proc.stderr.readline()
            got += line
            if word in line:
                return got
            if not line and proc.poll() is not None:
                break
    raise AssertionError(f"recorder did not start: {got.decode(errors='replace')}")


def _free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _png_folder(path: Path) -> Path:
    from PIL import Image as PILImage

    path.mkdir()
    for k in range(3):
        PILImage.fromarray(np.full((12, 16, 3), 40 * k, np.uint8)).save(path / f"{k}.png")
    return path


def test_sigkilled_recorder_leaves_all_but_the_last_second(tmp_path):
    master, slave = os.openpty()
    port = _free_udp_port()
    out = tmp_path / "run.bag"
    cmd = [sys.executable, "-m", "drivers.record", "--imu", os.ttyname(slave), "--imu-baud", "115200"]
    cmd += ["--lidar-port", str(port), "--lidar-host", "127.0.0.1"]
    cmd += ["--camera", str(_png_folder(tmp_path / "imgs")), "--camera-fps", "10", "--camera-loop", "-o", str(out)]
    proc = subprocess.Popen(cmd, cwd=ROOT, env=_env(), stderr=subprocess.PIPE)
    stop = threading.Event()
    imu_sent: list[float] = []  # host time at which cycle k was written
    try:
        _wait_for_line(proc, b"recording")

        def feed_imu():
            k = 0
            while not stop.is_set():
                data = build_packet(ACCEL, k, 0, 2048) + build_packet(GYRO, 0, 0, k % 100) + build_packet(ANGLE)
                try:  # a pty write may take only part of the bytes when its buffer is full
                    view = memoryview(data)
                    while view:
                        view = view[os.write(master, view) :]
                except OSError:
                    return
                imu_sent.append(time.time())
                k += 1
                time.sleep(0.005)

        def feed_lidar():
            rng = np.random.default_rng(0)
            with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as tx:
                k = 0
                while not stop.is_set():
                    xyz = rng.integers(-50_000, 50_000, (96, 3))
                    pkt = livox_packet(
                        CARTESIAN_HIGH, high_points_payload(xyz), 96, timestamp_ns=time.time_ns(), time_interval=2000
                    )
                    tx.sendto(pkt, ("127.0.0.1", port))
                    k += 1
                    time.sleep(0.002)

        threads = [threading.Thread(target=f, daemon=True) for f in (feed_imu, feed_lidar)]
        for t in threads:
            t.start()
        time.sleep(3.5)
        t_kill = time.time()
        proc.send_signal(signal.SIGKILL)
        proc.wait(10)
        stop.set()
        for t in threads:
            t.join(2)
    finally:
        stop.set()
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        proc.stderr.close()
        os.close(master)
        os.close(slave)
    assert proc.returncode == -signal.SIGKILL
    with pytest.raises(InputFormatError, match="reindex"):
        open_recording(out)
    stats = reindex(out)
    assert stats["messages"] > 0
    rec = open_recording(out)
    records = list(rec)
    assert not rec.skipped, rec.skipped
    imu = [r for r in records if isinstance(r, ImuSample)]
    ks = [round(r.acc[0] * 32768 / (16 * G)) for r in imu]
    assert ks == list(range(len(ks))), "IMU samples lost or reordered"
    due = [k for k, t in enumerate(imu_sent) if t < t_kill - 1.0]
    assert len(ks) >= len(due), (len(ks), len(due), len(imu_sent))
    assert len(due) > 300
    frames = [r for r in records if isinstance(r, LidarScan)]
    assert frames and frames[-1].t >= t_kill - 1.2, (frames[-1].t - t_kill, len(frames))
    assert all(len(f.points) > 0 and f.ring is not None for f in frames)
    images = [r for r in records if isinstance(r, Image)]
    assert len(images) >= 15 and images[-1].t >= t_kill - 1.2 and images[0].data.shape == (12, 16, 3)


def test_sigterm_stops_cleanly_with_an_indexed_bag(tmp_path):
    out = tmp_path / "cam.bag"
    cmd = [sys.executable, "-m", "drivers.record", "--camera", str(_png_folder(tmp_path / "imgs"))]
    cmd += ["--camera-fps", "20", "--camera-loop", "-o", str(out), "--duration", "60"]
    proc = subprocess.Popen(cmd, cwd=ROOT, env=_env(), stderr=subprocess.PIPE)
    try:
        _wait_for_line(proc, b"recording")
        time.sleep(1.0)
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=20)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 0, err
    assert b"wrote" in err
    images = list(open_recording(out))  # indexed: no reindex needed
    assert 10 <= len(images) <= 40 and all(isinstance(r, Image) for r in images)


def test_cli_errors_are_one_line(tmp_path, capsys):
    assert main(["-o", str(tmp_path / "x.bag")]) == 1
    assert "nothing to record" in capsys.readouterr().err
    assert main(["--imu", str(tmp_path / "no-tty"), "-o", str(tmp_path / "x.bag")]) == 1
    assert "cannot open" in capsys.readouterr().err
    assert not (tmp_path / "x.bag").exists()

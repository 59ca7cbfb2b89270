"""Livox SDK2 UDP driver without hardware: packet round trips, bad packets counted, frame
assembly, a fuzz test and a loopback (127.0.0.1) UDP receiver test."""

from __future__ import annotations

import socket
import struct
import threading
import time
import zlib

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from drivers import DriverError
from drivers.livox import (
    CARTESIAN_HIGH,
    CARTESIAN_LOW,
    DUAL_ECHO,
    HEADER_SIZE,
    IMU_DATA,
    SPHERICAL,
    LivoxStream,
    LivoxUDP,
    PacketError,
    build_packet,
    high_points_payload,
    imu_payload,
    low_points_payload,
    parse_packet,
)
from jaxslam.errors import InputFormatError, JaxSlamError
from jaxslam.measurements import ImuSample, LidarScan

G = 9.80665
BAD_REASONS = (
    "too_short",
    "bad_version",
    "bad_length",
    "unknown_type",
    "unsupported_type",
    "bad_dot_num",
    "bad_crc",
    "invalid_imu",
)


def accounted(stream: LivoxStream) -> bool:
    """Every datagram was parsed as points or IMU, or counted under one bad reason."""
    c = stream.counters
    return c["datagrams"] == c["point_packets"] + c["imu_packets"] + sum(c[r] for r in BAD_REASONS)


def point_packet(k: int, rng: np.random.Generator, *, n: int = 96, t0: int = 5_000_000_000, dt: int = 1_000_000):
    """Packet ``k`` of a stream: ``n`` high-precision points, timestamp t0 + k dt ns, 200 µs span."""
    xyz = rng.integers(-100_000, 100_000, size=(n, 3))
    payload = high_points_payload(xyz, rng.integers(0, 256, n), rng.integers(0, 256, n))
    return build_packet(CARTESIAN_HIGH, payload, n, timestamp_ns=t0 + k * dt, time_interval=2000, udp_cnt=k), xyz


# ----------------------------------------------------------------------------- packets


def test_header_offsets():
    pkt = build_packet(
        CARTESIAN_HIGH, bytes(14 * 3), 3, timestamp_ns=0x0102030405060708, time_interval=2123, udp_cnt=77
    )
    assert HEADER_SIZE == 36 and len(pkt) == 36 + 42
    assert pkt[0] == 0  # version
    assert struct.unpack_from("<H", pkt, 1)[0] == len(pkt)  # length
    assert struct.unpack_from("<H", pkt, 3)[0] == 2123  # time_interval, 0.1 µs
    assert struct.unpack_from("<H", pkt, 5)[0] == 3  # dot_num
    assert struct.unpack_from("<H", pkt, 7)[0] == 77  # udp_cnt
    assert pkt[10] == CARTESIAN_HIGH and pkt[11] == 1  # data_type, time_type
    assert struct.unpack_from("<I", pkt, 24)[0] == zlib.crc32(pkt[28:])  # crc32 of timestamp + data
    assert struct.unpack_from("<Q", pkt, 28)[0] == 0x0102030405060708  # timestamp


def test_round_trip_high_precision(rng):
    xyz = rng.integers(-(2**31), 2**31, size=(96, 3))
    refl, tag = rng.integers(0, 256, 96), rng.integers(0, 256, 96)
    data = build_packet(CARTESIAN_HIGH, high_points_payload(xyz, refl, tag), 96, timestamp_ns=123, time_interval=2400)
    pkt = parse_packet(data, check_crc=True)
    assert (pkt.dot_num, pkt.data_type, pkt.timestamp_ns, pkt.time_interval) == (96, CARTESIAN_HIGH, 123, 2400)
    np.testing.assert_allclose(pkt.points, xyz * 1e-3)
    np.testing.assert_array_equal(pkt.reflectivity, refl)
    np.testing.assert_array_equal(pkt.tag, tag)
    np.testing.assert_array_equal(pkt.offsets_ns, np.arange(96) * 240_000 // 96)  # 2400 x 0.1 µs spread
    assert not pkt.is_imu


def test_round_trip_low_precision(rng):
    xyz = rng.integers(-(2**15), 2**15, size=(50, 3))
    data = build_packet(CARTESIAN_LOW, low_points_payload(xyz, np.full(50, 9)), 50)
    pkt = parse_packet(data)
    assert len(data) == 36 + 8 * 50
    np.testing.assert_allclose(pkt.points, xyz * 1e-2)
    assert np.all(pkt.reflectivity == 9)


def test_round_trip_imu():
    gyro, acc_g = np.array([0.125, -0.5, 1.0]), np.array([0.0, 0.25, -1.0])  # exact in float32
    data = build_packet(IMU_DATA, imu_payload(gyro, acc_g), 1, timestamp_ns=2_500_000_000)
    pkt = parse_packet(data)
    assert pkt.is_imu and len(data) == 36 + 24
    np.testing.assert_array_equal(pkt.gyro, gyro)
    np.testing.assert_allclose(pkt.acc, acc_g * G)
    stream = LivoxStream()
    (sample,) = stream.feed(data)
    assert isinstance(sample, ImuSample) and sample.t == 2.5
    np.testing.assert_allclose(sample.acc, acc_g * G)
    sample.validate()


def _bad_packets():
    good = build_packet(CARTESIAN_HIGH, bytes(14 * 4), 4)
    wrong_crc = bytearray(good)
    wrong_crc[40] ^= 1
    nan_imu = build_packet(IMU_DATA, struct.pack("<6f", 0, 0, float("nan"), 0, 0, 1), 1)
    return [
        ("too_short", good[:20]),
        ("bad_version", build_packet(CARTESIAN_HIGH, bytes(14 * 4), 4, version=1)),
        ("bad_length", good + b"\x00"),
        ("bad_length", build_packet(CARTESIAN_HIGH, bytes(14 * 4), 4, length=99)),
        ("bad_dot_num", build_packet(CARTESIAN_HIGH, bytes(14 * 4), 5)),
        ("bad_dot_num", build_packet(CARTESIAN_LOW, bytes(14 * 4), 4)),  # 14-byte records as low
        ("bad_dot_num", build_packet(IMU_DATA, bytes(48), 2)),
        ("unknown_type", build_packet(0x07, bytes(14), 1)),
        ("unsupported_type", build_packet(SPHERICAL, bytes(10 * 4), 4)),
        ("unsupported_type", build_packet(DUAL_ECHO, bytes(28 * 2), 2)),
        ("bad_crc", bytes(wrong_crc)),
        ("invalid_imu", nan_imu),
        ("invalid_imu", build_packet(IMU_DATA, struct.pack("<5fI", 0, 0, 0, 0, 0, 0x7F800001), 1)),  # signalling NaN
        ("invalid_imu", build_packet(IMU_DATA, struct.pack("<3fI2f", 0, 0, 0, 0x7F800000, 0, 0), 1)),  # inf
    ]


@pytest.mark.parametrize(("reason", "data"), _bad_packets())
def test_bad_packets_raise_and_are_counted(reason, data):
    with pytest.raises(PacketError) as info:
        parse_packet(data, check_crc=True)
    assert info.value.reason == reason and isinstance(info.value, InputFormatError)
    stream = LivoxStream(check_crc=True)
    assert stream.feed(data) == []
    assert stream.counters[reason] == 1 and accounted(stream)


def test_crc_is_off_by_default():
    data = bytearray(build_packet(CARTESIAN_HIGH, bytes(14), 1))
    data[24] ^= 0xFF
    parse_packet(bytes(data))
    with pytest.raises(PacketError, match="crc32"):
        parse_packet(bytes(data), check_crc=True)


# ----------------------------------------------------------------------------- frames


def test_frames_of_a_tenth_of_a_second(rng):
    stream = LivoxStream(frame_period=0.1)
    frames, sent = [], []
    for k in range(250):  # 250 packets 1 ms apart: 0.25 s
        data, xyz = point_packet(k, rng)
        sent.append(xyz)
        frames += stream.feed(data)
    assert len(frames) == 2 and stream.counters["frames"] == 2
    frames += stream.flush()
    assert [f.t for f in frames] == pytest.approx([5.0, 5.1, 5.2])
    assert [len(f.points) for f in frames] == [9600, 9600, 4800]
    all_points = np.concatenate([f.points for f in frames])
    np.testing.assert_allclose(all_points, np.concatenate(sent) * 1e-3)
    for f in frames:
        assert isinstance(f, LidarScan)
        f.validate()
        assert f.point_times.min() >= 0 and f.point_times.max() < 0.1
        assert np.all(np.diff(f.point_times) >= 0)
        np.testing.assert_array_equal(f.ring, np.tile(np.arange(96) % 6, len(f.points) // 96))
    # point i of packet k at 5 s + k ms + floor(i * 200 µs / 96) (integer ns)
    np.testing.assert_allclose(frames[1].point_times[:3], [0.0, 2083e-9, 4166e-9], atol=1e-15)
    assert stream.counters["points"] == 250 * 96 and stream.counters["lost_packets"] == 0


def test_packet_straddling_a_frame_boundary_is_split():
    stream = LivoxStream(frame_period=0.1, lines=None)
    pts = np.tile([[1000, 0, 0]], (10, 1))
    # Packet 1 at 0; packet 2 spans 99.5 .. 100.4 ms: its first 5 points belong to frame 1.
    p1 = build_packet(CARTESIAN_HIGH, high_points_payload(pts), 10, timestamp_ns=0, time_interval=100)
    p2 = build_packet(CARTESIAN_HIGH, high_points_payload(pts), 10, timestamp_ns=99_500_000, time_interval=10_000)
    assert stream.feed(p1) == []
    (f1,) = stream.feed(p2)
    (f2,) = stream.flush()
    assert (len(f1.points), len(f2.points)) == (15, 5) and f1.ring is None
    assert f2.t == pytest.approx(0.1) and f2.point_times[0] == pytest.approx(0.0)


def test_zero_points_late_packets_time_jumps_and_lost_packets(rng):
    stream = LivoxStream(frame_period=0.1)
    pts = np.array([[0, 0, 0], [1, 2, 3], [0, 0, 0]])
    mk = lambda ts, cnt: build_packet(CARTESIAN_HIGH, high_points_payload(pts), 3, timestamp_ns=ts, udp_cnt=cnt)  # noqa: E731
    out = stream.feed(mk(10_000_000_000, 0))
    out += stream.feed(mk(10_050_000_000, 1))
    out += stream.feed(mk(9_990_000_000, 2))  # 10 ms before the open frame: late, dropped
    out += stream.feed(mk(10_000_000_000, 5))  # udp_cnt 3 and 4 lost
    assert out == [] and stream.counters["late_packets"] == 1 and stream.counters["lost_packets"] == 2
    assert stream.counters["zero_points"] == 8
    out = stream.feed(mk(12_000_000_000, 6))  # 2 s gap: frame closed, the next starts at 12 s
    out += stream.feed(mk(1_000_000_000, 7))  # clock reset (sync acquired): frame closed, restart
    assert [f.t for f in out] == pytest.approx([10.0, 12.0]) and [len(f.points) for f in out] == [3, 1]
    (last,) = stream.flush()
    assert last.t == pytest.approx(1.0) and stream.counters["time_resets"] == 1
    assert stream.counters["unsynced_packets"] == 0 and stream.time_type == 1
    assert accounted(stream)


def test_max_points_emits_early(rng):
    stream = LivoxStream(max_points=200)
    frames = []
    for k in range(5):
        frames += stream.feed(point_packet(k, rng, dt=10)[0])
    assert [len(f.points) for f in frames] == [288]
    assert stream.flush()[0].points.shape == (192, 3)


def test_bad_frame_period():
    with pytest.raises(JaxSlamError):
        LivoxStream(frame_period=0.0)


# ----------------------------------------------------------------------------- fuzz


def _valid_datagram(data_type: int, n: int, seed: int, ts: int, interval: int, cnt: int) -> bytes:
    rng = np.random.default_rng(seed)
    if data_type == IMU_DATA:
        payload, n = imu_payload(rng.normal(size=3), rng.normal(size=3)), 1
    elif data_type == CARTESIAN_HIGH:
        payload = high_points_payload(rng.integers(-(2**31), 2**31, (n, 3)))
    else:
        payload = low_points_payload(rng.integers(-(2**15), 2**15, (n, 3)))
    return build_packet(data_type, payload, n, timestamp_ns=ts, time_interval=interval, udp_cnt=cnt)


_valid = st.builds(
    _valid_datagram,
    st.sampled_from([IMU_DATA, CARTESIAN_HIGH, CARTESIAN_LOW]),
    st.integers(0, 40),
    st.integers(0, 2**16),
    st.one_of(st.integers(0, 2**64 - 1), st.integers(0, 3 * 10**8)),
    st.integers(0, 2**16 - 1),
    st.integers(0, 2**16 - 1),
)


def _mutate(args):
    data, edits, cut = args
    out = bytearray(data)
    for pos, val in edits:
        out[pos % len(out)] = val
    return bytes(out[: len(out) - cut]) if cut < len(out) else bytes(out)


_mutated = st.tuples(
    _valid, st.lists(st.tuples(st.integers(0, 200), st.integers(0, 255)), max_size=4), st.sampled_from([0, 0, 0, 1, 14])
).map(_mutate)
_datagram = st.one_of(_valid, _mutated, _mutated, st.binary(max_size=120))


@settings(
    max_examples=1500,
    deadline=None,
    database=None,
    derandomize=True,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)
@given(datagrams=st.lists(_datagram, min_size=1, max_size=8), check_crc=st.booleans())
def test_fuzz_only_packet_errors_or_counted_skips(datagrams, check_crc):
    stream = LivoxStream(frame_period=0.1, check_crc=check_crc, max_points=100)
    records = []
    for data in datagrams:
        try:
            parse_packet(data, check_crc=check_crc)
        except PacketError as exc:  # the only exception parse_packet raises
            assert exc.reason in BAD_REASONS
        records += stream.feed(data)  # never raises
    records += stream.flush()
    assert accounted(stream)
    n_points = 0
    for rec in records:
        rec.validate()
        if isinstance(rec, LidarScan):
            n_points += len(rec.points)
            assert rec.point_times.min() >= 0 and rec.point_times.max() < 0.1
    c = stream.counters
    assert n_points == c["points"]  # every accepted point is in exactly one frame
    assert sum(isinstance(r, ImuSample) for r in records) == c["imu_samples"] == c["imu_packets"]


# ----------------------------------------------------------------------------- loopback UDP


def test_udp_loopback_frames_and_imu(rng):
    with LivoxUDP("127.0.0.1", 0, 0, timeout=0.05) as rx, socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as tx:
        point_port, imu_port = rx.ports
        records = []
        for k in range(300):  # 300 packets, 1 ms apart: 3 frames of 0.1 s
            tx.sendto(point_packet(k, rng)[0], ("127.0.0.1", point_port))
            if k % 5 == 0:
                imu = build_packet(
                    IMU_DATA, imu_payload([0, 0, 0.1], [0, 0, 1]), 1, timestamp_ns=5_000_000_000 + k * 10**6
                )
                tx.sendto(imu, ("127.0.0.1", imu_port))
            tx.sendto(b"not a livox packet", ("127.0.0.1", point_port))
            if k % 20 == 19:  # drain: the socket buffer holds ~100 datagrams
                records += rx.poll(timeout=1.0)
        records += rx.poll(timeout=0.05)
        records += rx.stream.flush()
    frames = [r for r in records if isinstance(r, LidarScan)]
    imus = [r for r in records if isinstance(r, ImuSample)]
    assert len(frames) == 3 and [len(f.points) for f in frames] == [9600, 9600, 9600]
    assert len(imus) == 60 and all(s.acc[2] == pytest.approx(G) for s in imus)
    c = rx.counters
    assert c["point_packets"] == 300 and c["too_short"] == 300 and c["lost_packets"] == 0


def test_udp_recv_loop_with_timeout(rng):
    with LivoxUDP("127.0.0.1", 0, None, timeout=0.02) as rx:
        (port,) = rx.ports

        def send():
            with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as tx:
                for k in range(120):
                    tx.sendto(point_packet(k, rng, dt=2_000_000)[0], ("127.0.0.1", port))
                    if k % 10 == 9:
                        time.sleep(0.002)

        sender = threading.Thread(target=send, daemon=True)
        sender.start()
        t0 = time.monotonic()
        frames = list(rx.recv(duration=1.0))
        sender.join(2.0)
        assert 0.9 <= time.monotonic() - t0 < 3.0
        # 120 packets 2 ms apart: 0.24 s -> 2 full frames + the flushed rest
        assert [len(f.points) for f in frames] == [4800, 4800, 1920]
        assert rx.timeouts > 0
        assert list(rx.recv(duration=0.05)) == []  # nothing left; returns after its duration
        # max_records stops early and keeps the rest
        assert list(rx.recv(max_records=0)) == []


def test_udp_bind_conflict_raises_driver_error():
    with LivoxUDP("127.0.0.1", 0, None) as rx:
        (port,) = rx.ports
        with pytest.raises(DriverError, match="cannot bind"):
            LivoxUDP("127.0.0.1", port, None)

"""WitMotion HWT901B driver without hardware: packet decoding, resynchronisation, pairing,
command bytes, a pseudo-terminal serial round trip and a fuzz test of the stream parser."""

from __future__ import annotations

import math
import os
import select
import threading
import time

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from drivers import DriverError
from drivers.witmotion import (
    ACCEL,
    ANGLE,
    GYRO,
    MAG,
    QUATERNION,
    SAVE,
    TIME,
    UNLOCK,
    WitMotionParser,
    WitMotionSerial,
    baud_command,
    build_packet,
    check_bandwidth,
    checksum,
    decode_packet,
    is_valid_packet,
    rate_command,
    write_register,
)
from jaxslam.errors import ConfigError, JaxSlamError
from jaxslam.measurements import ImuSample

G = 9.80665


def cycle(acc=(0, 0, 2048), gyro=(0, 0, 0), angle=(0, 0, 0), temp=2500) -> bytes:
    """One output cycle as the sensor sends it: accel, gyro, angle, magnetic field."""
    return (
        build_packet(ACCEL, *acc, temp)
        + build_packet(GYRO, *gyro, 0)
        + build_packet(ANGLE, *angle, 0)
        + build_packet(MAG, 100, -200, 300, temp)
    )


def feed_all(parser: WitMotionParser, data: bytes, chunk: int, t: float = 0.0) -> list[ImuSample]:
    out = []
    for k in range(0, len(data), chunk):
        out += parser.feed(data[k : k + chunk], t)
    return out


def accounted(parser: WitMotionParser) -> bool:
    """Every byte fed is in an accepted packet, counted as skipped, or still buffered."""
    c = parser.counters
    return c["bytes_in"] == 11 * c["packets"] + c["skipped_bytes"] + parser.buffered


# ----------------------------------------------------------------------------- packets


def test_packet_layout_and_checksum():
    pkt = build_packet(ACCEL, 1, -2, 3, -4)
    assert len(pkt) == 11 and pkt[0] == 0x55 and pkt[1] == 0x51
    assert pkt[2:10] == bytes.fromhex("0100feff0300fcff")  # int16 little-endian
    assert pkt[10] == sum(pkt[:10]) % 256 == checksum(pkt[:10])
    assert is_valid_packet(pkt)
    assert not is_valid_packet(pkt[:10] + bytes([(pkt[10] + 1) % 256]))
    assert not is_valid_packet(build_packet(0x42, 1, 2, 3, 4))  # checksum fine, type unknown


def test_decode_scaling():
    acc = decode_packet(build_packet(ACCEL, 2048, -4096, 32767, 2534))
    np.testing.assert_allclose(acc.values, [G, -2 * G, 32767 * 16 * G / 32768, 25.34], rtol=1e-15)
    gyro = decode_packet(build_packet(GYRO, 16384, -32768, 164, 0))
    np.testing.assert_allclose(gyro.values, np.radians([1000.0, -2000.0, 164 * 2000 / 32768]), rtol=1e-15)
    ang = decode_packet(build_packet(ANGLE, 16384, -8192, 32767, 0))
    np.testing.assert_allclose(ang.values, [math.pi / 2, -math.pi / 4, math.pi * 32767 / 32768], rtol=1e-15)
    q = decode_packet(build_packet(QUATERNION, 32767, 0, -16384, 8192))
    np.testing.assert_allclose(q.values, [32767 / 32768, 0.0, -0.5, 0.25])  # (w, x, y, z) assumed
    mag = decode_packet(build_packet(MAG, 100, -200, 300, 2500))
    np.testing.assert_array_equal(mag.values, [100.0, -200.0, 300.0, 25.0])
    t = decode_packet(bytes([0x55, TIME, 24, 11, 22, 7, 28, 5, 0xE8, 0x03]) + b"\x00")  # checksum unchecked here
    np.testing.assert_array_equal(t.values, [2024, 11, 22, 7, 28, 5, 1000])


# ----------------------------------------------------------------------------- parser


@pytest.mark.parametrize("chunk", [1, 5, 11, 44, 1000])
def test_samples_any_chunking(chunk):
    data = b"".join(cycle(acc=(k, -k, 2048), gyro=(10 * k, 0, -k)) for k in range(20))
    parser = WitMotionParser()
    samples = feed_all(parser, data, chunk)
    assert len(samples) == 20
    for k, s in enumerate(samples):
        np.testing.assert_allclose(s.acc, np.array([k, -k, 2048]) * 16 * G / 32768)
        np.testing.assert_allclose(s.gyro, np.radians(np.array([10 * k, 0, -k]) * 2000 / 32768))
        s.validate()
    c = parser.counters
    assert (c["packets"], c["skipped_bytes"], c["samples"], c["bad_checksum"]) == (80, 0, 20, 0)
    np.testing.assert_allclose(parser.latest[MAG].values, [100, -200, 300, 25])
    assert accounted(parser)


@pytest.mark.parametrize("chunk", [1, 7, 14, 19, 1000])
def test_garbage_truncated_and_bad_checksum_are_counted_and_skipped(chunk):
    good = [cycle(acc=(k, 0, 2048), gyro=(0, k, 0)) for k in range(6)]
    bad_sum = bytearray(cycle(acc=(99, 99, 99)))
    bad_sum[10] ^= 0xFF  # accel packet of this cycle fails its checksum
    flipped = bytearray(cycle(gyro=(77, 77, 77)))
    flipped[11 + 4] ^= 0x10  # gyro packet of this cycle: one data bit flipped
    stream = (
        b"\x00\xff\x55\x55\x12"  # garbage with headers
        + good[0]
        + good[1][:7]  # truncated cycle
        + good[2]
        + bytes(bad_sum)
        + good[3]
        + b"\x55\x51\x00"  # truncated header
        + good[4]
        + bytes(flipped)
        + good[5]
    )
    parser = WitMotionParser()
    samples = feed_all(parser, stream, chunk)
    accs = [round(s.acc[0] * 32768 / (16 * G)) for s in samples]
    assert accs == [0, 2, 3, 4, 5]  # good cycles only; the corrupt ones never pair
    assert not any(np.allclose(s.gyro, np.radians(77 * 2000 / 32768)) for s in samples)
    c = parser.counters
    assert c["bad_checksum"] >= 2 and c["skipped_bytes"] >= 5 + 7 + 11 + 3 + 11
    assert c["unpaired_gyro"] >= 1  # the gyro packet after the corrupt accel packet
    assert accounted(parser)


def test_every_single_byte_corruption_is_rejected():
    """Exhaustive: any one byte of an accel+gyro pair changed to any other value never gives
    a sample (the 8-bit sum always changes), and the stream recovers for the next cycle."""
    before = cycle(acc=(1, 1, 1), gyro=(1, 1, 1))
    target = cycle(acc=(300, -300, 2000), gyro=(55, -55, 5))
    after = cycle(acc=(2, 2, 2), gyro=(2, 2, 2)) + cycle(acc=(3, 3, 3), gyro=(3, 3, 3))
    for pos in range(22):
        for xor in range(1, 256):
            bad = bytearray(target)
            bad[pos] ^= xor
            parser = WitMotionParser()
            samples = parser.feed(before + bytes(bad) + after, 0.0)
            firsts = [round(s.acc[0] * 32768 / (16 * G)) for s in samples]
            assert firsts[0] == 1 and firsts[-2:] == [2, 3] and 300 not in firsts, (pos, xor, firsts)
            assert accounted(parser)


@pytest.mark.parametrize("chunk", range(1, 40))
def test_no_pairing_across_a_skip_at_any_chunking(chunk):
    # Regression (found by the fuzz test): accel, then a corrupt accel (header byte flipped),
    # then a valid gyro. The skip between them must break the pair whatever the read sizes.
    good = build_packet(ACCEL) + build_packet(GYRO, 0, 0, 1) + build_packet(ANGLE)
    corrupt = bytearray(build_packet(ACCEL) + build_packet(GYRO) + build_packet(ANGLE))
    corrupt[0] ^= 0x01
    parser = WitMotionParser()
    samples = feed_all(parser, good + build_packet(ACCEL) + bytes(corrupt), chunk)
    assert len(samples) == 1 and samples[0].gyro[2] > 0
    assert parser.counters["unpaired_gyro"] == 1


def test_resync_needs_a_confirming_packet():
    # A stream that starts mid-packet: the fake header inside the data is rejected.
    fake = build_packet(ANGLE, 0, 0, 0, 0)  # a valid-looking packet inside garbage
    data = b"\x01\x02" + fake + b"\x03" + cycle() * 3
    parser = WitMotionParser()
    parser.feed(data, 0.0)
    assert parser.counters["unconfirmed"] == 1
    assert ANGLE in parser.latest and parser.latest[ANGLE].raw == (0, 0, 0, 0)  # from the real cycles
    assert parser.counters["samples"] == 3
    # The last accepted packet of a fresh stream waits for its confirmation.
    p2 = WitMotionParser()
    assert p2.feed(build_packet(ACCEL, 1, 2, 3, 4), 0.0) == [] and p2.buffered == 11
    assert len(p2.feed(build_packet(GYRO, 1, 2, 3, 4) + build_packet(ANGLE), 0.0)) == 1


def test_pairing_rule():
    a, g, ang = build_packet(ACCEL, 1, 1, 1), build_packet(GYRO, 2, 2, 2), build_packet(ANGLE)
    parser = WitMotionParser()
    out = parser.feed(a + ang + g + g + a + a + g + ang, 0.0)
    assert len(out) == 1  # only the last accel directly followed by gyro
    c = parser.counters
    assert (c["unpaired_accel"], c["unpaired_gyro"]) == (2, 2)


def test_host_timestamps_back_dated_by_byte_time():
    byte_time, latency = 1e-3, 2e-3
    parser = WitMotionParser(byte_time=byte_time, latency=latency)
    (s,) = parser.feed(cycle() + cycle()[:11], 10.0)  # 55 bytes; gyro ends at byte 21
    assert s.t == pytest.approx(10.0 - (54 - 21) * byte_time - latency)
    # A packet split over two reads gets the time of the read holding its last byte.
    parser = WitMotionParser(byte_time=byte_time)
    data = cycle() * 2
    assert parser.feed(data[:15], 1.0) == []
    (s,) = parser.feed(data[15:30], 2.0)
    assert s.t == pytest.approx(2.0 - (29 - 21) * byte_time)


def test_a_burst_faster_than_the_baud_rate_keeps_the_order():
    """Bytes that arrive faster than the baud rate (a pty) must not be back-dated before the
    previous read's packets: times are clamped to increase (by 1 us), and counted."""
    parser = WitMotionParser(byte_time=1e-3)
    (a,) = parser.feed(cycle(), 1.0)
    b, c = parser.feed(cycle() * 2, 1.001)  # back-dated, b would be at 1.001 - 0.066
    assert a.t < b.t < c.t
    # 2 us after the first read's last packet (its accel packet is clamped first)
    assert b.t == pytest.approx(1.0 + 2e-6, abs=1e-12) and parser.counters["clamped_times"] >= 1


# ----------------------------------------------------------------------------- commands


def test_command_bytes():
    assert bytes.fromhex("FF AA 69 88 B5") == UNLOCK == write_register(0x69, 0xB588)
    assert bytes.fromhex("FF AA 00 00 00") == SAVE == write_register(0x00, 0)
    assert rate_command(200) == bytes.fromhex("FF AA 03 0B 00") == write_register(0x03, 0x0B)
    assert baud_command(115200) == bytes.fromhex("FF AA 04 06 00") == write_register(0x04, 0x06)
    assert rate_command(10) == bytes.fromhex("FF AA 03 06 00")
    for bad in (lambda: rate_command(300), lambda: baud_command(1234), lambda: write_register(256, 0)):
        with pytest.raises(ConfigError):
            bad()
    with pytest.raises(ConfigError):
        write_register(3, 70000)
    check_bandwidth(200, 115200)  # 88 kbit/s fits
    check_bandwidth(21, 9600)  # FIELD-NOTES: ~21 Hz at 9600 baud
    with pytest.raises(ConfigError, match="too slow"):
        check_bandwidth(200, 9600)


# ----------------------------------------------------------------------------- serial (pty)


@pytest.fixture
def pty():
    """A pseudo-terminal: yields (master fd, slave path); the driver opens the slave path."""
    master, slave = os.openpty()
    path = os.ttyname(slave)
    yield master, path
    os.close(slave)
    os.close(master)


def _write_in_thread(fd: int, data: bytes) -> threading.Thread:
    def run():
        for k in range(0, len(data), 256):
            os.write(fd, data[k : k + 256])

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    return thread


def test_serial_samples_over_pty(pty):
    master, path = pty
    n = 150
    parts = []
    for k in range(n):
        parts.append(cycle(acc=(k, 2 * k, 2048), gyro=(-k, 0, 3 * k)))
        if k % 10 == 3:
            parts.append(b"\x55\xaa\x00garbage\x55")  # interleaved noise
        if k % 25 == 7:
            corrupt = bytearray(cycle(acc=(5000, 5000, 5000)))
            corrupt[6] ^= 0x01
            parts.append(bytes(corrupt))
    parts.append(cycle())  # the last cycle confirms the one before
    with WitMotionSerial(path, 115200, timeout=0.05, clock=lambda: 123.0) as dev:
        writer = _write_in_thread(master, b"".join(parts))
        samples = list(dev.read_samples(max_samples=n, duration=5.0))
        writer.join(5.0)
        assert len(samples) == n
        for k, s in enumerate(samples):
            np.testing.assert_allclose(s.acc, np.array([k, 2 * k, 2048]) * 16 * G / 32768)
            np.testing.assert_allclose(s.gyro, np.radians(np.array([-k, 0, 3 * k]) * 2000 / 32768))
            assert s.t <= 123.0
        c = dev.counters
        assert c["skipped_bytes"] > 0 and c["bad_checksum"] > 0 and c["unpaired_gyro"] == 6
        assert accounted(dev.parser)
        # A silent port: reads time out (counted) until the duration ends.
        t0 = time.monotonic()
        assert list(dev.read_samples(duration=0.2)) == []
        assert dev.timeouts >= 2 and time.monotonic() - t0 < 2.0


def _read_exactly(fd: int, n: int, timeout: float = 5.0) -> bytes:
    """Read n bytes from fd: a pty may hand back one write per read."""
    got = b""
    deadline = time.monotonic() + timeout
    while len(got) < n:
        left = deadline - time.monotonic()
        if left <= 0 or not select.select([fd], [], [], left)[0]:
            break
        got += os.read(fd, n - len(got))
    return got


def test_serial_configure_writes_documented_bytes(pty):
    master, path = pty
    with WitMotionSerial(path, 115200, timeout=0.05) as dev:
        sent = dev.configure(200, pause=0.0)
        assert sent == [UNLOCK, rate_command(200), SAVE]
        first = UNLOCK + bytes.fromhex("FFAA030B00") + SAVE
        assert _read_exactly(master, len(first)) == first
        sent = dev.configure(200, baud=230400, pause=0.0)
        expected = [UNLOCK, rate_command(200), SAVE, UNLOCK, bytes.fromhex("FFAA040700"), UNLOCK, SAVE]
        assert sent == expected
        assert _read_exactly(master, 35) == b"".join(expected)
        assert dev.serial.baudrate == 230400 and dev.parser.byte_time == pytest.approx(10 / 230400)
        with pytest.raises(ConfigError):
            dev.configure(200, baud=9600, pause=0.0)  # 200 Hz does not fit 9600 baud


def test_serial_missing_port_raises_driver_error(tmp_path):
    with pytest.raises(DriverError, match="cannot open"):
        WitMotionSerial(str(tmp_path / "no-such-tty"))
    assert issubclass(DriverError, JaxSlamError)


# ----------------------------------------------------------------------------- fuzz

_int16 = st.integers(-32768, 32767)
_packet = st.builds(
    build_packet, st.sampled_from([0x50, 0x51, 0x52, 0x53, 0x54, 0x59, 0x5A, 0x42]), _int16, _int16, _int16, _int16
)
_cycle = st.builds(
    lambda a, g, ang: build_packet(ACCEL, *a) + build_packet(GYRO, *g) + build_packet(ANGLE, *ang),
    st.tuples(_int16, _int16, _int16),
    st.tuples(_int16, _int16, _int16),
    st.tuples(_int16, _int16, _int16),
)


def _mutate(args):
    data, positions, xor = args
    out = bytearray(data)
    for p in positions:
        out[p % len(out)] ^= xor
    return bytes(out)


_mutated = st.tuples(
    st.one_of(_cycle, _packet), st.lists(st.integers(0, 32), min_size=1, max_size=3), st.integers(1, 255)
).map(_mutate)
_truncated = st.tuples(st.one_of(_cycle, _packet), st.integers(1, 30)).map(lambda a: a[0][: a[1] % len(a[0])])
_piece = st.one_of(_cycle, _cycle, _packet, _mutated, _truncated, st.binary(min_size=1, max_size=40), st.just(b"\x55"))


def _valid_pairs(stream: bytes) -> set[tuple[float, ...]]:
    """(acc, gyro) of every valid accel window directly followed by a valid gyro window."""
    pairs = set()
    for i in range(len(stream) - 21):
        if stream[i] == 0x55 and stream[i + 1] == ACCEL and stream[i + 12] == GYRO:
            a, g = stream[i : i + 11], stream[i + 11 : i + 22]
            if is_valid_packet(a) and is_valid_packet(g):
                pairs.add((*decode_packet(a).values[:3], *decode_packet(g).values))
    return pairs


def test_fuzz_parser_only_counted_skips():
    total = [0, 0]  # bytes fed, samples checked

    @settings(
        max_examples=2000,
        deadline=None,
        database=None,
        derandomize=True,
        suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
    )
    @given(pieces=st.lists(_piece, min_size=1, max_size=12), chunk=st.integers(1, 64))
    def run(pieces, chunk):
        stream = b"".join(pieces)
        parser = WitMotionParser(byte_time=1e-4)
        samples = []
        for k in range(0, len(stream), chunk):
            samples += parser.feed(stream[k : k + chunk], 1.0)  # bad bytes are counted, never raised
        total[0] += len(stream)
        total[1] += len(samples)
        assert accounted(parser)
        assert parser.counters["samples"] == len(samples)
        if samples:
            valid = _valid_pairs(stream)
            for s in samples:
                assert (*s.acc, *s.gyro) in valid, (stream.hex(), chunk, parser.counters)
                assert s.t <= 1.0

    run()
    assert total[0] >= 100_000, total
    assert total[1] > 1000, total  # the fuzz also exercised the sample path


def test_layer_rule():
    """STYLE: drivers import only the base of jaxslam (measurements, errors); jaxslam never
    imports drivers."""
    import ast
    from pathlib import Path

    root = Path(__file__).resolve().parents[2]

    def imported(path: Path) -> set[str]:
        names = set()
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                names |= {a.name for a in node.names}
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                names.add(node.module)
        return names

    for path in (root / "drivers").rglob("*.py"):
        jax_imports = {m for m in imported(path) if m.split(".")[0] == "jaxslam"}
        # records, errors, and the bag repair tool the recorder shares with `jaxslam run`
        assert jax_imports <= {"jaxslam.measurements", "jaxslam.errors", "jaxslam.io._reindex"}, (path, jax_imports)
    for path in (root / "jaxslam").rglob("*.py"):
        assert not {m for m in imported(path) if m.split(".")[0] == "drivers"}, path

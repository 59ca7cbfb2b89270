"""WitMotion HWT901B 9-axis IMU over a serial port: packet parser, command builders, reader.

Packet layout (WIT standard protocol, all multi-byte values little-endian)::

    offset  size  field
    0       1     0x55 (frame start)
    1       1     type (0x50..0x5A, table below)
    2       8     four int16 LE  d0 d1 d2 d3   (0x50: eight bytes, see below)
    10      1     checksum = (sum of bytes 0..9) & 0xFF

=====  ===========  ================================================================
type   content      decoding of d0..d3 (``values`` of :class:`WitPacket`)
=====  ===========  ================================================================
0x50   chip time    bytes 2..9 = YY MM DD hh mm ss msL msH -> (year, month, day,
                    hour, minute, second, millisecond); not used for timestamps
0x51   acceleration d0..d2 * 16 g / 32768 -> m/s^2 (g = 9.80665); d3 / 100 -> °C
0x52   angular rate d0..d2 * 2000 °/s / 32768 -> rad/s; d3 firmware-dependent
                    (voltage / 100 or temperature / 100), kept raw
0x53   angle        d0..d2 (roll, pitch, yaw) * 180° / 32768 -> rad; d3 = version
0x54   magnetic     d0..d2 raw counts (the unit differs between firmware: kept raw);
                    d3 / 100 -> °C
0x59   quaternion   d0..d3 / 32768, **assumed order (w, x, y, z)** (WitMotion's
                    protocol manual names them Q0..Q3 with Q0 the scalar; other
                    sources differ). Check on a still, level sensor against the 0x53
                    angles: q ≈ (cos(yaw/2), 0, 0, sin(yaw/2)); if the large component
                    comes last the order is (x, y, z, w).
other  0x55..0x5A   port status, pressure, GPS ...: accepted (they keep the stream in
                    sync), decoded as the four raw int16 values, otherwise unused
=====  ===========  ================================================================

**Resynchronisation.** :class:`WitMotionParser` scans for the next 0x55 whose 11-byte window
has a known type and a valid checksum; everything else is skipped and counted
(``skipped_bytes``; ``bad_checksum`` / ``unknown_type`` count the rejected candidate
headers). The 8-bit checksum passes a random window 1 time in 256, so after any loss of sync
(start of stream, skipped bytes, rejected header) a candidate is accepted only when the 11
bytes after it are a valid packet too (``unconfirmed`` counts the candidates that were not);
while in sync, packets are accepted one by one. Only valid-checksum windows are ever decoded:
a packet with one corrupt byte (any bit pattern) always fails its checksum; corruption of
several bytes that happens to keep the sum is beyond what an 8-bit checksum can detect.

**Pairing rule (ImuSample).** The sensor sends one packet of each enabled type per output
cycle, in increasing type order (0x50, 0x51, 0x52, 0x53, ...), so a cycle's gyro packet
directly follows its accel packet. A sample is emitted when a valid 0x52 packet is accepted
*immediately* after a valid 0x51 packet, with no byte skipped between them; an accel packet
not followed that way is counted as ``unpaired_accel`` (and a lone gyro as
``unpaired_gyro``) and dropped: a skipped byte between them may have been a lost cycle
boundary, and pairing across it would mix two cycles.

**Timestamps (host clock).** The HWT901B has no sync input. ``t`` of a sample is the host
time at which the gyro packet's last byte arrived, estimated as ``t_read - (bytes after it in
the same read) * byte_time - latency`` where ``t_read`` is the host time of the ``read()``
that returned the bytes and ``byte_time = 10 / baud`` (8N1). The stamp still contains the
transmission delay of the cycle (11 bytes per packet), the USB-serial adapter's latency timer
(FTDI default 16 ms; 1 ms after ``echo 1 > /sys/bus/usb-serial/devices/ttyUSB0/latency_timer``)
and OS scheduling jitter, none of which is constant: pass a fixed ``latency`` if measured,
and let the estimator estimate the residual camera/IMU time offset (SPEC §2). Back-dating
assumes the bytes came at the baud rate; a read that returns a burst faster than that (a pty,
a buffering hub) would date a packet before the previous read's last one, so a packet
dated before the previous one is moved to ``CLAMP_STEP`` (1 µs) after it, but never past its
own read's time (counted as ``clamped_times``): the stream keeps its order, and its times
keep increasing as readers require wherever the reads' host times do.

**Commands** are writes to a register: ``FF AA reg lo hi`` (value little-endian). Unlock is
register 0x69 = 0xB588 (``FF AA 69 88 B5``), save is register 0x00 = 0 (``FF AA 00 00 00``),
output rate is register 0x03 (code 0x0B = 200 Hz), baud register 0x04 (code 0x06 = 115200).
The unlock, save, 200 Hz and 115200 codes are from FIELD-NOTES; the other rate and baud codes
are from WitMotion's manual / SDK and unverified on our unit. Four packet types at 9600 baud
cap the rate at ~21 Hz; 200 Hz needs >= 115200 baud.
"""

from __future__ import annotations

import dataclasses
import math
import struct
import time
from collections.abc import Iterator

import numpy as np

from jaxslam.errors import ConfigError
from jaxslam.measurements import ImuSample

from ._common import Counters, DriverError, G, HostClock, host_time

# ----------------------------------------------------------------------------- packets

HEADER = 0x55
PACKET_SIZE = 11
TIME, ACCEL, GYRO, ANGLE, MAG, QUATERNION = 0x50, 0x51, 0x52, 0x53, 0x54, 0x59
KNOWN_TYPES = frozenset(range(0x50, 0x5B))
"""Packet types the WIT standard protocol defines (0x50..0x5A)."""

ACC_SCALE = 16.0 * G / 32768.0
"""m/s^2 per LSB (±16 g full scale)."""
GYRO_SCALE = math.radians(2000.0) / 32768.0
"""rad/s per LSB (±2000 °/s full scale)."""
ANGLE_SCALE = math.pi / 32768.0
"""rad per LSB (±180°)."""
QUAT_SCALE = 1.0 / 32768.0

_INT16X4 = struct.Struct("<4h")


CLAMP_STEP = 1e-6
"""Least step (s) between packet times when back-dating would not increase them."""


def checksum(data: bytes | bytearray) -> int:
    """The WIT checksum: low byte of the sum of ``data`` (the first 10 bytes of a packet)."""
    return sum(data) & 0xFF


def build_packet(kind: int, d0: int = 0, d1: int = 0, d2: int = 0, d3: int = 0) -> bytes:
    """An 11-byte packet of ``kind`` carrying four int16 values (for tests and simulators)."""
    body = bytes((HEADER, kind & 0xFF)) + _INT16X4.pack(d0, d1, d2, d3)
    return body + bytes((checksum(body),))


def is_valid_packet(window: bytes | bytearray) -> bool:
    """Whether 11 bytes form a packet: 0x55, a known type, a matching checksum."""
    return (
        len(window) == PACKET_SIZE
        and window[0] == HEADER
        and window[1] in KNOWN_TYPES
        and checksum(window[:10]) == window[10]
    )


@dataclasses.dataclass(frozen=True)
class WitPacket:
    """One decoded packet: ``kind`` (type byte), ``raw`` (the four int16 fields), ``values``
    (decoded, SI units, per the module table), ``t`` (host time of its last byte, s) and
    ``follows`` (it came directly after the previous accepted packet, no byte skipped)."""

    kind: int
    raw: tuple[int, int, int, int]
    values: np.ndarray
    t: float
    follows: bool = False


def decode_packet(window: bytes | bytearray, t: float = math.nan, follows: bool = False) -> WitPacket:
    """Decode one valid 11-byte packet (the caller checked :func:`is_valid_packet`)."""
    kind = window[1]
    raw = _INT16X4.unpack_from(window, 2)
    if kind == ACCEL:
        values = np.array([raw[0] * ACC_SCALE, raw[1] * ACC_SCALE, raw[2] * ACC_SCALE, raw[3] / 100.0])
    elif kind == GYRO:
        values = np.array([raw[0] * GYRO_SCALE, raw[1] * GYRO_SCALE, raw[2] * GYRO_SCALE])
    elif kind == ANGLE:
        values = np.array([raw[0] * ANGLE_SCALE, raw[1] * ANGLE_SCALE, raw[2] * ANGLE_SCALE])
    elif kind == MAG:
        values = np.array([float(raw[0]), float(raw[1]), float(raw[2]), raw[3] / 100.0])
    elif kind == QUATERNION:
        values = np.array(raw, dtype=np.float64) * QUAT_SCALE
    elif kind == TIME:
        b = window[2:10]
        values = np.array([2000 + b[0], b[1], b[2], b[3], b[4], b[5], b[6] | (b[7] << 8)], dtype=np.float64)
    else:
        values = np.array(raw, dtype=np.float64)
    return WitPacket(kind=kind, raw=raw, values=values, t=t, follows=follows)


# ----------------------------------------------------------------------------- parser


class WitMotionParser:
    """Streaming parser: bytes in (any chunking), :class:`ImuSample` out.

    ``feed(data, t_read)`` returns the samples completed by ``data``; the last decoded packet
    of every type is kept in ``latest`` (angles, quaternion, magnetic field, chip time).
    ``counters`` holds ``bytes_in``, ``packets``, ``skipped_bytes``, ``bad_checksum``,
    ``unknown_type``, ``unconfirmed``, ``samples``, ``unpaired_accel``, ``unpaired_gyro``,
    ``invalid_samples``. Bad input is counted and skipped, never raised.

    Args:
        byte_time: transmission time of one byte (s), ``10 / baud``; 0 stamps every packet of
            a read with the read's time.
        latency: a constant subtracted from every host timestamp (s).
    """

    def __init__(self, byte_time: float = 0.0, latency: float = 0.0):
        self.byte_time = float(byte_time)
        self.latency = float(latency)
        self.counters = Counters(
            "bytes_in",
            "packets",
            "skipped_bytes",
            "bad_checksum",
            "unknown_type",
            "unconfirmed",
            "samples",
            "unpaired_accel",
            "unpaired_gyro",
            "invalid_samples",
            "clamped_times",
        )
        self.latest: dict[int, WitPacket] = {}
        self._buf = bytearray()
        self._start = 0  # stream offset of self._buf[0]
        self._chunks: list[tuple[int, float]] = []  # (stream offset one past a read's end, its host time)
        self._locked = False  # the byte before the scan position ended an accepted packet
        self._accel: WitPacket | None = None  # accel packet waiting for its gyro packet
        self._last_t = -math.inf  # host time of the last packet: packet times increase

    def feed(self, data: bytes | bytearray, t_read: float | None = None) -> list[ImuSample]:
        """Parse ``data`` (read at host time ``t_read``, default now); return new samples."""
        samples = []
        for pkt in self.feed_packets(data, t_read):
            if pkt.kind == GYRO and self._accel is not None and pkt.follows:
                acc = self._accel.values[:3].copy()
                self._accel = None
                sample = ImuSample(t=pkt.t - self.latency, acc=acc, gyro=pkt.values.copy())
                try:
                    sample.validate("witmotion")
                except ValueError:  # InputFormatError; unreachable with int16 fields
                    self.counters.add("invalid_samples")
                    continue
                self.counters.add("samples")
                samples.append(sample)
            elif pkt.kind == GYRO:
                self.counters.add("unpaired_gyro")
                self._drop_accel()
            else:
                self._drop_accel()
                if pkt.kind == ACCEL:
                    self._accel = pkt
        return samples

    def feed_packets(self, data: bytes | bytearray, t_read: float | None = None) -> list[WitPacket]:
        """Parse ``data`` and return the packets it completes (no pairing into samples).

        Call :meth:`feed` *or* this, not both on one stream: pairing state lives in ``feed``.
        """
        if t_read is None:
            t_read = host_time()
        self.counters.add("bytes_in", len(data))
        if data:
            self._buf += data
            self._chunks.append((self._start + len(self._buf), float(t_read)))
        buf = self._buf
        n = len(buf)
        pos = 0
        packets: list[WitPacket] = []
        while pos < n:
            i = buf.find(HEADER, pos)
            if i < 0:
                self._skip(n - pos)
                pos = n
                break
            if i > pos:
                self._skip(i - pos)
                pos = i
            if n - i < PACKET_SIZE:
                break  # wait for the rest of the packet
            if not self._window_ok(buf, i):
                self._skip(1)
                pos = i + 1
                continue
            if not self._locked:
                if n - i < 2 * PACKET_SIZE:
                    break  # wait for the packet that confirms this one
                if not self._window_ok(buf, i + PACKET_SIZE, count=False):
                    self.counters.add("unconfirmed")
                    self._skip(1)
                    pos = i + 1
                    continue
            end = i + PACKET_SIZE
            t_pkt = self._arrival(self._start + end - 1)
            if t_pkt < self._last_t:  # a burst faster than the baud rate (a pty, a USB hub):
                self.counters.add("clamped_times")  # back-dating must not reorder packets
                t_pkt = max(t_pkt, min(self._last_t + CLAMP_STEP, self._chunk(self._start + end - 1)[1]))
            self._last_t = t_pkt
            pkt = decode_packet(buf[i:end], t_pkt, self._locked)
            self.latest[pkt.kind] = pkt
            self.counters.add("packets")
            packets.append(pkt)
            self._locked = True
            pos = end
        del buf[:pos]
        self._start += pos
        while self._chunks and self._chunks[0][0] <= self._start:
            self._chunks.pop(0)
        return packets

    @property
    def buffered(self) -> int:
        """Bytes held back waiting for the rest of a packet or its confirming packet."""
        return len(self._buf)

    def _window_ok(self, buf: bytearray, i: int, count: bool = True) -> bool:
        if buf[i + 1] not in KNOWN_TYPES:
            if count:
                self.counters.add("unknown_type")
            return False
        if sum(buf[i : i + 10]) & 0xFF != buf[i + 10]:
            if count:
                self.counters.add("bad_checksum")
            return False
        return True

    def _skip(self, n: int) -> None:
        self.counters.add("skipped_bytes", n)
        self._locked = False

    def _drop_accel(self) -> None:
        if self._accel is not None:
            self.counters.add("unpaired_accel")
            self._accel = None

    def _chunk(self, offset: int) -> tuple[int, float]:
        """``(end, t_read)`` of the read that returned the byte at stream ``offset``."""
        for end, t in self._chunks:
            if offset < end:
                return end, t
        return self._chunks[-1]  # pragma: no cover - offset is always inside a chunk

    def _arrival(self, offset: int) -> float:
        """Host time at which the byte at stream ``offset`` arrived."""
        end, t = self._chunk(offset)
        return t - (end - 1 - offset) * self.byte_time


# ----------------------------------------------------------------------------- commands

REG_SAVE, REG_RATE, REG_BAUD, REG_KEY = 0x00, 0x03, 0x04, 0x69

RATE_CODES: dict[float, int] = {
    0.2: 0x01,
    0.5: 0x02,
    1: 0x03,
    2: 0x04,
    5: 0x05,
    10: 0x06,
    20: 0x07,
    50: 0x08,
    100: 0x09,
    200: 0x0B,
}
"""Output rate (Hz) -> code of register 0x03. 0x0B = 200 Hz is from FIELD-NOTES; the rest
from WitMotion's SDK (0x0A is left out: manuals disagree on it)."""

BAUD_CODES: dict[int, int] = {
    4800: 0x01,
    9600: 0x02,
    19200: 0x03,
    38400: 0x04,
    57600: 0x05,
    115200: 0x06,
    230400: 0x07,
    460800: 0x08,
    921600: 0x09,
}
"""Baud rate -> code of register 0x04. 0x06 = 115200 is from FIELD-NOTES; the rest from
WitMotion's SDK (the HWT901B manual lists up to 921600; unverified on our unit)."""


def write_register(reg: int, value: int) -> bytes:
    """The command writing ``value`` (uint16) to register ``reg``: ``FF AA reg lo hi``."""
    if not 0 <= reg <= 0xFF:
        raise ConfigError(f"WitMotion register must be 0..255, got {reg}")
    if not 0 <= value <= 0xFFFF:
        raise ConfigError(f"WitMotion register value must be 0..65535, got {value}")
    return bytes((0xFF, 0xAA, reg, value & 0xFF, value >> 8))


UNLOCK = write_register(REG_KEY, 0xB588)
"""``FF AA 69 88 B5``: unlock before writing configuration registers (newer firmware)."""
SAVE = write_register(REG_SAVE, 0x0000)
"""``FF AA 00 00 00``: save the configuration to flash."""


def rate_command(rate_hz: float) -> bytes:
    """``FF AA 03 code 00``: set the output rate (one of :data:`RATE_CODES`)."""
    if rate_hz not in RATE_CODES:
        raise ConfigError(f"WitMotion rate must be one of {sorted(RATE_CODES)} Hz, got {rate_hz}")
    return write_register(REG_RATE, RATE_CODES[rate_hz])


def baud_command(baud: int) -> bytes:
    """``FF AA 04 code 00``: set the serial baud rate (one of :data:`BAUD_CODES`)."""
    if baud not in BAUD_CODES:
        raise ConfigError(f"WitMotion baud must be one of {sorted(BAUD_CODES)}, got {baud}")
    return write_register(REG_BAUD, BAUD_CODES[baud])


def check_bandwidth(rate_hz: float, baud: int, packets_per_cycle: int = 4) -> None:
    """Raise :class:`ConfigError` when ``packets_per_cycle`` packets at ``rate_hz`` do not fit
    the serial line (11 bytes x 10 bits per packet): e.g. 4 packets need 88 kbit/s at 200 Hz."""
    need = rate_hz * packets_per_cycle * PACKET_SIZE * 10
    if need > baud:
        raise ConfigError(
            f"{packets_per_cycle} packet types at {rate_hz} Hz need {need:.0f} bit/s; {baud} baud is too slow "
            f"(at most {baud / (packets_per_cycle * PACKET_SIZE * 10):.1f} Hz)"
        )


# ----------------------------------------------------------------------------- serial port


class WitMotionSerial:
    """The HWT901B on a serial port (pyserial): ``read_samples()`` and ``configure()``.

    ``port`` is a device path (``/dev/ttyUSB0``); ``baud`` the sensor's current baud rate
    (115200 recommended; factory default 9600); ``timeout`` (s) bounds each ``read``.
    Opening or reading a port that fails raises :class:`~drivers._common.DriverError`;
    usable as a context manager.
    """

    def __init__(
        self,
        port: str,
        baud: int = 115200,
        timeout: float = 0.1,
        *,
        latency: float = 0.0,
        clock: HostClock = host_time,
    ):
        try:
            import serial
        except ImportError as exc:  # pragma: no cover - pyserial is a dev dependency
            raise ConfigError("the WitMotion driver needs pyserial: pip install 'jaxslam[drivers]'") from exc
        self._serial_error = serial.SerialException
        try:
            self.serial = serial.Serial(port, baud, timeout=timeout)
        except (serial.SerialException, OSError, ValueError) as exc:
            raise DriverError(f"cannot open WitMotion serial port {port!r} at {baud} baud: {exc}") from exc
        self.port = port
        self.clock = clock
        self.parser = WitMotionParser(byte_time=10.0 / baud, latency=latency)
        self.timeouts = 0

    @property
    def counters(self) -> Counters:
        return self.parser.counters

    def read_samples(self, max_samples: int | None = None, duration: float | None = None) -> Iterator[ImuSample]:
        """Yield samples as they arrive, until ``max_samples`` were yielded or ``duration``
        seconds passed (both ``None``: forever). Reads that time out are counted in
        ``timeouts``; a failing port raises :class:`DriverError`."""
        deadline = None if duration is None else time.monotonic() + duration
        emitted = 0
        while max_samples is None or emitted < max_samples:
            if deadline is not None and time.monotonic() >= deadline:
                return
            try:
                data = self.serial.read(max(1, self.serial.in_waiting))
            except (self._serial_error, OSError) as exc:
                raise DriverError(f"reading WitMotion serial port {self.port!r} failed: {exc}") from exc
            t_read = self.clock()
            if not data:
                self.timeouts += 1
                continue
            for sample in self.parser.feed(data, t_read):
                yield sample
                emitted += 1
                if max_samples is not None and emitted >= max_samples:
                    return

    def send(self, command: bytes) -> None:
        """Write raw command bytes and wait until they are sent."""
        try:
            self.serial.write(command)
            self.serial.flush()
        except (self._serial_error, OSError) as exc:
            raise DriverError(f"writing WitMotion serial port {self.port!r} failed: {exc}") from exc

    def configure(
        self,
        rate_hz: float = 200,
        baud: int | None = None,
        *,
        packets_per_cycle: int = 4,
        pause: float = 0.1,
    ) -> list[bytes]:
        """Set the output rate (and optionally the baud rate) and save; return the commands sent.

        Sequence: unlock, rate, save at the current baud; then, when ``baud`` differs, unlock,
        baud (the sensor switches at once), switch this port, unlock, save at the new baud.
        ``pause`` (s) separates commands. Raises :class:`ConfigError` for an unsupported rate
        or baud, or when the rate does not fit the (new) baud rate (:func:`check_bandwidth`).
        Whether the save must follow the baud switch varies between WitMotion manuals: check
        the setting survives a power cycle.
        """
        current = int(self.serial.baudrate)
        target = current if baud is None else int(baud)
        commands = [UNLOCK, rate_command(rate_hz), SAVE]
        if target != current:
            commands_baud = [UNLOCK, baud_command(target)]
        else:
            commands_baud = []
        check_bandwidth(rate_hz, target, packets_per_cycle)
        for cmd in commands:
            self.send(cmd)
            time.sleep(pause)
        if commands_baud:
            for cmd in commands_baud:
                self.send(cmd)
                time.sleep(pause)
            self.serial.baudrate = target
            self.parser.byte_time = 10.0 / target
            for cmd in (UNLOCK, SAVE):
                self.send(cmd)
                time.sleep(pause)
            commands += [*commands_baud, UNLOCK, SAVE]
        return commands

    def close(self) -> None:
        self.serial.close()

    def __enter__(self) -> WitMotionSerial:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

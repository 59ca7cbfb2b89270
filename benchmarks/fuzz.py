"""Fuzz the packet parsers and the recording readers with random and mutated inputs.

Targets (each input is one stream / datagram / file):

- ``witmotion``: byte streams of valid cycles, mutated packets, truncated packets and random
  bytes, fed to :class:`drivers.witmotion.WitMotionParser` in random chunk sizes. It must never
  raise (bad bytes are counted); every byte must be accounted for.
- ``livox``: valid, mutated and random datagrams to :func:`drivers.livox.parse_packet` (only
  :class:`~drivers.livox.PacketError` allowed) and :class:`drivers.livox.LivoxStream` (never
  raises; every datagram counted once).
- ``rosbag``: a small valid ROS1 bag and a ROS2 mcap bag written by
  :class:`jaxslam.io.RosbagWriter` (IMU, image, cloud, pose, total-station fix), mutated (bit
  flips, byte overwrites, truncation, deleted / duplicated / inserted slices), then opened with
  ``open_recording`` and iterated (streams, records, ground truth).
- ``euroc``: an EuRoC folder from :class:`jaxslam.io.EurocWriter` whose csv files get mutated
  lines (fields replaced by odd tokens, dropped, added; non-UTF-8 bytes; truncation), opened
  and iterated.

Outcome per input: ``ok``, ``jaxslam_error`` (a :class:`~jaxslam.errors.JaxSlamError`: the
allowed failure) or ``other`` (anything else: a bug; the first few are printed with their
traceback and the input saved under ``--save``). Usage::

    python benchmarks/fuzz.py --count 100000 [--targets witmotion,livox,rosbag,euroc] [--seed 0]

Exits 1 when any target had an ``other`` outcome. Not a test (the tests run
:func:`run_target` with a small count).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import tempfile
import time
import traceback
import warnings
from collections import Counter
from collections.abc import Callable
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from drivers import livox, witmotion  # noqa: E402
from jaxslam.errors import JaxSlamError  # noqa: E402

# ----------------------------------------------------------------------------- mutations

_INTERESTING = bytes([0x00, 0x01, 0x7F, 0x80, 0xFF, 0x55, 0x0A, 0x2C, 0x3D])


def mutate_bytes(data: bytes, rng: np.random.Generator, max_edits: int = 8) -> bytes:
    """Apply 1..max_edits random edits: bit flips, byte overwrites, truncation, deleted,
    duplicated and inserted slices."""
    out = bytearray(data)
    for _ in range(int(rng.integers(1, max_edits + 1))):
        n = len(out)
        op = int(rng.integers(0, 7))
        if n == 0:
            out += rng.bytes(int(rng.integers(1, 16)))
            continue
        pos = int(rng.integers(0, n))
        if op == 0:
            out[pos] ^= 1 << int(rng.integers(0, 8))
        elif op == 1:
            out[pos] = _INTERESTING[int(rng.integers(0, len(_INTERESTING)))]
        elif op == 2:
            out[pos] = int(rng.integers(0, 256))
        elif op == 3:
            del out[pos:]
        elif op == 4:
            del out[pos : pos + int(rng.integers(1, 64))]
        elif op == 5:
            ln = int(rng.integers(1, 64))
            out[pos:pos] = out[pos : pos + ln]
        else:
            out[pos:pos] = rng.bytes(int(rng.integers(1, 16)))
    return bytes(out)


class Tally:
    """Outcome counts of one target and the first failures."""

    def __init__(self, name: str, save: Path | None = None, show: int = 3):
        self.name, self.save, self.show = name, save, show
        self.counts: Counter[str] = Counter(inputs=0, ok=0, jaxslam_error=0, other=0)
        self.errors: Counter[str] = Counter()

    def run(self, fn: Callable[[], None], payload: bytes | None = None) -> None:
        self.counts["inputs"] += 1
        try:
            fn()
            self.counts["ok"] += 1
        except JaxSlamError as exc:
            self.counts["jaxslam_error"] += 1
            self.errors[type(exc).__name__ + ": " + str(exc).split(": ")[-1][:60]] += 1
        except Exception as exc:
            self.counts["other"] += 1
            self.errors["OTHER " + type(exc).__name__ + ": " + str(exc)[:80]] += 1
            if self.counts["other"] <= self.show:
                print(f"[{self.name}] {type(exc).__name__}: {exc}", file=sys.stderr)
                traceback.print_exc(limit=6)
                if self.save is not None and payload is not None:
                    self.save.mkdir(parents=True, exist_ok=True)
                    (self.save / f"{self.name}-{self.counts['other']}.bin").write_bytes(payload)


# ----------------------------------------------------------------------------- targets


def _wit_stream(rng: np.random.Generator) -> bytes:
    parts = []
    for _ in range(int(rng.integers(1, 12))):
        kind = int(rng.integers(0, 6))
        vals = [int(v) for v in rng.integers(-32768, 32768, 4)]
        if kind <= 1:
            parts.append(
                witmotion.build_packet(witmotion.ACCEL, *vals)
                + witmotion.build_packet(witmotion.GYRO, *vals[::-1])
                + witmotion.build_packet(witmotion.ANGLE, *vals)
            )
        elif kind == 2:
            parts.append(witmotion.build_packet(int(rng.choice([0x50, 0x54, 0x59, 0x5A, 0x42])), *vals))
        elif kind == 3:
            good = witmotion.build_packet(witmotion.ACCEL, *vals) + witmotion.build_packet(witmotion.GYRO, *vals)
            parts.append(mutate_bytes(good, rng, 3))
        elif kind == 4:
            parts.append(witmotion.build_packet(witmotion.GYRO, *vals)[: int(rng.integers(1, 11))])
        else:
            parts.append(rng.bytes(int(rng.integers(1, 40))))
    return b"".join(parts)


def fuzz_witmotion(count: int, rng: np.random.Generator, tally: Tally) -> None:
    for _ in range(count):
        stream = _wit_stream(rng)
        chunk = int(rng.integers(1, 64))

        def run(stream: bytes = stream, chunk: int = chunk) -> None:
            p = witmotion.WitMotionParser(byte_time=1e-4)
            for k in range(0, len(stream), chunk):
                for s in p.feed(stream[k : k + chunk], 1.0):
                    s.validate()
            c = p.counters
            if c["bytes_in"] != 11 * c["packets"] + c["skipped_bytes"] + p.buffered:
                raise AssertionError(f"bytes not accounted for: {c}")

        tally.run(run, stream)


def _livox_datagram(rng: np.random.Generator) -> bytes:
    kind = int(rng.integers(0, 4))
    if kind == 3:
        return rng.bytes(int(rng.integers(0, 120)))
    dtype = int(rng.choice([livox.IMU_DATA, livox.CARTESIAN_HIGH, livox.CARTESIAN_LOW]))
    n = int(rng.integers(0, 40))
    if dtype == livox.IMU_DATA:
        payload, n = livox.imu_payload(rng.normal(size=3), rng.normal(size=3)), 1
    elif dtype == livox.CARTESIAN_HIGH:
        payload = livox.high_points_payload(rng.integers(-(2**31), 2**31, (n, 3)))
    else:
        payload = livox.low_points_payload(rng.integers(-(2**15), 2**15, (n, 3)))
    data = livox.build_packet(
        dtype,
        payload,
        n,
        timestamp_ns=int(rng.integers(0, 2**62)),
        time_interval=int(rng.integers(0, 2**16)),
        udp_cnt=int(rng.integers(0, 2**16)),
    )
    return data if kind == 0 else mutate_bytes(data, rng, 4)


def fuzz_livox(count: int, rng: np.random.Generator, tally: Tally) -> None:
    stream = livox.LivoxStream(max_points=500)
    for i in range(count):
        data = _livox_datagram(rng)
        check_crc = bool(i % 2)

        def run(data: bytes = data, check_crc: bool = check_crc) -> None:
            try:
                livox.parse_packet(data, check_crc=check_crc)
            finally:
                for r in stream.feed(data):  # never raises
                    r.validate()

        tally.run(run, data)
        if i % 50 == 49:
            stream.flush()


def _sample_records() -> list:
    from jaxslam.measurements import Image, ImuSample, LidarScan, PoseStamped, PositionFix

    rng = np.random.default_rng(7)
    t0 = 1_700_000_000.0
    recs: list = [ImuSample(t0 + k * 0.01, rng.normal(size=3), rng.normal(size=3)) for k in range(6)]
    for k in range(2):
        t = t0 + 0.003 + 0.02 * k
        recs.append(Image(t, rng.integers(0, 255, (4, 5), dtype=np.uint8), camera="cam0"))
        recs.append(LidarScan(t, rng.normal(size=(5, 3)), np.ones(5), np.arange(5) * 1e-3, np.arange(5)))
        q = rng.normal(size=4)
        recs.append(PoseStamped(t + 0.001, np.concatenate([q / np.linalg.norm(q), rng.normal(size=3)])))
        recs.append(PositionFix(t + 0.002, rng.normal(size=3), 0.003))
    return sorted(recs, key=lambda r: r.t)


def _consume(rec) -> None:
    rec.streams()
    for r in rec:
        r.validate()
    rec.ground_truth()


def fuzz_rosbag(count: int, rng: np.random.Generator, tally: Tally, work: Path) -> None:
    from jaxslam.io import open_recording, open_writer

    seeds: list[tuple[str, bytes]] = []
    for fmt, name in (("bag", "seed.bag"), ("bag2", "seed2")):
        with open_writer(work / name, fmt) as w:
            w.write_all(_sample_records())
        if fmt == "bag":
            seeds.append((".bag", (work / name).read_bytes()))
        else:
            (mcap,) = (work / name).glob("*.mcap")
            seeds.append((".mcap", mcap.read_bytes()))
    for i in range(count):
        suffix, seed = seeds[i % 4 == 3]  # 3 of 4 inputs ROS1
        data = mutate_bytes(seed, rng, 8)
        path = work / f"fuzz{suffix}"
        path.write_bytes(data)

        def run(path: Path = path) -> None:
            _consume(open_recording(path))

        tally.run(run, data)


_TOKENS = ["", "nan", "inf", "-inf", "1e400", "abc", "-", "0x10", " ", "9" * 30, "1.5", "-0", "\x00", "é", "1,2"]


def _mutate_csv(text: str, rng: np.random.Generator) -> bytes:
    lines = text.splitlines()
    for _ in range(int(rng.integers(1, 5))):
        if not lines:
            lines.append("")
        i = int(rng.integers(0, len(lines)))
        fields = lines[i].split(",")
        op = int(rng.integers(0, 6))
        j = int(rng.integers(0, len(fields)))
        if op == 0:
            fields[j] = _TOKENS[int(rng.integers(0, len(_TOKENS)))]
        elif op == 1:
            del fields[j]
        elif op == 2:
            fields.insert(j, _TOKENS[int(rng.integers(0, len(_TOKENS)))])
        elif op == 3:
            lines.insert(i, lines[i])  # duplicated line: time not increasing
            continue
        elif op == 4:
            del lines[i]
            continue
        else:
            fields[j] = fields[j][: int(rng.integers(0, len(fields[j]) + 1))]
        lines[i] = ",".join(fields)
    data = ("\n".join(lines) + "\n").encode()
    if rng.random() < 0.2:
        data = mutate_bytes(data, rng, 3)  # raw bytes: non-UTF-8, NUL, cut lines
    return data


def fuzz_euroc(count: int, rng: np.random.Generator, tally: Tally, work: Path) -> None:
    from jaxslam.io import EurocRecording, open_writer

    seed = work / "euroc"
    with open_writer(seed, "euroc") as w:
        w.write_all(_sample_records())
    csvs = sorted(p.relative_to(seed) for p in seed.rglob("data.csv"))
    originals = {p: (seed / p).read_text() for p in csvs}
    for _ in range(count):
        target = csvs[int(rng.integers(0, len(csvs)))]
        data = _mutate_csv(originals[target], rng)
        (seed / target).write_bytes(data)

        def run() -> None:
            _consume(EurocRecording(seed))

        tally.run(run, data)
        (seed / target).write_text(originals[target])


TARGETS = ("witmotion", "livox", "rosbag", "euroc")


def run_target(name: str, count: int, seed: int = 0, save: Path | None = None) -> Tally:
    """Fuzz one target with ``count`` inputs; return its :class:`Tally`."""
    rng = np.random.default_rng([seed, TARGETS.index(name)])
    tally = Tally(name, save)
    shm = Path("/dev/shm") if Path("/dev/shm").is_dir() else None
    work = Path(tempfile.mkdtemp(prefix=f"fuzz-{name}-", dir=shm))
    try:
        with warnings.catch_warnings(), np.errstate(all="ignore"):
            warnings.simplefilter("ignore")  # the bag reader warns when it stops part-way
            if name == "witmotion":
                fuzz_witmotion(count, rng, tally)
            elif name == "livox":
                fuzz_livox(count, rng, tally)
            elif name == "rosbag":
                fuzz_rosbag(count, rng, tally, work)
            elif name == "euroc":
                fuzz_euroc(count, rng, tally, work)
            else:
                raise ValueError(f"unknown target {name!r}; targets: {', '.join(TARGETS)}")
    finally:
        shutil.rmtree(work, ignore_errors=True)
    return tally


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--count", type=int, default=100_000, help="inputs per target")
    ap.add_argument("--targets", default=",".join(TARGETS))
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--save", type=Path, help="folder for inputs that raised something else")
    ap.add_argument("--json", action="store_true", help="print the counts as JSON")
    args = ap.parse_args()
    results = {}
    for name in args.targets.split(","):
        t0 = time.perf_counter()
        tally = run_target(name, args.count, args.seed, args.save)
        dt = time.perf_counter() - t0
        results[name] = {**tally.counts, "seconds": round(dt, 1)}
        print(
            f"{name:10s} inputs {tally.counts['inputs']:7d}  ok {tally.counts['ok']:7d}  "
            f"JaxSlamError {tally.counts['jaxslam_error']:7d}  other {tally.counts['other']:3d}  ({dt:.0f} s)",
            flush=True,
        )
        for msg, n in tally.errors.most_common(6):
            print(f"    {n:7d}  {msg}")
    if args.json:
        print(json.dumps(results))
    return 1 if any(r["other"] for r in results.values()) else 0


if __name__ == "__main__":
    os.environ.setdefault("JAX_PLATFORMS", "cpu")
    sys.exit(main())

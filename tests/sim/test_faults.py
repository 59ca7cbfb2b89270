"""Fault injection (jaxslam.sim._faults): each fault on a hand-made record stream, windows
relative to the first record, determinism by seed, and what survives a write + read round
trip through the recording writers and readers."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from jaxslam.errors import ConfigError, InputFormatError
from jaxslam.io import open_recording, open_writer
from jaxslam.measurements import Image, ImuSample, LidarScan, PositionFix
from jaxslam.sim import (
    CameraDark,
    NanSamples,
    SensorDropout,
    TimeJump,
    Truncate,
    inject_faults,
    truncate_file,
    write_faulty,
)

T0 = 1000.0


def stream(t0: float = T0, seconds: float = 2.0, first: str = "imu") -> list:
    """IMU at 100 Hz, images (8x6 uint8) and 20-point scans at 10 Hz, a fix at 1 Hz; stamps
    on a 10 ms grid (images and scans 5 ms off the IMU's), time ordered."""
    rng = np.random.default_rng(1)
    recs: list = []
    for k in range(int(seconds * 100)):
        recs.append(ImuSample(t0 + 0.01 * k, rng.normal(size=3) + np.array([0, 0, 9.81]), rng.normal(size=3) * 0.1))
    for k in range(int(seconds * 10)):
        t = t0 + 0.1 * k + 0.005
        recs.append(Image(t, rng.integers(0, 256, (6, 8), dtype=np.uint8)))
        pts = rng.normal(size=(20, 3)) * 5
        recs.append(LidarScan(t, pts, rng.uniform(0, 255, 20), np.linspace(0, 0.09, 20), np.arange(20) % 4))
    recs.append(PositionFix(t0 + 0.5025, np.array([1.0, 2.0, 3.0])))
    if first != "imu":  # a record of another kind opens the stream
        recs.append(dataclasses.replace(next(r for r in recs if r.kind == first), t=t0 - 0.002))
    return sorted(recs, key=lambda r: r.t)


def of(recs: list, kind: str) -> list:
    return [r for r in recs if r.kind == kind]


def rel(recs: list, t0: float = T0) -> np.ndarray:
    return np.array([r.t - t0 for r in recs])


def test_no_faults_is_the_identity():
    src = stream()
    out = list(inject_faults(iter(src), []))
    assert len(out) == len(src) and all(a is b for a, b in zip(out, src))


@pytest.mark.parametrize("float_image", [False, True])
def test_camera_dark_darkens_only_images_in_the_window(float_image):
    src = stream()
    if float_image:
        src = [dataclasses.replace(r, data=r.data / 255.0) if r.kind == "image" else r for r in src]
    fault = CameraDark(start=0.5, duration=0.6)  # images at 0.505 .. 1.005 (6 of 20)
    out = list(inject_faults(src, [fault], seed=3))
    assert len(out) == len(src)
    changed = 0
    for a, b in zip(src, out):
        inside = a.kind == "image" and 0.5 <= a.t - T0 < 1.1
        if not inside:
            assert a is b
            continue
        changed += 1
        assert b.t == a.t and b.data.dtype == a.data.dtype and b.data.shape == a.data.shape
        scale = 1.0 if float_image else 255.0
        dark = a.data * 0.02
        assert np.all(np.abs(b.data - dark) <= 6 / 255 * scale)  # read noise of 1 grey level
        assert b.data.mean() < 0.05 * scale
    assert changed == 6


def test_camera_dark_without_noise_is_exactly_the_gain_and_respects_the_camera():
    src = stream()
    src += [dataclasses.replace(r, camera="cam1", t=r.t + 0.001) for r in of(src, "image")]
    src.sort(key=lambda r: r.t)
    out = list(inject_faults(src, [CameraDark(0.0, 10.0, gain=0.1, read_noise=0.0, camera="cam1")]))
    for a, b in zip(src, out):
        if a.kind == "image" and a.camera == "cam1":
            np.testing.assert_array_equal(b.data, np.rint(a.data * 0.1).astype(np.uint8))
        else:
            assert a is b


@pytest.mark.parametrize(("kind", "start", "duration"), [("lidar", 0.3, 1.0), ("imu", 0.5, 0.5), ("image", 0.0, 0.2)])
def test_sensor_dropout_removes_exactly_the_window(kind, start, duration):
    src = stream()
    out = list(inject_faults(src, [SensorDropout(kind, start, duration)]))
    gone = [r for r in src if r.kind == kind and start <= r.t - T0 < start + duration]
    assert gone
    kept = [r for r in src if not any(r is g for g in gone)]
    assert len(out) == len(kept) and all(a is b for a, b in zip(out, kept))
    assert not any(start <= r.t - T0 < start + duration for r in of(out, kind))


def test_dropout_of_half_a_second_of_imu_counts():
    src = stream()
    out = list(inject_faults(src, [SensorDropout("imu", 0.995, 0.5)]))  # IMU at 1.00 .. 1.49
    assert len(of(out, "imu")) == len(of(src, "imu")) - 50
    t = rel(of(out, "imu"))
    assert np.max(np.diff(t)) == pytest.approx(0.51)


def test_nan_samples_imu_every_third():
    src = stream()
    out = list(inject_faults(src, [NanSamples("imu", 3)], seed=1))
    a, b = of(src, "imu"), of(out, "imu")
    for k, (x, y) in enumerate(zip(a, b), start=1):
        if k % 3:
            assert x is y
            continue
        assert y.t == x.t
        for name in ("acc", "gyro"):
            bad = ~np.isfinite(getattr(y, name))
            assert bad.sum() == 1  # one component
            np.testing.assert_array_equal(getattr(y, name)[~bad], getattr(x, name)[~bad])
        with pytest.raises(InputFormatError):
            y.validate()
        assert np.all(np.isfinite(x.acc))  # the input record is untouched
    assert all(x is y for x, y in zip(of(src, "image"), of(out, "image")))


def test_nan_samples_lidar_points_and_image_pixels():
    src = stream()
    out = list(inject_faults(src, [NanSamples("lidar", 2, fraction=0.25), NanSamples("image", 5, fraction=0.1)]))
    for k, (x, y) in enumerate(zip(of(src, "lidar"), of(out, "lidar")), start=1):
        if k % 2:
            assert x is y
            continue
        bad = ~np.isfinite(y.points)
        rows = bad.any(1)
        assert rows.sum() == 5 and np.all(bad[rows])  # 25 % of 20 points, all three coordinates
        np.testing.assert_array_equal(y.points[~rows], x.points[~rows])
        np.testing.assert_array_equal(y.intensity, x.intensity)
    for k, (x, y) in enumerate(zip(of(src, "image"), of(out, "image")), start=1):
        if k % 5:
            assert x is y
            continue
        assert y.data.dtype.kind == "f" and y.data.shape == x.data.shape
        bad = np.isnan(y.data)
        assert bad.sum() == round(0.1 * 48)
        np.testing.assert_allclose(y.data[~bad], x.data[~bad] / 255.0, rtol=0, atol=0)


def test_time_jump_moves_three_records_back_then_resumes():
    src = stream()
    out = list(inject_faults(src, [TimeJump("imu", at=1.0, back=0.2)]))
    assert len(out) == len(src)
    for x, y in zip(src, out):
        if x.kind == "imu" and 1.0 - 1e-9 < x.t - T0 < 1.025:  # IMU at 1.00, 1.01, 1.02
            assert y.t == x.t - 0.2
            np.testing.assert_array_equal(y.acc, x.acc)
        else:
            assert x is y
    t = rel(of(out, "imu"))
    assert (np.diff(t) < 0).sum() == 1  # one step back, then forward again


def test_truncate_ends_the_stream_and_stops_reading():
    src = stream()
    consumed = []

    def gen():
        for r in src:
            consumed.append(r)
            yield r

    out = list(inject_faults(gen(), [Truncate(at=0.7)]))
    assert out == [r for r in src if r.t - T0 < 0.7]
    assert len(consumed) == len(out) + 1
    assert list(inject_faults(src, [Truncate(0.0)])) == []


def test_windows_are_relative_to_the_first_record_of_any_kind():
    faults = [SensorDropout("lidar", 0.3, 1.0), TimeJump("imu", 1.0, 0.2), Truncate(1.5)]
    a = list(inject_faults(stream(t0=0.0), faults))
    b = list(inject_faults(stream(t0=1.7e9), faults))
    assert [r.kind for r in a] == [r.kind for r in b]
    np.testing.assert_allclose(rel(a, 0.0), rel(b, 1.7e9), atol=1e-6)
    # a scan first (2 ms before the first IMU sample) shifts every window by 2 ms
    c = list(inject_faults(stream(first="lidar"), [SensorDropout("imu", 0.0, 0.0205)]))
    assert c[0].kind == "lidar"
    assert [round(r.t - T0, 3) for r in of(c, "imu")][:2] == [0.02, 0.03]


def test_seeds_make_it_deterministic():
    src = stream()
    faults = [CameraDark(0.0, 2.0), NanSamples("lidar", 1), NanSamples("imu", 2)]

    def arrays(recs):
        return [
            np.nan_to_num(np.asarray(getattr(r, f), float), nan=-1)
            for r in recs
            for f in ("data", "points", "acc")
            if hasattr(r, f)
        ]

    a, b, c = (arrays(inject_faults(src, faults, seed=s)) for s in (5, 5, 6))
    assert all(np.array_equal(x, y) for x, y in zip(a, b))
    assert not all(np.array_equal(x, y) for x, y in zip(a, c))


@pytest.mark.parametrize(
    "make",
    [
        lambda: SensorDropout("sonar", 0, 1),
        lambda: SensorDropout("imu", 0, -1),
        lambda: CameraDark(float("nan"), 1),
        lambda: NanSamples("imu", 0),
        lambda: NanSamples("position", 2),
        lambda: TimeJump("imu", 1.0, 0.1, count=0),
        lambda: Truncate(float("inf")),
    ],
)
def test_bad_fault_specs_raise(make):
    with pytest.raises(ConfigError):
        make()


def test_not_a_fault_raises():
    with pytest.raises(TypeError, match="not a fault"):
        list(inject_faults(stream(), ["dark"]))


# --- recordings ----------------------------------------------------------------------------------


def tiny_stream() -> list:
    """Ten IMU samples (10 ms), two 8x6 images and two 6-point scans."""
    rng = np.random.default_rng(2)
    recs: list = [ImuSample(T0 + 0.01 * k, np.array([0.1 * k, 0, 9.81]), np.array([0, 0, 0.01 * k])) for k in range(10)]
    for t in (T0 + 0.025, T0 + 0.065):
        recs.append(Image(t, rng.integers(0, 256, (6, 8), dtype=np.uint8)))
        pts = rng.normal(size=(6, 3)).astype(np.float32).astype(np.float64)
        recs.append(LidarScan(t + 0.001, pts, np.arange(6.0), np.linspace(0, 0.05, 6), np.arange(6)))
    return sorted(recs, key=lambda r: r.t)


@pytest.fixture
def tiny_bag(tmp_path):
    path = tmp_path / "src.bag"
    with open_writer(path, "bag") as w:
        w.write_all(tiny_stream())
    return path


def test_write_faulty_bag_round_trip(tiny_bag, tmp_path):
    faults = [
        NanSamples("imu", 4),  # IMU 4 and 8 (0.03, 0.07 s): written, skipped on reading
        NanSamples("image", 2),  # the second image: not encodable, left out
        NanSamples("lidar", 1, fraction=0.5),  # 3 of 6 points each: dropped by the reader
        CameraDark(0.0, 0.05, read_noise=0.0),  # the first image
        TimeJump("imu", 0.085, 0.0425, count=1),  # IMU 9 (0.09 s) -> 0.0475 s: read back in order
    ]
    counts = write_faulty(tiny_bag, tmp_path / "bad.bag", faults)
    assert counts == {"imu: written": 10, "image: written": 1, "lidar: written": 2, "image: NaN not encodable": 1}
    rec = open_recording(tmp_path / "bad.bag")
    got = list(rec)
    assert rec.skipped == {"/imu/data: invalid (NaN or shape)": 2}
    src = tiny_stream()
    imu_t = [round(r.t - T0, 4) for r in of(got, "imu")]
    assert imu_t == [0.0, 0.01, 0.02, 0.04, 0.0475, 0.05, 0.06, 0.08]
    (img,) = of(got, "image")
    np.testing.assert_array_equal(img.data, np.rint(of(src, "image")[0].data * 0.02).astype(np.uint8))
    for scan, orig in zip(of(got, "lidar"), of(src, "lidar")):
        assert len(scan.points) == 3
        assert all(any(np.array_equal(p, q) for q in orig.points) for p in scan.points)


def test_write_faulty_euroc_skips_nan_scans_and_jumped_stamps(tiny_bag, tmp_path):
    faults = [NanSamples("lidar", 2), TimeJump("imu", 0.055, 0.0425, count=2), SensorDropout("image", 0.0, 0.03)]
    counts = write_faulty(tiny_bag, tmp_path / "bad", faults, fmt="euroc")
    assert counts == {"imu: written": 10, "image: written": 1, "lidar: written": 2}
    rec = open_recording(tmp_path / "bad")
    got = list(rec)
    assert rec.skipped == {"lidar0: invalid (NaN or shape)": 1, "imu0: time not increasing": 2}
    assert [round(r.t - T0, 4) for r in of(got, "imu")] == [0.0, 0.01, 0.02, 0.03, 0.04, 0.05, 0.08, 0.09]
    assert len(of(got, "lidar")) == 1 and len(of(got, "image")) == 1


def test_write_faulty_truncate_and_dropout_survive_exactly(tiny_bag, tmp_path):
    write_faulty(tiny_bag, tmp_path / "cut.bag", [Truncate(0.05), SensorDropout("lidar", 0.0, 0.03)])
    got = list(open_recording(tmp_path / "cut.bag"))
    want = [r for r in tiny_stream() if r.t - T0 < 0.05 and not (r.kind == "lidar" and r.t - T0 < 0.03)]
    assert [(r.kind, round(r.t * 1e9)) for r in got] == [(r.kind, round(r.t * 1e9)) for r in want]


def test_truncated_bag_needs_reindex(tmp_path):
    """A bag cut mid-write (3 chunks of ~1 MiB): the reader refuses it, ``reindex`` recovers
    the complete chunks, which read back as a prefix of the original stream."""
    from drivers.record import reindex

    rng = np.random.default_rng(0)
    src = tmp_path / "full.bag"
    recs = []
    for k in range(12):
        recs.append(ImuSample(T0 + 0.1 * k, np.array([0.0, 0.0, 9.81]), np.zeros(3)))
        recs.append(Image(T0 + 0.1 * k + 0.05, rng.integers(0, 256, (400, 640), dtype=np.uint8)))
    with open_writer(src, "bag") as w:
        w.write_all(recs)
    cut = tmp_path / "cut.bag"
    n = truncate_file(src, cut, 0.6)
    assert cut.stat().st_size == n == int(src.stat().st_size * 0.6)
    with pytest.raises(InputFormatError, match=r"no index.*reindex"):
        open_recording(cut)
    stats = reindex(cut, tmp_path / "fixed.bag")
    assert stats["chunks"] == 1 and stats["truncated_records"] == 1
    got = list(open_recording(tmp_path / "fixed.bag"))
    assert 0 < len(got) < len(recs)
    assert [(r.kind, round(r.t * 1e9)) for r in got] == [(r.kind, round(r.t * 1e9)) for r in recs[: len(got)]]
    np.testing.assert_array_equal(of(got, "image")[-1].data, of(recs, "image")[len(of(got, "image")) - 1].data)
    with pytest.raises(ConfigError):
        truncate_file(src, cut, 0.5)  # exists

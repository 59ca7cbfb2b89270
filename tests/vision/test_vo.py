"""Monocular VO on real KITTI frames (issue 4 "done" thresholds on a subset), the Sim(3)
alignment against evo and a closed form, and the input readers' errors."""

from __future__ import annotations

import shutil
from pathlib import Path

import jax.numpy as jnp
import numpy as np
import pytest

from jaxslam.errors import InputFormatError
from jaxslam.lie import SO3
from jaxslam.vision import VoConfig, ape_sim3, load_sequence, run_vo, umeyama_alignment
from jaxslam.vision._vo import read_calibration

DATA = Path(__file__).resolve().parents[2].parent / "shared" / "data"
KITTI = DATA / "kitti_mono"
EUROC = DATA / "euroc_V1_01"


@pytest.mark.skipif(not KITTI.is_dir(), reason="shared/data/kitti_mono is not present")
def test_vo_on_kitti_subset_meets_done_thresholds():
    """First 8 frames (~8 m), no enhancement, to stay well under a minute including JIT
    compilation; the full 51-frame run is the CLI's (see README)."""
    seq = load_sequence(KITTI)
    assert len(seq.paths) == 51 and seq.ground_truth is not None
    n = 8
    seq.paths, seq.timestamps, seq.ground_truth = seq.paths[:n], seq.timestamps[:n], seq.ground_truth[:n]
    result = run_vo(seq, VoConfig(enhance=False, max_features=1500, window=4, window_ba_every=3))
    stats = result.stats()
    assert stats["registered_images"] == n
    assert stats["reprojection_rmse_px"] < 1.0
    assert stats["track_length_min"] >= 2 and stats["points"] > 200
    ape = ape_sim3(result.poses[:, 4:], seq.ground_truth[:, :, 3])
    assert ape["rmse_percent_of_path"] < 1.0
    assert result.poses.shape == (n, 7) and np.all(np.isfinite(result.poses))


def _random_sim3(rng):
    R = np.asarray(SO3.exp(jnp.asarray(rng.normal(size=3))).as_matrix())
    return 2.5, R, rng.normal(size=3) * 4


def test_umeyama_closed_form():
    rng = np.random.default_rng(0)
    src = rng.normal(size=(30, 3)) * 5
    s, R, t = _random_sim3(rng)
    dst = s * src @ R.T + t
    s_e, R_e, t_e = umeyama_alignment(src, dst)
    assert s_e == pytest.approx(s, rel=1e-12)
    np.testing.assert_allclose(R_e, R, atol=1e-12)
    np.testing.assert_allclose(t_e, t, atol=1e-10)
    ape = ape_sim3(src, dst)
    assert ape["rmse"] < 1e-10 and ape["scale"] == pytest.approx(s)
    with pytest.raises(ValueError, match="N >= 3"):
        umeyama_alignment(src[:2], dst[:2])


def test_ape_equals_evo():
    evo_geometry = pytest.importorskip("evo.core.geometry")
    from evo.core import metrics
    from evo.core.trajectory import PosePath3D

    rng = np.random.default_rng(1)
    ref = np.cumsum(rng.normal(size=(40, 3)), axis=0)
    s, R, t = _random_sim3(rng)
    est = (ref - t) @ R / s + rng.normal(scale=0.05, size=ref.shape)
    r_evo, t_evo, s_evo = evo_geometry.umeyama_alignment(est.T, ref.T, with_scale=True)
    s_ours, R_ours, t_ours = umeyama_alignment(est, ref)
    assert s_ours == pytest.approx(s_evo, rel=1e-12)
    np.testing.assert_allclose(R_ours, r_evo, atol=1e-12)
    np.testing.assert_allclose(t_ours, t_evo, atol=1e-10)
    path_ref = PosePath3D(positions_xyz=ref, orientations_quat_wxyz=np.tile([1.0, 0, 0, 0], (40, 1)))
    path_est = PosePath3D(positions_xyz=est, orientations_quat_wxyz=np.tile([1.0, 0, 0, 0], (40, 1)))
    path_est.align(path_ref, correct_scale=True)
    ape = metrics.APE(metrics.PoseRelation.translation_part)
    ape.process_data((path_ref, path_est))
    assert ape_sim3(est, ref)["rmse"] == pytest.approx(ape.get_statistic(metrics.StatisticsType.rmse), rel=1e-10)


# --- input errors ---------------------------------------------------------------------------------


def test_calibration_formats(tmp_path: Path):
    f = tmp_path / "calib.txt"
    f.write_text("P0: 700 0 600 0 0 710 180 0 0 0 1 0\nP1: 700 0 600 -380 0 710 180 0 0 0 1 0\n")
    K, dist = read_calibration(f)
    np.testing.assert_allclose(K, [[700, 0, 600], [0, 710, 180], [0, 0, 1]])
    assert dist is None
    f.write_text("700 710 600 180\n")
    assert read_calibration(f)[0][1, 1] == 710
    if EUROC.is_dir():
        K, dist = read_calibration(EUROC / "mav0" / "cam0" / "sensor.yaml")
        assert K[0, 0] == pytest.approx(458.654) and dist is not None and len(dist) == 4


@pytest.mark.parametrize(
    ("text", "needle"),
    [("", "empty"), ("1 2 3\n", "12 numbers"), ("P0: a b c\n", "expected numbers"), ("0 0 1 1\n", "camera matrix")],
)
def test_wrong_calibration_raises(tmp_path: Path, text: str, needle: str):
    f = tmp_path / "calib.txt"
    f.write_text(text)
    with pytest.raises(InputFormatError, match=needle):
        read_calibration(f)


def test_bad_folders_raise(tmp_path: Path):
    with pytest.raises(InputFormatError, match="no such folder"):
        load_sequence(tmp_path / "missing")
    (tmp_path / "image_0").mkdir()
    (tmp_path / "calib.txt").write_text("700 710 600 180\n")
    with pytest.raises(InputFormatError, match="no images"):
        load_sequence(tmp_path)
    (tmp_path / "image_0" / "000000.png").write_bytes(b"not a png")
    (tmp_path / "image_0" / "000001.png").write_bytes(b"not a png either")
    seq = load_sequence(tmp_path)
    with pytest.raises(InputFormatError, match="cannot read the image"):
        run_vo(seq, VoConfig(enhance=False))


def test_single_image_raises(tmp_path: Path):
    (tmp_path / "image_0").mkdir()
    shutil.copy(KITTI / "image_l" / sorted(p.name for p in (KITTI / "image_l").iterdir())[0], tmp_path / "image_0")
    shutil.copy(KITTI / "calib.txt", tmp_path / "calib.txt")
    with pytest.raises(InputFormatError, match="at least 2 images"):
        run_vo(load_sequence(tmp_path), VoConfig(enhance=False))


@pytest.mark.skipif(not EUROC.is_dir(), reason="shared/data/euroc_V1_01 is not present")
def test_euroc_layout():
    seq = load_sequence(EUROC)
    assert len(seq.paths) == 20 and seq.distortion is not None
    assert np.all(np.diff(seq.timestamps) > 0) and seq.timestamps[0] > 1e9

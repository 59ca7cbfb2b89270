"""``jaxslam vo``: bad input gives one line on stderr and exit code 1; a short real run
writes every output file."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

from jaxslam.cli import main

KITTI = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "kitti_mono"


def _one_error_line(capsys: pytest.CaptureFixture[str], needle: str) -> None:
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("jaxslam vo: error:") and needle in err[0], err


def test_missing_folder(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["vo", str(tmp_path / "nope"), "-o", str(tmp_path / "out")]) == 1
    _one_error_line(capsys, "no such folder")


def test_empty_folder(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    (tmp_path / "calib.txt").write_text("700 710 600 180\n")
    assert main(["vo", str(tmp_path), "-o", str(tmp_path / "out")]) == 1
    _one_error_line(capsys, "no images")


def test_wrong_calibration(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    (tmp_path / "image_0").mkdir()
    (tmp_path / "image_0" / "0.png").write_bytes(b"x")
    bad = tmp_path / "calib.txt"
    bad.write_text("1 2 3 4 5\n")
    assert main(["vo", str(tmp_path), "--calib", str(bad), "-o", str(tmp_path / "out")]) == 1
    _one_error_line(capsys, "calib.txt:1")
    assert main(["vo", str(tmp_path), "--calib", str(tmp_path / "missing.txt"), "-o", str(tmp_path / "out")]) == 1
    _one_error_line(capsys, "calibration file not found")


def test_unreadable_images(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    (tmp_path / "image_0").mkdir()
    for i in range(3):
        (tmp_path / "image_0" / f"{i:06d}.png").write_bytes(b"\x89PNG truncated")
    (tmp_path / "calib.txt").write_text("P0: 700 0 600 0 0 710 180 0 0 0 1 0\n")
    assert main(["vo", str(tmp_path), "-o", str(tmp_path / "out"), "--no-enhance"]) == 1
    _one_error_line(capsys, "cannot read the image")


@pytest.mark.skipif(not KITTI.is_dir(), reason="shared/data/kitti_mono is not present")
def test_short_run_writes_outputs(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    src = tmp_path / "seq"
    (src / "image_l").mkdir(parents=True)
    for p in sorted((KITTI / "image_l").iterdir())[:6]:
        shutil.copy(p, src / "image_l")
    shutil.copy(KITTI / "calib.txt", src)
    lines = (KITTI / "poses.txt").read_text().splitlines()[:6]
    (src / "poses.txt").write_text("\n".join(lines) + "\n")
    out = tmp_path / "out"
    rc = main(["vo", str(src), "-o", str(out), "-q", "--no-enhance", "--ransac", "opencv", "--max-features", "1200"])
    assert rc == 0, capsys.readouterr()
    stats = json.loads((out / "stats.json").read_text())
    for key in (
        "input_images", "registered_images", "points", "residuals", "track_length_min",
        "track_length_mean", "track_length_max", "reprojection_rmse_px",
    ):  # fmt: skip
        assert key in stats
    assert stats["input_images"] == stats["registered_images"] == 6
    rows = [ln for ln in (out / "trajectory_tum.txt").read_text().splitlines() if not ln.startswith("#")]
    assert len(rows) == 6
    assert (out / "points.ply").read_text().startswith("ply\n")
    assert (out / "residuals_hist.png").stat().st_size > 0 and (out / "reprojection_hist.png").stat().st_size > 0
    assert "ape_sim3" in stats and stats["ape_sim3"]["rmse_percent_of_path"] < 1.0

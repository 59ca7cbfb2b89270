"""``jaxslam eval``: numbers equal evo's on the same files; bad input is one line, exit 1."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from jaxslam.cli import main
from jaxslam.io import write_kitti, write_tum

from .test_metrics import noisy_estimate, smooth_path

TOL = 1e-9


@pytest.fixture(scope="module")
def files(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    d = tmp_path_factory.mktemp("eval")
    ref = smooth_path(200, seed=4)
    est = noisy_estimate(ref, seed=5, scale=1.1)
    out = {"gt": d / "gt.txt", "est": d / "est.txt", "gt_kitti": d / "gt_kitti.txt", "est_kitti": d / "est_kitti.txt"}
    write_tum(out["gt"], ref)
    write_tum(out["est"], est)
    write_kitti(out["gt_kitti"], ref)
    write_kitti(out["est_kitti"], noisy_estimate(ref, seed=6, drop=False))
    return out


def _evo_numbers(gt, est, align: str, delta: float, unit: str, synced: bool = True):
    from evo.core import metrics, sync
    from evo.core.units import Unit

    if synced:
        gt, est = sync.associate_trajectories(gt, est, max_diff=0.01)
    if align != "none":
        est.align(gt, correct_scale=align == "sim3")
    a = metrics.APE(metrics.PoseRelation.translation_part)
    a.process_data((gt, est))
    r = metrics.RPE(metrics.PoseRelation.translation_part, delta, Unit.frames if unit == "frames" else Unit.meters)
    r.process_data((gt, est))
    return a.get_all_statistics(), r.get_all_statistics()


@pytest.mark.parametrize(("align", "delta", "unit"), [("se3", 1, "frames"), ("sim3", 2.0, "m"), ("none", 5, "frames")])
def test_cli_tum_matches_evo(
    files: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str], align: str, delta: float, unit: str
) -> None:
    pytest.importorskip("evo")
    from evo.tools import file_interface

    js = tmp_path / "r.json"
    argv = ["eval", str(files["gt"]), str(files["est"]), "--align", align, "--delta", str(delta)]
    rc = main([*argv, "--delta-unit", unit, "--json", str(js)])
    assert rc == 0
    text = capsys.readouterr().out
    assert "APE [m]" in text and "RPE trans" in text and "loop error" in text and "path length" in text
    res = json.loads(js.read_text())
    ape_evo, rpe_evo = _evo_numbers(
        file_interface.read_tum_trajectory_file(str(files["gt"])),
        file_interface.read_tum_trajectory_file(str(files["est"])),
        align,
        delta,
        unit,
    )
    for k, v in ape_evo.items():
        assert res["ape"]["stats"][k] == pytest.approx(v, abs=TOL), k
    for k, v in rpe_evo.items():
        assert res["rpe"]["stats"][k] == pytest.approx(v, abs=TOL), k
    assert res["matched"] == res["ape"]["matched"] > 100
    assert res["loop_error_m"] >= 0 and res["path_length_m"]["gt"] > 50
    assert res["loop_error_ratio"] == pytest.approx(res["loop_error_m"] / res["path_length_m"]["gt"])


def test_cli_kitti_pairs_by_index_and_plots(files: dict[str, Path], tmp_path: Path) -> None:
    pytest.importorskip("evo")
    from evo.tools import file_interface

    js, plots = tmp_path / "k.json", tmp_path / "plots"
    rc = main(["eval", str(files["gt_kitti"]), str(files["est_kitti"]), "--json", str(js), "--plot", str(plots)])
    assert rc == 0
    res = json.loads(js.read_text())
    assert res["association"].startswith("by index")
    gt = file_interface.read_kitti_poses_file(str(files["gt_kitti"]))
    est = file_interface.read_kitti_poses_file(str(files["est_kitti"]))
    ape_evo, rpe_evo = _evo_numbers(gt, est, "se3", 1, "frames", synced=False)
    for k, v in ape_evo.items():
        assert res["ape"]["stats"][k] == pytest.approx(v, abs=TOL), k
    for k, v in rpe_evo.items():
        assert res["rpe"]["stats"][k] == pytest.approx(v, abs=TOL), k
    assert (plots / "trajectory.png").stat().st_size > 5000 and (plots / "ape_over_distance.png").stat().st_size > 5000


def test_cli_lever_arm_with_position_file(files: dict[str, Path], tmp_path: Path) -> None:
    from jaxslam.io import read_tum

    ref = read_tum(files["gt"])
    arm = np.array([0.05, 0.0, 0.55])
    prism = np.asarray(ref.positions) + np.asarray(ref.poses.rotation.as_matrix()) @ arm
    rows = np.concatenate([ref.timestamps[:, None], prism], -1)
    gt_pos = tmp_path / "prism.txt"
    gt_pos.write_text("# t x y z\n" + "\n".join(" ".join(repr(float(v)) for v in r) for r in rows) + "\n")
    js = tmp_path / "p.json"
    assert main(["eval", str(gt_pos), str(files["gt"]), "--lever-arm", *map(str, arm), "--json", str(js)]) == 0
    res = json.loads(js.read_text())
    assert res["ape"]["stats"]["max"] < 1e-9 and res["rpe"]["pose_relation"] == "point_distance"
    assert res["rpe"]["stats"]["max"] < 1e-9 and res["loop_error_m"] < 1e-9
    assert main(["eval", str(gt_pos), str(files["gt"]), "--align", "none", "--json", str(js)]) == 0
    assert json.loads(js.read_text())["ape"]["stats"]["min"] == pytest.approx(np.linalg.norm(arm), rel=1e-9)


def _one_line_error(capsys: pytest.CaptureFixture[str], argv: list[str], needle: str) -> None:
    assert main(argv) == 1
    err = capsys.readouterr().err.strip()
    assert err.startswith("jaxslam eval: error:") and "\n" not in err and needle in err, err


def test_cli_bad_input(files: dict[str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    gt, est = str(files["gt"]), str(files["est"])
    _one_line_error(capsys, ["eval", str(tmp_path / "missing.txt"), est], "file not found")
    nan = tmp_path / "nan.txt"
    lines = files["est"].read_text().splitlines()
    lines[3] = lines[3].rsplit(" ", 1)[0] + " nan"
    nan.write_text("\n".join(lines) + "\n")
    _one_line_error(capsys, ["eval", gt, str(nan)], "NaN")
    late = tmp_path / "late.txt"
    late.write_text("0.0 0 0 0 0 0 0 1\n1.0 1 0 0 0 0 0 1\n2.0 2 1 0 0 0 0 1\n")
    _one_line_error(capsys, ["eval", gt, str(late)], "no matching timestamps")
    _one_line_error(capsys, ["eval", str(files["gt_kitti"]), str(late)], "by index")
    _one_line_error(capsys, ["eval", gt, est, "--delta", "1000", "--delta-unit", "m"], "no pose pair")
    with pytest.raises(SystemExit) as exc:
        main(["eval", gt, est, "--align", "affine"])
    assert exc.value.code == 2

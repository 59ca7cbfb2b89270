"""The jaxslam command: real runs and one-line errors with a non-zero exit."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from jaxslam.cli import main
from jaxslam.io import read_g2o

DATA = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "posegraph"


def test_optimize_writes_graph_and_summary(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "opt.g2o"
    js = tmp_path / "summary.json"
    rc = main(["optimize", str(DATA / "smallGrid3D.g2o"), "-o", str(out), "--json", str(js), "-q", "--init", "chordal"])
    assert rc == 0
    text = capsys.readouterr().out
    assert "initial cost" in text and "final cost" in text and "iterations" in text
    summary = json.loads(js.read_text())
    assert summary["status"] == "converged" and summary["final_cost"] < summary["initial_cost"]
    g = read_g2o(out)
    assert g.num_edges == read_g2o(DATA / "smallGrid3D.g2o").num_edges


def test_optimize_robust_gn(tmp_path: Path) -> None:
    rc = main(["optimize", str(DATA / "tinyGrid3D.g2o"), "--solver", "gn", "--robust", "cauchy:1.0", "-q"])
    assert rc == 0


@pytest.mark.parametrize(
    ("args", "needle"),
    [
        (["optimize", "/nonexistent/file.g2o"], "file not found"),
        (["optimize", "__BAD__", "--robust", "nope"], "unknown kernel"),
        (["optimize", "__BAD__", "--robust", "huber:-1"], "positive"),
    ],
)
def test_bad_input_is_one_line_and_exit_1(args: list[str], needle: str, tmp_path: Path) -> None:
    bad = tmp_path / "bad.g2o"
    bad.write_text("VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1\nEDGE_SE3:QUAT 0 1 0 0\n")
    args = [str(bad) if a == "__BAD__" else a for a in args]
    proc = subprocess.run([sys.executable, "-m", "jaxslam.cli", *args], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 1
    lines = [ln for ln in proc.stderr.strip().splitlines() if ln]
    assert len(lines) == 1 and needle in lines[0], proc.stderr


def test_corrupt_graph_names_file_and_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    bad = tmp_path / "bad.g2o"
    bad.write_text("VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1\nEDGE_SE3:QUAT 0 1 0 0\n")
    assert main(["optimize", str(bad)]) == 1
    err = capsys.readouterr().err
    assert "bad.g2o:2" in err


def test_demo_runs_and_writes_results(tmp_path: Path) -> None:
    assert main(["demo-graph", "-o", str(tmp_path), "--length", "30"]) == 0
    for name in ("trajectory_tum.txt", "ground_truth_tum.txt", "metrics.json", "trajectory.png", "graph_optimised.g2o"):
        assert (tmp_path / name).stat().st_size > 0, name
    m = json.loads((tmp_path / "metrics.json").read_text())
    assert m["ape_rmse_m"]["jaxslam LM"] < m["ape_rmse_m"]["chained odometry"]
    assert m["end_error_m"]["jaxslam LM"] < 0.5 * m["end_error_m"]["chained odometry"]


def test_sim_is_deterministic() -> None:
    from jaxslam.sim import tunnel_pose_graph

    a, b = tunnel_pose_graph(seed=3), tunnel_pose_graph(seed=3)
    np.testing.assert_array_equal(a.measured, b.measured)
    assert not np.array_equal(a.measured, tunnel_pose_graph(seed=4).measured)
    with pytest.raises(ValueError):
        tunnel_pose_graph(length=0.1)


def test_disconnected_graph_warns_and_chordal_refuses(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    edge = (
        "1 0 0 0 0 0 1 "
        + " ".join(["1", "0", "0", "0", "0", "0", "1", "0", "0", "0", "0", "1", "0", "0", "0"])
        + " 1 0 0 1 0 1"
    )
    lines = [f"VERTEX_SE3:QUAT {i} {x} 0 0 0 0 0 1" for i, x in enumerate([0, 1, 5, 6])]
    lines += [f"EDGE_SE3:QUAT 0 1 {edge}", f"EDGE_SE3:QUAT 2 3 {edge}"]
    g = tmp_path / "two.g2o"
    g.write_text("\n".join(lines) + "\n")
    assert main(["optimize", str(g), "-q"]) == 0
    err = capsys.readouterr().err
    assert "2 disconnected components" in err and "Pose3Var 2" in err
    assert main(["optimize", str(g), "-q", "--init", "chordal"]) == 1
    assert "not connected" in capsys.readouterr().err


def test_compilation_cache_is_written_and_reused(tmp_path: Path) -> None:
    cache = tmp_path / "cache"
    env = {**os.environ, "JAXSLAM_CACHE_DIR": str(cache)}
    cmd = [sys.executable, "-m", "jaxslam.cli", "optimize", str(DATA / "tinyGrid3D.g2o"), "-q"]
    first = subprocess.run(cmd, capture_output=True, text=True, timeout=300, env=env)
    assert first.returncode == 0, first.stderr
    files = sorted(p.name for p in cache.rglob("*") if p.is_file())
    assert files, "no compiled programs were cached"
    second = subprocess.run(cmd, capture_output=True, text=True, timeout=300, env=env)
    assert second.returncode == 0
    assert sorted(p.name for p in cache.rglob("*") if p.is_file()) == files  # reused, nothing new

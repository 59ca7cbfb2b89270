"""A visual loop joins the graph only when a loop from a later query agrees with it
(``loop.visual_confirm_m``): an alias that won where the estimate had drifted past the search
range stands alone, true loops agree with each other along the track."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from jaxslam.lie import host
from jaxslam.pipeline import LoopConfig, load_config
from jaxslam.pipeline._config import ConfigError
from jaxslam.pipeline._visual_loop import LoopQuery, VisualLoop, VisualLoopCloser

STEP = 0.5  # m between keyframes, driving along world x (body x)


def _poses(n: int) -> np.ndarray:
    return np.stack([host.make_pose(np.eye(3), np.array([STEP * k, 0.0, 0.0])) for k in range(n)])


def _query(k: int) -> LoopQuery:
    poses = _poses(k + 1)
    return LoopQuery(k, float(k), poses, STEP * np.arange(k + 1.0), np.arange(k + 1.0))


def _loop(i: int, j: int, ahead: float) -> VisualLoop:
    """A loop that puts keyframe j ``ahead`` m along the track from its estimate."""
    P = _poses(j + 1)
    T = host.inverse(P[i]) @ P[j] @ host.make_pose(np.eye(3), np.array([ahead, 0.0, 0.0]))
    return VisualLoop(i, j, T, np.eye(6), 30, 60, 0.9, 1.0)


def _closer(**changes) -> VisualLoopCloser:
    cfg = dataclasses.replace(LoopConfig(), **changes)
    return VisualLoopCloser(cfg, np.eye(4), 500.0, (640, 480), np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]]))


def test_a_loop_waits_for_a_later_one_that_agrees():
    c = _closer()
    first = _loop(0, 10, 0.30)
    assert c.confirm(_query(10), [first]) == [] and c.pending == [first] and c.accepted == []
    second = _loop(1, 12, 0.33)  # 1 m later, 3 cm apart: within 0.1 + 0.05 / m
    assert c.confirm(_query(12), [second]) == [first, second]
    assert c.accepted == [first, second] and c.pending == []
    third = _loop(0, 14, 0.35)  # agrees with an accepted loop: in at once
    assert c.confirm(_query(14), [third]) == [third]


def test_a_lone_alias_is_dropped_and_never_confirms_the_true_loops():
    c = _closer()
    assert c.confirm(_query(10), [_loop(0, 10, 0.30)]) == []
    assert c.confirm(_query(12), [alias := _loop(1, 12, 1.20)]) == []  # 0.9 m off the first
    true = _loop(0, 16, 0.32)
    got = c.confirm(_query(16), [true])
    assert len(got) == 2 and got[1] is true and got[0].j == 10  # the first, not the alias
    assert c.pending == [alias]
    # 6 m on, the alias is dropped unconfirmed
    assert c.confirm(_query(12 + 13), []) == [] and c.pending == []
    assert c.rejected[-1][:2] == (1, 12) and "unconfirmed" in c.rejected[-1][2]
    assert alias not in c.accepted


def test_loops_of_one_query_do_not_confirm_each_other():
    c = _closer()
    assert c.confirm(_query(10), [_loop(0, 10, 0.3), _loop(1, 10, 0.3)]) == []
    assert len(c.pending) == 2
    c.close()  # the recording ends: nothing accepted, both counted as rejected
    assert c.pending == [] and c.accepted == [] and len(c.rejected) == 2


def test_the_tolerance_grows_with_the_distance_between_the_loops():
    # 4 m apart: 0.1 + 0.05 * 4 = 0.3 m allowed
    for ahead, joins in ((0.55, True), (0.65, False)):
        c = _closer()
        c.confirm(_query(10), [_loop(0, 10, 0.3)])
        assert bool(c.confirm(_query(18), [_loop(0, 18, ahead)])) is joins


def test_off_accepts_at_once():
    c = _closer(visual_confirm_m=0.0)
    lp = _loop(0, 10, 2.0)
    assert c.confirm(_query(10), [lp]) == [lp] and c.accepted == [lp]


@pytest.mark.parametrize(
    "key",
    [
        "visual_confirm_m",
        "visual_confirm_tol",
        "visual_confirm_drift_per_m",
        "visual_wide_drift_per_m",
        "visual_drift_per_m",
        "visual_wide_max_shift",
    ],
)
def test_bad_values_are_config_errors(tmp_path, key):
    p = tmp_path / "c.yaml"
    p.write_text(f"loop:\n  {key}: -1\n")
    with pytest.raises(ConfigError, match=key):
        load_config(p)

"""The differentiable ABA-CLAHE front-end proxy (SPEC §6): gradients against central
differences, jit, the optimiser, bad input, and tuning from a no-brightening start on dark
frames (synthetic texture, and two frames of the simulated dark tunnel).

The discrete end-to-end check (held-out registration) is ``benchmarks/tune_enhance.py``.
"""

from __future__ import annotations

import jax
import numpy as np
import pytest
from scipy import ndimage

from jaxslam.errors import JaxSlamError
from jaxslam.tune._enhance_proxy import (
    enhancement_objective,
    evaluate_registration,
    from_params,
    simulate_frames,
    to_params,
    tune_enhancement,
)

SHAPE = (320, 512)  # the simulated camera's; one pair of this shape everywhere: one compilation each


def _dark_frames(n: int = 1, shape: tuple[int, int] = SHAPE, level: float = 0.12, seed: int = 0):
    """Dark textured frames and their noise twins (uint8): smooth random texture scaled to
    ``level``, plus independent Gaussian sensor noise per realisation."""
    rng = np.random.default_rng(seed)
    tex = ndimage.gaussian_filter(rng.random((n, *shape)), (0, 1.5, 1.5))
    tex = (tex - tex.min()) / (tex.max() - tex.min())
    base = 255.0 * level * (0.3 + 0.7 * tex)

    def shot():
        return np.clip(np.rint(base + 1.0 * rng.standard_normal(base.shape)), 0, 255).astype(np.uint8)

    return shot(), shot()


@pytest.fixture(scope="module")
def frames():
    return _dark_frames()


def test_parameterisation_round_trip():
    for s in [(0.25, 0.4, 2.0), (1.0, 1.0, 1.0), (0.1, 0.9, 6.0)]:
        np.testing.assert_allclose([float(x) for x in from_params(to_params(*s))], s, rtol=1e-9)


def test_gradient_matches_central_differences(frames):
    fa, fb = frames
    p0 = to_params(0.5, 0.6, 2.0)

    def f(p):
        return enhancement_objective(p, fa, fb)

    g = np.asarray(jax.grad(f)(p0))
    assert np.all(np.isfinite(g)) and np.linalg.norm(g) > 0
    h = 1e-5
    fd = np.array([(float(f(p0 + h * e)) - float(f(p0 - h * e))) / (2 * h) for e in np.eye(3)])
    np.testing.assert_allclose(g, fd, rtol=1e-4, atol=1e-6 * np.abs(g).max())


def test_jit_and_consecutive_pairs(frames):
    fa, fb = frames
    p = to_params(0.3, 0.5, 3.0)
    jitted = jax.jit(lambda q: enhancement_objective(q, fa, fb))
    np.testing.assert_allclose(float(jitted(p)), float(enhancement_objective(p, fa, fb)), rtol=1e-12)
    # without twins the views are consecutive frames; float input in [0, 1] is accepted too
    v = enhancement_objective(p, np.concatenate([fa, fb]).astype(np.float64) / 255.0)  # one pair
    assert np.isfinite(float(v))
    terms = enhancement_objective(p, fa, fb, terms=True)
    assert set(terms) == {"value", "repeatable", "count", "entropy", "noise"}
    assert 0.0 <= float(terms["entropy"]) <= 1.0 and float(terms["repeatable"]) <= float(terms["count"]) + 1e-9


def test_optimiser_decreases_objective(frames):
    fa, fb = frames
    res = tune_enhancement(fa, 0.9, 0.9, 1.5, twins=fb, steps=3, lr=0.2)
    assert len(res.history) == 4 and len(res.path) == 4
    assert min(res.history[1:]) < res.history[0] - 1e-3
    assert 0.05 < res.alpha < 1.25 and 0.05 < res.beta < 1.25 and 0.5 < res.clip < 8.0


@pytest.mark.parametrize(
    "bad",
    [
        np.zeros((0, 64, 96), np.uint8),  # no frames
        np.full((2, 64, 96), np.nan),  # NaN
        np.zeros((64, 96), np.uint8),  # one frame without the batch axis
        np.zeros((2, 64, 96, 3), np.uint8),  # colour
        np.zeros((2, 8, 8), np.uint8),  # too small for SURF's filters
        np.zeros((2, 64, 96), np.int32),  # wrong dtype
    ],
)
def test_bad_frames_raise(bad):
    with pytest.raises(JaxSlamError):
        enhancement_objective(to_params(0.25, 0.4, 2.0), bad)
    with pytest.raises(ValueError):  # the same errors are ValueErrors, as aba_clahe's
        tune_enhancement(bad, steps=1)


def test_bad_twins_and_options_raise(frames):
    fa, fb = frames
    with pytest.raises(JaxSlamError):
        enhancement_objective(to_params(0.25, 0.4, 2.0), fa, np.concatenate([fb, fb]))
    with pytest.raises(JaxSlamError):
        enhancement_objective(to_params(0.25, 0.4, 2.0), fa[:1])  # one frame, no pair
    with pytest.raises(JaxSlamError):
        tune_enhancement(fa, twins=fb, steps=1, lr=0.0)
    with pytest.raises(JaxSlamError):
        evaluate_registration(fa, None, np.eye(2), 0.25, 0.4, 2.0)


def test_tuning_brightens_dark_synthetic_frames():
    fa, fb = _dark_frames(level=0.06, seed=3)
    res = tune_enhancement(fa, 1.0, 1.0, 1.0, twins=fb, steps=4, lr=0.2)
    assert res.history[-1] < res.history[0]
    assert res.alpha < 0.9 and res.beta < 0.9, (res.alpha, res.beta, res.clip)


def test_tuning_brightens_simulated_dark_tunnel():
    """Frames (and noise twins) of the simulated tunnel in "dark" lighting, 16 s into the
    run (~19 grey levels mean): tuning on the first view from no brightening moves alpha and
    beta down, and the discrete pipeline on the two consecutive pairs finds more inliers with
    the tuned setting than with the start. (The proxy is a whole-frame objective: CLAHE tiles
    and the global mean V_mid of eq. 1 change on a crop.)"""
    (fs,) = simulate_frames(14, "dark", 16.0, 3, warmup=3)
    assert fs.twins is not None and fs.frames.shape == (3, *SHAPE) and fs.poses.shape == (3, 4, 4)
    res = tune_enhancement(fs.frames[:1], 1.0, 1.0, 1.0, twins=fs.twins[:1], steps=4, lr=0.2)
    assert res.alpha < 0.9 and res.beta < 0.9 and res.clip > 1.0, (res.alpha, res.beta, res.clip)
    before = evaluate_registration(fs.frames, fs.poses, fs.K, 1.0, 1.0, 1.0, distortion=fs.distortion)
    after = evaluate_registration(fs.frames, fs.poses, fs.K, res.alpha, res.beta, res.clip, distortion=fs.distortion)
    assert before["pairs"] == after["pairs"] == 2
    assert after["mean_inliers"] > before["mean_inliers"], (before, after)
    assert after["registered"] == 2 and after["rot_err_deg"] < 1.0 and after["sampson_px"] < 1.0

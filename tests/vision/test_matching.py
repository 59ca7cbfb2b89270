"""Brute-force matching against cv2.BFMatcher (the oracle): L2 and Hamming, ratio test,
cross-check, the Laplacian-sign gate, padding and empty inputs."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from jaxslam.vision import distance_matrix, match_arrays, match_descriptors


def _float_desc(rng, n, d=64):
    x = rng.normal(size=(n, d)).astype(np.float32)
    return x / np.linalg.norm(x, axis=1, keepdims=True)


def _pairs(matches):
    return sorted((m.queryIdx, m.trainIdx) for m in matches)


@pytest.fixture
def rng():
    return np.random.default_rng(7)


def test_l2_distances_equal_opencv(rng):
    a, b = _float_desc(rng, 40), _float_desc(rng, 50)
    cv = cv2.BFMatcher(cv2.NORM_L2).knnMatch(a, b, k=1)
    d = np.asarray(distance_matrix(a, b))
    for m in cv:
        assert d[m[0].queryIdx, m[0].trainIdx] == pytest.approx(m[0].distance, abs=1e-5)
        assert np.argmin(d[m[0].queryIdx]) == m[0].trainIdx


def test_cross_check_equals_opencv(rng):
    a = _float_desc(rng, 300)
    b = np.concatenate([a[:200] + 0.05 * _float_desc(rng, 200), _float_desc(rng, 150)])
    ours, _ = match_descriptors(a, b, ratio=1.0, cross_check=True)
    cv = cv2.BFMatcher(cv2.NORM_L2, crossCheck=True).match(a, b)
    assert sorted(map(tuple, ours.tolist())) == _pairs(cv)


def test_ratio_test_equals_opencv(rng):
    a = _float_desc(rng, 300)
    b = np.concatenate([a[:150] + 0.1 * _float_desc(rng, 150), _float_desc(rng, 200)])
    ours, dist = match_descriptors(a, b, ratio=0.8, cross_check=False)
    knn = cv2.BFMatcher(cv2.NORM_L2).knnMatch(a, b, k=2)
    cv = [m for m, n in knn if m.distance < 0.8 * n.distance]
    assert sorted(map(tuple, ours.tolist())) == _pairs(cv)
    cv_dist = {(m.queryIdx, m.trainIdx): m.distance for m in cv}
    np.testing.assert_allclose(dist, [cv_dist[tuple(p)] for p in ours.tolist()], atol=1e-5)


def test_hamming_equals_opencv(rng):
    a = rng.integers(0, 256, size=(200, 32), dtype=np.uint8)
    b = np.concatenate([a[:120].copy(), rng.integers(0, 256, size=(80, 32), dtype=np.uint8)])
    flips = rng.integers(0, 32, size=(120, 3))
    for i, cols in enumerate(flips):  # flip a few bits of the copies
        b[i, cols] ^= np.uint8(1 << (i % 8))
    ours, _dist = match_descriptors(a, b, ratio=1.0, cross_check=True)
    cv = cv2.BFMatcher(cv2.NORM_HAMMING, crossCheck=True).match(a, b)
    assert sorted(map(tuple, ours.tolist())) == _pairs(cv)
    d = np.asarray(distance_matrix(a, b, "hamming"))
    for m in cv:
        assert d[m.queryIdx, m.trainIdx] == m.distance


def test_laplacian_sign_gate(rng):
    a = _float_desc(rng, 100)
    b = a + 0.01 * _float_desc(rng, 100)
    s1 = rng.choice([-1, 1], size=100).astype(np.int8)
    s2 = s1.copy()
    s2[:30] *= -1  # the first 30 true partners have the other sign: never matched
    pairs, _ = match_descriptors(a, b, ratio=1.0, cross_check=True, sign1=s1, sign2=s2)
    assert np.all(s1[pairs[:, 0]] == s2[pairs[:, 1]])
    assert np.sum(pairs[:, 0] == pairs[:, 1]) == 70
    # oracle: OpenCV matching within each sign class
    for s in (-1, 1):
        qa, qb = np.nonzero(s1 == s)[0], np.nonzero(s2 == s)[0]
        cv = cv2.BFMatcher(cv2.NORM_L2, crossCheck=True).match(a[qa], b[qb])
        expect = sorted((int(qa[m.queryIdx]), int(qb[m.trainIdx])) for m in cv)
        got = sorted(tuple(p) for p in pairs.tolist() if s1[p[0]] == s)
        assert got == expect


def test_fixed_size_masks_and_jit(rng):
    a, b = _float_desc(rng, 64), _float_desc(rng, 64)
    b[:20] = a[:20]
    valid2 = np.arange(64) < 40
    idx, dist, ok = match_arrays(a, b, ratio=1.0, valid2=valid2)
    assert idx.shape == dist.shape == ok.shape == (64,)
    assert np.all(np.asarray(idx)[np.asarray(ok)] < 40)
    assert np.all(np.asarray(ok)[:20]) and np.all(np.asarray(idx)[:20] == np.arange(20))


def test_blocked_path_equals_single_block(rng):
    a, b = _float_desc(rng, 300), _float_desc(rng, 260)
    b[:100] = a[:100] + 0.01 * _float_desc(rng, 100)
    one, _ = match_descriptors(a, b, ratio=0.9)
    blocked, _ = match_descriptors(a, b, ratio=0.9, block=128)
    np.testing.assert_array_equal(one, blocked)


def test_empty_and_bad_shapes():
    pairs, dist = match_descriptors(np.zeros((0, 64), np.float32), np.ones((5, 64), np.float32))
    assert pairs.shape == (0, 2) and dist.shape == (0,)
    with pytest.raises(ValueError, match="equal widths"):
        match_descriptors(np.zeros((3, 64)), np.zeros((3, 128)))
    with pytest.raises(ValueError, match="metric"):
        distance_matrix(np.zeros((2, 4)), np.zeros((2, 4)), "cosine")

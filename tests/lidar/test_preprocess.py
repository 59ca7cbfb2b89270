from __future__ import annotations

import numpy as np
import pytest

from jaxslam.errors import InputFormatError
from jaxslam.lidar import crop_range, voxel_downsample, voxel_downsample_indices
from jaxslam.lidar._preprocess import voxel_keys


def test_voxel_downsample_invariants():
    rng = np.random.default_rng(0)
    pts = rng.uniform(-3, 3, (5000, 3))
    attr = np.arange(5000.0)
    out, a = voxel_downsample(pts, 0.5, attr)
    keys_in, keys_out = voxel_keys(pts, 0.5), voxel_keys(out, 0.5)
    assert len(np.unique(keys_out)) == len(out)  # one point per voxel
    assert set(keys_out) == set(keys_in)  # every occupied voxel kept
    np.testing.assert_array_equal(pts[a.astype(int)], out)  # attributes follow, real points
    assert np.all(np.diff(a) > 0)  # input order
    first = {}
    for i, k in enumerate(keys_in):
        first.setdefault(k, i)
    assert sorted(first.values()) == list(a.astype(int))  # the first point of each voxel
    np.testing.assert_array_equal(voxel_downsample(pts, 0.5), out)  # deterministic
    np.testing.assert_array_equal(voxel_downsample_indices(pts, 0.5), a.astype(int))


def test_voxel_downsample_edge_cases():
    assert voxel_downsample(np.zeros((0, 3)), 0.1).shape == (0, 3)
    with pytest.raises(InputFormatError):
        voxel_downsample(np.array([[0.0, np.nan, 1.0]]), 0.1)
    with pytest.raises(InputFormatError):
        voxel_downsample(np.zeros((4, 2)), 0.1)
    with pytest.raises(InputFormatError):
        voxel_downsample(np.zeros((4, 3)), 0.0)
    with pytest.raises(InputFormatError):
        voxel_downsample(np.zeros((4, 3)), 0.1, np.zeros(3))


def test_crop_range_drops_nonfinite_and_out_of_range():
    pts = np.array([[0.1, 0, 0], [1, 0, 0], [np.nan, 0, 0], [0, 50, 0], [0, 0, 200]])
    out, idx = crop_range(pts, 0.5, 100.0, np.arange(5))
    np.testing.assert_array_equal(idx, [1, 3])
    np.testing.assert_array_equal(out, pts[[1, 3]])

"""The LiDAR front end: arrays in, arrays out (no graphs).

Preprocessing (:func:`crop_range`, :func:`voxel_downsample`), motion compensation
(:func:`deskew`), a local voxel-hash map (:class:`VoxelMap`), robust point-to-plane ICP with
degeneracy detection and solution remapping, optionally aided by the return intensity
(:func:`relative_reflectivity`; :func:`register` -> :class:`Registration`), and
Scan Context place recognition (:func:`scan_context`, :class:`ScanContextDatabase`,
:func:`submap_points`). Everything is float64 numpy; poses are 4 x 4 matrices, tangents
[rotation, translation] with right perturbation (GTSAM's Pose3 convention).
"""

from .. import _config  # noqa: F401
from ._deskew import deskew
from ._icp import IcpConfig, Registration, register
from ._intensity import relative_reflectivity
from ._preprocess import crop_range, voxel_downsample, voxel_downsample_indices
from ._scan_context import ScanContext, ScanContextDatabase, scan_context, submap_points
from ._se3 import se3_exp, se3_inverse, se3_log
from ._voxel_map import VoxelMap, VoxelMapConfig, estimate_normals

__all__ = [
    "IcpConfig",
    "Registration",
    "ScanContext",
    "ScanContextDatabase",
    "VoxelMap",
    "VoxelMapConfig",
    "crop_range",
    "deskew",
    "estimate_normals",
    "register",
    "relative_reflectivity",
    "scan_context",
    "se3_exp",
    "se3_inverse",
    "se3_log",
    "submap_points",
    "voxel_downsample",
    "voxel_downsample_indices",
]

"""Synthetic data with ground truth (the low-light tunnel; for now its pose graph)."""

from .. import _config  # noqa: F401
from ._posegraph import SyntheticPoseGraph, tunnel_pose_graph

__all__ = ["SyntheticPoseGraph", "tunnel_pose_graph"]

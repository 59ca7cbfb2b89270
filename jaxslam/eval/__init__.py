"""Trajectory evaluation: association, alignment, APE / RPE / loop-closure error, plots.

Numbers equal evo 1.38's (``evo_ape`` / ``evo_rpe``) on the same files; see
:mod:`jaxslam.eval._metrics` for the definitions and :mod:`jaxslam.eval._align` for the
association and alignment conventions. Everything runs on host numpy arrays.
"""

from .. import _config  # noqa: F401  (float64 in JAX)
from ._align import (
    ALIGN_MODES,
    Alignment,
    PositionTrack,
    align,
    associate,
    associate_by_index,
    match_indices,
    read_track,
    umeyama,
)
from ._metrics import (
    DELTA_UNITS,
    POSE_RELATIONS,
    ApeResult,
    RpeResult,
    accumulated_distances,
    ape,
    error_stats,
    loop_error,
    loop_error_ratio,
    path_length,
    rpe,
)
from ._plots import plot_ape_over_distance, plot_residual_histograms, plot_trajectory

__all__ = [
    "ALIGN_MODES",
    "DELTA_UNITS",
    "POSE_RELATIONS",
    "Alignment",
    "ApeResult",
    "PositionTrack",
    "RpeResult",
    "accumulated_distances",
    "align",
    "ape",
    "associate",
    "associate_by_index",
    "error_stats",
    "loop_error",
    "loop_error_ratio",
    "match_indices",
    "path_length",
    "plot_ape_over_distance",
    "plot_residual_histograms",
    "plot_trajectory",
    "read_track",
    "rpe",
    "umeyama",
]

"""Vision front end: low-light image enhancement (ABA-CLAHE, SPEC §3.1) as JAX array ops.

Public surface: :func:`aba_clahe`, :func:`clahe`, :func:`equalize_hist`,
:func:`gamma_correct`, :func:`aba_curve`; local features (SURF in JAX, OpenCV SIFT/ORB):
:func:`detect_and_describe`, :func:`surf`.
"""

from ._enhance import aba_clahe, aba_curve, clahe, equalize_hist, gamma_correct
from ._features import detect_and_describe, surf

__all__ = ["aba_clahe", "aba_curve", "clahe", "detect_and_describe", "equalize_hist", "gamma_correct", "surf"]

from ._geometry import (
    BundleResult,
    EssentialResult,
    bundle_adjust,
    decompose_essential,
    find_essential,
    normalize_pixels,
    recover_pose,
    relative_pose,
    reprojection_residuals,
    sampson_error,
    triangulate_dlt,
    triangulate_points,
)
from ._matching import distance_matrix, match_arrays, match_descriptors
from ._vo import ImageSequence, VoConfig, VoError, VoResult, ape_sim3, load_sequence, run_vo, umeyama_alignment

__all__ += ["BundleResult", "EssentialResult", "bundle_adjust", "decompose_essential", "find_essential"]
__all__ += ["normalize_pixels", "recover_pose", "relative_pose", "reprojection_residuals", "sampson_error"]
__all__ += ["distance_matrix", "match_arrays", "match_descriptors", "triangulate_dlt", "triangulate_points"]
__all__ += ["ImageSequence", "VoConfig", "VoError", "VoResult", "ape_sim3", "load_sequence", "run_vo"]
__all__ += ["umeyama_alignment"]

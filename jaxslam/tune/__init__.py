"""Learning from surveyed trajectories (SPEC §6): gradients through the solver's optimum
(:class:`DifferentiableSolver`), noise-weight tuning against ground truth (:func:`tune`,
``jaxslam tune``), and a differentiable front-end objective for ABA-CLAHE's alpha, beta and
clip (:func:`enhancement_objective`, :func:`tune_enhancement`)."""

from ._enhance_proxy import (
    ALPHA_RANGE,
    CLIP_RANGE,
    EnhancementResult,
    FrameSet,
    ProxyWeights,
    enhancement_objective,
    evaluate_registration,
    from_params,
    simulate_frames,
    soft_keypoints,
    to_params,
    tune_enhancement,
)
from ._implicit import BackwardStats, DifferentiableSolver, ImplicitConfig
from ._synthetic import tunnel_capture
from ._tune import (
    GROUPS,
    Captured,
    Shards,
    TuneConfig,
    TuneReport,
    aligned_position_loss,
    apply_weights,
    tune,
    tune_graphs,
    weights_summary,
)

__all__ = ["BackwardStats", "DifferentiableSolver", "ImplicitConfig"]
__all__ += ["GROUPS", "Captured", "TuneConfig", "TuneReport", "aligned_position_loss", "apply_weights"]
__all__ += ["Shards", "tune", "tune_graphs", "tunnel_capture", "weights_summary"]
__all__ += ["ALPHA_RANGE", "CLIP_RANGE", "EnhancementResult", "FrameSet", "ProxyWeights", "enhancement_objective"]
__all__ += ["evaluate_registration", "from_params", "simulate_frames", "soft_keypoints", "to_params"]
__all__ += ["tune_enhancement"]

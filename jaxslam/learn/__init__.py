"""Learning from surveyed trajectories (SPEC §6): gradients through the solver's optimum,
noise-weight tuning against ground truth, and a differentiable front-end objective for
ABA-CLAHE's alpha, beta and clip."""

from ._implicit import BackwardStats, DifferentiableSolver, ImplicitConfig

__all__ = ["BackwardStats", "DifferentiableSolver", "ImplicitConfig"]

"""jaxslam: a JAX differentiable multi-sensor fusion framework for SLAM in low-light tunnels."""

from . import _config  # noqa: F401  (enables float64 before anything else runs)
from .errors import ConfigError, GraphError, InputFormatError, JaxSlamError, SolverError

__version__ = "0.1.0"

__all__ = ["ConfigError", "GraphError", "InputFormatError", "JaxSlamError", "SolverError", "__version__"]

"""Problem analysis, batch Gauss-Newton / Levenberg-Marquardt, sparse linear solvers."""

from .. import _config  # noqa: F401
from ._incremental import IncrementalConfig, IncrementalSolver, UpdateResult
from ._linear import SparseSystem, available_linear_solvers, pcg_solve
from ._nls import Solver, SolverConfig, SolverResult, Status, optimize
from ._problem import Problem, bucket

__all__ = [
    "IncrementalConfig",
    "IncrementalSolver",
    "Problem",
    "Solver",
    "SolverConfig",
    "SolverResult",
    "SparseSystem",
    "Status",
    "UpdateResult",
    "available_linear_solvers",
    "bucket",
    "optimize",
    "pcg_solve",
]
from ._initialize import chordal_initialize_se2, chordal_initialize_se3

__all__ += ["chordal_initialize_se2", "chordal_initialize_se3"]

"""The small exception hierarchy every jaxslam library call raises for bad input.

Messages say what was expected and where ("g2o line 17: EDGE_SE3:QUAT needs 30 fields,
found 29"). The CLI turns any :class:`JaxSlamError` into one line and exit code 1.
"""

from __future__ import annotations

from pathlib import Path


class JaxSlamError(Exception):
    """Base class of every error jaxslam raises on purpose."""


class InputFormatError(JaxSlamError, ValueError):
    """A file or packet does not have the expected format.

    Carries ``path`` and ``line`` (1-based) when known, and puts them in the message.
    """

    def __init__(self, message: str, path: str | Path | None = None, line: int | None = None):
        self.path = None if path is None else str(path)
        self.line = line
        where = ""
        if self.path is not None:
            where = self.path + (f":{line}" if line is not None else "") + ": "
        elif line is not None:
            where = f"line {line}: "
        super().__init__(where + message)


class GraphError(JaxSlamError, ValueError):
    """A factor graph is inconsistent: a factor names a missing variable, ids repeat, the
    graph is disconnected or its gauge is free."""


class SolverError(JaxSlamError, RuntimeError):
    """A solve failed and the caller asked for an exception (``throw=True``)."""


class ConfigError(JaxSlamError, ValueError):
    """A configuration value is missing or out of range."""

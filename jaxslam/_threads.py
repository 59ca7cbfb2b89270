"""One shared thread pool for running independent XLA calls side by side.

XLA:CPU runs one call's loops on one core, and a second call dispatched asynchronously waits
for the first; calls made from separate Python threads run at the same time (XLA releases
the GIL while it computes). Kernels that split their work into independent parts
(``jaxslam.factors.preintegrate``, ``jaxslam.vision.surf``) run the parts here."""

from __future__ import annotations

import concurrent.futures
import os
import threading
from collections.abc import Callable, Iterable
from typing import TypeVar

T = TypeVar("T")
R = TypeVar("R")

_POOL: concurrent.futures.ThreadPoolExecutor | None = None
_LOCK = threading.Lock()


def workers() -> int:
    """Cores to use (at most 8)."""
    return min(os.cpu_count() or 1, 8)


def parallel_map(fn: Callable[[T], R], items: Iterable[T]) -> list[R]:
    """``[fn(x) for x in items]``, each call on the shared pool (two threads per core)."""
    global _POOL
    with _LOCK:
        if _POOL is None:
            _POOL = concurrent.futures.ThreadPoolExecutor(2 * workers(), thread_name_prefix="jaxslam-parts")
    return list(_POOL.map(fn, items))

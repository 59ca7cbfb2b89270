"""What machine a figure was measured on (for run metrics and benchmark JSON).

Timings here move with the CPU model far more than with anything in the code (the same
estimator run measured 1.1-1.4x its recording on one 2-core machine and 0.7x on another),
so every timed output records the processor it ran on next to the figures, and a run
reports how much of its time went to JIT compilation (:func:`compile_seconds`)."""

from __future__ import annotations

import os
import platform
import threading
from typing import Any


def cpu_model() -> str:
    """The processor's model name (``/proc/cpuinfo`` on Linux, else ``platform``)."""
    try:
        with open("/proc/cpuinfo", encoding="utf-8") as fh:
            for line in fh:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def machine_info() -> dict[str, Any]:
    """CPU model, logical CPUs (the ones this process may use), load average, OS, Python and
    JAX versions: a dict for JSON."""
    try:
        cpus = len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        cpus = os.cpu_count() or 0
    try:
        load = [round(x, 2) for x in os.getloadavg()]
    except OSError:
        load = []
    try:
        import jax

        jax_version = jax.__version__
    except ImportError:  # pragma: no cover - jax is a core dependency
        jax_version = ""
    return {
        "cpu": cpu_model(),
        "cpus": cpus,
        "load_avg": load,
        "platform": platform.platform(),
        "python": platform.python_version(),
        "jax": jax_version,
    }


# JIT compilation, counted apart from a run's steady state: JAX reports every lowering and
# XLA compilation (or persistent-cache retrieval) through ``jax.monitoring``; one
# process-wide listener sums them. Tracing is left out: its events nest (a jitted function
# called inside another is traced inside the outer trace) and it is ~10 % of the total.
_COMPILE_EVENTS = frozenset(
    ("/jax/core/compile/jaxpr_to_mlir_module_duration", "/jax/core/compile/backend_compile_duration")
)
_compile_lock = threading.Lock()
_compile_total = [0.0]
_compile_listening = [False]


def _on_compile_event(event: str, duration_secs: float, **_: str | int) -> None:
    if event in _COMPILE_EVENTS:
        with _compile_lock:
            _compile_total[0] += duration_secs


def compile_seconds() -> float:
    """Seconds this process has spent lowering and compiling JAX programs (summed over
    threads, so it can exceed wall time) since the first call of this function; a run reads
    it before and after to report its compile time apart from its steady-state time."""
    import jax

    with _compile_lock:
        if not _compile_listening[0]:
            jax.monitoring.register_event_duration_secs_listener(_on_compile_event)
            _compile_listening[0] = True
        return _compile_total[0]

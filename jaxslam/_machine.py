"""What machine a figure was measured on (for run metrics and benchmark JSON).

Timings here move with the CPU model far more than with anything in the code (the same
estimator run measured 1.1-1.4x its recording on one 2-core machine and 0.7x on another),
so every timed output records the processor it ran on next to the figures."""

from __future__ import annotations

import os
import platform
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

"""Pieces the drivers share: the standard gravity, skip counters, the host clock.

Imports nothing from ``drivers`` and only the base layer of ``jaxslam`` (measurement records,
errors), so every driver can use it.
"""

from __future__ import annotations

import time
from collections.abc import Callable

from jaxslam.errors import JaxSlamError

G = 9.80665
"""Standard gravity (m/s^2): converts accelerometer readings in g to m/s^2."""

HostClock = Callable[[], float]
"""A host clock in seconds (``time.time`` by default; tests pass a fake one)."""

host_time: HostClock = time.time


class DriverError(JaxSlamError, OSError):
    """A device cannot be opened, read or written (port missing, unplugged, address in use)."""


class Counters:
    """Named event counters (packets accepted, bytes skipped, ...).

    Drivers never raise on bad sensor bytes: they count and skip. ``counters["bad_checksum"]``
    reads a counter (0 when never incremented); :meth:`as_dict` is a snapshot for logs.
    """

    def __init__(self, *names: str):
        self._counts: dict[str, int] = dict.fromkeys(names, 0)

    def add(self, name: str, n: int = 1) -> None:
        self._counts[name] = self._counts.get(name, 0) + n

    def __getitem__(self, name: str) -> int:
        return self._counts.get(name, 0)

    def as_dict(self) -> dict[str, int]:
        return dict(self._counts)

    def __repr__(self) -> str:
        body = ", ".join(f"{k}={v}" for k, v in self._counts.items())
        return f"Counters({body})"

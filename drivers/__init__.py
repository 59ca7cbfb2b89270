"""Drivers for the rig's sensors (SPEC §2): live hardware in, measurement records out.

* :mod:`drivers.witmotion` — WitMotion HWT901B IMU over a serial port (pyserial):
  11-byte 0x55 packets -> :class:`jaxslam.measurements.ImuSample` (host timestamps).
* :mod:`drivers.livox` — Livox HAP SDK2 UDP point-cloud and IMU packets ->
  :class:`~jaxslam.measurements.LidarScan` frames of 0.1 s and ``ImuSample`` (sensor clock).

Drivers emit the same records as the readers in ``jaxslam.io``, so the estimator cannot tell
live data from a recording. Layer rule (STYLE): drivers import only the base of jaxslam
(``jaxslam.measurements`` and the ``jaxslam.errors`` it builds on); nothing in ``jaxslam``
imports ``drivers``. Bad sensor bytes are counted and skipped (each driver's ``counters``),
never asserted on; device failures raise :class:`drivers._common.DriverError`, bad
configuration :class:`jaxslam.errors.ConfigError`, both :class:`jaxslam.errors.JaxSlamError`.

TODO: a recorder, ``python -m drivers.record``, that writes these records to a rosbag comes
with the rosbag writer (it depends on the bag writer, not yet built). Camera (Hikvision USB3
Vision) driver: not yet.
"""

from ._common import Counters, DriverError

__all__ = ["Counters", "DriverError"]

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

* :mod:`drivers.camera` — an OpenCV ``VideoCapture`` device, a video file or an image folder
  -> :class:`~jaxslam.measurements.Image` (host timestamps). GenICam/USB3 Vision: not yet.
* :mod:`drivers.record` — ``python -m drivers.record --imu PORT --lidar-port 57000 --camera
  SRC -o run.bag``: a ROS1 bag written as it goes (chunks flushed every 0.5 s); ``python -m
  drivers.record reindex run.bag`` repairs a bag whose recorder was killed.
"""

from ._common import Counters, DriverError

__all__ = ["Counters", "DriverError"]

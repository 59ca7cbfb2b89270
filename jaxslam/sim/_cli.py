"""``jaxslam simulate``: write a synthetic low-light tunnel recording (see :func:`simulate_tunnel`)."""

from __future__ import annotations

import argparse
import dataclasses

from ._camera import CameraConfig
from ._lidar import LidarConfig
from ._recording import SimConfig, simulate_tunnel
from ._texture import LightingConfig
from ._tunnel import TunnelConfig


def register(subparsers) -> None:
    """Add the ``simulate`` command to the ``jaxslam`` argument parser."""
    s = subparsers.add_parser(
        "simulate", help="simulate a low-light tunnel recording (IMU, camera, LiDAR, ground truth)"
    )
    s.add_argument("-o", "--output", required=True, help="output: a .bag file, ROS2 bag folder or EuRoC folder")
    s.add_argument("--seed", type=int, default=0)
    s.add_argument("--length", type=float, default=30.0, help="route length one way (m); the path is twice this")
    s.add_argument("--lighting", choices=["dark", "uneven", "normal"], default="uneven")
    s.add_argument("--lidar", choices=["hap", "ring16"], default="hap")
    s.add_argument("--format", choices=["bag", "bag2", "bag2-db3", "euroc"], default="bag")
    s.add_argument("--section", choices=["rectangular", "horseshoe"], default="rectangular")
    s.add_argument("--curvature", type=float, default=0.0, help="centreline curvature 1/m (0 = straight)")
    s.add_argument("--slope", type=float, default=0.01, help="rise per metre")
    s.add_argument("--width", type=int, default=512, help="image width (px)")
    s.add_argument("--height", type=int, default=320, help="image height (px)")
    s.add_argument("--camera-rate", type=float, default=10.0)
    s.add_argument("--colour", action="store_true", help="RGB frames instead of grey")
    s.add_argument("--flicker", type=float, default=0.0, help="lamp flicker amplitude (0..0.5)")
    s.add_argument("--decimation", type=int, default=None, help="keep every n-th LiDAR point (hap default 4)")
    s.add_argument("--speed", type=float, default=0.5, help="cruise speed m/s")
    s.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    s.set_defaults(func=cmd_simulate)


def cmd_simulate(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from ._trajectory import MotionConfig

    lidar = LidarConfig(model=args.lidar)
    if args.decimation is not None:
        lidar = dataclasses.replace(lidar, decimation=args.decimation)
    elif args.lidar == "ring16":
        lidar = dataclasses.replace(lidar, decimation=2, max_range=100.0, min_range=0.3, translation=(0.0, 0.0, 0.6))
    config = SimConfig(
        seed=args.seed,
        tunnel=TunnelConfig(length=args.length, section=args.section, curvature=args.curvature, slope=args.slope),
        lighting=LightingConfig(mode=args.lighting),
        motion=MotionConfig(speed=args.speed),
        camera=CameraConfig(
            width=args.width, height=args.height, rate=args.camera_rate, colour=args.colour, flicker=args.flicker
        ),
        lidar=lidar,
    )
    bar = tqdm(total=None, unit="frame", disable=args.quiet, desc="simulate")

    def progress(done: int, total: int) -> None:
        bar.total = total
        bar.n = done
        bar.refresh()

    try:
        summary = simulate_tunnel(config, args.output, fmt=args.format, progress=progress)
    finally:
        bar.close()
    c = summary["counts"]
    print(
        f"wrote {summary['output']} ({args.format}): {summary['duration_s']:.0f} s, "
        f"{summary['path_length_m']:.1f} m path; {c['imu']} IMU, {c['images']} images, {c['lidar']} scans "
        f"(~{summary['lidar_points_per_frame']['mean']:.0f} pts), {c['ground_truth']} poses, "
        f"{c['total_station']} prism fixes in {summary['seconds']['total']:.0f} s"
    )
    return 0

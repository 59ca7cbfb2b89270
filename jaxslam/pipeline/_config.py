"""Configuration of the fused estimator: the rig (calibration) and the pipeline options.

Everything is a frozen dataclass with defaults; :func:`load_config` reads a YAML file whose
sections mirror the dataclasses (``rig:``, ``keyframe:``, ``imu:``, ``lidar:``, ``vision:``,
``loop:``, ``solver:``) and rejects unknown keys by name. ``jaxslam run`` writes the effective
configuration back as ``config.yaml`` so a run can be repeated exactly.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from ..errors import ConfigError


@dataclasses.dataclass(frozen=True)
class RigConfig:
    """Calibration of the sensor rig. Body frame = IMU frame (x forward, y left, z up).

    Extrinsics are ``body_T_sensor`` as ``[qw, qx, qy, qz, x, y, z]`` (the sensor's pose in
    the body frame). IMU noise in Kalibr's units (continuous-time densities)."""

    camera_intrinsics: tuple[float, float, float, float] = (281.6, 281.6, 255.5, 159.5)
    """``fx, fy, cx, cy`` (px)."""
    camera_distortion: tuple[float, ...] = (0.0, 0.0, 0.0, 0.0)
    """Radial-tangential ``k1, k2, p1, p2`` (OpenCV / Kalibr ``radtan``)."""
    camera_size: tuple[int, int] = (512, 320)
    """Image ``width, height`` (px)."""
    body_T_camera: tuple[float, ...] = (0.5, -0.5, 0.5, -0.5, 0.2, 0.0, 0.3)
    """Camera pose in the body frame; camera axes x right, y down, z forward."""
    body_T_lidar: tuple[float, ...] = (1.0, 0.0, 0.0, 0.0, 0.25, 0.0, 0.45)
    lidar_model: str = "hap"
    accelerometer_noise_density: float = 2.0e-3
    gyroscope_noise_density: float = 1.7e-4
    accelerometer_random_walk: float = 3.0e-4
    gyroscope_random_walk: float = 2.0e-5
    gravity: float = 9.81

    def K(self) -> np.ndarray:
        fx, fy, cx, cy = self.camera_intrinsics
        return np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]])


@dataclasses.dataclass(frozen=True)
class KeyframeConfig:
    distance: float = 0.25
    """New keyframe after this much travel (m) ..."""
    angle_deg: float = 10.0
    """... or this much rotation (degrees) ..."""
    max_interval: float = 1.0
    """... or this much time (s) since the last one."""


@dataclasses.dataclass(frozen=True)
class ImuConfig:
    noise_scale: float = 1.0
    """Multiplies the rig's white-noise densities (a tuning weight)."""
    still_seconds: float = 1.0
    """Initialisation window at the start: gravity direction and gyro bias from its mean."""
    still_acc_std: float = 0.05
    """The start counts as standing still when the accelerometer's std is below this (m/s^2)."""
    acc_bias_sigma: float = 0.1
    """Prior sigma of the accelerometer bias (m/s^2)."""
    gyro_bias_sigma: float = 0.005
    """Prior sigma of the gyro bias around the still-start estimate (rad/s)."""
    gap_seconds: float = 0.1
    """An IMU gap longer than this inside a keyframe interval is bridged by holding the last
    sample and counted (``imu_gaps``)."""
    zupt: bool = True
    """Zero-velocity updates: a keyframe whose interval from the previous one (at least
    ``zupt_min_seconds``) shows no more accelerometer spread than the sensor's white noise
    (every axis's std below ``zupt_noise_ratio`` times the rig's per-sample sigma, density x
    sqrt(rate)) gets a zero-velocity prior. A wheeled robot that moves shakes the IMU far above
    its noise (simulated tunnel: 0.44-0.52 m/s^2 at 0.5 m/s, 0.06 at 0.05 m/s, 0.027-0.035
    standing or turning on the spot against a sigma of 0.028). Without it, velocity drifted
    during the turn on the spot of seed 4 dark (0.08 m/s at the end of it, with the LiDAR
    degenerate facing the portal and the camera dark), and the return leg came out 0.8 m short."""
    zupt_noise_ratio: float = 1.5
    zupt_min_seconds: float = 0.2
    zupt_sigma: float = 0.01
    """Sigma of the zero-velocity prior (m/s, each axis)."""
    zupt_hold_sigma: float = 0.002
    """A standing-still interval also holds the position: a between factor with zero
    translation (this sigma, m, each axis) and free rotation (a turn on the spot is allowed)
    joins its two keyframes. The velocity prior alone lets a keyframe pair drift by a
    ``zupt_sigma`` per second at 1 sigma, and during seed 4 dark's turn on the spot the dark
    visual odometry (4.7 cm measured for 1 mm moved, stated sigma 6 mm) moved the end-wall
    keyframes 6 cm along the tunnel. 0 = off."""


@dataclasses.dataclass(frozen=True)
class LidarConfig:
    enabled: bool = True
    voxel: float = 0.25
    """Downsampling of each scan before registration (m)."""
    map_voxel: float = 0.2
    map_points_per_voxel: int = 10
    map_radius: float = 40.0
    pairs: tuple[int, ...] = (1, 5, 20)
    """Odometry factors to the keyframes this many back (beyond 1: only between scans that
    are not degenerate, where the scan-to-map odometry does not drift)."""
    anchor_gap_scans: int = 3
    """A longer pair (``pairs`` beyond 1) may span up to this many consecutive axis-weak
    scans, its two ends anchored: an odd scan that saw too little of the end wall leaves the
    map, and so the anchoring of the scans after it, as it was. 0 = no weak scan between (the
    rule before 2026-12-04, session 17: one weak scan on the way out cut every 5- and 20-back
    pair across it; on dark seed 3 the way out then came out 0.4 % short, APE 0.047 m)."""
    map_every: int = 2
    """Insert every n-th registered scan into the local map (the map update, a k-d tree
    rebuild, is the front end's largest cost after ICP)."""
    map_after_failures: int = 5
    """A scan whose registration failed is kept out of the local map (its pose is only the
    prediction: inserted, every later scan registers to it, and after a LiDAR dropout one
    0.27 m off along the tunnel carried that error on); after this many consecutive failures
    it goes in anyway, so the map follows the robot where registration keeps failing."""
    max_range: float = 60.0
    min_range: float = 0.6
    information_scale: float = 0.1
    """Multiplies the registration Hessian (points are not independent: the raw Hessian is
    overconfident). A tuning weight."""
    min_sigma_rot: float = 0.0005
    """Floor on the odometry factor's rotation sigma (rad)."""
    min_sigma_trans: float = 0.003
    """Floor on the odometry factor's translation sigma (m)."""
    min_sigma_axis: float = 0.0
    """Extra translation sigma (m) along body x (the direction of travel, the tunnel axis)
    on every LiDAR odometry factor, added to the registration's: scan-to-map ICP along a
    tunnel leans on a few features, and its along-axis error is larger than the Hessian
    says and not independent between the 1-, 5- and 20-back pairs, which share the newer
    scan's error. 0 = none (the default: at 0.015 on the 30 benchmark runs it fixed uneven
    13's start, where the first scans registered 1-3 cm ahead of a standing vehicle, and dark
    14, but lost uneven 4 / 6 and dark 4 / 12: both goals on 26 of 30 against 28; on the
    consecutive pairs only it no longer fixed uneven 13; README)."""
    hold_still: bool = True
    """While the IMU says the vehicle stands still (the last ``imu.zupt_min_seconds`` + 0.05 s
    of samples pass the zero-velocity test of ``imu.zupt`` and the bias-corrected turn rate
    is below ``hold_still_rate``), a scan is not registered: it keeps the last scan's pose
    (not the IMU prediction, which drifts with the estimated velocity) and goes into the map
    there. Scan-to-map ICP against the sparse first scans slides along a tunnel (uneven seed
    13: the scans of the standing start registered 1.2-3.3 cm ahead of the first, not
    flagged weak), and what it inserts there offsets the map the moving scans register to.
    Held scans are counted (``lidar_scans_held_still``). On by default for the standing
    start only (``hold_still_start_only``; session 34: both goals on 28 of the 30 benchmark
    runs against 27 without, loop error at most 0.021 m on all 30 against 0.046; holding
    every stop, session 28, cost uneven 6 its loop error)."""
    hold_still_start_only: bool = True
    """Hold only at the standing start, until the first scan that is not held (a stop later
    in the run registers as usual)."""
    hold_still_rate: float = 0.01
    """Turn rate (rad/s, bias-corrected gyro mean) above which a vehicle is not still: a turn
    on the spot shakes the accelerometer no more than standing does."""
    degenerate_sigma: float = 1.0
    """Sigma given to a degenerate direction (m or rad): down-weighted, not trusted."""
    axis_weights: tuple[float, float] = (1.0, 1.0)
    """Information multipliers of the factor's (rotation, translation) blocks, after
    ``information_scale`` (sigmas divided by their square roots); learned by ``jaxslam tune``."""
    axis_sigma_scale: float = 1.0
    """Multiplies the factor's along-axis (body x, the direction of travel) sigma, keeping its
    correlations (row and column x of the information divided by it). For calibrating the
    stated sigma against ground truth along the one direction a tunnel leaves weak:
    ``metrics.json["factor_consistency"][kind]["axis_z_rms"]`` is the ratio to undo."""
    intensity: bool = False
    """Use the return intensity in registration (odometry and loop verification): the
    surface's reflectance pattern (stains, joints, pipes) can observe the tunnel axis where the
    plain walls' geometry cannot (:func:`jaxslam.lidar.relative_reflectivity`). Off by
    default: on the simulated tunnel it changed APE by -25 %, +27 %, -15 % on seeds 0-2 and
    +25 % in dark light, and
    the loops it made observable along the axis came out 0.1-0.4 m off there (the pattern
    seen from opposite headings is not yet viewpoint-free); see the README."""
    intensity_weight: float = 1.0
    """Weight of the reflectivity residuals against the geometric ones (``IcpConfig``)."""
    intensity_radius: float = 0.6
    """Neighbourhood (m) whose mean reflectivity a point is compared with."""
    intensity_smooth: float = 0.2
    """Radius (m) over which each point's relative reflectivity is averaged: the map's linear
    model resolves patterns of a few decimetres, finer texture is noise to it."""
    intensity_max_range: float = 6.0
    """Returns beyond this range (m) carry no reflectivity: grazing, sparse far views shift the
    pattern towards the sensor (a bias of ~2 cm per registration with all ranges, measured on
    the simulated tunnel)."""


@dataclasses.dataclass(frozen=True)
class VisionConfig:
    enabled: bool = True
    enhance: bool = True
    """ABA-CLAHE before features (``--no-enhance`` turns it off)."""
    alpha: float = 0.25
    beta: float = 0.4
    clip: float = 2.0
    detector: str = "surf"
    hessian_threshold: float = 100.0
    max_keypoints: int = 1000
    ransac: bool = True
    """Essential-matrix RANSAC on the matches (``--no-ransac``: every match is used)."""
    patch_refine: bool = True
    """After the motion-only fit, find each inlier's patch of the older image in the newer
    one (laid on its LiDAR plane, aligned by Gauss-Newton on normalised grey values) and fit
    again on those positions instead of the detected keypoints
    (:func:`jaxslam.pipeline._visual.align_patches`). Detected positions shift with a
    feature's scale and the light; with exact depth, coming home towards the bright portal
    (uneven seed 6) they made the visual lengths 0.8 % short, the aligned ones 0.02 %."""
    patch_min_fraction: float = 0.7
    """Refine only when at least this fraction of the inliers' patches align (else keep the
    detections). In the dark the sensor noise caps a true patch's NCC: on dark seed 8 a
    median of 12 % aligned on the way out and 51 % in the dark stretch of the way back (95 %
    in lit stretches), and fitting on those few made that stretch's visual lengths 4 % short
    (1 % with the detections)."""
    patch_half: int = 6
    """Half-size of the aligned patches ((2 half + 1)^2 pixels)."""
    patch_min_ncc: float = 0.7
    """A patch counts as aligned above this normalised cross-correlation. In the dark the
    sensor noise caps a true patch's NCC; larger patches raise it (see README: on dark seed
    12's darkest stretch, 15 % of 13x13 patches pass 0.7, 43 % of 21x21 patches pass 0.5, both
    within 0.05 px of the true position in the median, where the detections sit 0.5 px
    inwards)."""
    patch_retry_half: int = 0
    """When too few patches align, align again with patches of this half-size (0 = no retry),
    ``patch_retry_min_ncc`` and ``patch_retry_min_fraction``: only the keyframe pairs whose
    alignment fails change, so lit stretches keep their result."""
    patch_retry_min_ncc: float = 0.5
    """The retry's NCC bar (``patch_min_ncc`` of the second alignment)."""
    patch_retry_min_fraction: float = 0.4
    """The retry's share of the inliers that must align (``patch_min_fraction`` of it)."""
    ratio: float = 0.8
    ransac_threshold_px: float = 1.0
    min_inliers: int = 15
    """A keyframe is registered when at least this many matches with LiDAR depth survive the
    motion-only fit (2 px). In the dark the keypoints are noisier and fewer matches stay within
    2 px: seed 0 dark registered 88 % of keyframes at 25, 93 % at 20, 95 % at 15 (APE 0.060 /
    0.061 / 0.053 m); on uneven light (seeds 0-3) 15 registers 98.7-100 % where 25 gave
    97.5-100 %. The factor's information grows with the count, so a weak pose weighs little."""
    guided_radius_px: float = 15.0
    """When the image-wide matching leaves too few inliers, match again within this radius of
    where the predicted motion (IMU + LiDAR) projects the previous keyframe's 3-D points
    (``VisualFrontend.guided_pairs``); 0 turns it off. On the benchmark's bags (2026-12-02),
    registered keyframes went from 95.0 / 96.2 % to 98.3 / 99.2 % on dark seeds 0 / 1 (the
    approach to the dark end wall and the turn on the spot) and from 99.2 / 98.7 % to 100 /
    99.6 % on uneven seeds 0 / 3; the loop error moved both ways (see README)."""
    guided_ratio: float = 0.8
    """Ratio test of the guided matching, against the other candidates in the window."""
    guided_information_scale: float = 0.25
    """Multiplies the information of a pose fitted on guided pairs at 2 px (a wide-gate fit
    already carries its wider sigma). The pairs are chosen near where the prediction puts them,
    so the fit leans towards the prediction and its errors exceed what its inliers state: on
    seed 4 dark (12-04) the translation chi-square against ground truth had mean 21.3 / median
    7.5 over the 125 guided fits, 6.0 / 2.9 over the 115 image-wide ones (3 expected); 0.25
    brings the guided means level. 1 = trust them as the others."""
    odometry_kernel: str = "huber"
    """Which robust kernel ``odometry_kernel_scale`` sets: huber (convex) or cauchy."""
    odometry_kernel_scale: float = 6.0
    """Robust kernel on the visual-odometry factors, its scale in whitened units (0 = none,
    least squares). Most fits are calibrated (on dark seed 6 the translation chi-square
    against ground truth had a median of ~3 for 3 dof), but a few percent are gross
    (chi-square 30-200 in the dark textureless stretch on the way back) and, stated at a few
    millimetres, pulled that run 0.2 m along the tunnel (APE 0.051 m without a kernel). Not
    lower: the visual odometry is the only length measure on the way back, and at 3.5 the
    estimate of held-out dark seed 8 drifted 1.1 m there, the visual loops' search missed the
    true matches and two false loops were accepted (APE 0.50 m). A Cauchy kernel at 2.5 lost
    dark seed 6 (APE 1.06 m). Huber 6 was first reverted (12-04) for failing the LiDAR-dropout
    test (APE 0.18 m); the cause was the odometry's prediction after a dropout (fixed 12-04),
    which sent the estimate into the wrong basin with or without a kernel."""
    wide_inlier_px: float = 3.5
    """When the guided pairs leave fewer than ``min_inliers`` within 2 px of the motion-only
    fit, fit them again with this inlier threshold (and ``pixel_sigma`` scaled by
    ``wide_inlier_px / 2``, so the pose weighs less); 2 or less turns it off. In the dark the
    exposure reaches its 20 ms cap and a turn on the spot blurs features by several pixels:
    on seed 4 dark the keypoints found within 4 px of their true reprojection had a median
    error of 1.8 px at every size, so a 2 px gate keeps about half the true matches."""
    pixel_sigma: float = 1.0
    information_scale: float = 0.5
    axis_weights: tuple[float, float] = (1.0, 1.0)
    """Information multipliers of the factor's (rotation, translation) blocks, after
    ``information_scale`` (sigmas divided by their square roots); learned by ``jaxslam tune``."""
    axis_sigma_scale: float = 1.0
    """Multiplies the factor's along-axis (body x, the direction of travel) sigma, keeping its
    correlations (row and column x of the information divided by it). For calibrating the
    stated sigma against ground truth along the one direction a tunnel leaves weak:
    ``metrics.json["factor_consistency"][kind]["axis_z_rms"]`` is the ratio to undo."""
    depth_radius_px: float = 12.0
    """LiDAR points projected within this radius of a feature give it depth (a local plane)."""
    max_depth: float = 20.0
    max_time_offset: float = 0.02
    """An image is used for a keyframe when its stamp is within this of the keyframe's (s)."""
    depth_scale: bool = True
    """Take the translation's length from the LiDAR depths of both keyframes (3-D to 3-D),
    its direction and the rotation from the reprojection fit (see ``VisualFrontend``)."""
    length_sigma_ratio: float = 0.015
    """A relative standard deviation of the visual translation's length (0.01 = 1 % of the
    step), added to the factor's covariance along the translation (after
    ``information_scale``) on keyframe pairs where the LiDAR odometry is anchored along the
    axis throughout. The reprojection information states the length to a few mm, but the
    depth-based length can be biased by about as much in the dark (see README); with this
    term the anchored LiDAR decides the length there. Where the LiDAR is degenerate the
    vision keeps its full weight (softening it there hands the axis to the IMU). 0 turns it
    off. The default since 2026-12-04 (with the visual loops' search margin and kernel
    scale): on the 30 m tunnel, seeds 0-4 in uneven and dark light, loop error within 3 cm
    on all ten runs and APE on eight, against four and five of ten without it (README,
    "Measured figures")."""
    scale_depth: str = "map"
    """Depths the translation length is taken from (``depth_scale``): ``"map"``, the local map
    (many features, but its scans sit at LiDAR-odometry poses, so along a degenerate tunnel
    the depth difference of two keyframes repeats the odometry's own along-axis error);
    ``"scan"``, each keyframe's own deskewed scan (metric in its own frame, independent of the
    odometry, but fewer and noisier depths), falling back to the map where fewer than 10
    matched features have scan depth in both keyframes. Measured on the 30 m tunnel, inline
    vision, ``scale_from_lidar: false`` with ``scan``: APE 0.185 / 0.097 / 0.089 m on seeds
    0 / 1 / 2 against 0.031 / 0.080 / 0.154 with the defaults: better on one seed only."""
    scale_from_lidar: bool = False
    """Calibrate the visual translation length against LiDAR odometry on keyframe pairs where
    the LiDAR is not degenerate (ratio of lengths, after 20 pairs, clipped to +-5 %). Off by
    default since ``scale_variable`` estimates the scale in the graph: with both, the scale is
    corrected twice from the same LiDAR lengths (measured on seeds 0-3 of the 30 m tunnel, loop
    error 0.038 / 0.049 / 0.023 / 0.030 m with it, 0.010 / 0.019 / 0.018 / 0.020 without, at
    ``min_inliers`` 25)."""
    scale_variable: bool = True
    """Estimate the visual odometry's length scale in the graph: each keyframe gets a
    :class:`~jaxslam.core.ScaleVar` (log scale) joined to the previous one by a random walk,
    and visual factors are :class:`~jaxslam.factors.ScaledBetweenFactor` on it, so a length
    bias of the features is taken out wherever anything else sees the lengths (the LiDAR
    facing the end wall, loops) instead of shortening the whole trajectory."""
    scale_prior_sigma: float = 0.05
    """Prior sigma of the first keyframe's log scale."""
    unscaled_min_inliers: int = 50
    """Patch-refined visual factors (``vision.patch_refine``) with at least this many inliers
    are not multiplied by the scale variable (0 = off: every visual factor is). The scale is
    there for the detector's length bias in poor light (dark keypoints sit inwards of the
    truth, the motion comes out short), which patches aligned in good light do not have.
    Scaled, a lit stretch where only such factors measure lengths keeps whatever scale an
    earlier dark stretch left: on dark seed 6 the log scale was +0.0067 over the last 6 m
    home, where the refined factors (93-163 inliers) were 0.2 % short, and the estimate came
    home 3.9 cm long. Refined factors with ~20 inliers in the dark were 3.8 % short there: not
    unbiased, so they stay scaled. 50 was read off dark seed 6 (one of the 30 benchmark runs);
    over all 30, both goals on 27 against 25 with 0 (see README, session 33)."""
    scale_walk_sigma: float = 0.001
    """Random walk of the log scale per square-root metre travelled. Slower (0.0003, 12-04)
    made the scale one number per run: right where the whole run is dark (dark seed 0 loop
    error 0.037 -> 0.007 m), wrong where the bias changes with the light (uneven seeds 0 / 3:
    0.027 / 0.012 -> 0.046 / 0.038 m); kept at 0.001."""
    scale_revert_m: float = 0.0
    """Mean reversion of the log scale (m; 0 = off, a pure random walk): each keyframe's log
    scale also gets a prior towards 0 (the depth-calibrated length) of sigma
    ``scale_revert_m * scale_walk_sigma / sqrt(step)``, so that where nothing else measures
    lengths the scale returns to 1 over about this many metres (a first-order Gauss-Markov
    process) instead of keeping a bias learned from an earlier, darker stretch: on dark seed
    14 the last 8 m home, with no loop possible, inherited a log scale of -0.0055 from the
    dark return leg and came out 6 cm short while the visual odometry there was right."""
    scale_revert_to: str = "one"
    """What ``scale_revert_m`` pulls each keyframe's log scale towards: ``one`` (log scale
    0, the depth-calibrated length) or ``run`` (a run-wide log scale, one more
    :class:`~jaxslam.core.ScaleVar` with the first keyframe's prior, that the graph
    estimates from every keyframe: a hierarchical scale, so a length bias that lasts the
    whole run is kept while a local one fades)."""
    direction_fallback: bool = False
    """Where features have no LiDAR depth, add a scale-free factor (rotation + translation
    direction from the essential matrix, ``RelativeDirectionFactor``) instead of nothing.
    Off by default: camera + IMU alone still drift along the axis (measured with
    ``--no-lidar`` on a 42 s recording: 8.2 m RMS), and the README's figures are without it."""
    direction_min_motion: float = 0.05
    """... when the predicted motion exceeds this (m): a direction needs a baseline."""
    direction_sigmas: tuple[float, float] = (0.002, 0.02)
    """Sigmas (rad) of the scale-free factor's rotation and direction residuals."""
    pairs: tuple[int, ...] = (1,)
    """Relative poses to the keyframes this many back (1 = the previous; more pairs average
    the per-pair error along the tunnel axis, where LiDAR is blind)."""
    threaded: bool = True
    """Run the visual front end in a worker thread, overlapping the LiDAR front end; its
    factors join at the next keyframe (a fixed lag: runs are deterministic either way).
    False: inline, the factors join at their own keyframe."""


@dataclasses.dataclass(frozen=True)
class LoopConfig:
    enabled: bool = True
    min_gap_s: float = 15.0
    """Only keyframes at least this much older are loop candidates."""
    search_radius: float = 3.0
    """Candidates within this distance of the current estimate (m)."""
    every: int = 3
    """Try a loop at every n-th keyframe."""
    submap_radius: float = 10.0
    """The candidate's submap: the scans of old keyframes within this distance of it (the
    forward-looking LiDAR saw the place the current scan sees from other keyframes)."""
    min_fitness: float = 0.6
    max_rmse: float = 0.08
    chi2_gate: float = 22.46
    """Mahalanobis gate of the loop against the current estimate (chi^2, 6 dof, 0.999)."""
    drift_per_m: float = 0.01
    """Odometry drift assumed by the gate (m and rad per m travelled between the two)."""
    cauchy_scale: float = 1.0
    """Robust kernel on LiDAR loop factors (whitened units)."""
    visual_cauchy_scale: float = 10.0
    """Robust kernel on visual loop factors (whitened units). Their along-track sigma is a
    centimetre or two, so the few decimetres of drift they exist to take out are tens of
    sigmas: at 1 the kernel weighs such a loop by ~1e-3 and the estimate stays where the
    drift left it (seed 4 dark with ``vision.length_sigma_ratio: 0.015``: 14 true loops
    accepted, the drift still 0.7 m, APE 0.30 m); the loops have passed the search, the
    ambiguity test and the consistency gate by then (see README)."""
    information_scale: float = 0.01
    """Multiplies the loop registration's Hessian (chi^2 at ground truth ~6 with it on the
    simulated tunnel: submaps from two passes are less consistent than one scan-to-map)."""
    axis_weights: tuple[float, float] = (1.0, 1.0)
    """Information multipliers of the factor's (rotation, translation) blocks, after
    ``information_scale`` (sigmas divided by their square roots), on LiDAR and visual loops
    alike; learned by ``jaxslam tune``."""
    axis_sigma_scale: float = 1.0
    """Multiplies a LiDAR loop factor's along-axis (body x, the direction of travel) sigma,
    keeping its correlations (row and column x of the information divided by it), for
    calibrating it against ground truth:
    ``metrics.json["factor_consistency"]["lidar loop"]["axis_z_rms"]`` is the ratio to undo
    (``benchmarks/calibrate_axis.py``). Applied to the factor after the odometry-consistency
    gate, which keeps the registration's information: it changes a loop's weight, not which
    loops are accepted."""
    visual_axis_sigma_scale: float = 1.0
    """The same for visual loops (``factor_consistency["visual loop"]``): their along-track
    sigma comes from a different model (patch NCC peaks, not a registration Hessian)."""
    visual: bool = True
    """Visual loops by projection (:mod:`jaxslam.pipeline._visual_loop`): an old keyframe's
    features with LiDAR depth found again in the current image, from any heading (an
    out-and-back run sees each wall patch from the mirrored position), give a full relative
    pose, the tunnel axis included. Needs vision and LiDAR."""
    visual_every: int = 2
    """Look for visual loops at every n-th keyframe."""
    visual_radius: float = 12.0
    """Old keyframes within this distance of the current estimate (m) are candidates."""
    visual_candidates: int = 2
    """Verify at most this many candidates per keyframe (most predicted-visible points first)."""
    visual_min_depth: float = 1.5
    visual_max_depth: float = 12.0
    """Only points at this range from the current camera (m, along its axis) are searched."""
    visual_drift_per_m: float = 0.005
    """Along-track drift expected per metre travelled since the old keyframe: three times it
    (clamped below, plus ``visual_alias_margin``) is the search range, and it is the visual
    loops' consistency gate (as ``drift_per_m`` for LiDAR loops)."""
    visual_wide_drift_per_m: float = 0.02
    """When too few patches align within that range (or, with ``visual_widen_ambiguous``, two
    hypotheses tie), search again with this drift per metre (range and gate alike, the range
    clamped at ``visual_wide_max_shift``; 0 or no wider than ``visual_drift_per_m`` = off).
    0.01 with the range clamped at ``visual_max_shift`` until 2026-12-06: on dark seed 8 the
    dark way back ran 6-17 % short, the estimate was 1.8-2.0 m off keyframes 40-55 m back,
    past the 1.3 m searched, only aliases were inside (every search ambiguous or too few),
    and loop error came out 2.06 m; with 0.02 / 2.5 m / widening ambiguous searches, 0.006 m
    (see README for all 30 runs). On the dark way
    back of seed 6 the depth-scaled visual odometry ran 10 % short for 15 m while the LiDAR
    was blind along the axis: the estimate was 0.64 m off keyframes 15 m back, past the 0.6 m
    searched, and no visual loop was found for 36 s (APE 0.112 m). Widening every search
    instead (``visual_drift_per_m`` 0.01) fixed that run (0.028) but lost loops to
    ambiguous aliases elsewhere: loop error over 0.03 m on three dark runs (see README)."""
    visual_min_shift: float = 0.3
    visual_max_shift: float = 1.0
    """Bounds of the search range along the direction of travel (m)."""
    visual_wide_max_shift: float = 2.5
    """The upper bound for the wide search (``visual_wide_drift_per_m``; no lower than
    ``visual_max_shift``)."""
    visual_widen_ambiguous: bool = True
    """Search wide also where the first search was ambiguous (two hypotheses, aliases of a
    periodic structure, align about as many patches): when the estimate has drifted past the
    first range, the true peak lies outside it and only aliases are inside. The first
    search's hypotheses are aligned again in the wide one, so a tie found there stands."""
    visual_patch: int = 7
    """Side of the square patch (samples) laid on a point's LiDAR plane and compared by NCC."""
    visual_shift_step: float = 0.02
    """Step of the search along the direction of travel (m)."""
    visual_min_contrast: float = 1.0
    """Patches flatter than this grey-level standard deviation (on the search's blurred
    images) are not searched; the ``visual_max_points`` most contrasted are. Was 4: in the
    darkest stretches (mean grey level 3-7) no patch reached it."""
    visual_max_points: int = 150
    """Search at most this many points per candidate (the most contrasted)."""
    visual_blur_px: float = 2.0
    visual_dim_blur_px: float = 1.0
    """When no hypothesis aligns ``visual_min_inliers`` patches on the sharp images, align
    them again on images blurred by this much (Gaussian, px; 0 = off). In a dark stretch
    (mean grey level ~4 at full gain) the sensor noise caps a true patch's NCC on sharp
    images well below ``visual_min_ncc``; a 1 px blur lifts it (see README)."""
    visual_dim_blur_rungs: int = 2
    """How many blurs the dim retry climbs: rung r aligns on images blurred by r x
    ``visual_dim_blur_px``, tried only when the rung before aligned too few patches (and,
    above the first, only in the dark: ``visual_dim_ladder_max_grey``). 2 since session 36:
    on the 15 dark benchmark seeds (0-14) dark 8 / 12 APE 0.041 / 0.076 -> 0.022 / 0.013 m,
    every dark run within both goals, the uneven runs unchanged (only seeds 3 and 8 have
    frames darker than the gate, and neither climbed); held out: dark seeds 15 / 16 (see
    README). With ``visual_blur_noise_px: 1`` as well (session 35) uneven 13's loop error
    went past the goal, so the blurred loops keep the reprojection Hessian's variance."""
    visual_dim_ladder_max_grey: float = 12.0
    """Rungs above the first (``visual_dim_blur_rungs`` > 1) are climbed only where both
    images' mean raw grey level is below this (255 = everywhere): the blur that lifts a true
    patch's NCC out of the sensor noise of a very dark stretch also lets aliases align in
    brighter ones, where the sharp and 1 px alignments already find what there is (session
    22's ungated ladder raised uneven seeds 6 / 9's loop error past the goal). Of the
    uneven-light benchmark recordings (seeds 0-14) only 3 and 8 have frames darker than 12;
    the dark seeds' return legs are 5.5-26."""
    visual_blur_noise_px: float = 0.0
    """A visual loop aligned on images blurred by b px gets its along-track variance
    multiplied by 1 + (b / this)^2 (0 = no inflation): a blurred patch's NCC peak is wider,
    so its centre is found less precisely than the sharp-image reprojection Hessian says
    (session 23: loops aligned at 2 px had along-track z RMS 1.9-2.2 against ground truth,
    sharp and 1 px ones 0.5-1.6)."""
    visual_search_spacing_px: float = 3.0
    """The search along the track compares blurred images (Gaussian, px) with patches spaced
    this far apart (px in the old image): coarse, so that the prediction's error across the
    track (a few pixels) does not hide the peak; the 2-D location refines it."""
    visual_min_ncc: float = 0.8
    """A point votes with its best shift when its NCC peak reaches this."""
    visual_shift_tol: float = 0.03
    """Candidates whose shifts agree within this (m) vote together."""
    visual_hypotheses: int = 5
    """Peaks of the search along the track that are aligned and compared (aliases of a
    periodic structure peak too). With 3 the true peak was sometimes not among them and an
    alias one bracket period away won (seed 4 dark, 1.19 m off)."""
    visual_peak_ratio: float = 0.75
    """Refuse the loop when the runner-up hypothesis, converged elsewhere, aligns more than
    this fraction as many patches as the best (a repetitive wall)."""
    visual_alias_margin: float = 0.3
    """The search reaches this far (m) past three times the expected drift (after the clamp
    above). Without it, a drift just past the range hides the true peak (at or beyond the
    range's edge, where it cannot show as a peak) while a periodic alias sits inside and is
    accepted unopposed: on seed 4 dark with ``vision.length_sigma_ratio: 0.015`` five false
    loops, 1.13-1.20 m off, where the margin gives none (see README)."""
    visual_confirm_m: float = 6.0
    """A visual loop joins the graph only once a loop from a later query (within this many
    metres travelled after it) agrees with it on where the current keyframe is along the
    track (``visual_confirm_tol`` plus ``visual_confirm_drift_per_m`` per metre between the
    two); one left unconfirmed is dropped. An alias wins where the estimate has drifted
    past the search range, and the next query's alias lands elsewhere, while true loops
    agree: on dark seed 8 a lone false loop 0.88 m off (see README). 0 = accept at once."""
    visual_confirm_tol: float = 0.1
    visual_confirm_drift_per_m: float = 0.05
    """The agreement two loops need (m, and m per metre between their keyframes: the
    odometry's drift between them, 5 % where the dark visual odometry was worst)."""
    visual_min_inliers: int = 20
    visual_max_cross: float = 0.05
    """Refuse a visual loop whose alignment moved the prediction across the track (laterally
    or vertically, where the LiDAR is reliable) by more than this (m)."""
    visual_max_sigma: float = 0.05
    """Refuse a visual loop whose along-track sigma (below) exceeds this (m)."""
    visual_information_scale: float = 0.25
    """Multiplies the along-track information of a visual loop (from the reprojection Hessian
    of its aligned patch centres, 1 px)."""
    visual_rotation_sigma_deg: float = 10.0
    visual_loose_sigma: float = 1.0
    """A visual loop measures the along-track translation; its rotation (held at the
    prediction) and the other translation directions get these loose sigmas (deg, m)."""


@dataclasses.dataclass(frozen=True)
class SolverOptions:
    mode: str = "incremental"
    """``incremental`` (jaxslam's iSAM2-class solver) or ``batch`` (LM every keyframe)."""
    engine: str = "window"
    """The incremental solver's engine (``IncrementalConfig.engine``): ``window`` or
    ``bayes_tree`` (iSAM2's partial re-elimination; the benchmark figures of the estimator
    were measured with ``window``)."""
    final_optimize: bool = True
    """After the last keyframe, relinearise everything and solve to the batch optimum
    (``IncrementalSolver.refine``: Gauss-Newton with the incremental solver's compiled
    kernels, no batch-solver compilation)."""
    chunk_sizes: tuple[int, ...] = (64,)
    """The incremental solver's compiled row counts (``IncrementalConfig.chunk_sizes``; the
    solver's own default is (8, 64, 512)): each factor class's linearisation compiles once
    per size, most of the solver's share of a cold start. One size: on a 50 s recording
    with an empty compilation cache, linearisation compiles took 13.0 s instead of 23.1 s
    and the run 69 s instead of 80 s; warm runs 35.3 vs 34.1 s (solver 1.15 vs 1.11 s);
    estimates equal to 1e-10."""


@dataclasses.dataclass(frozen=True)
class PipelineConfig:
    rig: RigConfig = dataclasses.field(default_factory=RigConfig)
    keyframe: KeyframeConfig = dataclasses.field(default_factory=KeyframeConfig)
    imu: ImuConfig = dataclasses.field(default_factory=ImuConfig)
    lidar: LidarConfig = dataclasses.field(default_factory=LidarConfig)
    vision: VisionConfig = dataclasses.field(default_factory=VisionConfig)
    loop: LoopConfig = dataclasses.field(default_factory=LoopConfig)
    solver: SolverOptions = dataclasses.field(default_factory=SolverOptions)

    def to_dict(self) -> dict[str, Any]:
        return _plain(dataclasses.asdict(self))

    def replace(self, **sections: dict[str, Any]) -> PipelineConfig:
        """A copy with fields of sections replaced: ``cfg.replace(vision={"enhance": False})``."""
        out: dict[str, Any] = {}
        known = {f.name for f in dataclasses.fields(self)}
        for name, changes in sections.items():
            if name not in known:
                raise ConfigError(f"unknown config section {name!r}; expected one of {', '.join(sorted(known))}")
            cur = getattr(self, name)
            out[name] = _build(type(cur), {**dataclasses.asdict(cur), **changes}, name)
        return dataclasses.replace(self, **out)


def _plain(x: Any) -> Any:
    if isinstance(x, dict):
        return {k: _plain(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return [_plain(v) for v in x]
    if isinstance(x, np.generic):
        return x.item()
    return x


_CHOICES = {
    "detector": ("surf", "sift", "orb"),
    "scale_depth": ("map", "scan"),
    "mode": ("incremental", "batch"),
    "engine": ("window", "bayes_tree"),
    "lidar_model": ("hap", "ring16"),
    "odometry_kernel": ("cauchy", "huber"),
    "scale_revert_to": ("one", "run"),
}


_ANY_LENGTH = ("camera_distortion", "pairs", "chunk_sizes")
"""Tuple fields of any length (the others must keep their default's)."""


def _build(cls: type, data: dict[str, Any], where: str) -> Any:
    fields = {f.name: f for f in dataclasses.fields(cls)}
    unknown = sorted(set(data) - set(fields))
    if unknown:
        raise ConfigError(f"{where}: unknown key(s) {', '.join(unknown)}; expected some of {', '.join(fields)}")
    kwargs = {}
    for k, v in data.items():
        default = getattr(cls(), k)
        if isinstance(default, tuple):
            if not isinstance(v, list | tuple) or (len(v) != len(default) and k not in _ANY_LENGTH):
                raise ConfigError(f"{where}.{k}: expected a list of {len(default)} numbers, got {v!r}")
            if not all(isinstance(x, int | float) and not isinstance(x, bool) for x in v):
                raise ConfigError(f"{where}.{k}: expected numbers, got {v!r}")
            v = tuple(v)
            if k == "pairs" and not (v and all(isinstance(x, int) and x >= 1 for x in v)):
                raise ConfigError(f"{where}.{k}: expected keyframe offsets >= 1 (integers), got {v!r}")
            if k == "chunk_sizes" and not (
                v and all(isinstance(x, int) and x >= 1 for x in v) and list(v) == sorted(set(v))
            ):
                raise ConfigError(f"{where}.{k}: expected distinct row counts >= 1 in ascending order, got {v!r}")
            if k == "axis_weights" and not all(x > 0 for x in v):
                raise ConfigError(f"{where}.{k}: weights must be positive, got {v!r}")
        elif isinstance(default, bool):
            if not isinstance(v, bool):
                raise ConfigError(f"{where}.{k}: expected true/false, got {v!r}")
        elif isinstance(default, int):
            if isinstance(v, bool) or not isinstance(v, int):
                raise ConfigError(f"{where}.{k}: expected an integer, got {v!r}")
            if k == "patch_half" and v < 1:
                raise ConfigError(f"{where}.{k}: expected a patch half-size >= 1 (px), got {v!r}")
            if k == "patch_retry_half" and v < 0:
                raise ConfigError(f"{where}.{k}: expected a patch half-size >= 0 (px, 0 = no retry), got {v!r}")
            if k == "anchor_gap_scans" and v < 0:
                raise ConfigError(f"{where}.{k}: expected a number of scans >= 0, got {v!r}")
            if k == "visual_dim_blur_rungs" and v < 0:
                raise ConfigError(f"{where}.{k}: expected a number of blur rungs >= 0 (0 = off), got {v!r}")
            if k == "unscaled_min_inliers" and v < 0:
                raise ConfigError(f"{where}.{k}: expected a number of inliers >= 0 (0 = off), got {v!r}")
        elif isinstance(default, float):
            if isinstance(v, bool) or not isinstance(v, int | float):
                raise ConfigError(f"{where}.{k}: expected a number, got {v!r}")
            v = float(v)
            if k == "length_sigma_ratio" and not (np.isfinite(v) and v >= 0):
                raise ConfigError(f"{where}.{k}: expected a relative sigma >= 0 (0 = off), got {v!r}")
            if k == "wide_inlier_px" and not np.isfinite(v):
                raise ConfigError(f"{where}.{k}: expected a threshold in pixels (2 or less = off), got {v!r}")
            if k in ("visual_alias_margin", "visual_confirm_m", "visual_confirm_tol", "visual_wide_max_shift") and not (
                np.isfinite(v) and v >= 0
            ):
                raise ConfigError(f"{where}.{k}: expected a distance >= 0 (m), got {v!r}")
            if k in ("visual_confirm_drift_per_m", "visual_wide_drift_per_m", "visual_drift_per_m") and not (
                np.isfinite(v) and v >= 0
            ):
                raise ConfigError(f"{where}.{k}: expected a drift >= 0 (m per m), got {v!r}")
            if k == "odometry_kernel_scale" and not (np.isfinite(v) and v >= 0):
                raise ConfigError(f"{where}.{k}: expected a kernel scale >= 0 (whitened, 0 = off), got {v!r}")
            if k in ("patch_min_ncc", "patch_retry_min_ncc") and not (np.isfinite(v) and -1 <= v <= 1):
                raise ConfigError(f"{where}.{k}: expected a correlation in [-1, 1], got {v!r}")
            if k in ("patch_min_fraction", "patch_retry_min_fraction") and not (np.isfinite(v) and 0 <= v <= 1):
                raise ConfigError(f"{where}.{k}: expected a fraction in [0, 1], got {v!r}")
            if k == "guided_information_scale" and not (np.isfinite(v) and v > 0):
                raise ConfigError(f"{where}.{k}: expected a multiplier > 0, got {v!r}")
            if k in ("axis_sigma_scale", "visual_axis_sigma_scale") and not (np.isfinite(v) and v > 0):
                raise ConfigError(f"{where}.{k}: expected a multiplier > 0, got {v!r}")
            if k == "min_sigma_axis" and not (np.isfinite(v) and v >= 0):
                raise ConfigError(f"{where}.{k}: expected a sigma >= 0 (m, 0 = none), got {v!r}")
            if k == "zupt_hold_sigma" and not (np.isfinite(v) and v >= 0):
                raise ConfigError(f"{where}.{k}: expected a sigma >= 0 (m, 0 = off), got {v!r}")
            if k == "scale_revert_m" and not (np.isfinite(v) and v >= 0):
                raise ConfigError(f"{where}.{k}: expected a length >= 0 (m, 0 = off), got {v!r}")
            if k == "visual_dim_ladder_max_grey" and not (np.isfinite(v) and v >= 0):
                raise ConfigError(f"{where}.{k}: expected a grey level >= 0 (255 = no gate), got {v!r}")
            blurs = ("visual_dim_blur_px", "visual_blur_px", "visual_blur_noise_px")
            if k in blurs and not (np.isfinite(v) and v >= 0):
                raise ConfigError(f"{where}.{k}: expected a blur >= 0 (px, 0 = none), got {v!r}")
        elif isinstance(default, str):
            if not isinstance(v, str):
                raise ConfigError(f"{where}.{k}: expected a string, got {v!r}")
            allowed = _CHOICES.get(k)
            if allowed and v not in allowed:
                raise ConfigError(f"{where}.{k}: expected one of {', '.join(allowed)}, got {v!r}")
        kwargs[k] = v
    try:
        return cls(**kwargs)
    except (TypeError, ValueError) as e:
        raise ConfigError(f"{where}: {e}") from e


def config_from_dict(data: dict[str, Any], base: PipelineConfig | None = None, where: str = "config") -> PipelineConfig:
    """A :class:`PipelineConfig` from nested dicts (unknown sections or keys raise
    :class:`ConfigError`); missing keys keep ``base``'s values."""
    base = base or PipelineConfig()
    if not isinstance(data, dict):
        raise ConfigError(f"{where}: expected a mapping of sections, got {type(data).__name__}")
    sections = {f.name for f in dataclasses.fields(PipelineConfig)}
    unknown = sorted(set(data) - sections)
    if unknown:
        raise ConfigError(
            f"{where}: unknown section(s) {', '.join(unknown)}; expected some of {', '.join(sorted(sections))}"
        )
    out = {}
    for name, values in data.items():
        if values is None:
            continue
        if not isinstance(values, dict):
            raise ConfigError(f"{where}.{name}: expected a mapping, got {values!r}")
        cur = getattr(base, name)
        out[name] = _build(type(cur), {**dataclasses.asdict(cur), **values}, f"{where}.{name}")
    return dataclasses.replace(base, **out)


def load_config(path: str | Path, base: PipelineConfig | None = None) -> PipelineConfig:
    """Read a YAML config (sections as :class:`PipelineConfig`)."""
    p = Path(path)
    if not p.is_file():
        raise ConfigError(f"{p}: config file not found")
    try:
        data = yaml.safe_load(p.read_text()) or {}
    except yaml.YAMLError as e:
        raise ConfigError(f"{p}: not valid YAML ({e})") from e
    return config_from_dict(data, base, where=str(p))


def save_config(config: PipelineConfig, path: str | Path) -> None:
    Path(path).write_text(yaml.safe_dump(config.to_dict(), sort_keys=False))


def find_rig(recording: str | Path) -> Path | None:
    """The calibration file beside a recording: ``<stem>.rig.yaml`` or ``rig.yaml`` in its folder."""
    p = Path(recording)
    stem = p.parent / (p.stem if p.suffix else p.name)
    for cand in (Path(f"{stem}.rig.yaml"), p / "rig.yaml" if p.is_dir() else None, p.parent / "rig.yaml"):
        if cand is not None and cand.is_file():
            return cand
    return None


def load_rig(path: str | Path) -> RigConfig:
    p = Path(path)
    try:
        data = yaml.safe_load(p.read_text()) or {}
    except (OSError, yaml.YAMLError) as e:
        raise ConfigError(f"{p}: cannot read the rig calibration ({e})") from e
    if isinstance(data, dict) and "rig" in data:
        data = data["rig"]
    if not isinstance(data, dict):
        raise ConfigError(f"{p}: expected a mapping of calibration keys")
    return _build(RigConfig, data, str(p))

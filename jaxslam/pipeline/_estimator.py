"""The fused estimator: measurement records in, a keyframe factor graph solved incrementally.

Data flow (one pass over the records, in time order; nothing looks ahead more than one LiDAR
frame)::

    ImuSample  -> ImuBuffer (NaN / backwards samples skipped and counted)
    Image      -> recent-image queue
    LidarScan  -> waits until the IMU covers the scan, then a *frame event* at the scan's
                  mid time: IMU-propagated motion deskews it, scan-to-map ICP gives the
                  odometry pose (LidarOdometry)
    (no LiDAR for ``lidar_timeout`` s, or --no-lidar) -> images trigger frame events instead

    frame event -> keyframe? (travel / rotation / time since the last one)
       keyframe k: variables X_k (Pose3), V_k, B_k; factors
         IMU preintegration X_{k-1},V_{k-1} -> X_k,V_k with bias B_{k-1}; bias random walk
         LiDAR odometry between X_{k-1}, X_k (information from the registration Hessian,
           the tunnel axis down-weighted when degenerate)
         visual odometry between X_{k-1}, X_k (metric, LiDAR depth; VisualFrontend)
         loop closures X_i, X_k (LoopCloser: geometric verification + consistency gate,
           Cauchy kernel)
       -> IncrementalSolver.update; the new estimate seeds the next predictions.

Initialisation: gravity direction and gyro bias from the still start (first
``imu.still_seconds``), yaw 0 at the origin; zero velocity when the start is still (else a
loose velocity prior). A sensor that goes quiet only removes its factors: the IMU chain keeps
the graph connected, and the run reports what was missing (``warnings``).
"""

from __future__ import annotations

import dataclasses
import time
from collections import Counter, defaultdict, deque
from typing import Any

import jax.numpy as jnp
import numpy as np

from ..core import BiasVar, Cauchy, Factor, Gaussian, Huber, Pose3Var, ScaleVar, Values, VelocityVar
from ..errors import InputFormatError
from ..factors import (
    BetweenFactor,
    BiasRandomWalkFactor,
    ImuFactor,
    PreintegrationParams,
    PriorFactor,
    RelativeDirectionFactor,
    ScaledBetweenFactor,
)
from ..lie import SE3, host
from ..measurements import Image, ImuSample, LidarScan, PoseStamped, PositionFix
from ..solvers import IncrementalConfig, IncrementalSolver
from ._config import PipelineConfig
from ._imu import ImuBuffer, NavState, gravity_alignment, preintegrate_interval, propagate
from ._lidar_frontend import LidarOdometry, ScanResult, axis_sigma_scaled, axis_weighted, information_for_factor
from ._loop import Loop, LoopCloser
from ._visual import DirectionMeasurement, KeyframeFeatures, VisualFrontend, VisualMeasurement, with_length_sigma
from ._visual_loop import LoopQuery, VisualLoop, VisualLoopCloser


class _Done:
    """A finished job (the unthreaded path), shaped like a Future."""

    def __init__(self, value: Any):
        self.value = value

    def result(self) -> Any:
        return self.value


@dataclasses.dataclass
class Keyframe:
    index: int
    t: float
    scan: ScanResult | None
    features: KeyframeFeatures | None = None
    image: np.ndarray | None = None
    registered: bool = False


def _se3(T: np.ndarray) -> SE3:
    import jax.numpy as jnp

    return SE3(jnp.asarray(host.matrix_to_params(T)))


_FREE_ROTATION_INFO = 1e-6
"""Information on the rotation of a position-hold factor: ~1000 rad sigma, i.e. none."""


def position_hold(i: int, j: int, sigma: float) -> BetweenFactor:
    """Keyframes ``i`` and ``j`` at the same place, turned any way (``ImuConfig.zupt_hold_sigma``):
    a between factor with the identity measured, ``sigma`` (m) on each translation axis and
    no information to speak of on the rotation."""
    info = np.diag(np.r_[np.full(3, _FREE_ROTATION_INFO), np.full(3, sigma**-2.0)])
    return _between(i, j, np.eye(4), info)


def _between(i: int, j: int, T: np.ndarray, info: np.ndarray, robust=None) -> BetweenFactor:
    return BetweenFactor.create(
        Pose3Var(np.array([i])),
        Pose3Var(np.array([j])),
        _se3(T[None]),
        Gaussian.from_information(jnp.asarray(info[None])),
        robust=robust,
    )


RUN_SCALE_ID = 1_000_000_000
"""Id of the run-wide :class:`~jaxslam.core.ScaleVar` (``vision.scale_revert_to = "run"``);
the keyframes' log scales have their keyframe indices (all smaller)."""


def visual_odometry_factor(
    i: int, j: int, T: np.ndarray, info: np.ndarray, scaled: bool, kernel: str = "huber", kernel_scale: float = 0.0
) -> Factor:
    """The graph factor of one visual-odometry edge: a between factor (or, with ``scaled``,
    one whose translation is multiplied by the scale variable of keyframe ``j``) with
    ``info``, under a robust kernel when ``kernel_scale`` > 0 (``vision.odometry_kernel``)."""
    robust = (Huber if kernel == "huber" else Cauchy)(jnp.full(1, kernel_scale)) if kernel_scale > 0 else None
    if not scaled:
        return _between(i, j, T, info, robust=robust)
    return ScaledBetweenFactor.create(
        Pose3Var(np.array([i])),
        Pose3Var(np.array([j])),
        ScaleVar(np.array([j])),
        host.matrix_to_params(T)[None],
        Gaussian.from_information(jnp.asarray(info[None])),
        robust=robust,
    )


class Estimator:
    """Feed records with :meth:`feed`, then :meth:`finish`. See the module docstring."""

    lidar_timeout = 0.35

    def __init__(self, config: PipelineConfig):
        self.cfg = config
        rig = config.rig
        s = config.imu.noise_scale
        self.params = PreintegrationParams.make_shared_u(
            rig.gravity,
            accelerometer_noise_density=rig.accelerometer_noise_density * s,
            gyroscope_noise_density=rig.gyroscope_noise_density * s,
            accelerometer_random_walk=rig.accelerometer_random_walk,
            gyroscope_random_walk=rig.gyroscope_random_walk,
            integration_sigma=1e-4,
        )
        self.gravity = np.array([0.0, 0.0, -rig.gravity])
        self.T_bl = host.params_to_matrix(np.asarray(rig.body_T_lidar))
        self.imu = ImuBuffer()
        self.images: deque[Image] = deque(maxlen=30)
        self.pending: deque[LidarScan] = deque()
        self.lidar = LidarOdometry(config.lidar, self.T_bl) if config.lidar.enabled else None
        self.visual = VisualFrontend(config.vision, rig) if config.vision.enabled else None
        self.loops = (
            LoopCloser(config.loop, self.T_bl, config.lidar) if (config.loop.enabled and config.lidar.enabled) else None
        )
        self._scaled_vision = self.visual is not None and config.vision.scale_variable
        vcfg = config.vision
        self._scale_to_run = (
            self._scaled_vision
            and vcfg.scale_revert_m > 0
            and vcfg.scale_walk_sigma > 0
            and vcfg.scale_revert_to == "run"
        )
        self.visual_loops = (
            VisualLoopCloser(
                config.loop, self.visual.T_bc, self.visual.f, rig.camera_size, rig.K(), rig.camera_distortion
            )
            if self.visual is not None and self.lidar is not None and config.loop.enabled and config.loop.visual
            else None
        )
        self.solver = IncrementalSolver(
            IncrementalConfig(
                mode=config.solver.mode,  # type: ignore[arg-type]
                engine=config.solver.engine,  # type: ignore[arg-type]
                chunk_sizes=tuple(config.solver.chunk_sizes),
            )
        )
        self.keyframes: list[Keyframe] = []
        self.state: NavState | None = None  # estimate at the last keyframe
        self.warnings: Counter[str] = Counter()
        self.zupt_count = 0  # zero-velocity priors added (ImuConfig.zupt)
        self.length_softened = 0  # visual factors given vision.length_sigma_ratio (LiDAR anchored)
        self.ground_truth: list[PoseStamped] = []
        self.fixes: list[PositionFix] = []
        self.visual_edges: list[VisualMeasurement] = []
        self.direction_edges = 0
        """Scale-free visual factors added (no LiDAR depth)."""
        self.graph: list[tuple[str, Any]] = []
        """Every factor added, with its kind (see :meth:`_tag`)."""
        self.edges: list[tuple[str, int, int, np.ndarray, np.ndarray]] = []
        """Between factors added: (kind, i, j, measured T_i^-1 T_j, information)."""
        self.last_scan_t = -np.inf
        self.last_image_t = -np.inf
        self.t_first: float | None = None
        self.t_last = -np.inf
        self.frames_seen = 0
        self.timing: defaultdict[str, float] = defaultdict(float)
        self._cursor: NavState | None = None
        self._odom_cursor: np.ndarray | None = None  # LiDAR odometry pose at the cursor's time
        self._last_image_event: float | None = None
        self._lidar_rel: dict[tuple[int, int], np.ndarray] = {}
        self._scale_sums = [0.0, 0.0, 0]
        self._vo_scale = 1.0
        self._vjobs: deque[Any] = deque()
        self._recent_features: deque[KeyframeFeatures] = deque(maxlen=max(config.vision.pairs, default=1))
        self._executor = None
        if self.visual is not None and config.vision.threaded:
            from concurrent.futures import ThreadPoolExecutor

            self._executor = ThreadPoolExecutor(max_workers=1, thread_name_prefix="jaxslam-vision")

    def _stationary(self, acc: np.ndarray, dt: np.ndarray) -> bool:
        """The keyframe interval's samples ``acc`` (held ``dt`` each) look like standing still
        (see ``ImuConfig.zupt``): no more spread on any axis than the sensor's noise."""
        cfg = self.cfg.imu
        if not cfg.zupt or len(acc) < 10 or float(np.sum(dt)) < cfg.zupt_min_seconds:
            return False
        sigma = self.cfg.rig.accelerometer_noise_density / np.sqrt(float(np.median(dt)))
        return bool(np.all(np.std(acc, axis=0) < cfg.zupt_noise_ratio * sigma))

    def _standing_still(self, t: float, pred: NavState) -> bool:
        """``LidarConfig.hold_still``: the IMU samples just before ``t`` show neither motion
        (the zero-velocity test) nor a turn (bias-corrected rate below ``hold_still_rate``)."""
        lcfg = self.cfg.lidar
        if not lcfg.hold_still or self.lidar is None or self.lidar.last is None:
            return False
        if lcfg.hold_still_start_only and self.lidar.processed > self.lidar.held + 1:
            return False  # the vehicle has moved once (the first scan is never held)
        window = self.cfg.imu.zupt_min_seconds + 0.05
        if t - window < self.imu.t[0]:
            return False
        acc, gyro, dt, _ = self.imu.interval(t - window, t)
        if not self._stationary(acc, dt):
            return False
        rate = np.sum(gyro * dt[:, None], axis=0) / np.sum(dt) - pred.bias[3:]
        return bool(np.linalg.norm(rate) < lcfg.hold_still_rate)

    def _tag(self, kind: str, factor: Any) -> Any:
        """Keep every factor with its kind (``prior``, ``imu``, ``bias``, ``zupt``, ``lidar``,
        ``vision``, ``direction``, ``loop``): ``jaxslam tune`` re-weights the final graph by kind."""
        self.graph.append((kind, factor))
        return factor

    # --- input -------------------------------------------------------------------------------
    def feed(self, rec: Any) -> None:
        """One measurement record (ImuSample, Image, LidarScan, PositionFix, PoseStamped)."""
        try:
            rec.validate()
        except InputFormatError as e:
            self.warnings[f"{rec.kind}: bad sample ({e.message if hasattr(e, 'message') else e})"] += 1
            return
        if self.t_first is None:
            self.t_first = rec.t
        self.t_last = max(self.t_last, rec.t)
        if isinstance(rec, ImuSample):
            if not self.imu.append(rec.t, np.asarray(rec.acc, np.float64), np.asarray(rec.gyro, np.float64)):
                self.warnings["imu: timestamp not increasing (sample skipped)"] += 1
                return
            self._drain()
        elif isinstance(rec, Image):
            if rec.t <= self.last_image_t:
                self.warnings["camera: timestamp not increasing (frame skipped)"] += 1
                return
            self.last_image_t = rec.t
            self.images.append(rec)
            self.frames_seen += 1
            if self.lidar is None or rec.t - self.last_scan_t > self.lidar_timeout:
                if self.lidar is not None and self.last_scan_t > -np.inf:
                    self.warnings["lidar: no scan, camera frames drive keyframes"] += 1
                self._drain()
        elif isinstance(rec, LidarScan):
            if self.lidar is None:
                return
            if (self.pending and rec.t <= self.pending[-1].t) or rec.t <= self.last_scan_t:
                self.warnings["lidar: timestamp not increasing (scan skipped)"] += 1
                return
            if len(rec.points) < 100:
                self.warnings["lidar: scan with fewer than 100 points skipped"] += 1
                return
            self.pending.append(rec)
            self._drain()
        elif isinstance(rec, PoseStamped):
            self.ground_truth.append(rec)
        elif isinstance(rec, PositionFix):
            self.fixes.append(rec)

    def _drain(self) -> None:
        """Process the frame events whose IMU coverage is complete."""
        while self.pending:
            scan = self.pending[0]
            t_end = scan.t + float(np.max(scan.point_times, initial=0.0))
            if self.imu.last_time < t_end:
                return
            self.pending.popleft()
            self.last_scan_t = scan.t
            t_ref = scan.t + 0.5 * float(np.max(scan.point_times, initial=0.0))
            self._event(t_ref, scan)
        if (self.lidar is None or self.last_scan_t < self.imu.last_time - self.lidar_timeout) and self.images:
            img = self.images[-1]
            fresh = not self.keyframes or img.t > self.keyframes[-1].t + 1e-6
            if self.imu.last_time >= img.t and fresh and self._last_image_event != img.t:
                self._last_image_event = img.t
                self._event(img.t, None)

    # --- frame events -------------------------------------------------------------------------
    def _initialise(self, t: float) -> bool:
        cfg = self.cfg.imu
        t0 = self.imu.t[0] if self.imu.n else np.inf
        if t < t0 + cfg.still_seconds:
            return False
        acc, gyro, acc_std, n = self.imu.mean(t0, t0 + cfg.still_seconds)
        if n < 10:
            return False
        R = gravity_alignment(acc)
        still = bool(np.all(acc_std < cfg.still_acc_std))
        bias = np.zeros(6)
        if still:
            bias[3:] = gyro
        else:
            self.warnings["init: start not still (gyro bias and velocity from motion)"] += 1
        state = NavState(t0 + cfg.still_seconds, host.make_pose(R, np.zeros(3)), np.zeros(3), bias)
        self.state, _ = propagate(self.imu, state, t, self.gravity) if t > state.t else (state, None)
        self._still_start = still
        return True

    def _event(self, t: float, scan: LidarScan | None) -> None:
        if self.state is None and not self._initialise(t):
            return
        assert self.state is not None
        t0 = time.perf_counter()
        # propagate from the cursor (the state predicted at the previous event, from the current
        # keyframe estimate) so each event integrates only the samples since the last one
        cur = self._cursor if self._cursor is not None and self._cursor.t <= t else self.state
        dur = float(np.max(scan.point_times, initial=0.0)) if scan is not None else 0.0
        times = scan.t + np.linspace(0.0, dur, 6) if scan is not None else np.zeros(0)
        before = times[times <= t]
        pred, poses_a = propagate(self.imu, cur, t, self.gravity, times=before)
        self._cursor = pred
        result: ScanResult | None = None
        if scan is not None and self.lidar is not None:
            after = times[times > t]
            poses = poses_a
            if len(after):
                _, poses_b = propagate(self.imu, pred, float(after[-1]), self.gravity, times=after)
                poses = np.concatenate([poses_a, poses_b]) if poses_a is not None else poses_b
            # predicted odometry pose: the odometry pose at the cursor moved by the IMU-predicted
            # motion since (chained through events without a scan: after a LiDAR dropout the
            # last scan's pose is seconds old, and the motion since is not only this event's)
            T_odom_pred = self._odom_pose(cur, pred)
            try:
                result = self.lidar.process(
                    t,
                    scan.points,
                    scan.t + scan.point_times,
                    (times, poses),
                    T_odom_pred,
                    intensity=scan.intensity,
                    still=self._standing_still(t, pred),
                )
            except InputFormatError as e:
                self.warnings[f"lidar: scan rejected ({e})"] += 1
                result = None
        if self.lidar is not None and self.lidar.last is not None:
            self._odom_cursor = result.T_odom if result is not None else self._odom_pose(cur, pred)
        self.timing["lidar"] += time.perf_counter() - t0
        if self.keyframes and not self._is_keyframe(t, pred, result):
            return
        self._add_keyframe(t, pred, result)
        self._cursor = self.state

    def _odom_pose(self, cur: NavState, pred: NavState) -> np.ndarray:
        """The body pose in the LiDAR odometry frame predicted at ``pred``'s time: the odometry
        pose at the cursor ``cur`` moved by the IMU motion from ``cur`` to ``pred`` (the
        estimate's own pose before the first scan)."""
        if self._odom_cursor is None:
            return pred.T.copy()
        return self._odom_cursor @ host.inverse(cur.T) @ pred.T

    def _is_keyframe(self, t: float, pred: NavState, scan: ScanResult | None) -> bool:
        kcfg = self.cfg.keyframe
        last = self.keyframes[-1]
        if t - last.t >= kcfg.max_interval:
            return True
        if scan is not None and last.scan is not None:
            d = host.inverse(last.scan.T_odom) @ scan.T_odom
        else:
            assert self.state is not None
            d = host.inverse(self.state.T) @ pred.T
        ang = np.degrees(np.linalg.norm(host.so3_log(d[:3, :3])))
        return bool(np.linalg.norm(d[:3, 3]) >= kcfg.distance or ang >= kcfg.angle_deg)

    def _image_near(self, t: float) -> Image | None:
        best = min(self.images, key=lambda im: abs(im.t - t), default=None)
        if best is None or abs(best.t - t) > self.cfg.vision.max_time_offset:
            return None
        return best

    def _add_keyframe(self, t: float, pred: NavState, scan: ScanResult | None) -> None:
        k = len(self.keyframes)
        kf = Keyframe(k, t, scan)
        factors: list = []
        values: dict = {}
        tk = time.perf_counter()
        if k == 0:
            assert self.state is not None
            icfg = self.cfg.imu
            values = {
                Pose3Var(np.array([0])): _se3(pred.T[None]),
                VelocityVar(np.array([0])): pred.v[None],
                BiasVar(np.array([0])): pred.bias[None],
            }
            factors.append(
                self._tag(
                    "prior",
                    PriorFactor.create(
                        Pose3Var(np.array([0])), _se3(pred.T[None]), Gaussian.diagonal(jnp.full(6, 1e-3))
                    ),
                )
            )
            vs = 0.01 if self._still_start else 1.0
            v_prior = PriorFactor.create(VelocityVar(np.array([0])), pred.v[None], Gaussian.isotropic(3, vs))
            factors.append(self._tag("prior", v_prior))
            bsig = np.array([icfg.acc_bias_sigma] * 3 + [icfg.gyro_bias_sigma if self._still_start else 0.05] * 3)
            b_prior = PriorFactor.create(BiasVar(np.array([0])), pred.bias[None], Gaussian.diagonal(jnp.asarray(bsig)))
            factors.append(self._tag("prior", b_prior))
            if self._scaled_vision:
                # the first keyframe's log scale, and the run-wide one the keyframes revert to
                for sid in [0, RUN_SCALE_ID] if self._scale_to_run else [0]:
                    values[ScaleVar(np.array([sid]))] = np.zeros((1, 1))
                    s_prior = PriorFactor.create(
                        ScaleVar(np.array([sid])), np.zeros(1), Gaussian.isotropic(1, self.cfg.vision.scale_prior_sigma)
                    )
                    factors.append(self._tag("scale", s_prior))
        else:
            prev = self.keyframes[-1]
            acc, gyro, dt, gap = self.imu.interval(prev.t, t)
            if gap > self.cfg.imu.gap_seconds:
                self.warnings["imu: gap bridged inside a keyframe interval"] += 1
            assert self.state is not None
            pim = preintegrate_interval(acc, gyro, dt, self.params, self.state.bias)
            ids = (np.array([k - 1]), np.array([k]))
            factors.append(
                self._tag(
                    "imu",
                    ImuFactor.create(
                        Pose3Var(ids[0]),
                        VelocityVar(ids[0]),
                        Pose3Var(ids[1]),
                        VelocityVar(ids[1]),
                        BiasVar(ids[0]),
                        pim,
                        self.params,
                    ),
                )
            )
            bias_walk = BiasRandomWalkFactor.create(BiasVar(ids[0]), BiasVar(ids[1]), t - prev.t, self.params)
            factors.append(self._tag("bias", bias_walk))
            if self._stationary(acc, dt):
                sigma = self.cfg.imu.zupt_sigma
                zero = PriorFactor.create(VelocityVar(ids[1]), np.zeros((1, 3)), Gaussian.isotropic(3, sigma))
                factors.append(self._tag("zupt", zero))
                self.zupt_count += 1
                hold = self.cfg.imu.zupt_hold_sigma
                if hold > 0:
                    factors.append(self._tag("zupt", position_hold(k - 1, k, hold)))
            values = {
                Pose3Var(ids[1]): _se3(pred.T[None]),
                VelocityVar(ids[1]): pred.v[None],
                BiasVar(ids[1]): pred.bias[None],
            }
            if self._scaled_vision:  # the visual length scale random-walks with the distance travelled
                values[ScaleVar(ids[1])] = self.solver.value(ScaleVar, k - 1)[None]
                step = max(float(np.linalg.norm(pred.T[:3, 3] - self.state.T[:3, 3])), 0.05)
                walk = Gaussian.isotropic(1, self.cfg.vision.scale_walk_sigma * np.sqrt(step))
                factors.append(
                    self._tag("scale", BetweenFactor.create(ScaleVar(ids[0]), ScaleVar(ids[1]), np.zeros(1), walk))
                )
                # mean reversion: where nothing measures lengths, the scale returns towards 1
                revert = self.cfg.vision.scale_revert_m
                if revert > 0 and self.cfg.vision.scale_walk_sigma > 0:
                    noise = Gaussian.isotropic(1, revert * self.cfg.vision.scale_walk_sigma / np.sqrt(step))
                    pull: Factor
                    if self._scale_to_run:
                        run = ScaleVar(np.array([RUN_SCALE_ID]))
                        pull = BetweenFactor.create(run, ScaleVar(ids[1]), np.zeros(1), noise)
                    else:
                        pull = PriorFactor.create(ScaleVar(ids[1]), np.zeros(1), noise)
                    factors.append(self._tag("scale", pull))
            if (
                scan is not None
                and prev.scan is not None
                and scan.registration is not None
                and scan.registration.converged
            ):
                T_rel = host.inverse(prev.scan.T_odom) @ scan.T_odom
                info = axis_sigma_scaled(
                    axis_weighted(
                        information_for_factor(
                            scan.registration.strong_information(),
                            self.T_bl,
                            self.cfg.lidar,
                            self.cfg.lidar.information_scale,
                            self.cfg.lidar.min_sigma_axis,
                        ),
                        self.cfg.lidar.axis_weights,
                    ),
                    self.cfg.lidar.axis_sigma_scale,
                )
                self.edges.append(("lidar odometry", k - 1, k, T_rel, info))
                if scan.last_degenerate < prev.scan.index:  # anchored along the axis throughout
                    self._lidar_rel[(k - 1, k)] = T_rel
                factors.append(self._tag("lidar", _between(k - 1, k, T_rel, info)))
                # scan-to-map odometry does not drift while the LiDAR sees what pins the axis
                # (the end wall): longer baselines to older keyframes keep that anchoring,
                # which chained consecutive factors (independent errors) would lose
                for n in self.cfg.lidar.pairs:
                    old = self.keyframes[k - n] if n > 1 and k - n >= 0 else None
                    # only over a stretch where every scan kept the axis (else the odometry's
                    # axis there is our own IMU prediction, not a measurement)
                    if (
                        old is None
                        or old.scan is None
                        or self.lidar is None
                        or not self.lidar.anchored_between(old.scan.index, scan.index, self.cfg.lidar.anchor_gap_scans)
                    ):
                        continue
                    T_n = host.inverse(old.scan.T_odom) @ scan.T_odom
                    self.edges.append(("lidar odometry", k - n, k, T_n, info))
                    factors.append(self._tag("lidar", _between(k - n, k, T_n, info)))
            elif self.lidar is not None and not (scan is not None and scan.held):
                self.warnings["lidar: keyframe without odometry factor"] += 1
        self.timing["imu"] += time.perf_counter() - tk
        # vision: features + relative pose to the previous keyframe image, in a worker thread
        # when configured (SURF runs in XLA, which releases the GIL, so it overlaps the LiDAR
        # front end on a second core); its factors join the graph at the next keyframe's update,
        # waiting for the worker if it is behind: a fixed lag, so a threaded run is as
        # deterministic as an unthreaded one and a loaded machine does not delay vision further
        tv = time.perf_counter()
        if self.visual is not None:
            img = self._image_near(t)
            if img is not None:
                pts = scan_pts = None
                if scan is not None and self.lidar is not None:
                    if self.cfg.vision.scale_depth == "scan":
                        scan_pts = scan.points  # the keyframe's own scan (body frame): metric scale
                    # depth from the local map (the scans of the last metres), not one scan: the
                    # LiDAR's 25-degree band covers a fraction of the camera's view
                    pts = host.transform_points(host.inverse(scan.T_odom), self.lidar.map.points())
                kf.image = img.data if img.data.ndim == 2 else img.data.max(axis=2)
                assert self.state is not None
                guess = {}
                for off in self.cfg.vision.pairs:
                    if k - off >= 0:
                        T_prev = (
                            self.state.T if off == 1 else host.params_to_matrix(self.solver.value(Pose3Var, k - off))
                        )
                        guess[off] = host.inverse(T_prev) @ pred.T
                query = self._loop_query(k, t, pred.T) if self.visual_loops and self.visual_loops.due(k) else None
                args = (kf, img.data, pts, guess, scan_pts, query)
                if self._executor is not None:
                    self._vjobs.append(self._executor.submit(self._vision_job, *args))
                else:
                    self._vjobs.append(_Done(self._vision_job(*args)))
            else:
                self.warnings["camera: no image at a keyframe"] += 1
            factors += self._collect_vision(keep=1 if self._executor is not None else 0)
        self.timing["vision"] += time.perf_counter() - tv
        self.keyframes.append(kf)
        # loops
        tl = time.perf_counter()
        if self.loops is not None and scan is not None and k > 0:
            est = self._poses()
            factors += [self._loop_factor(loop) for loop in self.loops.detect(k, self.keyframes, est)]
        self.timing["loop"] += time.perf_counter() - tl
        ts = time.perf_counter()
        self.solver.update(factors, Values.create(values))
        self.timing["solver"] += time.perf_counter() - ts
        self.state = self._state(k)

    def _vision_job(
        self,
        kf: Keyframe,
        image: np.ndarray,
        pts: np.ndarray | None,
        guess: dict[int, np.ndarray],
        scan_pts: np.ndarray | None = None,
        query: LoopQuery | None = None,
    ):
        """Worker: features of ``kf`` and relative poses from earlier image keyframes
        (``vision.pairs`` keyframes back: 1 = the previous one); ``scan_pts``, the keyframe's own
        scan, only when the visual length is to come from it (``vision.scale_depth: scan``);
        visual loops to older keyframes when ``query`` is given."""
        assert self.visual is not None
        t0 = time.perf_counter()
        feats = self.visual.features(kf.index, kf.t, image, pts, scan_pts)
        recent = {f.kf: f for f in self._recent_features}
        out: list[VisualMeasurement | DirectionMeasurement | VisualLoop] = []
        paired = False
        for off in sorted(guess):
            prev = recent.get(kf.index - off)
            if prev is None:
                continue
            paired |= off == 1
            vm = self.visual.relative(prev, feats, guess[off])
            if vm is not None:
                out.append(vm)
        if query is not None and self.visual_loops is not None and kf.image is not None:
            feats_old, images_old = {}, {}
            for o in self.keyframes[: query.k]:
                if o.features is not None and o.image is not None:
                    feats_old[o.index], images_old[o.index] = o.features, o.image
            tq = time.perf_counter()
            out += self.visual_loops.detect(query, kf.image, feats_old, images_old)
            self.timing["visual loop (worker)"] += time.perf_counter() - tq
        kf.features = feats
        self._recent_features.append(feats)
        self.timing["vision (worker)"] += time.perf_counter() - t0
        return kf, paired, out

    def _loop_query(self, k: int, t: float, T_pred: np.ndarray) -> LoopQuery:
        """The estimate the vision worker searches visual loops from keyframe ``k`` with: all
        keyframe poses (the new one at its prediction ``T_pred``), their times and the distance
        travelled up to each."""
        poses = np.concatenate([self._poses()[:k], T_pred[None]])
        steps = np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1)
        times = np.array([kf.t for kf in self.keyframes[:k]] + [t])
        return LoopQuery(k, t, poses, np.concatenate([[0.0], np.cumsum(steps)]), times)

    def _last_loop(self) -> list:
        """The recording's last keyframe is always tried for a LiDAR loop: it is where a
        drive out and back returns to its start, and ``loop.every`` may have skipped it."""
        k = len(self.keyframes) - 1
        if self.loops is None or k <= 0 or k % self.loops.cfg.every == 0 or self.keyframes[k].scan is None:
            return []
        tl = time.perf_counter()
        loops = self.loops.detect(k, self.keyframes, self._poses(), force=True)
        self.timing["loop"] += time.perf_counter() - tl
        return [self._loop_factor(loop) for loop in loops]

    def _loop_factor(self, loop: Loop | VisualLoop):
        """The graph factor of an accepted loop (LiDAR or visual): its relative pose and
        information (its along-axis sigma scaled by ``loop.axis_sigma_scale``, or
        ``loop.visual_axis_sigma_scale`` for a visual loop) under a Cauchy kernel; the edge is
        recorded for the residual plots."""
        cfg = self.cfg.loop
        visual = isinstance(loop, VisualLoop)
        info = axis_sigma_scaled(loop.information, cfg.visual_axis_sigma_scale if visual else cfg.axis_sigma_scale)
        self.edges.append(("loop closure", loop.i, loop.j, loop.T, info))
        # per constraint (an array): LiDAR and visual loops share one factor group
        robust = Cauchy(jnp.full(1, cfg.visual_cauchy_scale if visual else cfg.cauchy_scale))
        return self._tag("loop", _between(loop.i, loop.j, loop.T, info, robust=robust))

    def _collect_vision(self, keep: int = 0) -> list:
        """Factors of all vision jobs but the newest ``keep``, in keyframe order (waiting for
        them to finish)."""
        out: list[Any] = []
        while len(self._vjobs) > keep:
            kf, paired, vms = self._vjobs.popleft().result()
            out += [self._loop_factor(lp) for lp in vms if isinstance(lp, VisualLoop)]
            for dm in [v for v in vms if isinstance(v, DirectionMeasurement)]:
                sr, sd = self.cfg.vision.direction_sigmas
                noise = Gaussian.diagonal(jnp.asarray([sr] * 3 + [sd] * 2))
                ids = (Pose3Var(np.array([dm.i])), Pose3Var(np.array([dm.j])))
                tbc = np.asarray(self.cfg.rig.body_T_camera)
                out.append(
                    self._tag(
                        "direction", RelativeDirectionFactor.create(*ids, dm.R, dm.u, tbc, noise, robust=Cauchy(1.0))
                    )
                )
                self.direction_edges += 1
                kf.registered = True
                self.keyframes[dm.i].registered = True
            vms = [v for v in vms if isinstance(v, VisualMeasurement)]
            for vm in vms:
                self._calibrate_scale(vm)
                if self._vo_scale != 1.0:
                    vm.T = vm.T.copy()
                    vm.T[:3, 3] *= self._vo_scale
                info = axis_sigma_scaled(
                    axis_weighted(vm.information, self.cfg.vision.axis_weights), self.cfg.vision.axis_sigma_scale
                )
                ratio = self.cfg.vision.length_sigma_ratio
                if ratio > 0 and all((k, k + 1) in self._lidar_rel for k in range(vm.i, vm.j)):
                    info = with_length_sigma(info, vm.T[:3, 3], ratio)
                    self.length_softened += 1
                vcfg = self.cfg.vision
                n_min = vcfg.unscaled_min_inliers
                scaled = self._scaled_vision and not (n_min > 0 and vm.refined and vm.inliers >= n_min)
                factor = visual_odometry_factor(
                    vm.i, vm.j, vm.T, info, scaled, vcfg.odometry_kernel, vcfg.odometry_kernel_scale
                )
                out.append(self._tag("vision", factor))
                self.edges.append(("visual odometry", vm.i, vm.j, vm.T, info))
                self.visual_edges.append(vm)
                kf.registered = True
                self.keyframes[vm.i].registered = True
            if paired and not kf.registered:
                self.warnings["camera: keyframe not registered (too few inliers)"] += 1
        return out

    def _calibrate_scale(self, vm: VisualMeasurement) -> None:
        """Visual odometry's translation length is biased by ~1 % on the simulated tunnel
        (measured with exact depth: the bias is in the image features, not the depth or the
        solver). Where the LiDAR is not degenerate (it sees the end wall) its relative motion
        is unbiased, so the ratio of the two over such keyframe pairs calibrates the visual
        scale for the stretches where LiDAR is blind along the axis (``vision.scale_from_lidar``)."""
        if not self.cfg.vision.scale_from_lidar:
            return
        T_l = self._lidar_rel.get((vm.i, vm.j))
        if T_l is None:
            return
        lv, ll = float(np.linalg.norm(vm.T[:3, 3])), float(np.linalg.norm(T_l[:3, 3]))
        if lv < 0.1:
            return
        self._scale_sums[0] += lv * ll
        self._scale_sums[1] += lv * lv
        self._scale_sums[2] += 1
        if self._scale_sums[2] >= 20:
            self._vo_scale = float(np.clip(self._scale_sums[0] / self._scale_sums[1], 0.95, 1.05))

    def _state(self, k: int) -> NavState:
        sv = self.solver
        T = host.params_to_matrix(sv.value(Pose3Var, k))
        return NavState(self.keyframes[k].t, T, sv.value(VelocityVar, k), sv.value(BiasVar, k))

    def _poses(self) -> np.ndarray:
        """Current keyframe pose estimates (K, 4, 4) (the newest keyframe at its prediction)."""
        self.solver.flush()  # the Bayes tree engine back-substitutes lazily
        s = self.solver.stores[Pose3Var]
        order = np.argsort(s.ids[: s.n], kind="stable")
        P = host.params_to_matrix(s.x[: s.n][order])
        if len(P) < len(self.keyframes):
            assert self.state is not None
            P = np.concatenate([P, np.repeat(self.state.T[None], len(self.keyframes) - len(P), 0)])
        return P

    # --- end -----------------------------------------------------------------------------------
    def finish(self) -> dict[str, Any]:
        """Flush what is pending, run the final batch optimisation (when configured) and return
        the keyframe trajectory and run statistics."""
        while self.pending:  # scans the IMU never fully covered (truncated recording)
            scan = self.pending.popleft()
            if self.imu.n and self.imu.last_time > scan.t:
                self.warnings["lidar: last scan only partly covered by the IMU"] += 1
                dur = float(np.max(scan.point_times, initial=0.0))
                t_ref = min(scan.t + 0.5 * dur, self.imu.last_time)
                self._event(t_ref, scan)
        late = self._collect_vision()
        if self._executor is not None:
            self._executor.shutdown(wait=True)
        if self.visual_loops is not None:
            self.visual_loops.close()
        late += self._last_loop()
        if late:
            self.solver.update(late)
        final = None
        if self.keyframes and self.cfg.solver.final_optimize:
            ts = time.perf_counter()
            final = self.solver.refine()
            self.timing["solver"] += time.perf_counter() - ts
        est = self.solver.estimate() if self.keyframes else None
        poses = host.params_to_matrix(np.asarray(est.params(Pose3Var))) if est is not None else np.zeros((0, 4, 4))
        return {
            "times": np.array([kf.t for kf in self.keyframes]),
            "poses": poses,
            "final": final,
        }

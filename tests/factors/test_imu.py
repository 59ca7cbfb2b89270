"""IMU preintegration, ImuFactor and BiasRandomWalkFactor.

Golden values come from the pinned gtsam 4.3.0 wheel at test time (never copied constants), on
the KITTI IMU stream shipped in the wheel and on random synthetic data:

* dR, dv, dp, dt, bias Jacobians, covariance (and the residual-chart covariance) against
  ``gtsam.PreintegratedImuMeasurements`` (the wheel's tangent preintegration) -- 1e-9 relative;
* the factor error vector and cost against ``gtsam.ImuFactor.evaluateError`` / ``error`` in
  both error charts, at random states with a bias away from the integration bias;
* Jacobians: autodiff == central differences on the manifold == jacrev, and the information
  form ``J^T J``, ``J^T r`` equals GTSAM's linearisation;
* closed forms: constant acceleration (exact) and constant twist (exact rotation, first-order
  convergence of dp, dv);
* bad input raises ``ValueError`` / ``ConfigError`` naming the argument, never a silent NaN.

Compilation dominates the run time, so the kernel sees few distinct shapes and the GTSAM
results are built once per module.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxslam.core import BiasVar, Pose3Var, VelocityVar, autodiff_jacobians, factor_cost, linearize
from jaxslam.errors import ConfigError
from jaxslam.factors import (
    BiasRandomWalkFactor,
    ImuFactor,
    PreintegrationParams,
    cut_imu_stream,
    preintegrate,
    preintegrate_stream,
)
from jaxslam.lie import SE3, SO3

TOL = 1e-9
GRAVITY = 9.81


# --------------------------------------------------------------------------------------------
# helpers
# --------------------------------------------------------------------------------------------


def rel_diff(ours, ref) -> float:
    """Largest over the leading axis of ``max|ours - ref| / max|ref|``."""
    ref = np.asarray(ref, dtype=np.float64)
    ours = np.asarray(ours, dtype=np.float64).reshape(ref.shape[0], -1)
    ref = ref.reshape(ref.shape[0], -1)
    scale = np.maximum(np.abs(ref).max(axis=1), np.finfo(float).tiny)
    return float((np.abs(ours - ref).max(axis=1) / scale).max())


def gtsam_params(gtsam, acc_cov, gyro_cov, int_cov):
    p = gtsam.PreintegrationParams.MakeSharedU(GRAVITY)
    p.setAccelerometerCovariance(np.asarray(acc_cov))
    p.setGyroscopeCovariance(np.asarray(gyro_cov))
    p.setIntegrationCovariance(np.asarray(int_cov))
    return p


def gtsam_pims(gtsam, p, acc, gyro, dt, mask, bias_hat, cls=None):
    cls = cls or gtsam.PreintegratedImuMeasurements
    out = []
    for k in range(acc.shape[0]):
        pim = cls(p, gtsam.imuBias.ConstantBias(bias_hat[k, :3], bias_hat[k, 3:]))
        for i in np.nonzero(mask[k])[0]:
            pim.integrateMeasurement(acc[k, i], gyro[k, i], float(dt[k, i]))
        out.append(pim)
    return out


def gtsam_bias_jacobian(gtsam, pim, bias_hat):
    """GTSAM's d preintegrated / d bias: ``predict`` from the identity NavState is affine in the
    bias (first-order correction), so unit bias steps give the columns."""
    g = np.array([0.0, 0.0, -GRAVITY])
    t = pim.deltaTij()

    def corrected(b):
        s = pim.predict(gtsam.NavState(), gtsam.imuBias.ConstantBias(b[:3], b[3:]))
        return np.concatenate([gtsam.Rot3.Logmap(s.attitude()), s.position() - 0.5 * g * t * t, s.velocity() - g * t])

    base = corrected(bias_hat)
    return np.stack([corrected(bias_hat + np.eye(6)[j]) - base for j in range(6)], axis=1)


def pose_row(pose) -> np.ndarray:
    q = pose.rotation().toQuaternion()
    return np.array([q.w(), q.x(), q.y(), q.z(), *pose.translation()])


def random_states(gtsam, rng, pims, bias_hat):
    """State i random; bias near bias_hat; state j = GTSAM's prediction moved by a random
    error (rotation error well below pi, where GTSAM's NavState::Logmap loses digits)."""
    n = len(pims)
    poses_i = [gtsam.Pose3(gtsam.Rot3.Expmap(rng.normal(size=3)), 3.0 * rng.normal(size=3)) for _ in range(n)]
    vel_i = rng.normal(size=(n, 3))
    bias_i = bias_hat + 0.02 * rng.normal(size=(n, 6))
    poses_j, vel_j = [], []
    for k, pim in enumerate(pims):
        pred = pim.predict(
            gtsam.NavState(poses_i[k], vel_i[k]), gtsam.imuBias.ConstantBias(bias_i[k, :3], bias_i[k, 3:])
        )
        poses_j.append(pred.pose().compose(gtsam.Pose3.Expmap(np.r_[0.4 * rng.normal(size=3), rng.normal(size=3)])))
        vel_j.append(pred.velocity() + rng.normal(size=3))
    return poses_i, vel_i, poses_j, np.asarray(vel_j), bias_i


def make_factor(pim, params, n, error_mode="logmap"):
    ids = np.arange(n)
    return ImuFactor.create(
        Pose3Var(ids),
        VelocityVar(ids),
        Pose3Var(ids + n),
        VelocityVar(ids + n),
        BiasVar(ids),
        pim,
        params,
        error_mode=error_mode,
    )


def gtsam_values(gtsam, pose_i, vel_i, pose_j, vel_j, bias):
    x, v, b = gtsam.symbol_shorthand.X, gtsam.symbol_shorthand.V, gtsam.symbol_shorthand.B
    vals = gtsam.Values()
    vals.insert(x(0), pose_i)
    vals.insert(v(0), vel_i)
    vals.insert(x(1), pose_j)
    vals.insert(v(1), vel_j)
    vals.insert(b(0), bias)
    return vals


def gtsam_factor(gtsam, pim):
    x, v, b = gtsam.symbol_shorthand.X, gtsam.symbol_shorthand.V, gtsam.symbol_shorthand.B
    return gtsam.ImuFactor(x(0), v(0), x(1), v(1), b(0), pim)


# --------------------------------------------------------------------------------------------
# fixtures (module scope: one GTSAM pass and few kernel shapes)
# --------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def kitti(gtsam):
    """The KITTI stream cut into 0.1 s intervals, ours and GTSAM's preintegration of it."""
    data = np.loadtxt(gtsam.findExampleDataFile("KittiEquivBiasedImu.txt"), skiprows=1)
    with open(gtsam.findExampleDataFile("KittiEquivBiasedImu_metadata.txt"), encoding="utf-8") as fh:
        meta = dict(zip(fh.readline().split(), (float(v) for v in fh.readline().split())))
    t, acc, gyro = data[1:, 0], data[1:, 2:5], data[1:, 5:8]  # row 0 is 1.9 s before row 1
    iv = cut_imu_stream(t, acc, gyro, np.arange(t[0], t[0] + 120.0, 0.1))
    params = PreintegrationParams.from_gtsam_metadata(meta, GRAVITY)
    bias_hat = np.tile([0.02, -0.03, 0.05, 1e-3, -2e-3, 5e-4], (len(iv), 1))
    ours = preintegrate(iv.acc, iv.gyro, iv.dt, params, bias_hat=bias_hat, mask=iv.mask)
    p = gtsam_params(
        gtsam,
        np.eye(3) * meta["AccelerometerSigma"] ** 2,
        np.eye(3) * meta["GyroscopeSigma"] ** 2,
        np.eye(3) * meta["IntegrationSigma"] ** 2,
    )
    ref = gtsam_pims(gtsam, p, iv.acc, iv.gyro, iv.dt, iv.mask, bias_hat)
    return {"iv": iv, "params": params, "bias_hat": bias_hat, "ours": ours, "ref": ref, "stream": (t, acc, gyro)}


@pytest.fixture(scope="module")
def synthetic(gtsam):
    """Random intervals of unequal length (padded with dt = 0) with large rotations (the
    closed-form branch of the SO(3) coefficients), full anisotropic covariances, non-zero
    integration covariance and per-interval biases."""
    rng = np.random.default_rng(11)
    k, m = 6, 120
    acc = rng.normal(size=(k, m, 3)) * 3.0 + np.array([0.0, 0.0, GRAVITY])
    gyro = rng.normal(size=(k, m, 3)) * np.array([0.3, 0.5, 1.5])
    dt = rng.uniform(0.002, 0.02, size=(k, m))
    lengths = np.array([m, 1 + m // 2, m - 7, 5, m, 2])
    mask = np.arange(m)[None, :] < lengths[:, None]
    dt = np.where(mask, dt, 0.0)
    la = np.array([[0.02, 0.0, 0.0], [0.005, 0.03, 0.0], [-0.004, 0.002, 0.05]])
    lg = np.array([[1e-3, 0.0, 0.0], [2e-4, 2e-3, 0.0], [-3e-4, 1e-4, 3e-3]])
    acc_cov, gyro_cov, int_cov = la @ la.T, lg @ lg.T, np.diag([1e-6, 2e-6, 3e-6])
    params = PreintegrationParams.from_covariances(
        acc_cov, gyro_cov, int_cov, accelerometer_random_walk=1e-3, gyroscope_random_walk=1e-4
    )
    bias_hat = 0.1 * rng.normal(size=(k, 6))
    ours = preintegrate(acc, gyro, dt, params, bias_hat=bias_hat)
    p = gtsam_params(gtsam, acc_cov, gyro_cov, int_cov)
    ref = gtsam_pims(gtsam, p, acc, gyro, dt, mask, bias_hat)
    return {
        "acc": acc,
        "gyro": gyro,
        "dt": dt,
        "mask": mask,
        "params": params,
        "bias_hat": bias_hat,
        "ours": ours,
        "ref": ref,
        "gtsam_params": p,
    }


@pytest.fixture(scope="module")
def factor_case(gtsam, synthetic):
    rng = np.random.default_rng(5)
    states = random_states(gtsam, rng, synthetic["ref"], synthetic["bias_hat"])
    pose_i, vel_i, pose_j, vel_j, bias_i = states
    x = (
        jnp.asarray(np.stack([pose_row(p) for p in pose_i])),
        jnp.asarray(vel_i),
        jnp.asarray(np.stack([pose_row(p) for p in pose_j])),
        jnp.asarray(vel_j),
        jnp.asarray(bias_i),
    )
    return {"states": states, "x": x}


# --------------------------------------------------------------------------------------------
# which preintegration the wheel uses
# --------------------------------------------------------------------------------------------


@pytest.mark.gtsam
def test_wheel_uses_tangent_preintegration_and_logmap_chart(gtsam, synthetic):
    """The parity target: the wheel's default PIM is the tangent variant (bit for bit), not
    the manifold one, and fresh parameters select the Logmap factor chart."""
    s = synthetic
    args = (s["acc"][:1], s["gyro"][:1], s["dt"][:1], s["mask"][:1], s["bias_hat"][:1])
    default = gtsam_pims(gtsam, s["gtsam_params"], *args)[0]
    tangent = gtsam_pims(gtsam, s["gtsam_params"], *args, cls=gtsam.PreintegratedImuMeasurementsTangent)[0]
    manifold = gtsam_pims(gtsam, s["gtsam_params"], *args, cls=gtsam.PreintegratedImuMeasurementsManifold)[0]
    assert np.array_equal(default.preintMeasCov(), tangent.preintMeasCov())
    assert np.array_equal(default.preintegrated(), tangent.preintegrated())
    assert not np.allclose(default.preintMeasCov(), manifold.preintMeasCov(), rtol=1e-6, atol=0)
    assert gtsam.PreintegrationParams.MakeSharedU(GRAVITY).getImuFactorErrorMode() == gtsam.ImuFactorErrorMode.Logmap


# --------------------------------------------------------------------------------------------
# preintegration parity
# --------------------------------------------------------------------------------------------


@pytest.mark.gtsam
@pytest.mark.parametrize("case", ["kitti", "synthetic"])
def test_preintegration_matches_gtsam(gtsam, case, request):
    data = request.getfixturevalue(case)
    ours, ref = data["ours"], data["ref"]
    assert bool(np.all(np.asarray(ours.valid)))
    assert rel_diff(ours.delta_rotation.as_matrix(), np.stack([p.deltaRij().matrix() for p in ref])) < TOL
    assert rel_diff(ours.delta_velocity, np.stack([p.deltaVij() for p in ref])) < TOL
    assert rel_diff(ours.delta_position, np.stack([p.deltaPij() for p in ref])) < TOL
    assert rel_diff(ours.preintegrated, np.stack([p.preintegrated() for p in ref])) < TOL
    np.testing.assert_allclose(ours.delta_time, [p.deltaTij() for p in ref], rtol=1e-13)
    assert rel_diff(ours.covariance, np.stack([p.preintMeasCov() for p in ref])) < TOL
    assert rel_diff(ours.residual_covariance(), np.stack([p.residualCovariance() for p in ref])) < TOL
    jac = np.stack([gtsam_bias_jacobian(gtsam, p, b) for p, b in zip(ref, data["bias_hat"])])
    assert rel_diff(ours.bias_jacobian, jac) < 1e-9
    np.testing.assert_array_equal(ours.bias_hat, np.stack([p.biasHatVector() for p in ref]))


@pytest.mark.gtsam
def test_kitti_intervals_cover_the_keyframe_spacing(kitti):
    iv, ours = kitti["iv"], kitti["ours"]
    np.testing.assert_allclose(np.asarray(ours.delta_time), iv.t_end - iv.t_start, rtol=0, atol=1e-12)
    assert iv.num_samples > 10 * len(iv)


@pytest.mark.gtsam
def test_preintegrate_stream_equals_cut_then_preintegrate(kitti):
    t, acc, gyro = kitti["stream"]
    iv = kitti["iv"]
    kf = np.r_[iv.t_start, iv.t_end[-1]]
    again = preintegrate_stream(t, acc, gyro, kf, kitti["params"], bias_hat=kitti["bias_hat"])
    np.testing.assert_array_equal(again.preintegrated, kitti["ours"].preintegrated)
    np.testing.assert_array_equal(again.covariance, kitti["ours"].covariance)


@pytest.mark.gtsam
def test_padding_and_mask_do_not_change_an_interval(synthetic):
    """An interval padded with dt = 0 equals the same interval given with an explicit mask
    (garbage in the masked slots), and the masked slots of a batch do not leak across."""
    s = synthetic
    noisy_acc = np.where(s["mask"][..., None], s["acc"], 1e6)
    masked = preintegrate(noisy_acc, s["gyro"], s["dt"] + ~s["mask"] * 7.0, s["params"], s["bias_hat"], mask=s["mask"])
    for name in ("preintegrated", "bias_jacobian", "covariance", "delta_time"):
        np.testing.assert_array_equal(getattr(masked, name), getattr(s["ours"], name))


@pytest.mark.gtsam
def test_batch_axes(synthetic):
    """Leading batch axes: (2, 3, M) gives the results of the flat (6, M) batch."""
    s = synthetic
    out = preintegrate(
        s["acc"].reshape(2, 3, *s["acc"].shape[1:]),
        s["gyro"].reshape(2, 3, *s["gyro"].shape[1:]),
        s["dt"].reshape(2, 3, -1),
        s["params"],
        bias_hat=s["bias_hat"].reshape(2, 3, 6),
    )
    assert out.batch_shape == (2, 3)
    assert out.covariance.shape == (2, 3, 9, 9)
    np.testing.assert_allclose(out.covariance.reshape(6, 9, 9), s["ours"].covariance, rtol=1e-14, atol=0)
    np.testing.assert_allclose(out.preintegrated.reshape(6, 9), s["ours"].preintegrated, rtol=1e-14, atol=1e-17)


@pytest.mark.gtsam
def test_preintegrate_under_jit(synthetic):
    """Traced inputs skip the eager checks and report them in ``valid`` instead."""
    s = synthetic

    @jax.jit
    def run(acc, dt):
        return preintegrate(acc, s["gyro"], dt, s["params"], bias_hat=s["bias_hat"])

    out = run(s["acc"], s["dt"])
    np.testing.assert_allclose(out.preintegrated, s["ours"].preintegrated, rtol=1e-14, atol=1e-16)
    bad = run(s["acc"], _with(s["dt"], (2, 3), -0.01))
    assert np.asarray(bad.valid).tolist() == [True, True, False, True, True, True]


def _with(a: np.ndarray, idx, value) -> np.ndarray:
    b = np.array(a, copy=True)
    b[idx] = value
    return b


@pytest.mark.gtsam
def test_bias_correction_is_first_order(synthetic):
    """``bias_corrected(b)`` matches re-integrating with b up to O(|b - b_hat|^2)."""
    s = synthetic
    rng = np.random.default_rng(3)
    for step in (1e-3, 5e-4):
        delta = step * rng.normal(size=(len(s["bias_hat"]), 6))
        again = preintegrate(s["acc"], s["gyro"], s["dt"], s["params"], bias_hat=s["bias_hat"] + delta)
        predicted = s["ours"].bias_corrected(s["bias_hat"] + delta)
        err = np.abs(np.asarray(predicted - again.preintegrated)).max()
        assert err < 50.0 * step**2 * np.abs(np.asarray(s["ours"].bias_jacobian)).max()


# --------------------------------------------------------------------------------------------
# closed forms
# --------------------------------------------------------------------------------------------


def test_constant_acceleration_is_exact():
    """No rotation, constant specific force: dv = a T, dp = a T^2 / 2 exactly, and the factor
    error vanishes at the true states (gravity included)."""
    rng = np.random.default_rng(2)
    m, step = 50, 0.01
    a_body = np.array([0.4, -1.2, 9.9])
    bias = np.array([0.1, 0.2, -0.3, 0.01, -0.02, 0.03])
    acc = np.broadcast_to(a_body + bias[:3], (2, m, 3))
    gyro = np.broadcast_to(bias[3:], (2, m, 3))
    dt = np.full((2, m), step)
    params = PreintegrationParams.make_shared_u(
        GRAVITY, accelerometer_noise_density=0.01, gyroscope_noise_density=1e-3, integration_sigma=1e-4
    )
    pim = preintegrate(acc, gyro, dt, params, bias_hat=np.broadcast_to(bias, (2, 6)))
    total = m * step
    np.testing.assert_allclose(pim.delta_velocity, np.broadcast_to(a_body * total, (2, 3)), rtol=1e-13)
    np.testing.assert_allclose(pim.delta_position, np.broadcast_to(0.5 * a_body * total**2, (2, 3)), rtol=1e-13)
    np.testing.assert_allclose(pim.delta_rotation.as_matrix(), np.broadcast_to(np.eye(3), (2, 3, 3)), atol=1e-15)

    rot = SO3.exp(jnp.asarray(rng.normal(size=(2, 3))))
    p_i, v_i = rng.normal(size=(2, 3)), rng.normal(size=(2, 3))
    a_nav = np.asarray(rot.act(jnp.asarray(a_body))) + np.array([0.0, 0.0, -GRAVITY])
    v_j = v_i + a_nav * total
    p_j = p_i + v_i * total + 0.5 * a_nav * total**2
    fac = make_factor(pim, params, 2)
    x = (
        SE3.from_rotation_translation(rot, jnp.asarray(p_i)).params,
        jnp.asarray(v_i),
        SE3.from_rotation_translation(rot, jnp.asarray(p_j)).params,
        jnp.asarray(v_j),
        jnp.broadcast_to(jnp.asarray(bias), (2, 6)),
    )
    np.testing.assert_allclose(fac.evaluate(x), np.zeros((2, 9)), atol=1e-12)


def test_constant_twist_rotation_exact_translation_first_order():
    """Constant body rate w and constant body velocity u (helix, gravity-free): the measured
    specific force is w x u. The tangent update keeps theta = w t exactly (w is the axis of
    Jr^-1(w t)), so dR = Exp(w T); dv = v_j - v_i and dp = p_j - p_i - v_i T (frame i)
    converge to (Exp(w T) - I) u and (Jl(w T) - I) u T with the zero-order hold's first-order
    error. Two step sizes share one padded batch."""
    w = np.array([0.1, -0.2, 0.9])
    u = np.array([2.0, 0.3, -0.1])
    total, m = 1.0, 2000
    steps = np.array([2 * total / m, total / m])
    counts = (total / steps).round().astype(int)
    mask = np.arange(m)[None, :] < counts[:, None]
    dt = np.where(mask, steps[:, None], 0.0)
    acc = np.broadcast_to(np.cross(w, u), (2, m, 3))
    gyro = np.broadcast_to(w, (2, m, 3))
    params = PreintegrationParams.create(0.01, 1e-3, gravity=(0.0, 0.0, 0.0))
    pim = preintegrate(acc, gyro, dt, params)
    rot_t = SO3.exp(jnp.asarray(w * total))
    np.testing.assert_allclose(pim.rotation_vector, np.broadcast_to(w * total, (2, 3)), rtol=1e-13)
    np.testing.assert_allclose(
        pim.delta_rotation.as_matrix(), np.broadcast_to(rot_t.as_matrix(), (2, 3, 3)), atol=1e-14
    )
    dv_true = np.asarray(rot_t.act(jnp.asarray(u))) - u
    dp_true = np.asarray(SO3.jl(jnp.asarray(w * total)) @ jnp.asarray(u)) * total - u * total  # minus v_i T
    err_v = np.linalg.norm(np.asarray(pim.delta_velocity) - dv_true, axis=1)
    err_p = np.linalg.norm(np.asarray(pim.delta_position) - dp_true, axis=1)
    assert err_v[1] < 2e-3 * np.linalg.norm(u) and err_p[1] < 2e-3 * np.linalg.norm(u)
    np.testing.assert_allclose(err_v[0] / err_v[1], 2.0, rtol=0.01)  # first order in dt
    np.testing.assert_allclose(err_p[0] / err_p[1], 2.0, rtol=0.01)


# --------------------------------------------------------------------------------------------
# the factor
# --------------------------------------------------------------------------------------------


@pytest.mark.gtsam
@pytest.mark.parametrize("mode", ["logmap", "component_wise"])
def test_imu_factor_error_matches_gtsam(gtsam, synthetic, factor_case, mode):
    s = synthetic
    pose_i, vel_i, pose_j, vel_j, bias_i = factor_case["states"]
    fac = make_factor(s["ours"], s["params"], len(pose_i), error_mode=mode)
    err = np.asarray(fac.evaluate(factor_case["x"]))
    cost = np.asarray(factor_cost(fac, factor_case["x"]))
    gmode = {"logmap": gtsam.ImuFactorErrorMode.Logmap, "component_wise": gtsam.ImuFactorErrorMode.ComponentWise}
    s["gtsam_params"].setImuFactorErrorMode(gmode[mode])
    try:
        ref_err, ref_cost = [], []
        for k, pim in enumerate(s["ref"]):
            f = gtsam_factor(gtsam, pim)
            b = gtsam.imuBias.ConstantBias(bias_i[k, :3], bias_i[k, 3:])
            ref_err.append(f.evaluateError(pose_i[k], vel_i[k], pose_j[k], vel_j[k], b))
            ref_cost.append(f.error(gtsam_values(gtsam, pose_i[k], vel_i[k], pose_j[k], vel_j[k], b)))
    finally:
        s["gtsam_params"].setImuFactorErrorMode(gtsam.ImuFactorErrorMode.Logmap)
    assert rel_diff(err, np.stack(ref_err)) < TOL
    np.testing.assert_allclose(cost, ref_cost, rtol=TOL)
    # the noise model whitens GTSAM's residual-chart covariance: R Sigma R^T = I
    sigma = np.stack([p.residualCovariance() for p in s["ref"]])
    r = np.asarray(fac.noise.sqrt_info)
    np.testing.assert_allclose(r @ sigma @ np.swapaxes(r, -1, -2), np.broadcast_to(np.eye(9), sigma.shape), atol=1e-10)


@pytest.mark.gtsam
def test_imu_factor_information_matches_gtsam_linearization(gtsam, synthetic, factor_case):
    """Whitened Jacobians differ from GTSAM's by an orthogonal factor (another square root of
    the information), so compare ``J^T J`` and ``J^T r`` over all five blocks."""
    s = synthetic
    pose_i, vel_i, pose_j, vel_j, bias_i = factor_case["states"]
    fac = make_factor(s["ours"], s["params"], len(pose_i))
    lin = linearize(fac, factor_case["x"])
    jac = np.concatenate([np.asarray(j) for j in lin.jacobians], axis=2)
    res = np.asarray(lin.residual)
    for k, pim in enumerate(s["ref"]):
        b = gtsam.imuBias.ConstantBias(bias_i[k, :3], bias_i[k, 3:])
        a_mat, b_vec = (
            gtsam_factor(gtsam, pim)
            .linearize(gtsam_values(gtsam, pose_i[k], vel_i[k], pose_j[k], vel_j[k], b))
            .jacobian()
        )
        assert rel_diff((jac[k].T @ jac[k])[None], (a_mat.T @ a_mat)[None]) < 1e-8
        assert rel_diff((jac[k].T @ res[k])[None], (-a_mat.T @ b_vec)[None]) < 1e-8


@pytest.mark.gtsam
def test_imu_factor_jacobians_autodiff_vs_central_differences_and_jacrev(synthetic, factor_case):
    s = synthetic
    n = len(s["ref"])
    fac = make_factor(s["ours"], s["params"], n)
    x = factor_case["x"]
    auto = autodiff_jacobians(fac, x)
    types = fac.variable_types()
    evaluate = jax.jit(fac.evaluate)
    h = 1e-6
    for slot, vtype in enumerate(types):
        num = np.zeros((n, 9, vtype.tangent_dim))
        for d in range(vtype.tangent_dim):
            delta = np.zeros((n, vtype.tangent_dim))
            delta[:, d] = h
            plus = list(x)
            minus = list(x)
            plus[slot] = vtype.retract(x[slot], jnp.asarray(delta))
            minus[slot] = vtype.retract(x[slot], jnp.asarray(-delta))
            num[:, :, d] = (np.asarray(evaluate(tuple(plus))) - np.asarray(evaluate(tuple(minus)))) / (2 * h)
        scale = np.abs(num).max()
        assert np.abs(np.asarray(auto[slot]) - num).max() < 1e-6 * max(scale, 1.0), vtype.__name__

    # jacfwd (autodiff_jacobians) == jacrev on the same manifold perturbation
    def one(k, *deltas):
        moved = tuple(t.retract(xi[k : k + 1], dd[None]) for t, xi, dd in zip(types, x, deltas))
        sub = jax.tree_util.tree_map(lambda leaf: leaf[k : k + 1] if jnp.ndim(leaf) >= 1 else leaf, fac)
        return sub.evaluate(moved)[0]

    zeros = tuple(jnp.zeros(t.tangent_dim) for t in types)
    rev = jax.jacrev(lambda *d: one(0, *d), argnums=tuple(range(5)))(*zeros)
    for slot in range(5):
        np.testing.assert_allclose(rev[slot], auto[slot][0], rtol=1e-10, atol=1e-12)


@pytest.mark.gtsam
def test_bias_random_walk_factor_matches_gtsam_between(gtsam):
    rng = np.random.default_rng(9)
    n = 4
    params = PreintegrationParams.create(0.01, 1e-3, accelerometer_random_walk=2e-3, gyroscope_random_walk=3e-5)
    dts = rng.uniform(0.05, 0.5, size=n)
    b_i, b_j = 0.1 * rng.normal(size=(n, 6)), 0.1 * rng.normal(size=(n, 6))
    fac = BiasRandomWalkFactor.create(BiasVar(np.arange(n)), BiasVar(np.arange(n) + n), dts, params)
    x = (jnp.asarray(b_i), jnp.asarray(b_j))
    cost = np.asarray(factor_cost(fac, x))
    key = gtsam.symbol_shorthand.B
    for k in range(n):
        sig = np.r_[np.full(3, 2e-3), np.full(3, 3e-5)] * np.sqrt(dts[k])
        f = gtsam.BetweenFactorConstantBias(
            key(0), key(1), gtsam.imuBias.ConstantBias(), gtsam.noiseModel.Diagonal.Sigmas(sig)
        )
        vals = gtsam.Values()
        vals.insert(key(0), gtsam.imuBias.ConstantBias(b_i[k, :3], b_i[k, 3:]))
        vals.insert(key(1), gtsam.imuBias.ConstantBias(b_j[k, :3], b_j[k, 3:]))
        np.testing.assert_allclose(fac.evaluate(x)[k], f.unwhitenedError(vals), rtol=1e-14, atol=1e-16)
        np.testing.assert_allclose(cost[k], f.error(vals), rtol=1e-12)
    for analytic, auto in zip(fac.jacobians(*x), autodiff_jacobians(fac, x)):
        np.testing.assert_array_equal(analytic, auto)


# --------------------------------------------------------------------------------------------
# cutting a stream
# --------------------------------------------------------------------------------------------


def test_cut_imu_stream_splits_the_boundary_sample():
    t = np.array([0.0, 0.1, 0.2, 0.3, 0.4, 0.5])
    acc = np.arange(18.0).reshape(6, 3)
    gyro = -acc
    iv = cut_imu_stream(t, acc, gyro, [0.05, 0.2, 0.45])
    # [0.05, 0.2]: sample 0 held 0.05..0.1, sample 1 0.1..0.2; [0.2, 0.45]: samples 2, 3, 4 (cut at 0.45)
    np.testing.assert_array_equal(iv.index, [[0, 1, -1], [2, 3, 4]])
    np.testing.assert_allclose(iv.dt, [[0.05, 0.1, 0.0], [0.1, 0.1, 0.05]], atol=1e-15)
    np.testing.assert_array_equal(iv.acc[1], acc[2:5])
    np.testing.assert_array_equal(iv.gyro[0, :2], gyro[:2])
    np.testing.assert_allclose(iv.dt.sum(axis=1), [0.15, 0.25], atol=1e-15)
    assert iv.num_samples == 5


def test_cut_imu_stream_bad_input():
    t = np.linspace(0.0, 1.0, 11)
    a = np.zeros((11, 3))
    with pytest.raises(ValueError, match="acc and gyro must have shape"):
        cut_imu_stream(t, a[:-1], a, [0.0, 0.5])
    with pytest.raises(ValueError, match="strictly increasing"):
        cut_imu_stream(t[::-1], a, a, [0.0, 0.5])
    with pytest.raises(ValueError, match="inside the stream"):
        cut_imu_stream(t, a, a, [0.0, 1.5])
    with pytest.raises(ValueError, match="keyframe_times"):
        cut_imu_stream(t, a, a, [0.5, 0.2])
    with pytest.raises(ValueError, match="max_samples"):
        cut_imu_stream(t, a, a, [0.0, 0.9], max_samples=3)


# --------------------------------------------------------------------------------------------
# bad input
# --------------------------------------------------------------------------------------------


def test_preintegrate_rejects_bad_shapes_and_values():
    params = PreintegrationParams.create(0.01, 1e-3)
    acc = np.zeros((2, 4, 3))
    dt = np.full((2, 4), 0.01)
    with pytest.raises(ValueError, match=r"acc must have shape \(\*batch, M, 3\)"):
        preintegrate(np.zeros((2, 4, 2)), acc, dt, params)
    with pytest.raises(ValueError, match="gyro must have the shape of acc"):
        preintegrate(acc, np.zeros((2, 5, 3)), dt, params)
    with pytest.raises(ValueError, match=r"dt must have shape \(\*batch, M\)"):
        preintegrate(acc, acc, dt[:, :3], params)
    with pytest.raises(ValueError, match="mask must have the shape of dt"):
        preintegrate(acc, acc, dt, params, mask=np.ones((2, 3), bool))
    with pytest.raises(ValueError, match="mask must be boolean"):
        preintegrate(acc, acc, dt, params, mask=np.ones((2, 4)))
    with pytest.raises(ValueError, match="bias_hat must have shape"):
        preintegrate(acc, acc, dt, params, bias_hat=np.zeros(5))
    with pytest.raises(ValueError, match="no samples"):
        preintegrate(np.zeros((2, 0, 3)), np.zeros((2, 0, 3)), np.zeros((2, 0)), params)
    for bad, msg in ((-0.01, "finite and >= 0"), (np.nan, "finite and >= 0"), (np.inf, "finite and >= 0")):
        with pytest.raises(ValueError, match=msg):
            preintegrate(acc, acc, _with(dt, (1, 2), bad), params)
    with pytest.raises(ValueError, match=r"dt must be > 0 for every sample the mask uses; dt\[0, 1\]"):
        preintegrate(acc, acc, _with(dt, (0, 1), 0.0), params, mask=np.ones((2, 4), bool))
    with pytest.raises(ValueError, match=r"acc\[1, 3\] is not finite"):
        preintegrate(_with(acc, (1, 3, 0), np.nan), acc, dt, params)
    with pytest.raises(ValueError, match=r"gyro\[0, 0\] is not finite"):
        preintegrate(acc, _with(acc, (0, 0, 2), np.inf), dt, params)


def test_params_from_gtsam_metadata():
    """GTSAM's example metadata names map onto the densities one by one (Z-up gravity); a
    missing name is a ConfigError naming it."""
    meta = {
        "AccelerometerSigma": 0.01,
        "GyroscopeSigma": 2e-4,
        "IntegrationSigma": 1e-3,
        "AccelerometerBiasSigma": 3e-4,
        "GyroscopeBiasSigma": 4e-5,
    }
    got = PreintegrationParams.from_gtsam_metadata(meta, 9.8)
    want = PreintegrationParams.make_shared_u(
        9.8,
        accelerometer_noise_density=0.01,
        gyroscope_noise_density=2e-4,
        integration_sigma=1e-3,
        accelerometer_random_walk=3e-4,
        gyroscope_random_walk=4e-5,
    )
    for a, b in zip(jax.tree_util.tree_leaves(got), jax.tree_util.tree_leaves(want)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    with pytest.raises(ConfigError, match="IntegrationSigma"):
        PreintegrationParams.from_gtsam_metadata({k: v for k, v in meta.items() if k != "IntegrationSigma"})


def test_params_and_factor_constructors_reject_bad_input():
    with pytest.raises(ConfigError, match="accelerometer_noise_density"):
        PreintegrationParams.create(-0.01, 1e-3)
    with pytest.raises(ConfigError, match="gyroscope_noise_density"):
        PreintegrationParams.create(0.01, [1e-3, np.nan, 1e-3])
    with pytest.raises(ConfigError, match="gravity"):
        PreintegrationParams.create(0.01, 1e-3, gravity=(0.0, -9.81))
    with pytest.raises(ConfigError, match="positive semi-definite"):
        PreintegrationParams.from_covariances(-np.eye(3), np.eye(3))

    params = PreintegrationParams.create(0.01, 1e-3)
    acc = np.zeros((2, 3, 3))
    dt = np.full((2, 3), 0.01)
    pim = preintegrate(acc, acc, dt, params)
    ids = np.arange(2)
    with pytest.raises(TypeError, match="vel_i must be a VelocityVar"):
        ImuFactor.create(
            Pose3Var(ids), Pose3Var(ids), Pose3Var(ids + 2), VelocityVar(ids + 2), BiasVar(ids), pim, params
        )
    with pytest.raises(ValueError, match="pim holds 2 intervals"):
        ImuFactor.create(
            Pose3Var(ids[:1]),
            VelocityVar(ids[:1]),
            Pose3Var(ids[:1] + 2),
            VelocityVar(ids[:1] + 2),
            BiasVar(ids[:1]),
            pim,
            params,
        )
    with pytest.raises(ValueError, match="error_mode"):
        make_factor(pim, params, 2, error_mode="euler")
    one_sample = preintegrate(acc[:, :1], acc[:, :1], dt[:, :1], params)  # rank-deficient covariance
    with pytest.raises(ValueError, match="singular"):
        make_factor(one_sample, params, 2)
    invalid = jax.jit(lambda d: preintegrate(acc, acc, d, params))(_with(dt, (1, 1), -1.0))
    with pytest.raises(ValueError, match=r"intervals \[1\] were preintegrated from invalid samples"):
        make_factor(invalid, params, 2)
    with pytest.raises(ValueError, match="delta_time > 0"):
        BiasRandomWalkFactor.create(BiasVar(ids), BiasVar(ids + 2), 0.0, params)


def test_isotropic_fast_path_equals_general_path() -> None:
    """Scalar noise densities take a kernel that skips the products with Qa and Qg; it must
    give the general kernel's result."""
    from jaxslam.factors import _preintegration as _imu

    rng = np.random.default_rng(11)
    k, m = 40, 7
    acc = rng.normal(size=(k, m, 3)) + np.array([0.0, 0.0, 9.81])
    gyro = 0.5 * rng.normal(size=(k, m, 3))
    dt = np.full((k, m), 0.01)
    params = PreintegrationParams.make_shared_u(
        9.81, accelerometer_noise_density=0.02, gyroscope_noise_density=0.003, integration_sigma=1e-3
    )
    assert _imu._isotropic(params)
    one = jnp.ones(())
    fast = _imu._preintegrate_jit(acc, gyro, dt, None, np.zeros(6), params, one, True)
    general = _imu._preintegrate_jit(acc, gyro, dt, None, np.zeros(6), params, one, False)
    for a, b in zip(jax.tree_util.tree_leaves(fast), jax.tree_util.tree_leaves(general)):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-13, atol=1e-18)


@pytest.mark.gtsam
def test_parallel_parts_equal_the_single_call(monkeypatch, synthetic, kitti):
    """Large concrete batches run as equal parts on a thread pool; the result must be the
    single call's to the last bit or so (the parts' smaller blocks put a lane in a vector
    loop's remainder differently: 2 of 97,119 KITTI numbers differ, by 1 ulp), for any
    batch shape, with or without a mask, and a bad sample must still be found and named."""
    from jaxslam.factors import _preintegration as _imu

    monkeypatch.setattr(_imu, "PARALLEL_MIN_INTERVALS", 2)
    calls = []
    parts = _imu._preintegrate_parts
    monkeypatch.setattr(_imu, "_preintegrate_parts", lambda *a: calls.append(a[-1]) or parts(*a))
    monkeypatch.setattr(_imu, "workers", lambda: 4)  # 4 parts: 6 intervals need padding
    s = synthetic
    shape = (3, 2, *s["acc"].shape[1:])
    got = preintegrate(
        s["acc"].reshape(shape),
        s["gyro"].reshape(shape),
        s["dt"].reshape(shape[:-1]),
        s["params"],
        bias_hat=s["bias_hat"].reshape(3, 2, 6),
    )
    iv = kitti["iv"]
    got_kitti = preintegrate(iv.acc, iv.gyro, iv.dt, kitti["params"], bias_hat=kitti["bias_hat"], mask=iv.mask)
    assert calls == [6, len(iv)]
    one = preintegrate(s["acc"], s["gyro"], s["dt"], s["params"], bias_hat=s["bias_hat"], parallel=False)
    assert calls == [6, len(iv)]  # parallel=False: one call on this thread
    for a, b in zip(jax.tree_util.tree_leaves(one), jax.tree_util.tree_leaves(s["ours"])):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    assert got.batch_shape == (3, 2)
    for a, b in zip(jax.tree_util.tree_leaves(got), jax.tree_util.tree_leaves(s["ours"])):
        np.testing.assert_allclose(np.asarray(a).reshape(np.shape(b)), np.asarray(b), rtol=1e-15, atol=0)
    for a, b in zip(jax.tree_util.tree_leaves(got_kitti), jax.tree_util.tree_leaves(kitti["ours"])):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-15, atol=0)
    with pytest.raises(ValueError, match=r"acc\[4, 3\] is not finite"):
        preintegrate(_with(s["acc"], (4, 3, 1), np.nan), s["gyro"], s["dt"], s["params"])

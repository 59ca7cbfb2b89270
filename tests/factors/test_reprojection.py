"""ReprojectionFactor: GTSAM parity, Jacobians three ways, batch shapes, cheirality.

Golden values come from ``gtsam.GenericProjectionFactorCal3_S2`` at test time: residual
(``unwhitenedError``), cost (``error()``) and whitened Jacobians (``linearize()``), with and
without a ``body_P_sensor``, and for points behind the camera (where GTSAM returns
``(2 fx, 2 fx)``).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxslam.core import Gaussian, Point3Var, Pose2Var, Pose3Var, autodiff_jacobians, factor_cost, linearize
from jaxslam.factors import ReprojectionFactor, pinhole_project, project_pinhole
from jaxslam.lie import SE3

from ._numeric import manifold_central_difference

N = 6


def _calibrations(rng: np.random.Generator, n: int) -> np.ndarray:
    f = rng.uniform(300.0, 600.0, size=n)
    return np.stack(
        [f, f * rng.uniform(0.9, 1.1, size=n), rng.uniform(-0.5, 0.5, size=n), rng.uniform(300, 340, size=n),
         rng.uniform(220, 260, size=n)],
        axis=-1,
    )  # fmt: skip


def _scene(rng: np.random.Generator, n: int, with_body: bool) -> dict:
    """Random cameras and points in front of them (depth 2..8), noisy pixel measurements."""
    poses = SE3.exp(jnp.asarray(rng.normal(size=(n, 6))))
    body = SE3.exp(jnp.asarray(rng.normal(size=(n, 6)) * 0.2)) if with_body else SE3.identity((n,))
    p_cam = np.concatenate([rng.uniform(-2, 2, size=(n, 2)), rng.uniform(2, 8, size=(n, 1))], axis=-1)
    points = np.asarray((poses @ body).act(jnp.asarray(p_cam)))
    calib = _calibrations(rng, n)
    uv, _ = project_pinhole(jnp.asarray(calib), jnp.asarray(p_cam))
    measured = np.asarray(uv) + rng.normal(size=(n, 2)) * 2.0
    sigmas = rng.uniform(0.5, 2.0, size=(n, 2))
    factor = ReprojectionFactor.create(
        Pose3Var(np.arange(n)),
        Point3Var(np.arange(n)),
        measured,
        calib,
        Gaussian.diagonal(sigmas),
        body_T_sensor=body if with_body else None,
    )
    return {
        "poses": poses,
        "body": body,
        "points": points,
        "calib": calib,
        "measured": measured,
        "sigmas": sigmas,
        "factor": factor,
        "params": (poses.params, jnp.asarray(points)),
    }


@pytest.fixture(scope="module")
def scenes():
    rng = np.random.default_rng(5)
    return {False: _scene(rng, N, False), True: _scene(rng, N, True)}


def _gtsam_pose(gtsam, params) -> object:
    params = np.asarray(params)
    return gtsam.Pose3(gtsam.Rot3.Quaternion(*params[:4]), params[4:])


def _gtsam_factors(gtsam, scene: dict, with_body: bool, points: np.ndarray | None = None):
    points = scene["points"] if points is None else points
    values = gtsam.Values()
    factors = []
    for k in range(len(points)):
        values.insert(gtsam.symbol("x", k), _gtsam_pose(gtsam, scene["poses"].params[k]))
        values.insert(gtsam.symbol("l", k), points[k])
        model = gtsam.noiseModel.Diagonal.Sigmas(scene["sigmas"][k])
        args = [scene["measured"][k], model, gtsam.symbol("x", k), gtsam.symbol("l", k)]
        args.append(gtsam.Cal3_S2(*scene["calib"][k]))
        if with_body:
            args += [False, False, _gtsam_pose(gtsam, scene["body"].params[k])]
        factors.append(gtsam.GenericProjectionFactorCal3_S2(*args))
    return factors, values


@pytest.mark.gtsam
@pytest.mark.parametrize("with_body", [False, True], ids=["camera", "body_T_sensor"])
def test_vs_gtsam(gtsam, scenes, with_body):
    scene = scenes[with_body]
    factor, params = scene["factor"], scene["params"]
    r = np.asarray(factor.evaluate(params))
    cost = np.asarray(factor_cost(factor, params))
    lin = linearize(factor, params)
    gfactors, values = _gtsam_factors(gtsam, scene, with_body)
    for k, gf in enumerate(gfactors):
        np.testing.assert_allclose(r[k], gf.unwhitenedError(values), rtol=0, atol=1e-9, err_msg=f"residual {k}")
        assert cost[k] == pytest.approx(gf.error(values), rel=1e-12), f"cost {k}"
        a, b = gf.linearize(values).jacobian()  # whitened [d/dpose (6), d/dpoint (3)]
        np.testing.assert_allclose(np.asarray(lin.jacobians[0][k]), a[:, :6], rtol=1e-9, atol=1e-9)
        np.testing.assert_allclose(np.asarray(lin.jacobians[1][k]), a[:, 6:], rtol=1e-9, atol=1e-9)
        np.testing.assert_allclose(np.asarray(lin.residual[k]), -np.ravel(b), rtol=1e-12, atol=1e-9)


@pytest.mark.parametrize("with_body", [False, True], ids=["camera", "body_T_sensor"])
def test_jacobians_three_ways(scenes, with_body, fast_jit):
    scene = scenes[with_body]
    factor, params = scene["factor"], scene["params"]
    analytic = factor.jacobians(*factor.wrap_values(params))
    auto = fast_jit(autodiff_jacobians)(factor, params)
    for slot, (ja, jd) in enumerate(zip(analytic, auto)):
        assert ja.shape == jd.shape == (N, 2, (6, 3)[slot])
        np.testing.assert_allclose(np.asarray(ja), np.asarray(jd), rtol=1e-10, atol=1e-9, err_msg=f"slot {slot}")
        cd = manifold_central_difference(factor, params, slot)
        np.testing.assert_allclose(np.asarray(jd), cd, rtol=1e-6, atol=1e-5, err_msg=f"slot {slot}")


def test_batch_shapes(scenes):
    """N constraints at once == one at a time; a shared calibration / measurement (5,) /
    (2,) broadcasts; pinhole_project broadcasts one camera over many points."""
    scene = scenes[True]
    factor, params = scene["factor"], scene["params"]
    r_all = np.asarray(factor.evaluate(params))
    k = 3
    single = ReprojectionFactor.create(
        Pose3Var(np.array([0])),
        Point3Var(np.array([0])),
        scene["measured"][k],
        scene["calib"][k],
        Gaussian.diagonal(scene["sigmas"][k]),
        body_T_sensor=scene["body"][k],
    )
    assert single.measured.shape == (1, 2) and single.calibration.shape == (1, 5)
    r_one = np.asarray(single.evaluate((params[0][k : k + 1], params[1][k : k + 1])))
    np.testing.assert_allclose(r_one[0], r_all[k], rtol=0, atol=1e-12)

    shared = ReprojectionFactor.create(
        Pose3Var(np.arange(N)), Point3Var(np.arange(N)), np.zeros(2), scene["calib"][0], Gaussian.isotropic(2, 1.0)
    )
    assert shared.calibration.shape == (N, 5) and shared.noise.sqrt_info.shape == (N, 2, 2)
    cam = scene["poses"][0] @ scene["body"][0]
    uv, front = pinhole_project(cam, jnp.asarray(scene["points"]), jnp.asarray(scene["calib"][0]))
    assert uv.shape == (N, 2) and front.shape == (N,)
    # The shared factor with identity body frame reproduces pinhole_project from camera 0.
    cam_params = jnp.broadcast_to(cam.params, (N, 7))
    np.testing.assert_allclose(
        np.asarray(shared.evaluate((cam_params, params[1])))[front], np.asarray(uv)[front], atol=1e-12
    )
    # A (2, 3) batch of points through one camera.
    uv23, front23 = pinhole_project(cam, jnp.asarray(scene["points"]).reshape(2, 3, 3), jnp.asarray(scene["calib"][0]))
    assert uv23.shape == (2, 3, 2) and front23.shape == (2, 3)
    np.testing.assert_allclose(np.asarray(uv23).reshape(N, 2), np.asarray(uv), atol=1e-12)


# Depths in the camera frame for the cheirality test: in front, far behind, exactly at the
# centre plane, the camera centre itself, tinier than min_depth, just above it.
DEPTHS = np.array([4.0, -3.0, 0.0, 0.0, 1e-300, 1e-9, 2e-8])
LATERAL = np.array([[0.5, -0.2], [0.5, -0.2], [0.3, 0.1], [0.0, 0.0], [0.2, 0.2], [1.0, 1.0], [1e-8, 0.0]])


@pytest.fixture(scope="module")
def cheirality():
    rng = np.random.default_rng(8)
    n = len(DEPTHS)
    # Random cameras for the first two rows; identity cameras for the rest, so that the
    # exact depths (0, 1e-300, ...) survive the world -> camera transform bit for bit.
    tangents = np.zeros((n, 6))
    tangents[:2] = rng.normal(size=(2, 6))
    poses = SE3.exp(jnp.asarray(tangents))
    p_cam = np.concatenate([LATERAL, DEPTHS[:, None]], axis=-1)
    points = np.asarray(poses.act(jnp.asarray(p_cam)))
    calib = _calibrations(rng, n)
    factor = ReprojectionFactor.create(
        Pose3Var(np.arange(n)), Point3Var(np.arange(n)), np.full((n, 2), 100.0), calib, Gaussian.isotropic(2, 1.0)
    )
    return {"poses": poses, "points": points, "calib": calib, "factor": factor, "params": (poses.params, points)}


def test_cheirality_is_finite_and_constant(cheirality, fast_jit):
    factor = cheirality["factor"]
    pose, point = factor.wrap_values((cheirality["params"][0], jnp.asarray(cheirality["params"][1])))
    params = (pose.params, point)
    depth = np.asarray(pose.inverse().act(point))[:, 2]
    np.testing.assert_array_equal(depth[2:], DEPTHS[2:])
    front = np.asarray(factor.in_front(pose, point))
    np.testing.assert_array_equal(front, depth > 1e-8)
    assert front[0] and front[-1] and not front[1]
    r = np.asarray(factor.evaluate(params))
    assert np.all(np.isfinite(r))
    behind = ~front
    fx2 = 2.0 * cheirality["calib"][:, 0]
    np.testing.assert_array_equal(r[behind], np.stack([fx2, fx2], -1)[behind])
    # Jacobians: zero behind, finite everywhere, analytic == autodiff.
    analytic = factor.jacobians(pose, point)
    auto = fast_jit(autodiff_jacobians)(factor, params)
    for ja, jd in zip(analytic, auto):
        assert np.all(np.isfinite(np.asarray(ja))) and np.all(np.isfinite(np.asarray(jd)))
        np.testing.assert_array_equal(np.asarray(ja)[behind], 0.0)
        np.testing.assert_array_equal(np.asarray(jd)[behind], 0.0)
        np.testing.assert_allclose(np.asarray(ja)[front], np.asarray(jd)[front], rtol=1e-9, atol=1e-9)
    # Gradients of the total cost w.r.t. the raw parameters are finite (no NaN from 1/Z).
    grads = fast_jit(jax.grad(lambda f, p: jnp.sum(factor_cost(f, p)), argnums=1))(factor, params)
    assert all(np.all(np.isfinite(np.asarray(g))) for g in grads)
    cost = np.asarray(factor_cost(factor, params))
    assert np.all(np.isfinite(cost))


@pytest.mark.gtsam
def test_cheirality_matches_gtsam_behind_camera(gtsam, cheirality):
    """For Z <= 0 GTSAM returns (2 fx, 2 fx) too (it catches its CheiralityException)."""
    factor = cheirality["factor"]
    pose, point = factor.wrap_values((cheirality["params"][0], jnp.asarray(cheirality["params"][1])))
    depth = np.asarray(pose.inverse().act(point))[:, 2]
    r = np.asarray(factor.evaluate((pose.params, point)))
    scene = {
        "poses": pose,
        "measured": np.asarray(factor.measured),
        "sigmas": np.ones((len(depth), 2)),
        "calib": cheirality["calib"],
    }
    gfactors, values = _gtsam_factors(gtsam, scene, False, points=np.asarray(point))
    checked = 0
    for k, gf in enumerate(gfactors):
        if depth[k] <= 0 or depth[k] > 1e-6:  # GTSAM has no min_depth: skip 0 < Z <= 1e-6
            np.testing.assert_allclose(r[k], gf.unwhitenedError(values), rtol=1e-9, atol=1e-9, err_msg=f"{k}")
            checked += 1
    assert checked >= 3


def test_bad_input_raises():
    calib = np.array([500.0, 500.0, 0.0, 320.0, 240.0])
    noise = Gaussian.isotropic(2, 1.0)
    two_poses, two_points = Pose3Var(np.array([0, 1])), Point3Var(np.array([0, 1]))
    with pytest.raises(TypeError, match=r"needs \(Pose3Var, Point3Var\)"):
        ReprojectionFactor.create(Pose2Var(np.array([0])), Point3Var(np.array([0])), np.zeros(2), calib, noise)
    with pytest.raises(ValueError, match="2 pose ids but 3 point ids"):
        ReprojectionFactor.create(two_poses, Point3Var(np.arange(3)), np.zeros(2), calib, noise)
    with pytest.raises(ValueError, match="noise model has dimension 3, the residual has 2"):
        ReprojectionFactor.create(two_poses, two_points, np.zeros(2), calib, Gaussian.isotropic(3, 1.0))
    with pytest.raises(ValueError, match=r"calibration .* must have shape \(5,\) or \(2, 5\)"):
        ReprojectionFactor.create(two_poses, two_points, np.zeros(2), calib[:4], noise)
    with pytest.raises(ValueError, match=r"measured .* got \(3, 2\)"):
        ReprojectionFactor.create(two_poses, two_points, np.zeros((3, 2)), calib, noise)
    with pytest.raises(ValueError, match="focal lengths"):
        ReprojectionFactor.create(two_poses, two_points, np.zeros(2), calib * np.array([1, -1, 1, 1, 1]), noise)

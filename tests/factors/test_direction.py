"""The scale-free relative-pose factor (rotation + translation direction, SPEC §3.3): blind to
the length of the camera's translation, not to its direction or the rotation; finite when the
bodies coincide; autodiff Jacobians equal central differences on the manifold."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxslam.core import Gaussian, Pose3Var
from jaxslam.factors import RelativeDirectionFactor
from jaxslam.lie import SE3, host

TBC = np.array([0.5, -0.5, 0.5, -0.5, 0.2, 0.0, 0.3])


def _se3(T: np.ndarray) -> SE3:
    return SE3(jnp.asarray(host.matrix_to_params(T)[None]))


def _factor(Tc: np.ndarray) -> RelativeDirectionFactor:
    ids = (Pose3Var(np.array([0])), Pose3Var(np.array([1])))
    return RelativeDirectionFactor.create(*ids, Tc[:3, :3], Tc[:3, 3], TBC, Gaussian.isotropic(5, 0.01))


def _body_j(Xi: np.ndarray, Tc: np.ndarray) -> np.ndarray:
    Tbc = host.params_to_matrix(TBC)
    return Xi @ Tbc @ Tc @ host.inverse(Tbc)


@pytest.mark.parametrize("scale", [0.2, 1.0, 7.5])
def test_zero_for_any_length_of_the_measured_direction(scale: float) -> None:
    Xi = host.se3_exp(np.array([0.01, 0.02, 0.1, 1.0, 2.0, 0.3]))
    Tc = host.se3_exp(np.array([0.01, -0.02, 0.03, 0.1, 0.05, 0.4]))
    f = _factor(Tc)
    Tc_s = Tc.copy()
    Tc_s[:3, 3] *= scale
    r = np.asarray(f.residual(_se3(Xi), _se3(_body_j(Xi, Tc_s))))
    np.testing.assert_allclose(r, 0.0, atol=1e-6 * max(1.0, 1 / scale))


def test_sees_direction_and_rotation() -> None:
    Xi = np.eye(4)
    Tc = host.se3_exp(np.array([0.0, 0.0, 0.0, 0.0, 0.0, 0.3]))
    f = _factor(Tc)
    side = host.se3_exp(np.array([0.0, 0.0, 0.0, 0.03, 0.0, 0.3]))  # 0.1 rad off sideways
    r = np.asarray(f.residual(_se3(Xi), _se3(_body_j(Xi, side))))[0]
    assert np.linalg.norm(r[3:]) == pytest.approx(np.sin(np.arctan(0.1)), rel=1e-3) and np.allclose(
        r[:3], 0, atol=1e-12
    )
    turned = Tc @ host.se3_exp(np.array([0.0, 0.02, 0.0, 0.0, 0.0, 0.0]))
    r = np.asarray(f.residual(_se3(Xi), _se3(_body_j(Xi, turned))))[0]
    assert np.linalg.norm(r[:3]) == pytest.approx(0.02, rel=1e-6)


def test_finite_when_the_bodies_coincide_and_jacobians_match_differences() -> None:
    Tc = host.se3_exp(np.array([0.0, 0.0, 0.0, 0.0, 0.0, 0.3]))
    f = _factor(Tc)
    X = host.se3_exp(np.array([0.1, -0.2, 0.3, 1.0, 2.0, 3.0]))

    def res(d):
        xi = _se3(X) @ SE3.exp(d[:6][None])
        xj = _se3(X) @ SE3.exp(d[6:][None])
        return f.residual(xi, xj)[0]

    J = np.asarray(jax.jacfwd(res)(jnp.zeros(12)))
    assert np.all(np.isfinite(J)) and np.all(np.isfinite(np.asarray(res(jnp.zeros(12)))))
    Xj = _body_j(X, Tc)

    def res2(d):
        xi = _se3(X) @ SE3.exp(d[:6][None])
        xj = _se3(Xj) @ SE3.exp(d[6:][None])
        return f.residual(xi, xj)[0]

    J = np.asarray(jax.jacfwd(res2)(jnp.zeros(12)))
    h = 1e-6
    num = np.stack(
        [(np.asarray(res2(jnp.eye(12)[k] * h)) - np.asarray(res2(-jnp.eye(12)[k] * h))) / (2 * h) for k in range(12)], 1
    )
    np.testing.assert_allclose(J, num, atol=1e-6)

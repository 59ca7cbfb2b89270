"""Gaussian noise models, one representation: a batch of square-root information matrices.

``sqrt_info`` has shape ``(N, r, r)`` and is upper triangular with ``R^T R = Sigma^-1`` (the
same ``R`` GTSAM's ``noiseModel.Gaussian`` holds). Whitening is ``R @ r``. Diagonal and
isotropic models are the same object with a diagonal ``R``; the sigmas stay differentiable
(learnable noise weights build the model inside the differentiated function).
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
from jax import Array

from ..lie import mm, mv


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Gaussian:
    """Square-root information ``R`` (``(N, r, r)``): whitened residual ``R @ r``."""

    sqrt_info: Array

    @property
    def dim(self) -> int:
        return int(self.sqrt_info.shape[-1])

    def whiten(self, r: Array) -> Array:
        """``(N, r) -> (N, r)``."""
        return mv(self.sqrt_info, r)

    def whiten_jacobian(self, jac: Array) -> Array:
        """``(N, r, t) -> (N, r, t)``."""
        return mm(self.sqrt_info, jac)

    def covariance(self) -> Array:
        info = jnp.einsum("nki,nkj->nij", self.sqrt_info, self.sqrt_info)
        return jnp.linalg.inv(info)

    def broadcast(self, n: int) -> Gaussian:
        """Repeat a single model (leading axis 1) to ``n`` constraints."""
        return Gaussian(jnp.broadcast_to(self.sqrt_info, (n, self.dim, self.dim)))

    def __len__(self) -> int:
        return int(self.sqrt_info.shape[0])

    # --- constructors (GTSAM's vocabulary) ---------------------------------------------
    @staticmethod
    def isotropic(dim: int, sigma: float | Array, n: int = 1) -> Gaussian:
        """From one sigma (repeated ``n`` times) or ``(N,)`` sigmas, one per constraint."""
        sigma = jnp.asarray(sigma, dtype=jnp.float64)
        r = jnp.broadcast_to(jnp.eye(dim), (*sigma.shape, dim, dim)) / sigma[..., None, None]
        r = r.reshape(-1, dim, dim)
        if r.shape[0] == 1:
            r = jnp.broadcast_to(r, (n, dim, dim))
        return Gaussian(r)

    @staticmethod
    def diagonal(sigmas: Array, n: int | None = None) -> Gaussian:
        """From sigmas ``(r,)`` (shared, repeated ``n`` times) or ``(N, r)``."""
        sigmas = jnp.asarray(sigmas, dtype=jnp.float64)
        r = jax.vmap(jnp.diag)(1.0 / sigmas.reshape(-1, sigmas.shape[-1]))
        if n is not None:
            r = jnp.broadcast_to(r, (n, *r.shape[1:]))
        return Gaussian(r)

    @staticmethod
    def from_covariance(cov: Array, n: int | None = None) -> Gaussian:
        cov = jnp.asarray(cov, dtype=jnp.float64)
        cov = cov.reshape(-1, *cov.shape[-2:])
        return Gaussian.from_information(jnp.linalg.inv(cov), n)

    @staticmethod
    def from_information(info: Array, n: int | None = None) -> Gaussian:
        """Upper-triangular ``R`` with ``R^T R = info`` (Cholesky of the information)."""
        info = jnp.asarray(info, dtype=jnp.float64)
        info = info.reshape(-1, *info.shape[-2:])
        lower = jnp.linalg.cholesky(0.5 * (info + jnp.swapaxes(info, -1, -2)))
        r = jnp.swapaxes(lower, -1, -2)
        if n is not None:
            r = jnp.broadcast_to(r, (n, *r.shape[1:]))
        return Gaussian(r)

    @staticmethod
    def from_sqrt_information(sqrt_info: Array, n: int | None = None) -> Gaussian:
        r = jnp.asarray(sqrt_info, dtype=jnp.float64)
        r = r.reshape(-1, *r.shape[-2:])
        if n is not None:
            r = jnp.broadcast_to(r, (n, *r.shape[1:]))
        return Gaussian(r)


def information_is_valid(info: np.ndarray) -> np.ndarray:
    """Per-matrix check (numpy, for readers): finite, symmetric and positive definite."""
    info = np.asarray(info, dtype=np.float64)
    finite = np.all(np.isfinite(info), axis=(-1, -2))
    sym = np.all(np.abs(info - np.swapaxes(info, -1, -2)) <= 1e-9 * (1 + np.abs(info)), axis=(-1, -2))
    ok = finite & sym
    eig_ok = np.zeros(info.shape[:-2], dtype=bool)
    if np.any(ok):
        eig = np.linalg.eigvalsh(np.where(ok[..., None, None], info, np.eye(info.shape[-1])))
        eig_ok = eig.min(axis=-1) > 0
    return ok & eig_ok

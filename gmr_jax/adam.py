"""Adam as the S-step runs it: ``optax.adam`` operation for operation, with the bias corrections
computed before the loop (the S-step's loops and its GPU kernel share these two functions)."""

from __future__ import annotations

import jax.numpy as jnp

from gmr_jax.config import SStepConfig


def adam_corrections(cfg: SStepConfig, steps: int, dtype):
    """Adam's bias corrections (1 − b1^t, 1 − b2^t) [steps] for t = 1 … steps, computed as
    ``optax.adam`` computes them at step t."""
    count = jnp.arange(1, steps + 1, dtype=jnp.int32)
    return (1 - cfg.b1 ** count).astype(dtype), (1 - cfg.b2 ** count).astype(dtype)


def adam_update(cfg: SStepConfig, theta, mu, nu, grad, c1, c2):
    """One step of ``optax.adam(cfg.lr, cfg.b1, cfg.b2, cfg.eps)``, operation for operation, with
    its bias corrections c1, c2 (``adam_corrections``) given: θ, μ, ν, grad [n] -> (θ, μ, ν).

    Taking the corrections as inputs keeps the step counter and the powers b^t, scalar kernels
    on a GPU, out of the S-step's loop.
    """
    mu = (1 - cfg.b1) * grad + cfg.b1 * mu
    nu = (1 - cfg.b2) * grad ** 2 + cfg.b2 * nu
    update = -cfg.lr * ((mu / c1) / (jnp.sqrt(nu / c2 + 0.0) + cfg.eps))
    return (theta + update).astype(theta.dtype), mu, nu

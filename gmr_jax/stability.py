"""Local stability of a trained policy's closed loop: x' = f(x, u(x)).

The paper leaves the stability of the generated reflexes to future work. Here it is measured
locally: the Jacobian of one control step of the closed loop, J(x) = ∂f/∂x + ∂f/∂u · ∂u/∂x
[dX, dX] (the plant f differentiated through MJX, the policy's mean u through JAX), and its
spectral radius ρ(J). ρ < 1 at a state means that small perturbations of the state shrink from
one control step to the next there (the discrete-time map contracts locally, asymptotically);
ρ > 1 means some perturbation grows. Reported: ρ at the target, and along the policy's noiseless
rollouts from the robustness test's random states, the fraction of visited states where ρ < 1.

Eigenvalues of the non-symmetric Jacobians are taken on the host (numpy), which every backend
supports.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from gmr_jax import evaluate, sim, tasks
from gmr_jax.config import Config


class Stability(NamedTuple):
    """Local stability of one policy (numpy).

    Attributes:
      target_radius: ρ(J) at the target state (at rest).
      radius: [S, T] ρ(J) at every state of the rollouts from the S initial states.
      contracting: [S] fraction of each rollout's states with ρ(J) < 1.
    """

    target_radius: float
    radius: np.ndarray
    contracting: np.ndarray


def closed_loop_step(cfg: Config, params):
    """The closed loop's control step ``x [dX] -> x' [dX]`` with the policy's mean action,
    the plant in MJX (differentiable)."""
    s = sim.make_sim(dataclasses.replace(cfg.sim, backend="mjx"))
    policy = evaluate._global_policy(cfg)
    return lambda x: sim.step(s, x, policy.mean(params, x))


def closed_loop_jacobian(cfg: Config, params, x: jax.Array) -> jax.Array:
    """J(x) = d x' / d x of :func:`closed_loop_step`, [..., dX] -> [..., dX, dX] (forward mode)."""
    jac = jax.jacfwd(closed_loop_step(cfg, params))
    flat = x.reshape(-1, x.shape[-1])
    return jax.vmap(jac)(flat).reshape(x.shape + (x.shape[-1],))


def spectral_radius(J) -> np.ndarray:
    """max |eigenvalue| of each [..., n, n] matrix (numpy, on the host)."""
    return np.abs(np.linalg.eigvals(np.asarray(J, np.float64))).max(axis=-1)


@functools.partial(jax.jit, static_argnums=0)
def _jacobians(cfg: Config, params, x0: jax.Array):
    """(J along the noiseless rollouts from x0 [S, dX]: [S, T, dX, dX], J at the target [dX, dX])."""
    X = evaluate.execute_policy(cfg, params, x0).X
    target = tasks.target_state(cfg.task, X.dtype)
    return closed_loop_jacobian(cfg, params, X), closed_loop_jacobian(cfg, params, target)


def stability(cfg: Config, params, x0: jax.Array | None = None) -> Stability:
    """ρ of the closed loop at the target and along the policy's noiseless rollouts from x0
    [S, dX] (default: the robustness test's random states). One jitted program per
    configuration; ``params`` of one policy."""
    dtype = jax.tree_util.tree_leaves(params)[0].dtype
    if x0 is None:
        x0 = evaluate.robustness_states(cfg, dtype=dtype)
    J, J_target = _jacobians(cfg, params, jnp.asarray(x0, dtype))
    radius = spectral_radius(J)
    contracting = np.where(np.isfinite(radius), radius < 1.0, False).mean(axis=-1)
    return Stability(float(spectral_radius(J_target)), radius, contracting)

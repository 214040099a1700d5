"""Local stability of a trained policy's closed loop x' = f(x, u(x)) (the paper's future work).

One control step of the closed loop has the Jacobian

    J(x) = F_x + F_u · D(x) · ∂μ/∂x        [dX, dX]

with F_x, F_u the plant's control-step Jacobians (central differences of C MuJoCo's step, the
same plant on every device), ∂μ/∂x the Jacobian of the policy's mean action (JAX autodiff) and
D(x) the derivative of the torque saturation (0 for a saturated joint, else 1). Its spectral
radius ρ(J) says whether small perturbations of the state shrink (ρ < 1: the discrete-time map
contracts locally) or some grow (ρ > 1) from one control step to the next.

Reported per policy (:func:`measure`): ρ at the task's target state (at rest) and along the
policy's noiseless rollouts from the robustness test's random states (every ``every``-th control
step), with the fraction of those states where ρ < 1. A linearisation says nothing about large
perturbations: the robustness counts do.
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from gmr_jax import evaluate, policies, sim as sim_lib, tasks
from gmr_jax.config import Config

FD_STEP = 1e-6  # central differences: truncation ~h²·f''' and rounding ~ε·|f|/h both ≲ 1e-9


class Stability(NamedTuple):
    """Local stability of policies (numpy), leading seed axis [S].

    Attributes:
      target_radius: [S] ρ(J) at the target state.
      radius: [S, R, n] ρ(J) at every ``every``-th state of the noiseless rollouts from R states.
      contracting: [S] fraction of those states with ρ(J) < 1 (a non-finite ρ counts as not).
    """

    target_radius: np.ndarray
    radius: np.ndarray
    contracting: np.ndarray


def plant_jacobians(cfg: Config, x: np.ndarray, u: np.ndarray, h: float = FD_STEP):
    """Central-difference Jacobians of one control step of the plant at (x, u).

    Args:
      x: [B, dX] states; u: [B, dU] torques (applied as given: saturate them first).
      h: step, relative to max(1, |entry|).
    Returns:
      (F_x [B, dX, dX], F_u [B, dX, dU]) float64.
    """
    s = sim_lib.make_sim(cfg.sim)
    x, u = np.asarray(x, np.float64), np.asarray(u, np.float64)
    B, dX = x.shape
    dU = u.shape[-1]
    n = dX + dU
    z = np.concatenate([x, u], axis=1)  # [B, n]
    step = h * np.maximum(1.0, np.abs(z))  # [B, n]
    pert = np.eye(n)[None] * step[:, :, None]  # [B, n (direction), n]
    zz = np.concatenate([z[:, None] + pert, z[:, None] - pert], axis=1).reshape(-1, n)
    out = s._host()(zz[:, :dX], zz[:, dX:]).reshape(B, 2, n, dX)  # C MuJoCo, on all host cores
    F = (out[:, 0] - out[:, 1]) / (2.0 * step[:, :, None])  # [B, n, dX]: row j = ∂x'/∂z_j
    F = np.swapaxes(F, 1, 2)
    return F[:, :, :dX], F[:, :, dX:]


def spectral_radius(J) -> np.ndarray:
    """max |eigenvalue| of each [..., n, n] matrix (numpy; NaN where J is not finite)."""
    J = np.asarray(J, np.float64)
    ok = np.isfinite(J).all(axis=(-2, -1))
    rho = np.abs(np.linalg.eigvals(np.where(ok[..., None, None], J, 0.0))).max(axis=-1)
    return np.where(ok, rho, np.nan)


@functools.partial(jax.jit, static_argnums=0)
def _policy_terms(cfg: Config, params, x):
    """Saturated mean actions u [..., dU] and D·∂μ/∂x [..., dU, dX] at states x [..., dX]."""
    s = sim_lib.make_sim(cfg.sim)
    policy = policies.for_config(cfg)
    flat = x.reshape(-1, x.shape[-1])
    mu = jax.vmap(lambda xx: policy.mean(params, xx))(flat)
    dmu = jax.vmap(jax.jacfwd(lambda xx: policy.mean(params, xx)))(flat)
    u = sim_lib.clip_torques(s, mu)
    free = (u == mu).astype(mu.dtype)  # the saturation's derivative
    return (u.reshape(x.shape[:-1] + mu.shape[-1:]),
            (free[:, :, None] * dmu).reshape(x.shape[:-1] + dmu.shape[-2:]))


def closed_loop_jacobians(cfg: Config, params, x) -> np.ndarray:
    """J(x) [B, dX, dX] of one policy (``params`` without a seed axis) at states x [B, dX]."""
    x = jnp.asarray(x)
    u, gain = (np.asarray(a, np.float64) for a in _policy_terms(cfg, params, x))
    Fx, Fu = plant_jacobians(cfg, np.asarray(x), u)
    return Fx + Fu @ gain


@functools.partial(jax.jit, static_argnums=0)
def _rollout_states(cfg: Config, params, x0):
    """[S, R, T, dX] noiseless policy rollouts of every seed's params from x0 [R, dX]."""
    return jax.vmap(lambda p: evaluate.execute_policy(cfg, p, x0).X)(params)


EVERY = 5  # measure's default: every 5th control step of a rollout


def warm_up(cfg: Config, params, num_rollouts: int = evaluate.ROBUSTNESS_STATES, every: int = EVERY) -> None:
    """Trace and compile (or load from JAX's compilation cache) the policy's part of
    :func:`measure` for policies shaped like ``params`` (PolicyParams or their shapes, leading
    seed axis [S]) along ``num_rollouts`` rollouts of the task's horizon, by running it once on
    zeros: a runner calls this while training, so that the measurement after it does not wait
    for the tracing. Changes nothing else."""
    # NumPy parameters and a JAX array of states, as measure passes them: the same call signature
    one = jax.tree_util.tree_map(lambda a: np.zeros(a.shape[1:], a.dtype), params)
    dtype = jax.tree_util.tree_leaves(one)[0].dtype
    n = 1 + num_rollouts * len(range(0, cfg.task.T, every))
    jax.block_until_ready(_policy_terms(cfg, one, jnp.asarray(np.zeros((n, sim_lib.make_sim(cfg.sim).dX), dtype))))


def measure(cfg: Config, params, X=None, every: int = EVERY) -> Stability:
    """ρ(J) of every seed's policy at the target and along its noiseless rollouts, every
    ``every``-th control step.

    Args:
      cfg: the run's configuration (an algorithm with a global policy).
      params: PolicyParams with a leading seed axis [S].
      X: [S, R, T, dX] the rollouts' states (e.g. ``Robustness.X`` of the robustness test);
        default: rolled out here from the robustness test's random states.
    """
    dtype = jax.tree_util.tree_leaves(params)[0].dtype
    if X is None:
        x0 = evaluate.robustness_states(cfg, dtype=dtype)
        X = _rollout_states(cfg, params, x0)
    X = np.asarray(X)[:, :, ::every]  # [S, R, n, dX]
    target = np.asarray(tasks.target_state(cfg.task, dtype))
    S, R, n, dX = X.shape
    radius, target_radius = np.empty((S, R, n)), np.empty(S)
    for i in range(S):
        p = jax.tree_util.tree_map(lambda a: a[i], params)
        states = np.concatenate([target[None], X[i].reshape(-1, dX)]).astype(dtype)
        rho = spectral_radius(closed_loop_jacobians(cfg, p, states))
        target_radius[i], radius[i] = rho[0], rho[1:].reshape(R, n)
    contracting = np.where(np.isfinite(radius), radius < 1.0, False).mean(axis=(1, 2))
    return Stability(target_radius, radius, contracting)

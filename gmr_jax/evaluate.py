"""Evaluation of trained policies: final-state MSE, success, robustness from random states.

Robustness (gmr-method.md §3.1–§3.2): the global policy is executed noiselessly for T steps
from random initial states drawn from one fixed key (the same states for every algorithm and
seed), and succeeds when the final-state MSE is below the task's threshold (0.01 headline, 0.1
also reported). The disturbance sweep reports the success rate against the distance of the
initial state from the nearest training initial state.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from gmr_jax import mdgps, tasks
from gmr_jax import sim as sim_lib
from gmr_jax.config import Config

# The fixed key of the robustness states: every algorithm and seed is tested on the same states.
ROBUSTNESS_KEY = 2018
ROBUSTNESS_STATES = 50


class Robustness(NamedTuple):
    """Robustness of one trained policy (leading axes from ``vmap`` over seeds, if any).

    Attributes:
      x0: [S, dX] initial states.
      final_x: [S, dX] final states x_{T-1}.
      mse: [S] final-state MSE against the target.
      success: [S] bool, mse < task.success_threshold.
      success_loose: [S] bool, mse < task.success_threshold_loose.
      distance: [S] Euclidean distance of x0 from the nearest training initial state.
      ee: [S, T, 3] end-effector paths.
    """

    x0: jax.Array
    final_x: jax.Array
    mse: jax.Array
    success: jax.Array
    success_loose: jax.Array
    distance: jax.Array
    ee: jax.Array


def robustness_states(cfg: Config, num: int = ROBUSTNESS_STATES, seed: int = ROBUSTNESS_KEY,
                      dtype=None) -> jax.Array:
    """The fixed random initial states of the robustness test: [num, dX]."""
    s = sim_lib.make_sim(cfg.sim)
    x = tasks.robustness_states(jax.random.PRNGKey(seed), num, s.dU)
    return x.astype(dtype or jnp.result_type(float))


def execute_policy(cfg: Config, params, x0: jax.Array):
    """Noiseless execution of the global policy's mean from each initial state.

    Args:
      cfg: configuration of an MDGPS/GMR run (static).
      params: PolicyParams of the trained policy.
      x0: [S, dX] initial states.
    Returns:
      Trajectories [S, T, ...].
    """
    s = sim_lib.make_sim(cfg.sim)
    eps = jnp.zeros((cfg.task.T, s.dU), x0.dtype)
    fn = mdgps.policy_mean_fn(cfg, params)
    return jax.vmap(lambda x: sim_lib.rollout(s, fn, x, eps))(x0)


def robustness(cfg: Config, params, x0: jax.Array | None = None) -> Robustness:
    """Robustness of a trained global policy from the fixed random states (or ``x0``).

    Args:
      cfg: configuration of the run (static); its algorithm must train a policy.
      params: PolicyParams (e.g. ``final_state.policy``).
      x0: [S, dX] initial states, default ``robustness_states(cfg)``.
    Returns:
      Robustness.
    """
    if not mdgps.uses_policy(cfg):
        raise ValueError(f"algorithm={cfg.algorithm!r} trains no global policy to evaluate")
    dtype = jax.tree_util.tree_leaves(params)[0].dtype
    if x0 is None:
        x0 = robustness_states(cfg, dtype=dtype)
    return summarize_robustness(cfg, x0, execute_policy(cfg, params, x0))


def summarize_robustness(cfg: Config, x0: jax.Array, out) -> Robustness:
    """Robustness from executed rollouts: x0 [S, dX] and their Trajectories [S, T, ...] (e.g.
    from :func:`execute_policy`, when the caller needs the trajectories too)."""
    target = tasks.target_state(cfg.task, x0.dtype)
    final_x = out.X[:, -1]
    mse = tasks.final_state_mse(final_x, target)
    train_x0 = tasks.initial_states(cfg.task, x0.dtype)
    distance = jnp.min(jnp.linalg.norm(x0[:, None, :] - train_x0[None], axis=-1), axis=1)
    # A diverged rollout (non-finite state) counts as a failure, never as a success.
    finite = jnp.all(jnp.isfinite(final_x), axis=-1)
    return Robustness(x0=x0, final_x=final_x, mse=mse,
                      success=finite & (mse < cfg.task.success_threshold),
                      success_loose=finite & (mse < cfg.task.success_threshold_loose),
                      distance=distance, ee=out.ee)


def disturbance_sweep(cfg: Config, params, radii, per_radius: int = 20, seed: int = ROBUSTNESS_KEY):
    """Success rate against the size of a disturbance of the training initial states.

    For each radius r, ``per_radius`` initial states per training condition are drawn as
    x0_m + r·d with d uniform on the unit sphere of the joint-angle subspace (velocities stay 0),
    from a fixed key.

    Args:
      radii: [R] disturbance radii (rad, Euclidean norm over the joint angles).
    Returns:
      (success rate [R] at the headline threshold, success rate [R] at the loose threshold,
       mse [R, M·per_radius]).
    """
    s = sim_lib.make_sim(cfg.sim)
    dtype = jax.tree_util.tree_leaves(params)[0].dtype
    radii = jnp.asarray(radii, dtype)
    train_x0 = tasks.initial_states(cfg.task, dtype)
    M = train_x0.shape[0]
    d = jax.random.normal(jax.random.PRNGKey(seed + 1), (M, per_radius, s.dU), dtype)
    d = d / jnp.linalg.norm(d, axis=-1, keepdims=True)
    d = jnp.concatenate([d, jnp.zeros_like(d)], axis=-1).reshape(M * per_radius, -1)
    base = jnp.repeat(train_x0, per_radius, axis=0)
    x0 = base[None] + radii[:, None, None] * d[None]  # [R, M·per_radius, dX]
    rob = robustness(cfg, params, x0.reshape(-1, x0.shape[-1]))
    mse = rob.mse.reshape(radii.shape[0], -1)
    ok = rob.success.reshape(mse.shape)
    ok_loose = rob.success_loose.reshape(mse.shape)
    return jnp.mean(ok, axis=1), jnp.mean(ok_loose, axis=1), mse

"""Tasks: initial states, targets, the cost of each task and the robustness state sampler.

The reach task (gmr-method.md §2): the Jaco 2 moves from one or two initial joint configurations
(conditions A, B; at rest) to a common target configuration (at rest) in T = 80 steps of 50 ms.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np

from gmr_jax import cost as cost_lib
from gmr_jax import sim as sim_lib
from gmr_jax.config import Config, TaskConfig


def initial_states(task: TaskConfig, dtype=None) -> jax.Array:
    """Training initial states of the scenario's conditions, at rest.

    Returns:
      [M, dX] with dX = 12 (joint angles, zero joint velocities).
    """
    q = np.asarray(task.initial_angles, dtype=np.float64)
    x = np.concatenate([q, np.zeros_like(q)], axis=-1)
    return jnp.asarray(x, dtype=dtype or jnp.result_type(float))


def target_state(task: TaskConfig, dtype=None) -> jax.Array:
    """The target state [dX]: target joint angles, zero velocities."""
    q = np.asarray(task.target, dtype=np.float64)
    return jnp.asarray(np.concatenate([q, np.zeros_like(q)]), dtype=dtype or jnp.result_type(float))


def make_cost(cfg: Config):
    """The task's cost function ``cost_fn(x [dX], u [dU], t) -> scalar`` (see ``gmr_jax.cost``)."""
    s = sim_lib.make_sim(cfg.sim)
    target = target_state(cfg.task)
    target_ee = sim_lib.end_effector(s, target[: s.dU]) if cfg.cost.ee_weight > 0 else None
    ee_fn = (lambda q: sim_lib.end_effector(s, q)) if cfg.cost.ee_weight > 0 else None
    return cost_lib.reach_cost(cfg.cost, target, cfg.task.T, ee_fn=ee_fn, target_ee=target_ee)


def final_state_mse(x_final: jax.Array, target: jax.Array) -> jax.Array:
    """Final-state mean squared error over the state entries (rad, rad/s), gmr-method.md §3.1.

    Args:
      x_final: [..., dX] final states.
      target: [dX] target state.
    Returns:
      [...] MSE per state.
    """
    return jnp.mean((x_final - target) ** 2, axis=-1)


def robustness_states(key: jax.Array, num: int = 50, dU: int = 6) -> jax.Array:
    """Random initial states of the robustness test (gmr-method.md §2 and §3.2).

    Joints 1, 4, 5, 6 uniform in [−π, π]; joints 2 and 3 uniform in π ± π/2; velocities zero.
    Draw them from one fixed key so every algorithm and seed is tested on the same states.

    Returns:
      [num, 2·dU].
    """
    if num < 1:
        raise ValueError(f"num={num}: the number of robustness states must be positive")
    lo = np.full(dU, -math.pi)
    hi = np.full(dU, math.pi)
    lo[1:3] = math.pi / 2
    hi[1:3] = 3 * math.pi / 2
    q = jax.random.uniform(key, (num, dU), minval=lo, maxval=hi)
    return jnp.concatenate([q, jnp.zeros_like(q)], axis=-1)

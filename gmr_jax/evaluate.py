"""Evaluation: noiseless execution, final-state MSE, success, robustness from random states.

Robustness (gmr-method.md §3.1–§3.2): the global policy is executed noiselessly for T steps
from random initial states drawn from one fixed key (the same states for every algorithm and
seed; the task defines their distribution), and succeeds when the final-state MSE is below the
task's threshold (0.01 headline, 0.1 also reported). The disturbance sweep reports the success
rate against the distance of the initial state from the training initial states.
"""

from __future__ import annotations

import itertools
from typing import NamedTuple

import jax
import jax.numpy as jnp

from gmr_jax import cost as cost_lib
from gmr_jax import policies, tasks
from gmr_jax import sim as sim_lib
from gmr_jax.config import Config
from gmr_jax.types import LinearGaussianPolicy, Trajectories

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
      X: [S, T, dX] the visited states (e.g. for ``gmr_jax.stability``).
      extra: the task's further success measures, {name: [S] bool} (e.g. insertion depth).
    """

    x0: jax.Array
    final_x: jax.Array
    mse: jax.Array
    success: jax.Array
    success_loose: jax.Array
    distance: jax.Array
    ee: jax.Array
    X: jax.Array
    extra: dict


def final_state_mse(x_final: jax.Array, target: jax.Array) -> jax.Array:
    """Final-state mean squared error over the state entries (rad, rad/s), gmr-method.md §3.1,
    in raw angles (:func:`task_mse` follows the task's angle convention).

    Args:
      x_final: [..., dX] final states.
      target: [dX] target state.
    Returns:
      [...] MSE per state.
    """
    return jnp.mean((x_final - target) ** 2, axis=-1)


def task_error(cfg: Config, x: jax.Array) -> jax.Array:
    """x − target [..., dX] for states x [..., dX], with the task's angle convention
    (``TaskConfig.wrap_angles``)."""
    return cost_lib.wrap_angles(x - tasks.target_state(cfg.task, x.dtype), tasks.wrapped_entries(cfg.task))


def task_mse(cfg: Config, x_final: jax.Array) -> jax.Array:
    """The final-state MSE [...] of final states x_final [..., dX] against the task's target, with
    the task's angle convention (:func:`task_error`)."""
    return jnp.mean(task_error(cfg, x_final) ** 2, axis=-1)


def execute(cfg: Config, controller, x0: jax.Array) -> Trajectories:
    """Noiseless rollouts from each initial state.

    Args:
      controller: a LinearGaussianPolicy with a leading axis matching x0 (each state its own
        controller) or a callable ``(t, x, eps_t) -> u`` shared by all.
      x0: [S, dX].
    Returns:
      Trajectories [S, T, ...].
    """
    s = sim_lib.make_sim(cfg.sim)
    eps = jnp.zeros((cfg.task.T, s.dU), x0.dtype)
    axis = 0 if isinstance(controller, LinearGaussianPolicy) else None
    return jax.vmap(lambda p, x: sim_lib.rollout(s, p, x, eps), in_axes=(axis, 0))(controller, x0)


def execute_pair(cfg: Config, traj: LinearGaussianPolicy, policy_fn, x0: jax.Array) -> tuple[Trajectories, Trajectories]:
    """Noiseless rollouts of the local controllers ``traj`` [M, T, ...] and of a policy callable
    ``(t, x, eps_t) -> u`` from the M initial states x0 [M, dX].

    With MJX both run as one batched rollout of 2M trajectories (the controller chosen per member
    by a flag), so a program that needs both holds one instance of MJX's step instead of two:
    each instance costs seconds of compilation. With C MuJoCo they stay two rollouts (the local
    controllers' one host callback per rollout is faster there). Returns (Trajectories [M, T, ...]
    of the controllers, of the policy).
    """
    s = sim_lib.make_sim(cfg.sim)
    if s.backend == "mujoco":
        return execute(cfg, traj, x0), execute(cfg, policy_fn, x0)
    M = x0.shape[0]
    twice = lambda a: jnp.concatenate([a, a])  # noqa: E731
    both = sim_lib.rollout_per_row(s, jax.tree_util.tree_map(twice, traj), (policy_fn,),
                                   jnp.repeat(jnp.arange(2), M), twice(x0),
                                   jnp.zeros((2 * M, cfg.task.T, s.dU), x0.dtype))
    return jax.tree_util.tree_map(lambda a: a[:M], both), jax.tree_util.tree_map(lambda a: a[M:], both)


def controllers_mse(cfg: Config, controller, x0: jax.Array) -> tuple[Trajectories, jax.Array]:
    """Noiseless execution from the training initial states and its final-state MSE [M]."""
    out = execute(cfg, controller, x0)
    return out, task_mse(cfg, out.X[:, -1])


def _global_policy(cfg: Config):
    policy = policies.for_config(cfg)
    if policy is None:
        raise ValueError(f"algorithm={cfg.algorithm!r} trains no global policy to evaluate")
    return policy


def execute_policy(cfg: Config, params, x0: jax.Array) -> Trajectories:
    """Noiseless execution of the global policy's mean from each initial state x0 [S, dX]."""
    return execute(cfg, policies.mean_fn(_global_policy(cfg), params), x0)


def robustness_states(cfg: Config, num: int = ROBUSTNESS_STATES, seed: int = ROBUSTNESS_KEY,
                      dtype=None) -> jax.Array:
    """The task's fixed random initial states of the robustness test: [num, dX] (with
    ``task.random_angles_around_target``, the continuous joints' angles moved by whole turns to
    within [−π, π) of the target's: the same arm configurations)."""
    x = tasks.of(cfg).robustness_states(cfg, num, seed, dtype or jnp.result_type(float))
    if not cfg.task.random_angles_around_target:
        return x
    d = x - tasks.target_state(cfg.task, x.dtype)
    return x - (d - cost_lib.wrap_angles(d, tasks.of(cfg).continuous_joints))  # whole turns; 0 elsewhere


def robustness(cfg: Config, params, x0: jax.Array | None = None) -> Robustness:
    """Robustness of a trained global policy from the fixed random states (or ``x0``).

    Args:
      cfg: configuration of the run (static); its algorithm must train a policy.
      params: PolicyParams (e.g. ``final_state.policy.params``).
      x0: [S, dX] initial states, default ``robustness_states(cfg)``.
    Returns:
      Robustness.
    """
    _global_policy(cfg)
    dtype = jax.tree_util.tree_leaves(params)[0].dtype
    if x0 is None:
        x0 = robustness_states(cfg, dtype=dtype)
    return summarize_robustness(cfg, x0, execute_policy(cfg, params, x0))


def summarize_robustness(cfg: Config, x0: jax.Array, out: Trajectories) -> Robustness:
    """Robustness from executed rollouts: x0 [S, dX] and their Trajectories [S, T, ...] (e.g.
    from :func:`execute_policy`, when the caller needs the trajectories too)."""
    final_x = out.X[:, -1]
    mse = task_mse(cfg, final_x)
    train_x0 = tasks.initial_states(cfg.task, x0.dtype)
    distance = jnp.min(jnp.linalg.norm(x0[:, None, :] - train_x0[None], axis=-1), axis=1)
    # A diverged rollout (non-finite state) counts as a failure, never as a success.
    finite = jnp.all(jnp.isfinite(final_x), axis=-1)
    extra = {name: finite & ok for name, ok in tasks.of(cfg).success_extra(cfg, final_x).items()}
    return Robustness(x0=x0, final_x=final_x, mse=mse,
                      success=finite & (mse < cfg.task.success_threshold),
                      success_loose=finite & (mse < cfg.task.success_threshold_loose),
                      distance=distance, ee=out.ee, X=out.X, extra=extra)


def sweep_states(cfg: Config, radii=None, per_radius: int | None = None, seed: int = ROBUSTNESS_KEY,
                 dtype=None) -> jax.Array:
    """The disturbance sweep's initial states [R, M·per_radius, dX] (defaults: the task's radii
    and states per radius, drawn from a fixed key)."""
    task = tasks.of(cfg)
    radii = task.sweep_radii if radii is None else radii
    per_radius = task.sweep_per_radius if per_radius is None else per_radius
    return task.disturbed_states(cfg, radii, per_radius, seed + 1, dtype or jnp.result_type(float))


def sweep_rates(cfg: Config, x0: jax.Array, out: Trajectories):
    """The disturbance sweep's result from executed rollouts: x0 [R, n, dX] from
    :func:`sweep_states` and their Trajectories [R·n, T, ...]. Returns (success rate [R] at the
    headline threshold, at the loose threshold, mse [R, n])."""
    rob = summarize_robustness(cfg, x0.reshape(-1, x0.shape[-1]), out)
    mse = rob.mse.reshape(x0.shape[:2])
    ok = rob.success.reshape(mse.shape)
    ok_loose = rob.success_loose.reshape(mse.shape)
    return jnp.mean(ok, axis=1), jnp.mean(ok_loose, axis=1), mse


def disturbance_sweep(cfg: Config, params, radii=None, per_radius: int | None = None,
                      seed: int = ROBUSTNESS_KEY):
    """Success rate against the size of a disturbance of the training initial states.

    For each radius r, ``per_radius`` initial states per training condition are drawn by the
    task (reach: x0_m + r·d with d uniform on the unit sphere of the joint-angle subspace,
    velocities 0) from a fixed key.

    Args:
      radii: [R] disturbance radii (rad; default the task's).
      per_radius: states per radius and condition (default the task's).
    Returns:
      (success rate [R] at the headline threshold, success rate [R] at the loose threshold,
       mse [R, M·per_radius]).
    """
    _global_policy(cfg)
    dtype = jax.tree_util.tree_leaves(params)[0].dtype
    x0 = sweep_states(cfg, radii, per_radius, seed, dtype)
    return sweep_rates(cfg, x0, execute_policy(cfg, params, x0.reshape(-1, x0.shape[-1])))


class Evaluation(NamedTuple):
    """The evaluation of a trained policy after training (:func:`evaluation`).

    Attributes:
      robustness: Robustness from the fixed random states.
      sweep: (success rate [R], loose success rate [R], mse [R, n]) of the disturbance sweep.
      training: Trajectories [M, T, ...] of the noiseless policy from the training initial
        states (e.g. for pictures).
    """

    robustness: Robustness
    sweep: tuple
    training: Trajectories


def evaluation(cfg: Config, params) -> Evaluation:
    """The robustness test, the disturbance sweep and the noiseless rollouts from the training
    states, executed as one batch of rollouts: one rollout in the compiled program instead of
    one per part (equal to :func:`robustness` and :func:`disturbance_sweep` up to the rounding
    of the policy's batched products)."""
    _global_policy(cfg)
    dtype = jax.tree_util.tree_leaves(params)[0].dtype
    parts = [robustness_states(cfg, dtype=dtype), sweep_states(cfg, dtype=dtype),
             tasks.initial_states(cfg.task, dtype)]
    flat = [parts[0], parts[1].reshape(-1, parts[1].shape[-1]), parts[2]]
    out = execute_policy(cfg, params, jnp.concatenate(flat))
    ends = list(itertools.accumulate(x.shape[0] for x in flat))
    rob_out, sweep_out, train_out = (jax.tree_util.tree_map(lambda a, lo=lo, hi=hi: a[lo:hi], out)
                                     for lo, hi in zip([0] + ends[:-1], ends))
    return Evaluation(robustness=summarize_robustness(cfg, parts[0], rob_out),
                      sweep=sweep_rates(cfg, parts[1], sweep_out), training=train_out)

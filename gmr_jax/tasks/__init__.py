"""Tasks: one module per task behind one small interface, :class:`Task`.

A task module (``gmr_jax/tasks/<name>.py``) defines ``TASK = Task(...)``: its scenarios (which
conditions are trained), its stage settings (scene, cost, the arm's initial controller), the
training initial states and the target, the cost, the robustness states and the disturbance
sweep, any success measure reported beside the final-state MSE, and the paper's reference
numbers. ``mdgps``, ``evaluate``, the runner and the reports use nothing else of a task, so a new
task is one module and one line in :data:`TASKS`.

The registry imports task modules lazily: ``get("reach")`` imports ``gmr_jax.tasks.reach``.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any, Callable, Mapping, NamedTuple, Sequence

import jax
import jax.numpy as jnp
import numpy as np

if TYPE_CHECKING:
    from gmr_jax.config import Config, TaskConfig

# name -> module defining TASK
TASKS = {
    "reach": "gmr_jax.tasks.reach",
    "block_in_hole": "gmr_jax.tasks.block_in_hole",
}


class Task(NamedTuple):
    """A task: its data and the functions the training and the evaluation need.

    Attributes:
      name: registry name, also ``TaskConfig.name``.
      title: human-readable name for reports ("Reach").
      scenarios: scenario -> the names of its conditions, in order (e.g. "AB" -> ("A", "B")).
      default_scenarios: the scenarios a study runs by default.
      default_config: scenario -> the task's whole :class:`~gmr_jax.config.Config` (algorithm
        "lqr"; the builders in ``gmr_jax.config`` apply overrides).
      cost_config: the frozen dataclass type of ``Config.cost`` for this task.
      initial_states: (TaskConfig) -> [M, dX] numpy float64, the training conditions at rest.
      target_state: (TaskConfig) -> [dX] numpy float64, the target of the final-state MSE.
      make_cost: (Config) -> ``gmr_jax.cost.CostFn``, the per-step cost ℓ(x, u, t).
      robustness_states: (Config, num, seed, dtype) -> [num, dX], the fixed random initial states
        of the robustness test (the same for every algorithm and seed).
      disturbed_states: (Config, radii [R], per_radius, seed, dtype) -> [R, M·per_radius, dX],
        the initial states of the disturbance sweep around the training conditions.
      success_extra: (Config, final states [..., dX]) -> {name: bool [...]}, success measures
        reported beside the final-state MSE (empty for reach).
      sweep_radii: the default radii of the disturbance sweep; sweep_per_radius: states per
        radius and condition.
      paper_robustness: (scenario, algorithm) -> the paper's successes out of 50.
      continuous_joints: the joints without limits (their angles are only defined modulo 2π);
        ``TaskConfig.wrap_angles`` wraps their angle errors in the success test and the cost.
      mjx_min_rollouts: on a GPU, the rollout batch (seeds × conditions × samples) from which
        MJX steps this task's scene faster than C MuJoCo on the host, by measurement
        (benchmarks/RESULTS.md); None where MJX is slower at every measured batch (contacts).
    """

    name: str
    title: str
    scenarios: Mapping[str, tuple[str, ...]]
    default_scenarios: tuple[str, ...]
    default_config: Callable[[str], "Config"]
    cost_config: type
    initial_states: Callable[["TaskConfig"], np.ndarray]
    target_state: Callable[["TaskConfig"], np.ndarray]
    make_cost: Callable[["Config"], Any]
    robustness_states: Callable[..., jax.Array]
    disturbed_states: Callable[..., jax.Array]
    success_extra: Callable[["Config", jax.Array], dict]
    sweep_radii: tuple[float, ...]
    sweep_per_radius: int
    paper_robustness: Mapping[tuple[str, str], int]
    mjx_min_rollouts: int | None = 32
    continuous_joints: tuple[int, ...] = ()


def get(name: str) -> Task:
    """The registered task ``name`` (imports its module on first use)."""
    if name not in TASKS:
        raise ValueError(f"task.name={name!r}: allowed values are {tuple(TASKS)}")
    return importlib.import_module(TASKS[name]).TASK


def of(cfg: "Config") -> Task:
    """The task of a configuration."""
    return get(cfg.task.name)


def _float(dtype):
    return dtype or jnp.result_type(float)


def initial_states(task: "TaskConfig", dtype=None) -> jax.Array:
    """Training initial states of the scenario's conditions, at rest: [M, dX]."""
    return jnp.asarray(get(task.name).initial_states(task), dtype=_float(dtype))


def target_state(task: "TaskConfig", dtype=None) -> jax.Array:
    """The target state [dX] of the final-state MSE."""
    return jnp.asarray(get(task.name).target_state(task), dtype=_float(dtype))


def wrapped_entries(task: "TaskConfig") -> tuple[int, ...]:
    """The state entries whose errors are wrapped to [−π, π): the task's continuous joints' angles
    where ``task.wrap_angles``, else none."""
    return get(task.name).continuous_joints if task.wrap_angles else ()


def at_rest(q) -> np.ndarray:
    """Joint angles [..., nq] -> states [..., 2·nq] with zero velocities (float64)."""
    q = np.asarray(q, dtype=np.float64)
    return np.concatenate([q, np.zeros_like(q)], axis=-1)


def fixed_draw(draw: Callable[[], jax.Array]) -> np.ndarray:
    """``draw()``, random numbers from a fixed key, evaluated at once in float64 whatever the
    run's precision (also inside a ``jit`` trace).

    JAX draws other numbers from one key in float32 than in float64, so the evaluation's fixed
    random states drawn in the run's precision were a different set in float32 runs; drawn here
    they are the same states in both (rounded in float32).
    """
    with jax.enable_x64(True), jax.ensure_compile_time_eval():
        return np.asarray(draw(), np.float64)


def disturb(x0: jax.Array, radii: Sequence[float], per_radius: int, seed: int, nq: int) -> jax.Array:
    """States x0_m + r·d around each training state, d uniform on the unit sphere of the
    joint-angle subspace (velocities unchanged): the directions drawn from ``seed`` in float64
    (``fixed_draw``), the states formed in x0's dtype.

    Args:
      x0: [M, dX] training initial states.
      radii: [R] disturbance radii (rad, Euclidean norm over the joint angles).
      per_radius: states per radius and condition.
      seed: PRNG seed of the directions.
      nq: number of joint angles (the first nq state entries).
    Returns:
      [R, M·per_radius, dX].
    """
    dtype = x0.dtype
    M = x0.shape[0]
    radii = jnp.asarray(radii, dtype)
    d = jnp.asarray(fixed_draw(lambda: jax.random.normal(jax.random.PRNGKey(seed), (M, per_radius, nq),
                                                         jnp.float64)), dtype)
    d = d / jnp.linalg.norm(d, axis=-1, keepdims=True)
    d = jnp.concatenate([d, jnp.zeros((M, per_radius, x0.shape[-1] - nq), dtype)], axis=-1)
    d = d.reshape(M * per_radius, -1)
    base = jnp.repeat(x0, per_radius, axis=0)
    return base[None] + radii[:, None, None] * d[None]

"""The reach task (paper scenarios A and B, gmr-method.md §2): the Jaco 2 moves from one or two
initial joint configurations (at rest) to a common target configuration (at rest) in T = 80
steps of 50 ms, in free space (scene ``jaco_mjcf/reach.xml``, no contacts).

Robustness (gmr-method.md §2–§3.2): 50 random initial states drawn from the authors' reset
distribution with a fixed key; the disturbance sweep moves the training joint angles by radii up
to 3 rad.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np

from gmr_jax import cost as cost_lib
from gmr_jax import sim as sim_lib
from gmr_jax import tasks
from gmr_jax.config import Config, TaskConfig, check_choice, check_nonnegative, check_number_tuple
from gmr_jax.tasks import Task, at_rest, disturb, jaco

# Kinova actuator angles (rad) of the paper-era Jaco experiment (gmr-method.md §2).
INITIAL = {
    "A": (-0.2046, 3.4193, 1.2257, 4.449, 2.0378, 2.1919),
    "B": (-0.2046, 2.419, 1.2255, 4.449, 2.038, 2.1919),
}
TARGET = (-0.7046, 4.1905, 1.4259, 4.4488, 2.0376, 2.1919)
SCENARIOS = {"A": ("A",), "B": ("B",), "AB": ("A", "B")}
# The paper's robustness table (successes out of 50 random initial states after 10 iterations).
PAPER_ROBUSTNESS = {("A", "mdgps"): 12, ("A", "gmr"): 50, ("AB", "mdgps"): 50, ("AB", "gmr"): 50}


@dataclass(frozen=True)
class CostConfig:
    """Reach cost (mdgps-toolbox.md §5, weights after gmr-method.md §2).

    ℓ_t = ½ Σ wu u² + state term + final-state term (+ end-effector term).

    Attributes:
      action_weight: wu per joint (the authors': 5e-3 / Jaco gains).
      state_wp: per-entry weights of the joint-state term over x = [q, q̇] (angles 1, velocities 0).
      state_l1, state_l2, state_alpha: l1/l2/α of the joint-state term.
      state_ramp: ramp of the joint-state term: "constant", "linear", "quadratic", "final_only".
      final_wp: weights of an extra final-only term on [q, q̇] (velocities count, so the arm stops).
      final_l1, final_l2, final_alpha: its l1/l2/α.
      final_multiplier: wp_final_multiplier of the final term.
      ee_weight: weight of an end-effector position (l2) term towards the target's end-effector
        position; 0 disables it.
    """

    action_weight: tuple[float, ...] = jaco.ACTION_WEIGHT
    state_wp: tuple[float, ...] = (1.0,) * 6 + (0.0,) * 6
    state_l1: float = 0.0
    state_l2: float = 1.0
    state_alpha: float = 1e-2
    state_ramp: str = "constant"
    final_wp: tuple[float, ...] = (1.0,) * 6 + (0.1,) * 6
    final_l1: float = 0.0
    final_l2: float = 1.0
    final_alpha: float = 1e-5
    final_multiplier: float = 10.0
    ee_weight: float = 0.0

    def __post_init__(self):
        for name in ("action_weight", "state_wp", "final_wp"):
            check_number_tuple(f"cost.{name}", getattr(self, name))
        for name in ("state_l1", "state_l2", "state_alpha", "final_l1", "final_l2", "final_alpha",
                     "final_multiplier", "ee_weight"):
            check_nonnegative(f"cost.{name}", getattr(self, name))
        check_choice("cost.state_ramp", self.state_ramp, cost_lib.RAMP_MODES)
        if len(self.state_wp) != len(self.final_wp):
            raise ValueError(f"cost.final_wp has {len(self.final_wp)} entries: must have as many as "
                             f"cost.state_wp ({len(self.state_wp)})")


def default_config(scenario: str) -> Config:
    """The reach configuration of a scenario: the reach scene, its cost, the Jaco's init_lqr."""
    return Config(task=TaskConfig(name="reach", scenario=scenario), cost=CostConfig(),
                  init=jaco.INIT_LQR)


def initial_states(task: TaskConfig) -> np.ndarray:
    """[M, 12]: the scenario's initial joint angles at rest."""
    return at_rest([INITIAL[c] for c in SCENARIOS[task.scenario]])


def target_state(task: TaskConfig) -> np.ndarray:
    """[12]: the target joint angles at rest."""
    return at_rest(TARGET)


def reach_cost(cfg: CostConfig, target_x, T: int, ee_fn: Callable | None = None,
               target_ee=None, wrapped: tuple[int, ...] = ()) -> cost_lib.CostFn:
    """The reach cost of a :class:`CostConfig`.

    ℓ_t = ½ Σ wu u²                                        (action)
        + state term   on x − target_x, weights state_wp, ramp state_ramp
        + final term   on x − target_x, weights final_wp, final-only ramp × final_multiplier
        + end-effector l2 term ½ ee_weight ‖ee(q) − target_ee‖²   (only if ee_weight > 0)

    Args:
      cfg: the cost settings.
      target_x: [dX] target state (target angles, zero velocity).
      T: horizon.
      ee_fn: q [6] -> [3]; needed only when cfg.ee_weight > 0.
      target_ee: [3] target end-effector position (default: ee_fn at the target's angles).
      wrapped: state entries whose errors the state terms wrap to [−π, π) (``cost.wrap_angles``).
    """
    dX = len(cfg.state_wp)
    if np.shape(target_x) != (dX,):
        raise ValueError(f"reach_cost: target_x has shape {np.shape(target_x)}, expected ({dX},) "
                         "to match cost.state_wp")
    terms = [
        cost_lib.action_cost(cfg.action_weight),
        cost_lib.state_cost(target_x, cfg.state_wp, cfg.state_l1, cfg.state_l2, cfg.state_alpha,
                            cost_lib.ramp(T, cfg.state_ramp, 1.0), wrapped=wrapped),
        cost_lib.state_cost(target_x, cfg.final_wp, cfg.final_l1, cfg.final_l2, cfg.final_alpha,
                            cost_lib.ramp(T, "final_only", cfg.final_multiplier), wrapped=wrapped),
    ]
    if cfg.ee_weight > 0:
        if ee_fn is None:
            raise ValueError("cost.ee_weight > 0 needs an end-effector function (ee_fn)")
        n_joints = dX // 2
        if target_ee is None:
            target_ee = ee_fn(jnp.asarray(target_x)[:n_joints])
        # A pure l2 term (l1 = 0), so the choice of norm does not matter; logl2 is CostFK's.
        terms.append(cost_lib.end_effector_cost(ee_fn, target_ee, (cfg.ee_weight,) * 3, 0.0, 1.0, 1e-5,
                                                cost_lib.ramp(T, "constant", 1.0), norm="logl2",
                                                n_joints=n_joints))
    return cost_lib.cost_sum(terms)


def make_cost(cfg: Config) -> cost_lib.CostFn:
    """The run's reach cost ``cost_fn(x [dX], u [dU], t) -> scalar``."""
    target = jnp.asarray(target_state(cfg.task), dtype=jnp.result_type(float))
    ee_fn = None
    if cfg.cost.ee_weight > 0:
        s = sim_lib.make_sim(cfg.sim)
        ee_fn = lambda q: sim_lib.end_effector(s, q)  # noqa: E731
    return reach_cost(cfg.cost, target, cfg.task.T, ee_fn=ee_fn, wrapped=tasks.wrapped_entries(cfg.task))


def random_states(num: int, seed: int) -> np.ndarray:
    """[num, 12] float64: the reach study's random initial states from ``seed`` (drawn in
    float64 whatever the run's precision, ``tasks.fixed_draw``).

    Joints 1, 4, 5, 6 uniform in [−π, π]; joints 2 and 3 uniform in π ± π/2 (the authors'
    reset distribution, "to prevent getting stuck in the ground"); velocities zero.
    """
    if num < 1:
        raise ValueError(f"num={num}: the number of robustness states must be positive")
    nq = len(TARGET)
    lo = np.full(nq, -math.pi)
    hi = np.full(nq, math.pi)
    lo[1:3] = math.pi / 2
    hi[1:3] = 3 * math.pi / 2
    return at_rest(tasks.fixed_draw(
        lambda: jax.random.uniform(jax.random.PRNGKey(seed), (num, nq), jnp.float64, lo, hi)))


def robustness_states(cfg: Config, num: int, seed: int, dtype=None) -> jax.Array:
    """Random initial states of the robustness test (gmr-method.md §2 and §3.2), from ``seed``:
    ``random_states`` in ``dtype``, the same states in every precision.

    Returns:
      [num, 12].
    """
    return jnp.asarray(random_states(num, seed), dtype or jnp.result_type(float))


def disturbed_states(cfg: Config, radii, per_radius: int, seed: int, dtype=None) -> jax.Array:
    """The disturbance sweep's states [R, M·per_radius, 12] around the training conditions."""
    x0 = jnp.asarray(initial_states(cfg.task), dtype=dtype or jnp.result_type(float))
    return disturb(x0, radii, per_radius, seed, len(TARGET))


TASK = Task(
    name="reach", title="Reach", scenarios=SCENARIOS, default_scenarios=("A", "AB"),
    default_config=default_config, cost_config=CostConfig, initial_states=initial_states,
    target_state=target_state, make_cost=make_cost, robustness_states=robustness_states,
    disturbed_states=disturbed_states, success_extra=lambda cfg, final_x: {},
    sweep_radii=(0.0, 0.25, 0.5, 1.0, 1.5, 2.0, 3.0), sweep_per_radius=10,
    # MJX costs about the same for any batch on a GPU, C MuJoCo grows with it; they cross
    # between 10 and 60 rollouts (benchmarks/RESULTS.md)
    paper_robustness=PAPER_ROBUSTNESS, mjx_min_rollouts=32,
    continuous_joints=jaco.CONTINUOUS_JOINTS)

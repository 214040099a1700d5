"""The block-in-hole task (paper scenarios C and D, block-in-hole.md): the Jaco 2 holds a wooden
block rigidly in its hand and presses it into a square hole with a light press fit, from two
initial conditions C and D above the hole (scene ``jaco_mjcf/block_in_hole.xml``, contacts on;
its README section has the geometry, contact parameters and measured insertion forces).

- Conditions (Kinova actuator angles, rad, at rest; derived by ``python -m
  experiments.block_in_hole_poses``): C with the block's tip 60 mm above the rim, D 120 mm above
  it, their lateral offsets such that the straight joint-space path to the target enters the
  hole. Target q*: the block fully inserted (tip on the hole bottom, 50 mm below the rim), axis
  vertical, faces parallel to the walls.
- Cost: the GPS toolbox's peg form (block-in-hole.md §2) on three points of the block (its tip
  centre, a tip corner, which fixes the yaw, and its top centre): a log-l2 point term with a
  constant ramp plus a final-step point term, and the action cost with the Jaco gains.
- Success: the paper's final-state MSE (< 0.01; 0.1 loose) against q* at rest, and, reported
  beside it, "inserted": the tip inside the hole, at least 90 % of the hole depth below the rim.
- Robustness: 50 fixed random initial states drawn from the reach study's distribution and kept
  only when the arm, the block and the fixture are free of contact (rejection sampling with
  :func:`collision_free`); the disturbance sweep keeps only collision-free disturbed states too.

Physics: 2 ms steps (25 substeps per 50 ms action), elliptic friction cones (the block does not
pass the press-fit nubs with pyramidal ones).
"""

from __future__ import annotations

import copy
from dataclasses import dataclass

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from gmr_jax import cost as cost_lib
from gmr_jax import sim as sim_lib
from gmr_jax.config import Config, SimConfig, TaskConfig, check_nonnegative, check_number_tuple
from gmr_jax.tasks import Task, at_rest, disturb, fixed_draw, jaco
from gmr_jax.tasks import reach as reach_task

INITIAL = {
    "C": (-1.704952, 3.682464, 1.510390, -0.308968, 1.136327, -0.443124),
    "D": (-1.697230, 3.571914, 1.578322, -0.382596, 1.355386, -0.509029),
}
TARGET = (-1.710931, 3.893994, 1.400860, -0.195280, 0.753419, -0.335414)
SCENARIOS = {"C": ("C",), "D": ("D",), "CD": ("C", "D")}
# The paper's real-robot robustness table (successes out of 50 random initial states).
PAPER_ROBUSTNESS = {("C", "mdgps"): 4, ("C", "gmr"): 39, ("CD", "mdgps"): 9, ("CD", "gmr"): 44}
SCENE = "block_in_hole"
SUBSTEPS = 25  # 2 ms physics steps in contact (jaco_mjcf/README.md)
BLOCK_POINTS = ("block_tip", "block_tip_corner", "block_top")
HOLE_DEPTH = 0.05  # m, from the rim to the hole bottom
HOLE_HALF_WIDTH = 0.0203  # m, from the hole axis to a wall (40.6 mm hole)
INSERTED_FRACTION = 0.9  # "inserted": the tip at least this fraction of HOLE_DEPTH below the rim


@dataclass(frozen=True)
class CostConfig:
    """Block-in-hole cost: the toolbox's peg cost (block-in-hole.md §2) on the block's points.

    ℓ_t = ½ Σ wu u² + CostFK(points) + final-step CostFK(points), with CostFK the log-l2 norm
    ½ l2 Σ wp d² + ½ l1 log(α + Σ (wp d)²) of d = points(q) − points(q*).

    Attributes:
      action_weight: wu per joint (the Jaco's: 5e-3 / gains).
      points_wp: per-coordinate weights of the point term, (x, y, z) per point of BLOCK_POINTS
        (toolbox: x and y 2, z 1).
      points_l1, points_l2, points_alpha: its log-l2 norm (toolbox 0.1, 10, 1e-5; l2 here 100:
        with the toolbox's 10 the base layer is still pushing the block in at iteration 10,
        20–45 mm deep, benchmarks/RESULTS.md "Block-in-hole: the base layer inserts").
      final_l1, final_l2, final_alpha: the final-step point term's (toolbox 1.0, 0, 1e-5).
      final_multiplier: wp_final_multiplier of the final-step term (toolbox 10).
    """

    action_weight: tuple[float, ...] = jaco.ACTION_WEIGHT
    points_wp: tuple[float, ...] = (2.0, 2.0, 1.0) * len(BLOCK_POINTS)
    points_l1: float = 0.1
    points_l2: float = 100.0
    points_alpha: float = 1e-5
    final_l1: float = 1.0
    final_l2: float = 0.0
    final_alpha: float = 1e-5
    final_multiplier: float = 10.0

    def __post_init__(self):
        check_number_tuple("cost.action_weight", self.action_weight)
        check_number_tuple("cost.points_wp", self.points_wp)
        if len(self.points_wp) != 3 * len(BLOCK_POINTS):
            raise ValueError(f"cost.points_wp has {len(self.points_wp)} entries: must have "
                             f"{3 * len(BLOCK_POINTS)} (x, y, z of {BLOCK_POINTS})")
        for name in ("points_l1", "points_l2", "points_alpha", "final_l1", "final_l2", "final_alpha",
                     "final_multiplier"):
            check_nonnegative(f"cost.{name}", getattr(self, name))


def default_config(scenario: str) -> Config:
    """The block-in-hole configuration of a scenario: its scene at 2 ms steps, its cost, the
    Jaco's init_lqr."""
    return Config(task=TaskConfig(name="block_in_hole", scenario=scenario), cost=CostConfig(),
                  sim=SimConfig(scene=SCENE, substeps=SUBSTEPS), init=jaco.INIT_LQR)


def initial_states(task: TaskConfig) -> np.ndarray:
    """[M, 12]: the scenario's conditions at rest."""
    return at_rest([INITIAL[c] for c in SCENARIOS[task.scenario]])


def target_state(task: TaskConfig) -> np.ndarray:
    """[12]: q*, the block fully inserted, at rest."""
    return at_rest(TARGET)


def block_points(s: sim_lib.Sim, q: jax.Array) -> jax.Array:
    """World positions of the block's cost points, [6] → [3·len(BLOCK_POINTS)] (m)."""
    return jnp.concatenate([sim_lib.site_position(s, q, name) for name in BLOCK_POINTS])


def make_cost(cfg: Config) -> cost_lib.CostFn:
    """The run's block-in-hole cost ``cost_fn(x [12], u [6], t) -> scalar``."""
    s = sim_lib.make_sim(cfg.sim)
    c = cfg.cost
    points = lambda q: block_points(s, q)  # noqa: E731
    with jax.ensure_compile_time_eval():  # a constant, also when the cost is built in a trace
        target = np.asarray(points(jnp.asarray(TARGET, jnp.float64)))
    T = cfg.task.T
    return cost_lib.cost_sum([
        cost_lib.action_cost(c.action_weight),
        cost_lib.end_effector_cost(points, target, c.points_wp, c.points_l1, c.points_l2, c.points_alpha,
                                   cost_lib.ramp(T, "constant", 1.0), norm="logl2", n_joints=s.nq),
        cost_lib.end_effector_cost(points, target, c.points_wp, c.final_l1, c.final_l2, c.final_alpha,
                                   cost_lib.ramp(T, "final_only", c.final_multiplier), norm="logl2",
                                   n_joints=s.nq),
    ])


# ---------------------------------------------------------------------------------------------
# Where the block is, and which arm configurations touch nothing


def _rim(m: mujoco.MjModel) -> np.ndarray:
    """[3]: the rim centre (site hole_rim, on the hole axis), a fixed point of the scene."""
    d = mujoco.MjData(m)
    mujoco.mj_kinematics(m, d)
    return np.array(d.site("hole_rim").xpos)


def _tip_from_rim(s: sim_lib.Sim, q: jax.Array) -> jax.Array:
    """The block tip's position relative to the rim centre (m): q [..., 6] → [..., 3]."""
    tip = jnp.vectorize(lambda qq: sim_lib.site_position(s, qq, "block_tip"), signature="(n)->(k)")(q)
    return tip - _rim(s.model)


def insertion_depth(s: sim_lib.Sim, q: jax.Array) -> jax.Array:
    """Depth of the block's tip below the rim (m; negative above it): q [..., 6] → [...]."""
    return -_tip_from_rim(s, q)[..., 2]


def success_extra(cfg: Config, final_x: jax.Array) -> dict:
    """{"inserted": the tip inside the hole (the larger of its |Δx|, |Δy| from the axis at most
    HOLE_HALF_WIDTH; the hole is square and axis-aligned) and at least INSERTED_FRACTION of the
    hole depth below the rim} [...]. Depth alone is not enough: a block swung down beside the
    fixture also ends below the rim's height."""
    s = sim_lib.make_sim(cfg.sim)
    rel = _tip_from_rim(s, final_x[..., : s.nq])
    return {"inserted": (-rel[..., 2] >= INSERTED_FRACTION * HOLE_DEPTH)
            & (jnp.max(jnp.abs(rel[..., :2]), axis=-1) <= HOLE_HALF_WIDTH)}


def _colliding_copy(m: mujoco.MjModel) -> mujoco.MjModel:
    """A copy of the scene in which every geom collides with every other (contype = conaffinity
    = 1, contacts on); MuJoCo still filters parent-child body pairs and the scene's excludes."""
    m2 = copy.copy(m)
    m2.geom_contype[:] = 1
    m2.geom_conaffinity[:] = 1
    m2.opt.disableflags &= ~int(mujoco.mjtDisableBit.mjDSBL_CONTACT)
    return m2


def collision_free(checker: mujoco.MjModel, q) -> np.ndarray:
    """Whether each arm configuration q [..., 6] is free of contact with the table, the fixture
    (walls, bottom, nubs) and itself, the block included (any penetration counts: the block
    pressed into the nubs, as at q*, is in contact).

    Args:
      checker: the scene with every geom colliding, from :func:`collision_checker`.
    Returns: bool [...].
    """
    q = np.asarray(q, dtype=np.float64)
    flat = q.reshape(-1, q.shape[-1])
    d = mujoco.MjData(checker)
    free = np.empty(flat.shape[0], bool)
    for i, qi in enumerate(flat):
        d.qpos[:] = qi
        mujoco.mj_kinematics(checker, d)
        mujoco.mj_collision(checker, d)
        free[i] = not any(c.dist < 0 for c in d.contact[: d.ncon])
    return free.reshape(q.shape[:-1])


def collision_checker(cfg: Config) -> mujoco.MjModel:
    """The run's scene with every geom colliding (for :func:`collision_free`)."""
    return _colliding_copy(sim_lib.make_sim(cfg.sim).model)


def _first_free(checker, candidates: np.ndarray, num: int, what: str) -> np.ndarray:
    """The first ``num`` collision-free states of candidates [n, 12]."""
    free = candidates[collision_free(checker, candidates[:, :6])]
    if free.shape[0] < num:
        raise ValueError(f"only {free.shape[0]} of {candidates.shape[0]} candidate {what} are "
                         f"collision-free; {num} are needed")
    return free[:num]


def robustness_states(cfg: Config, num: int, seed: int, dtype=None) -> jax.Array:
    """[num, 12]: the reach study's random initial states from ``seed``, those in contact with
    the table or the fixture rejected (about 2 % are); velocities zero."""
    candidates = reach_task.random_states(2 * num + 16, seed)
    states = _first_free(collision_checker(cfg), candidates, num, "robustness states")
    return jnp.asarray(states, dtype=dtype or jnp.result_type(float))


def disturbed_states(cfg: Config, radii, per_radius: int, seed: int, dtype=None) -> jax.Array:
    """[R, M·per_radius, 12]: for each radius and condition, the first ``per_radius``
    collision-free states x0 + r·d (d uniform on the unit sphere of the joint angles)."""
    x0 = initial_states(cfg.task)
    pool = 8 * per_radius
    cand = fixed_draw(lambda: disturb(jnp.asarray(x0, jnp.float64), radii, pool, seed, 6))
    checker = collision_checker(cfg)
    M = x0.shape[0]
    out = [np.concatenate([_first_free(checker, cand[r, m * pool:(m + 1) * pool], per_radius,
                                       f"states at radius {radii[r]}") for m in range(M)])
           for r in range(len(radii))]
    return jnp.asarray(np.stack(out), dtype=dtype or jnp.result_type(float))


TASK = Task(
    name="block_in_hole", title="Block-in-hole", scenarios=SCENARIOS, default_scenarios=("C", "CD"),
    default_config=default_config, cost_config=CostConfig, initial_states=initial_states,
    target_state=target_state, make_cost=make_cost, robustness_states=robustness_states,
    disturbed_states=disturbed_states, success_extra=success_extra,
    sweep_radii=(0.0, 0.1, 0.25, 0.5, 1.0, 2.0), sweep_per_radius=10,
    paper_robustness=PAPER_ROBUSTNESS, mjx_min_rollouts=None,
    continuous_joints=jaco.CONTINUOUS_JOINTS)

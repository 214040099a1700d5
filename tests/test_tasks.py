"""The task contract: every registered task satisfies the interface that mdgps, evaluate, the
runner and the reports rely on (gmr_jax/tasks/__init__.py)."""

import dataclasses

import jax.numpy as jnp
import numpy as np
import pytest

from gmr_jax import config, cost, policies, sim, tasks


@pytest.fixture(scope="module", params=sorted(tasks.TASKS))
def task(request):
    return tasks.get(request.param)


def test_registry_names_and_errors(task):
    assert task.name in tasks.TASKS and tasks.get(task.name) is task
    with pytest.raises(ValueError, match="task.name='nope': allowed values"):
        tasks.get("nope")
    assert set(task.default_scenarios) <= set(task.scenarios)
    for (scenario, algorithm), successes in task.paper_robustness.items():
        assert scenario in task.scenarios and algorithm in policies.ALGORITHMS and 0 <= successes <= 50
    assert task.sweep_per_radius >= 1 and all(r >= 0 for r in task.sweep_radii)


def test_configurations_of_every_scenario(task):
    for scenario, conditions in task.scenarios.items():
        cfg = config.make(task.name, scenario, "gmr")
        assert cfg.task.name == task.name and cfg.task.scenario == scenario
        assert isinstance(cfg.cost, task.cost_config)
        assert cfg.task.num_conditions == len(conditions)
        assert config.from_dict(config.to_dict(cfg)) == cfg
    with pytest.raises(ValueError, match="task.scenario='nope'"):
        config.make(task.name, "nope")


def test_states_target_and_cost(task):
    """Training states at rest with the plant's sizes; the cost is finite and smallest at the
    target with zero action (a small move away from it or a torque costs more)."""
    cfg = config.make(task.name, task.default_scenarios[-1], "lqr", sim__backend="mujoco")
    s = sim.make_sim(cfg.sim)
    x0 = np.asarray(tasks.initial_states(cfg.task))
    target = np.asarray(tasks.target_state(cfg.task))
    assert x0.shape == (cfg.task.num_conditions, s.dX) and target.shape == (s.dX,)
    np.testing.assert_array_equal(x0[:, s.nq:], 0.0)
    np.testing.assert_array_equal(target[s.nq:], 0.0)
    cost_fn = task.make_cost(cfg)
    T = cfg.task.T
    zero = jnp.zeros(s.dU)
    for t in (0, T // 2, T - 1):
        at_target = float(cost_fn(jnp.asarray(target), zero, t))
        assert np.isfinite(at_target)
        for d in (np.eye(s.dX)[0] * 0.05, np.eye(s.dX)[s.nq - 1] * 0.05):
            assert float(cost_fn(jnp.asarray(target + d), zero, t)) > at_target
        assert float(cost_fn(jnp.asarray(target), jnp.ones(s.dU), t)) > at_target
    qc, cs = cost.quadratic_expansion(cost_fn, jnp.asarray(x0)[:, None, None].repeat(T, 2),
                                      jnp.zeros((x0.shape[0], 1, T, s.dU)))
    assert bool(cost.expansion_is_finite(qc, cs))


def test_robustness_and_sweep_states(task):
    cfg = config.make(task.name, task.default_scenarios[0], "gmr", sim__backend="mujoco")
    s = sim.make_sim(cfg.sim)
    a = np.asarray(task.robustness_states(cfg, 8, 7, jnp.float64))
    assert a.shape == (8, s.dX) and a.dtype == np.float64 and np.all(np.isfinite(a))
    np.testing.assert_array_equal(a, task.robustness_states(cfg, 8, 7, jnp.float64))  # fixed by the seed
    assert not np.allclose(a, task.robustness_states(cfg, 8, 8, jnp.float64))
    np.testing.assert_array_equal(a[:, s.nq:], 0.0)  # at rest
    assert np.asarray(task.robustness_states(cfg, 3, 7, jnp.float32)).dtype == np.float32
    radii = (0.0, 0.2)
    d = np.asarray(task.disturbed_states(cfg, radii, 3, 5, jnp.float64))
    M = cfg.task.num_conditions
    assert d.shape == (2, 3 * M, s.dX)
    np.testing.assert_allclose(d[0], np.repeat(np.asarray(tasks.initial_states(cfg.task)), 3, axis=0))
    extra = task.success_extra(cfg, jnp.asarray(a))
    assert all(np.asarray(v).shape == (8,) and np.asarray(v).dtype == bool for v in extra.values())


def test_config_fields_are_validated_where_they_are_defined():
    cfg = config.reach("A", "gmr")
    for group, field, bad, needle in (("sim", "substeps", 0, "sim.substeps=0"),
                                      ("sim", "backend", "gpu", "sim.backend='gpu'"),
                                      ("lqr", "max_iterations", 2.5, "lqr.max_iterations=2.5"),
                                      ("step", "step_rule", "x", "step.step_rule='x'"),
                                      ("dynamics", "max_samples", -1, "dynamics.max_samples=-1"),
                                      ("cost", "state_ramp", "cubic", "cost.state_ramp='cubic'"),
                                      ("task", "T", 0, "task.T=0"),
                                      ("task", "wrap_angles", 1, "task.wrap_angles=1"),
                                      ("sim", "clip_torques", "no", "sim.clip_torques='no'")):
        with pytest.raises(ValueError, match=needle.replace("(", r"\(").replace(".", r"\.")):
            dataclasses.replace(getattr(cfg, group), **{field: bad})
    with pytest.raises(ValueError, match="needs a gmr_jax.tasks.reach.CostConfig"):
        dataclasses.replace(cfg, cost=config.NoiseConfig())


def test_inserted_needs_the_tip_in_the_hole():
    """"inserted" is depth and place: q* is inserted; the same depth beside the fixture (the tip
    50 mm below the rim's height, 0.2 m to the side, where a flailing arm can end) is not."""
    from experiments import block_in_hole_poses as bp
    from gmr_jax.tasks import block_in_hole as bih

    cfg = config.make("block_in_hole", "C", "gmr", sim__backend="mujoco")
    m = sim.make_sim(cfg.sim).model
    beside = bp.solve_ik(m, bp.hole_rim(m) + np.array([0.2, 0.0, -0.05]), bp.rotz(bp.YAW))
    x = np.zeros((2, 12))
    x[0, :6], x[1, :6] = bih.TARGET, beside
    s = sim.make_sim(cfg.sim)
    np.testing.assert_allclose(np.asarray(bih.insertion_depth(s, jnp.asarray(x[:, :6]))), [0.05, 0.05], atol=1e-6)
    np.testing.assert_array_equal(np.asarray(bih.success_extra(cfg, jnp.asarray(x))["inserted"]), [True, False])


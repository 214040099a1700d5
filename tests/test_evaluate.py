"""Robustness evaluation: fixed states, MSE/success/distance against direct computations."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from tolerances import SAFETY, assert_close, assert_tolerances_small, assert_trees_within, linear_tol, measured_tol

from gmr_jax import config, evaluate, policies, sim, tasks


CFG = config.reach("AB", "mdgps", task__T=6, sim__backend="mujoco")


def test_robustness_states_are_fixed_and_in_range():
    a = np.asarray(evaluate.robustness_states(CFG))
    b = np.asarray(evaluate.robustness_states(CFG))
    np.testing.assert_array_equal(a, b)
    assert a.shape == (50, 12)
    q, v = a[:, :6], a[:, 6:]
    assert np.all(v == 0)
    assert np.all(np.abs(q[:, [0, 3, 4, 5]]) <= math.pi)
    assert np.all((q[:, 1:3] >= math.pi / 2) & (q[:, 1:3] <= 3 * math.pi / 2))
    # Spread over the range, not a constant.
    assert np.all(q.std(axis=0) > 0.3)


@pytest.mark.parametrize("task", ["reach", "block_in_hole"])
def test_evaluation_states_are_the_same_in_both_precisions(task):
    # JAX draws other numbers from one key in float32 than in float64: the fixed states must not
    # follow the run's precision (a float32 study evaluated other states before).
    cfg = config.make(task, None, "mdgps", sim__backend="mujoco")
    rob64, sweep64 = (np.asarray(f(cfg)) for f in (evaluate.robustness_states, evaluate.sweep_states))
    with jax.enable_x64(False):
        rob32, sweep32 = (np.asarray(f(cfg)) for f in (evaluate.robustness_states, evaluate.sweep_states))
    assert rob32.dtype == sweep32.dtype == np.float32
    np.testing.assert_array_equal(rob32, rob64.astype(np.float32))  # drawn in float64, then rounded
    # The sweep's states x0 + r·d/‖d‖ are formed in the run's precision: the norm over nq angles
    # and the four other roundings (d, the division, the product, the sum) each add at most ε
    # of |x0| + r.
    nq = 6
    x0 = np.asarray(tasks.initial_states(cfg.task))
    radii = np.asarray(tasks.of(cfg).sweep_radii)
    scale = np.max(np.abs(x0)) + np.max(radii)
    tol = (nq + 4) * np.finfo(np.float32).eps * scale
    np.testing.assert_allclose(sweep32, sweep64, rtol=0, atol=tol)
    assert np.max(np.abs(sweep64 - sweep64[:1])) > 100 * tol  # the radii spread the states


def test_robustness_matches_single_rollouts():
    params = policies.for_config(CFG).init(jax.random.PRNGKey(0), 12, 6)
    x0 = evaluate.robustness_states(CFG, num=4)
    rob = jax.jit(evaluate.robustness, static_argnums=0)(CFG, params, x0)
    s = sim.make_sim(CFG.sim)
    target = np.asarray(tasks.target_state(CFG.task))
    train = np.asarray(tasks.initial_states(CFG.task))
    def single(p, x):  # one rollout from x, its final state and final-state MSE
        mean = policies.mean_fn(policies.for_config(CFG), p)
        final = sim.rollout(s, mean, x, jnp.zeros((CFG.task.T, 6))).X[-1]
        return final, jnp.mean((final - target) ** 2)

    for i in range(4):
        # Tolerance from the computation (tests/tolerances.py): the single rollout rerun from
        # parameters and a start perturbed by ε relative, SAFETY times the spread (the batched
        # program rounds the policy's products differently; the rollout carries that forward).
        (final, mse), tol = measured_tol(single, (params, x0[i]), SAFETY)
        assert_tolerances_small((final, mse), tol, 1e-8)
        assert_trees_within((rob.final_x[i], rob.mse[i]), (final, mse), tol)
        assert bool(rob.success[i]) == (float(mse) < CFG.task.success_threshold)
        dist = np.min(np.linalg.norm(np.asarray(x0[i]) - train, axis=1))
        # A norm of 12 differences and a min: relative error ≤ c·n·ε with n = 12, κ = 1.
        assert_close(rob.distance[i], dist, linear_tol(1.0, 12))


def test_non_finite_final_state_is_a_failure():
    params = policies.for_config(CFG).init(jax.random.PRNGKey(0), 12, 6)
    x0 = jnp.full((1, 12), jnp.nan)
    rob = evaluate.robustness(CFG, params, x0)
    assert not bool(rob.success[0]) and not bool(rob.success_loose[0])


def test_disturbance_sweep_states_and_rates():
    """Radius 0 starts at the training states; radius r lies r away in the joint angles, at
    rest; the rates are the fractions of those states below each threshold."""
    params = policies.for_config(CFG).init(jax.random.PRNGKey(0), 12, 6)
    radii = [0.0, 0.3]
    rate, rate_loose, mse = evaluate.disturbance_sweep(CFG, params, radii, per_radius=2)
    assert rate.shape == (2,) and mse.shape == (2, 4)
    x0 = tasks.initial_states(CFG.task)
    # The sweep's batch and a direct evaluation are two programs: tolerance from the computation
    # (tests/tolerances.py), the direct evaluation rerun on inputs perturbed by ε relative.
    direct, tol = measured_tol(lambda p, x: evaluate.robustness(CFG, p, x).mse, (params, jnp.repeat(x0, 2, axis=0)),
                               SAFETY)
    assert_tolerances_small(direct, tol, 1e-8)
    assert_trees_within(mse[0], direct, tol)
    states = np.asarray(tasks.of(CFG).disturbed_states(CFG, radii, 2, evaluate.ROBUSTNESS_KEY + 1))
    base = np.repeat(np.asarray(x0), 2, axis=0)
    # a norm of 6 differences: relative error ≤ c·n·ε with n = 6, κ = 1
    assert_close(np.linalg.norm(states[1] - base, axis=-1), np.full(4, 0.3), linear_tol(1.0, 6))
    np.testing.assert_array_equal(states[:, :, 6:], 0.0)
    mse = np.asarray(mse)
    np.testing.assert_array_equal(np.asarray(rate), (mse < CFG.task.success_threshold).mean(axis=1))
    np.testing.assert_array_equal(np.asarray(rate_loose), (mse < CFG.task.success_threshold_loose).mean(axis=1))


def test_config_round_trips_through_its_json_and_rejects_unknown_fields():
    """A run's config.json rebuilds the same (hashable, jit-static) Config; typos are named."""
    import json

    cfg = config.reach("AB", "gmr", gmr__alpha=0.3, task__T=20, sample_on_policy=True)
    again = config.from_dict(json.loads(config.to_json(cfg)))
    assert again == cfg and hash(again) == hash(cfg)
    for bad, name in (({"gmr": {"alph": 1.0}}, "alph"), ({"foo": 1}, "foo")):
        with pytest.raises(ValueError, match=name):
            config.from_dict(bad)


def test_wrap_angles_counts_whole_turns_of_continuous_joints_as_no_error():
    wrap = config.reach("A", "mdgps", task__wrap_angles=True)
    raw = config.reach("A", "mdgps")
    target = np.asarray(tasks.target_state(raw.task))
    turned = target.copy()
    turned[3] -= 2 * np.pi  # joint 4 (continuous): the target's 4.45 rad seen as −1.83
    limited = target.copy()
    limited[1] -= 2 * np.pi  # joint 2 has limits: a turn is a real error
    x = jnp.asarray(np.stack([turned, limited]))
    got_wrap, got_raw = np.asarray(evaluate.task_mse(wrap, x)), np.asarray(evaluate.task_mse(raw, x))
    turn_mse = (2 * np.pi) ** 2 / 12
    # Two roundings at magnitude 2π + 4.45 (the turn, the wrap), squared and averaged.
    assert got_wrap[0] <= (linear_tol(1.0, 2) * (2 * np.pi + 4.45)) ** 2
    assert_close(got_wrap[1], turn_mse, linear_tol(1.0, 14))
    assert_close(got_raw, [turn_mse, turn_mse], linear_tol(1.0, 14))
    assert tasks.wrapped_entries(wrap.task) == (0, 3, 4, 5) and tasks.wrapped_entries(raw.task) == ()


def test_random_angles_around_target_are_the_same_configurations():
    raw = config.reach("A", "mdgps")
    around = config.reach("A", "mdgps", task__random_angles_around_target=True)
    a, b = np.asarray(evaluate.robustness_states(raw)), np.asarray(evaluate.robustness_states(around))
    target = np.asarray(tasks.target_state(raw.task))
    turns = (b - a) / (2 * np.pi)
    # Whole turns only, and only on the continuous joints (1, 4, 5, 6).
    np.testing.assert_allclose(turns, np.round(turns), rtol=0, atol=linear_tol(1.0, 2))
    moved = np.any(np.round(turns) != 0, axis=0)
    assert not moved[[1, 2]].any() and not moved[6:].any()
    assert moved[3]  # joint 4's target 4.45 lies outside the drawn [−π, π]: most states move
    d = b[:, [0, 3, 4, 5]] - target[[0, 3, 4, 5]]
    assert np.all((d >= -np.pi) & (d < np.pi))
    np.testing.assert_array_equal(b[:, [1, 2]], a[:, [1, 2]])


def test_evaluation_is_robustness_sweep_and_training_rollouts_in_one_batch():
    """``evaluation`` executes the robustness states, the sweep's states and the training states
    as one batch: each part equals its own evaluation up to the rounding of the policy's batched
    products (tolerance measured from the separate evaluations)."""
    params = policies.for_config(CFG).init(jax.random.PRNGKey(0), 12, 6)
    ev = jax.jit(evaluate.evaluation, static_argnums=0)(CFG, params)

    def separate(p):
        rob = evaluate.robustness(CFG, p)
        _, _, sweep_mse = evaluate.disturbance_sweep(CFG, p)
        return rob.mse, rob.X, sweep_mse, evaluate.execute_policy(CFG, p, tasks.initial_states(CFG.task)).X

    ref, tol = measured_tol(jax.jit(separate), (params,), SAFETY)
    assert_tolerances_small(ref, tol, 1e-8)
    assert_trees_within((ev.robustness.mse, ev.robustness.X, ev.sweep[2], ev.training.X), ref, tol)
    np.testing.assert_array_equal(ev.robustness.x0, evaluate.robustness_states(CFG))
    # the rates are the sweep's successes per radius
    np.testing.assert_array_equal(ev.sweep[0], np.mean(np.asarray(ev.sweep[2]) < CFG.task.success_threshold, axis=1))
    assert ev.training.X.shape == (2, CFG.task.T, 12)

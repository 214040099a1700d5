"""The GPS iteration on the simulated arm: learning, jit/vmap consistency, on-policy sampling.

Short horizons and tiny S-steps keep the compile and run times within the CPU budget; the same
configurations are shared by several tests so each function compiles once per process.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from tolerances import SAFETY, assert_tolerances_small, assert_trees_within, measured_tol

from gmr_jax import config, mdgps


def small(algorithm: str, **overrides) -> config.Config:
    """A small but complete configuration of ``algorithm`` (T = 8, 2 samples, 2-epoch S-steps)."""
    base = dict(iterations=2, num_samples=2, task__T=8, sim__backend="mujoco",
                dynamics__em_iterations=10, policy_prior__em_iterations=10,
                sstep__epochs=2, sstep__batch_size=4)
    base.update(overrides)
    return config.reach("A", algorithm, **base)


def assert_trees_close(a, b, rtol=1e-9, atol=1e-12):
    la, ta = jax.tree_util.tree_flatten(a)
    lb, tb = jax.tree_util.tree_flatten(b)
    assert ta == tb
    for x, y in zip(la, lb):
        if jnp.issubdtype(jnp.asarray(x).dtype, jax.dtypes.prng_key):
            x, y = jax.random.key_data(x), jax.random.key_data(y)
        np.testing.assert_allclose(np.asarray(x), np.asarray(y), rtol=rtol, atol=atol)


def test_lqr_base_layer_lowers_the_cost():
    cfg = config.reach("A", "lqr", iterations=3, num_samples=3, task__T=20, sim__backend="mujoco",
                       dynamics__em_iterations=20)
    _, hist = jax.jit(mdgps.train, static_argnums=0)(cfg, jax.random.PRNGKey(0))
    cost = np.asarray(hist["sample_cost"])[:, 0]
    assert np.all(np.asarray(hist["ok"]))
    assert np.all(np.isfinite(cost))
    # The controllers start by holding the initial pose; every C-step must improve on it.
    assert cost[-1] < 0.8 * cost[0], cost
    mse = np.asarray(hist["final_state_mse_lqr"])[:, 0]
    assert mse[-1] < mse[0], mse
    # The KL constraint holds to the search tolerance at every iteration.
    kl, eps = np.asarray(hist["kl"])[:, 0], np.asarray(hist["epsilon"])[:, 0]
    np.testing.assert_array_less(np.abs(kl - eps), 0.1 * eps + 1e-9)


def test_block_in_hole_base_layer_lowers_the_insertion_cost():
    """The contact task's short CPU training: the peg cost on the block's points falls and the
    block's tip moves down towards the hole (tip depth below the rim, from the noiseless runs)."""
    from gmr_jax import sim
    from gmr_jax.tasks import block_in_hole as bih

    cfg = config.make("block_in_hole", "C", "lqr", iterations=3, num_samples=3, task__T=20,
                      sim__backend="mujoco", dynamics__em_iterations=20)
    _, hist = jax.jit(mdgps.train, static_argnums=0)(cfg, jax.random.PRNGKey(0))
    cost = np.asarray(hist["sample_cost"])[:, 0]
    assert np.all(np.asarray(hist["ok"])) and np.all(np.isfinite(cost))
    assert cost[-1] < cost[0], cost  # the peg cost's log term makes it negative near the goal
    depth = np.asarray(bih.insertion_depth(sim.make_sim(cfg.sim), jnp.asarray(hist["eval_final_x"])[:, 0, :6]))
    # the tip starts 55 mm above the rim (1 s horizon): it must come down by more than 20 mm
    assert depth[-1] - depth[0] > 0.02, depth


_iteration_jit = jax.jit(mdgps.iteration, static_argnums=0)


def _run_from(cfg, state, keys):
    """What ``mdgps.train`` runs after ``init``, one jitted iteration at a time (the first
    flagged); returns (final state, history with a leading iteration axis)."""
    state, metrics = _iteration_jit(cfg, state, keys[0], jnp.asarray(True))
    hist = [metrics]
    for k in keys[1:]:
        state, metrics = _iteration_jit(cfg, state, k, jnp.asarray(False))
        hist.append(metrics)
    return state, jax.tree_util.tree_map(lambda *a: jnp.stack(a), *hist)


def test_policy_iteration_jit_equals_eager():
    # GMR's iteration only: MDGPS's runs the same stages with the MLP policy in GMR's place
    # (gmr_jax.policies), and the MLP's S-step is compared with its eager run in test_sstep.py
    # (test_jit_equals_nojit_and_vmap_equals_loop). Not compared eager against jit for the MLP:
    # the policy's linearisation with the prior's update, the S-step's data without the state
    # marginals, the catch-up's lax.cond over the MLP's parameters and the learning curve's
    # rollout of its mean; each is the same code as GMR's around another policy's functions. An
    # eager iteration compiles each of its operations as a program of its own: with both
    # algorithms this test took 117 s of the suite, with GMR's alone 79 s (benchmarks/RESULTS.md,
    # forty-sixth session).
    cfg = small("gmr")
    state = mdgps.init(cfg, jax.random.PRNGKey(1))
    key = jax.random.PRNGKey(2)
    # Tolerance from the computation (tests/tolerances.py): jit and eager round differently at
    # every operation of the iteration (rollouts, EM, η search, Adam); the jitted iteration rerun
    # from states perturbed by ε relative shows how far such differences move each output, and
    # SAFETY times that spread bounds the jit/eager difference. Measured on a 2-core AMD EPYC
    # (when both algorithms ran here): jit and eager differ by at most 3.7× (mdgps) and 4.2× (gmr)
    # that spread, and the spread is at most 5e-9 of each output's largest entry. A fixed rtol of
    # 1e-7 per element failed there on one entry of 6336 that cancellation had made small
    # (-0.016, off by 3e-9 = 1.8e-7 of it).
    first = jnp.asarray(True)
    jitted, tol = measured_tol(lambda s: _iteration_jit(cfg, s, key, first), (state,), SAFETY)
    assert_tolerances_small(jitted, tol, 1e-5)
    eager = mdgps.iteration(cfg, state, key, first)
    assert_trees_within(eager, jitted, tol)
    assert np.all(np.asarray(jitted[1]["ok"]))
    assert np.isfinite(np.asarray(jitted[1]["final_state_mse_policy"])).all()


def _iteration_in_parts(cfg, groups):
    """``mdgps.iteration`` as the runner compiles it in parts: each group of parts a jitted
    program of its own (``mdgps.part_program``), the carry passed between them."""
    programs = [jax.jit(mdgps.part_program(names), static_argnums=0) for names in groups]

    def step(state, key, first):
        carry = {"state": state, "key": key}
        for program in programs:
            carry.update(program(cfg, carry, first))
        return mdgps.iteration_result(carry)
    return step


@pytest.mark.parametrize("algorithm", ["mdgps", "gmr"])
def test_iteration_in_separate_programs_equals_the_whole_program(algorithm):
    # The runner may compile an iteration as the programs of its parts (runner.ITERATION_PARTS,
    # or runner.SPLIT_PARTS, some of them on another device);
    # they are the same computation split at stage boundaries, so the two differ only where XLA
    # fuses and orders sums differently across a boundary: within the tolerance measured from
    # ε-perturbed inputs (tests/tolerances.py), for the first iteration (catch-up S-step) and a
    # later one. Every part is used once, in ``mdgps.ITERATION_PARTS``' order.
    from gmr_jax import runner

    for groups in (runner.ITERATION_PARTS, runner.SPLIT_PARTS):
        assert [n for g in groups for n in g] == list(mdgps.ITERATION_PARTS)
    assert set(runner.HOST_PARTS) <= set(runner.SPLIT_PARTS)
    cfg = small(algorithm)
    state = mdgps.init(cfg, jax.random.PRNGKey(1))
    groupings = [_iteration_in_parts(cfg, groups) for groups in (runner.ITERATION_PARTS, runner.SPLIT_PARTS)]
    for first, key in ((True, jax.random.PRNGKey(2)), (False, jax.random.PRNGKey(3))):
        flag = jnp.asarray(first)
        whole, tol = measured_tol(lambda s: _iteration_jit(cfg, s, key, flag), (state,), SAFETY)
        assert_tolerances_small(whole, tol, 1e-5)
        for in_parts in groupings:
            assert_trees_within(in_parts(state, key, flag), whole, tol)
        state = whole[0]
    assert int(state.iteration) == 2


def test_a_part_may_not_replace_an_entry_of_the_carry():
    cfg = small("lqr")
    state = jax.eval_shape(lambda k: mdgps.init(cfg, k), jax.random.PRNGKey(1))
    with pytest.raises(ValueError, match="would replace"):
        jax.eval_shape(lambda s: mdgps.run_parts(cfg, ("rollouts", "rollouts"), {"state": s, "key": jax.random.PRNGKey(0)},
                                                 jnp.asarray(True)), state)


def test_first_iteration_defaults_to_the_state_counter(monkeypatch):
    # Without the flag ``iteration`` takes the first iteration from ``state.iteration == 0``; the
    # flag then reaches the stages as the explicit one would (checked at the first stage, which
    # stops the iteration there, so nothing is computed or compiled).
    class Reached(Exception):
        pass

    seen = []

    def first_stage(cfg, state, x0, key, first):
        seen.append(bool(first))
        raise Reached

    monkeypatch.setattr(mdgps, "sample_stage", first_stage)
    cfg = small("mdgps")
    abstract = jax.eval_shape(lambda k: mdgps.init(cfg, k), jax.random.PRNGKey(1))
    for count in (0, 1, 3):
        state = abstract._replace(iteration=jnp.asarray(count, abstract.iteration.dtype))
        for flag in (None, count == 0):
            with pytest.raises(Reached):
                mdgps.iteration(cfg, state, jax.random.PRNGKey(2), flag)
    assert seen == [True, True, False, False, False, False]


def test_train_traces_the_update_once(monkeypatch):
    # ``train``'s last scan step skips the update through a ``lax.cond`` whose skipped branch
    # needs the update's metric shapes; they come from the traced branch, not from tracing the
    # update again (that Python tracing is a large part of the program's lowering). Tracing only.
    calls = []
    update = mdgps.update
    monkeypatch.setattr(mdgps, "update", lambda *a, **k: calls.append(1) or update(*a, **k))
    cfg = small("mdgps")
    final, history = jax.eval_shape(lambda k: mdgps.train(cfg, k), jax.random.PRNGKey(0))
    assert len(calls) == 1
    assert history["sample_cost"].shape[0] == cfg.iterations


@pytest.fixture(scope="module")
def vmapped_mdgps_runs():
    cfg = small("mdgps")
    keys = jnp.stack([jax.random.PRNGKey(s) for s in (0, 1, 2)])
    train = jax.jit(mdgps.train, static_argnums=0)
    finals, hists = jax.jit(jax.vmap(mdgps.train, in_axes=(None, 0)), static_argnums=0)(cfg, keys)
    return cfg, keys, train, finals, hists


def test_vmap_over_keys_equals_separate_runs(vmapped_mdgps_runs):
    cfg, keys, train, finals, hists = vmapped_mdgps_runs
    for i in range(keys.shape[0]):
        final_i, hist_i = train(cfg, keys[i])
        pick = lambda t: jax.tree_util.tree_map(lambda a: a[i], t)  # noqa: E731
        # Batched and unbatched matrix products sum in different orders, and two iterations of
        # EM fits and η searches amplify those ε differences. Tolerance from the computation
        # (tests/tolerances.py): the same two iterations rerun from the run's initial state
        # perturbed by ε relative, SAFETY times their spread.
        k_init, iter_keys = mdgps.iteration_keys(keys[i], cfg.iterations)
        ref, tol = measured_tol(lambda s: _run_from(cfg, s, iter_keys), (mdgps.init(cfg, k_init),), SAFETY)
        assert_tolerances_small(ref, tol, 1e-4)
        assert_trees_within(final_i, ref[0], tol[:len(jax.tree_util.tree_leaves(final_i))])
        assert_trees_within((pick(finals), pick(hists)), (final_i, hist_i), tol)
    # Different keys give different runs.
    assert not np.allclose(np.asarray(hists["sample_cost"][0]), np.asarray(hists["sample_cost"][1]))


def test_sampling_the_global_policy_applies_its_noisy_action():
    """``sample_on_policy``'s rollouts: every applied torque is the clipped u = mean(x) + L·ε_t of
    the global policy at the visited state, with the toolbox's smoothed noise of the sample key."""
    from gmr_jax import noise as noise_lib
    from gmr_jax import policies, tasks
    from gmr_jax import sim as sim_lib

    cfg = small("gmr", sample_on_policy=True)
    s = sim_lib.make_sim(cfg.sim)
    params = mdgps.init(cfg, jax.random.PRNGKey(3)).policy.params
    pol = policies.for_config(cfg)
    x0 = tasks.initial_states(cfg.task)[:1]
    key = jax.random.PRNGKey(4)
    trajs = jax.jit(lambda p, k: mdgps.sample(cfg, policies.sampling_fn(pol, p), x0, k, 2))(params, key)
    keys = jax.random.split(key, (1, 2))
    for n in range(2):
        eps = noise_lib.smooth_noise(keys[0, n], cfg.task.T, s.dU, cfg.noise).astype(x0.dtype)
        X = trajs.X[0, n]
        # Tolerance from the computation (tests/tolerances.py): the eager noisy actions rerun on
        # parameters, states and noise perturbed by ε relative, SAFETY times the spread.
        u, tol = measured_tol(lambda p, x, e: jax.vmap(lambda xx, ee: policies.noisy_action(pol, p, xx, ee))(x, e),
                              (params, X, eps), SAFETY)
        assert_tolerances_small(u, tol, 1e-8)
        assert_trees_within(trajs.U[0, n], sim_lib.clip_torques(s, u), tol)
        # the noise is there: the applied torques are not the policy means
        assert not np.allclose(trajs.U[0, n], jax.vmap(lambda x: pol.mean(params, x))(X), atol=1e-6)


def test_one_batched_rollout_equals_the_separate_rollouts():
    """``train``'s one batched MJX rollout per iteration (``rollout_stage``: samples, noiseless
    controllers, noiseless policy; here the samples explore with the policy, so every row kind
    is there) and the learning curve's batched pair (``evaluate.execute_pair``) give what
    separate rollouts of each controller give: ``sample_stage``'s samples and the metrics of
    ``evaluate.execute`` of the controllers and of the policy, for the same state and key.
    Tolerance from the computation (tests/tolerances.py): the separate rollouts rerun on the
    state perturbed by ε relative, SAFETY times the spread."""
    from gmr_jax import evaluate, policies, tasks

    cfg = config.reach("AB", "mdgps", task__T=6, num_samples=2, sim__backend="mjx", sample_on_policy=True)
    state = jax.jit(lambda k: mdgps.init(cfg, k))(jax.random.PRNGKey(0))
    x0 = tasks.initial_states(cfg.task)
    key, first = jax.random.PRNGKey(3), jnp.asarray(False)
    mean = lambda st: policies.mean_fn(policies.for_config(cfg), st.policy.params)  # noqa: E731

    @jax.jit
    def separate(st, f):
        curve = mdgps._curve_metrics(cfg, evaluate.execute(cfg, st.traj, x0), evaluate.execute(cfg, mean(st), x0))
        return mdgps.sample_stage(cfg, st, x0, key, f), curve

    ref, tol = measured_tol(lambda st: separate(st, first), (state,), SAFETY)
    assert_tolerances_small(ref, tol, 1e-8)
    got = jax.jit(lambda st: mdgps.rollout_stage(cfg, st, x0, key, first))(state)
    assert_trees_within(got, ref, tol)
    pair = jax.jit(lambda st: mdgps.learning_curve(cfg, st.traj, st.policy, x0))(state)
    assert_trees_within(pair, ref[1], tol[len(jax.tree_util.tree_leaves(ref[0])):])
    np.testing.assert_array_equal(np.asarray(pair["eval_ee"].shape), (x0.shape[0], cfg.task.T, 3))
    # the samples are the policy's noisy rollouts, not the controllers' (the row kinds differ)
    local = separate(state, jnp.asarray(True))[0]
    assert not np.allclose(got[0].U[:, :, 1:], local.U[:, :, 1:], atol=1e-6)


def test_in_float32_rounds_inputs_and_widens_outputs():
    def stage(a, b):
        return a * b + 1.0, {"sum": jnp.sum(a), "n": jnp.arange(2)}

    a, b = jnp.asarray([1 / 3, 2 / 3]), jnp.asarray([3.0, 1 / 7])
    out = mdgps.in_float32("stage", stage)(a, b)
    ref = stage(a.astype(jnp.float32), b.astype(jnp.float32))
    assert out[0].dtype == out[1]["sum"].dtype == jnp.float64 and out[1]["n"].dtype == ref[1]["n"].dtype
    np.testing.assert_array_equal(np.asarray(out[0]), np.asarray(ref[0]).astype(np.float64))
    np.testing.assert_array_equal(np.asarray(out[1]["sum"]), np.float64(ref[1]["sum"]))
    assert not np.array_equal(np.asarray(out[0]), np.asarray(stage(a, b)[0]))  # not float64 arithmetic
    with pytest.raises(TypeError, match="mixes in float64"):
        mdgps.in_float32("leaky", lambda x: x + jnp.ones(2))(a)  # jnp.ones: float64 under x64
    with pytest.raises(ValueError, match="float64 run"):
        mdgps.in_float32("stage", stage)(a.astype(jnp.float32), b)
    with pytest.raises(ValueError, match="float32_stages"):
        small("mdgps", float32_stages=("dynamics", "sim"))
    with pytest.raises(ValueError, match="tuple"):
        small("mdgps", float32_stages="dynamics")


@pytest.mark.parametrize("algorithm", ["mdgps", "gmr"])
def test_every_stage_traces_in_float32_inside_a_float64_iteration(algorithm):
    """``in_float32`` raises when a stage mixes in float64 arithmetic: tracing the iteration with
    every stage in float32 checks each stage's code follows its inputs' dtype."""
    cfg = small(algorithm, float32_stages=config.FLOAT32_STAGES)
    state = mdgps.init(cfg, jax.random.PRNGKey(0))
    new_state, metrics = jax.eval_shape(lambda s, k: mdgps.iteration(cfg, s, k), state, jax.random.PRNGKey(1))
    dtypes = {a.dtype for a in jax.tree_util.tree_leaves((new_state, metrics))
              if jnp.issubdtype(a.dtype, jnp.floating)}
    assert dtypes == {jnp.dtype(jnp.float64)}


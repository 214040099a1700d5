"""The GPS iteration on the simulated arm: learning, jit/vmap consistency, on-policy sampling.

Short horizons and tiny S-steps keep the compile and run times within the CPU budget; the same
configurations are shared by several tests so each function compiles once per process.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

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


@pytest.mark.parametrize("algorithm", ["mdgps", "gmr"])
def test_policy_iteration_jit_equals_eager(algorithm):
    cfg = small(algorithm)
    state = mdgps.init(cfg, jax.random.PRNGKey(1))
    key = jax.random.PRNGKey(2)
    first = jnp.asarray(True)
    jitted = jax.jit(mdgps.iteration, static_argnums=0)(cfg, state, key, first)
    eager = mdgps.iteration(cfg, state, key, first)
    assert_trees_close(jitted, eager, rtol=1e-7, atol=1e-9)
    # Without the flag the first iteration is recognised from the state's counter.
    by_counter = jax.jit(mdgps.iteration, static_argnums=0)(cfg, state, key)
    assert_trees_close(by_counter, jitted, rtol=1e-7, atol=1e-9)
    assert np.all(np.asarray(jitted[1]["ok"]))
    assert np.isfinite(np.asarray(jitted[1]["final_state_mse_policy"])).all()


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
        # Batched and unbatched matrix products may sum in different orders; two iterations of
        # EM fits and η searches amplify those 1e-16 differences to ~1e-6 relative at most.
        assert_trees_close(pick(finals), final_i, rtol=2e-5, atol=1e-7)
        assert_trees_close(pick(hists), hist_i, rtol=2e-5, atol=1e-7)
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
        u = jax.vmap(lambda x, e: policies.noisy_action(pol, params, x, e))(X, eps)
        np.testing.assert_allclose(trajs.U[0, n], sim_lib.clip_torques(s, u), rtol=1e-9, atol=1e-9)
        # the noise is there: the applied torques are not the policy means
        assert not np.allclose(trajs.U[0, n], jax.vmap(lambda x: pol.mean(params, x))(X), atol=1e-6)

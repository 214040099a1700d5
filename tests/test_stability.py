"""gmr_jax.stability: the spectral radius, and the chain-rule Jacobian of the closed loop
against central differences of the whole closed-loop step (an independent computation)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gmr_jax import config, evaluate, mdgps, policies, sim as sim_lib, stability

STATE = np.r_[0.3, 2.9, 1.0, 4.2, 1.4, 1.3, 0.1, -0.2, 0.1, 0.3, -0.1, 0.2]


def test_spectral_radius_of_known_matrices():
    th = 0.7
    rot = 0.9 * np.array([[np.cos(th), -np.sin(th)], [np.sin(th), np.cos(th)]])  # eigenvalues 0.9·e^{±iθ}
    J = np.stack([rot, np.diag([1.5, -0.2]), np.full((2, 2), np.nan)])
    rho = stability.spectral_radius(J)
    np.testing.assert_allclose(rho[:2], [0.9, 1.5], rtol=1e-14)
    assert np.isnan(rho[2])


@pytest.fixture(scope="module", params=["gmr", "mdgps"])
def policy_run(request):
    cfg = config.reach("A", request.param, sim__backend="mujoco")
    params = mdgps.init(cfg, jax.random.PRNGKey(1)).policy.params
    return cfg, params


def _closed_loop_fd(cfg, params, x, h):
    s = sim_lib.make_sim(cfg.sim)
    pol = policies.for_config(cfg)
    f = lambda xx: np.asarray(sim_lib.step(s, jnp.asarray(xx), pol.mean(params, jnp.asarray(xx))))  # noqa: E731
    steps = h * np.maximum(1.0, np.abs(x))
    return np.stack([(f(x + d) - f(x - d)) / (2 * d.max()) for d in np.eye(x.size) * steps], axis=1)


def test_closed_loop_jacobian_matches_differences_of_the_whole_step(policy_run):
    cfg, params = policy_run
    J = stability.closed_loop_jacobians(cfg, params, STATE[None])[0]
    fd1 = _closed_loop_fd(cfg, params, STATE, 1e-6)
    fd2 = _closed_loop_fd(cfg, params, STATE, 2e-6)
    # Central differences err by c·h² (truncation) + ε·|f|/h (rounding): the two step sizes'
    # difference estimates the truncation part (3·c·h² for h and 2h), and the rounding bound is
    # added for both estimates (the chain rule's plant differences use the same h).
    scale = np.abs(fd1).max()
    rounding = np.finfo(float).eps * 10.0 / 1e-6 * max(1.0, np.abs(STATE).max())
    tol = np.abs(fd2 - fd1).max() + 4 * rounding * scale
    assert np.abs(J - fd1).max() <= tol, (np.abs(J - fd1).max(), tol)


def test_measure_on_given_and_own_rollouts(policy_run):
    cfg, params = policy_run
    batched = jax.tree_util.tree_map(lambda a: jnp.stack([a, a]), params)
    out = stability.measure(cfg, batched, every=40)
    R = 50
    assert out.radius.shape == (2, R, 2) and out.target_radius.shape == (2,)
    np.testing.assert_array_equal(out.radius[0], out.radius[1])  # the same policy twice
    assert ((0 <= out.contracting) & (out.contracting <= 1)).all()
    assert np.isclose(out.contracting[0], np.mean(out.radius[0] < 1))
    # the robustness test's own rollouts (what the runner passes) give the same states
    X = evaluate.robustness(cfg, params).X
    given = stability.measure(cfg, jax.tree_util.tree_map(lambda a: a[None], params), X=X[None], every=40)
    np.testing.assert_array_equal(given.radius[0], out.radius[0])


def test_warm_up_prepares_the_program_that_measure_runs(policy_run):
    """After ``warm_up`` for policies of these shapes, ``measure`` along the robustness test's
    rollouts adds no entry to the policy program's cache (nothing traced or compiled anew): the
    runner's warm-up while training covers the measurement."""
    cfg, params = policy_run
    batched = jax.tree_util.tree_map(lambda a: jnp.stack([a, a]), params)
    stability.warm_up(cfg, jax.eval_shape(lambda: batched))  # shapes are enough
    traced = stability._policy_terms._cache_size()
    dtype = jax.tree_util.tree_leaves(params)[0].dtype
    X = np.zeros((2, evaluate.ROBUSTNESS_STATES, cfg.task.T, 12), dtype)
    stability.measure(cfg, jax.device_get(batched), X=X)  # as the runner calls it
    assert stability._policy_terms._cache_size() == traced

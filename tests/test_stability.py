"""gmr_jax.stability: the closed loop's Jacobian (MJX autodiff and the policy's JAX derivative)
against central finite differences of the same closed loop stepped in C MuJoCo."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gmr_jax import evaluate, mdgps, sim, stability
from test_mdgps import small


@pytest.fixture(scope="module", params=["gmr"])
def trained(request):
    cfg = small(request.param, task__T=4)
    return cfg, mdgps.init(cfg, jax.random.PRNGKey(3)).policy.params


def test_jacobian_matches_finite_differences_of_the_c_mujoco_closed_loop(trained):
    """Central differences with h = 1e-6 rad (rad/s): truncation O(h²·|f'''|) ~ 1e-12, rounding
    ~ ε·|x'|/h ~ 1e-9 per entry (|x'| ≲ 5), and the two engines agree on a free-space step to
    about 1e-12; so the entries must agree to 1e-6 of the Jacobian's largest entry, a bound a
    wrong chain rule (a missing ∂f/∂u·∂u/∂x term) misses by orders of magnitude."""
    cfg, params = trained
    x = jnp.asarray(evaluate.robustness_states(cfg, 1)[0]).at[6:].set(0.3)
    J = np.asarray(stability.closed_loop_jacobian(cfg, params, x))
    s = sim.make_sim(cfg.sim)  # C MuJoCo
    policy = evaluate._global_policy(cfg)
    step = jax.jit(lambda x: sim.step(s, x, policy.mean(params, x)))
    h = 1e-6
    fd = np.stack([(np.asarray(step(x.at[i].add(h))) - np.asarray(step(x.at[i].add(-h)))) / (2 * h)
                   for i in range(x.shape[0])], axis=1)
    np.testing.assert_allclose(J, fd, atol=1e-6 * np.abs(J).max())
    # the policy's feedback matters: with u held fixed (no ∂u/∂x) the Jacobian is another matrix
    u = policy.mean(params, x)
    s_mjx = sim.make_sim(dataclasses.replace(cfg.sim, backend="mjx"))
    plant_only = np.asarray(jax.jacfwd(lambda y: sim.step(s_mjx, y, u))(x))
    assert np.abs(plant_only - J).max() > 1e-3 * np.abs(J).max()


def test_stability_reports_radii_along_the_rollouts(trained):
    cfg, params = trained
    x0 = evaluate.robustness_states(cfg, 3)
    st = stability.stability(cfg, params, x0)
    assert st.radius.shape == (3, cfg.task.T)
    np.testing.assert_allclose(st.contracting, (st.radius < 1).mean(axis=1))
    X = evaluate.execute_policy(cfg, params, x0).X
    J = stability.closed_loop_jacobian(cfg, params, X[1, 2])
    assert st.radius[1, 2] == pytest.approx(np.abs(np.linalg.eigvals(np.asarray(J))).max(), rel=1e-12)
    assert np.isfinite(st.target_radius) and st.target_radius > 0

"""gmr_jax.linalg against LAPACK (numpy/scipy), and the absence of LAPACK calls on the CPU."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.linalg as sl

from gmr_jax import config, linalg, mdgps


def _spd(rng, shape, n):
    a = rng.normal(size=shape + (n, n))
    return a @ np.swapaxes(a, -1, -2) + 0.1 * np.eye(n)


def test_cholesky_matches_lapack():
    rng = np.random.default_rng(0)
    a = _spd(rng, (4, 3), 18)
    low = np.asarray(jax.jit(linalg.cholesky)(a))
    np.testing.assert_allclose(low, np.linalg.cholesky(a), rtol=1e-12, atol=1e-13)
    # Only the symmetric part counts (as jnp.linalg.cholesky).
    skew = rng.normal(size=a.shape)
    np.testing.assert_allclose(linalg.cholesky(a + skew - np.swapaxes(skew, -1, -2)), low, atol=1e-12)


def test_cholesky_of_a_non_pd_matrix_is_all_nan():
    rng = np.random.default_rng(1)
    a = _spd(rng, (2,), 6)
    a[0, 3, 3] = -1.0
    low = np.asarray(linalg.cholesky(a))
    assert np.isnan(low[0]).all()
    assert np.isfinite(low[1]).all()


@pytest.mark.parametrize("lower", [True, False])
@pytest.mark.parametrize("trans", [False, True])
def test_solve_triangular_matches_lapack(lower, trans):
    rng = np.random.default_rng(2)
    low = np.linalg.cholesky(_spd(rng, (5,), 12))
    a = low if lower else np.swapaxes(low, -1, -2)
    b = rng.normal(size=(5, 12, 3))
    x = np.asarray(linalg.solve_triangular(a, b, lower=lower, trans=trans))
    for i in range(5):
        ref = sl.solve_triangular(a[i], b[i], lower=lower, trans=1 if trans else 0)
        np.testing.assert_allclose(x[i], ref, rtol=1e-12, atol=1e-12)


def test_cho_solve_and_vmap():
    rng = np.random.default_rng(3)
    a = _spd(rng, (3, 4), 8)
    b = rng.normal(size=(3, 4, 8, 2))
    x = jax.vmap(jax.vmap(lambda a_, b_: linalg.cho_solve(linalg.cholesky(a_), b_)))(a, b)
    np.testing.assert_allclose(x, np.linalg.solve(a, b), rtol=1e-10, atol=1e-11)
    with pytest.raises(ValueError, match="must be"):
        linalg.solve_triangular(a, b[..., 0], lower=True)


def test_cholesky_is_differentiable():
    rng = np.random.default_rng(4)
    a = _spd(rng, (), 5)
    f = lambda m: jnp.sum(jnp.log(jnp.diagonal(linalg.cholesky(m))))  # ½ log|m|  # noqa: E731
    g = np.asarray(jax.grad(f)(a))
    np.testing.assert_allclose(0.5 * (g + g.T), 0.5 * np.linalg.inv(a), rtol=1e-9, atol=1e-10)


def test_mdgps_iteration_lowers_to_no_lapack_call_on_cpu():
    """The XLA:CPU hang needs a batched LAPACK call (README, known issues): there must be none."""
    for algorithm in ("mdgps", "gmr"):
        cfg = config.reach("A", algorithm, iterations=2, num_samples=2, task__T=4, sim__backend="mujoco",
                            sstep__batch_size=4, sstep__epochs=1)
        state = jax.eval_shape(lambda k: mdgps.init(cfg, k), jax.random.PRNGKey(0))
        # The CLI's program: both first-iteration branches, under one lax.cond.
        text = jax.jit(mdgps.iteration, static_argnums=0).lower(
            cfg, state, jax.random.PRNGKey(1), jnp.asarray(True)).as_text()
        assert "lapack" not in text.lower(), algorithm

"""gmr_jax.linalg against LAPACK (numpy/scipy), and the absence of LAPACK calls on the CPU."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.linalg as sl

from tolerances import assert_close, linear_tol

from gmr_jax import config, linalg, mdgps


def _spd(rng, shape, n):
    a = rng.normal(size=shape + (n, n))
    return a @ np.swapaxes(a, -1, -2) + 0.1 * np.eye(n)


def test_cholesky_matches_lapack():
    rng = np.random.default_rng(0)
    a = _spd(rng, (4, 3), 18)
    low = np.asarray(jax.jit(linalg.cholesky)(a))
    ref = np.linalg.cholesky(a)
    # Both factorisations are backward stable: each factor is within c·n·ε·κ(A) of the exact
    # one, normwise (tests/tolerances.py), so they are within twice that of each other.
    kappa = np.linalg.cond(a)  # [4, 3]
    for idx in np.ndindex(a.shape[:2]):
        assert_close(low[idx], ref[idx], 2 * linear_tol(kappa[idx], 18), f"matrix {idx}")
    # Only the symmetric part counts (as jnp.linalg.cholesky). Forming it from a + S − Sᵀ rounds
    # at the size of S: the input moves by ε·(‖A‖ + 2‖S‖), amplified by κ(A) as above.
    skew = rng.normal(size=a.shape)
    got = np.asarray(linalg.cholesky(a + skew - np.swapaxes(skew, -1, -2)))
    for idx in np.ndindex(a.shape[:2]):
        growth = 1.0 + 2.0 * np.linalg.norm(skew[idx], 2) / np.linalg.norm(a[idx], 2)
        assert_close(got[idx], low[idx], 2 * linear_tol(kappa[idx] * growth, 18), f"matrix {idx}")


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
        # Triangular substitution is backward stable: forward error ≤ c·n·ε·κ(T) normwise, for
        # each of the two programs (tests/tolerances.py).
        assert_close(x[i], ref, 2 * linear_tol(np.linalg.cond(a[i]), 12), f"matrix {i}")


def test_cho_solve_and_vmap():
    rng = np.random.default_rng(3)
    a = _spd(rng, (3, 4), 8)
    b = rng.normal(size=(3, 4, 8, 2))
    x = jax.vmap(jax.vmap(lambda a_, b_: linalg.cho_solve(linalg.cholesky(a_), b_)))(a, b)
    ref = np.linalg.solve(a, b)
    # Cholesky solve and LU solve are both backward stable: each within c·n·ε·κ(A) of the exact
    # solution, normwise (tests/tolerances.py).
    kappa = np.linalg.cond(a)
    for idx in np.ndindex(a.shape[:2]):
        assert_close(x[idx], ref[idx], 2 * linear_tol(kappa[idx], 8), f"system {idx}")
    with pytest.raises(ValueError, match="must be"):
        linalg.solve_triangular(a, b[..., 0], lower=True)


def test_cholesky_is_differentiable():
    rng = np.random.default_rng(4)
    a = _spd(rng, (), 5)
    f = lambda m: jnp.sum(jnp.log(jnp.diagonal(linalg.cholesky(m))))  # ½ log|m|  # noqa: E731
    g = np.asarray(jax.grad(f)(a))
    # The gradient ½A⁻¹ goes through the factor and two triangular solves (backward stable,
    # each c·n·ε·κ(A) normwise, tests/tolerances.py); numpy's inverse likewise.
    assert_close(0.5 * (g + g.T), 0.5 * np.linalg.inv(a), 3 * linear_tol(np.linalg.cond(a), 5))


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


def _transition_covariance(rng, n_points=400, dx=12, du=6):
    """The covariance of points [x, u, x'] with x' = F [x; u] exactly (a deterministic plant):
    rank dx + du of D = 2dx + du, scales of joint angles, velocities and torques."""
    x = rng.normal(size=(n_points, dx)) * np.r_[np.full(dx // 2, 0.3), np.full(dx - dx // 2, 2.0)]
    u = 3.0 * rng.normal(size=(n_points, du))
    xu = np.concatenate([x, u], axis=1)
    F = np.eye(dx, dx + du) + 0.05 * rng.normal(size=(dx, dx + du))
    y = np.concatenate([xu, xu @ F.T], axis=1)
    return np.cov(y.T, bias=True)


def _lambda_min_scaled(a) -> float:
    """λ_min of D⁻¹AD⁻¹, D² = diag(A), computed in float64 (the quantity of Demmel's theorem)."""
    a = np.asarray(a, np.float64)
    d = np.sqrt(np.diag(a))
    return float(np.linalg.eigvalsh(a / np.outer(d, d)).min())


def test_ridge_is_bitwise_the_absolute_ridge_in_float64():
    a = _transition_covariance(np.random.default_rng(2))
    got = np.asarray(linalg.ridge(jnp.asarray(a), 1e-6))
    np.testing.assert_array_equal(got, a + 1e-6 * np.eye(a.shape[0]))


def test_ridge_makes_a_rank_deficient_float32_covariance_factorisable():
    a = _transition_covariance(np.random.default_rng(3)).astype(np.float32)
    n = a.shape[0]
    demmel = n * (n + 1) * np.finfo(np.float32).eps  # λ_min(H) above this: Cholesky completes
    # The toolbox's absolute 1e-6 ridge leaves the scaled matrix below the theorem's threshold:
    # no guarantee in float32 (it fails or not with the rounding of the CPU at hand).
    plain = a + np.float32(1e-6) * np.eye(n, dtype=np.float32)
    assert _lambda_min_scaled(plain) < demmel
    ridged = linalg.ridge(jnp.asarray(a), 1e-6)
    assert ridged.dtype == jnp.float32
    assert _lambda_min_scaled(ridged) > demmel
    for chol in (jax.jit(linalg.cholesky), jnp.linalg.cholesky):  # the CPU columns and LAPACK
        low = np.asarray(chol(ridged), np.float64)
        assert np.isfinite(low).all()
        # backward stable: L Lᵀ reproduces the input to c·n·ε relative (Higham Thm 10.3)
        err = np.abs(low @ low.T - np.asarray(ridged, np.float64)).max() / np.abs(a).max()
        assert err < 4 * n * np.finfo(np.float32).eps

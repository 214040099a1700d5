"""Dynamics fit with the GMM prior: closed forms against numpy, recovery of a linear system,
the prior's pull with few samples, ring buffer, initial state, masks, vmap over conditions."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.special import logsumexp
from scipy.stats import multivariate_normal

from tolerances import SAFETY, assert_close, assert_tolerances_small, assert_trees_within, linear_tol, measured_tol

from gmr_jax.config import DynamicsConfig
from gmr_jax.dynamics import (dynamics_ok, dynamics_prior_empty, fit_dynamics, prior_initial_state, update_dynamics_prior)
from gmr_jax.prior import gauss_fit_joint_prior, ring_insert

dX, dU, T = 3, 2, 12
CFG = DynamicsConfig(max_samples=6, max_clusters=4, min_samples_per_cluster=40, strength=1.0)

_update = jax.jit(update_dynamics_prior, static_argnums=4)
_fit = jax.jit(fit_dynamics, static_argnums=3)


def _system(seed):
    r = np.random.default_rng(seed)
    A = np.eye(dX) + 0.1 * r.normal(size=(dX, dX))
    B = 0.3 * r.normal(size=(dX, dU))
    c = 0.1 * r.normal(size=dX)
    return A, B, c


def _rollout(system, N, seed, noise=0.01, x0_std=0.1):
    A, B, c = system
    r = np.random.default_rng(seed)
    X = np.zeros((N, T, dX))
    U = r.normal(size=(N, T, dU))
    X[:, 0] = 0.5 + x0_std * r.normal(size=(N, dX))
    for t in range(T - 1):
        X[:, t + 1] = X[:, t] @ A.T + U[:, t] @ B.T + c + noise * r.normal(size=(N, dX))
    return X, U


SYS1, SYS2 = _system(1), _system(2)


@pytest.fixture(scope="module")
def prior1():
    """Prior holding 6 trajectories (two batches of 3) of system 1."""
    prior = dynamics_prior_empty(T, dX, dU, CFG, jnp.float64)
    for i in range(2):
        X, U = _rollout(SYS1, 3, 10 + i)
        prior = _update(prior, jax.random.key(i), jnp.asarray(X), jnp.asarray(U), CFG)
    return prior


# ------------------------------------------------------------------ independent numpy reference

def np_gauss_fit_joint_prior(pts, mu0, Phi, m, n0, dwts, d1, d2, sig_reg):
    N = len(dwts)
    mun = (pts * dwts[:, None]).sum(0)
    diff = pts - mun
    empsig = diff.T @ np.diag(dwts) @ diff
    sigma = (N * empsig + Phi + N * m / (N + m) * np.outer(mun - mu0, mun - mu0)) / (N + n0)
    sigma = 0.5 * (sigma + sigma.T) + sig_reg
    fd = np.linalg.solve(sigma[:d1, :d1], sigma[:d1, d1:d1 + d2]).T
    fc = mun[d1:] - fd @ mun[:d1]
    dynsig = sigma[d1:, d1:] - fd @ sigma[:d1, :d1] @ fd.T
    return fd, fc, 0.5 * (dynsig + dynsig.T)


def np_inference(gmm, pts, strength):
    act = np.asarray(gmm.active)
    mu, sig, lm = np.asarray(gmm.mu)[act], np.asarray(gmm.sigma)[act], np.asarray(gmm.logmass)[act]
    logobs = np.stack([multivariate_normal(mu[i], sig[i]).logpdf(pts) + lm[i] for i in range(len(mu))], 1)
    w = np.exp(logobs - logsumexp(logobs, 1, keepdims=True)).mean(0)
    mu0 = w @ mu
    Phi = sum(w[i] * (sig[i] + np.outer(mu[i] - mu0, mu[i] - mu0)) for i in range(len(mu)))
    Ng, D = float(gmm.n_points), pts.shape[1]
    m, n0 = strength, strength * (Ng - 2 - D) / Ng
    return mu0, m * Phi, m, n0


def np_fit_dynamics(prior, X, U, cfg):
    N = X.shape[0]
    D = 2 * dX + dU
    sig_reg = np.zeros((D, D))
    if cfg.regularizer == "toolbox":
        sig_reg[:dX + dU, :dX + dU] = cfg.regularization  # the toolbox's line: numpy broadcasts it
    else:
        sig_reg[:dX + dU, :dX + dU] = cfg.regularization * np.eye(dX + dU)
    Fm, fv, dyn = np.zeros((T, dX, dX + dU)), np.zeros((T, dX)), np.zeros((T, dX, dX))
    for t in range(T - 1):
        pts = np.c_[X[:, t], U[:, t], X[:, t + 1]]
        mu0, Phi, m, n0 = np_inference(prior.gmm, pts, cfg.strength)
        Fm[t], fv[t], dyn[t] = np_gauss_fit_joint_prior(pts, mu0, Phi, m, n0, np.full(N, 1.0 / N),
                                                        dX + dU, dX, sig_reg)
    x0 = X[:, 0]
    x0mu = x0.mean(0)
    x0sigma = np.diag(np.maximum(x0.var(0), cfg.initial_state_var))
    stored = np.asarray(prior.X)[: min(int(prior.count), cfg.max_samples), 0]
    mu0, m = stored.mean(0), dX * cfg.strength
    Phi0 = m * np.diag(stored.var(0))
    x0sigma += (Phi0 + N * m / (N + m) * np.outer(x0mu - mu0, x0mu - mu0)) / (N + m)
    return Fm, fv, dyn, x0mu, x0sigma


# ------------------------------------------------------------------ tests

def test_gauss_fit_joint_prior_matches_numpy():
    r = np.random.default_rng(0)
    N, d1, d2 = 7, 3, 2
    D = d1 + d2
    pts = r.normal(size=(N, D))
    mu0 = r.normal(size=D)
    G = r.normal(size=(D, D))
    Phi = G @ G.T + 0.1 * np.eye(D)
    sig_reg = 1e-6 * np.eye(D)
    dwts = np.full(N, 1.0 / N)
    # Tolerance from the computation (tests/tolerances.py): the numpy transcription rerun on
    # inputs perturbed by ε relative, SAFETY times the spread of each output.
    ref, tol = measured_tol(np_gauss_fit_joint_prior, (pts, mu0, Phi, 1.3, 0.9, dwts, d1, d2, sig_reg), SAFETY)
    assert_tolerances_small(ref, tol, 1e-10)
    f = jax.jit(gauss_fit_joint_prior, static_argnums=(6, 7))
    got = f(jnp.asarray(pts), jnp.asarray(mu0), jnp.asarray(Phi), 1.3, 0.9, jnp.asarray(dwts), d1, d2,
            jnp.asarray(sig_reg))
    assert_trees_within(tuple(got), tuple(ref), tol)
    # Zero-weight padding rows (holding garbage) do not change the fit.
    pts_pad = np.r_[pts, np.full((3, D), 1e6)]
    got_pad = f(jnp.asarray(pts_pad), jnp.asarray(mu0), jnp.asarray(Phi), 1.3, 0.9,
                jnp.asarray(np.r_[dwts, np.zeros(3)]), d1, d2, jnp.asarray(sig_reg))
    assert_trees_within(tuple(got_pad), tuple(ref), tol)


def test_ring_buffer_keeps_last_max_samples(prior1):
    # Trajectory ids are written into the states, so the stored set can be read back.
    S = CFG.max_samples
    buf, count, seen = jnp.zeros((S, 2)), 0, []
    for n in (2, 3, 4, 1, 9):  # the last batch is larger than the buffer
        new = np.stack([np.full(2, count + j, float) for j in range(n)])
        buf = ring_insert(buf, jnp.asarray(count), jnp.asarray(new))
        count += n
        seen += list(range(count - n, count))
        assert sorted(np.asarray(buf[:min(count, S), 0]).astype(int).tolist()) == seen[-S:]
    # Through the prior update: 2 batches of 3 filled all 6 slots; a third batch evicts the first.
    assert int(prior1.count) == 6
    X, U = _rollout(SYS1, 3, 12)
    p = _update(prior1, jax.random.key(2), jnp.asarray(X), jnp.asarray(U), CFG)
    assert int(p.count) == 9
    X10, _ = _rollout(SYS1, 3, 10)
    X11, _ = _rollout(SYS1, 3, 11)
    np.testing.assert_array_equal(np.asarray(p.X), np.r_[X, X11])  # the first batch (slots 0-2) is gone
    assert not np.any(np.all(np.asarray(p.X) == X10[0], axis=(1, 2)))


def test_prior_update_fits_gmm_with_toolbox_cluster_count(prior1):
    g = prior1.gmm
    # First update: 3·(T−1) = 33 points -> K = max(2, 33 // 40) = 2; the second (66 points) keeps
    # K = 2, so EM warm-starts and n_points stays at the first count (toolbox behaviour).
    assert np.asarray(g.active).tolist() == [True, True, False, False]
    assert int(g.n_points) == 33
    assert bool(g.initialized)


def test_padding_slots_do_not_change_the_prior_or_fit():
    X, U = _rollout(SYS1, 3, 10)
    clean = dynamics_prior_empty(T, dX, dU, CFG, jnp.float64)
    junk = clean._replace(X=jnp.full_like(clean.X, 1e3), U=jnp.full_like(clean.U, jnp.nan))
    a = _update(clean, jax.random.key(0), jnp.asarray(X), jnp.asarray(U), CFG)
    b = _update(junk, jax.random.key(0), jnp.asarray(X), jnp.asarray(U), CFG)
    # Empty slots are masked and zeroed before any sum, so the same program sees the same
    # numbers: bit-equal.
    for x, y in zip(a.gmm, b.gmm):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
    for x, y in zip(_fit(a, jnp.asarray(X), jnp.asarray(U), CFG), _fit(b, jnp.asarray(X), jnp.asarray(U), CFG)):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


def test_fit_dynamics_matches_numpy_reference(prior1):
    X, U = _rollout(SYS1, 3, 12, x0_std=0.3)
    dyn = _fit(prior1, jnp.asarray(X), jnp.asarray(U), CFG)
    assert bool(dynamics_ok(dyn))
    # Tolerance from the computation (tests/tolerances.py): the numpy transcription rerun on the
    # data and the prior perturbed by ε relative, SAFETY times the spread of each output.
    ref, tol = measured_tol(lambda p, x, u: np_fit_dynamics(p, x, u, CFG), (prior1, X, U), SAFETY)
    assert_tolerances_small(ref, tol, 1e-8)
    assert_trees_within(tuple(dyn), tuple(ref), tol)
    # t = T−1 is left at zero (toolbox).
    assert not np.any(np.asarray(dyn.Fm[-1])) and not np.any(np.asarray(dyn.dyn_covar[-1]))


def test_initial_state_hand_case():
    # Stored x0 in 3 of 6 slots (junk in the others): μ₀ = mean, Φ₀ = m·diag(var), m = n₀ = dX·strength.
    prior = dynamics_prior_empty(T, dX, dU, CFG, jnp.float64)
    x0s = np.array([[0.0, 1.0, 2.0], [1.0, 1.0, 0.0], [2.0, 1.0, 1.0]])
    prior = prior._replace(X=prior.X.at[:3, 0].set(x0s).at[3:].set(7.0), count=jnp.asarray(3, jnp.int32))
    mu0, Phi0, m, n0 = prior_initial_state(prior, 2.0)
    np.testing.assert_allclose(mu0, [1.0, 1.0, 1.0])
    np.testing.assert_allclose(Phi0, 6.0 * np.diag([2 / 3, 0.0, 2 / 3]))
    assert float(m) == 6.0 and float(n0) == 6.0

    # Deterministic x0 equal to the stored mean: everything vanishes except the 1e-6 floor.
    X = np.zeros((3, T, dX))
    X[:, 0] = [1.0, 1.0, 1.0]
    prior_det = prior._replace(X=prior.X.at[:3, 0].set(1.0))
    dyn = _fit(prior_det, jnp.asarray(X), jnp.zeros((3, T, dU)), CFG)
    np.testing.assert_allclose(dyn.x0mu, [1.0, 1.0, 1.0])
    # Every other term is 0 up to rounding: x0mu − μ₀ (two means of equal values) is at most
    # c·n·ε·|x₀| and enters squared; normwise against the 1e-6 floor (tests/tolerances.py).
    assert_close(dyn.x0sigma, 1e-6 * np.eye(dX), linear_tol(1.0, 8))

    # With the x0 prior above (strength 1: m = n₀ = 3) and N = 3 samples at (2, 1, 1):
    # x0sigma = floor + (Φ₀ + N·m/(N+m)·ΔΔᵀ)/(N+n₀), Φ₀ inside the division (the corrected form).
    X[:, 0] = [2.0, 1.0, 1.0]
    dyn = _fit(prior, jnp.asarray(X), jnp.zeros((3, T, dU)), CFG)
    d = np.array([1.0, 0.0, 0.0])
    expect = 1e-6 * np.eye(dX) + (3.0 * np.diag([2 / 3, 0.0, 2 / 3]) + 3 * 3 / 6 * np.outer(d, d)) / 6
    # A few products and sums of exact small numbers: c·8·ε relative, normwise (tests/tolerances.py)
    assert_close(dyn.x0sigma, expect, 2 * linear_tol(1.0, 8))


def test_recovers_linear_system_with_many_samples(prior1):
    X, U = _rollout(SYS1, 400, 5)
    dyn = _fit(prior1, jnp.asarray(X), jnp.asarray(U), CFG)
    A, B, c = SYS1
    np.testing.assert_allclose(np.asarray(dyn.Fm[:-1]), np.broadcast_to(np.c_[A, B], (T - 1, dX, dX + dU)), atol=0.03)
    np.testing.assert_allclose(np.asarray(dyn.fv[:-1]), np.broadcast_to(c, (T - 1, dX)), atol=0.03)
    np.testing.assert_allclose(np.asarray(dyn.dyn_covar[:-1]), np.broadcast_to(1e-4 * np.eye(dX), (T - 1, dX, dX)),
                               atol=3e-5)
    # Same with only 3 samples (N < D = 8: the plain fit is undefined); the prior makes it accurate.
    X2, U2 = _rollout(SYS1, 3, 6)
    dyn2 = _fit(prior1, jnp.asarray(X2), jnp.asarray(U2), CFG)
    np.testing.assert_allclose(np.asarray(dyn2.Fm[:-1]), np.broadcast_to(np.c_[A, B], (T - 1, dX, dX + dU)), atol=0.1)


def _least_squares(X, U):
    """Plain per-step least-squares fit of x_{t+1} on [x_t, u_t, 1] -> [T−1, dX, dX+dU]."""
    out = []
    for t in range(T - 1):
        A = np.c_[X[:, t], U[:, t], np.ones(len(X))]
        out.append(np.linalg.lstsq(A, X[:, t + 1], rcond=None)[0][:-1].T)
    return np.array(out)


def test_prior_pulls_few_samples_toward_pooled_fit(prior1):
    # The prior holds 6 trajectories of system 1; the samples come from system 2. The prior pulls
    # the fit away from the samples' own least-squares fit toward the pooled fit of the stored
    # data, the less the more samples there are.
    n_st = int(prior1.count)
    Xs, Us = np.asarray(prior1.X)[:n_st], np.asarray(prior1.U)[:n_st]
    A = np.c_[Xs[:, :-1].reshape(-1, dX), Us[:, :-1].reshape(-1, dU), np.ones(n_st * (T - 1))]
    F_pool = np.linalg.lstsq(A, Xs[:, 1:].reshape(-1, dX), rcond=None)[0][:-1].T  # all stored transitions
    F2 = np.c_[SYS2[0], SYS2[1]]
    fits, lsq = {}, {}
    for N in (3, 30, 400):
        X, U = _rollout(SYS2, N, 99)
        dyn = _fit(prior1, jnp.asarray(X), jnp.asarray(U), CFG)
        assert bool(dynamics_ok(dyn))
        fits[N] = np.asarray(dyn.Fm[:-1])
        if N > dX + dU + 1:
            lsq[N] = _least_squares(X, U)
    dist = lambda F, G: np.abs(F - G).mean()
    for N in (30, 400):
        assert dist(fits[N], F_pool) < dist(lsq[N], F_pool)
    assert dist(fits[400], lsq[400]) < 0.25 * dist(fits[30], lsq[30])
    assert dist(fits[3], F2) > dist(fits[30], F2) > dist(fits[400], F2)
    assert dist(fits[400], F2) < 0.01


def test_vmap_over_conditions_equals_separate_calls(prior1):
    X = np.stack([_rollout(SYS1, 3, 20)[0], _rollout(SYS2, 3, 21)[0]])
    U = np.stack([_rollout(SYS1, 3, 20)[1], _rollout(SYS2, 3, 21)[1]])
    empty = dynamics_prior_empty(T, dX, dU, CFG, jnp.float64)
    priors = jax.tree.map(lambda a, b: jnp.stack([a, b]), prior1, empty)
    keys = jax.random.split(jax.random.key(3), 2)

    @jax.jit
    @jax.vmap
    def both(p, k, x, u):
        p = update_dynamics_prior(p, k, x, u, CFG)
        return p, fit_dynamics(p, x, u, CFG)

    pb, db = both(priors, keys, jnp.asarray(X), jnp.asarray(U))

    def single(p, k, x, u):
        p = _update(p, k, x, u, CFG)
        return p, _fit(p, x, u, CFG)

    for c, p in enumerate((prior1, empty)):
        # Tolerance from the computation (tests/tolerances.py): the separate calls rerun on
        # inputs perturbed by ε relative, SAFETY times the spread (EM amplifies rounding).
        ref, tol = measured_tol(single, (p, keys[c], jnp.asarray(X[c]), jnp.asarray(U[c])), SAFETY)
        assert_tolerances_small(ref, tol, 1e-6)
        assert_trees_within(jax.tree.map(lambda a: a[c], (pb, db)), ref, tol)


def test_float32_follows_input_dtype(prior1):
    p32 = jax.tree.map(lambda a: a.astype(jnp.float32) if a.dtype == jnp.float64 else a, prior1)
    X, U = _rollout(SYS1, 3, 30)
    X, U = jnp.asarray(X, jnp.float32), jnp.asarray(U, jnp.float32)
    p32 = _update(p32, jax.random.key(0), X, U, CFG)
    dyn = _fit(p32, X, U, CFG)
    assert all(a.dtype == jnp.float32 for a in dyn) and p32.gmm.sigma.dtype == jnp.float32
    assert bool(dynamics_ok(dyn))
    ref = _fit(prior1, jnp.asarray(X, jnp.float64), jnp.asarray(U, jnp.float64), CFG)
    np.testing.assert_allclose(np.asarray(dyn.Fm), np.asarray(ref.Fm), atol=0.05)


def test_one_sample_is_rejected(prior1):
    X, U = _rollout(SYS1, 1, 0)
    with pytest.raises(ValueError, match="at least 2"):
        fit_dynamics(prior1, jnp.asarray(X), jnp.asarray(U), CFG)


def test_float32_joint_fit_of_collinear_inputs_without_ridge_is_finite():
    """The policy prior's fit has no ridge after t = 0; in float32 the (a, a) block gets the
    precision's Cholesky floor (``linalg.cholesky_floor``), so exactly collinear inputs (no prior,
    no ridge: singular in exact arithmetic) still give a finite fit that reproduces b = W a."""
    r = np.random.default_rng(5)
    N, d2 = 40, 2
    x = r.normal(size=(N, 3))
    a = np.c_[x, x[:, :1] + x[:, 1:2]]  # rank 3 of 4
    W = r.normal(size=(d2, 4))
    pts = np.c_[a, a @ W.T].astype(np.float32)
    d1, D = 4, 4 + d2
    zeros = jnp.zeros((D, D), jnp.float32)
    fd, fc, dynsig = jax.jit(gauss_fit_joint_prior, static_argnums=(6, 7))(
        jnp.asarray(pts), jnp.zeros(D, jnp.float32), zeros, 0.0, 0.0, jnp.full(N, 1.0 / N, jnp.float32),
        d1, d2, zeros)
    assert all(np.isfinite(np.asarray(v)).all() for v in (fd, fc, dynsig))
    pred = pts[:, :d1] @ np.asarray(fd, np.float64).T + np.asarray(fc)
    # the floor biases the fit by about its own size relative to the data (2·4·5·ε ≈ 5e-6)
    assert np.abs(pred - pts[:, d1:]).max() < 1e-3 * np.abs(pts[:, d1:]).max()

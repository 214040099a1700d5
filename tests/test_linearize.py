"""Policy prior and linearisation: exact on linear policies, numpy reference, modes, vmap, autodiff."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.special import logsumexp
from scipy.stats import multivariate_normal

from tolerances import SAFETY, affine_tol, assert_tolerances_small, assert_trees_within, measured_tol

from gmr_jax.config import PolicyPriorConfig
from gmr_jax.linearize import (linearize_policy, linearize_policy_autodiff, policy_prior_empty,
                               update_policy_prior)

dX, dU, T, N = 4, 2, 6, 3
CFG = PolicyPriorConfig(max_samples=5, max_clusters=4, min_samples_per_cluster=10)


def _act(params, x):
    """u = W x + b + a·tanh(V x): linear for a = 0. One parametrised family, so one compile."""
    W, b, a, V = params
    return W @ x + b + a * jnp.tanh(V @ x)


def _params(seed, a=0.0):
    r = np.random.default_rng(seed)
    return (jnp.asarray(r.normal(size=(dU, dX))), jnp.asarray(r.normal(size=dU)), jnp.asarray(a),
            jnp.asarray(r.normal(size=(dU, dX))))


@jax.jit
def _update_add(prior, key, X, params):
    return update_policy_prior(prior, key, X, lambda x: _act(params, x), CFG, "add")


@jax.jit
def _update_replace(prior, key, X, params):
    return update_policy_prior(prior, key, X, lambda x: _act(params, x), CFG, "replace")


_linearize = jax.jit(linearize_policy, static_argnums=4)


def _states(seed, n=N):
    """Random-walk states with a deterministic x0 (as in the MuJoCo tasks)."""
    r = np.random.default_rng(seed)
    steps = 0.3 * r.normal(size=(n, T - 1, dX))
    return np.concatenate([np.zeros((n, 1, dX)), np.cumsum(steps, axis=1)], axis=1) + 0.2


def _pol_mu(params, X):
    return np.asarray(jax.vmap(jax.vmap(lambda x: _act(params, x)))(jnp.asarray(X)))


POL_VAR = np.diag([0.05, 0.02])


@pytest.fixture(scope="module")
def linear_prior():
    params = _params(0)
    prior = policy_prior_empty(T, dX, dU, CFG, jnp.float64)
    for i in range(2):
        prior = _update_add(prior, jax.random.key(i), jnp.asarray(_states(10 + i)), params)
    return params, prior


def test_linear_policy_is_recovered(linear_prior):
    params, prior = linear_prior
    W, b = np.asarray(params[0]), np.asarray(params[1])
    X = _states(20)
    K, k, S = _linearize(prior, jnp.asarray(X), jnp.asarray(_pol_mu(params, X)), jnp.asarray(POL_VAR), CFG)
    # N = 3 < dX + 1 and x0 is deterministic: only the prior makes the regression well-posed. The
    # only error left is the shrinkage by the GMM's 1e-6·I covariance jitter (largest at t = 0,
    # where the state spread comes from the prior alone).
    np.testing.assert_allclose(np.asarray(K), np.broadcast_to(W, (T, dU, dX)), atol=5e-4)
    np.testing.assert_allclose(np.asarray(K[1:]), np.broadcast_to(W, (T - 1, dU, dX)), atol=1e-4)
    np.testing.assert_allclose(np.asarray(k), np.broadcast_to(b, (T, dU)), atol=5e-4)
    # pol_S = conditional covariance (≈ 0: the policy is exactly linear) + the policy variance.
    np.testing.assert_allclose(np.asarray(S), np.broadcast_to(POL_VAR, (T, dU, dU)), atol=1e-5)
    assert np.all(np.linalg.eigvalsh(np.asarray(S)) > 0)


def test_add_mode_keeps_last_max_samples_and_reevaluates_policy(linear_prior):
    params, prior = linear_prior
    assert int(prior.count) == 6
    X2 = _states(12)
    new_params = _params(7)  # the policy changed since the states were stored
    p = _update_add(prior, jax.random.key(5), jnp.asarray(X2), new_params)
    assert int(p.count) == 9
    # S = 5 slots: slot order is 9 mod 5 … ; as a set: the last 5 trajectories (2 of batch 11, batch 12).
    kept = np.r_[_states(11)[1:], X2]
    stored = np.asarray(p.X)
    for x in kept:
        assert np.any(np.all(stored == x, axis=(1, 2)))
    assert not np.any(np.all(stored == _states(11)[0], axis=(1, 2)))
    # The GMM was fitted on [x, π_new(x)]: every active cluster mean lies on the new linear policy.
    W, b = np.asarray(new_params[0]), np.asarray(new_params[1])
    act = np.asarray(p.gmm.active)
    mu = np.asarray(p.gmm.mu)[act]
    np.testing.assert_allclose(mu[:, dX:], mu[:, :dX] @ W.T + b, atol=1e-9)
    # K = max(2, min(4, ⌊5·6/10⌋)) = 3 clusters.
    assert int(act.sum()) == 3


def test_replace_mode_keeps_only_current_samples(linear_prior):
    params, prior = linear_prior
    X = _states(30)
    p = _update_replace(prior, jax.random.key(1), jnp.asarray(X), params)
    assert int(p.count) == N
    np.testing.assert_array_equal(np.asarray(p.X[:N]), X)
    # 3·6 = 18 points -> K = 2 (changed from 3), so the GMM was re-initialised on those 18 points.
    assert int(p.gmm.n_points) == N * T and int(np.asarray(p.gmm.active).sum()) == 2
    with pytest.raises(ValueError, match="max_samples"):
        update_policy_prior(prior, jax.random.key(0), jnp.zeros((6, T, dX)), lambda x: x[:dU], CFG, "replace")
    with pytest.raises(ValueError, match="allowed values"):
        PolicyPriorConfig(mode="append")


def _np_linearize(prior, X, pol_mu, pol_sig_mean, cfg):
    """Independent numpy implementation of the per-step fit (inference + NIW MAP + conditioning)."""
    g = prior.gmm
    act = np.asarray(g.active)
    mu, sig, lm = np.asarray(g.mu)[act], np.asarray(g.sigma)[act], np.asarray(g.logmass)[act]
    D = dX + dU
    Ng = float(g.n_points)
    Ks, ks, Ss = [], [], []
    for t in range(T):
        pts = np.c_[X[:, t], pol_mu[:, t]]
        logobs = np.stack([multivariate_normal(mu[i], sig[i]).logpdf(pts) + lm[i] for i in range(len(mu))], 1)
        w = np.exp(logobs - logsumexp(logobs, 1, keepdims=True)).mean(0)
        mu0 = w @ mu
        Phi = sum(w[i] * (sig[i] + np.outer(mu[i] - mu0, mu[i] - mu0)) for i in range(len(mu)))
        m, n0 = cfg.strength, cfg.strength * (Ng - 2 - D) / Ng
        Phi = m * Phi
        mun = pts.mean(0)
        emp = (pts - mun).T @ (pts - mun) / N
        sigma = (N * emp + Phi + N * m / (N + m) * np.outer(mun - mu0, mun - mu0)) / (N + n0)
        if t == 0 and cfg.t0_regularizer == "toolbox":
            sigma[:dX, :dX] += cfg.t0_regularization  # the toolbox's broadcast to every entry
        elif t == 0:
            sigma[:dX, :dX] += cfg.t0_regularization * np.eye(dX)
        Kt = np.linalg.solve(sigma[:dX, :dX], sigma[:dX, dX:]).T
        Ks.append(Kt)
        ks.append(mun[dX:] - Kt @ mun[:dX])
        Ss.append(sigma[dX:, dX:] - Kt @ sigma[:dX, :dX] @ Kt.T + pol_sig_mean[t])
    return np.array(Ks), np.array(ks), np.array(Ss)


def test_nonlinear_policy_matches_numpy_reference():
    params = _params(3, a=0.8)
    prior = policy_prior_empty(T, dX, dU, CFG, jnp.float64)
    for i in range(2):
        prior = _update_add(prior, jax.random.key(i), jnp.asarray(_states(40 + i)), params)
    X = _states(50)
    pol_mu = _pol_mu(params, X)
    # Per-sample covariances [N, T, dU, dU]: the fit uses their mean over samples.
    r = np.random.default_rng(0)
    A = r.normal(size=(N, T, dU, dU))
    pol_sig = 0.01 * A @ np.swapaxes(A, -1, -2) + 0.01 * np.eye(dU)
    got = _linearize(prior, jnp.asarray(X), jnp.asarray(pol_mu), jnp.asarray(pol_sig), CFG)
    # Tolerance from the computation (tests/tolerances.py): the numpy transcription rerun on the
    # data and the prior perturbed by ε relative, SAFETY times the spread of each output.
    ref, tol = measured_tol(lambda p, x, mu, sig: _np_linearize(p, x, mu, sig.mean(0), CFG),
                            (prior, X, pol_mu, pol_sig), SAFETY)
    assert_tolerances_small(ref, tol, 1e-8)
    assert_trees_within(tuple(got), tuple(ref), tol)
    # A state-independent [dU, dU] covariance equals the same covariance tiled to [N, T, dU, dU]
    # (two programs: the tiled one averages N equal matrices; tolerance measured as above).
    tiled = np.broadcast_to(POL_VAR, (N, T, dU, dU))
    a = _linearize(prior, jnp.asarray(X), jnp.asarray(pol_mu), jnp.asarray(tiled), CFG)
    b, tol = measured_tol(lambda p, x, mu, sig: _linearize(p, x, mu, sig, CFG),
                          (prior, jnp.asarray(X), jnp.asarray(pol_mu), jnp.asarray(POL_VAR)), SAFETY)
    assert_tolerances_small(b, tol, 1e-8)
    assert_trees_within(tuple(a), tuple(b), tol)


def test_vmap_over_conditions_equals_separate_calls(linear_prior):
    params, prior = linear_prior
    empty = policy_prior_empty(T, dX, dU, CFG, jnp.float64)
    priors = jax.tree.map(lambda a, b: jnp.stack([a, b]), prior, empty)
    X = np.stack([_states(60), _states(61)])
    pol_mu = np.stack([_pol_mu(params, X[0]), _pol_mu(params, X[1])])
    keys = jax.random.split(jax.random.key(2), 2)

    @jax.jit
    @jax.vmap
    def both(p, key, x, mu):
        p = update_policy_prior(p, key, x, lambda s: _act(params, s), CFG, "add")
        return p, linearize_policy(p, x, mu, jnp.asarray(POL_VAR), CFG)

    pb, lb = both(priors, keys, jnp.asarray(X), jnp.asarray(pol_mu))

    def single(p, key, x, mu):
        p = _update_add(p, key, x, params)
        return p, _linearize(p, x, mu, jnp.asarray(POL_VAR), CFG)

    for c, p in enumerate((prior, empty)):
        # Tolerance from the computation (tests/tolerances.py): the separate calls rerun on
        # inputs perturbed by ε relative, SAFETY times the spread (EM amplifies rounding).
        ref, tol = measured_tol(single, (p, keys[c], jnp.asarray(X[c]), jnp.asarray(pol_mu[c])), SAFETY)
        assert_tolerances_small(ref, tol, 1e-6)
        assert_trees_within(jax.tree.map(lambda a: a[c], (pb, lb)), ref, tol)


def test_autodiff_linearisation():
    params = _params(4, a=0.5)
    W, b, a, V = (np.asarray(p) for p in params)
    x = jnp.asarray(_states(70)[0])  # [T, dX]
    K, k, S = jax.jit(lambda x: linearize_policy_autodiff(lambda s: _act(params, s), x, jnp.asarray(POL_VAR)))(x)
    xs = np.asarray(x)
    for t in range(T):
        # Tolerance from the computation (tests/tolerances.py): the numpy Jacobian rerun at x_t
        # perturbed by ε relative, SAFETY times the spread; K x + k against π(x): affine_tol.
        Jref, tol = measured_tol(lambda xt: W + a * (1 - np.tanh(V @ np.asarray(xt)) ** 2)[:, None] * V,
                                 (xs[t],), SAFETY)
        assert_trees_within(K[t], Jref, tol)
        assert_trees_within(K[t] @ x[t] + k[t], _act(params, x[t]), 2 * affine_tol(K[t], x[t], k[t]))
    np.testing.assert_allclose(np.asarray(S), np.broadcast_to(POL_VAR, (T, dU, dU)))

"""GMM M-step log-masses in the log domain (toolbox ``GMM.update``): a cluster far from every point.

The toolbox computes logmass_i = logsumexp_n log r_ni (renormalised by logsumexp over clusters)
from the log-responsibilities log r_ni = logobs_ni − logsumexp_j logobs_nj. A cluster whose
responsibilities all underflow to 0 in float64 keeps a finite (very negative) log-mass that way;
the log of a sum of linear-domain responsibilities is −inf.
"""

import jax
import jax.numpy as jnp
import numpy as np
from scipy.special import logsumexp
from scipy.stats import multivariate_normal

from gmr_jax.gmm import gmm_inference, gmm_update_with_info
from gmr_jax.types import GMM

EPS = np.finfo(np.float64).eps
K_MAX, D, K = 4, 3, 3
FAR = 1e3  # the third cluster's mean is FAR·(1, 1, 1): −½·maha ≈ −1.5e6 at every point


def _problem():
    rng = np.random.default_rng(0)
    data = np.concatenate([rng.normal(0.0, 0.5, (60, D)), rng.normal(5.0, 0.5, (60, D))])
    mu = np.zeros((K_MAX, D))
    mu[0], mu[1], mu[2] = data[:60].mean(0), data[60:].mean(0), FAR
    sigma = np.broadcast_to(np.eye(D), (K_MAX, D, D)).copy()
    sigma[0], sigma[1] = np.cov(data[:60].T, bias=True), np.cov(data[60:].T, bias=True)
    logmass = np.full(K_MAX, -np.inf)
    logmass[:K] = -np.log(K)
    gmm = GMM(mu=jnp.asarray(mu), sigma=jnp.asarray(sigma), logmass=jnp.asarray(logmass),
              active=jnp.arange(K_MAX) < K, n_points=jnp.asarray(len(data), jnp.int32),
              initialized=jnp.asarray(True))
    return data, mu[:K], sigma[:K], logmass[:K], gmm


def _np_toolbox_logmass(data, mu, sigma, logmass):
    """The toolbox's M-step log-masses, transcribed with scipy (independent of gmr_jax)."""
    logobs = np.stack([multivariate_normal(mu[i], sigma[i]).logpdf(data) for i in range(len(mu))], 1)
    logobs = logobs + logmass[None, :]
    logw = logobs - logsumexp(logobs, axis=1, keepdims=True)
    new = logsumexp(logw, axis=0)
    return new - logsumexp(new), logobs, logw


def test_far_cluster_keeps_a_finite_log_mass():
    data, mu, sigma, logmass, gmm = _problem()
    ref, logobs, logw = _np_toolbox_logmass(data, mu, sigma, logmass)
    # The case: every responsibility of the far cluster underflows in float64, so the log of
    # their linear-domain sum is −inf (what the M-step returned before it summed in the log domain).
    assert np.all(np.exp(logw[:, 2]) == 0.0)
    with np.errstate(divide="ignore"):
        assert np.isneginf(np.log(np.exp(logw).sum(0))[2])
    assert np.isfinite(ref).all() and ref[2] < -1e6

    fit = jax.jit(gmm_update_with_info, static_argnums=5)
    # Warm start with the same cluster count and one EM iteration: one E-step on these parameters
    # and the M-step that follows (the returned parameters).
    one, _ = fit(gmm, jax.random.key(0), jnp.asarray(data), None, K, 1)
    got = np.asarray(one.logmass[:K])
    assert np.isfinite(got).all(), got

    # Tolerance from the computation. logobs_ni = −½·maha − ½·log|2πΣ_i| + logmass_i, with
    # maha = ‖L_i⁻¹(x − μ_i)‖², agrees between the two programs (Cholesky + triangular solve here,
    # eigendecomposition in scipy) to δ_ni ≤ c·D·ε·κ(Σ_i)·(|logobs_ni| + 1) (backward-stable
    # factorisations of a D×D matrix; c = 8 covers the few rounding steps of each formula).
    # logsumexp moves by at most the largest error among its inputs (weighted by their softmax
    # weights ≤ 1): log r moves by ≤ 2·max δ, logsumexp_n log r by the same, and the
    # renormalisation doubles it: |Δ logmass_i| ≤ 4·(max_n δ_ni + max_{n,j} δ_nj of the near
    # clusters, which carry all the softmax weight of the normalisers).
    kappa = np.array([np.linalg.cond(s) for s in sigma])
    delta = 8 * D * EPS * kappa[None, :] * (np.abs(logobs) + 1.0)
    tol = 4.0 * (delta.max(0) + delta[:, :2].max())
    np.testing.assert_array_less(np.abs(got - ref), tol)
    # The bound is tight enough to mean something: below 1e-6 relative for the far cluster and
    # 1e-9 absolute for the near ones.
    assert tol[2] < 1e-6 * abs(ref[2]) and np.all(tol[:2] < 1e-9)

    # Downstream: the rebooted far cluster (refitted on all points, tiny mass kept) leaves every
    # parameter, further EM iterations and the NIW prior finite.
    more, info = fit(gmm, jax.random.key(0), jnp.asarray(data), None, K, 5)
    assert bool(info.ok)
    assert np.isfinite(np.asarray(more.logmass[:K])).all()
    mu0, Phi, m, n0 = gmm_inference(more, jnp.asarray(data))
    assert np.isfinite(np.asarray(mu0)).all() and np.isfinite(np.asarray(Phi)).all()

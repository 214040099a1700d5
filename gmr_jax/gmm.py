"""Gaussian mixture model fitted by EM, jittable with a fixed cluster capacity and point masks.

Toolbox reference: ``shared/reference/mdgps-toolbox.md`` §3.2 (``gps/utility/gmm.py``).

Static shapes: a GMM has room for ``K_max`` clusters, of which the first ``k_active`` are in use
(``GMM.active``); the data come with a boolean row mask so that a growing sample store can live in
a fixed-size array. Inactive clusters keep mean 0, covariance I (so every Cholesky stays finite)
and log-mass −inf, so they never receive responsibility. Masked rows are zeroed on entry, so
padding (even NaN/inf padding) never reaches a sum.

Numerics follow the toolbox, with two corrections, both marked ``FIX`` below:
- the relative stopping test is |ll − ll_prev| < 1e-5·|ll_prev| (the toolbox omits the absolute
  value, so its test never fires for a negative log-likelihood and EM always runs to the cap);
  it fires only while the improvement is not growing, so that EM does not stop on the plateau
  next to its random start (see ``gmm_update_with_info``);
- covariances are accumulated in centred form Σ w (x−μ)(x−μ)ᵀ, which equals the toolbox's
  Σ w x xᵀ − μμᵀ (the weights sum to one) but does not lose precision in float32.
Additionally, an E-step that produces a non-finite log-likelihood stops EM and restores the last
parameters with a finite one (``GMMFitInfo.ok`` reports failure).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
from jax import lax
from jax.scipy.special import logsumexp

from gmr_jax import linalg
from gmr_jax.types import GMM

Array = jax.Array

INIT_JITTER = 2e-6  # added to the initial covariances (toolbox)
EM_JITTER = 1e-6  # added to every M-step covariance (toolbox "quick and dirty regularisation")
REBOOT_MASS = 1e-4  # clusters with mass < REBOOT_MASS / K are re-spread over all points
REL_TOL = 1e-5  # relative log-likelihood change that ends EM
# Full float32 products on GPUs, whose default for float32 matmuls is TF32 (~1e-3 relative error,
# enough to make a tight cluster covariance indefinite). No effect on CPU.
_HI = lax.Precision.HIGHEST


class GMMFitInfo(NamedTuple):
    """Diagnostics of one ``gmm_update``.

    Attributes:
      loglik: [] log-likelihood of the last E-step (of the returned parameters unless EM ran to
        ``max_iterations``, in which case the last M-step is not evaluated, as in the toolbox).
      iterations: [] E-steps run.
      ok: [] bool, log-likelihood and all active parameters finite.
    """

    loglik: Array
    iterations: Array
    ok: Array


def gmm_empty(K_max: int, D: int, dtype=jnp.float32) -> GMM:
    """An uninitialised GMM with capacity ``K_max`` clusters in ``D`` dimensions.

    Returns: GMM with mu [K_max, D] = 0, sigma [K_max, D, D] = I, logmass [K_max] = −inf,
    active [K_max] = False, n_points [] = 0, initialized [] = False.
    """
    return GMM(
        mu=jnp.zeros((K_max, D), dtype),
        sigma=jnp.broadcast_to(jnp.eye(D, dtype=dtype), (K_max, D, D)),
        logmass=jnp.full((K_max,), -jnp.inf, dtype),
        active=jnp.zeros((K_max,), bool),
        n_points=jnp.zeros((), jnp.int32),
        initialized=jnp.zeros((), bool),
    )


def num_clusters(n_points, min_samples_per_cluster: int, max_clusters: int) -> Array:
    """Toolbox cluster-count rule K = max(2, min(max_clusters, ⌊n_points / min_samples⌋)).

    Args:
      n_points: [] (traced) number of valid points.
    Returns: [] int32.
    """
    n = jnp.asarray(n_points, jnp.int32)
    return jnp.maximum(2, jnp.minimum(max_clusters, n // min_samples_per_cluster)).astype(jnp.int32)


def _default_mask(data: Array, mask) -> Array:
    if mask is None:
        return jnp.ones(data.shape[:1], bool)
    return jnp.asarray(mask, bool)


def _mahalanobis_rows(Linv: Array, mu: Array, data: Array) -> Array:
    """‖L_k⁻¹ (x_n − μ_k)‖² [K, n] from Linv [K, D, D], mu [K, D], data [n, D], with the
    differences laid out as [K, n, D] (the faster layout on a CPU)."""
    diff = data[None, :, :] - mu[:, None, :]  # [K, n, D]
    z = jnp.einsum("kne,kde->knd", diff, Linv, precision=_HI)  # rows of L⁻¹ (x − μ)
    return jnp.sum(z * z, axis=-1)


def _mahalanobis_columns(Linv: Array, mu: Array, data: Array) -> Array:
    """``_mahalanobis_rows`` with the differences laid out as [K, D, n], the points along the
    minor axis: the same products and sums. On a GPU an EM step of the dynamics priors of 256
    seeds (512 GMMs) is 29 % faster this way, with bit-identical training results
    (benchmarks/RESULTS.md, seventeenth session)."""
    diff = data.T[None, :, :] - mu[:, :, None]  # [K, D, n]
    z = jnp.einsum("kde,ken->kdn", Linv, diff, precision=_HI)  # columns of L⁻¹ (x − μ)
    return jnp.sum(z * z, axis=1)


def _log_obs(mu: Array, sigma: Array, logmass: Array, active: Array, data: Array) -> Array:
    """log N(x_n; μ_i, Σ_i) + log π_i for every point and cluster.

    Args: mu [K, D], sigma [K, D, D], logmass [K], active [K], data [n, D].
    Returns: [n, K], −inf in inactive columns.
    """
    D = data.shape[-1]
    L = linalg.cholesky(sigma)  # [K, D, D] lower
    # L⁻¹ by a triangular solve on the small [K, D, D] identity, then one batched matrix product
    # over all points: on a GPU this is ~3.5x faster than a triangular solve with n right-hand
    # sides, and as accurate (with full-precision products).
    eye = jnp.broadcast_to(jnp.eye(D, dtype=sigma.dtype), sigma.shape)
    Linv = linalg.solve_triangular(L, eye, lower=True)  # [K, D, D]
    maha = lax.platform_dependent(Linv, mu, data, cpu=_mahalanobis_rows, default=_mahalanobis_columns)
    half_logdet = jnp.sum(jnp.log(jnp.diagonal(L, axis1=-2, axis2=-1)), axis=-1)  # [K]
    logobs = (-0.5 * D * math.log(2.0 * math.pi) - half_logdet[:, None] - 0.5 * maha
              + logmass[:, None])
    return jnp.where(active[:, None], logobs, -jnp.inf).T


def _loglik(logobs: Array, mask: Array) -> Array:
    return jnp.sum(jnp.where(mask, logsumexp(logobs, axis=1), 0.0))


def _responsibilities(logobs: Array, mask: Array, active: Array) -> Array:
    """Posterior cluster probabilities r_ni [n, K], zero on masked rows and inactive clusters."""
    lse = logsumexp(logobs, axis=1, keepdims=True)
    return jnp.where(mask[:, None] & active[None, :], jnp.exp(logobs - lse), 0.0)


def _weighted_moments(w: Array, data: Array):
    """Means μ_i = Σ_n w_ni x_n [K, D] and centred scatters Σ_n w_ni (x_n−μ_i)(x_n−μ_i)ᵀ [K, D, D]."""
    mu = jnp.matmul(w.T, data, precision=_HI)
    diff = data[None, :, :] - mu[:, None, :]  # [K, n, D]
    scatter = jnp.matmul(jnp.swapaxes(diff * w.T[:, :, None], -1, -2), diff, precision=_HI)
    return mu, scatter


def _inactive_defaults(active, mu, sigma, logmass):
    D = mu.shape[-1]
    eye = jnp.eye(D, dtype=mu.dtype)
    mu = jnp.where(active[:, None], mu, 0.0)
    sigma = jnp.where(active[:, None, None], sigma, eye)
    logmass = jnp.where(active, logmass, -jnp.inf)
    return mu, sigma, logmass


def _fmix32(h: Array) -> Array:
    """MurmurHash3 32-bit finaliser: a bijective avalanche mix of uint32 values."""
    h = h ^ (h >> 16)
    h = h * jnp.uint32(0x85EBCA6B)
    h = h ^ (h >> 13)
    h = h * jnp.uint32(0xC2B2AE35)
    return h ^ (h >> 16)


def _row_hash(key, n: int) -> Array:
    """[n] uint32 pseudo-random values, the i-th depending only on (key, i).

    Per-row ``fold_in`` would give the same prefix property but costs a Threefry block per row,
    which dominates the compile time of EM on CPU; two seeds from the key and an integer mix do not.
    """
    seed = jax.random.bits(key, (2,), jnp.uint32)
    rows = jnp.arange(n, dtype=jnp.uint32)
    return _fmix32(_fmix32(rows * jnp.uint32(0x9E3779B9) + seed[0]) ^ seed[1])


def _init_params(key, data: Array, mask: Array, k: Array, K_max: int):
    """Toolbox initialisation: random hard assignment to k clusters, Σ_i scaled by 1/k (sic).

    Each row's cluster is a hash of (key, row index), so appending padding rows does not change
    the assignment of the valid ones. An empty cluster (possible only when there are about as few
    points as clusters; the toolbox would produce NaN) takes the overall mean and covariance.
    """
    dtype = data.dtype
    n, D = data.shape
    cidx = (_row_hash(key, n) % k.astype(jnp.uint32)).astype(jnp.int32)
    active = jnp.arange(K_max) < k
    A = ((cidx[:, None] == jnp.arange(K_max)[None, :]) & mask[:, None]).astype(dtype)  # [n, K]
    counts = A.sum(0)
    n_valid = jnp.maximum(mask.sum(), 1).astype(dtype)

    mu, scatter = _weighted_moments(A / jnp.maximum(counts, 1.0), data)
    scatter = scatter * jnp.maximum(counts, 1.0)[:, None, None]  # unnormalised Σ_assigned (x−μ)(x−μ)ᵀ
    sigma = scatter / k.astype(dtype)  # toolbox quirk kept: 1/K, not 1/n_i

    m_all, s_all = _weighted_moments((mask / n_valid).astype(dtype)[:, None], data)
    empty = counts == 0
    mu = jnp.where(empty[:, None], m_all, mu)
    sigma = jnp.where(empty[:, None, None], s_all, sigma)
    sigma = linalg.ridge(linalg.sym(sigma), INIT_JITTER)
    logmass = jnp.full((K_max,), -jnp.log(k.astype(dtype)), dtype)
    return _inactive_defaults(active, mu, sigma, logmass)


def _m_step(data: Array, mask: Array, logobs: Array, active: Array, k: Array):
    """Toolbox M-step: masses, reboot of tiny clusters, means, covariances (+1e-6·I).

    Masses and weights are computed in the log domain, as in the toolbox:
    log r_ni = logobs_ni − logsumexp_j logobs_nj;  logmass_i = logsumexp_n log r_ni, renormalised
    by logsumexp_i;  w_ni = exp(log r_ni − logsumexp_n log r_ni). A cluster far from every point
    has responsibilities that all underflow to 0 in the linear domain (log of their sum: −inf,
    and the cluster could never receive mass again); in the log domain its log-mass stays finite.
    """
    dtype = data.dtype
    valid = mask[:, None] & active[None, :]
    logr = jnp.where(valid, logobs - logsumexp(logobs, axis=1, keepdims=True), -jnp.inf)  # [n, K]
    log_s = logsumexp(logr, axis=0)  # [K], −inf only for inactive clusters
    logmass = log_s - logsumexp(log_s)
    # Reboot: a cluster with almost no mass is refitted on all points with equal weights; its
    # (tiny) log-mass is kept, as in the toolbox.
    reboot = active & (jnp.exp(logmass) < REBOOT_MASS / k.astype(dtype))
    n_valid = jnp.maximum(mask.sum(), 1).astype(dtype)
    w = jnp.where(reboot[None, :], (mask / n_valid)[:, None].astype(dtype),
                  jnp.exp(logr - jnp.where(jnp.isfinite(log_s), log_s, 0.0)[None, :]))
    w = jnp.where(active[None, :], w, 0.0)
    # FIX (numerics only): centred scatter instead of Σ w x xᵀ − μμᵀ, identical in exact arithmetic.
    mu, sigma = _weighted_moments(w, data)
    sigma = linalg.ridge(linalg.sym(sigma), EM_JITTER)  # raised to the Cholesky floor in float32
    return _inactive_defaults(active, mu, sigma, logmass)


def gmm_update_with_info(gmm: GMM, key, data: Array, mask, k_active, max_iterations: int):
    """``gmm_update`` that also returns its diagnostics.

    Returns: (GMM, GMMFitInfo).
    """
    K_max, D = gmm.mu.shape
    if data.ndim != 2 or data.shape[1] != D:
        raise ValueError(f"data must have shape [n, {D}], got {data.shape}")
    mask = _default_mask(data, mask)
    data = jnp.where(mask[:, None], data, 0.0).astype(gmm.mu.dtype)
    k = jnp.clip(jnp.asarray(k_active, jnp.int32), 1, K_max)
    active = jnp.arange(K_max) < k

    # Re-initialise when there are no parameters yet or the cluster count changed; otherwise the
    # previous parameters warm-start EM and n_points (which sets the prior's n₀) is kept (toolbox).
    reinit = (~gmm.initialized) | (k != jnp.sum(gmm.active))
    init = _init_params(key, data, mask, k, K_max)
    params = jax.tree.map(lambda a, b: jnp.where(reinit, a, b), init, (gmm.mu, gmm.sigma, gmm.logmass))
    n_points = jnp.where(reinit, mask.sum().astype(jnp.int32), gmm.n_points)

    dtype = data.dtype
    neg_inf = jnp.asarray(-jnp.inf, dtype)

    def cond_fn(c):
        return (~c[-1]) & (c[0] < max_iterations)

    def body_fn(c):
        itr, cur, prev, prevll, prev_delta, _, _ = c
        logobs = _log_obs(*cur, active, data)
        ll = _loglik(logobs, mask)
        bad = ~jnp.isfinite(ll)
        delta = ll - prevll
        # FIX: |prevll| makes the relative test work for negative log-likelihoods too (the toolbox
        # tests Δ < 1e-5·prevll, which never holds when prevll ≤ 0, so it always runs to the cap).
        # Guard: the test fires only while the improvement is not growing (Δ_k ≤ Δ_{k−1}, and not
        # on the first change, which is the jump away from the initialisation). A random
        # hard-assignment start puts every cluster near the overall mean, a saddle of the
        # likelihood that EM leaves with geometrically *growing* tiny improvements; a bare
        # relative test would stop there with all clusters merged.
        small = jnp.abs(delta) < REL_TOL * jnp.abs(prevll)
        stop = bad | (ll < prevll) | (small & (delta <= prev_delta))
        new = _m_step(data, mask, logobs, active, k)
        # On a decrease the toolbox keeps the parameters just evaluated; on a non-finite ll we
        # fall back to the previous ones, whose ll was finite.
        kept = jax.tree.map(lambda p, q: jnp.where(bad, p, q), prev, cur)
        out = jax.tree.map(lambda a, b: jnp.where(stop, a, b), kept, new)
        prev_out = jax.tree.map(lambda a, b: jnp.where(stop, a, b), prev, cur)
        next_delta = jnp.where(itr >= 2, delta, neg_inf)
        return itr + 1, out, prev_out, jnp.where(stop, prevll, ll), next_delta, ll, stop

    c0 = (jnp.zeros((), jnp.int32), params, params, neg_inf, neg_inf, neg_inf, jnp.zeros((), bool))
    itr, params, _, _, _, last_ll, _ = lax.while_loop(cond_fn, body_fn, c0)
    mu, sigma, logmass = params
    finite = (jnp.all(jnp.isfinite(jnp.where(active[:, None], mu, 0.0)))
              & jnp.all(jnp.isfinite(jnp.where(active[:, None, None], sigma, 0.0)))
              & jnp.isfinite(last_ll))
    out = GMM(mu=mu, sigma=sigma, logmass=logmass, active=active, n_points=n_points,
              initialized=jnp.ones((), bool))
    return out, GMMFitInfo(loglik=last_ll, iterations=itr, ok=finite)


def gmm_update(gmm: GMM, key, data: Array, mask, k_active, max_iterations: int) -> GMM:
    """Run EM on the valid rows of ``data`` with ``k_active`` clusters (toolbox ``GMM.update``).

    Warm-starts from ``gmm`` when it is initialised and ``k_active`` equals its active count;
    otherwise initialises from a random hard assignment drawn with ``key``. EM stops when the
    log-likelihood decreases or changes by less than 1e-5 relative, or after ``max_iterations``.

    Args:
      gmm: GMM with capacity [K_max, D].
      key: PRNG key (used only on (re-)initialisation).
      data: [n, D] points.
      mask: [n] bool, valid rows (None: all).
      k_active: [] int (may be traced), clusters to use, clipped to [1, K_max].
      max_iterations: EM cap (toolbox 100); a Python int or a traced integer.
    Returns: the updated GMM.
    """
    return gmm_update_with_info(gmm, key, data, mask, k_active, max_iterations)[0]


def gmm_loglik(gmm: GMM, data: Array, mask=None) -> Array:
    """Σ over valid rows of log Σ_i π_i N(x_n; μ_i, Σ_i).

    Args: data [n, D], mask [n] bool or None.
    Returns: [] scalar.
    """
    mask = _default_mask(data, mask)
    data = jnp.where(mask[:, None], data, 0.0)
    return _loglik(_log_obs(gmm.mu, gmm.sigma, gmm.logmass, gmm.active, data), mask)


def gmm_inference(gmm: GMM, pts: Array, mask=None):
    """Normal-inverse-Wishart prior for a set of query points (toolbox ``GMM.inference``).

    w_i = mean over valid points of the posterior of cluster i; μ₀ = Σ w_i μ_i;
    Φ = Σ w_i (Σ_i + (μ_i−μ₀)(μ_i−μ₀)ᵀ) (the symmetric form; the toolbox's (μ_i−μ₀)μ_iᵀ is equal
    because Σ w_i = 1); m = 1 and n₀ = (N − 2 − D)/N with N = ``gmm.n_points``.

    Args:
      pts: [n, D] query points; mask: [n] bool or None.
    Returns: (mu0 [D], Phi [D, D], m [], n0 []).
    """
    mask = _default_mask(pts, mask)
    pts = jnp.where(mask[:, None], pts, 0.0)
    dtype = gmm.mu.dtype
    D = gmm.mu.shape[-1]
    logobs = _log_obs(gmm.mu, gmm.sigma, gmm.logmass, gmm.active, pts)
    r = _responsibilities(logobs, mask, gmm.active)
    wts = r.sum(0) / jnp.maximum(mask.sum(), 1).astype(dtype)  # [K]
    mu0 = jnp.matmul(wts, gmm.mu, precision=_HI)
    diff = gmm.mu - mu0
    Phi = jnp.einsum("k,kde->de", wts, gmm.sigma + diff[:, :, None] * diff[:, None, :], precision=_HI)
    N = gmm.n_points.astype(dtype)
    m = jnp.ones((), dtype)
    n0 = (N - 2.0 - D) / N
    return mu0, linalg.sym(Phi), m, n0


def niw_prior(gmm: GMM, pts: Array, strength: float, mask=None):
    """GMM prior scaled by ``strength`` (toolbox ``DynamicsPriorGMM.eval`` / ``PolicyPriorGMM.eval``).

    m ← strength·m, n₀ ← strength·n₀, Φ ← m·Φ.

    Args: pts [n, D], mask [n] or None.
    Returns: (mu0 [D], Phi [D, D], m [], n0 []).
    """
    mu0, Phi, m, n0 = gmm_inference(gmm, pts, mask)
    m = m * strength
    n0 = n0 * strength
    return mu0, Phi * m, m, n0

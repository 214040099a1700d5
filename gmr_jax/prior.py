"""The sample store and the normal-inverse-Wishart fit shared by the dynamics prior
(``dynamics.py``) and the policy prior (``linearize.py``) (mdgps-toolbox.md §3, §4.2).

Both keep a ring buffer of the last trajectories, refit a GMM on points built from them
(:func:`refit_gmm`), and fit each time step's linear-Gaussian conditional with the GMM as a
normal-inverse-Wishart prior (:func:`conditional_fit`). One condition per call; vmappable.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from gmr_jax import linalg
from gmr_jax.config import REGULARIZERS
from gmr_jax.gmm import gmm_update, niw_prior, num_clusters
from gmr_jax.types import GMM

Array = jax.Array
_HI = jax.lax.Precision.HIGHEST  # full float32 products on GPUs (their default is TF32)


def ring_insert(buf: Array, count: Array, new: Array) -> Array:
    """Write ``new`` trajectories into the ring buffer ``buf`` after ``count`` earlier ones.

    Args:
      buf: [S, ...] buffer; count: [] trajectories added before; new: [N, ...].
    Returns: [S, ...] the buffer holding the last min(count + N, S) trajectories. If N > S only
      the last S new ones are written (statically sliced, so the scatter indices are distinct).
    """
    S, N = buf.shape[0], new.shape[0]
    skip = max(0, N - S)
    new = new[skip:]
    idx = (count + skip + jnp.arange(new.shape[0])) % S
    return buf.at[idx].set(new.astype(buf.dtype), unique_indices=True)


def stored_mask(count: Array, S: int) -> Array:
    """[S] bool, which ring-buffer slots hold a trajectory."""
    return jnp.arange(S) < jnp.minimum(count, S)


def sample_sizes(X: Array, who: str) -> tuple[int, int, int]:
    """(N, T, dX) of samples X [N, T, dX]; a fit needs N ≥ 2 (ValueError naming ``who``)."""
    N, T, dX = X.shape
    if N < 2:
        raise ValueError(f"{who}: needs at least 2 samples, got N={N}")
    return N, T, dX


def refit_gmm(gmm: GMM, key, pts: Array, count: Array, min_samples_per_cluster: int,
              max_clusters: int, em_iterations: int) -> GMM:
    """Refit a prior's GMM on the points of its stored trajectories (toolbox ``update``).

    K = max(2, min(max_clusters, ⌊n_stored·L/min_samples_per_cluster⌋)); EM warm-starts when K
    is unchanged.

    Args:
      gmm: the current GMM.
      key: PRNG key for a (re-)initialisation.
      pts: [S, L, D] points of the S ring-buffer slots (L per trajectory); rows of empty slots
        are masked out.
      count: [] trajectories ever added.
    Returns: the updated GMM.
    """
    S, L, D = pts.shape
    mask = jnp.repeat(stored_mask(count, S), L)
    K = num_clusters(jnp.minimum(count, S) * L, min_samples_per_cluster, max_clusters)
    return gmm_update(gmm, key, pts.reshape(S * L, D), mask, K, em_iterations)


def regularizer_matrix(kind: str, value: float, n: int, D: int, dtype) -> Array:
    """[D, D] zeros with ``value`` added to the leading [n, n] block of a joint covariance.

    kind "ridge": value·I on the block (FIX, the default). kind "toolbox": value added to every
    entry of the block, value·11ᵀ, which is what the toolbox's ``sig_reg[:n, :n] = value`` numpy
    broadcast does. The rank-one form shifts the block only along 11ᵀ, so it cannot make a
    rank-deficient block (the transitions of a deterministic plant, a deterministic x₀)
    invertible; it is kept as an option to reproduce the toolbox's numbers.
    """
    if kind == "ridge":
        block = value * jnp.eye(n, dtype=dtype)
    elif kind == "toolbox":
        block = jnp.full((n, n), value, dtype)
    else:
        raise ValueError(f"regularizer={kind!r}: allowed values are {REGULARIZERS}")
    return jnp.zeros((D, D), dtype).at[:n, :n].set(block, unique_indices=True)


def gauss_fit_joint_prior(pts: Array, mu0: Array, Phi: Array, m, n0, dwts: Array, d1: int, d2: int,
                          sig_reg: Array):
    """MAP Gaussian fit of [a; b] under a NIW prior, then condition b on a (toolbox formula).

    μ̂ = Σ w_n y_n;  Ŝ = Σ w_n (y_n−μ̂)(y_n−μ̂)ᵀ;
    Σ = [N·Ŝ + Φ + N·m/(N+m)·(μ̂−μ₀)(μ̂−μ₀)ᵀ]/(N + n₀) (symmetrised) + sig_reg;
    fd = (Σ_aa⁻¹ Σ_ab)ᵀ,  fc = μ̂_b − fd μ̂_a,  dynsig = Σ_bb − fd Σ_aa fdᵀ (symmetrised).
    The posterior mean is the empirical mean; the prior enters only the covariance.

    Args:
      pts: [N, d1 + d2] rows y = [a; b].
      mu0: [d1 + d2], Phi: [d1 + d2, d1 + d2], m: [], n0: [] the prior (m = n0 = 0, Φ = 0: none).
      dwts: [N] weights summing to one (toolbox: 1/N). N counts the rows with positive weight,
        so zero-weight padding rows do not change the result.
      d1, d2: static block sizes.
      sig_reg: [d1 + d2, d1 + d2] added to the joint covariance.
    Returns: (fd [d2, d1], fc [d2], dynsig [d2, d2]).
    """
    dtype = pts.dtype
    N = jnp.sum(dwts > 0).astype(dtype)
    dwts = dwts.astype(dtype)
    pts = jnp.where((dwts > 0)[:, None], pts, 0.0)
    mm = lambda a, b: jnp.matmul(a, b, precision=_HI)
    mun = mm(dwts, pts)
    diff = pts - mun
    empsig = linalg.sym(mm((diff * dwts[:, None]).T, diff))
    dmu = mun - mu0
    sigma = (N * empsig + Phi + (N * m / (N + m)) * jnp.outer(dmu, dmu)) / (N + n0)
    sigma = linalg.sym(sigma) + sig_reg
    if jnp.finfo(dtype).bits < 64:
        # The (a, a) block's ridge raised to the precision's Cholesky floor where it lies below
        # it (the policy fit has no ridge after t = 0). In float64 the floor (~1e-13·Σ_ii) lies
        # below the rounding of the fit's own inputs; it is left out there, so that float64
        # stays bitwise the toolbox's formula.
        floor = jnp.maximum(linalg.cholesky_floor(sigma[:d1, :d1]) - jnp.diagonal(sig_reg)[:d1], 0.0)
        sigma = sigma.at[jnp.arange(d1), jnp.arange(d1)].add(floor, unique_indices=True)
    s11 = sigma[:d1, :d1]
    s12 = sigma[:d1, d1:d1 + d2]
    # Σ_aa is symmetric positive definite (prior or ridge): a Cholesky solve, not a general one.
    fd = linalg.cho_solve(linalg.cholesky(s11), s12).T
    fc = mun[d1:d1 + d2] - mm(fd, mun[:d1])
    dynsig = linalg.sym(sigma[d1:d1 + d2, d1:d1 + d2] - mm(mm(fd, s11), fd.T))
    return fd, fc, dynsig


def conditional_fit(gmm: GMM, pts: Array, strength: float, dwts: Array, d1: int, d2: int,
                    sig_reg: Array):
    """One time step's conditional fit of b on a (:func:`gauss_fit_joint_prior`) with the GMM
    evaluated at the points as its normal-inverse-Wishart prior; without a fitted GMM the prior
    terms are dropped (m = n₀ = 0, Φ = 0: the plain empirical fit).

    Args: pts [N, d1 + d2]; the rest as :func:`gauss_fit_joint_prior`.
    Returns: (fd [d2, d1], fc [d2], conditional covariance [d2, d2]).
    """
    mu0, Phi, m, n0 = niw_prior(gmm, pts, strength)
    mu0, Phi, m, n0 = (jnp.where(gmm.initialized, a, 0.0) for a in (mu0, Phi, m, n0))
    return gauss_fit_joint_prior(pts, mu0, Phi, m, n0, dwts, d1, d2, sig_reg)

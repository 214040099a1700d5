"""Linearisation of the global policy around the samples, with a GMM prior (MDGPS π̄).

Toolbox reference: ``shared/reference/mdgps-toolbox.md`` §4.2 (``PolicyPriorGMM``) and §1.2.

The prior is a GMM over [x, π(x)] rows: the stored sample states paired with the *current*
policy mean re-evaluated on them. Each step t then gets a MAP linear-Gaussian fit of π's mean
actions at the N current samples, conditioned u on x with ``gauss_fit_joint_prior``; the policy's
own (state-independent) variance is added to the conditional covariance.

One condition per call; vmappable over a leading condition axis.

Deviation from the toolbox (``FIX``): the t = 0 regularisation is a ridge
``t0_regularization·I`` on the state block; the toolbox broadcasts 1e-8 to every entry of that
block (rank one), which cannot make a degenerate block (deterministic x₀) invertible
(``PolicyPriorConfig.t0_regularizer = "toolbox"`` restores the broadcast; see
``prior.regularizer_matrix``).

Also here: ``linearize_policy_autodiff``, the exact first-order expansion of a differentiable
policy around given states (the option for GMR policies).
"""

from __future__ import annotations

from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp

from gmr_jax.config import POLICY_PRIOR_MODES, PolicyPriorConfig
from gmr_jax import linalg
from gmr_jax.gmm import gmm_empty
from gmr_jax.prior import (conditional_fit, refit_gmm, regularizer_matrix, ring_insert, sample_sizes,
                           stored_mask)
from gmr_jax.types import GMM

Array = jax.Array


class PolicyPrior(NamedTuple):
    """Store of sample states and the GMM over [x, π(x)].

    Attributes:
      X: [S, T, dX] stored states, S = max_samples (ring buffer).
      count: [] int32, trajectories ever added ('replace' resets it to N). min(count, S) slots are
        filled (slots 0 … min(count, S) − 1); the next one goes to slot count mod S.
      gmm: GMM over D = dX + dU, capacity max_clusters.
    """

    X: Array
    count: Array
    gmm: GMM


def policy_prior_empty(T: int, dX: int, dU: int, cfg: PolicyPriorConfig, dtype=jnp.float32) -> PolicyPrior:
    """An empty policy prior: a zero state buffer [max_samples, T, dX] and an uninitialised GMM."""
    return PolicyPrior(
        X=jnp.zeros((cfg.max_samples, T, dX), dtype),
        count=jnp.zeros((), jnp.int32),
        gmm=gmm_empty(cfg.max_clusters, dX + dU, dtype),
    )


def update_policy_prior(prior: PolicyPrior, key, X: Array, action_fn: Callable[[Array], Array],
                        cfg: PolicyPriorConfig, mode: str | None = None) -> PolicyPrior:
    """Store the new sample states and refit the GMM on [x, π(x)] (toolbox ``PolicyPriorGMM.update``).

    'add' appends and keeps the last max_samples trajectories; 'replace' keeps only X. The policy
    mean is re-evaluated on every stored state (the policy changed since they were stored).
    K = max(2, min(max_clusters, ⌊n_stored·T/min_samples_per_cluster⌋)), T the full horizon.

    Args:
      prior: PolicyPrior of one condition.
      key: PRNG key for a GMM (re-)initialisation.
      X: [N, T, dX] the current sample states.
      action_fn: x [dX] -> u [dU], the current policy mean (vmapped here).
      cfg: PolicyPriorConfig; mode: 'add' or 'replace' (static), default ``cfg.mode``.
    Returns: the updated PolicyPrior.
    """
    mode = cfg.mode if mode is None else mode
    if mode not in POLICY_PRIOR_MODES:
        raise ValueError(f"mode={mode!r}: allowed values are {POLICY_PRIOR_MODES}")
    S, T, dX = prior.X.shape
    N = X.shape[0]
    if mode == "replace":
        if N > S:
            raise ValueError(f"update_policy_prior: mode 'replace' stores all N={N} samples, "
                             f"but max_samples={S}; raise max_samples")
        Xb = prior.X.at[:N].set(X.astype(prior.X.dtype), unique_indices=True)
        count = jnp.asarray(N, jnp.int32)
    else:
        Xb = ring_insert(prior.X, prior.count, X)
        count = prior.count + N
    mask = stored_mask(count, S)[:, None, None]
    U = jax.vmap(action_fn)(Xb.reshape(S * T, dX)).reshape(S, T, -1)
    # the policy may be undefined on empty slots: their rows are zeroed (and masked in the fit)
    pts = jnp.where(mask, jnp.concatenate([Xb, U.astype(Xb.dtype)], axis=-1), 0.0)
    gmm = refit_gmm(prior.gmm, key, pts, count, cfg.min_samples_per_cluster, cfg.max_clusters,
                    cfg.em_iterations)
    return PolicyPrior(X=Xb, count=count, gmm=gmm)


def _collapse_pol_sig(pol_sig: Array, T: int) -> Array:
    """pol_sig [N, T, dU, dU], [T, dU, dU] or [dU, dU] -> [T, dU, dU] (mean over samples)."""
    if pol_sig.ndim == 4:
        # The toolbox averages over samples; exact because the policy variance is state-independent.
        pol_sig = jnp.mean(pol_sig, axis=0)
    elif pol_sig.ndim == 2:
        pol_sig = jnp.broadcast_to(pol_sig, (T,) + pol_sig.shape)
    elif pol_sig.ndim != 3:
        raise ValueError(f"pol_sig must be [N, T, dU, dU], [T, dU, dU] or [dU, dU], got {pol_sig.shape}")
    return pol_sig


def linearize_policy(prior: PolicyPrior, X: Array, pol_mu: Array, pol_sig: Array, cfg: PolicyPriorConfig):
    """Time-varying linear-Gaussian fit π̄_t(u|x) = N(pol_K_t x + pol_k_t, pol_S_t) (toolbox ``fit``).

    Per t: prior (μ₀, Φ, m, n₀) from the GMM at the points [x_{n,t}, π(x_{n,t})], then
    ``gauss_fit_joint_prior`` with weights 1/N; pol_S_t = conditional covariance + mean_n pol_sig.
    Call ``update_policy_prior`` first: the prior is what makes the fit well-posed for N < dX.

    Args:
      prior: PolicyPrior of this condition.
      X: [N, T, dX] sample states, N ≥ 2.
      pol_mu: [N, T, dU] policy means at those states.
      pol_sig: [N, T, dU, dU], [T, dU, dU] or [dU, dU] policy covariance.
      cfg: PolicyPriorConfig.
    Returns: (pol_K [T, dU, dX], pol_k [T, dU], pol_S [T, dU, dU]).
    """
    N, T, dX = sample_sizes(X, "linearize_policy")
    dU = pol_mu.shape[-1]
    dtype = X.dtype
    D = dX + dU
    pol_sig = _collapse_pol_sig(jnp.asarray(pol_sig, dtype), T)
    Y = jnp.swapaxes(jnp.concatenate([X, pol_mu.astype(dtype)], axis=-1), 0, 1)  # [T, N, D]
    dwts = jnp.full((N,), 1.0 / N, dtype)
    # FIX (default "ridge"): ridge on the x block at t = 0 only (toolbox: 1e-8 broadcast over the
    # block, "toolbox").
    reg0 = regularizer_matrix(cfg.t0_regularizer, cfg.t0_regularization, dX, D, dtype)
    sig_reg = jnp.zeros((T, D, D), dtype).at[0].set(reg0, unique_indices=True)

    def step(pts, reg):
        return conditional_fit(prior.gmm, pts, cfg.strength, dwts, dX, dU, reg)

    pol_K, pol_k, cond_S = jax.vmap(step)(Y, sig_reg)
    return pol_K, pol_k, linalg.sym(cond_S + pol_sig)


def linearize_policy_autodiff(action_fn: Callable[[Array], Array], x: Array, pol_sig: Array):
    """First-order expansion of a differentiable policy mean around states x_t.

    pol_K_t = ∂π/∂x (x_t), pol_k_t = π(x_t) − pol_K_t x_t, pol_S_t = pol_sig.

    Args:
      action_fn: x [dX] -> u [dU].
      x: [T, dX] expansion points (e.g. the sample mean states).
      pol_sig: [T, dU, dU] or [dU, dU] policy covariance.
    Returns: (pol_K [T, dU, dX], pol_k [T, dU], pol_S [T, dU, dU]).
    """
    T = x.shape[0]
    u, K = jax.vmap(lambda xt: (action_fn(xt), jax.jacfwd(action_fn)(xt)))(x)
    k = u - jnp.einsum("tux,tx->tu", K, x, precision=jax.lax.Precision.HIGHEST)
    return K, k, linalg.sym(_collapse_pol_sig(jnp.asarray(pol_sig, x.dtype), T))

"""Linear-Gaussian dynamics fit with a GMM normal-inverse-Wishart prior, and the initial state.

Toolbox reference: ``shared/reference/mdgps-toolbox.md`` §3 (``DynamicsPriorGMM``,
``DynamicsLRPrior.fit``, ``gauss_fit_joint_prior``) and §1.6 (x0mu, x0sigma).

One condition per call; every function is pure and vmappable over a leading condition axis
(each condition has its own ``DynamicsPrior``). Usage per iteration, as in the toolbox::

    prior = update_dynamics_prior(prior, key, X, U, cfg)   # store samples, refit the GMM
    dyn = fit_dynamics(prior, X, U, cfg)                    # per-step fit + x0 (uses the updated prior)

Deviations from the toolbox (plain defects, see §10 of the reference), marked ``FIX`` below:
- the (x, u)-block regularisation is a ridge ``regularization·I``, not the rank-one
  ``regularization·11ᵀ`` that the toolbox's broadcast produces (``DynamicsConfig.regularizer =
  "toolbox"`` restores the broadcast, for exact toolbox numerics; ``regularizer_matrix``);
- the ring buffer keeps the last ``max_samples`` trajectories, not ``max_samples − 1``;
- the x0 prior term is (Φ₀ + N·m/(N+m)·ΔΔᵀ)/(N + n₀), Φ₀ included in the division.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from gmr_jax import linalg
from gmr_jax.config import DynamicsConfig
from gmr_jax.gmm import gmm_empty
from gmr_jax.prior import (conditional_fit, refit_gmm, regularizer_matrix, ring_insert, sample_sizes,
                           stored_mask)
from gmr_jax.types import GMM, Dynamics

Array = jax.Array


class DynamicsPrior(NamedTuple):
    """Store of past trajectories (a ring buffer) and the GMM fitted on their transitions.

    Attributes:
      X: [S, T, dX] stored states, S = max_samples.
      U: [S, T, dU] stored actions.
      count: [] int32, trajectories ever added. min(count, S) slots are filled (slots
        0 … min(count, S) − 1) and the next one goes to slot count mod S.
      gmm: GMM over points [x_t, u_t, x_{t+1}] (D = 2dX + dU), capacity max_clusters.
    """

    X: Array
    U: Array
    count: Array
    gmm: GMM


def dynamics_prior_empty(T: int, dX: int, dU: int, cfg: DynamicsConfig, dtype=jnp.float32) -> DynamicsPrior:
    """An empty prior: zero buffers of capacity ``cfg.max_samples`` and an uninitialised GMM."""
    S = cfg.max_samples
    return DynamicsPrior(
        X=jnp.zeros((S, T, dX), dtype),
        U=jnp.zeros((S, T, dU), dtype),
        count=jnp.zeros((), jnp.int32),
        gmm=gmm_empty(cfg.max_clusters, 2 * dX + dU, dtype),
    )


def transition_points(X: Array, U: Array) -> Array:
    """Points [x_t, u_t, x_{t+1}] for t < T−1.

    Args: X [..., T, dX], U [..., T, dU].
    Returns: [..., T−1, 2dX + dU].
    """
    return jnp.concatenate([X[..., :-1, :], U[..., :-1, :], X[..., 1:, :]], axis=-1)


def update_dynamics_prior(prior: DynamicsPrior, key, X: Array, U: Array, cfg: DynamicsConfig) -> DynamicsPrior:
    """Append this iteration's samples and refit the GMM (toolbox ``DynamicsPriorGMM.update``).

    K = max(2, min(max_clusters, ⌊n_stored·(T−1)/min_samples_per_cluster⌋)); EM warm-starts when K
    is unchanged.

    Args:
      prior: DynamicsPrior of one condition.
      key: PRNG key for a GMM (re-)initialisation.
      X: [N, T, dX], U: [N, T, dU] the new trajectories.
    Returns: the updated DynamicsPrior.
    """
    S, T, _ = prior.X.shape
    N = X.shape[0]
    # FIX: the toolbox keeps only max_samples − 1 trajectories (start = N_tot − max_samples + 1).
    Xb = ring_insert(prior.X, prior.count, X)
    Ub = ring_insert(prior.U, prior.count, U)
    count = prior.count + N
    # the points [x_t, u_t, x_{t+1}] of every stored trajectory, trajectory-major as in the toolbox
    gmm = refit_gmm(prior.gmm, key, transition_points(Xb, Ub), count, cfg.min_samples_per_cluster,
                    cfg.max_clusters, cfg.em_iterations)
    return DynamicsPrior(X=Xb, U=Ub, count=count, gmm=gmm)


def prior_initial_state(prior: DynamicsPrior, strength: float):
    """Prior of the initial state from the stored trajectories (toolbox ``initial_state``).

    μ₀ = mean of the stored x₀, Φ₀ = m·diag(population variance of the stored x₀), m = n₀ = dX·strength.

    Returns: (mu0 [dX], Phi0 [dX, dX], m [], n0 []).
    """
    S, _, dX = prior.X.shape
    dtype = prior.X.dtype
    valid = stored_mask(prior.count, S)
    n = jnp.maximum(valid.sum(), 1).astype(dtype)
    x0 = jnp.where(valid[:, None], prior.X[:, 0, :], 0.0)
    mu0 = x0.sum(0) / n
    var = jnp.where(valid[:, None], (x0 - mu0) ** 2, 0.0).sum(0) / n
    m = jnp.asarray(dX * strength, dtype)
    return mu0, m * jnp.diag(var), m, m


def fit_initial_state(prior: DynamicsPrior, X: Array, cfg: DynamicsConfig):
    """x0mu and x0sigma (toolbox ``Algorithm._update_dynamics``).

    x0mu = mean_n x_{n,0}; x0sigma = diag(max(var_n x_{n,0}, initial_state_var))
    + (Φ₀ + N·m/(N+m)·(x0mu−μ₀)(x0mu−μ₀)ᵀ)/(N + n₀), the prior term only when the prior holds data.

    Args: X [N, T, dX].
    Returns: (x0mu [dX], x0sigma [dX, dX]).
    """
    N = X.shape[0]
    dtype = X.dtype
    x0 = X[:, 0, :]
    x0mu = jnp.mean(x0, axis=0)
    x0sigma = jnp.diag(jnp.maximum(jnp.var(x0, axis=0), cfg.initial_state_var).astype(dtype))
    mu0, Phi0, m, n0 = prior_initial_state(prior, cfg.strength)
    d = x0mu - mu0
    # FIX: the toolbox divides only the outer-product term by (N + n₀); Φ₀ belongs inside too.
    term = (Phi0 + (N * m / (N + m)) * jnp.outer(d, d)) / (N + n0)
    x0sigma = x0sigma + jnp.where(prior.count > 0, term, 0.0)
    return x0mu, linalg.sym(x0sigma)


def fit_dynamics(prior: DynamicsPrior, X: Array, U: Array, cfg: DynamicsConfig) -> Dynamics:
    """Per-step linear-Gaussian dynamics with the GMM prior, plus the initial state.

    For t < T−1, with the N points y = [x_t, u_t, x_{t+1}] and weights 1/N, the prior
    (μ₀, Φ, m, n₀) comes from the GMM evaluated at those points and ``gauss_fit_joint_prior``
    conditions x_{t+1} on [x_t, u_t]. Entries at t = T−1 are zero (toolbox). Call
    ``update_dynamics_prior`` with the same samples first. Without a fitted GMM the prior terms are
    dropped (m = n₀ = 0, Φ = 0: the plain empirical fit, toolbox ``DynamicsLR``).

    Args:
      prior: DynamicsPrior of this condition (already updated with X, U).
      X: [N, T, dX], U: [N, T, dU] the current samples, N ≥ 2.
    Returns: Dynamics with Fm [T, dX, dX+dU], fv [T, dX], dyn_covar [T, dX, dX], x0mu [dX],
      x0sigma [dX, dX].
    """
    N, T, dX = sample_sizes(X, "fit_dynamics")
    dU = U.shape[-1]
    dtype = X.dtype
    dxu = dX + dU
    D = 2 * dX + dU
    Y = jnp.swapaxes(transition_points(X, U), 0, 1)  # [T−1, N, D]
    dwts = jnp.full((N,), 1.0 / N, dtype)
    # FIX (default "ridge"): ridge on the (x, u) diagonal; the toolbox's sig_reg[:dX+dU, :dX+dU] =
    # reg broadcasts to a rank-one reg·11ᵀ, which does not regularise ("toolbox").
    sig_reg = regularizer_matrix(cfg.regularizer, cfg.regularization, dxu, D, dtype)

    def step(pts):
        return conditional_fit(prior.gmm, pts, cfg.strength, dwts, dxu, dX, sig_reg)

    Fm, fv, dyn_covar = jax.vmap(step)(Y)
    pad = lambda a: jnp.concatenate([a, jnp.zeros((1,) + a.shape[1:], a.dtype)], axis=0)
    x0mu, x0sigma = fit_initial_state(prior, X, cfg)
    return Dynamics(Fm=pad(Fm), fv=pad(fv), dyn_covar=pad(dyn_covar), x0mu=x0mu, x0sigma=x0sigma)


def dynamics_ok(dyn: Dynamics) -> Array:
    """[] bool, every field finite (use on the host to fail loudly on a broken fit)."""
    return jnp.all(jnp.stack([jnp.all(jnp.isfinite(a)) for a in dyn]))

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
from gmr_jax.config import REGULARIZERS, DynamicsConfig
from gmr_jax.gmm import gmm_empty, gmm_update, niw_prior, num_clusters
from gmr_jax.types import GMM, Dynamics

Array = jax.Array
_HI = jax.lax.Precision.HIGHEST  # full float32 products on GPUs (their default is TF32)


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


def _sym(a: Array) -> Array:
    return 0.5 * (a + jnp.swapaxes(a, -1, -2))


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
    return buf.at[idx].set(new.astype(buf.dtype))


def stored_mask(count: Array, S: int) -> Array:
    """[S] bool, which ring-buffer slots hold a trajectory."""
    return jnp.arange(S) < jnp.minimum(count, S)


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
    valid = stored_mask(count, S)
    pts = transition_points(Xb, Ub)  # [S, T−1, D], trajectory-major rows as in the toolbox
    D = pts.shape[-1]
    mask = jnp.repeat(valid, T - 1)
    n_stored = jnp.minimum(count, S)
    K = num_clusters(n_stored * (T - 1), cfg.min_samples_per_cluster, cfg.max_clusters)
    gmm = gmm_update(prior.gmm, key, pts.reshape(S * (T - 1), D), mask, K, cfg.em_iterations)
    return DynamicsPrior(X=Xb, U=Ub, count=count, gmm=gmm)


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
    return jnp.zeros((D, D), dtype).at[:n, :n].set(block)


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
    empsig = _sym(mm((diff * dwts[:, None]).T, diff))
    dmu = mun - mu0
    sigma = (N * empsig + Phi + (N * m / (N + m)) * jnp.outer(dmu, dmu)) / (N + n0)
    sigma = _sym(sigma) + sig_reg
    s11 = sigma[:d1, :d1]
    s12 = sigma[:d1, d1:d1 + d2]
    # Σ_aa is symmetric positive definite (prior or ridge): a Cholesky solve, not a general one.
    fd = linalg.cho_solve(linalg.cholesky(s11), s12).T
    fc = mun[d1:d1 + d2] - mm(fd, mun[:d1])
    dynsig = _sym(sigma[d1:d1 + d2, d1:d1 + d2] - mm(mm(fd, s11), fd.T))
    return fd, fc, dynsig


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
    return x0mu, _sym(x0sigma)


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
    N, T, dX = X.shape
    dU = U.shape[-1]
    if N < 2:
        raise ValueError(f"fit_dynamics: needs at least 2 samples, got N={N}")
    dtype = X.dtype
    dxu = dX + dU
    D = 2 * dX + dU
    Y = jnp.swapaxes(transition_points(X, U), 0, 1)  # [T−1, N, D]
    dwts = jnp.full((N,), 1.0 / N, dtype)
    # FIX (default "ridge"): ridge on the (x, u) diagonal; the toolbox's sig_reg[:dX+dU, :dX+dU] =
    # reg broadcasts to a rank-one reg·11ᵀ, which does not regularise ("toolbox").
    sig_reg = regularizer_matrix(cfg.regularizer, cfg.regularization, dxu, D, dtype)
    has_gmm = prior.gmm.initialized

    def step(pts):
        mu0, Phi, m, n0 = niw_prior(prior.gmm, pts, cfg.strength)
        mu0 = jnp.where(has_gmm, mu0, 0.0)
        Phi = jnp.where(has_gmm, Phi, 0.0)
        m = jnp.where(has_gmm, m, 0.0)
        n0 = jnp.where(has_gmm, n0, 0.0)
        return gauss_fit_joint_prior(pts, mu0, Phi, m, n0, dwts, dxu, dX, sig_reg)

    Fm, fv, dyn_covar = jax.vmap(step)(Y)
    pad = lambda a: jnp.concatenate([a, jnp.zeros((1,) + a.shape[1:], a.dtype)], axis=0)
    x0mu, x0sigma = fit_initial_state(prior, X, cfg)
    return Dynamics(Fm=pad(Fm), fv=pad(fv), dyn_covar=pad(dyn_covar), x0mu=x0mu, x0sigma=x0sigma)


def dynamics_ok(dyn: Dynamics) -> Array:
    """[] bool, every field finite (use on the host to fail loudly on a broken fit)."""
    return jnp.all(jnp.stack([jnp.all(jnp.isfinite(a)) for a in dyn]))

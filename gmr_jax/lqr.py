"""KL-constrained LQR: the C-step of MDGPS (mdgps-toolbox.md §2, §4.1, §10); the step size is
``step_size.py``.

Everything here is for ONE condition and is pure, jittable and vmappable over a leading
condition axis (each condition carries its own η). Loops over time are ``lax.scan``; the
non-PD repair (§2.3) and the η dual search (§2.4) are ``lax.while_loop``s, so a C-step of M
conditions is one compiled program: ``jax.vmap(eta_search, in_axes=(0, 0, 0, 0, 0, None))``.

Conventions (types.py): y = [x; u]; a controller's ``chol_pol_covar`` is the *upper* Cholesky
factor U with pol_covar = Uᵀ U; quadratic costs are in absolute coordinates.

Numerical failures never raise inside ``jit``: ``lqr_backward`` and ``eta_search`` return an
``ok`` flag (False where the toolbox raises its ValueError, i.e. when the non-PD repair pushes
η to ``max_eta``, or where a NaN appears). Callers check it on the host
(``check_eta_search`` raises the toolbox's errors).

All functions follow the dtype of their array inputs (float32 on GPU, float64 in tests).
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
from jax import lax

from gmr_jax import linalg
from gmr_jax.config import InitLQRConfig, LQRConfig
from gmr_jax.types import Dynamics, LinearGaussianPolicy, Marginals, QuadraticCost

Array = jax.Array

__all__ = [
    "EtaSearchInfo",
    "bracket_update",
    "check_eta_search",
    "estimate_cost",
    "eta_search",
    "guess_dynamics",
    "init_lqr",
    "init_pd",
    "kl_augmented_cost",
    "lqr_backward",
    "lqr_forward",
    "policy_from_covariance",
    "policy_from_precision",
    "policy_precision",
    "traj_kl",
]


# ---------------------------------------------------------------------------------------------
# Small linear-algebra helpers (all batched over leading axes)


def _mT(a: Array) -> Array:
    return jnp.swapaxes(a, -1, -2)


def _chol_upper(a: Array) -> Array:
    """Upper Cholesky factor U with A = Uᵀ U (NaN where A is not PD, as jnp.linalg.cholesky)."""
    return _mT(linalg.cholesky(a))


def _eye_like(a: Array) -> Array:
    """Identity broadcast to the shape of the square matrices ``a`` [..., n, n]."""
    return jnp.broadcast_to(jnp.eye(a.shape[-1], dtype=a.dtype), a.shape)


def policy_precision(policy: LinearGaussianPolicy) -> Array:
    """Precision S⁻¹ [T, dU, dU] recomputed from the upper Cholesky factor by triangular solves.

    The toolbox recomputes precisions from ``chol_pol_covar`` (the linearised policy carries no
    valid ``inv_pol_covar``), so we do the same: S⁻¹ = U⁻¹ U⁻ᵀ.
    """
    u = policy.chol_pol_covar
    u_inv = linalg.solve_triangular(u, _eye_like(u), lower=False)
    return linalg.sym(u_inv @ _mT(u_inv))


def policy_from_precision(K: Array, k: Array, prec: Array) -> LinearGaussianPolicy:
    """Controller from gains and action precision.

    Args:
      K: [..., T, dU, dX] gains.  k: [..., T, dU] offsets.  prec: [..., T, dU, dU] precision.
    Returns:
      LinearGaussianPolicy with pol_covar = prec⁻¹, chol_pol_covar its upper Cholesky factor
      (pol_covar = Uᵀ U) and inv_pol_covar = prec (symmetrised). NaNs mark a non-PD ``prec``.
    """
    prec = linalg.sym(prec)
    low = linalg.cholesky(prec)
    covar = linalg.sym(linalg.cho_solve(low, _eye_like(prec)))
    return LinearGaussianPolicy(K=K, k=k, pol_covar=covar, chol_pol_covar=_chol_upper(covar),
                                inv_pol_covar=prec)


def policy_from_covariance(K: Array, k: Array, covar: Array) -> LinearGaussianPolicy:
    """Controller from gains and action covariance (e.g. a policy linearisation's pol_S).

    Args:
      K: [..., T, dU, dX].  k: [..., T, dU].  covar: [..., T, dU, dU].
    Returns:
      LinearGaussianPolicy with chol_pol_covar = upper Cholesky of ``covar`` and
      inv_pol_covar recomputed from it by triangular solves (toolbox ``PolicyInfo.traj_distr``).
    """
    covar = linalg.sym(covar)
    u = _chol_upper(covar)
    u_inv = linalg.solve_triangular(u, _eye_like(u), lower=False)
    return LinearGaussianPolicy(K=K, k=k, pol_covar=covar, chol_pol_covar=u,
                                inv_pol_covar=linalg.sym(u_inv @ _mT(u_inv)))


# ---------------------------------------------------------------------------------------------
# Backward pass (§2.1) — the one Riccati recursion of the project


def _riccati(Fm: Array, fv: Array, Cm: Array, cv: Array) -> tuple[LinearGaussianPolicy, Array]:
    """Backward pass of §2.1 on an already-augmented cost (no η, no constants).

    Args:
      Fm: [T, dX, dX+dU], fv: [T, dX] dynamics (the entry at T−1 is never used).
      Cm: [T, dX+dU, dX+dU], cv: [T, dX+dU] (augmented) cost.
    Returns:
      (policy, fail): fail is a [] bool, True where a Cholesky of Q_uu or of the resulting
      covariance failed (NaN) at some t. After the first failure the remaining steps are NaN,
      which is harmless: the caller discards the whole sweep, as the toolbox aborts it.
    """
    T, dX = fv.shape
    dU = Cm.shape[-1] - dX
    is_last = jnp.arange(T) == T - 1
    eye_u = jnp.eye(dU, dtype=Cm.dtype)

    def step(carry, inp):
        V, v = carry  # V_{t+1} [dX, dX], v_{t+1} [dX]; zero at T
        F, f, C, c, last = inp
        # jnp.where (not V = 0 alone) keeps a NaN/garbage Fm at T−1 out of Q_{T−1}.
        Q = C + jnp.where(last, 0.0, F.T @ V @ F)
        q = c + jnp.where(last, 0.0, F.T @ (v + V @ f))
        Q = linalg.sym(Q)
        Quu, Qux, Qxu = Q[dX:, dX:], Q[dX:, :dX], Q[:dX, dX:]
        low = linalg.cholesky(Quu)  # NaN when Q_uu is not PD
        # Q_uu⁻¹ [I, Q_ux, q_u] by one pair of triangular solves (smaller program than three).
        sol = linalg.cho_solve(low, jnp.concatenate([eye_u, Qux, q[dX:, None]], axis=1))
        covar = linalg.sym(sol[:, :dU])
        chol_cov = _chol_upper(covar)
        K = -sol[:, dU:dU + dX]
        k = -sol[:, dU + dX]
        V_new = linalg.sym(Q[:dX, :dX] + Qxu @ K)
        v_new = q[:dX] + Qxu @ k
        # A failure of the covariance's Cholesky (possible in float32 for an ill-conditioned
        # but PD Q_uu) is treated like a non-PD Q_uu, so that η is raised instead of NaNs
        # leaking into the controller.
        fail = ~(linalg.all_finite(low) & linalg.all_finite(chol_cov))
        return (V_new, v_new), (K, k, covar, chol_cov, Quu, fail)

    init = (jnp.zeros((dX, dX), Cm.dtype), jnp.zeros((dX,), Cm.dtype))
    _, (K, k, covar, chol_cov, Quu, fail) = lax.scan(step, init, (Fm, fv, Cm, cv, is_last),
                                                     reverse=True)
    policy = LinearGaussianPolicy(K=K, k=k, pol_covar=covar, chol_pol_covar=chol_cov,
                                  inv_pol_covar=Quu)
    return policy, jnp.any(fail)


def kl_augmented_cost(cost: QuadraticCost, anchor: LinearGaussianPolicy, eta) -> QuadraticCost:
    """The η-scaled Lagrangian cost of §2.1 (``compute_costs``), with ω = max_ent_traj = 0.

    With π̄_t(u|x) = N(K̄x + k̄, S̄), P̄ = S̄⁻¹:  −log π̄ = ½ yᵀ M̄ y + yᵀ v̄ + ½k̄ᵀP̄k̄ + const,
    M̄ = [[K̄ᵀP̄K̄, −K̄ᵀP̄], [−P̄K̄, P̄]], v̄ = [K̄ᵀP̄k̄; −P̄k̄], and

        fCm = (Cm + η M̄)/η,  fcv = (cv + η v̄)/η,  fcc = (cc + η ½k̄ᵀP̄k̄)/η.

    Computed as Cm/η + M̄ (same value) so that no η·M̄ product can overflow in float32 for
    η up to max_eta. The constant omits π̄'s normaliser; constants never enter the backward pass.

    Args:
      cost: Cm [T, dX+dU, dX+dU], cv [T, dX+dU], cc [T].
      anchor: the KL anchor π̄ (previous controller, or the linearised global policy), [T, ...].
      eta: [] dual variable, > 0.
    Returns:
      QuadraticCost of the same shapes.
    """
    dtype = cost.Cm.dtype
    eta = jnp.asarray(eta, dtype)
    Kb, kb = anchor.K, anchor.k
    P = policy_precision(anchor)  # [T, dU, dU]
    PK = P @ Kb  # [T, dU, dX]
    Pk = jnp.einsum("tij,tj->ti", P, kb)
    top = jnp.concatenate([_mT(Kb) @ PK, -_mT(PK)], axis=-1)
    bot = jnp.concatenate([-PK, P], axis=-1)
    M = linalg.sym(jnp.concatenate([top, bot], axis=-2))
    v = jnp.concatenate([jnp.einsum("tji,tj->ti", Kb, Pk), -Pk], axis=-1)
    c = 0.5 * jnp.einsum("ti,ti->t", kb, Pk)
    return QuadraticCost(Cm=linalg.sym(cost.Cm) / eta + M, cv=cost.cv / eta + v, cc=cost.cc / eta + c)


def lqr_backward(dyn: Dynamics, cost: QuadraticCost, anchor: LinearGaussianPolicy, eta,
                 cfg: LQRConfig = LQRConfig()) -> tuple[LinearGaussianPolicy, Array, Array]:
    """KL-regularised LQR backward pass with the toolbox's non-PD rule (§2.1, §2.3).

    Runs the recursion on ``kl_augmented_cost(cost, anchor, η)``. If the Cholesky of Q_uu fails
    at any t, the whole sweep is redone with η = η₀ + δ, δ = del0, 2·del0, 4·del0, … (η₀ the
    η passed in; after k failures η = η₀ + del0·2^(k−1), not cumulative). When η would reach
    ``max_eta`` the toolbox raises; here ``ok`` is False instead.

    Args:
      dyn: Fm [T, dX, dX+dU], fv [T, dX] (dyn_covar, x0 unused here).
      cost: Cm [T, dX+dU, dX+dU], cv [T, dX+dU], cc [T].
      anchor: π̄, a LinearGaussianPolicy [T, ...] (upper ``chol_pol_covar`` must be valid).
      eta: [] initial η₀ > 0.
      cfg: LQRConfig (del0, max_eta).
    Returns:
      (policy [T, ...], eta_used [], ok [] bool). pol_covar = Q̃_uu⁻¹, inv_pol_covar = Q̃_uu of
      the η-scaled Q-function.
    """
    dtype = cost.Cm.dtype
    eta0 = jnp.asarray(eta, dtype)
    max_eta = jnp.asarray(cfg.max_eta, dtype)

    def attempt(e):
        fc = kl_augmented_cost(cost, anchor, e)
        return _riccati(dyn.Fm, dyn.fv, fc.Cm, fc.cv)

    # One loop for the first try and the repairs (so the recursion is traced once): δ runs
    # 0, del0, 2·del0, 4·del0, … and the k-th try uses η₀ + δ.
    def cond(state):
        e, delta, _, failed, started = state
        # Stop on success, or once η reached max_eta (the toolbox's ValueError point).
        return ~started | (failed & (e < max_eta))

    def body(state):
        _, delta, _, _, started = state
        e = eta0 + delta
        pol, failed = attempt(e)
        # A repair that reaches max_eta counts as failure even if its sweep succeeded: the
        # toolbox raises before trying it. (η₀ ≥ max_eta itself is tried, as in the toolbox.)
        failed = failed | (started & (e >= max_eta))
        delta = jnp.where(started, 2.0 * delta, jnp.asarray(cfg.del0, dtype))
        return e, delta, pol, failed, jnp.asarray(True)

    placeholder = jax.tree_util.tree_map(lambda a: jnp.zeros(a.shape, dtype), anchor)
    state = (eta0, jnp.zeros((), dtype), placeholder, jnp.asarray(True), jnp.asarray(False))
    eta_used, _, policy, fail, _ = lax.while_loop(cond, body, state)
    return policy, eta_used, ~fail


# ---------------------------------------------------------------------------------------------
# Forward pass, KL and cost estimate (§2.2, §2.4, §2.5)


def lqr_forward(dyn: Dynamics, policy: LinearGaussianPolicy) -> Marginals:
    """State-action marginals of a controller under linear-Gaussian dynamics (§2.2).

    Args:
      dyn: Fm [T, dX, dX+dU], fv [T, dX], dyn_covar [T, dX, dX], x0mu [dX], x0sigma [dX, dX].
      policy: K [T, dU, dX], k [T, dU], pol_covar [T, dU, dU].
    Returns:
      Marginals: mu [T, dX+dU], sigma [T, dX+dU, dX+dU] (symmetrised).
    """

    def step(carry, inp):
        mx, Sx = carry
        K, k, Su, F, f, W = inp
        SxKt = Sx @ K.T
        mu = jnp.concatenate([mx, K @ mx + k])
        sigma = jnp.concatenate([
            jnp.concatenate([Sx, SxKt], axis=1),
            jnp.concatenate([SxKt.T, K @ SxKt + Su], axis=1),
        ], axis=0)
        sigma = linalg.sym(sigma)
        # The transition out of T−1 is computed but never emitted (Fm[T−1] is unused).
        mx_next = F @ mu + f
        Sx_next = linalg.sym(F @ sigma @ F.T + W)
        return (mx_next, Sx_next), (mu, sigma)

    init = (dyn.x0mu, linalg.sym(dyn.x0sigma))
    _, (mu, sigma) = lax.scan(step, init, (policy.K, policy.k, policy.pol_covar, dyn.Fm, dyn.fv,
                                           linalg.sym(dyn.dyn_covar)))
    return Marginals(mu=mu, sigma=sigma)


def traj_kl(marginals: Marginals, new: LinearGaussianPolicy,
            anchor: LinearGaussianPolicy) -> Array:
    """Per-step KL(p_new(u|x) ‖ π̄(u|x)) in expectation over the state marginal, clipped at 0 (§2.4).

    Uses the closed form of §2.4 (the toolbox's ``traj_distr_kl_alt`` form)

        KL_t = ½[tr(P̄ S_new) − dU + log|S̄| − log|S_new| + dᵀP̄d + tr(ΔKᵀP̄ΔK Σ_x)],
        d = ΔK μ_x + Δk,  Δ = new − anchor,

    evaluated under the state part (μ_x, Σ_x) of ``marginals``. With the marginals of ``new``
    (the C-step's case) it equals the toolbox's ``traj_distr_kl`` exactly; we prefer this form
    because every term is a difference or a non-negative quadratic, whereas the toolbox's
    −½μᵀΔMμ − … form cancels large terms and loses the KL in float32. Precisions and
    log-determinants come from the upper Cholesky factors, as in the toolbox.

    Args:
      marginals: mu [T, dX+dU], sigma [T, dX+dU, dX+dU].
      new, anchor: LinearGaussianPolicy [T, ...].
    Returns:
      [T] per-step KL (nats), each ≥ 0.
    """
    dX = new.K.shape[-1]
    dU = new.K.shape[-2]
    mx = marginals.mu[:, :dX]
    Sx = marginals.sigma[:, :dX, :dX]
    Ub, Un = anchor.chol_pol_covar, new.chol_pol_covar
    dK = new.K - anchor.K  # [T, dU, dX]
    d = jnp.einsum("tij,tj->ti", dK, mx) + (new.k - anchor.k)  # [T, dU]

    def whiten(b):  # Ū⁻ᵀ b, so that bᵀ P̄ b = ‖Ū⁻ᵀ b‖²
        return linalg.solve_triangular(Ub, b, lower=False, trans=True)

    W = whiten(jnp.concatenate([_mT(Un), d[..., None], dK], axis=-1))  # one solve for all
    A = W[..., :dU]  # tr(P̄ S_new) = ‖Ū⁻ᵀ U_newᵀ‖²_F
    z = W[..., dU]  # dᵀP̄d = ‖Ū⁻ᵀ d‖²
    Y = W[..., dU + 1:]  # tr(ΔKᵀ P̄ ΔK Σ_x) = tr(Y Σ_x Yᵀ)
    logdet_b = 2.0 * jnp.sum(jnp.log(jnp.abs(jnp.diagonal(Ub, axis1=-2, axis2=-1))), axis=-1)
    logdet_n = 2.0 * jnp.sum(jnp.log(jnp.abs(jnp.diagonal(Un, axis1=-2, axis2=-1))), axis=-1)
    kl = 0.5 * (jnp.sum(A * A, axis=(-2, -1)) - dU + logdet_b - logdet_n
                + jnp.sum(z * z, axis=-1) + jnp.sum((Y @ Sx) * Y, axis=(-2, -1)))
    # Toolbox safeguard: per-step KL clipped at 0 (NaN is kept, so it can be detected).
    return jnp.where(kl < 0, jnp.zeros_like(kl), kl)


def estimate_cost(policy: LinearGaussianPolicy, dyn: Dynamics, cost: QuadraticCost) -> Array:
    """Laplace estimate of the expected per-step cost (§2.5).

    EC_t = cc_t + ½tr(Σ_t Cm_t) + ½μ_tᵀCm_tμ_t + μ_tᵀcv_t under ``lqr_forward(dyn, policy)``;
    exact for a quadratic cost under the Gaussian marginals.

    Args:
      policy: [T, ...].  dyn: Dynamics [T, ...].  cost: Cm [T, D, D], cv [T, D], cc [T].
    Returns:
      [T] expected cost per step.
    """
    m = lqr_forward(dyn, policy)
    Cm = linalg.sym(cost.Cm)
    return (cost.cc + 0.5 * jnp.sum(m.sigma * Cm, axis=(-2, -1))
            + 0.5 * jnp.einsum("ti,tij,tj->t", m.mu, Cm, m.mu)
            + jnp.einsum("ti,ti->t", m.mu, cost.cv))


# ---------------------------------------------------------------------------------------------
# η dual search (§2.4)


class EtaSearchInfo(NamedTuple):
    """Diagnostics of ``eta_search`` (leaves get a leading condition axis under vmap).

    Attributes:
      iterations: [] int, backward/forward passes run (≤ max_iterations).
      converged: [] bool, |KL − ε| < tolerance·ε at the returned controller.
      ok: [] bool, False if the non-PD repair hit max_eta or the KL was not finite (the
        toolbox raises in those cases); the returned controller must then not be used.
      eta_used: [] the η that produced the returned controller (after non-PD repair).
      kl_per_step: [T] per-step KL of the returned controller.
      eta_trace: [max_iterations] η used at each iteration (NaN after the last).
      kl_trace: [max_iterations] summed KL at each iteration (NaN after the last).
    """

    iterations: Array
    converged: Array
    ok: Array
    eta_used: Array
    kl_per_step: Array
    eta_trace: Array
    kl_trace: Array


def bracket_update(con, eta, min_eta, max_eta):
    """One η bracket step of §2.4 given the constraint value con = KL − ε.

    con < 0 (KL too small, η too big): max_eta = η, η ← max(√(min·max), 0.1·max).
    otherwise (η too small):           min_eta = η, η ← min(√(min·max), 10·min).
    The geometric mean is √min·√max so the product of two bounds near 1e16 cannot overflow
    float32. Returns (new_eta, min_eta, max_eta), all [].
    """
    too_big = con < 0
    max_eta = jnp.where(too_big, eta, max_eta)
    min_eta = jnp.where(too_big, min_eta, eta)
    geo = jnp.sqrt(min_eta) * jnp.sqrt(max_eta)
    new_eta = jnp.where(too_big, jnp.maximum(geo, 0.1 * max_eta), jnp.minimum(geo, 10.0 * min_eta))
    return new_eta, min_eta, max_eta


def eta_search(dyn: Dynamics, cost: QuadraticCost, anchor: LinearGaussianPolicy, eta0, epsilon,
               cfg: LQRConfig = LQRConfig()):
    """Dual search on η for KL(p_new ‖ π̄) ≈ ε (toolbox ``TrajOptLQRPython.update``, §2.4).

    Loop (``lax.while_loop``, ≤ cfg.max_iterations): backward (which may raise η, §2.3),
    forward, kl = Σ_t KL_t, con = kl − ε; stop if |con| < tolerance·ε; else move η by the
    bracket rule (``bracket_update``), starting from the bracket [min_eta, max_eta].

    Args:
      dyn: Dynamics [T, ...] with x0mu [dX], x0sigma [dX, dX].
      cost: QuadraticCost [T, ...].
      anchor: π̄ [T, ...].
      eta0: [] starting η (carried over from the previous iteration; 1.0 initially).
      epsilon: [] KL target ε = kl_step·step_mult·T (see ``kl_epsilon``).
      cfg: LQRConfig (static).
    Returns:
      (policy, marginals, eta, kl_sum, info): the last controller, its marginals, the η to
      carry to the next iteration (as the toolbox: the converged η, or the next bracket η if the
      loop ran out of iterations; ``info.eta_used`` is the η of the returned controller), its
      summed KL [] and an ``EtaSearchInfo``.
    """
    dtype = cost.Cm.dtype
    T, dX = dyn.fv.shape
    dU = cost.Cm.shape[-1] - dX
    eps = jnp.asarray(epsilon, dtype)
    n_max = cfg.max_iterations
    nan_trace = jnp.full((n_max,), jnp.nan, dtype)

    def cond(s):
        itr, *_, converged, ok, _, _ = s
        return (itr < n_max) & ~converged & ok

    def body(s):
        itr, eta, lo, hi, _, _, _, _, _, _, eta_tr, kl_tr = s
        policy, eta_used, ok = lqr_backward(dyn, cost, anchor, eta, cfg)
        marg = lqr_forward(dyn, policy)
        kl_t = traj_kl(marg, policy, anchor)
        kl = jnp.sum(kl_t)
        ok = ok & jnp.isfinite(kl)
        con = kl - eps
        converged = ok & (jnp.abs(con) < cfg.tolerance * eps)
        new_eta, new_lo, new_hi = bracket_update(con, eta_used, lo, hi)
        eta_next = jnp.where(converged | ~ok, eta_used, new_eta)
        return (itr + 1, eta_next, new_lo, new_hi, policy, marg, kl_t, eta_used, converged, ok,
                eta_tr.at[itr].set(eta_used, unique_indices=True),
                kl_tr.at[itr].set(kl, unique_indices=True))

    # Placeholders with the output shapes; the loop body always runs at least once.
    zero_pol = jax.tree_util.tree_map(lambda a: jnp.zeros(a.shape, dtype), anchor)
    zero_marg = Marginals(mu=jnp.zeros((T, dX + dU), dtype),
                          sigma=jnp.zeros((T, dX + dU, dX + dU), dtype))
    eta0 = jnp.asarray(eta0, dtype)
    init = (jnp.asarray(0, jnp.int32), eta0, jnp.asarray(cfg.min_eta, dtype),
            jnp.asarray(cfg.max_eta, dtype), zero_pol, zero_marg, jnp.zeros((T,), dtype), eta0,
            jnp.asarray(False), jnp.asarray(True), nan_trace, nan_trace)
    (itr, eta, _, _, policy, marg, kl_t, eta_used, converged, ok, eta_tr,
     kl_tr) = lax.while_loop(cond, body, init)
    info = EtaSearchInfo(iterations=itr, converged=converged, ok=ok, eta_used=eta_used,
                         kl_per_step=kl_t, eta_trace=eta_tr, kl_trace=kl_tr)
    return policy, marg, eta, jnp.sum(kl_t), info


def check_eta_search(info: EtaSearchInfo, dyn: Dynamics | None = None) -> None:
    """Host-side check of ``eta_search`` results (any leading condition axes); raises ValueError.

    The toolbox raises inside its backward pass when the non-PD repair reaches η ≥ 1e16,
    first checking the dynamics for NaNs; under ``jit`` that becomes ``info.ok`` = False, and
    this function turns it back into the toolbox's error, naming the failed conditions.
    """
    import numpy as np  # host-side only

    ok = np.asarray(info.ok)
    if ok.all():
        return
    bad = [tuple(int(i) for i in idx) for idx in zip(*np.nonzero(~ok))] if ok.ndim else [()]
    if dyn is not None:
        Fm, fv = np.asarray(dyn.Fm), np.asarray(dyn.fv)
        nan = (np.isnan(Fm).reshape(ok.shape + (-1,)).any(-1)
               | np.isnan(fv).reshape(ok.shape + (-1,)).any(-1))
        if (nan & ~ok).any():
            raise ValueError(f"NaNs encountered in dynamics (conditions {bad})")
    raise ValueError(f"Failed to find PD solution even for very large eta, or the KL was not "
                     f"finite (conditions {bad}); check that dynamics and cost are reasonably "
                     "well conditioned")


# ---------------------------------------------------------------------------------------------
# Initial controllers (§4.1)


def guess_dynamics(gains: Array, acc: Array, dX: int, dU: int, dt: float) -> tuple[Array, Array]:
    """Double-integrator guess used by ``init_lqr`` (toolbox ``guess_dynamics``).

    Positions are the first dU state entries, velocities the next dU; other states map to 0:
    q' = q + dt·q̇ + dt²·diag(g)·u,  q̇' = q̇ + dt·diag(g)·u,  f = [acc·dt², acc·dt, 0].

    Args:
      gains: [dU].  acc: [dU].
    Returns:
      (Fd [dX, dX+dU], fc [dX]) with the dtype of ``gains``.
    """
    if dX < 2 * dU:
        raise ValueError(f"guess_dynamics: dX={dX} must be at least 2·dU={2 * dU}")
    dtype = gains.dtype
    eye = jnp.eye(dU, dtype=dtype)
    Fd = jnp.zeros((dX, dX + dU), dtype)
    Fd = Fd.at[:dU, :dU].set(eye, unique_indices=True).at[:dU, dU:2 * dU].set(dt * eye, unique_indices=True)
    Fd = Fd.at[:dU, dX:].set(dt ** 2 * jnp.diag(gains), unique_indices=True)
    Fd = Fd.at[dU:2 * dU, dU:2 * dU].set(eye, unique_indices=True)
    Fd = Fd.at[dU:2 * dU, dX:].set(dt * jnp.diag(gains), unique_indices=True)
    fc = jnp.concatenate([acc * dt ** 2, acc * dt, jnp.zeros((dX - 2 * dU,), dtype)])
    return Fd, fc


def _vector_setting(values: tuple, dU: int, default: float, name: str, dtype) -> Array:
    if len(values) == 0:  # toolbox: an empty setting means the default for every joint
        return jnp.full((dU,), default, dtype)
    if len(values) != dU:
        raise ValueError(f"InitLQRConfig.{name} has {len(values)} entries: must have dU={dU} "
                         "(or be empty)")
    return jnp.asarray(values, dtype)


def init_lqr(x0: Array, T: int, dU: int, dt: float,
             cfg: InitLQRConfig = InitLQRConfig()) -> LinearGaussianPolicy:
    """Initial controller holding x0 by LQR on the guessed double integrator (§4.1).

    Cost per step: ½ yᵀ L y + yᵀ l with L = diag(stiffness·1_dU, stiffness·stiffness_vel·1_dU,
    0_{dX−2dU}, 1_dU)/init_var, l = −L [x0; 0]; both ×final_weight at t = T−1. Solved with the
    same backward recursion as the C-step (no η, no anchor).

    Args:
      x0: [dX] state to hold (positions first dU entries, velocities next dU).
      T, dU: static sizes.  dt: control period (s).  cfg: InitLQRConfig.
    Returns:
      LinearGaussianPolicy [T, ...] with pol_covar = Q_uu⁻¹, inv_pol_covar = Q_uu.
    """
    x0 = jnp.asarray(x0)
    dtype = x0.dtype if jnp.issubdtype(x0.dtype, jnp.floating) else jnp.result_type(float)
    x0 = x0.astype(dtype)
    dX = x0.shape[-1]
    gains = _vector_setting(cfg.init_gains, dU, 1.0, "init_gains", dtype)
    acc = _vector_setting(cfg.init_acc, dU, 0.0, "init_acc", dtype)
    Fd, fc = guess_dynamics(gains, acc, dX, dU, dt)
    diag = jnp.concatenate([
        jnp.full((dU,), cfg.stiffness, dtype),
        jnp.full((dU,), cfg.stiffness * cfg.stiffness_vel, dtype),
        jnp.zeros((dX - 2 * dU,), dtype),
        jnp.ones((dU,), dtype),
    ]) / cfg.init_var
    L = jnp.diag(diag)
    l = -L @ jnp.concatenate([x0, jnp.zeros((dU,), dtype)])
    w = jnp.ones((T,), dtype).at[T - 1].set(cfg.final_weight, unique_indices=True)
    Cm = w[:, None, None] * L
    cv = w[:, None] * l
    policy, _ = _riccati(jnp.broadcast_to(Fd, (T,) + Fd.shape), jnp.broadcast_to(fc, (T, dX)),
                         Cm, cv)
    # The cost's action block is I/init_var > 0 and V stays PSD, so the recursion cannot fail.
    return policy


def init_pd(x0: Array, T: int, dU: int, *, init_var: float = 10.0, pos_gains: float = 10.0,
            vel_gains_mult: float = 0.01, dQ: int | None = None) -> LinearGaussianPolicy:
    """PD initial controller (toolbox ``init_pd``, §4.1).

    K = −pos_gains·[I, vel_gains_mult·I, 0] (positions = first dQ entries, velocities the next
    dQ; dQ = dU by default; for dU < dQ the first dU joints get the gains), k = −K x0,
    pol_covar = init_var·I.

    Args:
      x0: [dX] set point.  T, dU: static sizes.
    Returns:
      LinearGaussianPolicy [T, ...].
    """
    x0 = jnp.asarray(x0)
    dtype = x0.dtype if jnp.issubdtype(x0.dtype, jnp.floating) else jnp.result_type(float)
    x0 = x0.astype(dtype)
    dX = x0.shape[-1]
    dQ = dU if dQ is None else dQ
    if dU > dQ:
        # Toolbox case dU ≥ dQ: the gains act on the first dU positions and next dU velocities.
        dQ = dU
    if dX < 2 * dQ:
        raise ValueError(f"init_pd: dX={dX} must be at least 2·dQ={2 * dQ}")
    n = min(dU, dQ)
    K1 = jnp.zeros((dU, dX), dtype)
    K1 = K1.at[:n, :n].set(jnp.eye(n, dtype=dtype), unique_indices=True)
    K1 = K1.at[:n, dQ:dQ + n].set(vel_gains_mult * jnp.eye(n, dtype=dtype), unique_indices=True)
    K1 = -pos_gains * K1
    K = jnp.broadcast_to(K1, (T, dU, dX))
    k = jnp.broadcast_to(-K1 @ x0, (T, dU))
    eye = jnp.broadcast_to(jnp.eye(dU, dtype=dtype), (T, dU, dU))
    return LinearGaussianPolicy(K=K, k=k, pol_covar=init_var * eye,
                                chol_pol_covar=jnp.sqrt(jnp.asarray(init_var, dtype)) * eye,
                                inv_pol_covar=eye / init_var)

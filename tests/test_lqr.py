"""Tests of gmr_jax.lqr against closed forms, independent numpy recursions and Monte Carlo."""


import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from tolerances import (SAFETY, affine_tol, assert_close, assert_tolerances_small, assert_trees_within, linear_tol,
                        measured_tol)

from gmr_jax import lqr, step_size
from gmr_jax.tasks import jaco
from gmr_jax.config import InitLQRConfig, LQRConfig, StepConfig
from gmr_jax.types import Dynamics, QuadraticCost

CFG = LQRConfig()
T, DX, DU = 8, 4, 2

eta_search_jit = jax.jit(lqr.eta_search, static_argnums=5)
backward_jit = jax.jit(lqr.lqr_backward, static_argnums=4)
forward_jit = jax.jit(lqr.lqr_forward)
kl_jit = jax.jit(lqr.traj_kl)
cost_jit = jax.jit(lqr.estimate_cost)
init_lqr_jit = jax.jit(lqr.init_lqr, static_argnums=(1, 2, 3, 4))
init_pd_jit = jax.jit(lqr.init_pd, static_argnums=(1, 2),
                      static_argnames=("init_var", "pos_gains", "vel_gains_mult", "dQ"))
augment_jit = jax.jit(lqr.kl_augmented_cost)


# ---------------------------------------------------------------------------------------------
# Problem generators and numpy references


def _spd(rng, n, scale=1.0, floor=0.1):
    a = rng.standard_normal((n, n))
    return scale * (a @ a.T / n) + floor * np.eye(n)


def random_dynamics(rng, T=T, dX=DX, dU=DU, noise=1e-2):
    A = np.eye(dX) + 0.1 * rng.standard_normal((T, dX, dX))
    B = 0.3 * rng.standard_normal((T, dX, dU))
    Fm = np.concatenate([A, B], axis=-1)
    Fm[-1] = 0.0  # toolbox: the fitted dynamics at T-1 are zero (and unused)
    fv = 0.1 * rng.standard_normal((T, dX))
    fv[-1] = 0.0
    W = np.stack([_spd(rng, dX, noise, noise) for _ in range(T)])
    x0mu = rng.standard_normal(dX)
    x0sigma = _spd(rng, dX, 0.05, 0.01)
    return Dynamics(*(jnp.asarray(a) for a in (Fm, fv, W, x0mu, x0sigma)))


def random_cost(rng, T=T, dX=DX, dU=DU):
    D = dX + dU
    Cm = np.stack([_spd(rng, D, 1.0, 0.2) for _ in range(T)])
    cv = rng.standard_normal((T, D))
    cc = rng.standard_normal(T)
    return QuadraticCost(jnp.asarray(Cm), jnp.asarray(cv), jnp.asarray(cc))


def random_policy(rng, T=T, dX=DX, dU=DU, k_scale=1.0, var=1.0):
    K = 0.3 * rng.standard_normal((T, dU, dX))
    k = k_scale * rng.standard_normal((T, dU))
    S = np.stack([_spd(rng, dU, var, 0.2 * var) for _ in range(T)])
    return lqr.policy_from_covariance(jnp.asarray(K), jnp.asarray(k), jnp.asarray(S))


def np_riccati(Fm, fv, Cm, cv):
    """Standard finite-horizon discrete Riccati recursion in (A, B, f) form with affine terms."""
    T, dX = fv.shape
    dU = Cm.shape[-1] - dX
    P, p = np.zeros((dX, dX)), np.zeros(dX)
    K, k, H_all = np.zeros((T, dU, dX)), np.zeros((T, dU)), np.zeros((T, dU, dU))
    for t in range(T - 1, -1, -1):
        A, B, f = Fm[t][:, :dX], Fm[t][:, dX:], fv[t]
        C, c = Cm[t], cv[t]
        Cxx, Cux, Cuu, cx, cu = C[:dX, :dX], C[dX:, :dX], C[dX:, dX:], c[:dX], c[dX:]
        H = Cuu + B.T @ P @ B
        G = Cux + B.T @ P @ A
        g = cu + B.T @ (p + P @ f)
        K[t] = -np.linalg.solve(H, G)
        k[t] = -np.linalg.solve(H, g)
        H_all[t] = H
        P_new = Cxx + A.T @ P @ A - G.T @ np.linalg.solve(H, G)
        p = cx + A.T @ (p + P @ f) - G.T @ np.linalg.solve(H, g)
        P = 0.5 * (P_new + P_new.T)
    return K, k, H_all


def np_simulate(dyn, pol, N, rng):
    """Sample N trajectories of the linear-Gaussian system: X [N, T, dX], U [N, T, dU]."""
    Fm, fv, W, x0mu, x0sigma = (np.asarray(a) for a in dyn)
    K, k, S = np.asarray(pol.K), np.asarray(pol.k), np.asarray(pol.pol_covar)
    T, dX = fv.shape
    dU = k.shape[-1]
    X, U = np.zeros((N, T, dX)), np.zeros((N, T, dU))
    x = rng.multivariate_normal(x0mu, x0sigma, size=N)
    for t in range(T):
        u = x @ K[t].T + k[t] + rng.standard_normal((N, dU)) @ np.linalg.cholesky(S[t]).T
        X[:, t], U[:, t] = x, u
        if t < T - 1:
            x = (np.concatenate([x, u], 1) @ Fm[t].T + fv[t]
                 + rng.standard_normal((N, dX)) @ np.linalg.cholesky(W[t]).T)
    return X, U


def np_logpdf(u, mean, S):
    L = np.linalg.cholesky(S)
    z = np.linalg.solve(L, (u - mean).T)
    return -0.5 * np.sum(z * z, 0) - np.sum(np.log(np.diag(L))) - 0.5 * len(S) * np.log(2 * np.pi)


def np_toolbox_kl(mu, sigma, new, prev):
    """The toolbox's traj_distr_kl form: E[log p_new − log p_prev] via M, v, c (no clipping)."""
    T, D = mu.shape
    out = np.zeros(T)
    for t in range(T):
        terms = []
        for p in (new, prev):
            K, k, U = np.asarray(p.K[t]), np.asarray(p.k[t]), np.asarray(p.chol_pol_covar[t])
            P = np.linalg.inv(U.T @ U)
            M = np.block([[K.T @ P @ K, -K.T @ P], [-P @ K, P]])
            v = np.concatenate([K.T @ P @ k, -P @ k])
            c = 0.5 * k @ P @ k
            logdet = 2 * np.sum(np.log(np.abs(np.diag(U))))
            terms.append((M, v, c, logdet))
        (Mn, vn, cn, ln), (Mp, vp, cp, lp) = terms
        dM, dv, dc = Mn - Mp, vn - vp, cn - cp
        out[t] = (-0.5 * mu[t] @ dM @ mu[t] - mu[t] @ dv - dc - 0.5 * np.sum(sigma[t] * dM)
                  - 0.5 * ln + 0.5 * lp)
    return out


# ---------------------------------------------------------------------------------------------
# Backward pass


def test_backward_equals_riccati_and_batch_qp():
    rng = np.random.default_rng(0)
    dyn, cost = random_dynamics(rng), random_cost(rng)
    # Anchor with precision 1e-12·I: its KL term is negligible against the cost at η = 1.
    anchor = random_policy(rng)._replace(chol_pol_covar=1e6 * jnp.broadcast_to(jnp.eye(DU), (T, DU, DU)))
    pol, eta_used, ok = backward_jit(dyn, cost, anchor, 1.0, CFG)
    assert bool(ok) and float(eta_used) == 1.0
    # The reference solves the same problem: the cost plus the anchor's −log π̄ terms at η = 1
    # (M̄, v̄ with P̄ = 1e-12·I; negligible, but included so that only rounding separates the
    # two programs). Tolerance from the computation (tests/tolerances.py): the numpy recursion
    # rerun on inputs perturbed by ε relative, SAFETY times the spread.
    Kb, kb, Ub = (np.asarray(a) for a in (anchor.K, anchor.k, anchor.chol_pol_covar))
    Pb = np.linalg.inv(np.swapaxes(Ub, 1, 2) @ Ub)  # the anchor's precision, from its factor
    Mb = np.block([[np.swapaxes(Kb, 1, 2) @ Pb @ Kb, -np.swapaxes(Kb, 1, 2) @ Pb], [-Pb @ Kb, Pb]])
    vb = np.concatenate([np.einsum("tux,tuv,tv->tx", Kb, Pb, kb), -np.einsum("tuv,tv->tu", Pb, kb)], -1)
    Cm_aug, cv_aug = np.asarray(cost.Cm) + Mb, np.asarray(cost.cv) + vb

    def riccati(Fm, fv, Cm, cv):
        K, k, H = np_riccati(Fm, fv, Cm, cv)
        return K, k, H, np.linalg.inv(H)

    ref, tol = measured_tol(riccati, (np.asarray(dyn.Fm), np.asarray(dyn.fv), Cm_aug, cv_aug), SAFETY)
    assert_tolerances_small(ref, tol, 1e-8)
    assert_trees_within((pol.K, pol.k, pol.inv_pol_covar, pol.pol_covar), ref, tol)
    # chol_pol_covar is the upper factor of pol_covar (to the backward error of a Cholesky
    # factorisation, c·n·ε relative normwise, tests/tolerances.py).
    U = np.asarray(pol.chol_pol_covar)
    np.testing.assert_array_equal(np.tril(U, -1), 0.0)
    for t in range(T):
        assert_close(U[t].T @ U[t], pol.pol_covar[t], linear_tol(1.0, DU))

    # Independent check: the deterministic problem solved as one quadratic program in the
    # stacked actions; its optimum equals the LQR mean actions along the mean trajectory.
    Fm, fv, x0 = np.asarray(dyn.Fm), np.asarray(dyn.fv), np.asarray(dyn.x0mu)
    Cm, cv = np.asarray(cost.Cm), np.asarray(cost.cv)
    n = T * DU
    a, B = x0.copy(), np.zeros((DX, n))
    H, g = np.zeros((n, n)), np.zeros(n)
    for t in range(T):
        E = np.zeros((DU, n))
        E[:, t * DU:(t + 1) * DU] = np.eye(DU)
        ya, yB = np.concatenate([a, np.zeros(DU)]), np.vstack([B, E])
        H += yB.T @ Cm[t] @ yB
        g += yB.T @ (Cm[t] @ ya + cv[t])
        a, B = Fm[t] @ ya + fv[t], Fm[t] @ yB
    u_qp = np.linalg.solve(H, -g).reshape(T, DU)
    mu = forward_jit(dyn, pol).mu
    # Two algorithms (the Riccati recursion and one dense solve with the stacked Hessian H): the
    # QP's error is c·n·ε·κ(H) normwise (tests/tolerances.py); the LQR's is measured as above,
    # on the jitted backward and forward passes; the anchor's 1e-12 terms (not in the QP) move
    # the actions by at most 1e-12·‖K̄x + k̄‖·‖H⁻¹‖.
    _, tol_lqr = measured_tol(lambda d, c, a: forward_jit(d, backward_jit(d, c, a, 1.0, CFG)[0]).mu[:, DX:],
                              (dyn, cost, anchor), SAFETY)
    model = 1e-12 * np.linalg.norm(np.linalg.inv(H), 2) * (np.abs(Kb).max() * np.abs(np.asarray(mu)).max()
                                                             + np.abs(kb).max()) * n
    tol = tol_lqr[0] + linear_tol(np.linalg.cond(H), n) * np.abs(u_qp).max() + model
    assert np.abs(np.asarray(mu[:, DX:]) - u_qp).max() <= tol
    assert tol < 1e-8 * np.abs(u_qp).max()


def test_large_eta_tends_to_anchor():
    rng = np.random.default_rng(1)
    dyn, cost, anchor = random_dynamics(rng), random_cost(rng), random_policy(rng)
    errs = []
    for eta in (1e0, 1e2, 1e4, 1e6, 1e8):
        pol, _, ok = backward_jit(dyn, cost, anchor, eta, CFG)
        assert bool(ok)
        errs.append(max(float(jnp.max(jnp.abs(pol.K - anchor.K))),
                        float(jnp.max(jnp.abs(pol.k - anchor.k))),
                        float(jnp.max(jnp.abs(pol.pol_covar - anchor.pol_covar)))))
    # The deviation is O(1/η): it shrinks ~100× per 100× in η once η dominates the cost.
    assert errs[0] > 1e-2
    assert all(e2 < 0.05 * e1 for e1, e2 in zip(errs[1:], errs[2:])), errs
    assert errs[-1] < 1e-5


def test_kl_augmented_cost_is_negative_log_anchor():
    rng = np.random.default_rng(2)
    cost, anchor = random_cost(rng), random_policy(rng)
    eta = 0.37
    # ½yᵀM̄y + yᵀv̄ + c̄ must equal −log π̄(u|x) − ½log|2πS̄| at random y.
    for t in (0, T - 1):
        y = rng.standard_normal(DX + DU)

        def ours(y, cost, anchor):
            aug = augment_jit(cost, anchor, eta)
            quad = 0.5 * y @ aug.Cm[t] @ y + y @ aug.cv[t] + aug.cc[t]
            own = (0.5 * y @ cost.Cm[t] @ y + y @ cost.cv[t] + cost.cc[t]) / eta
            return quad - own

        def numpy_nlog(y, K, k, S):
            x, u = y[:DX], y[DX:]
            nlog = -np_logpdf(u[None], (K @ x + k)[None], S)[0]
            return nlog - 0.5 * np.linalg.slogdet(2 * np.pi * S)[1]

        # quad − own cancels the cost's terms: tolerances from the computation on both sides
        # (tests/tolerances.py), SAFETY times the spread under ε-relative input perturbations.
        got, tol_ours = measured_tol(ours, (y, cost, anchor), SAFETY)
        want, tol_np = measured_tol(
            numpy_nlog, (y, np.asarray(anchor.K[t]), np.asarray(anchor.k[t]), np.asarray(anchor.pol_covar[t])), SAFETY)
        assert abs(float(got) - float(want)) <= tol_ours[0] + tol_np[0]
        assert tol_ours[0] + tol_np[0] < 1e-9 * abs(float(want))


# ---------------------------------------------------------------------------------------------
# Non-PD rule


def _indefinite_problem(a):
    """Q_uu = −a/η·I + I at T−1 only (anchor S̄ = I, K̄ = 0, no cross terms): PD iff η > a."""
    rng = np.random.default_rng(3)
    dyn = random_dynamics(rng)
    Cm = np.zeros((T, DX + DU, DX + DU))
    Cm[:, :DX, :DX] = np.eye(DX)
    Cm[:, DX:, DX:] = 0.1 * np.eye(DU)
    Cm[-1, DX:, DX:] = -a * np.eye(DU)
    cost = QuadraticCost(jnp.asarray(Cm), jnp.asarray(rng.standard_normal((T, DX + DU))), jnp.zeros(T))
    anchor = lqr.policy_from_covariance(jnp.zeros((T, DU, DX)), jnp.zeros((T, DU)),
                                        jnp.broadcast_to(jnp.eye(DU), (T, DU, DU)))
    return dyn, cost, anchor


@pytest.mark.parametrize("eta0,a", [(1e-3, 0.5), (2.0, 3.0)])
def test_non_pd_repair_follows_doubling_rule(eta0, a):
    dyn, cost, anchor = _indefinite_problem(a)
    pol, eta_used, ok = backward_jit(dyn, cost, anchor, eta0, CFG)
    # Smallest k with η₀ + del0·2^(k−1) > a (not cumulative: δ only doubles).
    k = 1
    while not eta0 + CFG.del0 * 2 ** (k - 1) > a:
        k += 1
    assert bool(ok)
    # one product by a power of 2 (exact) and one sum: two roundings (tests/tolerances.py)
    np.testing.assert_allclose(float(eta_used), eta0 + CFG.del0 * 2 ** (k - 1), rtol=linear_tol(1.0, 2))
    if eta0 == 1e-3:  # the toolbox's documented example: 14 failures, η = 0.8202
        assert k == 14 and abs(float(eta_used) - 0.8202) < 1e-4
    assert all(bool(jnp.all(jnp.isfinite(leaf))) for leaf in pol)
    assert float(jnp.min(jnp.linalg.eigvalsh(pol.inv_pol_covar))) > 0


def test_non_pd_failure_and_nan_are_flagged():
    dyn, cost, anchor = _indefinite_problem(0.5)
    bad = dyn._replace(Fm=dyn.Fm.at[2, 0, 0].set(jnp.nan))
    _, eta_used, ok = backward_jit(bad, cost, anchor, 1.0, CFG)
    assert not bool(ok) and float(eta_used) >= CFG.max_eta
    *_, info = eta_search_jit(bad, cost, anchor, 1.0, 1.0, CFG)
    assert not bool(info.ok) and not bool(info.converged) and int(info.iterations) == 1
    with pytest.raises(ValueError, match="NaNs encountered in dynamics"):
        lqr.check_eta_search(info, bad)
    with pytest.raises(ValueError, match="PD solution"):
        lqr.check_eta_search(info)
    good = info._replace(ok=jnp.asarray(True))
    batched = jax.tree_util.tree_map(lambda a, b: jnp.stack([a, b]), info, good)
    with pytest.raises(ValueError, match=r"conditions \[\(0,\)\]"):
        lqr.check_eta_search(batched)
    lqr.check_eta_search(info._replace(ok=jnp.asarray(True)))  # no error


# ---------------------------------------------------------------------------------------------
# Forward pass, KL, cost estimate


def test_forward_kl_and_cost_match_monte_carlo():
    rng = np.random.default_rng(4)
    dyn, cost, anchor = random_dynamics(rng), random_cost(rng), random_policy(rng, k_scale=0.5)
    pol, _, ok = backward_jit(dyn, cost, anchor, 1.0, CFG)
    assert bool(ok)
    marg = forward_jit(dyn, pol)
    N = 40000
    X, U = np_simulate(dyn, pol, N, np.random.default_rng(5))
    Y = np.concatenate([X, U], -1)  # [N, T, D]

    # Marginals: mean within 5 standard errors, covariance within 5% of its scale.
    se = Y.std(0) / np.sqrt(N)
    assert np.all(np.abs(Y.mean(0) - np.asarray(marg.mu)) < 5 * se + 1e-12)
    cov_mc = np.einsum("nti,ntj->tij", Y - Y.mean(0), Y - Y.mean(0)) / (N - 1)
    scale = np.sqrt(np.einsum("tii,tjj->tij", cov_mc, cov_mc))
    assert np.max(np.abs(cov_mc - np.asarray(marg.sigma)) / scale) < 0.05

    # Per-step KL: exact toolbox form (independent numpy) and Monte Carlo log-ratio.
    kl = np.asarray(kl_jit(marg, pol, anchor))
    # Tolerance from the computation (tests/tolerances.py): the numpy form rerun on inputs
    # perturbed by ε relative, SAFETY times the spread (its terms cancel to the small KL).
    kl_np, tol = measured_tol(lambda m, s, p, a: np_toolbox_kl(np.asarray(m), np.asarray(s), p, a),
                              (marg.mu, marg.sigma, pol, anchor), SAFETY)
    assert_tolerances_small(kl_np, tol, 1e-6)
    assert_trees_within(kl, kl_np, tol)
    def logp(p, t):
        mean = X[:, t] @ np.asarray(p.K[t]).T + np.asarray(p.k[t])
        return np_logpdf(U[:, t], mean, np.asarray(p.pol_covar[t]))

    lr = np.stack([logp(pol, t) - logp(anchor, t) for t in range(T)], 1)  # [N, T]
    assert np.all(np.abs(lr.mean(0) - kl) < 5 * lr.std(0) / np.sqrt(N))
    tot = lr.sum(1)
    assert abs(tot.mean() - kl.sum()) < 5 * tot.std() / np.sqrt(N)

    # Laplace estimate = exact expected quadratic cost (Monte Carlo check).
    ec = np.asarray(cost_jit(pol, dyn, cost))
    Cm, cv, cc = (np.asarray(a) for a in cost)
    samp = 0.5 * np.einsum("nti,tij,ntj->nt", Y, Cm, Y) + np.einsum("nti,ti->nt", Y, cv) + cc
    assert np.all(np.abs(samp.mean(0) - ec) < 5 * samp.std(0) / np.sqrt(N))


def test_kl_of_controller_with_itself_is_zero():
    rng = np.random.default_rng(6)
    dyn, p, q = random_dynamics(rng), random_policy(rng), random_policy(rng)
    marg = forward_jit(dyn, p)
    np.testing.assert_allclose(kl_jit(marg, p, p), 0.0, atol=1e-12)
    assert float(jnp.min(kl_jit(marg, p, q))) > 0


def test_estimate_cost_closed_form_for_deterministic_policy():
    # Zero noise everywhere: the Laplace estimate is just the cost of the mean trajectory.
    rng = np.random.default_rng(7)
    dyn, cost, pol = random_dynamics(rng), random_cost(rng), random_policy(rng)
    tiny = 1e-14 * jnp.broadcast_to(jnp.eye(DU), (T, DU, DU))
    pol = lqr.policy_from_covariance(pol.K, pol.k, tiny)
    dyn = dyn._replace(dyn_covar=jnp.zeros_like(dyn.dyn_covar), x0sigma=jnp.zeros_like(dyn.x0sigma))

    def mean_trajectory_cost(x0, K, k, Fm, fv, Cm, cv, cc):
        x, expect = np.asarray(x0), []
        for t in range(T):
            y = np.concatenate([x, np.asarray(K[t]) @ x + np.asarray(k[t])])
            expect.append(0.5 * y @ np.asarray(Cm[t]) @ y + y @ np.asarray(cv[t]) + float(cc[t]))
            x = np.asarray(Fm[t]) @ y + np.asarray(fv[t])
        return np.array(expect)

    # Tolerance from the computation (tests/tolerances.py): the numpy rollout rerun on inputs
    # perturbed by ε relative, SAFETY times the spread; the 1e-14 policy covariance adds
    # ½tr(Σ Cm) ≤ ½·1e-14·T·dU·max|Cm| at most.
    expect, tol = measured_tol(mean_trajectory_cost, (dyn.x0mu, pol.K, pol.k, dyn.Fm, dyn.fv, *cost), SAFETY)
    assert_tolerances_small(expect, tol, 1e-8)
    noise_cost = 0.5 * 1e-14 * T * DU * np.abs(np.asarray(cost.Cm)).max()
    assert_trees_within(cost_jit(pol, dyn, cost), expect, tol[0] + noise_cost)


# ---------------------------------------------------------------------------------------------
# η search


def _replay_bracket(kl_trace, eta0, eps, cfg=CFG):
    """Python replay of the §2.4 bracket rules on a recorded KL trace → expected η sequence."""
    eta, lo, hi, etas = eta0, cfg.min_eta, cfg.max_eta, []
    for kl in kl_trace:
        etas.append(eta)
        con = kl - eps
        if abs(con) < cfg.tolerance * eps:
            break
        if con < 0:
            hi = eta
            eta = max(np.sqrt(lo * hi), 0.1 * hi)
        else:
            lo = eta
            eta = min(np.sqrt(lo * hi), 10.0 * lo)
    return np.array(etas)


def test_bracket_update_reproduces_toolbox_trace():
    eta, lo, hi = 1.0, CFG.min_eta, CFG.max_eta
    trace = [eta]
    for con in (-1.0, 1.0, 1.0, 1.0):
        eta, lo, hi = lqr.bracket_update(jnp.asarray(con), jnp.asarray(eta), jnp.asarray(lo), jnp.asarray(hi))
        trace.append(float(eta))
    np.testing.assert_allclose(trace, [1.0, 0.1, 0.316, 0.562, 0.750], atol=1e-3)


def _random_problems(seeds, k_scale=1.0):
    probs = []
    for s in seeds:
        rng = np.random.default_rng(s)
        probs.append((random_dynamics(rng), random_cost(rng), random_policy(rng, k_scale=k_scale)))
    return [jax.tree_util.tree_map(lambda *a: jnp.stack(a), *parts) for parts in zip(*probs)]


@pytest.fixture(scope="module")
def batched_search():
    """η search on 6 random problems at once (vmap over a leading condition axis)."""
    dyn, cost, anchor = _random_problems(range(10, 16))
    eps = jnp.asarray([0.2 * T * m for m in (0.1, 0.5, 1.0, 2.0, 5.0, 0.3)])
    eta0 = jnp.asarray([1.0, 1.0, 3.0, 1.0, 0.01, 1e3])
    out = jax.vmap(eta_search_jit, in_axes=(0, 0, 0, 0, 0, None))(dyn, cost, anchor, eta0, eps, CFG)
    return (dyn, cost, anchor, eta0, eps), out


def _sub(tree, m):
    return jax.tree_util.tree_map(lambda a: a[m], tree)


def test_eta_search_meets_kl_target_on_random_problems(batched_search):
    (dyn, cost, anchor, eta0, eps), (pol, marg, eta, kl_sum, info) = batched_search
    assert bool(jnp.all(info.ok)) and bool(jnp.all(info.converged))
    assert bool(jnp.all(jnp.abs(kl_sum - eps) < 0.1 * eps))
    np.testing.assert_array_equal(eta, info.eta_used)  # converged: the η of the controller
    for m in range(len(eps)):
        # kl_sum is the KL of the returned controller under its own marginals ...
        d, p, a = _sub(dyn, m), _sub(pol, m), _sub(anchor, m)
        # (tolerance from the computation, tests/tolerances.py: the separate forward pass and KL
        # rerun on inputs perturbed by ε relative, SAFETY times the spread)
        ref, tol = measured_tol(lambda d_, p_, a_: (jnp.sum(kl_jit(forward_jit(d_, p_), p_, a_)), forward_jit(d_, p_).mu),
                                (d, p, a), SAFETY)
        assert_tolerances_small(ref, tol, 1e-8)
        assert_trees_within((kl_sum[m], _sub(marg, m).mu), ref, tol)
        # ... and the η sequence follows the bracket rules of §2.4 (each update: a product, a
        # square root or a factor of 10, so after n updates c·2n·ε relative, tests/tolerances.py).
        n = int(info.iterations[m])
        expect = _replay_bracket(np.asarray(info.kl_trace[m, :n]), float(eta0[m]), float(eps[m]))
        np.testing.assert_allclose(info.eta_trace[m, :n], expect, rtol=linear_tol(1.0, 2 * n))


def test_eta_search_vmap_equals_separate_and_jit_equals_eager(batched_search):
    (dyn, cost, anchor, eta0, eps), batched = batched_search
    for m in range(2):
        args = (_sub(dyn, m), _sub(cost, m), _sub(anchor, m), float(eta0[m]), float(eps[m]))
        # Tolerance from the computation (tests/tolerances.py): the jitted search rerun on the
        # problem perturbed by ε relative, SAFETY times the spread of each output. The η
        # iterations (integers) must agree exactly.
        single, tol = measured_tol(lambda *a: eta_search_jit(*a, CFG), args, SAFETY)
        assert_tolerances_small(single, tol, 1e-6)
        assert_trees_within(_sub(batched, m), single, tol)
        if m == 0:
            assert_trees_within(lqr.eta_search(*args, CFG), single, tol)


def test_eta_search_brackets_far_anchor():
    # Anchor offsets far from the optimum: KL at η = 1 ≫ ε, so η must grow by ×10 steps
    # until the target is bracketed, then bisect geometrically.
    dyn, cost, anchor = _random_problems([20], k_scale=30.0)
    dyn, cost, anchor = _sub(dyn, 0), _sub(cost, 0), _sub(anchor, 0)
    eps = 0.2 * T
    pol, marg, eta, kl_sum, info = eta_search_jit(dyn, cost, anchor, 1.0, eps, CFG)
    n = int(info.iterations)
    etas, kls = np.asarray(info.eta_trace[:n]), np.asarray(info.kl_trace[:n])
    assert bool(info.ok) and bool(info.converged) and abs(float(kl_sum) - eps) < 0.1 * eps
    assert kls[0] > 10 * eps and float(eta) > 10.0
    m = int(np.argmax(kls < eps))  # first iteration whose KL is below target
    assert m >= 2
    np.testing.assert_allclose(etas[:m], 10.0 ** np.arange(m), rtol=linear_tol(1.0, m))  # ×10 steps
    assert np.all(etas[m + 1:] > etas[m - 1]) and np.all(etas[m + 1:] < etas[m])  # inside bracket
    np.testing.assert_allclose(etas, _replay_bracket(kls, 1.0, eps), rtol=linear_tol(1.0, 2 * n))
    assert np.all(np.isnan(np.asarray(info.eta_trace[n:])))


def test_eta_search_float32_follows_dtype():
    dyn, cost, anchor = _random_problems([40])
    to32 = lambda tree: jax.tree_util.tree_map(lambda a: a[0].astype(jnp.float32), tree)
    pol, marg, eta, kl_sum, info = eta_search_jit(to32(dyn), to32(cost), to32(anchor), 1.0, 1.6, CFG)
    for leaf in jax.tree_util.tree_leaves((pol, marg, eta, kl_sum, info.eta_trace, info.kl_per_step)):
        assert leaf.dtype == jnp.float32
    assert bool(info.ok) and bool(info.converged) and abs(float(kl_sum) - 1.6) < 0.16


def test_cstep_two_conditions_jaco_sizes_compiles_once():
    Tj, dXj, dUj = 80, 12, 6
    traces = []

    def cstep(dyn, cost, anchor, eta0, eps):
        traces.append(1)  # runs only while tracing
        return jax.vmap(lqr.eta_search, in_axes=(0, 0, 0, 0, 0, None))(dyn, cost, anchor, eta0, eps, CFG)

    cstep = jax.jit(cstep)
    cfg = jaco.INIT_LQR
    for seed in (50, 51):
        probs = []
        for m in range(2):
            rng = np.random.default_rng(seed * 10 + m)
            x0 = np.concatenate([rng.uniform(-1, 1, dXj // 2), np.zeros(dXj // 2)])
            anchor = init_lqr_jit(jnp.asarray(x0), Tj, dUj, 0.05, cfg)
            Fd, fc = lqr.guess_dynamics(jnp.asarray(cfg.init_gains), jnp.zeros(dUj), dXj, dUj, 0.05)
            shape = (Tj, dXj, dXj + dUj)
            Fm = np.broadcast_to(np.asarray(Fd), shape) + 1e-3 * rng.standard_normal(shape)
            dyn = Dynamics(jnp.asarray(Fm), jnp.broadcast_to(fc, (Tj, dXj)),
                           jnp.broadcast_to(1e-4 * jnp.eye(dXj), (Tj, dXj, dXj)),
                           jnp.asarray(x0), 1e-6 * jnp.eye(dXj))
            target = x0 + np.concatenate([rng.uniform(-0.5, 0.5, dXj // 2), np.zeros(dXj // 2)])
            w = np.concatenate([np.ones(dXj // 2), 0.01 * np.ones(dXj // 2), 1e-3 * np.ones(dUj)])
            Cm = np.broadcast_to(np.diag(w), (Tj, dXj + dUj, dXj + dUj))
            cv = np.broadcast_to(-np.diag(w) @ np.concatenate([target, np.zeros(dUj)]), (Tj, dXj + dUj))
            probs.append((dyn, QuadraticCost(jnp.asarray(Cm), jnp.asarray(cv), jnp.zeros(Tj)), anchor))
        dyn, cost, anchor = [jax.tree_util.tree_map(lambda *a: jnp.stack(a), *p) for p in zip(*probs)]
        eps = jnp.full((2,), 0.2 * Tj)
        pol, marg, eta, kl_sum, info = cstep(dyn, cost, anchor, jnp.ones(2), eps)
        assert pol.K.shape == (2, Tj, dUj, dXj) and marg.sigma.shape == (2, Tj, dXj + dUj, dXj + dUj)
        assert bool(jnp.all(info.ok)) and bool(jnp.all(info.converged))
        assert bool(jnp.all(jnp.abs(kl_sum - eps) < 0.1 * eps))
    assert len(traces) == 1


# ---------------------------------------------------------------------------------------------
# Initial controllers and step size


def test_init_lqr_on_guessed_double_integrator():
    Ti, dX, dU, dt = 12, 5, 2, 0.05
    cfg = InitLQRConfig(init_var=2.0, stiffness=1.5, stiffness_vel=0.25, final_weight=50.0,
                        init_acc=(0.0, 0.0), init_gains=(0.5, 2.0))
    x0 = np.array([0.3, -0.7, 0.0, 0.0, 0.9])  # at rest; the 5th (extra) state has no cost
    pol = init_lqr_jit(jnp.asarray(x0), Ti, dU, dt, cfg)
    # The guessed model, written out.
    g = np.array([0.5, 2.0])
    Fd = np.zeros((dX, dX + dU))
    Fd[:2, :2] = np.eye(2); Fd[:2, 2:4] = dt * np.eye(2); Fd[:2, 5:] = dt ** 2 * np.diag(g)
    Fd[2:4, 2:4] = np.eye(2); Fd[2:4, 5:] = dt * np.diag(g)
    Fd_j, fc_j = lqr.guess_dynamics(jnp.asarray(g), jnp.zeros(2), dX, dU, dt)
    np.testing.assert_array_equal(Fd_j, Fd)
    np.testing.assert_array_equal(fc_j, 0.0)
    L = np.diag([1.5, 1.5, 1.5 * 0.25, 1.5 * 0.25, 0.0, 1.0, 1.0]) / 2.0
    l = -L @ np.concatenate([x0, np.zeros(dU)])
    w = np.ones(Ti); w[-1] = 50.0

    def riccati(Fm, fv, Cm, cv):
        K, k, H = np_riccati(Fm, fv, Cm, cv)
        return K, k, H, np.linalg.inv(H)

    # Tolerance from the computation (tests/tolerances.py): the numpy recursion rerun on inputs
    # perturbed by ε relative, SAFETY times the spread.
    ref, tol = measured_tol(riccati, (np.broadcast_to(Fd, (Ti,) + Fd.shape), np.zeros((Ti, dX)),
                                      w[:, None, None] * L, w[:, None] * l), SAFETY)
    assert_tolerances_small(ref, tol, 1e-10)
    assert_trees_within((pol.K, pol.k, pol.inv_pol_covar, pol.pol_covar), ref, tol)
    # It holds x0: x0 at rest is a zero-cost equilibrium, so the mean action there is 0,
    # and a displaced position is pushed back.
    # (zero up to the rounding of K x0 + k: affine_tol, tests/tolerances.py)
    held = np.einsum("tij,j->ti", pol.K, x0) + pol.k
    np.testing.assert_allclose(held, 0.0, atol=2 * affine_tol(pol.K, np.broadcast_to(x0, (Ti, dX)), pol.k))
    push = np.asarray(pol.K[0]) @ np.array([0.1, 0.0, 0.0, 0.0, 0.0])
    assert push[0] < 0 and abs(push[1]) < 1e-12
    # Mismatched per-joint settings are rejected with the field's name; empty ones mean the
    # toolbox's defaults (gain 1, acceleration 0 for every joint).
    with pytest.raises(ValueError, match="init_gains"):
        lqr.init_lqr(jnp.asarray(x0), Ti, dU, dt, jaco.INIT_LQR)
    ones = dataclasses.replace(cfg, init_gains=(1.0, 1.0), init_acc=(0.0, 0.0))
    np.testing.assert_array_equal(init_lqr_jit(jnp.asarray(x0), Ti, dU, dt, ones).K,
                                  init_lqr_jit(jnp.asarray(x0), Ti, dU, dt,
                                               dataclasses.replace(cfg, init_gains=(), init_acc=())).K)


def test_init_pd():
    x0 = jnp.asarray([0.2, -0.4, 0.5, 0.1, 7.0])
    pol = init_pd_jit(x0, 3, 2, init_var=4.0, pos_gains=10.0, vel_gains_mult=0.01)
    K = -10.0 * np.array([[1, 0, 0.01, 0, 0], [0, 1, 0, 0.01, 0]])
    np.testing.assert_allclose(pol.K, np.broadcast_to(K, (3, 2, 5)))
    np.testing.assert_allclose(np.einsum("tij,j->ti", pol.K, x0) + pol.k, 0.0,
                               atol=2 * affine_tol(pol.K, np.broadcast_to(x0, (3, 5)), pol.k))
    np.testing.assert_allclose(pol.pol_covar, 4.0 * np.eye(2)[None].repeat(3, 0))
    np.testing.assert_allclose(np.swapaxes(pol.chol_pol_covar, 1, 2) @ pol.chol_pol_covar, pol.pol_covar)
    np.testing.assert_allclose(pol.inv_pol_covar @ pol.pol_covar, np.eye(2)[None].repeat(3, 0))


def test_policy_from_precision_and_covariance_agree():
    rng = np.random.default_rng(8)
    p = random_policy(rng)
    # p's covariance side came from inverting its precision (or the reverse): two roundings of
    # a dU×dU inverse and Cholesky factor, c·n·ε·κ normwise (tests/tolerances.py).
    q = lqr.policy_from_precision(p.K, p.k, p.inv_pol_covar)
    kappa = max(np.linalg.cond(np.asarray(S)) for S in p.pol_covar)
    for a, b in zip(p, q):
        for t in range(T):
            assert_close(a[t], b[t], 4 * linear_tol(kappa, DU))
    for t in range(T):
        assert_close(lqr.policy_precision(p)[t], p.inv_pol_covar[t], 4 * linear_tol(kappa, DU))


def test_step_multiplier():
    cfg = StepConfig()
    # The toolbox's worked example quotes 1.2076 from unrounded improvements; the rounded
    # inputs 21.75 and 12.74 give 21.75 / (2·9.01) = 1.20699.
    new = step_size.step_multiplier(21.75, 12.74, 1.0, cfg)
    # a subtraction, a product and a division on each side: c·3·ε relative (tests/tolerances.py)
    np.testing.assert_allclose(new, 21.75 / (2 * 9.01), rtol=2 * linear_tol(1.0, 3))
    assert abs(float(new) - 1.2076) < 1e-3
    np.testing.assert_allclose(step_size.step_multiplier(21.75, 12.74, 2.0, cfg), 2 * 21.75 / 18.02,
                               rtol=2 * linear_tol(1.0, 4))
    assert float(step_size.step_multiplier(10.0, 10.0, 1.0, cfg)) == 5.0  # denominator floor → clip 5
    assert float(step_size.step_multiplier(-1.0, 3.0, 1.0, cfg)) == pytest.approx(0.1)  # clip 0.1
    assert float(step_size.step_multiplier(10.0, 10.0, 9.0, cfg)) == 10.0  # max_step_mult
    assert float(step_size.step_multiplier(-1.0, 3.0, 0.05, cfg)) == pytest.approx(0.01)  # min_step_mult
    batch = step_size.step_multiplier(jnp.asarray([21.75, 10.0]), jnp.asarray([12.74, 10.0]), jnp.ones(2), cfg)
    np.testing.assert_allclose(batch, [21.75 / 18.02, 5.0], rtol=2 * linear_tol(1.0, 3))
    assert step_size.kl_epsilon(1.5, 80, cfg) == pytest.approx(0.2 * 1.5 * 80)

"""The toolbox's rank-one regulariser as an option (``DynamicsConfig.regularizer``,
``PolicyPriorConfig.t0_regularizer``): equal to numpy transcriptions of the toolbox's fits, and
what it changes against the default ridge on rank-deficient data (a deterministic linear plant).
"""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from test_dynamics import CFG, SYS1, T, _fit, _rollout, _update, dU, dX, np_fit_dynamics
import test_linearize as tl
from tolerances import EPS, SAFETY, assert_trees_within, measured_tol

from gmr_jax.config import DynamicsConfig, PolicyPriorConfig
from gmr_jax.dynamics import dynamics_ok, dynamics_prior_empty
from gmr_jax.prior import regularizer_matrix
from gmr_jax.linearize import policy_prior_empty


def test_regularizer_matrix_and_validation():
    ridge = np.asarray(regularizer_matrix("ridge", 2.0, 3, 5, jnp.float64))
    broadcast = np.asarray(regularizer_matrix("toolbox", 2.0, 3, 5, jnp.float64))
    expect = np.zeros((5, 5))
    expect[:3, :3] = 2.0 * np.eye(3)
    np.testing.assert_array_equal(ridge, expect)
    expect[:3, :3] = 2.0  # the toolbox's ``sig_reg[:n, :n] = value``
    np.testing.assert_array_equal(broadcast, expect)
    assert DynamicsConfig().regularizer == "ridge" and PolicyPriorConfig().t0_regularizer == "ridge"
    with pytest.raises(ValueError, match=r"dynamics\.regularizer='rank1': allowed values are \('ridge', 'toolbox'\)"):
        DynamicsConfig(regularizer="rank1")
    with pytest.raises(ValueError, match=r"policy_prior\.t0_regularizer='x': allowed values are"):
        PolicyPriorConfig(t0_regularizer="x")
    with pytest.raises(ValueError, match="regularizer='x'"):
        regularizer_matrix("x", 1.0, 2, 3, jnp.float64)


def _deterministic_fit(kind: str):
    """Fit of a deterministic linear plant x' = A x + B u + c (no process noise) from N = 3
    samples, fewer than dX + dU = 5: the empirical (x, u) covariance of every step is rank 2.
    The prior holds two earlier batches of 3, as in an MDGPS iteration."""
    cfg = dataclasses.replace(CFG, regularizer=kind)
    prior = dynamics_prior_empty(T, dX, dU, cfg, jnp.float64)
    for i in range(2):
        Xp, Up = _rollout(SYS1, 3, 10 + i, noise=0.0)
        prior = _update(prior, jax.random.key(i), jnp.asarray(Xp), jnp.asarray(Up), cfg)
    X, U = _rollout(SYS1, 3, 5, noise=0.0)
    return cfg, prior, X, U, _fit(prior, jnp.asarray(X), jnp.asarray(U), cfg)


@pytest.mark.parametrize("kind", ["toolbox", "ridge"])
def test_dynamics_fit_matches_numpy_transcription(kind):
    cfg, prior, X, U, dyn = _deterministic_fit(kind)
    assert bool(dynamics_ok(dyn))
    # Tolerance from the computation: the numpy transcription run on inputs (the data and the
    # prior's GMM) perturbed by ε relative shows how far rounding moves each output (the
    # conditioning of Σ_xu,xu and of the GMM responsibilities at work), times SAFETY
    # (tests/tolerances.py). Measured on a 2-core AMD EPYC: the two programs differ by at most
    # 1.8× that spread (dyn_covar, a difference of O(1) terms that is O(1e-6)).
    ref, tol = measured_tol(lambda p, x, u: np_fit_dynamics(p, x, u, cfg), (prior, X, U), SAFETY)
    assert_trees_within(tuple(dyn), tuple(ref), tol)


def test_toolbox_regularizer_differs_from_ridge_on_rank_deficient_data():
    _, _, X, U, ridge = _deterministic_fit("ridge")
    cfg, prior, _, _, toolbox = _deterministic_fit("toolbox")
    A, B, c = SYS1
    # With the GMM prior (whose covariances carry EM's 1e-6·I) both fits are well-posed and close
    # to the plant, and they differ by what the rank-one 1e-6·11ᵀ changes against 1e-6·I on
    # (x, u) covariances whose smallest eigenvalues are of the order of the prior's 1e-6: measured
    # max|ΔFm| = 1.7e-4, max|Δfv| = 1.1e-4, max|Δdyn_covar| = 1.2e-6, about the fits' own error
    # against [A B] (2e-4).
    dF = np.abs(np.asarray(ridge.Fm) - np.asarray(toolbox.Fm)).max()
    dfv = np.abs(np.asarray(ridge.fv) - np.asarray(toolbox.fv)).max()
    dS = np.abs(np.asarray(ridge.dyn_covar) - np.asarray(toolbox.dyn_covar)).max()
    assert 3e-5 < dF < 1e-3 and 2e-5 < dfv < 1e-3 and 2e-7 < dS < 1e-5, (dF, dfv, dS)
    for dyn in (ridge, toolbox):
        assert np.abs(np.asarray(dyn.Fm[:-1]) - np.c_[A, B]).max() < 1e-3
    # The difference is the regulariser's, not rounding: the numpy transcriptions of both fits
    # differ by the same amount, to the rounding tolerance of the two comparisons.
    ref_r, tol_r = measured_tol(lambda p, x, u: np_fit_dynamics(p, x, u, dataclasses.replace(cfg, regularizer="ridge")),
                                (prior, X, U), SAFETY)
    ref_t, tol_t = measured_tol(lambda p, x, u: np_fit_dynamics(p, x, u, cfg), (prior, X, U), SAFETY)
    for i in range(3):
        got = np.asarray(ridge[i]) - np.asarray(toolbox[i])
        want = ref_r[i] - ref_t[i]
        assert np.abs(got - want).max() <= tol_r[i] + tol_t[i]
        assert np.abs(want).max() > 1e3 * (tol_r[i] + tol_t[i])  # far above rounding

    # Without a prior (the toolbox's DynamicsLR) the rank-one term leaves Σ_xu,xu singular
    # (rank 2 + 1 < 5): the fit fails (non-finite, caught by dynamics_ok); the ridge makes it
    # well-posed and the fitted model reproduces every observed transition.
    empty = dynamics_prior_empty(T, dX, dU, cfg, jnp.float64)
    no_prior = {k: _fit(empty, jnp.asarray(X), jnp.asarray(U), dataclasses.replace(cfg, regularizer=k))
                for k in ("ridge", "toolbox")}
    assert not bool(dynamics_ok(no_prior["toolbox"]))
    assert bool(dynamics_ok(no_prior["ridge"]))
    d = no_prior["ridge"]
    pred = (np.einsum("tij,ntj->nti", np.asarray(d.Fm[:-1]), np.concatenate([X[:, :-1], U[:, :-1]], -1))
            + np.asarray(d.fv[:-1]))
    # The ridge's bias on a transition is ≈ λ·‖Σ_aa⁻¹‖·‖x'‖ with λ = 1e-6 and the data's
    # smallest nonzero variance ~0.1: ≲ 1e-4.
    assert np.abs(pred - X[:, 1:]).max() < 1e-4


@pytest.mark.parametrize("kind", ["toolbox", "ridge"])
def test_policy_linearization_t0_regularizer_matches_numpy(kind):
    """The same option at t = 0 of the policy linearisation (deterministic x₀: the x block of the
    t = 0 data is all zeros, only the prior makes it invertible)."""
    cfg = dataclasses.replace(tl.CFG, t0_regularizer=kind, t0_regularization=1e-4)
    params = tl._params(3, a=0.8)
    prior = policy_prior_empty(tl.T, tl.dX, tl.dU, cfg, jnp.float64)
    for i in range(2):
        prior = tl._update_add(prior, jax.random.key(i), jnp.asarray(tl._states(40 + i)), params)
    X = tl._states(50)
    pol_mu = tl._pol_mu(params, X)
    got = tl._linearize(prior, jnp.asarray(X), jnp.asarray(pol_mu), jnp.asarray(tl.POL_VAR), cfg)
    pol_sig = np.broadcast_to(tl.POL_VAR, (tl.T, tl.dU, tl.dU))
    ref, tol = measured_tol(lambda p, x, mu: tl._np_linearize(p, x, mu, pol_sig, cfg), (prior, X, pol_mu), SAFETY)
    assert_trees_within(tuple(got), tuple(ref), tol)
    # Only t = 0 is regularised: the other steps equal those of the other regulariser.
    other = dataclasses.replace(cfg, t0_regularizer="ridge" if kind == "toolbox" else "toolbox")
    alt = tl._linearize(prior, jnp.asarray(X), jnp.asarray(pol_mu), jnp.asarray(tl.POL_VAR), other)
    np.testing.assert_array_equal(np.asarray(got[0][1:]), np.asarray(alt[0][1:]))
    assert np.abs(np.asarray(got[0][0]) - np.asarray(alt[0][0])).max() > 1e3 * EPS * np.abs(np.asarray(got[0][0])).max()

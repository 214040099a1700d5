"""The Generative Motor Reflex policy: forward pass against numpy, test-time latent, PD reflex
covariance, loss terms against direct and Monte Carlo computations, S-step on a linear-Gaussian
teacher, autodiff linearisation, jit/vmap consistency, dtypes."""

import dataclasses
import functools
import math
from types import SimpleNamespace

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from tolerances import (SAFETY, affine_tol, assert_close, assert_tolerances_small, assert_trees_within,
                        linear_tol, measured_tol)

from gmr_jax.config import GMRConfig, SStepConfig
from gmr_jax.policies import make_policy, make_sstep_data
from gmr_jax.policies.base import Normalization
from gmr_jax.policies.gmr import cholesky_factor, gmr_linearize, make_gmr, make_gmr_policy
from gmr_jax.sstep import set_normalization, sstep

dX, dU, LAT = 5, 3, 2
CFG = GMRConfig(latent=LAT, encoder_hidden=(16, 16), decoder_hidden=(16, 16),
                translation_hidden=(16, 16))
RAW = dataclasses.replace(CFG, head_coordinates="raw")
NTRI = dU * (dU + 1) // 2


# ------------------------------------------------------------------------------------ helpers


@functools.lru_cache(maxsize=None)
def _fns(cfg=CFG):
    """Jitted GMR functions (eager Flax dispatch is slow on CPU; each jit compiles once)."""
    g = make_gmr(cfg)
    return SimpleNamespace(
        init=jax.jit(g.policy.init, static_argnums=(1, 2, 3)), mean=jax.jit(g.policy.mean),
        cov=jax.jit(g.policy.covariance), loss=jax.jit(g.policy.loss), finalize=jax.jit(g.policy.finalize),
        encode=jax.jit(g.encode), decode=jax.jit(g.decode), translate=jax.jit(g.translate),
        reflex=jax.jit(g.reflex), action=jax.jit(g.action),
        linearize=jax.jit(jax.vmap(g.linearize, in_axes=(None, 0))))


def _spd(rng, n, count):
    A = rng.normal(size=(count, n, n))
    return A @ np.transpose(A, (0, 2, 1)) / n + 0.5 * np.eye(n)


def _init(cfg=CFG, key=0, dtype=None, dx=dX, du=dU):
    return _fns(cfg).init(jax.random.key(key), dx, du, dtype)


def _with_norm(params, seed=0):
    rng = np.random.default_rng(seed)
    norm = Normalization(scale=jnp.asarray(rng.uniform(0.5, 2.0, dX)), bias=jnp.asarray(rng.normal(size=dX)),
                         set=jnp.asarray(True))
    return params._replace(norm=norm)


def _np_mlp(layers, h, slope=0.2):
    n = len(layers)
    for i in range(n):
        h = h @ np.asarray(layers[f"Dense_{i}"]["kernel"]) + np.asarray(layers[f"Dense_{i}"]["bias"])
        if i < n - 1:
            h = np.where(h > 0, h, slope * h)
    return h


def _np_chol(r, cfg):
    """Independent numpy version of the bounded Cholesky factor (one r [NTRI])."""
    s = math.log(cfg.cov_std_range)
    c = cfg.cov_offdiag_bound
    V = np.eye(dU)
    sig = np.zeros(dU)
    idx = 0
    for i in range(dU):
        for j in range(i + 1):
            if i == j:
                sig[i] = math.sqrt(cfg.init_var) * math.exp(s * math.tanh(r[idx] / s))
            else:
                V[i, j] = c * math.tanh(r[idx] / c)
            idx += 1
    R = V / np.linalg.norm(V, axis=1, keepdims=True)
    return sig[:, None] * R


def _np_squash(xn, cfg):
    c = cfg.encoder_squash
    return c * np.tanh(xn / c) if c > 0 else xn


def _np_reflex(params, x, cfg, z=None):
    """Numpy GMR at z (default μ_z): (u, Ψ_K, Ψ_k, Ψ_Σ, μ_z, log σ²_z) for one x [dX]."""
    net = params.net["params"]
    scale, bias = np.asarray(params.norm.scale), np.asarray(params.norm.bias)
    xn = x * scale + bias
    enc = _np_mlp(net["encoder"], _np_squash(xn, cfg), cfg.negative_slope)
    mu, lv = enc[:LAT], enc[LAT:]
    z = mu if z is None else z
    out = _np_mlp(net["translation"], z, cfg.negative_slope)
    G = out[: dU * dX].reshape(dU, dX)
    g = out[dU * dX: dU * dX + dU]
    L = _np_chol(out[dU * dX + dU:], cfg)
    if cfg.head_coordinates == "raw":
        K, k = G, g
    else:
        K, k = G * scale, g + G @ bias
    return K @ x + k, K, k, L @ L.T, mu, lv


def _zero_last(params, net_name, bias=None):
    """Zero the last-layer kernel of one network (its output becomes the constant bias)."""
    net = jax.tree_util.tree_map(lambda a: a, params.net)
    layers = net["params"][net_name]
    last = f"Dense_{len(layers) - 1}"
    layers[last]["kernel"] = jnp.zeros_like(layers[last]["kernel"])
    if bias is not None:
        layers[last]["bias"] = jnp.asarray(bias, layers[last]["bias"].dtype)
    return params._replace(net=net)


def _teacher(seed, n, state_scale=1.0):
    """Linear-Gaussian teacher: K_p, k_p, P, state mean μ and covariance Σ."""
    rng = np.random.default_rng(seed)
    Kp = rng.normal(size=(dU, dX))
    kp = rng.normal(size=dU)
    P = _spd(rng, dU, 1)[0]
    mu = rng.normal(size=dX) * 2.0
    A = rng.normal(size=(dX, dX)) * state_scale
    Sig = A @ A.T / dX + 0.05 * np.eye(dX)
    return Kp, kp, P, mu, Sig


def _kl_gauss(m1, S1, m2, P2):
    """KL(N(m1, S1) ‖ N(m2, P2⁻¹)) in closed form."""
    d = m1 - m2
    n = len(m1)
    return 0.5 * (np.trace(P2 @ S1) + d @ P2 @ d - n - np.linalg.slogdet(P2)[1] - np.linalg.slogdet(S1)[1])


# -------------------------------------------------------------------------------------- tests


def test_paper_architecture_and_init():
    params = jax.eval_shape(lambda k: make_gmr(GMRConfig()).policy.init(k, 12, 6), jax.random.key(0))
    net = params.net["params"]
    shapes = {name: [net[name][f"Dense_{i}"]["kernel"].shape for i in range(3)] for name in net}
    assert shapes == {"encoder": [(12, 64), (64, 64), (64, 8)],
                      "decoder": [(4, 64), (64, 64), (64, 12)],
                      "translation": [(4, 64), (64, 64), (64, 72 + 6 + 21)]}
    for leaf in jax.tree_util.tree_leaves(params):
        assert leaf.dtype in (jnp.float64, jnp.bool_)
    params = _init(CFG)
    np.testing.assert_array_equal(params.var, np.full(dU, 0.1))
    np.testing.assert_array_equal(params.norm.scale, np.ones(dX))
    np.testing.assert_array_equal(params.norm.bias, np.zeros(dX))
    assert not bool(params.norm.set)
    # float32 params give float32 outputs (no hard-coded dtype); abstract evaluation suffices
    pol = make_gmr(CFG).policy
    p32 = jax.eval_shape(lambda k: pol.init(k, dX, dU, jnp.float32), jax.random.key(0))
    assert {leaf.dtype for leaf in jax.tree_util.tree_leaves(p32)} == {jnp.dtype(jnp.float32), jnp.dtype(bool)}
    x32 = jax.ShapeDtypeStruct((dX,), jnp.float32)
    assert jax.eval_shape(pol.mean, p32, x32).dtype == jnp.float32
    assert jax.eval_shape(pol.covariance, p32, x32).dtype == jnp.float32
    assert jax.eval_shape(make_gmr(CFG).linearize, p32, x32)[0].dtype == jnp.float32
    data = make_sstep_data(np.ones((4, dX), np.float32), np.ones((4, dU), np.float32),
                           np.tile(np.eye(dU, dtype=np.float32), (4, 1, 1)))
    value, aux = jax.eval_shape(pol.loss, p32, data, jax.random.key(0))
    assert value.dtype == jnp.float32 and all(v.dtype == jnp.float32 for v in aux.values())


def test_make_policy_hook_and_validation():
    assert make_policy("gmr") is make_policy("gmr", GMRConfig())
    assert make_policy("gmr", CFG) is make_policy("gmr", CFG)
    assert make_gmr_policy(CFG) is make_gmr(CFG).policy
    for bad in (dict(latent=0), dict(alpha=-1.0), dict(head_coordinates="x"), dict(exploration="y"),
                dict(cov_std_range=1.0), dict(negative_slope=1.5), dict(encoder_hidden=[64]),
                dict(encoder_squash=-1.0)):
        with pytest.raises(ValueError, match="gmr."):
            GMRConfig(**bad)


@pytest.mark.parametrize("cfg", [CFG, RAW], ids=["normalized", "raw"])
def test_forward_matches_numpy(cfg):
    F = _fns(cfg)
    params = _with_norm(_init(cfg, key=1))
    x = np.random.default_rng(3).normal(size=(6, dX)) * 2.0
    u = F.mean(params, jnp.asarray(x))
    cov = F.cov(params, jnp.asarray(x))
    refl = F.reflex(params, jnp.asarray(x))
    for b in range(len(x)):
        # Tolerance from the computation (tests/tolerances.py): the numpy forward pass rerun on
        # parameters and state perturbed by ε relative, SAFETY times the spread of each output.
        ref, tol = measured_tol(lambda p, xb: _np_reflex(p, xb, cfg)[:5], (params, x[b]), SAFETY)
        assert_tolerances_small(ref, tol, 1e-8)
        got = (u[b], refl.K[b], refl.k[b], cov[b], F.encode(params, jnp.asarray(x[b]))[0])
        assert_trees_within(got, tuple(ref), tol)
    # u = Ψ_K x + Ψ_k with the raw state (two summation orders: affine_tol)
    assert_trees_within(u, np.einsum("bij,bj->bi", refl.K, x) + refl.k, affine_tol(refl.K, x, refl.k))
    # log|Ψ_Σ| from the Cholesky factor against LU: |Δ log det| ≤ dU·c·dU·ε·κ (tests/tolerances.py)
    for b in range(len(x)):
        kappa = np.linalg.cond(np.asarray(cov[b]))
        assert abs(float(refl.logdet[b]) - np.linalg.slogdet(np.asarray(cov[b]))[1]) <= dU * linear_tol(kappa, dU)


def test_encoder_input_is_bounded_far_from_the_data():
    """With encoder_squash > 0 the latent, hence the reflex, saturates far away, and the action
    stays the saturated reflex applied linearly to the state; without it the latent keeps growing."""
    d = np.random.default_rng(5).normal(size=dX)
    for cfg, bounded in ((CFG, True), (dataclasses.replace(CFG, encoder_squash=0.0), False)):
        F = _fns(cfg)
        params = _with_norm(_init(cfg, key=2))
        far1, far2 = jnp.asarray(1e3 * d), jnp.asarray(1e4 * d)
        mu1, mu2 = F.encode(params, far1)[0], F.encode(params, far2)[0]
        if bounded:
            np.testing.assert_allclose(mu1, mu2, rtol=1e-12, atol=1e-12)
            refl = F.reflex(params, far1)
            np.testing.assert_allclose(F.mean(params, far2) - F.mean(params, far1),
                                       refl.K @ (far2 - far1), rtol=1e-9)
        else:
            assert np.linalg.norm(mu2) > 5 * np.linalg.norm(mu1)
    assert CFG.encoder_squash == GMRConfig().encoder_squash == 1.0


def test_cholesky_factor_centre_and_bounds():
    cfg = GMRConfig()
    L, logdet = cholesky_factor(jnp.zeros(21), 6, cfg.init_var, cfg.cov_std_range, cfg.cov_offdiag_bound)
    np.testing.assert_allclose(L @ L.T, cfg.init_var * np.eye(6), rtol=1e-14, atol=1e-16)
    np.testing.assert_allclose(logdet, 6 * math.log(cfg.init_var), rtol=1e-14)
    # saturated inputs: standard deviations at the bounds, correlation factor at its limit
    r = jnp.asarray(np.random.default_rng(0).choice([-1e6, 1e6], size=21))
    L, logdet = cholesky_factor(r, 6, cfg.init_var, cfg.cov_std_range, cfg.cov_offdiag_bound)
    std = np.sqrt(np.diag(L @ L.T))
    lo, hi = math.sqrt(cfg.init_var) / cfg.cov_std_range, math.sqrt(cfg.init_var) * cfg.cov_std_range
    at_bound = np.minimum(np.abs(std / lo - 1), np.abs(std / hi - 1))
    np.testing.assert_allclose(at_bound, 0, atol=1e-10)  # σ_i is exactly the std of entry i
    np.testing.assert_allclose(logdet, np.linalg.slogdet(np.asarray(L @ L.T))[1], rtol=1e-9)


def test_reflex_covariance_positive_definite():
    """Random (also inflated) weights and inputs far outside the data: Ψ_Σ stays PD in float64."""
    F = _fns(GMRConfig())
    rng = np.random.default_rng(5)
    lo = math.sqrt(GMRConfig().init_var) / GMRConfig().cov_std_range
    hi = math.sqrt(GMRConfig().init_var) * GMRConfig().cov_std_range
    reflex = F.reflex
    for seed, mult in ((0, 1.0), (1, 5.0), (2, 30.0)):
        params = _init(GMRConfig(), key=seed, dx=12, du=6)
        params = params._replace(net=jax.tree_util.tree_map(lambda a: mult * a, params.net))
        for s in (1.0, 1e2, 1e8):
            x = jnp.asarray(rng.normal(size=(40, 12)) * s)
            refl = reflex(params, x)
            cov = np.asarray(refl.cov)
            assert np.all(np.isfinite(cov)) and np.all(np.isfinite(np.asarray(refl.logdet)))
            np.testing.assert_array_equal(cov, np.swapaxes(cov, -1, -2))
            L = np.asarray(refl.chol)
            assert np.all(np.triu(L, 1) == 0) and np.all(np.diagonal(L, axis1=-2, axis2=-1) > 0)
            assert np.all(np.linalg.eigvalsh(cov)[:, 0] > 0)
            np.linalg.cholesky(cov)  # raises if not numerically PD
            std = np.sqrt(np.diagonal(cov, axis1=-2, axis2=-1))
            assert np.all(std >= lo * (1 - 1e-9)) and np.all(std <= hi * (1 + 1e-9))


def test_test_time_latent_is_the_mean():
    """mean/covariance use z = μ_z: deterministic, independent of σ_z, equal to translate(μ_z)."""
    F = _fns(CFG)
    params = _with_norm(_init(CFG, key=2))
    x = jnp.asarray(np.random.default_rng(7).normal(size=(5, dX)))
    u = F.mean(params, x)
    np.testing.assert_array_equal(u, F.mean(params, x))
    mu, _ = F.encode(params, x)
    # Two programs each time: tolerances from the computation (tests/tolerances.py), the
    # reference rerun on inputs perturbed by ε relative, SAFETY times the spread.
    assert_trees_within(u, *measured_tol(F.action, (params, x, mu), SAFETY))
    refl = F.translate(params, mu)
    assert_trees_within(F.cov(params, x), *measured_tol(lambda p, m: F.translate(p, m).cov, (params, mu), SAFETY))
    assert_trees_within(u, jnp.einsum("bij,bj->bi", refl.K, x) + refl.k, affine_tol(refl.K, x, refl.k))
    # changing the log σ²_z outputs of the encoder leaves the test-time outputs unchanged …
    net = jax.tree_util.tree_map(lambda a: a, params.net)
    last = net["params"]["encoder"]["Dense_2"]
    last["kernel"] = last["kernel"].at[:, LAT:].set(3.0)
    last["bias"] = last["bias"].at[LAT:].set(2.0)
    wide = params._replace(net=net)
    np.testing.assert_array_equal(F.mean(wide, x), u)
    np.testing.assert_array_equal(F.cov(wide, x), F.cov(params, x))
    # … but not the training loss, which samples z = μ_z + σ_z·ε
    rng = np.random.default_rng(8)
    data = make_sstep_data(np.asarray(x), rng.normal(size=(5, dU)), _spd(rng, dU, 5))
    key = jax.random.key(3)
    assert abs(float(F.loss(wide, data, key)[0]) - float(F.loss(params, data, key)[0])) > 1e-3
    # the decoder at μ_z against numpy
    xhat = F.decode(params, mu)
    ref, tol = measured_tol(lambda net, m: _np_mlp(net, np.asarray(m)), (params.net["params"]["decoder"], mu), SAFETY)
    assert_tolerances_small(ref, tol, 1e-8)
    assert_trees_within(xhat, ref, tol)


def test_loss_terms_against_direct_computation():
    F = _fns(CFG)
    params = _with_norm(_init(CFG, key=4), seed=4)
    rng = np.random.default_rng(9)
    B = 7
    x = rng.normal(size=(B, dX)) * 1.5
    tgt = rng.normal(size=(B, dU))
    P = _spd(rng, dU, B)
    Kp = rng.normal(size=(B, dU, dX))
    kp = rng.normal(size=(B, dU))
    S = _spd(rng, dX, B) * 0.3
    w = rng.uniform(0.5, 2.0, B)
    w[3] = 0.0  # a padding row
    data = make_sstep_data(x, tgt, w[:, None, None] * P, wt=w, K=Kp, k=kp, state_cov=S)
    key = jax.random.key(11)
    value, aux = F.loss(params, data, key)

    eps = np.asarray(jax.random.normal(key, (B, LAT), jnp.float64))  # the documented noise draw

    def np_terms(params, x, tgt, P, Kp, S):
        scale, bias = np.asarray(params.norm.scale), np.asarray(params.norm.bias)
        x, tgt, P, Kp, S = (np.asarray(a) for a in (x, tgt, P, Kp, S))
        terms = {k: np.zeros(B) for k in ("recon", "latent_kl", "action", "gain", "cov")}
        for b in range(B):
            _, _, _, _, mu, lv = _np_reflex(params, x[b], CFG)
            z = mu + np.exp(0.5 * lv) * eps[b]
            u, K, _, Psi, _, _ = _np_reflex(params, x[b], CFG, z=z)
            xn = _np_squash(x[b] * scale + bias, CFG)  # the encoder's input is the reconstruction target
            xhat = _np_mlp(params.net["params"]["decoder"], z)
            du, dK = u - tgt[b], K - Kp[b]
            terms["recon"][b] = w[b] * np.sum((xn - xhat) ** 2)
            terms["latent_kl"][b] = w[b] * 0.5 * np.sum(mu ** 2 + np.exp(lv) - lv - 1)
            terms["action"][b] = 0.5 * w[b] * du @ P[b] @ du
            terms["gain"][b] = 0.5 * w[b] * np.trace(dK.T @ P[b] @ dK @ S[b])
            # the covariance part of the exact Gaussian KL: KL(N(0, Ψ_Σ) ‖ N(0, P⁻¹))
            terms["cov"][b] = w[b] * _kl_gauss(np.zeros(dU), Psi, np.zeros(dU), P[b])
        means = {k: t.mean() for k, t in terms.items()}
        means["value"] = (means["recon"] + CFG.alpha * means["latent_kl"] + means["action"] + means["gain"]
                          + means["cov"])
        return means

    # Tolerance from the computation (tests/tolerances.py): the numpy terms rerun on inputs
    # perturbed by ε relative, SAFETY times the spread of each.
    want, tol = measured_tol(np_terms, (params, x, tgt, P, Kp, S), SAFETY)
    assert_tolerances_small(want, tol, 1e-8)
    got = {k: (value if k == "value" else aux[k]) for k in want}
    assert_trees_within(got, want, tol)
    assert aux["cov"] >= 0 and aux["latent_kl"] >= 0
    # the S-step's precomputed log|P| (SStepData.tgt_logdet) gives the same loss
    from gmr_jax.policies.base import target_logdet
    pre = data._replace(tgt_logdet=target_logdet(jnp.asarray(P), jnp.asarray(w)))
    v_pre, aux_pre = F.loss(params, pre, key)
    # (another program: tolerance measured on the loss as above)
    loss_ref, loss_tol = measured_tol(lambda p, d: (lambda v, a: (v, a["cov"], a["latent_kl"]))(*F.loss(p, d, key)),
                                      (params, data), SAFETY)
    assert_trees_within((v_pre, aux_pre["cov"]), loss_ref[:2], loss_tol[:2])
    # α scales only the latent term (value and v2 each within their measured tolerance)
    v2, _ = _fns(dataclasses.replace(CFG, alpha=0.25)).loss(params, data, key)
    assert abs(float(value - v2) - 0.75 * float(aux["latent_kl"])) <= 2 * loss_tol[0] + loss_tol[2]


def test_controller_term_is_expected_gaussian_kl():
    """action + gain + cov = E_{x~N(μ,Σ)} KL(π_Ψ(·|x) ‖ p(·|x)) for a reflex that is constant in x.

    With the sample mean and the (biased) sample covariance of the Monte Carlo draws the identity
    is exact; against the true (μ, Σ) it holds to Monte Carlo accuracy.
    """
    F = _fns(CFG)
    rng = np.random.default_rng(12)
    head = rng.normal(size=dU * dX + dU + NTRI) * 0.7
    params = _zero_last(_with_norm(_init(CFG, key=5), seed=5), "translation", bias=head)
    Kp, kp, P, mu, Sig = _teacher(13, 1)
    refl = F.reflex(params, jnp.asarray(mu))
    PsiK, Psik, PsiS = (np.asarray(a) for a in (refl.K, refl.k, refl.cov))

    n = 20000
    xs = rng.multivariate_normal(mu, Sig, size=n)
    kls = np.array([_kl_gauss(PsiK @ xx + Psik, PsiS, Kp @ xx + kp, P) for xx in xs[:2000]])
    # vectorised for all draws: the mean part is quadratic in x, the rest constant
    dmean = xs @ (PsiK - Kp).T + (Psik - kp)
    kl_all = 0.5 * np.einsum("ni,ij,nj->n", dmean, P, dmean) + _kl_gauss(np.zeros(dU), PsiS, np.zeros(dU), P)

    def vectorised(xs, PsiK, Psik, PsiS, Kp, kp, P):
        dm = xs @ (PsiK - Kp).T + (Psik - kp)
        return 0.5 * np.einsum("ni,ij,nj->n", dm, P, dm) + _kl_gauss(np.zeros(dU), PsiS, np.zeros(dU), P)

    # Two numpy programs: tolerance from the computation (tests/tolerances.py), the vectorised
    # form rerun on inputs perturbed by ε relative, SAFETY times the spread (both sides: ×2).
    _, kl_tol = measured_tol(vectorised, (xs[:2000], PsiK, Psik, PsiS, Kp, kp, P), SAFETY)
    assert_trees_within(kl_all[:2000], kls, 2 * kl_tol[0])

    def controller(m, S):
        data = make_sstep_data(m[None], (Kp @ m + kp)[None], P[None], K=Kp[None], k=kp[None], state_cov=S[None])
        _, aux = F.loss(params, data, jax.random.key(0))
        return float(aux["action"] + aux["gain"] + aux["cov"])

    m_hat = xs.mean(axis=0)
    S_hat = (xs - m_hat).T @ (xs - m_hat) / n
    # The identity is exact in (m̂, Ŝ); the two sides round differently: the loss's tolerance
    # measured on (m̂, Ŝ) and the mean's on the draws (tests/tolerances.py), SAFETY times each spread.
    got, tol_c = measured_tol(controller, (m_hat, S_hat), SAFETY)
    want, tol_m = measured_tol(lambda xs_: vectorised(xs_, PsiK, Psik, PsiS, Kp, kp, P).mean(), (xs,), SAFETY)
    assert abs(got - want) <= tol_c[0] + tol_m[0]
    assert tol_c[0] + tol_m[0] < 1e-8 * abs(want)
    stderr = kl_all.std() / math.sqrt(n)
    assert abs(controller(mu, Sig) - kl_all.mean()) < 4 * stderr
    # without the gain term (Σ = 0) the expectation is underestimated
    assert controller(mu, 0 * Sig) < kl_all.mean() - 10 * stderr


@pytest.mark.parametrize("impl", ["reference", "packed"])
def test_sstep_fits_linear_gaussian_teacher(impl):
    """A short S-step drives the controller KL (training loss) and the test-time action error down
    (in both forms of the S-step)."""
    F = _fns(CFG)
    Kp, kp, P, mu, Sig = _teacher(21, 1)
    rng = np.random.default_rng(22)
    B = 160
    x = rng.multivariate_normal(mu, Sig, size=B)
    data = make_sstep_data(x, x @ Kp.T + kp, np.tile(P, (B, 1, 1)), K=np.tile(Kp, (B, 1, 1)),
                           k=np.tile(kp, (B, 1)), state_cov=np.tile(Sig, (B, 1, 1)))
    params0 = set_normalization(_init(CFG, key=6), data.x)

    def controller_kl(p):
        _, aux = F.loss(p, data, jax.random.key(99))
        return float(aux["action"] + aux["gain"] + aux["cov"])

    def test_time_action_error(p):
        du = np.asarray(F.mean(p, data.x)) - np.asarray(data.tgt_mu)
        return 0.5 * np.mean(np.einsum("bi,ij,bj->b", du, P, du))

    params, metrics = jax.jit(sstep, static_argnums=(0, 4), static_argnames="impl")(
        make_gmr(CFG).policy, params0, data, jax.random.key(23), SStepConfig(epochs=60, statistics_epochs="all"),
        impl=impl)
    assert bool(metrics["finite"])
    before, after = controller_kl(params0), controller_kl(params)
    e0, e1 = test_time_action_error(params0), test_time_action_error(params)
    assert after < 0.05 * before, (before, after)
    assert e1 < 0.05 * e0, (e0, e1)
    assert float(metrics["aux"]["recon"][-1]) < 0.8 * float(metrics["aux"]["recon"][0])
    # the covariance term (the Gaussian KL of Ψ_Σ against P⁻¹) falls too, Ψ_Σ moving towards P⁻¹
    cov0 = float(F.loss(params0, data, jax.random.key(99))[1]["cov"])
    cov1 = float(F.loss(params, data, jax.random.key(99))[1]["cov"])
    assert cov1 < 0.2 * cov0, (cov0, cov1)
    # finalize: closed-form variance 1/diag(P) (constant weights): the mean of B equal positive
    # diagonals and a reciprocal, c·(B + 1)·ε relative (tests/tolerances.py)
    assert_close(params.var, 1.0 / np.diag(P), linear_tol(1.0, B + 1))


def test_fixed_exploration_uses_closed_form_variance():
    fixed = _fns(dataclasses.replace(CFG, exploration="fixed"))
    params = _init(CFG, key=7)
    rng = np.random.default_rng(14)
    B = 9
    prc = _spd(rng, dU, B)
    fin = fixed.finalize(params, make_sstep_data(rng.normal(size=(B, dX)), rng.normal(size=(B, dU)), prc))
    # a mean of B positive diagonals and a reciprocal in each program: c·(B + 1)·ε relative
    assert_close(fin.var, 1.0 / np.diag(prc.mean(axis=0)), 2 * linear_tol(1.0, B + 1))
    x = jnp.asarray(rng.normal(size=(4, dX)))
    np.testing.assert_allclose(fixed.cov(fin, x), np.broadcast_to(np.diag(fin.var), (4, dU, dU)))
    np.testing.assert_allclose(fixed.cov(fin, x[0]), np.diag(fin.var))
    # the default ("reflex") mode ignores var
    np.testing.assert_allclose(_fns(CFG).cov(fin, x), _fns(CFG).reflex(fin, x).cov)


@pytest.mark.parametrize("cfg", [CFG, RAW], ids=["normalized", "raw"])
def test_linearize_constant_reflex_is_exact(cfg):
    F = _fns(cfg)
    head = np.random.default_rng(15).normal(size=dU * dX + dU + NTRI)
    params = _zero_last(_with_norm(_init(cfg, key=8), seed=8), "translation", bias=head)
    x = jnp.asarray(np.random.default_rng(16).normal(size=(6, dX)) * 3.0)
    K, k = F.linearize(params, x)
    refl = F.reflex(params, x)
    # The Jacobian of a constant reflex is Ψ_K through a few products with the normalisation
    # (c·4·ε relative); k = u − K x then cancels: affine_tol (tests/tolerances.py).
    assert_close(K, refl.K, linear_tol(1.0, 4))
    assert_trees_within(k, refl.k, 2 * affine_tol(refl.K, x, refl.k))
    # Ψ_K, Ψ_k are constants: identical at every x (up to the rounding of the rows' few products)
    assert_close(refl.K, np.broadcast_to(refl.K[0], refl.K.shape), linear_tol(1.0, 4))


def test_linearize_general_against_finite_differences():
    F = _fns(CFG)
    params = _with_norm(_init(CFG, key=9), seed=9)
    x = jnp.asarray(np.random.default_rng(17).normal(size=dX))
    K, k = (a[0] for a in F.linearize(params, x[None]))
    h = 1e-6
    fd = np.stack([(F.mean(params, x + h * e) - F.mean(params, x - h * e)) / (2 * h)
                   for e in np.eye(dX)], axis=1)
    np.testing.assert_allclose(K, fd, rtol=1e-6, atol=1e-7)
    assert_trees_within(K @ x + k, F.mean(params, x), 2 * affine_tol(K, x, k))  # k = u − K x, then K x + k
    # the state-dependence of the Ψ's contributes: K differs from the generated Ψ_K
    assert np.abs(np.asarray(K - F.reflex(params, x).K)).max() > 1e-3


def test_jit_equals_no_jit_and_vmap_over_keys():
    gmr = make_gmr(CFG)
    pol = gmr.policy
    F = _fns(CFG)
    params = _with_norm(_init(CFG, key=10), seed=10)
    rng = np.random.default_rng(18)
    B = 6
    data = make_sstep_data(rng.normal(size=(B, dX)), rng.normal(size=(B, dU)), _spd(rng, dU, B),
                           K=rng.normal(size=(B, dU, dX)), k=rng.normal(size=(B, dU)),
                           state_cov=_spd(rng, dX, B))
    x = data.x[:2]
    key = jax.random.key(19)
    # eager (no jit) against the jitted functions; gmr_linearize is the public convenience form.
    # Tolerances from the computation (tests/tolerances.py): each jitted function rerun on
    # inputs perturbed by ε relative, SAFETY times the spread of each output.
    checks = ((pol.mean, F.mean, (params, x)), (pol.covariance, F.cov, (params, x)),
              (lambda p, d: pol.loss(p, d, key), lambda p, d: F.loss(p, d, key), (params, data)),
              (lambda p, xs: gmr_linearize(p, xs[1], CFG), lambda p, xs: tuple(a[1] for a in F.linearize(p, xs)),
               (params, x)))
    for eager_fn, jit_fn, args in checks:
        ref, tol = measured_tol(jit_fn, args, SAFETY)
        assert_tolerances_small(ref, tol, 1e-8)
        assert_trees_within(eager_fn(*args), ref, tol)
    # vmap over keys: initialisation and the (stochastic) loss equal the per-key results
    keys = jax.random.split(jax.random.key(20), 3)
    inits = jax.jit(jax.vmap(lambda k: pol.init(k, dX, dU)))(keys)
    for i in range(3):
        single = F.init(keys[i], dX, dU, None)
        for la, lb in zip(jax.tree_util.tree_leaves(inits), jax.tree_util.tree_leaves(single), strict=True):
            np.testing.assert_array_equal(la[i], lb)
    losses = jax.jit(jax.vmap(lambda k: pol.loss(params, data, k)[0]))(keys)
    for i, k in enumerate(keys):
        ref, tol = measured_tol(lambda p, d: F.loss(p, d, k)[0], (params, data), SAFETY)
        assert_trees_within(losses[i], ref, tol)
    assert len(set(np.round(np.asarray(losses), 10))) == 3  # the key drives the latent sample
    # vmap over a leading seed axis of the params
    means = jax.jit(jax.vmap(pol.mean, in_axes=(0, None)))(inits, x)
    ref, tol = measured_tol(F.mean, (F.init(keys[1], dX, dU, None), x), SAFETY)
    assert_trees_within(means[1], ref, tol)

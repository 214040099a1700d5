"""The Generative Motor Reflex (GMR) policy (paper §"Generative Motor Reflex"; gmr-method.md §3).

Architecture (sizes: ``GMRConfig``, decision §3.4), all hidden layers fully connected with a leaky
ReLU (slope 0.2):

    x̃ = x·scale + bias                       (statistics fixed at the first S-step)
    x̄ = c·tanh(x̃/c)                          (c = encoder_squash; x̄ = x̃ if c = 0)
    h_enc(x̄)  → (μ_z, log σ²_z)               [2·latent]
    z = μ_z + σ_z·ε (training),  z = μ_z (test time: ``mean``, ``covariance`` are deterministic)
    h_dec(z)   → x̂                           [dX], the reconstruction of x̄
    h_trans(z) → (G [dU·dX], g [dU], r [dU(dU+1)/2])

The bound x̄ is this project's deviation from the paper (GMRConfig.encoder_squash, default 1):
the robustness states lie 12–35 training standard deviations from the data, and an unbounded
encoder maps them to latents the translation network never saw; bounded, every state gets a
reflex generated from a familiar latent (benchmarks/RESULTS.md: 31.5 → 49.7 successes of 50 on A).

The motor reflex in raw state coordinates, π_Ψ(u | x) = N(Ψ_K x + Ψ_k, Ψ_Σ):

- ``head_coordinates="normalized"`` (default): the head acts on the standardised state,
  u = G x̃ + g, i.e. Ψ_K = G·diag(scale), Ψ_k = g + G·bias. This is the same function class as a
  head that emits Ψ_K, Ψ_k directly, but its outputs are of the size of actions (see GMRConfig).
  ``"raw"``: Ψ_K = G, Ψ_k = g.
- u(x) = Ψ_K(x)·x + Ψ_k(x) with the *raw* state x; the Ψ's depend on x only through z.
- Ψ_Σ = L Lᵀ, L = diag(σ)·R, R the unit lower-triangular V (V_ij = c·tanh(r_ij/c), i > j) with
  its rows scaled to unit norm, log σ_i = ½·log(init_var) + s·tanh(r_ii/s), s = log(cov_std_range)
  (``cholesky_factor``). L is lower triangular with a positive diagonal, so Ψ_Σ is positive
  definite by construction; σ_i is exactly the standard deviation of action entry i. Every entry
  is bounded, which bounds the condition number: far outside the training data (the robustness
  test's random initial states) the leaky-ReLU outputs grow linearly with the input, and an
  unbounded factor (softplus diagonal with a floor, free off-diagonals) makes L Lᵀ numerically
  singular there. This matters beyond sampling: MDGPS linearises the policy with this
  covariance, and the C-step factorises it. log|Ψ_Σ| = 2·Σ log L_ii exactly.

Exploration covariance (``covariance``): Ψ_Σ(x) with ``exploration="reflex"`` (the paper's reflex);
the authors' code sampled with a fixed diagonal variance instead, which ``exploration="fixed"``
selects: diag(var), var set by ``finalize`` with the toolbox's closed-form rule (as the MLP).
``params.var`` is kept up to date in both modes.

S-step loss (per datum, averaged over the minibatch; w the normalised weight, P the LQR
controller's precision Q_uu, batch.tgt_prc = w·P; ``sstep`` adds β·Σθ²):

    recon      = w·‖x̄ − h_dec(z)‖²                             (on the encoder's input)
    latent_kl  = w·½·Σ_j (μ_j² + σ_j² − log σ_j² − 1)              (weighted by α)
    action     = ½·Δuᵀ (wP) Δu,      Δu = Ψ_K x + Ψ_k − tgt_mu      (tgt_mu = K_p x + k_p)
    gain       = ½·tr(ΔKᵀ (wP) ΔK Σ_t),  ΔK = Ψ_K − K_p
    cov        = ½·[tr(wP Ψ_Σ) − w·(log|Ψ_Σ| + dU + log|P|)]

action + gain + cov = w·E_{x'~N(x, Σ_t)} KL(π_Ψ(·|x') ‖ p(·|x')) for a reflex held fixed at its
value at x (decision §3.5; the constants −dU − log|P⁻¹| are included, so ``cov`` is itself a
weighted Gaussian KL ≥ 0 and the sum is ≥ 0). The factor ½ is the one of the Gaussian KL, which
makes ``action`` the MLP's loss ½·Δuᵀ(wP)Δu: both policies train on the same scale. The paper
writes the reconstruction error unhalved, ‖x − x̂‖², and so do we; it is measured on the
standardised state x̃ so that every state entry counts alike whatever its unit. The offset Ψ_k is
supervised only through the actions (the appendix's Δk trick), the gain Ψ_K through its exact
contribution to the KL under the state covariance Σ_t.

The loss draws the latent noise as ε = jax.random.normal(key, [B, latent]) (one draw per row).
"""

from __future__ import annotations

import functools
import math
from typing import Any, NamedTuple

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

from gmr_jax.config import GMRConfig
from gmr_jax.policies.base import (Normalization, Policy, PolicyParams, SStepData, default_float,
                                   identity_normalization, normalize_input, target_logdet)
from gmr_jax.policies.mlp import closed_form_variance


Array = jax.Array


class LeakyMLP(nn.Module):
    """Fully connected network [..., d_in] -> [..., out]: leaky-ReLU hidden layers, linear output.

    Layers are named ``Dense_0 … Dense_{len(hidden)}``; weights start as Flax's lecun_normal,
    biases at zero (as the MLP's default).
    """

    hidden: tuple[int, ...]
    out: int
    negative_slope: float = 0.2
    param_dtype: Any = jnp.float32

    @nn.compact
    def __call__(self, x):
        for width in self.hidden:
            x = nn.leaky_relu(nn.Dense(width, param_dtype=self.param_dtype)(x), self.negative_slope)
        return nn.Dense(self.out, param_dtype=self.param_dtype)(x)


class GMRNet(nn.Module):
    """The three networks of GMR; their params live under "encoder", "decoder", "translation".

    ``__call__(x̃, ε)`` runs all three (used to initialise); the methods ``encode``, ``decode``,
    ``translate`` run one each.
    """

    dX: int
    dU: int
    latent: int
    encoder_hidden: tuple[int, ...]
    decoder_hidden: tuple[int, ...]
    translation_hidden: tuple[int, ...]
    negative_slope: float
    param_dtype: Any = jnp.float32

    def setup(self):
        kw = dict(negative_slope=self.negative_slope, param_dtype=self.param_dtype)
        self.encoder = LeakyMLP(self.encoder_hidden, 2 * self.latent, **kw)
        self.decoder = LeakyMLP(self.decoder_hidden, self.dX, **kw)
        self.translation = LeakyMLP(self.translation_hidden, head_size(self.dX, self.dU), **kw)

    def encode(self, xn):
        """x̃ [..., dX] -> (μ_z [..., latent], log σ²_z [..., latent])."""
        h = self.encoder(xn)
        return h[..., : self.latent], h[..., self.latent:]

    def decode(self, z):
        """z [..., latent] -> x̂ [..., dX] (standardised coordinates)."""
        return self.decoder(z)

    def translate(self, z):
        """z [..., latent] -> raw head output [..., dU·dX + dU + dU(dU+1)/2]."""
        return self.translation(z)

    def __call__(self, xn, eps):
        mu, logvar = self.encode(xn)
        z = mu + jnp.exp(0.5 * logvar) * eps
        return self.decode(z), self.translate(z)


def head_size(dX: int, dU: int) -> int:
    """Outputs of h_trans: dU·dX (gain) + dU (offset) + dU(dU+1)/2 (Cholesky factor)."""
    return dU * dX + dU + dU * (dU + 1) // 2


class MotorReflex(NamedTuple):
    """A generated motor reflex π_Ψ(u | x) = N(K x + k, cov), in raw state coordinates.

    Attributes:
      K: [..., dU, dX] Ψ_K.
      k: [..., dU] Ψ_k.
      cov: [..., dU, dU] Ψ_Σ = chol·cholᵀ (symmetric PD).
      chol: [..., dU, dU] lower-triangular factor of Ψ_Σ with positive diagonal.
      logdet: [...] log|Ψ_Σ|.
    """

    K: Array
    k: Array
    cov: Array
    chol: Array
    logdet: Array


class GMR(NamedTuple):
    """The GMR policy and its parts, all pure functions of (params, ...) for one configuration.

    Attributes:
      policy: the :class:`~gmr_jax.policies.base.Policy` (what the S-step and MDGPS use).
      encode: (params, x [..., dX]) -> (μ_z, log σ²_z) [..., latent]; x raw (normalised inside).
      decode: (params, z [..., latent]) -> x̂ [..., dX], the reconstruction of the standardised x̃.
      translate: (params, z [..., latent]) -> MotorReflex (raw coordinates).
      reflex: (params, x [..., dX]) -> MotorReflex at z = μ_z(x) (test time).
      action: (params, x [..., dX], z [..., latent]) -> u [..., dU], u = Ψ_K(z) x + Ψ_k(z).
      linearize: (params, x [dX]) -> (K [dU, dX], k [dU]), first-order expansion of ``mean``.
    """

    policy: Policy
    encode: Any
    decode: Any
    translate: Any
    reflex: Any
    action: Any
    linearize: Any


def _split_head(out: Array, dX: int, dU: int):
    """Raw head output [..., head_size] -> (G [..., dU, dX], g [..., dU], r [..., dU(dU+1)/2])."""
    nK = dU * dX
    G = out[..., :nK].reshape(out.shape[:-1] + (dU, dX))  # row-major, as the authors' Ψ_K
    return G, out[..., nK: nK + dU], out[..., nK + dU:]


def cholesky_factor(r: Array, dU: int, init_var: float, std_range: float, offdiag_bound: float):
    """Bounded Cholesky parameterisation of Ψ_Σ: r [..., dU(dU+1)/2] -> (L [..., dU, dU], log|L Lᵀ| [...]).

    r fills the lower triangle row by row (numpy's ``tril_indices`` order). V is unit lower
    triangular with V_ij = c·tanh(r_ij/c) (i > j, c = offdiag_bound); R = V with every row scaled
    to unit norm (R Rᵀ is a correlation matrix); L = diag(σ)·R with
    log σ_i = ½·log(init_var) + s·tanh(r_ii/s), s = log(std_range). So L is lower triangular with
    the positive diagonal σ_i/‖V_i‖, the standard deviations of Ψ_Σ = L Lᵀ are exactly σ, each
    within sqrt(init_var)·[1/std_range, std_range], and r = 0 gives Ψ_Σ = init_var·I.
    """
    rows, cols = np.tril_indices(dU)
    full = jnp.zeros(r.shape[:-1] + (dU, dU), r.dtype).at[..., rows, cols].set(r)
    s = math.log(std_range)
    log_sigma = 0.5 * math.log(init_var) + s * jnp.tanh(jnp.diagonal(full, axis1=-2, axis2=-1) / s)
    strict = jnp.tril(jnp.ones((dU, dU), dtype=bool), -1)
    V = jnp.where(strict, offdiag_bound * jnp.tanh(full / offdiag_bound), 0.0) + jnp.eye(dU, dtype=r.dtype)
    row_norm = jnp.sqrt(jnp.sum(jnp.square(V), axis=-1))  # ≥ 1: the diagonal of V is 1
    L = (jnp.exp(log_sigma) / row_norm)[..., :, None] * V
    return L, 2.0 * jnp.sum(log_sigma - jnp.log(row_norm), axis=-1)


def linearize_mean(mean_fn, params: PolicyParams, x: Array):
    """Exact first-order expansion of a policy mean u(x) at x [dX] -> (K [dU, dX], k [dU]).

    K = ∂u/∂x (forward-mode autodiff), k = u(x) − K x, so u(x') ≈ K x' + k near x. Vmappable
    over x (and over params).
    """
    def f(y):
        u = mean_fn(params, y)
        return u, u

    K, u = jax.jacfwd(f, has_aux=True)(x)  # one pass gives both the Jacobian and u(x)
    return K, u - K @ x


@functools.lru_cache(maxsize=None)
def make_gmr(cfg: GMRConfig = GMRConfig()) -> GMR:
    """All GMR functions for a configuration (cached: equal configurations give the same object)."""

    def module(dX: int, dU: int, dtype=jnp.float32) -> GMRNet:
        return GMRNet(dX=dX, dU=dU, latent=cfg.latent, encoder_hidden=tuple(cfg.encoder_hidden),
                      decoder_hidden=tuple(cfg.decoder_hidden),
                      translation_hidden=tuple(cfg.translation_hidden),
                      negative_slope=cfg.negative_slope, param_dtype=dtype)

    def dims(params: PolicyParams):
        return params.norm.scale.shape[-1], params.var.shape[-1]

    def apply(params: PolicyParams, method, *args):
        dX, dU = dims(params)
        return module(dX, dU).apply(params.net, *args, method=method)

    def init(key, dX: int, dU: int, dtype=None) -> PolicyParams:
        """Params: net (Flax weights of the three networks), identity normalisation, var [dU] = init_var."""
        dtype = default_float() if dtype is None else jnp.dtype(dtype)
        net = module(dX, dU, dtype).init(key, jnp.zeros((dX,), dtype), jnp.zeros((cfg.latent,), dtype))
        return PolicyParams(net=net, norm=identity_normalization(dX, dtype),
                            var=jnp.full((dU,), cfg.init_var, dtype))

    def encoder_input(norm: Normalization, x):
        """What h_enc sees: x̃, or c·tanh(x̃/c) with c = encoder_squash > 0 (bounded far away)."""
        xn = normalize_input(norm, x)
        c = cfg.encoder_squash
        return xn if c <= 0 else c * jnp.tanh(xn / c)

    def encode(params: PolicyParams, x):
        """x [..., dX] (raw) -> (μ_z, log σ²_z), each [..., latent]."""
        return apply(params, GMRNet.encode, encoder_input(params.norm, x))

    def decode(params: PolicyParams, z):
        """z [..., latent] -> x̂ [..., dX] (standardised coordinates)."""
        return apply(params, GMRNet.decode, z)

    def head(params: PolicyParams, z):
        """z [..., latent] -> (G [..., dU, dX], g [..., dU], L [..., dU, dU], logdet [...])."""
        dX, dU = dims(params)
        G, g, r = _split_head(apply(params, GMRNet.translate, z), dX, dU)
        L, logdet = cholesky_factor(r, dU, cfg.init_var, cfg.cov_std_range, cfg.cov_offdiag_bound)
        return G, g, L, logdet

    def to_raw(norm: Normalization, G, g):
        """Head gain/offset -> (Ψ_K, Ψ_k) in raw coordinates (see the module docstring)."""
        if cfg.head_coordinates == "raw":
            return G, g
        # u = G (x·scale + bias) + g = (G·diag(scale)) x + (g + G·bias)
        return G * norm.scale, g + jnp.einsum("...ij,j->...i", G, norm.bias)

    def head_input(norm: Normalization, x):
        """The state the head's gain multiplies: x̃ ("normalized") or x ("raw")."""
        return x if cfg.head_coordinates == "raw" else normalize_input(norm, x)

    def translate(params: PolicyParams, z) -> MotorReflex:
        """z [..., latent] -> the motor reflex (Ψ_K, Ψ_k, Ψ_Σ) in raw coordinates."""
        G, g, L, logdet = head(params, z)
        K, k = to_raw(params.norm, G, g)
        return MotorReflex(K=K, k=k, cov=L @ jnp.swapaxes(L, -1, -2), chol=L, logdet=logdet)

    def reflex(params: PolicyParams, x) -> MotorReflex:
        """x [..., dX] -> the test-time motor reflex, generated at z = μ_z(x)."""
        mu, _ = encode(params, x)
        return translate(params, mu)

    def action(params: PolicyParams, x, z):
        """u = Ψ_K(z) x + Ψ_k(z): x [..., dX] (raw), z [..., latent] -> [..., dU]."""
        G, g, _, _ = head(params, z)
        # Evaluated in the head's coordinates (G x̃ + g), identical to Ψ_K x + Ψ_k but free of
        # the cancellation between a large Ψ_K x and Ψ_k.
        return jnp.einsum("...ij,...j->...i", G, head_input(params.norm, x)) + g

    def mean(params: PolicyParams, x):
        """Deterministic action (z = μ_z): x [..., dX] -> u [..., dU]."""
        mu, _ = encode(params, x)
        return action(params, x, mu)

    def covariance(params: PolicyParams, x):
        """Exploration covariance [..., dU, dU]: Ψ_Σ(x) at z = μ_z ("reflex") or diag(var) ("fixed")."""
        if cfg.exploration == "fixed":
            dU = params.var.shape[-1]
            return jnp.broadcast_to(jnp.diag(params.var), x.shape[:-1] + (dU, dU))
        return reflex(params, x).cov

    def loss(params: PolicyParams, batch: SStepData, key):
        """GMR S-step data term on a minibatch of B rows (module docstring); key: latent noise.

        Returns (recon + α·latent_kl + action + gain + cov, aux) with aux the five terms (batch
        means, as they enter the sum except for α) and ``action_mse`` = mean (u − tgt_mu)².
        """
        norm = params.norm
        xn = encoder_input(norm, batch.x)  # also the reconstruction target
        mu, logvar = apply(params, GMRNet.encode, xn)
        eps = jax.random.normal(key, mu.shape, mu.dtype)
        z = mu + jnp.exp(0.5 * logvar) * eps
        xhat = decode(params, z)
        G, g, L, logdet = head(params, z)
        K, _ = to_raw(norm, G, g)
        u = jnp.einsum("bij,bj->bi", G, head_input(norm, batch.x)) + g

        w = batch.wt
        P = batch.tgt_prc  # = w·P_lqr
        dU = u.shape[-1]
        recon = jnp.mean(w * jnp.sum(jnp.square(xn - xhat), axis=-1))
        latent_kl = jnp.mean(w * 0.5 * jnp.sum(jnp.square(mu) + jnp.exp(logvar) - logvar - 1.0, axis=-1))
        du = u - batch.tgt_mu
        action_term = 0.5 * jnp.mean(jnp.einsum("bi,bij,bj->b", du, P, du))
        dK = K - batch.K
        PdK = jnp.einsum("bij,bjx->bix", P, dK)
        gain = 0.5 * jnp.mean(jnp.einsum("biy,bix,bxy->b", dK, PdK, batch.state_cov))
        # tr(wP L Lᵀ) and the constants of the Gaussian KL; log|P| of the unweighted precision
        # (identity on zero-weight rows, whose term is multiplied by w = 0 anyway).
        tr = jnp.einsum("bij,bjk,bik->b", P, L, L)
        if batch.tgt_logdet is None:
            P_unw = P / jnp.where(w > 0, w, 1.0)[:, None, None]
            logdet_P = target_logdet(P_unw, w)
        else:
            logdet_P = batch.tgt_logdet
        cov = 0.5 * jnp.mean(tr - w * (logdet + dU + logdet_P))

        value = recon + cfg.alpha * latent_kl + action_term + gain + cov
        aux = {"recon": recon, "latent_kl": latent_kl, "action": action_term, "gain": gain,
               "cov": cov, "action_mse": jnp.mean(jnp.square(du))}
        return value, aux

    def finalize(params: PolicyParams, data: SStepData) -> PolicyParams:
        """Closed-form variance var = 1/diag(weighted mean precision + 2·ent_reg) (as the MLP)."""
        var = closed_form_variance(data.tgt_prc, data.wt, cfg.ent_reg)
        return params._replace(var=var.astype(params.var.dtype))

    def linearize(params: PolicyParams, x):
        """x [dX] -> (K [dU, dX], k [dU]): exact first-order expansion of u(x) = Ψ_K(x) x + Ψ_k(x)."""
        return linearize_mean(mean, params, x)

    policy = Policy(init=init, mean=mean, covariance=covariance, loss=loss, finalize=finalize)
    return GMR(policy=policy, encode=encode, decode=decode, translate=translate, reflex=reflex,
               action=action, linearize=linearize)


def make_gmr_policy(cfg: GMRConfig = GMRConfig()) -> Policy:
    """The GMR policy for a configuration (the hook of ``gmr_jax.policies.make_policy``)."""
    return make_gmr(cfg).policy


def gmr_linearize(params: PolicyParams, x: Array, cfg: GMRConfig = GMRConfig()):
    """Exact first-order expansion of the GMR action at x [dX] -> (K [dU, dX], k [dU]).

    K = ∂u/∂x of u(x) = Ψ_K(x)·x + Ψ_k(x) (autodiff, including the dependence of the Ψ's on x),
    k = u(x) − K x. Vmappable over x (e.g. the T mean states) and over params.
    """
    return make_gmr(cfg).linearize(params, x)

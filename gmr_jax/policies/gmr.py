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
reflex generated from a familiar latent (benchmarks/RESULTS.md, 32 seeds: 37.7 → 48.3 successes of
50 on A, 40.0 → 50.0 on A,B; the Jaco's torque limit is not why: without it, 38.1 and 41.6).

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
from types import SimpleNamespace
from typing import Any, NamedTuple

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

from gmr_jax.config import GMRConfig
from gmr_jax.policies import gmr_cuda, gmr_kernel
from gmr_jax.policies.base import (Normalization, Policy, PolicyParams, SStepData, TrainingForm,
                                   column_blocks, default_float, dense_chain, dense_entries, dense_layout,
                                   dense_stack, dense_value_and_grad, flax_dense_layers, flax_dense_params,
                                   identity_normalization, join_columns, normalize_input, pack_dense,
                                   pack_rows, reduced_products, small_product, split_columns, squash,
                                   symmetrize, target_logdet, unpack_dense, unpack_rows)
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


class LossRows(NamedTuple):
    """The per-datum constants of the GMR loss (shapes per row; a batch adds a leading axis).

    Attributes:
      xn: [dX] the encoder's input x̄ = c·tanh(x̃/c), also the reconstruction target.
      xh: [dX] the state the head's gain multiplies (x̃, or x for ``head_coordinates="raw"``).
      tgt_mu: [dU] target action.
      prc: [dU, dU] weighted target precision w·P.
      K: [dU, dX] the local controller's gain K_p.
      state_cov: [dX, dX] Σ_t.
      wt: [] the normalised weight w.
      logdet: [] log|P| of the unweighted precision (0 on zero-weight rows).
    """

    xn: Array
    xh: Array
    tgt_mu: Array
    prc: Array
    K: Array
    state_cov: Array
    wt: Array
    logdet: Array


class FusedRows(NamedTuple):
    """The per-datum constants of the GMR loss in the S-step's packed form (``fused_head``).

    Attributes:
      xn: [dX] the encoder's input x̄, also the reconstruction target.
      xs: [dX, 1 + dX] the head's input x̃ (or x) beside Σ_t: [xh | Σ_t] (Σ_t symmetrised).
      tgt_mu: [dU] target action.
      prc: [dU, dU] w·P, symmetrised.
      K: [dU, dX] the local controller's gain K_p.
      wt: [] the normalised weight w.
      logdet: [] log|P| of the unweighted precision.

    The gradients of ``fused_head`` assume symmetric matrices. Symmetrising, ½(A + Aᵀ), changes
    nothing for a symmetric A (precisions and covariances are symmetric), and the loss's terms
    see only the symmetric part of P when Σ_t is symmetric, and the other way round.
    """

    xn: Array
    xs: Array
    tgt_mu: Array
    prc: Array
    K: Array
    wt: Array
    logdet: Array


def _fused_head_fwd(init_var, std_range, offdiag_bound, reduced, G, g, full, scale, xs, tgt_mu, prc, K):
    dU, dX = G.shape[-2:]
    L, logdet, (T, V, row_norm, sigma, t) = _cholesky_parts(full, init_var, std_range, offdiag_bound)
    dK = G * scale - K
    # one product gives G x̃ (first column of the top half) and ΔK Σ (the rest of the bottom half)
    C1 = small_product(jnp.concatenate([G, dK], axis=-2), xs, reduced)
    du = C1[..., :dU, 0] + g - tgt_mu
    # one product gives P Δu, P ΔK Σ and P L
    C2 = small_product(prc, jnp.concatenate([du[..., None], C1[..., dU:, 1:], L], axis=-1), reduced)
    Pdu, PdKS, PL = C2[..., 0], C2[..., 1: 1 + dX], C2[..., 1 + dX:]
    action = jnp.sum(du * Pdu, axis=-1)
    gain = jnp.sum(dK * PdKS, axis=(-2, -1))
    tr_rows = jnp.sum(L * PL, axis=-1)
    out = (action, gain, jnp.sum(tr_rows, axis=-1), logdet, du)
    return out, (Pdu, PdKS, PL, tr_rows, xs[..., 0], scale, T, V, row_norm, sigma, t)


def _fused_head_bwd(init_var, std_range, offdiag_bound, reduced, res, cts):
    Pdu, PdKS, PL, tr_rows, xh, scale, T, V, row_norm, sigma, t = res
    ct_action, ct_gain, ct_tr, ct_logdet, ct_du = cts
    dU = V.shape[-1]
    # P and Σ_t symmetric: ∂action/∂Δu = 2 P Δu, ∂gain/∂ΔK = 2 P ΔK Σ, ∂tr/∂L = 2 P L
    g_du = (2.0 * ct_action)[..., None] * Pdu + ct_du
    g_G = g_du[..., :, None] * xh[..., None, :] + ((2.0 * ct_gain)[..., None, None] * PdKS) * scale
    g_L = (2.0 * ct_tr)[..., None, None] * PL
    # L_ij = σ_i V_ij/n_i, n_i = ‖V_i‖, logdet = 2 Σ_i (log σ_i − log n_i):
    #   ∂/∂log σ_i = Σ_j g_L,ij L_ij + 2·ct_logdet =: q_i (Σ_j g_L,ij L_ij = 2·ct_tr·tr_rows_i),
    #   ∂/∂V_ij = (σ_i/n_i)·g_L,ij − q_i·V_ij/n_i²,
    # then through log σ_i = ½ log(init_var) + s·tanh(r_ii/s) and V_ij = c·tanh(r_ij/c).
    q = (2.0 * ct_tr)[..., None] * tr_rows + (2.0 * ct_logdet)[..., None]
    g_V = (sigma / row_norm)[..., :, None] * g_L - (q / jnp.square(row_norm))[..., :, None] * V
    strict = jnp.tril(jnp.ones((dU, dU), dtype=bool), -1)
    eye = jnp.eye(dU, dtype=bool)
    g_full = jnp.where(strict, g_V * (1.0 - jnp.square(T)),
                       jnp.where(eye, (q * (1.0 - jnp.square(t)))[..., :, None], 0.0))
    return g_G, g_du, g_full, None, None, None, None, None


@functools.partial(jax.custom_vjp, nondiff_argnums=(0, 1, 2, 3))
def fused_head(init_var: float, std_range: float, offdiag_bound: float, reduced: bool, G, g, full, scale, xs,
               tgt_mu, prc, K):
    """The controller terms of the GMR loss per row from the packed head, with two batched
    products and a gradient in closed form (no product and no reduction in the backward pass).

    Args:
      init_var, std_range, offdiag_bound: the parameters of ``cholesky_factor``.
      reduced: the two products as sums of broadcast products (``base.small_product``).
      G: [b, dU, dX], g: [b, dU] the head's gain and offset; full: [b, dU, dU] the Cholesky
        entries r as a lower triangle (``cholesky_from_square``).
      scale: [dX] Ψ_K = G·diag(scale) (ones for raw head coordinates).
      xs, tgt_mu, prc, K: the FusedRows fields of the minibatch (prc and Σ_t symmetric).
    Returns:
      (action [b] = Δuᵀ P Δu, gain [b] = tr(ΔKᵀ P ΔK Σ_t), tr [b] = tr(P L Lᵀ),
       logdet [b] = log|L Lᵀ|, Δu [b, dU]) with Δu = G x̃ + g − tgt_mu, ΔK = G·diag(scale) − K_p:
      ``quadratics`` (the loss's einsums) and ``cholesky_factor`` summed in another order.
    """
    return _fused_head_fwd(init_var, std_range, offdiag_bound, reduced, G, g, full, scale, xs, tgt_mu, prc, K)[0]


fused_head.defvjp(_fused_head_fwd, _fused_head_bwd)


def _reparameterize_fwd(h, eps):
    latent = eps.shape[-1]
    mu, logvar = h[..., :latent], h[..., latent:]
    std, var = jnp.exp(0.5 * logvar), jnp.exp(logvar)
    kl = jnp.sum(jnp.square(mu) + var - logvar - 1.0, axis=-1)
    return (mu + std * eps, kl), (mu, std, var, eps)


def _reparameterize_bwd(res, cts):
    mu, std, var, eps = res
    ct_z, ct_kl = cts
    ct_kl = ct_kl[..., None]
    g_mu = ct_z + ct_kl * (2.0 * mu)
    g_logvar = ct_z * eps * (0.5 * std) + ct_kl * (var - 1.0)
    return jnp.concatenate([g_mu, g_logvar], axis=-1), None


@jax.custom_vjp
def reparameterize(h, eps):
    """The latent sample and the latent term with their gradient in one elementwise step.

    Args: h [b, 2·latent] the encoder's output (μ_z, log σ²_z); eps [b, latent] the noise.
    Returns: (z [b, latent] = μ + exp(½ log σ²)·ε, kl [b] = Σ_j (μ_j² + σ_j² − log σ_j² − 1)),
      computed as ``loss`` computes them; the gradient is autodiff's, written out (one kernel
      instead of three in the S-step's loop).
    """
    return _reparameterize_fwd(h, eps)[0]


reparameterize.defvjp(_reparameterize_fwd, _reparameterize_bwd)


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
    """Raw head output [..., head_size] -> (G [..., dU, dX], g [..., dU], r [..., dU(dU+1)/2])
    (for the packed head [..., packed_head_size], r holds the square's dU² entries)."""
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
    full = jnp.zeros(r.shape[:-1] + (dU, dU), r.dtype).at[..., rows, cols].set(r, unique_indices=True)
    return cholesky_from_square(full, init_var, std_range, offdiag_bound)


def cholesky_from_square(full: Array, init_var: float, std_range: float, offdiag_bound: float):
    """``cholesky_factor`` with r given as the lower triangle of full [..., dU, dU] (the entries
    above the diagonal are not read) -> (L [..., dU, dU], log|L Lᵀ| [...])."""
    L, logdet, _ = _cholesky_parts(full, init_var, std_range, offdiag_bound)
    return L, logdet


def _cholesky_parts(full: Array, init_var: float, std_range: float, offdiag_bound: float):
    """``cholesky_from_square`` and the intermediate values its gradient needs:
    (L, logdet, (T [..., dU, dU] = tanh(full/c), V, row_norm [..., dU], σ [..., dU],
    t [..., dU] = tanh(r_ii/s)))."""
    dU = full.shape[-1]
    s = math.log(std_range)
    # the diagonal as a strided slice of the flattened square (jnp.diagonal is a gather, one more
    # kernel in the S-step's loop; a slice fuses into its consumers)
    t = jnp.tanh(full.reshape(full.shape[:-2] + (dU * dU,))[..., :: dU + 1] / s)
    log_sigma = 0.5 * math.log(init_var) + s * t
    strict = jnp.tril(jnp.ones((dU, dU), dtype=bool), -1)
    T = jnp.tanh(full / offdiag_bound)
    V = jnp.where(strict, offdiag_bound * T, 0.0) + jnp.eye(dU, dtype=full.dtype)
    row_norm = jnp.sqrt(jnp.sum(jnp.square(V), axis=-1))  # ≥ 1: the diagonal of V is 1
    sigma = jnp.exp(log_sigma)
    L = (sigma / row_norm)[..., :, None] * V
    return L, 2.0 * jnp.sum(log_sigma - jnp.log(row_norm), axis=-1), (T, V, row_norm, sigma, t)


def packed_head_size(dX: int, dU: int) -> int:
    """Outputs of h_trans in the S-step's layout: dU·dX (gain) + dU (offset) + dU² (the Cholesky
    entries r as the lower triangle of a square, zeros above it)."""
    return dU * dX + dU + dU * dU


def head_columns(dX: int, dU: int) -> np.ndarray:
    """For each column of the packed head (``packed_head_size``), the column of the head
    (``head_size``) it holds, or -1 for the always-zero entries above the diagonal.

    The square layout needs no scatter to build the Cholesky factor inside the S-step's loop.
    """
    n = dU * dX + dU
    rows, cols = np.tril_indices(dU)
    src = np.full(packed_head_size(dX, dU), -1)
    src[:n] = np.arange(n)
    src[n + rows * dU + cols] = n + np.arange(len(rows))
    return src


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
    net = _network_functions(cfg)
    reflexes = _reflex_functions(cfg, net)
    terms = _loss_functions(cfg, net)
    training = _training_form(cfg, net, terms, _packing(cfg, net))

    def finalize(params: PolicyParams, data: SStepData) -> PolicyParams:
        """Closed-form variance var = 1/diag(weighted mean precision + 2·ent_reg) (as the MLP)."""
        var = closed_form_variance(data.tgt_prc, data.wt, cfg.ent_reg)
        return params._replace(var=var.astype(params.var.dtype))

    def linearize(params: PolicyParams, x):
        """x [dX] -> (K [dU, dX], k [dU]): exact first-order expansion of u(x) = Ψ_K(x) x + Ψ_k(x)."""
        return linearize_mean(reflexes.mean, params, x)

    def kernel_form(fit):
        def kernel(params: PolicyParams, train: SStepData, idx, noise, c1, c2, scfg):
            """Policy.kernel / Policy.cuda: the S-step's Adam loop as one GPU kernel (``fit``)."""
            net, stats = fit(cfg, scfg, params, terms.loss_rows(params, train), idx, noise, c1, c2)
            per_step = dict(zip(gmr_kernel.STATS, stats.T))
            return net, (per_step.pop("total"), per_step.pop("value"), per_step)
        return kernel

    policy = Policy(init=net.init, mean=reflexes.mean, covariance=reflexes.covariance, loss=terms.loss,
                    finalize=finalize, training=training, kernel=kernel_form(gmr_kernel.fit),
                    cuda=kernel_form(gmr_cuda.fit))
    return GMR(policy=policy, encode=net.encode, decode=net.decode, translate=reflexes.translate,
               reflex=reflexes.reflex, action=reflexes.action, linearize=linearize)


def _network_functions(cfg: GMRConfig) -> SimpleNamespace:
    """The three networks (Flax) and their inputs: module, dims, apply, init, encoder_input,
    encode, decode, head, to_raw, head_input."""

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
        return squash(normalize_input(norm, x), cfg.encoder_squash)

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

    return SimpleNamespace(module=module, dims=dims, apply=apply, init=init, encoder_input=encoder_input, encode=encode, decode=decode, head=head, to_raw=to_raw, head_input=head_input)


def _reflex_functions(cfg: GMRConfig, net: SimpleNamespace) -> SimpleNamespace:
    """The motor reflex and the actions: translate, reflex, action, mean, covariance."""

    def translate(params: PolicyParams, z) -> MotorReflex:
        """z [..., latent] -> the motor reflex (Ψ_K, Ψ_k, Ψ_Σ) in raw coordinates."""
        G, g, L, logdet = net.head(params, z)
        K, k = net.to_raw(params.norm, G, g)
        return MotorReflex(K=K, k=k, cov=L @ jnp.swapaxes(L, -1, -2), chol=L, logdet=logdet)

    def reflex(params: PolicyParams, x) -> MotorReflex:
        """x [..., dX] -> the test-time motor reflex, generated at z = μ_z(x)."""
        mu, _ = net.encode(params, x)
        return translate(params, mu)

    def action(params: PolicyParams, x, z):
        """u = Ψ_K(z) x + Ψ_k(z): x [..., dX] (raw), z [..., latent] -> [..., dU]."""
        G, g, _, _ = net.head(params, z)
        # Evaluated in the head's coordinates (G x̃ + g), identical to Ψ_K x + Ψ_k but free of
        # the cancellation between a large Ψ_K x and Ψ_k.
        return jnp.einsum("...ij,...j->...i", G, net.head_input(params.norm, x)) + g

    def mean(params: PolicyParams, x):
        """Deterministic action (z = μ_z): x [..., dX] -> u [..., dU]."""
        mu, _ = net.encode(params, x)
        return action(params, x, mu)

    def covariance(params: PolicyParams, x):
        """Exploration covariance [..., dU, dU]: Ψ_Σ(x) at z = μ_z ("reflex") or diag(var) ("fixed")."""
        if cfg.exploration == "fixed":
            dU = params.var.shape[-1]
            return jnp.broadcast_to(jnp.diag(params.var), x.shape[:-1] + (dU, dU))
        return reflex(params, x).cov

    return SimpleNamespace(translate=translate, reflex=reflex, action=action, mean=mean, covariance=covariance)


def _loss_functions(cfg: GMRConfig, net: SimpleNamespace) -> SimpleNamespace:
    """The S-step's loss and its pieces: noise, loss_rows, quadratics, combine, loss."""

    def noise(key, n: int, dtype):
        """The latent noise ε [n, latent] of a minibatch of n rows (one standard normal draw)."""
        return jax.random.normal(key, (n, cfg.latent), dtype)

    def loss_rows(params: PolicyParams, data: SStepData) -> LossRows:
        """The loss's per-datum constants of ``data`` [B rows] (``data.tgt_prc`` = w·P)."""
        norm, w = params.norm, data.wt
        if data.tgt_logdet is None:
            # log|P| of the unweighted precision (identity on zero-weight rows, whose term is
            # multiplied by w = 0 anyway)
            logdet_P = target_logdet(data.tgt_prc / jnp.where(w > 0, w, 1.0)[:, None, None], w)
        else:
            logdet_P = data.tgt_logdet
        return LossRows(xn=net.encoder_input(norm, data.x), xh=net.head_input(norm, data.x), tgt_mu=data.tgt_mu,
                        prc=data.tgt_prc, K=data.K, state_cov=data.state_cov, wt=w, logdet=logdet_P)

    def quadratics(norm: Normalization, rows: LossRows, G, g, L):
        """The controller terms per row, written out as einsums (``loss``'s definition).

        Args: rows (LossRows of [b, ...]); G [b, dU, dX]; g [b, dU]; L [b, dU, dU].
        Returns (action [b] = Δuᵀ(wP)Δu, gain [b] = tr(ΔKᵀ(wP)ΔK Σ_t), tr [b] = tr(wP L Lᵀ),
        Δu [b, dU]), as ``fused_head`` (the loss takes half of each).
        """
        K, _ = net.to_raw(norm, G, g)
        du = jnp.einsum("bij,bj->bi", G, rows.xh) + g - rows.tgt_mu
        P = rows.prc  # = w·P_lqr
        action = jnp.einsum("bi,bij,bj->b", du, P, du)
        dK = K - rows.K
        PdK = jnp.einsum("bij,bjx->bix", P, dK)
        gain = jnp.einsum("biy,bix,bxy->b", dK, PdK, rows.state_cov)
        tr = jnp.einsum("bij,bjk,bik->b", P, L, L)
        return action, gain, tr, du

    halved = ("action", "gain", "cov")  # ½ of a batch mean: the factor of the Gaussian KL

    def combine(rows, kl, xhat, logdet, action, gain, tr, du, stacked: bool = False):
        """The loss and its aux dict from a minibatch's per-row pieces.

        Args: rows (LossRows or FusedRows of [b, ...]: xn, wt, logdet); kl [b] the latent term
          Σ_j (μ_j² + σ_j² − log σ_j² − 1); xhat [b, dX]; logdet [b] of Ψ_Σ; action, gain, tr [b]
          and du [b, dU] (``quadratics``);
          stacked: take all batch means as one reduction of the stacked per-row terms (the
          packed form: one kernel instead of six; ``action_mse`` then averages each row first,
          the same mean summed in another order) instead of one mean per term (``loss``).
        """
        w = rows.wt
        dU = du.shape[-1]
        per_row = {
            "recon": w * jnp.sum(jnp.square(rows.xn - xhat), axis=-1),
            "latent_kl": w * 0.5 * kl,
            "action": action,
            "gain": gain,
            # tr(wP L Lᵀ) and the constants of the Gaussian KL
            "cov": tr - w * (logdet + dU + rows.logdet),
            "action_mse": jnp.square(du),
        }
        if stacked:
            per_row["action_mse"] = jnp.mean(per_row["action_mse"], axis=-1)
            means = dict(zip(per_row, jnp.mean(jnp.stack(list(per_row.values()), axis=-1), axis=0)))
        else:
            means = {name: jnp.mean(v) for name, v in per_row.items()}
        aux = {name: 0.5 * m if name in halved else m for name, m in means.items()}
        value = aux["recon"] + cfg.alpha * aux["latent_kl"] + aux["action"] + aux["gain"] + aux["cov"]
        return value, aux

    def loss(params: PolicyParams, batch: SStepData, key):
        """GMR S-step data term on a minibatch of B rows (module docstring); key: latent noise.

        Returns (recon + α·latent_kl + action + gain + cov, aux) with aux the five terms (batch
        means, as they enter the sum except for α) and ``action_mse`` = mean (u − tgt_mu)².
        """
        rows = loss_rows(params, batch)
        mu, logvar = net.apply(params, GMRNet.encode, rows.xn)
        z = mu + jnp.exp(0.5 * logvar) * noise(key, mu.shape[0], mu.dtype)
        G, g, L, logdet = net.head(params, z)
        kl = jnp.sum(jnp.square(mu) + jnp.exp(logvar) - logvar - 1.0, axis=-1)
        return combine(rows, kl, net.decode(params, z), logdet, *quadratics(params.norm, rows, G, g, L))

    return SimpleNamespace(noise=noise, loss_rows=loss_rows, quadratics=quadratics, combine=combine, loss=loss)


def _packing(cfg: GMRConfig, net: SimpleNamespace) -> SimpleNamespace:
    """The dense layout of the S-step's packed form and the map between it and the Flax weights:
    n_enc, n_dec, n_trans, slot_order, layout, network_order, pack, unpack.

    Slots of the dense layout: the encoder's layers, then the decoder's and the translation
    network's. Both read z; with equal depths they run side by side (one batched product per
    layer, slots interleaved layer by layer), otherwise one after the other. The translation
    network's last layer emits the packed head (head_columns); as it is wider than every other
    layer, it is held as column blocks as wide as the widest other layer (``head_parts`` slots,
    ``column_blocks``), so that the other slots carry little padding.
    """
    n_enc = len(cfg.encoder_hidden) + 1
    n_dec = len(cfg.decoder_hidden) + 1
    n_trans = len(cfg.translation_hidden) + 1
    side_by_side = n_dec == n_trans

    def slot_order(enc, dec, trans, side_by_side):
        """Per-network lists of slots (the translation network's last layer as its column blocks)
        -> the list in slot order."""
        if not side_by_side:
            return enc + dec + trans
        pairs = [a for pair in zip(dec[:-1], trans[: n_trans - 1]) for a in pair]
        return enc + pairs + [dec[-1]] + trans[n_trans - 1:]

    def network_order(slots, side_by_side):
        """The inverse of slot_order: slots -> (enc, dec, trans) lists of slots."""
        enc, rest = slots[:n_enc], slots[n_enc:]
        if side_by_side:
            k = 2 * (n_dec - 1)
            return enc, rest[0:k:2] + [rest[k]], rest[1:k:2] + rest[k + 1:]
        return enc, rest[:n_dec], rest[n_dec:]

    def chains(dX: int, dU: int):
        """(enc, dec, trans) lists of (fan_in, fan_out), the head as its column blocks."""
        enc = dense_chain(dX, cfg.encoder_hidden, 2 * cfg.latent)
        dec = dense_chain(cfg.latent, cfg.decoder_hidden, dX)
        trans = dense_chain(cfg.latent, cfg.translation_hidden, packed_head_size(dX, dU))
        width = max(fan_out for _, fan_out in enc + dec + trans[:-1])
        return enc, dec, trans[:-1] + column_blocks(trans[-1], width)

    def layout(dX: int, dU: int):
        """(DenseLayout, side_by_side) for a state of dX and an action of dU entries."""
        return dense_layout(slot_order(*chains(dX, dU), side_by_side)), side_by_side

    def head_blocks(dX: int, dU: int):
        """The (fan_in, fan_out) of the translation network's last layer's slots."""
        return chains(dX, dU)[2][n_trans - 1:]

    def head_parts(dX: int, dU: int) -> int:
        """The slots of the translation network's last layer."""
        return len(head_blocks(dX, dU))

    def pack(params: PolicyParams):
        """params.net (Flax) -> θ [S·(I+1)·O], the S-step's flat weight vector."""
        dX, dU = net.dims(params)
        lay, side = layout(dX, dU)
        weights = params.net["params"]
        enc, dec, trans = (flax_dense_layers(weights[name], n) for name, n in
                           (("encoder", n_enc), ("decoder", n_dec), ("translation", n_trans)))
        src = head_columns(dX, dU)
        square = lambda a: jnp.where(src >= 0, a[..., np.maximum(src, 0)], 0)  # noqa: E731
        head = tuple(square(a) for a in trans[-1])
        trans = trans[:-1] + split_columns(head, head_blocks(dX, dU))
        return pack_dense(lay, slot_order(enc, dec, trans, side)).reshape(-1)

    def unpack(params: PolicyParams, theta):
        """θ -> params.net (Flax), the inverse of ``pack``."""
        dX, dU = net.dims(params)
        lay, side = layout(dX, dU)
        enc, dec, trans = network_order(unpack_dense(lay, theta.reshape(lay.array_shape)), side)
        src = head_columns(dX, dU)
        cols = np.argsort(np.where(src >= 0, src, len(src)))[: head_size(dX, dU)]  # head col -> packed col
        head = join_columns(trans[n_trans - 1:])
        trans = trans[: n_trans - 1] + [tuple(a[..., cols] for a in head)]
        return {"params": {"encoder": flax_dense_params(enc), "decoder": flax_dense_params(dec),
                           "translation": flax_dense_params(trans)}}

    return SimpleNamespace(n_enc=n_enc, n_dec=n_dec, n_trans=n_trans, slot_order=slot_order, layout=layout,
                           head_parts=head_parts, network_order=network_order, pack=pack, unpack=unpack)


def _training_form(cfg: GMRConfig, net: SimpleNamespace, terms: SimpleNamespace,
                   packing: SimpleNamespace) -> TrainingForm:
    """The S-step's packed form (TrainingForm): the same loss, fewer operations per step."""

    def fused_rows(params: PolicyParams, data: SStepData) -> FusedRows:
        """The packed form's per-datum constants of ``data`` [B rows]."""
        r = terms.loss_rows(params, data)
        return FusedRows(xn=r.xn, xs=jnp.concatenate([r.xh[..., None], symmetrize(r.state_cov)], axis=-1),
                         tgt_mu=r.tgt_mu, prc=symmetrize(r.prc), K=r.K, wt=r.wt, logdet=r.logdet)

    def row_shapes(dX: int, dU: int) -> FusedRows:
        return FusedRows(xn=(dX,), xs=(dX, 1 + dX), tgt_mu=(dU,), prc=(dU, dU), K=(dU, dX), wt=(), logdet=())

    def packed_loss(params: PolicyParams, W, rows: FusedRows, eps, deltas):
        """``loss`` on the packed weights W [S, I+1, O] with ``deltas`` added to the
        pre-activations (see dense_value_and_grad) -> (value, (aux, inputs [S, b, I]))."""
        dX, dU = net.dims(params)
        lay, side = packing.layout(dX, dU)
        act = functools.partial(nn.leaky_relu, negative_slope=cfg.negative_slope)
        parts = packing.head_parts(dX, dU)
        enc, inputs = dense_stack(W, lay, 0, 1, packing.n_enc, rows.xn, act, deltas)
        z, kl = reparameterize(enc[0][:, : 2 * cfg.latent], eps)
        if side:
            out, dt_inputs = dense_stack(W, lay, packing.n_enc, 2, packing.n_dec, z, act, deltas, (1, parts))
            xhat, out_head, inputs = out[0], out[1], [inputs, dt_inputs]
        else:
            dec, dec_inputs = dense_stack(W, lay, packing.n_enc, 1, packing.n_dec, z, act, deltas)
            trans, trans_inputs = dense_stack(W, lay, packing.n_enc + packing.n_dec, 1, packing.n_trans, z, act,
                                              deltas, (parts,))
            xhat, out_head, inputs = dec[0], trans[0], [inputs, dec_inputs, trans_inputs]
        G, g, square = _split_head(out_head[:, : packed_head_size(dX, dU)], dX, dU)
        scale = jnp.ones_like(params.norm.scale) if cfg.head_coordinates == "raw" else params.norm.scale
        action, gain, tr, logdet, du = fused_head(
            cfg.init_var, cfg.cov_std_range, cfg.cov_offdiag_bound, reduced_products(), G, g,
            square.reshape(square.shape[:-1] + (dU, dU)), scale, rows.xs, rows.tgt_mu, rows.prc, rows.K)
        value, aux = terms.combine(rows, kl, xhat[:, :dX], logdet, action, gain, tr, du, stacked=True)
        return value, (aux, jnp.concatenate(inputs, axis=0))

    def packed_value_and_grad(params: PolicyParams, theta, rows, eps):
        """TrainingForm.value_and_grad: θ, rows [b, F], ε [b, latent] -> ((value, aux), grad)."""
        dX, dU = net.dims(params)
        lay, _ = packing.layout(dX, dU)
        W = theta.reshape(lay.array_shape)
        batch = unpack_rows(rows, row_shapes(dX, dU))
        (value, aux), grad = dense_value_and_grad(lambda d: packed_loss(params, W, batch, eps, d), W,
                                                  rows.shape[0])
        return (value, aux), grad.reshape(-1)

    def trained(params: PolicyParams):
        """TrainingForm.trained: θ's entries outside the layout's padding."""
        return dense_entries(packing.layout(*net.dims(params))[0])

    return TrainingForm(pack=packing.pack, unpack=packing.unpack,
                        rows=lambda params, data: pack_rows(fused_rows(params, data)),
                        noise=terms.noise, value_and_grad=packed_value_and_grad, trained=trained)



def make_gmr_policy(cfg: GMRConfig = GMRConfig()) -> Policy:
    """The GMR policy for a configuration (the hook of ``gmr_jax.policies.make_policy``)."""
    return make_gmr(cfg).policy


def gmr_linearize(params: PolicyParams, x: Array, cfg: GMRConfig = GMRConfig()):
    """Exact first-order expansion of the GMR action at x [dX] -> (K [dU, dX], k [dU]).

    K = ∂u/∂x of u(x) = Ψ_K(x)·x + Ψ_k(x) (autodiff, including the dependence of the Ψ's on x),
    k = u(x) − K x. Vmappable over x (e.g. the T mean states) and over params.
    """
    return make_gmr(cfg).linearize(params, x)

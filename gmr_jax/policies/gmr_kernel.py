"""GMR's S-step as one GPU kernel (Pallas, Triton): every Adam step of an S-step in one launch.

The S-step's minibatch steps are strictly sequential and tiny (a minibatch of 20 rows through
three networks of about 22 000 weights), so an XLA program spends its time in the ~57 dependent
kernels of each step (about 1.7 µs each on an H100), not computing. This kernel runs the whole loop inside one program of one
thread block: per step it gathers the minibatch's rows, runs the three networks forward, the
loss, the backward pass written out by hand (the same closed forms as ``gmr.fused_head`` and
``gmr.reparameterize``) and Adam, with the weights and Adam's moments in global memory (they
stay in the GPU's caches). Under ``jax.vmap`` (seeds) every seed gets its own thread block.

Speed (``benchmarks/RESULTS.md``, eighth to tenth sessions, H100, float32): with IEEE float32
products on the SM's FMA units ("ieee") the kernel takes about 550 µs per Adam step (Nsight
Compute: 32 registers and an 8.6 KB stack per thread, the warps waiting on local memory). With
three TF32 tensor-core products per product ("tf32x3", ``DOT``, the default) it takes 127–133 µs,
against the packed form's 112–122 µs, with 255 registers and a 3.8 KB stack per thread and 0.9
instructions issued per cycle (Nsight Compute). Compiled off the device
(``python -m benchmarks.kernel_sass``), a step is about 23 600 instructions per warp, among them
667 barriers and 2 300 spill loads and stores; Adam's update of the padded θ, the translation
network's backward pass and the per-row products ``rowwise`` and ``left`` are the costliest
lines. It is therefore opt-in (``impl="kernel"``). A rewrite in Triton cannot beat the packed
form either: ``python -m benchmarks.kernel_mlp`` measures what one dependent product costs inside
such a kernel, and GMR's three networks alone with the simplest loss already take longer per
Adam step than the packed form's whole step (benchmarks/RESULTS.md, twenty-first session).

It computes the S-step's packed form (``gmr_jax.sstep``, ``impl="packed"``) with the same
minibatches, noise and Adam steps; the sums run in another order, so the two agree to round-off
(tests/test_sstep.py bounds the difference). Off a GPU the kernel runs in Pallas's interpreter
(slow, for tests).

Layout. Triton needs every array a kernel touches to have power-of-two sides, and matrix
products need sides of at least 16, so every layer is zero-padded: widths to a power of two
≥ 16, the minibatch to ``padded(batch_size)`` rows (the extra rows get zero weight). The weights
live in one flat vector θ of layer blocks [W (fan_in × fan_out, row-major) | b (fan_out)]. The
encoder's last layer is split into two blocks (μ_z and log σ²_z, so that neither needs slicing
inside the kernel), and the translation network's last layer into the gain block, which holds
Ψ's gain G as rows of X entries with the offset g in column dX (the head's input gets a 1 there,
so G·[x̃, 1] = G x̃ + g), and the Cholesky block, the square of r (``gmr.cholesky_from_square``).
"""

from __future__ import annotations

import functools
import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from jax.experimental import pallas as pl
from jax.experimental.pallas import triton as plt

from gmr_jax.adam import adam_update
from gmr_jax.config import GMRConfig, SStepConfig
from gmr_jax.policies.base import PolicyParams, symmetrize


Array = jax.Array
STATS = ("total", "value", "action", "action_mse", "cov", "gain", "latent_kl", "recon")
"""The scalars written per step, in the order of ``jax.tree_util.tree_flatten((total, value, aux))``."""


def padded(n: int, floor: int = 16) -> int:
    """The smallest power of two ≥ max(n, floor)."""
    return 1 << (max(int(n), floor) - 1).bit_length()


class Block(NamedTuple):
    """One dense layer in θ: W at ``offset`` ([fan_in, fan_out] row-major), b after it.

    ``rows``/``cols``: for each padded input/output index, the index in the Flax kernel it holds,
    or -1 (padding)."""

    name: str
    fan_in: int
    fan_out: int
    offset: int
    rows: np.ndarray
    cols: np.ndarray

    @property
    def bias_offset(self) -> int:
        return self.offset + self.fan_in * self.fan_out

    @property
    def end(self) -> int:
        return self.bias_offset + self.fan_out


class Layout(NamedTuple):
    """The padded sizes and θ's blocks for a state of dX and an action of dU entries."""

    dX: int
    dU: int
    X: int   # padded state (with the head's constant-1 entry at dX)
    U: int   # padded action
    Z: int   # padded latent
    b: int   # padded minibatch
    blocks: dict[str, Block]
    encoder: tuple[str, ...]      # hidden layers, then "mu" and "logvar" read the last one
    decoder: tuple[str, ...]
    translation: tuple[str, ...]  # hidden layers, then "gain" and "chol" read the last one
    size: int


def layout(cfg: GMRConfig, dX: int, dU: int, batch_size: int) -> Layout:
    """The kernel's layout of GMR's networks (module docstring)."""
    X, Z, b = padded(dX + 1), padded(cfg.latent), padded(batch_size)
    U = max(padded(dU, 1), 4)  # the Cholesky block's U² outputs must be ≥ 16
    blocks, offset = {}, 0
    ident = lambda n, pad: np.where(np.arange(pad) < n, np.arange(pad), -1)  # noqa: E731

    def add(name, rows, cols):
        nonlocal offset
        blocks[name] = Block(name, len(rows), len(cols), offset, rows, cols)
        offset = blocks[name].end

    def chain(prefix, d_in, d_in_pad, hidden):
        names, a, a_pad = [], d_in, d_in_pad
        for i, w in enumerate(hidden):
            add(f"{prefix}{i}", ident(a, a_pad), ident(w, padded(w)))
            names.append(f"{prefix}{i}")
            a, a_pad = w, padded(w)
        return names, a, a_pad

    enc, a, a_pad = chain("enc", dX, X, cfg.encoder_hidden)
    add("mu", ident(a, a_pad), ident(cfg.latent, Z))
    add("logvar", ident(a, a_pad), np.where(np.arange(Z) < cfg.latent, cfg.latent + np.arange(Z), -1))
    dec, a, a_pad = chain("dec", cfg.latent, Z, cfg.decoder_hidden)
    add("xhat", ident(a, a_pad), ident(dX, X))
    trans, a, a_pad = chain("trans", cfg.latent, Z, cfg.translation_hidden)
    # the head's columns (gmr._split_head): G row-major [dU·dX], g [dU], r (tril, row-major)
    gain = np.full(U * X, -1)
    for i in range(dU):
        gain[i * X: i * X + dX] = i * dX + np.arange(dX)
        gain[i * X + dX] = dU * dX + i
    chol = np.full(U * U, -1)
    r_rows, r_cols = np.tril_indices(dU)
    chol[r_rows * U + r_cols] = dU * dX + dU + np.arange(len(r_rows))
    add("gain", ident(a, a_pad), gain)
    add("chol", ident(a, a_pad), chol)
    return Layout(dX, dU, X, U, Z, b, blocks, tuple(enc) + ("mu", "logvar"), tuple(dec) + ("xhat",),
                  tuple(trans) + ("gain", "chol"), offset)


def _flax_layers(cfg: GMRConfig, lay: Layout):
    """(block name, Flax network, Dense index) of every block."""
    out = [(n, "encoder", i) for i, n in enumerate(lay.encoder[:-2])]
    out += [("mu", "encoder", len(cfg.encoder_hidden)), ("logvar", "encoder", len(cfg.encoder_hidden))]
    out += [(n, "decoder", i) for i, n in enumerate(lay.decoder)]
    out += [(n, "translation", i) for i, n in enumerate(lay.translation[:-2])]
    out += [("gain", "translation", len(cfg.translation_hidden)), ("chol", "translation", len(cfg.translation_hidden))]
    return out


def pack(cfg: GMRConfig, lay: Layout, net: dict) -> Array:
    """params.net (Flax) -> θ [lay.size] (zeros in the padding)."""
    parts = []
    for name, network, i in _flax_layers(cfg, lay):
        blk = lay.blocks[name]
        dense = net["params"][network][f"Dense_{i}"]
        kernel, bias = dense["kernel"], dense["bias"]
        W = jnp.where((blk.rows[:, None] >= 0) & (blk.cols[None, :] >= 0),
                      kernel[np.maximum(blk.rows, 0)][:, np.maximum(blk.cols, 0)], 0)
        parts += [W.reshape(-1), jnp.where(blk.cols >= 0, bias[np.maximum(blk.cols, 0)], 0)]
    return jnp.concatenate(parts)


def _dense_sources(cfg: GMRConfig, lay: Layout, net: dict) -> dict:
    """{(network, i): (kernel, bias)}, int arrays of the Flax layer ``Dense_i`` of ``network``'s
    own shapes ([fan_in, fan_out] and [fan_out], unpadded): the θ entry that holds each of its
    entries (-1 where no block holds it)."""
    out = {}
    for name, network, i in _flax_layers(cfg, lay):
        blk = lay.blocks[name]
        dense = net["params"][network][f"Dense_{i}"]
        kernel, bias = out.setdefault((network, i), (np.full(np.shape(dense["kernel"]), -1),
                                                     np.full(np.shape(dense["bias"]), -1)))
        r, c = np.flatnonzero(blk.rows >= 0), np.flatnonzero(blk.cols >= 0)
        kernel[np.ix_(blk.rows[r], blk.cols[c])] = blk.offset + r[:, None] * blk.fan_out + c[None, :]
        bias[blk.cols[c]] = blk.bias_offset + c
    return out


def take(source: Array, index: np.ndarray, fallback: Array) -> Array:
    """``source[index]`` (``source`` 1-D, ``index`` a static int array of ``fallback``'s shape) in
    ``fallback``'s dtype, with ``fallback``'s entry wherever ``index`` is negative: a gather,
    where a scatter into ``fallback`` would, under XLA's deterministic GPU options, be rewritten
    into a sort of its indices (many kernels to compile)."""
    picked = source[np.maximum(index, 0)].astype(fallback.dtype)
    return picked if np.all(index >= 0) else jnp.where(index >= 0, picked, fallback)


def unpack(cfg: GMRConfig, lay: Layout, net: dict, theta: Array, position: np.ndarray | None = None) -> dict:
    """θ -> params.net (Flax), the inverse of ``pack`` (``net`` gives the tree and shapes, and the
    values of entries that no block holds). With ``position`` [lay.size], ``theta`` is another
    vector that holds θ's entry p at ``position[p]`` (-1: not held; every entry of a layer must
    be held), e.g. ``gmr_cuda``'s compact θ: one gather per leaf straight from it."""
    out = jax.tree_util.tree_map(lambda a: a, net)
    for (network, i), in_theta in _dense_sources(cfg, lay, net).items():
        sources = in_theta
        if position is not None:
            sources = tuple(np.where(s >= 0, position[np.maximum(s, 0)], -1) for s in in_theta)
            if any(np.any((s < 0) & (t >= 0)) for s, t in zip(sources, in_theta)):
                raise ValueError(f"gmr_kernel.unpack: `position` does not hold every entry of {network}'s Dense_{i}")
        dense = out["params"][network][f"Dense_{i}"]
        dense["kernel"] = take(theta, sources[0], dense["kernel"])
        dense["bias"] = take(theta, sources[1], dense["bias"])
    return out


class KernelRows(NamedTuple):
    """The per-datum constants of the loss in the kernel's padded shapes (B rows each).

    xn [B, X] the encoder's input x̄ (reconstruction target); xe [B, X] the head's input x̃ (or
    x) with 1 at dX; sig [B, X, X] Σ_t (symmetrised); tgt [B, U]; prc [B, U, U] w·P
    (symmetrised); K [B, U, X]; wt [B]; logdet [B] log|P|. And scale [X], Ψ_K = G·diag(scale),
    0 at dX and beyond.
    """

    xn: Array
    xe: Array
    sig: Array
    tgt: Array
    prc: Array
    K: Array
    wt: Array
    logdet: Array
    scale: Array


def kernel_rows(cfg: GMRConfig, lay: Layout, params: PolicyParams, rows) -> KernelRows:
    """gmr's LossRows of the whole data set -> KernelRows (zero padding)."""
    X, U = lay.X, lay.U
    B = rows.xn.shape[0]
    pad = lambda a, shape: jnp.pad(a, [(0, s - d) for d, s in zip(a.shape, shape)])  # noqa: E731
    ones = jnp.ones((B, 1), rows.xh.dtype)
    scale = jnp.ones_like(params.norm.scale) if cfg.head_coordinates == "raw" else params.norm.scale
    return KernelRows(xn=pad(rows.xn, (B, X)), xe=pad(jnp.concatenate([rows.xh, ones], axis=1), (B, X)),
                      sig=pad(symmetrize(rows.state_cov), (B, X, X)), tgt=pad(rows.tgt_mu, (B, U)),
                      prc=pad(symmetrize(rows.prc), (B, U, U)), K=pad(rows.K, (B, U, X)), wt=rows.wt,
                      logdet=rows.logdet, scale=pad(scale, (X,)))


def _precision(dot: str, dtype, interpret: bool):
    """The kernel's matrix-product precision for ``dot`` (one of ``DOTS``).

    "tf32x3" applies to float32 on a GPU only: Pallas's interpreter runs on XLA:CPU, which has
    no TF32 algorithms, and float64 products have one exact algorithm."""
    if dot not in DOTS:
        raise ValueError(f"gmr_kernel: dot must be one of {DOTS}, got {dot!r}")
    if dot == "tf32x3" and not interpret and jnp.dtype(dtype) == jnp.float32:
        return lax.DotAlgorithmPreset.TF32_TF32_F32_X3
    return lax.Precision.HIGHEST


def _body(cfg: GMRConfig, scfg: SStepConfig, lay: Layout, interpret: bool, precision):
    """The kernel: (idx, eps, c1, c2, KernelRows…, θ, μ, ν in) -> (θ, μ, ν, stats) in place."""
    dU, X, U, b = lay.dU, lay.X, lay.U, lay.b
    bs = scfg.batch_size
    s = math.log(cfg.cov_std_range)
    c = cfg.cov_offdiag_bound
    slope = cfg.negative_slope
    hi = precision
    blocks = lay.blocks

    def dot(a, w):
        return jnp.dot(a, w, precision=hi)

    def dot_t(a, w):  # a wᵀ
        return lax.dot_general(a, w, (((1,), (1,)), ((), ())), precision=hi)

    def t_dot(a, d):  # aᵀ d
        return lax.dot_general(a, d, (((0,), (0,)), ((), ())), precision=hi)

    def act(pre):
        return jnp.where(pre >= 0, pre, slope * pre)

    def act_grad(pre, g):
        return jnp.where(pre >= 0, g, slope * g)

    def kernel(idx_ref, eps_ref, c1_ref, c2_ref, xn_ref, xe_ref, sig_ref, tgt_ref, prc_ref, K_ref,
               wt_ref, logdet_ref, scale_ref, theta_in, mu_in, nu_in, theta_ref, mu_ref, nu_ref, stats_ref):
        del theta_in, mu_in, nu_in  # aliased with theta_ref, mu_ref, nu_ref
        dtype = theta_ref.dtype
        iU = lax.broadcasted_iota(jnp.int32, (U, U), 0)
        jU = lax.broadcasted_iota(jnp.int32, (U, U), 1)
        eye = (iU == jU)
        strict = (iU > jU) & (iU < dU)
        valid = lax.broadcasted_iota(jnp.int32, (U,), 0) < dU
        rho = jnp.where(lax.broadcasted_iota(jnp.int32, (b,), 0) < bs, 1.0 / bs, 0.0).astype(dtype)
        scale = scale_ref[...]

        def weight(name):
            blk = blocks[name]
            return theta_ref[pl.ds(blk.offset, blk.fan_in * blk.fan_out)].reshape(blk.fan_in, blk.fan_out)

        def bias(name):
            blk = blocks[name]
            return theta_ref[pl.ds(blk.bias_offset, blk.fan_out)]

        def dense(h, name):
            return dot(h, weight(name)) + bias(name)[None, :]

        def chain(h, names):
            """Hidden layers: -> (output, [(input, pre-activation)])."""
            saved = []
            for name in names:
                pre = dense(h, name)
                saved.append((h, pre))
                h = act(pre)
            return h, saved

        def back(g, saved, names, grads):
            """Backward through hidden layers (g: gradient of the last output) -> input gradient."""
            for (h, pre), name in zip(reversed(saved), reversed(names)):
                d = act_grad(pre, g)
                grads[name] = (t_dot(h, d), jnp.sum(d, axis=0))
                g = dot_t(d, weight(name))
            return g

        def rowwise(A, S):
            """Σ_k A[r, i, k] S[r, j, k] per row r: A [b, m, k], S [b, n, k] -> [b, m, n]."""
            m = A.shape[1]
            out = jnp.zeros((A.shape[0], m, S.shape[1]), dtype)
            im = lax.broadcasted_iota(jnp.int32, (1, m, 1), 1)
            for i in range(m):
                a_i = jnp.sum(jnp.where(im == i, A, 0.0), axis=1)          # [b, k]
                r_i = jnp.sum(a_i[:, None, :] * S, axis=2)                 # [b, n]
                out = out + jnp.where(im == i, r_i[:, None, :], 0.0)
            return out

        def left(P, Y):
            """P Y per row for a symmetric P: P [b, m, m], Y [b, m, n] -> [b, m, n]."""
            m = P.shape[1]
            out = jnp.zeros(Y.shape, dtype)
            ik = lax.broadcasted_iota(jnp.int32, (1, m, 1), 1)
            jk = lax.broadcasted_iota(jnp.int32, (1, 1, m), 2)
            for k in range(m):
                p_k = jnp.sum(jnp.where(jk == k, P, 0.0), axis=2)           # [b, m] column k
                y_k = jnp.sum(jnp.where(ik == k, Y, 0.0), axis=1)           # [b, n] row k
                out = out + p_k[:, :, None] * y_k[:, None, :]
            return out

        def step(i, carry):
            idx = idx_ref[i, :]
            xn, xe, sig = xn_ref[idx, :], xe_ref[idx, :], sig_ref[idx, :, :]
            tgt, P, Kp = tgt_ref[idx, :], prc_ref[idx, :, :], K_ref[idx, :, :]
            w, logdet_P = wt_ref[idx], logdet_ref[idx]
            eps = eps_ref[i, :, :]

            # ---- forward: encoder, latent sample, decoder, translation network
            h, enc_saved = chain(xn, lay.encoder[:-2])
            mu, logvar = dense(h, "mu"), dense(h, "logvar")
            std, var = jnp.exp(0.5 * logvar), jnp.exp(logvar)
            z = mu + std * eps
            kl = jnp.sum(jnp.square(mu) + var - logvar - 1.0, axis=1)
            hd, dec_saved = chain(z, lay.decoder[:-1])
            xhat = dense(hd, "xhat")
            ht, trans_saved = chain(z, lay.translation[:-2])
            G = dense(ht, "gain").reshape(b, U, X)
            full = dense(ht, "chol").reshape(b, U, U)

            # ---- the head (gmr.fused_head): Ψ_Σ's factor, Δu, ΔK, the controller terms
            t = jnp.tanh(jnp.sum(jnp.where(eye, full, 0.0), axis=2) / s)
            log_sigma = 0.5 * math.log(cfg.init_var) + s * t
            T = jnp.tanh(full / c)
            V = jnp.where(strict, c * T, 0.0) + jnp.where(eye, 1.0, 0.0)
            row_norm = jnp.sqrt(jnp.sum(jnp.square(V), axis=2))
            sigma = jnp.exp(log_sigma)
            L = jnp.where(valid[:, None], (sigma / row_norm)[:, :, None] * V, 0.0)
            logdet = 2.0 * jnp.sum(jnp.where(valid, log_sigma - jnp.log(row_norm), 0.0), axis=1)
            dK = G * scale[None, None, :] - Kp
            du = jnp.sum(G * xe[:, None, :], axis=2) - tgt
            Pdu = jnp.sum(P * du[:, None, :], axis=2)
            dKS = rowwise(dK, sig)
            PdKS = left(P, dKS)
            PL = left(P, L)
            action = jnp.sum(du * Pdu, axis=1)
            gain = jnp.sum(jnp.sum(dK * PdKS, axis=2), axis=1)
            tr_rows = jnp.sum(L * PL, axis=2)

            # ---- the loss (gmr combine): batch means over the bs real rows
            per_row = {
                "recon": w * jnp.sum(jnp.square(xn - xhat), axis=1),
                "latent_kl": w * 0.5 * kl,
                "action": action,
                "gain": gain,
                "cov": jnp.sum(tr_rows, axis=1) - w * (logdet + dU + logdet_P),
                "action_mse": jnp.sum(jnp.square(du), axis=1) / dU,
            }
            aux = {k: jnp.sum(rho * v) for k, v in per_row.items()}
            for k in ("action", "gain", "cov"):
                aux[k] = 0.5 * aux[k]
            value = aux["recon"] + cfg.alpha * aux["latent_kl"] + aux["action"] + aux["gain"] + aux["cov"]

            # ---- backward (cotangents of the per-row terms: ρ = 1/bs on real rows)
            grads = {}
            ct_half = 0.5 * rho
            g_du = (2.0 * ct_half)[:, None] * Pdu
            g_G = (g_du[:, :, None] * xe[:, None, :]
                   + (2.0 * ct_half)[:, None, None] * PdKS * scale[None, None, :])
            g_L = (2.0 * ct_half)[:, None, None] * PL
            q = (2.0 * ct_half)[:, None] * tr_rows + jnp.where(valid, (2.0 * -ct_half * w)[:, None], 0.0)
            g_V = (sigma / row_norm)[:, :, None] * g_L - (q / jnp.square(row_norm))[:, :, None] * V
            g_full = jnp.where(strict, g_V * (1.0 - jnp.square(T)),
                               jnp.where(eye & valid[:, None], (q * (1.0 - jnp.square(t)))[:, :, None], 0.0))
            D_gain, D_chol = g_G.reshape(b, U * X), g_full.reshape(b, U * U)
            grads["gain"] = (t_dot(ht, D_gain), jnp.sum(D_gain, axis=0))
            grads["chol"] = (t_dot(ht, D_chol), jnp.sum(D_chol, axis=0))
            g_z = back(dot_t(D_gain, weight("gain")) + dot_t(D_chol, weight("chol")), trans_saved,
                       lay.translation[:-2], grads)
            D_xhat = (-2.0 * rho * w)[:, None] * (xn - xhat)
            grads["xhat"] = (t_dot(hd, D_xhat), jnp.sum(D_xhat, axis=0))
            g_z = g_z + back(dot_t(D_xhat, weight("xhat")), dec_saved, lay.decoder[:-1], grads)
            ct_kl = (cfg.alpha * 0.5 * rho * w)[:, None]
            g_mu = g_z + ct_kl * (2.0 * mu)
            g_logvar = g_z * eps * (0.5 * std) + ct_kl * (var - 1.0)
            grads["mu"] = (t_dot(h, g_mu), jnp.sum(g_mu, axis=0))
            grads["logvar"] = (t_dot(h, g_logvar), jnp.sum(g_logvar, axis=0))
            back(dot_t(g_mu, weight("mu")) + dot_t(g_logvar, weight("logvar")), enc_saved,
                 lay.encoder[:-2], grads)

            # ---- L2 term and Adam, block by block
            c1, c2 = c1_ref[i], c2_ref[i]
            l2 = jnp.zeros((), dtype)
            for name, (gW, gb) in grads.items():
                blk = blocks[name]
                for start, n, g in ((blk.offset, blk.fan_in * blk.fan_out, gW.reshape(-1)),
                                    (blk.bias_offset, blk.fan_out, gb)):
                    sl = pl.ds(start, n)
                    theta = theta_ref[sl]
                    l2 = l2 + jnp.sum(jnp.square(theta))
                    theta, m_new, v_new = adam_update(scfg, theta, mu_ref[sl], nu_ref[sl],
                                                      g + scfg.weight_decay * (2.0 * theta), c1, c2)
                    theta_ref[sl], mu_ref[sl], nu_ref[sl] = theta, m_new, v_new
            stats = {"total": value + scfg.weight_decay * l2, "value": value, **aux}
            k8 = lax.broadcasted_iota(jnp.int32, (len(STATS),), 0)
            row = jnp.zeros((len(STATS),), dtype)
            for k, name in enumerate(STATS):
                row = row + jnp.where(k8 == k, stats[name], 0.0)
            stats_ref[i, :] = row
            if not interpret:
                # the next step reads what every thread of the block wrote
                plt.debug_barrier()
            return carry

        lax.fori_loop(0, idx_ref.shape[0], step, 0)

    return kernel


NUM_WARPS = 8

DOTS = ("ieee", "tf32x3")
DOT = "tf32x3"
"""The default matrix-product form inside the kernel: "ieee" (IEEE float32 products on the SM's
FMA units, as ``Precision.HIGHEST``) or "tf32x3" (three TF32 tensor-core products per product:
a = a_hi + a_lo with a_hi, a_lo TF32 holds a to 22 of float32's 24 bits, and a·b ≈ a_hi·b_hi +
a_hi·b_lo + a_lo·b_hi drops terms of about 2⁻²²·|a·b|, a few float32 rounding errors; float32 on a
GPU only). Measured on an H100, both train the packed form's weights to 1.1–1.3e-7 relative after
240–480 Adam steps, and "tf32x3" is four times faster (``benchmarks.sstep --kernel-dot``)."""


@functools.lru_cache(maxsize=None)
def _call(cfg: GMRConfig, scfg: SStepConfig, dX: int, dU: int, steps: int, dtype, interpret: bool,
          num_warps: int, dot: str):
    """The pallas_call of one configuration and shape (cached)."""
    lay = layout(cfg, dX, dU, scfg.batch_size)
    n = lay.size
    out_shape = [jax.ShapeDtypeStruct((n,), dtype)] * 3 + [jax.ShapeDtypeStruct((steps, len(STATS)), dtype)]
    return pl.pallas_call(
        _body(cfg, scfg, lay, interpret, _precision(dot, dtype, interpret)), out_shape=out_shape,
        input_output_aliases={13: 0, 14: 1, 15: 2}, interpret=interpret,
        compiler_params=plt.CompilerParams(num_warps=num_warps, num_stages=1),
        name="gmr_sstep")


def fit(cfg: GMRConfig, scfg: SStepConfig, params: PolicyParams, rows, idx: Array, noise: Array,
        c1: Array, c2: Array, *, num_warps: int | None = None, dot: str | None = None,
        interpret: bool | None = None):
    """All Adam steps of an S-step in one kernel.

    Args:
      cfg, scfg: the GMR and S-step configurations (static).
      params: the policy params (warm start; normalisation set).
      rows: gmr's LossRows of the whole training set (B rows, ``tgt_prc`` = w·P).
      idx: [steps, batch_size] int, each step's rows; noise: [steps, batch_size, latent] ε.
      c1, c2: [steps] Adam's bias corrections.
      num_warps: the thread block's warps (default ``NUM_WARPS``).
      dot: the products' form, one of ``DOTS`` (default ``DOT``).
      interpret: run in Pallas's interpreter (default: off a GPU).
    Returns: (net (Flax), stats [steps, len(STATS)]: total, value and the aux entries per step).
    """
    if interpret is None:
        interpret = jax.default_backend() != "gpu"
    dX, dU = params.norm.scale.shape[-1], params.var.shape[-1]
    lay = layout(cfg, dX, dU, scfg.batch_size)
    dtype = params.norm.scale.dtype
    steps, bs = idx.shape
    kr = kernel_rows(cfg, lay, params, rows)
    idx = jnp.pad(idx.astype(jnp.int32), ((0, 0), (0, lay.b - bs)))
    eps = jnp.pad(noise.astype(dtype), ((0, 0), (0, lay.b - bs), (0, lay.Z - noise.shape[-1])))
    theta0 = pack(cfg, lay, params.net).astype(dtype)
    call = _call(cfg, scfg, dX, dU, steps, jnp.dtype(dtype), bool(interpret), num_warps or NUM_WARPS,
                 dot or DOT)
    theta, _, _, stats = call(idx, eps, c1.astype(dtype), c2.astype(dtype), *kr, theta0,
                              jnp.zeros_like(theta0), jnp.zeros_like(theta0))
    return unpack(cfg, lay, params.net, theta), stats

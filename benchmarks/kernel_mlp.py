"""The floor of a one-kernel S-step in Pallas (Triton): Adam steps of plain MLPs in one thread block.

``gmr_kernel`` runs GMR's whole S-step in one Pallas (Triton) kernel and takes 127–133 µs per Adam
step on an H100 (benchmarks/RESULTS.md, tenth session): 23 600 instructions per warp and step,
among them Adam's update, the head's per-row products and spills. Goal 1 of issue 14 asks for
20 µs. This benchmark measures what the simplest part of such a kernel costs on its own, so that
the floor of the approach is a measurement rather than an extrapolation: the minibatch steps of
``--nets`` independent 3-layer leaky-ReLU MLPs of GMR's widths (input 16, hidden 64, 64, output
16, the GMR encoder's, decoder's and translation network's shapes up to the head), all reading
the same gathered minibatch of 20 rows (padded to 32), with a squared-error loss, the backward
pass written out and Adam (or plain SGD) on every weight, all steps in one kernel launch of one
thread block::

    python -m benchmarks.kernel_mlp --nets 1,3 --weights global,carry --update adam,sgd --out f.json
    python -m benchmarks.kernel_mlp --nets "" --chain 1,8,32 --mosaic-chain 1,8,32 --out chain.json
    python -m benchmarks.kernel_mlp --nets 3 --weights carry --update adam --num-warps 8 --seeds 1,132,256

``--seeds N`` runs N independent S-steps side by side (``jax.vmap`` over each seed's data, weights
and moments, as the runner maps seeds; Pallas makes the seeds a grid axis of the one kernel, a
thread block per seed), the floor of the one-kernel form for many seeds per GPU. Its rows add the
differences per seed from the XLA steps mapped the same way (many seeds of this synthetic problem
amplify round-off over the steps, whichever two forms are compared, the XLA steps for many seeds
and for one included) and how far seed 0 and the most different seed lie from the same kernel run
for that seed alone (0 when they are the same bits).

``--weights global`` keeps weights and Adam's moments in global memory (read and written every
step, as ``gmr_kernel`` does); ``carry`` keeps them in the loop's carry (registers, or local
memory where they spill). Every configuration's final weights are compared with the same steps
run as an XLA program (``reference``, also timed: its kernels per step set its floor,
``benchmarks.kernel_floor``). ``--chain`` times a kernel of dependent products alone (Triton), and
``--mosaic-chain`` the same in Pallas's Mosaic GPU backend, whose products keep their operands in
registers. Off a GPU the Triton kernels run in Pallas's interpreter (slow; a check of the
arithmetic only) and the Mosaic ones are skipped.
"""

from __future__ import annotations

import argparse
import functools
import itertools
import json
import os
import platform
import time

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from jax.experimental import pallas as pl
from jax.experimental.pallas import triton as plt

from benchmarks.rollout import timed
from benchmarks.sstep import per_seed_relative_differences
from experiments import cli
from gmr_jax.adam import adam_corrections, adam_update
from gmr_jax.config import SStepConfig

WIDTHS = (16, 64, 64, 16)
"""Input, hidden, hidden, output: GMR's networks' shapes, padded as ``gmr_kernel`` pads them."""
BATCH, PADDED_BATCH = 20, 32
SLOPE = 0.2
Array = jax.Array
PRECISIONS = {"ieee": lax.Precision.HIGHEST, "tf32x3": lax.DotAlgorithmPreset.TF32_TF32_F32_X3}
WEIGHTS = ("global", "carry")
UPDATES = ("adam", "sgd")


def init_weights(key, nets: int, dtype) -> list[Array]:
    """Per net and layer W [fan_in, fan_out] (lecun normal) and b [fan_out] (zeros), flattened in
    the order net 0 (W0, b0, W1, b1, W2, b2), net 1, …"""
    out = []
    for n in range(nets):
        for i, (a, b) in enumerate(zip(WIDTHS[:-1], WIDTHS[1:])):
            k = jax.random.fold_in(key, 3 * n + i)
            out += [jax.random.normal(k, (a, b), dtype) / float(np.sqrt(a)), jnp.zeros((b,), dtype)]
    return out


def _step_math(params, x, y, rho, update: str, cfg: SStepConfig, c1, c2, moments, dot, dot_t, t_dot):
    """One minibatch step of all nets -> (loss [], new params, new moments).

    params: per net [W0 [16, 64], b0 [64], W1 [64, 64], b1 [64], W2 [64, 16], b2 [16]]; x, y
    [b, 16] the minibatch; rho [b] (1/20 on real rows, 0 on padding); c1, c2 [] Adam's bias
    corrections of this step; moments: Adam's (μ, ν) per parameter, in parameter order (empty for
    SGD); dot, dot_t, t_dot: a·w, a·wᵀ, aᵀ·d. The same code runs inside the kernel and in the XLA
    reference (only the products' precision differs)."""
    grads, loss = [], 0.0
    for n in range(len(params) // 6):
        W0, b0, W1, b1, W2, b2 = params[6 * n: 6 * n + 6]
        p0 = dot(x, W0) + b0[None, :]
        h0 = jnp.where(p0 >= 0, p0, SLOPE * p0)
        p1 = dot(h0, W1) + b1[None, :]
        h1 = jnp.where(p1 >= 0, p1, SLOPE * p1)
        out = dot(h1, W2) + b2[None, :]
        r = out - y
        loss = loss + jnp.sum(rho[:, None] * r * r)
        d2 = (2.0 * rho)[:, None] * r
        g1 = dot_t(d2, W2)
        d1 = jnp.where(p1 >= 0, g1, SLOPE * g1)
        g0 = dot_t(d1, W1)
        d0 = jnp.where(p0 >= 0, g0, SLOPE * g0)
        grads += [t_dot(x, d0), jnp.sum(d0, axis=0), t_dot(h0, d1), jnp.sum(d1, axis=0),
                  t_dot(h1, d2), jnp.sum(d2, axis=0)]
    new, new_moments = [], []
    for k, (theta, g) in enumerate(zip(params, grads)):
        if update == "adam":
            mu, nu = moments[2 * k], moments[2 * k + 1]
            theta, mu, nu = adam_update(cfg, theta, mu, nu, g, c1, c2)
            new_moments += [mu, nu]
        else:
            theta = theta - cfg.lr * g
        new.append(theta)
    return loss, new, new_moments


def _products(precision):
    dot = lambda a, w: jnp.dot(a, w, precision=precision)  # noqa: E731
    dot_t = lambda a, w: lax.dot_general(a, w, (((1,), (1,)), ((), ())), precision=precision)  # noqa: E731
    t_dot = lambda a, d: lax.dot_general(a, d, (((0,), (0,)), ((), ())), precision=precision)  # noqa: E731
    return dot, dot_t, t_dot


@functools.lru_cache(maxsize=None)
def kernel_call(nets: int, steps: int, weights: str, update: str, num_warps: int, dot: str, dtype,
                interpret: bool):
    """The pallas_call: (idx [steps, 32], c1, c2 [steps], X [B, 16], Y [B, 16], params…, moments…)
    -> (params…, moments…, loss [steps])."""
    if dot not in PRECISIONS or weights not in WEIGHTS or update not in UPDATES:
        raise ValueError(f"kernel_mlp: dot, weights, update must be in {tuple(PRECISIONS)}, {WEIGHTS}, "
                         f"{UPDATES}; got {dot!r}, {weights!r}, {update!r}")
    cfg = SStepConfig()
    n_params = 6 * nets
    n_moments = 2 * n_params if update == "adam" else 0
    # the interpreter (off a GPU) has no TF32 algorithms and ignores num_warps
    precision = lax.Precision.HIGHEST if interpret else PRECISIONS[dot]
    products = _products(precision)

    def kernel(*refs):
        idx_ref, c1_ref, c2_ref, x_ref, y_ref = refs[:5]
        outs = refs[5 + n_params + n_moments:]
        p_refs, m_refs, loss_ref = outs[:n_params], outs[n_params: n_params + n_moments], outs[-1]
        rho = jnp.where(lax.broadcasted_iota(jnp.int32, (PADDED_BATCH,), 0) < BATCH, 1.0 / BATCH,
                        0.0).astype(dtype)

        def math(i, params, moments):
            idx = idx_ref[i, :]
            x, y = x_ref[idx, :], y_ref[idx, :]
            return _step_math(params, x, y, rho, update, cfg, c1_ref[i], c2_ref[i], moments, *products)

        if weights == "global":
            def step(i, carry):
                loss, params, moments = math(i, [r[...] for r in p_refs], [r[...] for r in m_refs])
                if not interpret:
                    plt.debug_barrier()  # every thread has read this step's weights
                for r, v in zip(p_refs + m_refs, params + moments):
                    r[...] = v
                loss_ref[i] = loss
                if not interpret:
                    plt.debug_barrier()  # the next step reads what every thread wrote
                return carry
            lax.fori_loop(0, steps, step, 0)
        else:
            def step(i, carry):
                params, moments = carry
                loss, params, moments = math(i, params, moments)
                loss_ref[i] = loss
                return params, moments
            init = ([r[...] for r in p_refs], [r[...] for r in m_refs])
            params, moments = lax.fori_loop(0, steps, step, init)
            for r, v in zip(p_refs + m_refs, params + moments):
                r[...] = v

    def out_shapes(args):
        return ([jax.ShapeDtypeStruct(a.shape, a.dtype) for a in args]
                + [jax.ShapeDtypeStruct((steps,), dtype)])

    def call(idx, c1, c2, X, Y, params, moments):
        state = list(params) + list(moments)
        first = 5
        return pl.pallas_call(
            kernel, out_shape=out_shapes(state), interpret=interpret,
            input_output_aliases={first + k: k for k in range(len(state))},
            compiler_params=plt.CompilerParams(num_warps=num_warps, num_stages=1), name="mlp_sstep",
        )(idx, c1, c2, X, Y, *state)

    return jax.jit(call)


@functools.lru_cache(maxsize=None)
def reference_call(nets: int, steps: int, update: str, dtype):
    """The same steps as an XLA program: a fori_loop of ``_step_math`` with float32 products."""
    cfg = SStepConfig()
    products = _products(lax.Precision.HIGHEST)

    def run(idx, c1, c2, X, Y, params, moments):
        rho = jnp.where(jnp.arange(PADDED_BATCH) < BATCH, 1.0 / BATCH, 0.0).astype(dtype)

        def step(i, carry):
            params, moments, losses = carry
            loss, params, moments = _step_math(params, X[idx[i]], Y[idx[i]], rho, update, cfg, c1[i],
                                               c2[i], moments, *products)
            return params, moments, losses.at[i].set(loss)

        params, moments, losses = lax.fori_loop(0, steps, step, (list(params), list(moments),
                                                                  jnp.zeros((steps,), dtype)))
        return (*params, *moments, losses)

    return jax.jit(run)


@functools.lru_cache(maxsize=None)
def chain_call(chain: int, steps: int, num_warps: int, dot: str, interpret: bool):
    """A kernel whose loop body is ``chain`` dependent products h ← leaky_relu(h W), h [32, 64],
    W [64, 64] (read from the kernel's input for every product): (h, W) -> h."""
    precision = lax.Precision.HIGHEST if interpret else PRECISIONS[dot]

    def kernel(h_ref, w_ref, o_ref):
        def body(_, h):
            for _ in range(chain):
                pre = jnp.dot(h, w_ref[...], precision=precision)
                h = jnp.where(pre >= 0, pre, SLOPE * pre)
            return h
        o_ref[...] = lax.fori_loop(0, steps, body, h_ref[...])

    return jax.jit(lambda h, w: pl.pallas_call(
        kernel, out_shape=jax.ShapeDtypeStruct(h.shape, h.dtype), interpret=interpret,
        compiler_params=plt.CompilerParams(num_warps=num_warps, num_stages=1), name="chain")(h, w))


@functools.lru_cache(maxsize=None)
def mosaic_chain_call(chain: int, steps: int, dtype):
    """``chain_call`` in Pallas's Mosaic GPU backend (Lane semantics): each product an MMA with
    its operands in registers (``plgpu.mma``), the result returned to shared memory to be loaded
    as the next left operand (an accumulator cannot be cast to an operand layout). (h [64, 64],
    Wᵀ [64, 64]) -> h; h padded to 64 rows (the layouts' tile); bfloat16 operands (float32 ones
    are not supported by ``plgpu.mma``), float32 accumulation. GPU only."""
    from jax.experimental.pallas import mosaic_gpu as plgpu

    rows, width = 64, 64

    def body(h_ref, wt_ref, o_ref, smem):
        rhs = plgpu.load(wt_ref.T, layout=plgpu.Layout.MMA_RHS(dtype), optimized=False)
        smem[...] = h_ref[...]

        def it(_, carry):
            for _ in range(chain):
                lhs = plgpu.load(smem, layout=plgpu.Layout.MMA_LHS(dtype), optimized=False)
                acc = plgpu.layout_cast(jnp.zeros((rows, width), jnp.float32), plgpu.Layout.MMA_ACC(dtype))
                pre = plgpu.mma(acc, lhs, rhs)
                smem[...] = jnp.where(pre >= 0, pre, SLOPE * pre).astype(dtype)
            return carry

        lax.fori_loop(0, steps, it, 0)
        o_ref[...] = smem[...]

    params = plgpu.CompilerParams(lowering_semantics=plgpu.LoweringSemantics.Lane)
    return jax.jit(plgpu.kernel(body, out_type=jax.ShapeDtypeStruct((rows, width), dtype),
                                scratch_types=[plgpu.SMEM((rows, width), dtype)], compiler_params=params))


def problem(nets: int, steps: int, update: str, dtype, rows: int = 400, seed: int = 0, seeds: int = 1):
    """Synthetic data and initial state: (idx, c1, c2, X, Y, params, moments). With ``seeds`` > 1,
    X, Y, the params and moments have a leading seed axis, seed i's those of ``problem(…,
    seed=seed + i)``; the minibatch rows (``seed``'s) and Adam's corrections are shared."""
    rng = np.random.default_rng(seed)

    def one(r, s):
        X = jnp.asarray(r.normal(size=(rows, WIDTHS[0])), dtype)
        Y = jnp.asarray(np.tanh(r.normal(size=(rows, WIDTHS[-1]))), dtype)
        params = init_weights(jax.random.key(s), nets, dtype)
        moments = [jnp.zeros_like(p) for p in params for _ in range(2)] if update == "adam" else []
        return X, Y, params, moments

    first = one(rng, seed)  # drawn before the rows, from the same generator (as with one seed before)
    idx = np.concatenate([rng.permutation(rows)[:BATCH] for _ in range(steps)]).reshape(steps, BATCH)
    idx = jnp.asarray(np.pad(idx, ((0, 0), (0, PADDED_BATCH - BATCH))), jnp.int32)  # pad rows read row 0
    c1, c2 = adam_corrections(SStepConfig(), steps, dtype)
    if seeds == 1:
        return (idx, c1, c2, *first)
    others = [one(np.random.default_rng(seed + s), seed + s) for s in range(1, seeds)]
    X, Y, params, moments = jax.tree_util.tree_map(lambda *a: jnp.stack(a), first, *others)
    return idx, c1, c2, X, Y, params, moments


def seed_of(prob, s: int):
    """Seed ``s``'s arguments from ``problem(…, seeds=N)``'s: the shared rows and corrections with its
    own X, Y, params and moments (``problem(…, seed=s)``'s, with the shared rows)."""
    idx, c1, c2, *per_seed = prob
    return (idx, c1, c2, *jax.tree_util.tree_map(lambda a: a[s], per_seed))


def over_seeds(fn, seeds: int):
    """``fn`` (a kernel_call or reference_call) for ``problem(…, seeds=seeds)``'s arguments:
    itself for one seed, else mapped over the leading seed axis of X, Y, the params and moments."""
    return fn if seeds == 1 else jax.vmap(fn, in_axes=(None, None, None, 0, 0, 0, 0))


def relative_difference(a, b) -> float:
    """max |a − b| / max |b| over two lists of arrays (the measure of benchmarks.sstep)."""
    a, b = (np.concatenate([np.ravel(np.asarray(t)) for t in x]) for x in (a, b))
    return float(np.max(np.abs(a - b)) / np.max(np.abs(b)))


def per_seed_differences(out, ref, n_params: int, seeds: int) -> dict:
    """For outputs with a leading seed axis: each seed's ``relative_difference`` of the params,
    their median over seeds, how many exceed 1e-4, and how many seeds' losses part
    (``first_divergence``); seeds can amplify round-off (Adam moves a weight whose gradient is near
    zero by about ±lr whatever its sign), the median says whether most agree."""
    def by_seed(arrays):  # [seeds, n]: each seed's params as one row, one copy to the host
        return np.concatenate([np.asarray(a).reshape(seeds, -1) for a in arrays], axis=1)

    per_seed = np.asarray(per_seed_relative_differences(by_seed(out[:n_params]), by_seed(ref[:n_params])))
    loss, ref_loss = np.asarray(out[-1]), np.asarray(ref[-1])
    parted = [first_divergence(loss[s], ref_loss[s]) for s in range(seeds)]
    return {"median_rel_diff_over_seeds": float(np.median(per_seed)),
            "seeds_rel_diff_above_1e-4": int(np.sum(np.asarray(per_seed) > 1e-4)),
            "seeds_whose_losses_part": int(sum(p is not None for p in parted)),
            "seed_of_largest_rel_diff": int(np.argmax(per_seed))}


def difference_from_each_seed_alone(fn, prob, out, seeds) -> float:
    """The largest ``relative_difference`` (over every output: params, moments, losses) between
    ``out`` (``fn`` mapped over ``prob``'s seeds) and ``fn`` run for each of ``seeds`` alone: 0 when
    the seeds of one launch compute exactly what each computes alone."""
    out = [np.asarray(a) for a in out]
    return max(relative_difference([a[s] for a in out], list(fn(*seed_of(prob, s)))) for s in seeds)


def first_divergence(loss, ref, rtol: float = 1e-5) -> int | None:
    """The first step whose loss differs from the reference's by more than ``rtol`` relative
    (None if none does): where two runs of the same steps part. Losses [..., steps]: the first
    step at which any of the leading axes' runs (seeds) part."""
    loss, ref = np.asarray(loss), np.asarray(ref)
    differs = np.abs(loss - ref) > rtol * np.abs(ref)
    bad = np.flatnonzero(differs.reshape(-1, differs.shape[-1]).any(axis=0))
    return int(bad[0]) if len(bad) else None


def _split(text: str) -> list[str]:
    return [v for v in text.split(",") if v]


def time_kernels(args, dtype, interpret: bool) -> list[dict]:
    """Every (nets, update, seeds) with its XLA reference and every (weights, warps, dot) kernel of it."""
    rows = []
    for nets, update, seeds in itertools.product([int(n) for n in _split(args.nets)], _split(args.update),
                                                 [int(n) for n in _split(args.seeds)]):
        prob = problem(nets, args.steps, update, dtype, seeds=seeds)
        _, ref_s, _, ref_out = timed(over_seeds(reference_call(nets, args.steps, update, dtype), seeds),
                                     prob, args.repeats)
        n_params = 6 * nets
        rows.append({"form": "reference", "nets": nets, "update": update, "seeds": seeds,
                     "us_per_step": 1e6 * ref_s / args.steps})
        print(f"nets {nets} {update:4s} seeds {seeds:3d} reference (XLA)            : "
              f"{rows[-1]['us_per_step']:8.2f} µs/step", flush=True)
        for weights in _split(args.weights):
            for warps in [int(w) for w in _split(args.num_warps)]:
                for dot in _split(args.dot):
                    row = {"form": "kernel", "nets": nets, "update": update, "seeds": seeds,
                           "weights": weights, "num_warps": warps, "dot": dot}
                    fn = over_seeds(kernel_call(nets, args.steps, weights, update, warps, dot,
                                                jnp.dtype(dtype), interpret), seeds)
                    try:
                        _, s, first_s, out = timed(fn, prob, args.repeats)
                    except Exception as e:  # noqa: BLE001 (a configuration Triton rejects is a result)
                        print(f"nets {nets} {update:4s} seeds {seeds:3d} kernel {weights:6s} {warps} warps {dot}: "
                              f"failed: {type(e).__name__}: {str(e).splitlines()[0][:200]}", flush=True)
                        rows.append({**row, "error": str(e)[:2000]})
                        continue
                    diff = relative_difference(out[:n_params], ref_out[:n_params])
                    row.update({"us_per_step": 1e6 * s / args.steps, "first_call_s": first_s,
                                "max_rel_diff_vs_reference": diff,
                                "max_loss_diff_vs_reference": float(np.max(np.abs(
                                    np.asarray(out[-1]) - np.asarray(ref_out[-1])))),
                                "first_step_loss_differs": first_divergence(out[-1], ref_out[-1])})
                    if seeds > 1:
                        row.update(per_seed_differences(out, ref_out, n_params, seeds))
                        row["seeds_checked_alone"] = sorted({0, row["seed_of_largest_rel_diff"]})
                        row["max_rel_diff_from_the_seeds_alone"] = difference_from_each_seed_alone(
                            kernel_call(nets, args.steps, weights, update, warps, dot, jnp.dtype(dtype), interpret),
                            prob, out, row["seeds_checked_alone"])
                    rows.append(row)
                    print(f"nets {nets} {update:4s} seeds {seeds:3d} kernel {weights:6s} {warps} warps {dot:6s}: "
                          f"{row['us_per_step']:8.2f} µs/step, weights vs reference {diff:.1e}, losses part "
                          f"at step {row['first_step_loss_differs']}"
                          + (f"; median over seeds {row['median_rel_diff_over_seeds']:.1e}, "
                             f"{row['seeds_rel_diff_above_1e-4']} seeds above 1e-4, "
                             f"{row['seeds_whose_losses_part']} seeds' losses part; seeds "
                             f"{row['seeds_checked_alone']} against the seed alone: "
                             f"{row['max_rel_diff_from_the_seeds_alone']:.1e}"
                             if seeds > 1 else ""),
                          flush=True)
    return rows


def time_chains(args, dtype, interpret: bool) -> tuple[list[dict], dict]:
    """The chain kernels of every length, warps and dot, and per (warps, dot) the least-squares
    line of µs per loop iteration over the chain's length: its slope is one dependent product."""
    chains = []
    rng = np.random.default_rng(0)
    h = jnp.asarray(rng.normal(size=(PADDED_BATCH, 64)), dtype)
    # orthogonal: h shrinks through the leaky ReLUs and never overflows (the products' time does
    # not depend on the values)
    w = jnp.asarray(np.linalg.qr(rng.normal(size=(64, 64)))[0], dtype)
    for chain in [int(c) for c in _split(args.chain)]:
        for warps in [int(n) for n in _split(args.num_warps)]:
            for dot in _split(args.dot):
                _, s, _, _ = timed(chain_call(chain, args.steps, warps, dot, interpret), (h, w), args.repeats)
                chains.append({"chain": chain, "num_warps": warps, "dot": dot,
                               "us_per_iteration": 1e6 * s / args.steps})
                print(f"chain {chain:3d} {warps:2d} warps {dot:6s}: "
                      f"{chains[-1]['us_per_iteration']:8.2f} µs per loop iteration", flush=True)
    fits = {}
    for warps in [int(n) for n in _split(args.num_warps)]:
        for dot in _split(args.dot):
            pts = [(c["chain"], c["us_per_iteration"]) for c in chains if (c["num_warps"], c["dot"]) == (warps, dot)]
            if len(pts) >= 2:
                slope, intercept = np.polyfit(*zip(*pts), 1)
                fits[f"{warps}_{dot}"] = {"us_per_product": float(slope),
                                          "us_per_iteration_besides": float(intercept)}
                print(f"in-kernel floor, {warps} warps {dot}: {slope:.3f} µs per dependent product, "
                      f"{intercept:.2f} µs per loop iteration besides", flush=True)
    return chains, fits


def time_mosaic_chains(args) -> tuple[list[dict], dict | None]:
    """``mosaic_chain_call`` for every chain length (bfloat16) and the least-squares µs per product."""
    rng = np.random.default_rng(0)
    h = jnp.asarray(0.1 * rng.normal(size=(64, 64)), jnp.bfloat16)
    wt = jnp.asarray(np.linalg.qr(rng.normal(size=(64, 64)))[0].T, jnp.bfloat16)
    rows = []
    for chain in [int(c) for c in _split(args.mosaic_chain)]:
        _, s, _, out = timed(mosaic_chain_call(chain, args.steps, jnp.dtype(jnp.bfloat16)), (h, wt),
                             args.repeats)
        rows.append({"chain": chain, "dtype": "bfloat16", "us_per_iteration": 1e6 * s / args.steps,
                     "finite": bool(np.all(np.isfinite(np.asarray(out, np.float32))))})
        print(f"Mosaic GPU chain {chain:3d} bfloat16: {rows[-1]['us_per_iteration']:8.2f} µs per loop iteration",
              flush=True)
    fit = None
    if len(rows) >= 2:
        slope, intercept = np.polyfit([r["chain"] for r in rows], [r["us_per_iteration"] for r in rows], 1)
        fit = {"us_per_product": float(slope), "us_per_iteration_besides": float(intercept)}
        print(f"in-kernel floor, Mosaic GPU bfloat16: {slope:.3f} µs per dependent product", flush=True)
    return rows, fit


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks.kernel_mlp", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--nets", default="1,3", help="comma-separated numbers of MLPs per step")
    p.add_argument("--weights", default="global,carry", help="comma-separated: " + ", ".join(WEIGHTS))
    p.add_argument("--update", default="adam,sgd", help="comma-separated: " + ", ".join(UPDATES))
    p.add_argument("--num-warps", default="4,8", help="comma-separated warps per thread block")
    p.add_argument("--dot", default="tf32x3", help="comma-separated: " + ", ".join(PRECISIONS))
    p.add_argument("--chain", default="", help="comma-separated chain lengths: also time a kernel of "
                   "that many dependent products per loop iteration (the in-kernel cost of one product)")
    p.add_argument("--mosaic-chain", default="", help="comma-separated chain lengths: the chain kernel in "
                   "Pallas's Mosaic GPU backend as well (bfloat16 products with register operands; GPU only)")
    p.add_argument("--seeds", default="1", help="comma-separated numbers of independent S-steps side by "
                   "side (one thread block each, in one launch)")
    p.add_argument("--steps", type=int, default=2000, help="Adam steps per launch")
    p.add_argument("--repeats", type=int, default=3, help="timed calls (median)")
    p.add_argument("--out", help="write the results as JSON to this file")
    args = p.parse_args(argv)
    for name, allowed in (("dot", PRECISIONS), ("weights", WEIGHTS), ("update", UPDATES)):
        bad = [v for v in _split(getattr(args, name)) if v not in allowed]
        if bad:
            p.error(f"--{name} {','.join(bad)}: allowed values are {', '.join(allowed)}")
    cli.setup_jax("float32")
    dtype = jnp.float32
    dev = jax.devices()[0]
    interpret = dev.platform != "gpu"
    env = {"date": time.strftime("%Y-%m-%dT%H:%M:%S%z"), "device": dev.device_kind, "platform": dev.platform,
           "jax": jax.__version__, "python": platform.python_version(),
           "XLA_FLAGS": os.environ.get("XLA_FLAGS", ""), "interpret": interpret}
    print(f"Device: {env['device']}, jax {env['jax']}" + (" (Pallas interpreter)" if interpret else ""), flush=True)
    rows = time_kernels(args, dtype, interpret)
    chains, fits = time_chains(args, dtype, interpret)
    mosaic, mosaic_fit = [], None
    if args.mosaic_chain and interpret:
        print("--mosaic-chain: skipped, Mosaic GPU kernels run on a GPU only", flush=True)
    elif args.mosaic_chain:
        mosaic, mosaic_fit = time_mosaic_chains(args)
    if args.out:
        with open(args.out, "w") as f:
            json.dump({"env": env, "args": vars(args), "rows": rows, "chains": chains, "chain_fits": fits,
                       "mosaic_chains": mosaic, "mosaic_chain_fit": mosaic_fit}, f, indent=1)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

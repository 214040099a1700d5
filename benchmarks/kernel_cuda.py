"""The floor of a hand-written CUDA S-step: warp-level products and a grid-wide Adam update.

Goal 1 of issue 14 asks for 20 µs per GMR Adam step at one seed. XLA's programs are bound by
their number of dependent kernels, Pallas's kernels by the cost of a dependent product inside a
kernel (``benchmarks.kernel_mlp``); a step forms about 32 products. What the issue's last way —
one kernel with the weights on chip — would cost written in CUDA itself is measured here, from
the parts that set its floor (``benchmarks/kernel_cuda.cu``, built with nvcc for the GPU at
hand):

- ``chain_fma`` / ``chain_mma``: a loop whose body is ``--chain`` dependent products
  h ← leaky_relu(h W), h [32, 64] (the minibatch's 20 rows padded to two 16-row tiles), W [64, 64],
  in one thread block: on the CUDA cores (float32), and on the tensor cores with warp-level
  ``mma.sync`` (TF32 operands, one pass or three, ``tf32x3``, the float32-accurate split), each
  warp keeping its rows' activations in registers from one product to the next (W's rows stored
  in the order of an accumulator fragment, so no shuffle and no shared memory sits between two
  products), or with the columns split over 2 or 4 warps that exchange fragments through shared
  memory. The least-squares slope over the chain lengths is one dependent product.
- ``chains_mma``: 2, 3 or 4 such chains (tf32x3, two warps per row tile) at once in one block, each
  on warps, exchange buffers and named barriers of its own: a GMR step's products are not one
  chain (the decoder and the translation network run side by side, and a layer's weight gradient
  is off the path of the input gradients), so what products beside the dependent chain cost is
  timed here, as µs per product of each chain.
- ``chain_wgmma`` (sm_90a only): the same chain with Hopper's warpgroup products (``wgmma``,
  m64n64k8, A from registers in the same fragments, B in shared memory), one warpgroup, the
  chain's 32 rows (the minibatch's 20, padded) padded again to 64.
- ``chain_cluster`` (sm_90 and later): the tf32x3 chain over a thread-block cluster of 2, 4 or 8
  blocks (``split``: warps per row tile in each block), the columns split over the blocks, each
  block on a multiprocessor of its own (checked), each product's output passed to every block's
  shared memory (distributed shared memory) before the cluster's barrier; and ``cluster_adam``,
  Adam over a cluster of the same size: grid_adam's work (one block's gradient, barrier, update,
  barrier: "update"), or each block its own slice's gradient and update ("local"), and the barrier
  alone ("sync"). ``cluster_estimates``: per cluster size, its products and its "local" Adam; and
  the fastest product and the fastest Adam from one block's gradient of every design together.
- ``grid_adam``: Adam on ``--adam-n`` entries (GMR's packed θ: 41 600) per step, spread over a
  cooperative grid of one block per multiprocessor between two grid-wide syncs (block 0 reads the
  weights and writes a gradient first, as the block that forms the products would); the syncs
  alone; and the whole update in one block.
- ``seed_steps``: many seeds in one launch, one thread block per seed (``--seeds``), each running
  whole steps: ``--products`` dependent tf32x3 products on weight slots held in shared memory
  (each seed's ``--seed-n`` weights stay on chip for the launch), then Adam over all of them with
  the moments in global memory; and the same with no products (Adam alone). Every step starts
  from the seed's input rows, as a minibatch does. Every seed has data of its own; each seed's
  products are checked against the chain's bound (one step on slots 0–3; two steps from the last
  slot wrapping to the first, the second on the weights the first step's Adam left) and its
  weights after five steps against Adam's. This is the floor of a hand-written kernel for goal 4's
  256 seeds, where one seed's step cannot spread over the whole GPU.
- ``grid_step`` and ``cluster_step``: one seed's whole steps (``seed_steps``' step, the same
  checks) in one launch over more than one multiprocessor, so that the one-seed designs whose parts
  the kernels above time apart are timed as one program, the hand-offs between the parts included:
  over a cooperative grid (the weights in global memory; block 0 copies them into its shared memory,
  runs the chain and writes the whole gradient; grid sync; every block updates its slice; grid sync)
  and over a cluster of 2, 4 or 8 blocks (the weights and the gradient in block 0's shared memory for
  the whole launch, read and written by every block's slice of Adam through distributed shared
  memory; the cluster's barrier between); ``cluster_step_presplit``, the cluster with the weights
  split into their TF32 parts once per step, by the blocks that update them, into block 0's shared
  memory (the float32 weights and the gradient in global memory), so that the chain reads its
  operands as ``chain_mma`` does instead of splitting them at every product. ``one_seed_steps`` in
  the JSON: every one-seed design's step measured as one program (with ``seed_steps`` at one seed,
  the one-block design), where the estimates above only add up parts. Its products are stand-ins
  (``--products`` full 64 × 64 products; GMR A,B's step is about 16 full products' worth of
  tensor-core instructions), so it measures a design, not GMR's step.

Every kernel is checked against a double-precision host computation before it is timed (the
chains entry by entry against a forward-error bound of the chain, ``reference_chain`` in the
.cu file; Adam against ``adam_bound``); after a failed check the benchmark still writes its JSON, then exits with an error: its
timings are not to be used. The one-seed estimate it prints, ``--products`` dependent
products plus the grid's Adam step, and the many-seed kernel, which runs ``--products`` products
per step, leave out the head, the loss, the gather and the statistics: they are floors of the
approach, not kernels::

    python -m benchmarks.kernel_cuda --out kernel_cuda.json

Needs nvcc and an NVIDIA GPU (``--arch native`` builds for the GPU present); results:
benchmarks/RESULTS.md, twenty-second session (one seed), thirty-ninth (many seeds), fortieth
(clusters) and forty-first (one seed's whole steps in one launch).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import re
import shutil
import subprocess
import tempfile
import time
from pathlib import Path

import numpy as np

SOURCE = Path(__file__).with_name("kernel_cuda.cu")


def adam_bound(steps: int, max_abs_w: float, max_update: float, b2: float = 0.999) -> float:
    """Bound on max|w − w_ref| / max|w − w0| after ``steps`` float32 Adam steps: each step rounds
    w (at most an ulp of max|w|, 2·2⁻²⁴·max|w|), and the update carries its own float32
    arithmetic (a few operations, 8·2⁻²⁴) and the bias correction's cancellation: 1 − β₂ᵗ from a
    powf good to 2⁻²⁴ of β₂ᵗ is off by 2⁻²⁴/(1 − β₂) relative at t = 1, all relative to the
    update."""
    u = 2.0 ** -24
    return steps * (2.0 * u * max_abs_w + (8.0 * u + u / (1.0 - b2)) * max_update) / max_update


def moment_bound(steps: int) -> float:
    """Bound on max|m − m_ref| / max|m_ref| (and the same for v) after ``steps`` float32 Adam steps
    with the synthetic gradient g = 1e-3·|w| + 1e-4 > 0: every term of m = β₁m + (1 − β₁)g and of
    v = β₂v + (1 − β₂)g² is positive, so nothing cancels and each step adds at most a few
    roundings (4·2⁻²⁴, with g² and the products) to the relative error already carried (scaled by
    β ≤ 1); g itself carries 2·2⁻²⁴ of its own rounding and, where it is formed from the weights' TF32
    parts hi + lo (``cluster_step_presplit``), at most 2⁻²² more, doubled in g². A gradient that is
    wrong by more than round-off (stale by a step, scaled, from another entry) moves m and v by
    10⁻³ of their size or more."""
    u = 2.0 ** -24
    return (4.0 * steps + 8.0) * u + 2.0 * 2.0 ** -22


def adam_float32_error(w0: np.ndarray, steps: int, absolute: bool = True, lr: float = 1e-3, b1: float = 0.9,
                       b2: float = 0.999, eps: float = 1e-8) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``steps`` Adam steps in float32 against the same in float64 (NumPy, the kernels' formulas and
    float32 constants), with the kernels' synthetic gradient 1e-3·|w| + 1e-4 (``absolute``) or the
    earlier 1e-3·w + 1e-4, which crosses zero at w = −0.1.

    Args:
      w0: [S, n] float32 starting weights (one row per seed).
    Returns:
      per row: (max|w32 − w64| / max|w64 − w0|, max|w64|, max|w64 − w0|), the quantities the
      kernels' checks hold against ``adam_bound``.
    """
    w0 = np.asarray(w0, np.float32)

    def run(dtype):
        c = lambda x: dtype(np.float32(x))  # noqa: E731  (the kernels' float32 constants)
        w, m, v = w0.astype(dtype), np.zeros(w0.shape, dtype), np.zeros(w0.shape, dtype)
        for s in range(steps):
            g = c(1e-3) * (np.abs(w) if absolute else w) + c(1e-4)
            m = c(b1) * m + (dtype(1) - c(b1)) * g
            v = c(b2) * v + (dtype(1) - c(b2)) * g * g
            c1, c2 = dtype(1) / (dtype(1) - c(b1) ** dtype(s + 1)), dtype(1) / (dtype(1) - c(b2) ** dtype(s + 1))
            w = w - c(lr) * (m * c1) / (np.sqrt(v * c2) + c(eps))
        return w

    w, wr = run(np.float32), run(np.float64)
    update = np.abs(wr - w0).max(axis=-1)
    return np.abs(w - wr).max(axis=-1) / update, np.abs(wr).max(axis=-1), update


def emulate(seeds: int, n: int, steps: int = 5, seed: int = 0) -> dict:
    """The many-seed Adam check in NumPy for both synthetic gradients, on weights drawn as the
    kernel draws them (He's scale for leaky ReLU; another generator, so other values): each
    seed's error against its own ``adam_bound``."""
    scale = np.sqrt(2.0 / (1.0 + 0.2 ** 2) / 64)
    w0 = (scale * np.random.default_rng(seed).standard_normal((seeds, n))).astype(np.float32)
    out = {}
    for name, absolute in (("1e-3*|w|+1e-4", True), ("1e-3*w+1e-4", False)):
        err, abs_w, update = adam_float32_error(w0, steps, absolute)
        bound = np.array([adam_bound(steps, a, u) for a, u in zip(abs_w, update)])
        worst = int(np.argmax(err / bound))
        out[name] = {"worst_seed": worst, "max_err_over_update": float(err[worst]), "bound": float(bound[worst]),
                     "seeds_over_bound": int(np.sum(~(err <= bound))), "median_err_over_update": float(np.median(err))}
    return out


def line_fit(points: list[tuple[float, float]]) -> tuple[float, float]:
    """Least-squares (slope, intercept) of (x, y) points (at least two distinct x)."""
    x, y = np.asarray(points, dtype=float).T
    if len(set(x.tolist())) < 2:
        raise ValueError("line_fit needs at least two distinct chain lengths (--chain 1,8,32)")
    slope, intercept = np.polyfit(x, y, 1)
    return float(slope), float(intercept)


def resolve_arch(arch: str) -> str:
    """``native`` on a host whose GPUs are all Hopper (compute capability 9.0) -> ``sm_90a``, whose
    warpgroup products (``chain_wgmma``) need the architecture-specific target; anything else,
    or no answer from nvidia-smi, as given."""
    if arch != "native":
        return arch
    try:
        cap = subprocess.run(["nvidia-smi", "--query-gpu=compute_cap", "--format=csv,noheader"],
                             capture_output=True, text=True, timeout=30).stdout.split()
    except (OSError, subprocess.SubprocessError):
        return arch
    # every GPU listed (nvidia-smi does not follow CUDA_VISIBLE_DEVICES), so that a mixed host keeps native
    return "sm_90a" if cap and all(c == "9.0" for c in cap) else arch


def nvcc_arch_flags(arch: str) -> list[str]:
    """nvcc's flags for ``arch``: sm_90a compiles the architecture-specific PTX and the warpgroup
    kernels (``-DKERNEL_CUDA_WGMMA``); other targets build without them."""
    if arch == "sm_90a":
        return ["-gencode", "arch=compute_90a,code=sm_90a", "-DKERNEL_CUDA_WGMMA"]
    return [f"-arch={arch}"]


def build(nvcc: str, arch: str, out_dir: str, *, device_only: bool = False) -> tuple[Path, str]:
    """Compile kernel_cuda.cu -> (executable, ptxas's report). ``device_only``: only the device
    code, into a cubin (ptxas's report is the same; the tests' spill check needs no host build)."""
    exe = Path(out_dir) / ("kernel_cuda.cubin" if device_only else "kernel_cuda")
    cmd = [nvcc, "-O3", "-std=c++17", *nvcc_arch_flags(arch), *(["-cubin"] if device_only else []),
           "-Xptxas", "-v", "-o", str(exe), str(SOURCE)]
    res = subprocess.run(cmd, capture_output=True, text=True)
    if res.returncode != 0:
        raise SystemExit(f"kernel_cuda: nvcc failed ({' '.join(cmd)}):\n{res.stderr[-3000:]}")
    return exe, res.stderr


def parse_lines(stdout: str) -> list[dict]:
    """The executable's JSON lines. C's printf writes a NaN as ``nan`` or ``-nan`` and an infinity
    as ``inf``, which JSON lacks; they are read as Python's NaN and infinities, so that a check
    with a non-finite error fails instead of the parse."""
    fix = lambda line: re.sub(r"(?<![\w.])(-?)(nan|inf)(?![\w])", lambda m: "NaN" if m.group(2) == "nan"  # noqa: E731
                              else f"{m.group(1)}Infinity", line)
    return [json.loads(fix(line)) for line in stdout.splitlines() if line.startswith("{")]


def spills(ptxas_report: str) -> int:
    """Bytes of spill stores summed over every kernel in ptxas's -v report."""
    return sum(int(n) for n in re.findall(r"(\d+) bytes spill stores", ptxas_report))


def summarize(lines: list[dict], products: int, run_steps: int = 192_000) -> dict:
    """Checks, fits and the floor estimates from the executable's JSON lines (``run_steps``: the
    Adam steps of a run, for the many-seed estimate)."""
    device = next(r for r in lines if "device" in r)
    checks, failed = [], []
    for r in lines:
        if r.get("check", "").startswith("chain"):
            # the executable bounds every entry by a forward-error bound of the chain
            # (kernel_cuda.cu, reference_chain): the largest ratio must not exceed 1
            bound, err = 1.0, r["max_err_over_bound"]
        elif "check" in r:
            # one value per seed (seed_steps) or one for the kernel: each seed against its own bound
            errs, abs_ws, updates = (np.atleast_1d(np.asarray(r[k], dtype=float))
                                     for k in ("max_err_over_update", "max_abs_w", "max_update"))
            bounds = np.array([adam_bound(r["steps"], a, u) for a, u in zip(abs_ws, updates)])
            worst = int(np.argmax(errs / bounds))
            bound, err = float(bounds[worst]), float(errs[worst])
            # the moments (whole-step kernels): each seed's m and v against the same bound
            moments = [np.atleast_1d(np.asarray(r[k], dtype=float)) for k in ("m_max_rel_err", "v_max_rel_err")
                       if k in r]
            moments_ok = all(bool(np.all(m <= moment_bound(r["steps"]))) for m in moments)
            if isinstance(r["max_err_over_update"], list):
                worst_moments = {k: float(np.max(np.asarray(r[k], dtype=float))) for k in ("m_max_rel_err", "v_max_rel_err")
                                 if k in r}
                r = {k: val for k, val in r.items() if not isinstance(val, list)}
                r.update(worst_seed=worst, max_err_over_update=err, max_abs_w=float(abs_ws[worst]),
                         max_update=float(updates[worst]), **worst_moments)
            if moments:
                r = {**r, "moment_bound": moment_bound(r["steps"]), "moments_ok": moments_ok}
        else:
            continue
        # a cluster whose blocks shared a multiprocessor is another design than the one named
        shared = r.get("distinct_sms", r.get("cluster", 1)) < r.get("cluster", 1)
        checks.append({**r, "bound": bound, "blocks_shared_a_multiprocessor": shared,
                       "ok": bool(err <= bound) and not shared and r.get("moments_ok", True)})
        if not checks[-1]["ok"]:
            failed.append(checks[-1])
    chains = [r for r in lines if r.get("kernel", "").startswith("chain")]
    fits = {}
    variant = lambda r: (r["kernel"], r["precision"], r["nsplit"], r.get("accumulators", 1), r["threads"],  # noqa: E731
                         r.get("cluster", 1), r.get("concurrent", 1))
    in_cluster = lambda c: f"_cluster{c}" if c > 1 else ""  # noqa: E731
    at_once = lambda c: f"_{c}chains" if c > 1 else ""  # noqa: E731
    for key in sorted({variant(r) for r in chains}):
        pts = [(r["chain"], r["us_per_iteration"]) for r in chains if variant(r) == key]
        if len({c for c, _ in pts}) >= 2:
            slope, intercept = line_fit(pts)
            fits[f"{key[0]}_{key[1]}_split{key[2]}_acc{key[3]}_{key[4]}threads{in_cluster(key[5])}{at_once(key[6])}"] = {
                "us_per_product": slope, "us_per_iteration_besides": intercept, "cluster": key[5],
                "concurrent": key[6]}
    adam = {f"{r['kernel']}_{r['mode']}_{r['threads']}threads{in_cluster(r.get('cluster', 1))}": r["us_per_step"]
            for r in lines if r.get("kernel", "").endswith("adam")}
    estimate = None
    # the one-block chains with the grid's Adam; the clusters' chains with their own Adam (below);
    # chains run side by side (chains_mma) time each of them, not one chain alone
    accurate = {k: v for k, v in fits.items()
                if ("_tf32x3_" in k or "_ieee_" in k) and v["cluster"] == 1 and v["concurrent"] == 1}
    updates = {k: v for k, v in adam.items() if k.startswith("grid_adam_update")}
    if accurate and updates:
        best = min(accurate, key=lambda k: accurate[k]["us_per_product"])
        update = min(updates, key=updates.get)
        estimate = {"products": products, "product_kernel": best,
                    "us_per_product": accurate[best]["us_per_product"],
                    "adam_kernel": update, "adam_us": updates[update],
                    "us_per_step": products * accurate[best]["us_per_product"] + updates[update]}
    seeds = seeds_estimate([r for r in lines if r.get("kernel") == "seed_steps"], products, run_steps)
    return {"device": device, "checks": checks, "failed_checks": failed, "chain_fits": fits,
            "adam_us_per_step": adam, "floor_estimate": estimate,
            "cluster_estimates": cluster_estimates(fits, adam, products), "seed_steps": seeds,
            "one_seed_steps": one_seed_steps(lines, products), "skipped": [r for r in lines if "skipped" in r]}


STEP_KERNELS = ("seed_steps", "grid_step", "cluster_step", "cluster_step_presplit")
"""The kernels that run whole steps (the chain, the gradient's hand-off and Adam) in one launch."""


def one_seed_steps(lines: list[dict], products: int) -> dict | None:
    """The whole-step kernels at one seed, each one program: ``seed_steps`` (one block), ``grid_step``
    (a cooperative grid), ``cluster_step`` and ``cluster_step_presplit`` (a cluster of 2, 4 or 8
    blocks). Per variant its µs per step with ``products`` stand-in products and with none (Adam and
    the hand-offs alone); per design (kernel and cluster size) its fastest variant with the
    products; and the fastest design. No head, loss, gather or statistics."""
    rows = [r for r in lines if r.get("kernel") in STEP_KERNELS and r.get("seeds") == 1]
    if not rows:
        return None
    design = lambda r: r["kernel"] + (f"_cluster{r['cluster']}" if r.get("cluster", 1) > 1 else "")  # noqa: E731
    name = lambda r: f"{design(r)}_split{r['nsplit']}_{r['threads']}threads"  # noqa: E731
    variants: dict = {}
    for r in rows:
        variants.setdefault(name(r), {})["products" if r["products"] == products else "adam_alone"
                                         if r["products"] == 0 else f"{r['products']}_products"] = r["us_per_step"]
    designs: dict = {}
    for r in rows:
        if r["products"] == products and (design(r) not in designs
                                          or r["us_per_step"] < designs[design(r)]["us_per_step"]):
            designs[design(r)] = {"variant": name(r), "us_per_step": r["us_per_step"],
                                  "adam_alone_us": variants[name(r)].get("adam_alone")}
    best = min(designs, key=lambda d: designs[d]["us_per_step"]) if designs else None
    return {"products": products, "variants": variants, "designs": designs, "fastest": best,
            "chains_not_finite": [f"{name(r)}_{r['products']}products" for r in rows if r.get("out_finite") is False]}


def cluster_estimates(fits: dict, adam: dict, products: int) -> dict:
    """Per cluster size: ``products`` times the fastest float32-accurate product of a chain over that
    many blocks (``chain_fits``) plus the fastest Adam step over a cluster of that size in which each
    block forms its own slice's gradient (``cluster_adam`` mode "local", as when the cluster's blocks
    form the products, each its columns' weight gradient), and the cluster's barrier alone: the
    one-seed estimate of a step run by one cluster, before the head, the loss, the gather and the
    statistics. Under "any": the fastest accurate product of every chain measured and the fastest
    Adam step that starts from one block's gradient (``grid_adam`` or ``cluster_adam`` mode
    "update"), the least that a kernel combining the two designs could take."""
    out = {}
    for size in sorted({v["cluster"] for v in fits.values() if v["cluster"] > 1}):
        chains = {k: v for k, v in fits.items() if v["cluster"] == size and "_tf32x3_" in k}
        updates = {k: v for k, v in adam.items() if k.startswith("cluster_adam_local") and k.endswith(f"_cluster{size}")}
        syncs = [v for k, v in adam.items() if k.startswith("cluster_adam_sync") and k.endswith(f"_cluster{size}")]
        if not chains or not updates:
            continue
        best = min(chains, key=lambda k: chains[k]["us_per_product"])
        update = min(updates, key=updates.get)
        out[str(size)] = {"products": products, "product_kernel": best, "us_per_product": chains[best]["us_per_product"],
                          "adam_kernel": update, "adam_us": updates[update],
                          "barrier_alone_us": min(syncs) if syncs else None,
                          "us_per_step": products * chains[best]["us_per_product"] + updates[update]}
    accurate = {k: v for k, v in fits.items() if ("_tf32x3_" in k or "_ieee_" in k) and v.get("concurrent", 1) == 1}
    handoff = {k: v for k, v in adam.items() if k.startswith(("grid_adam_update", "cluster_adam_update"))}
    if out and accurate and handoff:
        best = min(accurate, key=lambda k: accurate[k]["us_per_product"])
        update = min(handoff, key=handoff.get)
        out["any"] = {"products": products, "product_kernel": best, "us_per_product": accurate[best]["us_per_product"],
                      "adam_kernel": update, "adam_us": handoff[update], "barrier_alone_us": None,
                      "us_per_step": products * accurate[best]["us_per_product"] + handoff[update]}
    return out


def seeds_estimate(rows: list[dict], products: int, run_steps: int) -> dict | None:
    """The many-seed kernel's timings (``seed_steps`` lines) and, at the largest seed count, the
    fastest variant's step with ``products`` products and with none (Adam alone), and what
    ``run_steps`` such steps take."""
    if not rows:
        return None
    name = lambda r: f"split{r['nsplit']}_{r['threads']}threads"  # noqa: E731
    table = {f"{name(r)}_{r['seeds']}seeds_{r['products']}products": r["us_per_step"] for r in rows}
    most = max(r["seeds"] for r in rows)
    at_most = [r for r in rows if r["seeds"] == most]
    out = {"us_per_step": table, "seeds": most, "run_steps": run_steps,
           "chains_not_finite": [f"{name(r)}_{r['seeds']}seeds_{r['products']}products" for r in rows
                                 if r.get("out_finite") is False]}
    for key, p in (("step", products), ("adam_alone", 0)):
        cand = [r for r in at_most if r["products"] == p]
        if cand:
            best = min(cand, key=lambda r: r["us_per_step"])
            out[key] = {"variant": name(best), "blocks_per_sm": best["blocks_per_sm"], "products": p,
                        "us_per_step": best["us_per_step"], "run_s": best["us_per_step"] * run_steps * 1e-6}
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks.kernel_cuda", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--chain", default="1,8,32", help="comma-separated chain lengths (dependent products "
                   "per loop iteration)")
    p.add_argument("--steps", type=int, default=2000, help="loop iterations per launch")
    p.add_argument("--repeats", type=int, default=5, help="timed launches (the fastest counts)")
    p.add_argument("--adam-n", type=int, default=41_600, help="Adam's entries (GMR's packed θ)")
    p.add_argument("--adam-steps", type=int, default=2000, help="Adam steps per launch")
    p.add_argument("--products", type=int, default=32, help="products per GMR Adam step (11 forward, 11 weight "
                   "gradients, 10 input gradients): in the one-seed estimate, and the products each step of the "
                   "many-seed kernel runs")
    p.add_argument("--seeds", default="1,132,256", help="comma-separated seed counts for the many-seed "
                   "kernel (one thread block per seed)")
    p.add_argument("--seed-n", type=int, default=22_664, help="each seed's weights in the many-seed kernel "
                   "(GMR A,B's 22 662 trained entries, rounded up to a multiple of 4)")
    p.add_argument("--seed-steps", type=int, default=500, help="whole steps per launch of the many-seed kernel")
    p.add_argument("--run-steps", type=int, default=192_000, help="Adam steps of a run in the many-seed "
                   "estimate (GMR A,B: 10 iterations × 19 200)")
    p.add_argument("--emulate", action="store_true", help="instead of the kernels: the many-seed Adam check in "
                   "NumPy (float32 against float64) for the synthetic gradient and the earlier one, which crossed "
                   "zero; needs no GPU")
    p.add_argument("--nvcc", default="nvcc", help="the CUDA compiler")
    p.add_argument("--arch", default="native", help="nvcc's -arch (native: the GPU present, sm_90a on a Hopper "
                   "GPU, which adds the warpgroup products)")
    p.add_argument("--out", help="write the results as JSON to this file")
    args = p.parse_args(argv)
    try:
        chains = [int(c) for c in args.chain.split(",") if c.strip()]
    except ValueError:
        p.error(f"--chain {args.chain!r}: expected comma-separated integers such as 1,8,32")
    if len(set(chains)) < 2 or min(chains) < 1:
        p.error(f"--chain {args.chain!r}: give at least two distinct positive lengths, e.g. 1,8,32")
    try:
        seed_counts = [int(c) for c in args.seeds.split(",") if c.strip()]
    except ValueError:
        p.error(f"--seeds {args.seeds!r}: expected comma-separated integers such as 1,132,256")
    if not seed_counts or min(seed_counts) < 1:
        p.error(f"--seeds {args.seeds!r}: give positive seed counts, e.g. 1,132,256")
    for name in ("steps", "repeats", "adam_n", "adam_steps", "products", "seed_steps", "run_steps"):
        if getattr(args, name) < 1:
            p.error(f"--{name.replace('_', '-')} must be at least 1")
    for name in ("adam_n", "seed_n"):
        if getattr(args, name) % 4:
            p.error(f"--{name.replace('_', '-')} {getattr(args, name)}: the Adam kernels take entries in fours; "
                    "give a multiple of 4")
    if args.seed_n < 64 * 64:
        p.error(f"--seed-n {args.seed_n}: the many-seed kernel needs at least one 64 × 64 weight slot (4096)")
    if args.emulate:
        n_seeds = max(seed_counts)
        result = emulate(n_seeds, args.seed_n)
        for name, r in result.items():
            print(f"gradient {name}: worst seed {r['worst_seed']} of {n_seeds}, error {r['max_err_over_update']:.2e} "
                  f"of the update (its bound {r['bound']:.1e}); {r['seeds_over_bound']} seeds over their bound",
                  flush=True)
        if args.out:
            with open(args.out, "w") as f:
                json.dump({"env": {"date": time.strftime("%Y-%m-%dT%H:%M:%S%z"), "numpy": np.__version__},
                           "args": vars(args), "emulate": result}, f, indent=1)
        return 0
    nvcc = shutil.which(args.nvcc)
    if nvcc is None:
        raise SystemExit(f"kernel_cuda: the CUDA compiler {args.nvcc!r} was not found; install the CUDA "
                         "toolkit or pass --nvcc PATH (this benchmark needs an NVIDIA GPU)")
    version = subprocess.run([nvcc, "--version"], capture_output=True, text=True).stdout.strip().splitlines()[-1]
    with tempfile.TemporaryDirectory() as tmp:
        exe, report = build(nvcc, resolve_arch(args.arch), tmp)
        cmd = [str(exe), ",".join(map(str, chains)), str(args.steps), str(args.repeats), str(args.adam_n),
               str(args.adam_steps), ",".join(map(str, seed_counts)), str(args.seed_n), str(args.seed_steps),
               str(args.products)]
        res = subprocess.run(cmd, capture_output=True, text=True)
    if res.returncode != 0:
        raise SystemExit(f"kernel_cuda: the benchmark failed (exit {res.returncode}): "
                         f"{(res.stderr.strip() or res.stdout.strip()).splitlines()[-1:]}")
    lines = parse_lines(res.stdout)
    summary = summarize(lines, args.products, args.run_steps)
    env = {"date": time.strftime("%Y-%m-%dT%H:%M:%S%z"), "device": summary["device"], "nvcc": version,
           "python": platform.python_version(), "spill_store_bytes": spills(report),
           "cuda_visible_devices": os.environ.get("CUDA_VISIBLE_DEVICES", "")}
    print(f"Device: {summary['device']['device']} ({summary['device']['multiprocessors']} multiprocessors), "
          f"{version}", flush=True)
    for c in summary["checks"]:
        if "max_err_over_bound" in c:
            threads = f" {c['threads']} threads" if "seeds" in c else ""
            width = (f" (bound at most {c['max_bound_over_max_h']:.1e} of max|h|)"
                     if "max_bound_over_max_h" in c else "")
            blocks = f" cluster {c['cluster']}" if c.get("cluster", 1) > 1 else ""
            blocks += f" {c['concurrent']} chains at once" if c.get("concurrent", 1) > 1 else ""
            what = (f"{c['precision']:6s} split {c['nsplit']} acc {c['accumulators']}{blocks}{threads}: max error "
                    f"{c['max_rel_err']:.2e} of max|h|, {c['max_err_over_bound']:.2e} of its bound{width}")
        else:
            seeds = f", worst of {c['seeds']} seeds" if "seeds" in c else ""
            seeds += f", cluster of {c['cluster']}" if "cluster" in c else ""
            what = (f"{c['threads']:4d} threads: max error {c['max_err_over_update']:.2e} of the update "
                    f"(bound {c['bound']:.1e}{seeds})")
            if "moment_bound" in c:
                what += (f", moments m {c['m_max_rel_err']:.1e} and v {c['v_max_rel_err']:.1e} of their size "
                         f"(bound {c['moment_bound']:.1e})")
        shared = " (its blocks shared a multiprocessor)" if c["blocks_shared_a_multiprocessor"] else ""
        print(f"check {c['check']:10s} {what}{shared} {'ok' if c['ok'] else 'FAILED'}", flush=True)
    for name, f in summary["chain_fits"].items():
        print(f"{name:36s}: {f['us_per_product']:.3f} µs per dependent product, "
              f"{f['us_per_iteration_besides']:.2f} µs per loop iteration besides", flush=True)
    for name, us in summary["adam_us_per_step"].items():
        print(f"{name:36s}: {us:.2f} µs per Adam step of {args.adam_n} entries", flush=True)
    if summary["floor_estimate"]:
        e = summary["floor_estimate"]
        print(f"floor of a one-kernel CUDA S-step: {e['products']} × {e['us_per_product']:.3f} µs "
              f"({e['product_kernel']}) + {e['adam_us']:.2f} µs Adam = {e['us_per_step']:.1f} µs per step, "
              "before the head, the loss, the gather and the statistics", flush=True)
    for size, e in summary["cluster_estimates"].items():
        what = "the fastest product and hand-off Adam of any design" if size == "any" else f"a cluster of {size} blocks"
        print(f"floor over {what}: {e['products']} × {e['us_per_product']:.3f} µs "
              f"({e['product_kernel']}) + {e['adam_us']:.2f} µs Adam ({e['adam_kernel']}) = {e['us_per_step']:.1f} µs "
              "per step, before the head, the loss, the gather and the statistics"
              + (f" (the cluster's barrier alone {e['barrier_alone_us']:.2f} µs)"
                 if e["barrier_alone_us"] is not None else ""), flush=True)
    if summary["seed_steps"]:
        e = summary["seed_steps"]
        for name, us in e["us_per_step"].items():
            print(f"seed_steps {name:36s}: {us:.2f} µs per step of all seeds", flush=True)
        if e["chains_not_finite"]:
            print(f"seed_steps: the timed chains ended non-finite in {', '.join(e['chains_not_finite'])} "
                  "(the timings stand; the values are not checked there)", flush=True)
        for key, what in (("adam_alone", "Adam alone"), ("step", f"{args.products} products + Adam")):
            if key in e:
                b = e[key]
                print(f"{e['seeds']} seeds, one block each ({b['variant']}, {b['blocks_per_sm']} per multiprocessor), "
                      f"{what} over {args.seed_n} weights: {b['us_per_step']:.1f} µs per step; "
                      f"{e['run_steps']} steps {b['run_s']:.1f} s", flush=True)
    for r in summary["skipped"]:
        print(f"skipped {r['skipped']} ({r['threads']} threads): {r['reason']}", flush=True)
    if summary["one_seed_steps"]:
        e = summary["one_seed_steps"]
        if e["chains_not_finite"]:
            print(f"one seed: the timed chains ended non-finite in {', '.join(e['chains_not_finite'])} "
                  "(the timings stand; the values are not checked there)", flush=True)
        for d, b in sorted(e["designs"].items(), key=lambda kv: kv[1]["us_per_step"]):
            alone = f" ({b['adam_alone_us']:.2f} µs without the products)" if b["adam_alone_us"] is not None else ""
            print(f"one seed, whole steps in one launch, {d:22s}: {b['us_per_step']:.2f} µs per step of "
                  f"{e['products']} products + Adam{alone} ({b['variant']})", flush=True)
    if args.out:
        with open(args.out, "w") as f:
            json.dump({"env": env, "args": vars(args), "lines": lines, **summary}, f, indent=1)
    if summary["failed_checks"]:
        raise SystemExit(f"kernel_cuda: {len(summary['failed_checks'])} kernel(s) failed their check: they disagree "
                         "with the host computation beyond their bound, or a cluster's blocks shared a "
                         "multiprocessor (see the lines marked FAILED); timings not to be used")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""benchmarks.kernel_cuda: the fragment layout its tensor-core chain relies on, its reporting, and
its build.

The kernels themselves run on a GPU only, where the benchmark checks each against a
double-precision host computation before timing it (and exits with an error after a failed
check). Here: a model
of ``mma.m16n8k8``'s fragments (PTX's layout, one 16-row tile, 32 lanes) shows that storing W's
rows in an accumulator fragment's order lets a product's output fragments serve as the next
product's input fragments unchanged, as the kernel does; the summary's fits, checks and estimates
(one seed, one thread-block cluster, many seeds, one seed's whole steps in one launch); the NumPy emulation of Adam's float32 check; and, where nvcc is installed,
that the kernels build for sm_90 and sm_90a without spilling registers.
"""

import json
import shutil

import numpy as np
import pytest

from benchmarks import kernel_cuda

SLOPE = 0.2
# chain timings of the synthetic executable output: precision -> (µs besides, µs per product)
CHAIN_US = {"ieee": (0.05, 1.5), "tf32": (0.08, 0.5), "tf32x3": (0.04, 0.7)}


def _lanes():
    lane = np.arange(32)
    return lane // 4, lane % 4  # g (group), t (thread in group)


def _mma(a, b, c):
    """mma.m16n8k8 on per-lane fragments: a [32, 4], b [32, 2], c [32, 4] -> d [32, 4] (PTX's
    fragment layout for .tf32 A/B and .f32 C/D)."""
    g, t = _lanes()
    A = np.zeros((16, 8))
    A[g, t], A[g + 8, t], A[g, t + 4], A[g + 8, t + 4] = a.T
    B = np.zeros((8, 8))
    B[t, g], B[t + 4, g] = b.T
    C = np.zeros((16, 8))
    C[g, 2 * t], C[g, 2 * t + 1], C[g + 8, 2 * t], C[g + 8, 2 * t + 1] = c.T
    D = A @ B + C
    return np.stack([D[g, 2 * t], D[g, 2 * t + 1], D[g + 8, 2 * t], D[g + 8, 2 * t + 1]], axis=1)


def test_output_fragments_are_the_next_products_input_fragments():
    """Three dependent products h ← leaky_relu(h W) of one 16-row tile, computed the way
    ``chain_mma`` holds them (input fragment of k-step kk = (c0, c2, c1, c3) of the last
    product's n-tile kk; B fragment (kk, nn) = W rows 8kk+2t and 8kk+2t+1 of column 8nn+g), equal
    the plain matrix chain."""
    rng = np.random.default_rng(0)
    H = rng.normal(size=(16, 64))
    W = rng.normal(size=(64, 64)) / 8
    g, t = _lanes()
    frag = [np.stack([H[g, 8 * kk + 2 * t], H[g + 8, 8 * kk + 2 * t], H[g, 8 * kk + 2 * t + 1],
                      H[g + 8, 8 * kk + 2 * t + 1]], axis=1) for kk in range(8)]
    ref = H
    for _ in range(3):
        acc = [np.zeros((32, 4)) for _ in range(8)]
        for kk in range(8):
            for nn in range(8):
                b = np.stack([W[8 * kk + 2 * t, 8 * nn + g], W[8 * kk + 2 * t + 1, 8 * nn + g]], axis=1)
                acc[nn] = _mma(frag[kk], b, acc[nn])
        leaky = [np.where(c > 0, c, SLOPE * c) for c in acc]
        frag = [c[:, [0, 2, 1, 3]] for c in leaky]
        ref = ref @ W
        ref = np.where(ref > 0, ref, SLOPE * ref)
    # the kernel's write-back of the last product: frag[kk] = (c0, c2, c1, c3) of n-tile kk
    out = np.zeros((16, 64))
    for kk in range(8):
        out[g, 8 * kk + 2 * t], out[g + 8, 8 * kk + 2 * t] = frag[kk][:, 0], frag[kk][:, 1]
        out[g, 8 * kk + 2 * t + 1], out[g + 8, 8 * kk + 2 * t + 1] = frag[kk][:, 2], frag[kk][:, 3]
    np.testing.assert_allclose(out, ref, rtol=1e-12, atol=1e-12 * np.max(np.abs(ref)))


def _lines(chain_us=CHAIN_US, over_bound=1e-2):
    """Executable output: a device line, checks, chain timings (µs = a + b·chain) and Adam."""
    lines = [{"device": "GPU", "multiprocessors": 132, "sm": "9.0"}]
    for precision, nsplit, threads, ratio in (("ieee", 0, 256, 1e-3), ("tf32", 1, 64, 1e-2),
                                              ("tf32x3", 2, 128, over_bound)):
        kernel = "chain_fma" if precision == "ieee" else "chain_mma"
        lines.append({"check": kernel, "precision": precision, "nsplit": nsplit, "accumulators": 1,
                      "products": 4, "max_rel_err": 1e-6, "max_err_over_bound": ratio})
        a, b = chain_us[precision]
        lines += [{"kernel": kernel, "precision": precision, "nsplit": nsplit, "accumulators": 1,
                   "threads": threads, "chain": c, "steps": 10, "us_per_iteration": a + b * c} for c in (1, 8, 32)]
    lines.append({"check": "grid_adam", "threads": 1024, "steps": 5, "max_err_over_update": 1e-5,
                  "max_abs_w": 0.4, "max_update": 5e-3})
    lines += [{"kernel": "grid_adam", "mode": "update", "threads": th, "us_per_step": us}
              for th, us in ((256, 11.0), (1024, 7.0))]
    lines.append({"kernel": "grid_adam", "mode": "sync", "threads": 256, "us_per_step": 2.2})
    return lines


def test_summary_fits_checks_and_estimate():
    s = kernel_cuda.summarize(_lines(), products=32)
    assert not s["failed_checks"] and all(c["ok"] for c in s["checks"])
    fits = s["chain_fits"]
    assert fits["chain_mma_tf32x3_split2_acc1_128threads"]["us_per_product"] == pytest.approx(0.7)
    assert fits["chain_fma_ieee_split0_acc1_256threads"]["us_per_iteration_besides"] == pytest.approx(0.05)
    est = s["floor_estimate"]
    # the fastest float32-accurate product (tf32x3 here; one TF32 pass is not float32-accurate)
    # and the fastest grid update
    assert est["product_kernel"] == "chain_mma_tf32x3_split2_acc1_128threads"
    assert est["adam_kernel"] == "grid_adam_update_1024threads"
    assert est["us_per_step"] == pytest.approx(32 * 0.7 + 7.0)
    # an entry beyond the chain's forward-error bound fails the check
    bad = kernel_cuda.summarize(_lines(over_bound=1.5), products=32)
    assert [c["precision"] for c in bad["failed_checks"]] == ["tf32x3"]


def test_cluster_chains_get_their_own_estimate_with_the_clusters_adam():
    lines = _lines()
    # a cluster's chain faster per product than every one-block chain, and its Adam
    for size, per_product, adam_us in ((2, 0.5, 9.0), (4, 0.4, 6.0)):
        lines.append({"check": "chain_cluster", "precision": "tf32x3", "nsplit": 1, "accumulators": 3,
                      "cluster": size, "distinct_sms": size, "products": 4, "max_rel_err": 1e-6,
                      "max_err_over_bound": 1e-2})
        lines += [{"kernel": "chain_cluster", "precision": "tf32x3", "nsplit": 1, "accumulators": 3, "threads": 64,
                   "cluster": size, "chain": c, "steps": 10, "us_per_iteration": 0.1 + per_product * c}
                  for c in (1, 8, 32)]
        lines.append({"check": "cluster_adam", "mode": "local", "cluster": size, "distinct_sms": size,
                      "threads": 1024, "steps": 5, "max_err_over_update": 1e-5, "max_abs_w": 0.4, "max_update": 5e-3})
        lines += [{"kernel": "cluster_adam", "mode": mode, "cluster": size, "threads": 1024, "us_per_step": us}
                  for mode, us in (("local", adam_us), ("update", adam_us + 1.0), ("sync", 0.3 * size))]
    s = kernel_cuda.summarize(lines, products=32)
    assert not s["failed_checks"]
    # the one-block estimate keeps the one-block chains and the grid's Adam
    assert s["floor_estimate"]["product_kernel"] == "chain_mma_tf32x3_split2_acc1_128threads"
    assert s["adam_us_per_step"]["cluster_adam_local_1024threads_cluster4"] == pytest.approx(6.0)
    est = s["cluster_estimates"]
    assert sorted(est) == ["2", "4", "any"]
    assert est["4"]["product_kernel"] == "chain_cluster_tf32x3_split1_acc3_64threads_cluster4"
    assert est["4"]["us_per_product"] == pytest.approx(0.4)
    assert est["4"]["us_per_step"] == pytest.approx(32 * 0.4 + 6.0)
    assert est["2"]["us_per_step"] == pytest.approx(32 * 0.5 + 9.0)
    assert est["2"]["barrier_alone_us"] == pytest.approx(0.6)
    # any design: the fastest product (cluster of 4) with the fastest Adam from one block's gradient
    # (the cluster of 4's "update", 7.0, against the grid's 7.0 and the cluster of 2's 10.0)
    assert est["any"]["us_per_product"] == pytest.approx(0.4)
    assert est["any"]["us_per_step"] == pytest.approx(32 * 0.4 + 7.0)
    # a cluster whose blocks shared a multiprocessor fails its check: another design than the one named
    shared = [dict(r, distinct_sms=1) if r.get("check") == "chain_cluster" and r["cluster"] == 4 else r
              for r in lines]
    failed = kernel_cuda.summarize(shared, products=32)["failed_checks"]
    assert [(c["check"], c["cluster"]) for c in failed] == [("chain_cluster", 4)]


def test_chains_side_by_side_get_fits_of_their_own_and_stay_out_of_the_serial_estimates():
    """chains_mma (several chains at once in one block): a fit per number of chains, its check
    covers every chain, and its µs per product (of each chain) never stands for one dependent
    product in the estimates, even when it is the smallest."""
    lines = _lines()
    for concurrent, per_product in ((2, 0.1), (4, 0.2)):
        lines.append({"check": "chains_mma", "precision": "tf32x3", "nsplit": 2, "accumulators": 3, "cluster": 1,
                      "distinct_sms": 1, "concurrent": concurrent, "products": 4, "max_rel_err": 1e-6,
                      "max_err_over_bound": 1e-2})
        lines += [{"kernel": "chains_mma", "precision": "tf32x3", "nsplit": 2, "accumulators": 3,
                   "threads": 128 * concurrent, "cluster": 1, "concurrent": concurrent, "chain": c, "steps": 10,
                   "us_per_iteration": 0.1 + per_product * c} for c in (1, 8, 32)]
    s = kernel_cuda.summarize(lines, products=32)
    assert not s["failed_checks"]
    fit = s["chain_fits"]["chains_mma_tf32x3_split2_acc3_512threads_4chains"]
    assert fit["us_per_product"] == pytest.approx(0.2) and fit["concurrent"] == 4
    assert s["chain_fits"]["chain_mma_tf32x3_split2_acc1_128threads"]["concurrent"] == 1
    assert s["floor_estimate"]["product_kernel"] == "chain_mma_tf32x3_split2_acc1_128threads"
    bad = [dict(r, max_err_over_bound=1.2) if r.get("check") == "chains_mma" and r["concurrent"] == 4 else r
           for r in lines]
    assert [(c["check"], c["concurrent"]) for c in kernel_cuda.summarize(bad, products=32)["failed_checks"]] == [
        ("chains_mma", 4)]


def _seed_lines(errs):
    """The many-seed kernel's lines: a per-seed Adam check with errors ``errs`` (relative to each
    seed's update) and timings for 1 and 256 seeds, two variants."""
    n = len(errs)
    lines = [{"check": "adam_seed_steps", "nsplit": 2, "threads": 256, "seeds": n, "steps": 5,
              "max_err_over_update": list(errs), "max_abs_w": [0.4] * n, "max_update": [5e-3] * n}]
    for nsplit, us in ((1, {0: 30.0, 32: 80.0}), (2, {0: 28.0, 32: 60.0})):
        for seeds in (1, 256):
            for products in (0, 32):
                lines.append({"kernel": "seed_steps", "precision": "tf32x3", "nsplit": nsplit, "threads": 256,
                              "blocks_per_sm": 2, "seeds": seeds, "products": products, "n": 22664,
                              "steps": 500, "us_per_step": us[products] / (10 if seeds == 1 else 1)})
    return lines


def test_many_seed_summary_checks_every_seed_and_estimates_a_run():
    bound = kernel_cuda.adam_bound(5, 0.4, 5e-3)
    s = kernel_cuda.summarize(_lines() + _seed_lines([bound / 10] * 3), products=32, run_steps=1000)
    assert not s["failed_checks"]
    e = s["seed_steps"]
    # the fastest variant at the largest seed count, with the products and with Adam alone
    assert e["seeds"] == 256 and e["step"]["variant"] == "split2_256threads"
    assert e["step"]["us_per_step"] == 60.0 and e["step"]["run_s"] == pytest.approx(60.0 * 1000 * 1e-6)
    assert e["adam_alone"]["us_per_step"] == 28.0
    assert e["us_per_step"]["split1_256threads_1seeds_32products"] == pytest.approx(8.0)
    assert e["chains_not_finite"] == []
    # a timed chain that ended non-finite is named; a seed chain check goes through like the others
    lines = _lines() + _seed_lines([bound / 10] * 3)
    lines[-1] = {**lines[-1], "out_finite": False}
    lines.append({"check": "chain_seed_steps", "precision": "tf32x3", "nsplit": 2, "accumulators": 3,
                  "threads": 256, "seeds": 3, "steps": 2, "products": 2, "first_slot": 4, "max_rel_err": 1e-6,
                  "max_err_over_bound": 2.5, "max_bound_over_max_h": 3e-4})
    s = kernel_cuda.summarize(lines, products=32)
    assert s["seed_steps"]["chains_not_finite"] == ["split2_256threads_256seeds_32products"]
    assert [c["check"] for c in s["failed_checks"]] == ["chain_seed_steps"]
    # one seed beyond its own bound fails the check, and the check names it
    bad = kernel_cuda.summarize(_lines() + _seed_lines([bound / 10, bound * 1.01, bound / 10]), products=32)
    assert [(c["check"], c["worst_seed"]) for c in bad["failed_checks"]] == [("adam_seed_steps", 1)]


def test_one_seed_whole_step_kernels_are_summarized_per_design():
    """grid_step and cluster_step (one seed, one program each) beside seed_steps at one seed: per
    design its fastest variant with the products, its time without them, and the fastest design;
    their checks go through like the others', and a cluster whose blocks shared a multiprocessor
    fails."""
    bound = kernel_cuda.adam_bound(5, 0.4, 5e-3)
    lines = _lines() + _seed_lines([bound / 10] * 3)
    timed = {("grid_step", None, 256): (20.0, 41.0), ("grid_step", None, 512): (15.0, 33.0),
             ("cluster_step", 2, 256): (6.0, 27.0), ("cluster_step", 8, 512): (4.0, 26.5),
             ("cluster_step_presplit", 4, 512): (2.0, 5.5)}
    for (kernel, cluster, threads), (alone, step) in timed.items():
        extra = {"cluster": cluster} if cluster else {}
        checked = {**extra, "distinct_sms": cluster} if cluster else {}
        lines.append({"check": f"chain_{kernel}", "precision": "tf32x3", "nsplit": 2, "accumulators": 3,
                      "threads": threads, "seeds": 1, "steps": 1, "products": 4, "first_slot": 0,
                      "max_rel_err": 1e-6, "max_err_over_bound": 1e-2, "max_bound_over_max_h": 3e-4, **checked})
        lines.append({"check": f"adam_{kernel}", "nsplit": 2, "threads": threads, "seeds": 1, "steps": 5,
                      "max_err_over_update": [bound / 10], "max_abs_w": [0.4], "max_update": [5e-3], **checked})
        lines += [{"kernel": kernel, "precision": "tf32x3", "nsplit": 2, "threads": threads, "blocks_per_sm": 1,
                   "blocks": cluster or 132, "seeds": 1, "products": p, "n": 22664, "steps": 500,
                   "us_per_step": us, **extra} for p, us in ((0, alone), (32, step))]
    s = kernel_cuda.summarize(lines, products=32)
    assert not s["failed_checks"]
    e = s["one_seed_steps"]
    # seed_steps at one seed (the one-block design, _seed_lines: 8.0 and 6.0 µs) is one of them
    assert sorted(e["designs"]) == ["cluster_step_cluster2", "cluster_step_cluster8", "cluster_step_presplit_cluster4",
                                    "grid_step", "seed_steps"]
    assert e["designs"]["grid_step"] == {"variant": "grid_step_split2_512threads", "us_per_step": 33.0,
                                         "adam_alone_us": 15.0}
    assert e["designs"]["seed_steps"]["us_per_step"] == pytest.approx(6.0)
    assert e["variants"]["cluster_step_cluster8_split2_512threads"] == {"adam_alone": 4.0, "products": 26.5}
    assert e["fastest"] == "cluster_step_presplit_cluster4"
    # the 256-seed rows stay out of it, and the many-seed summary keeps to seed_steps
    assert s["seed_steps"]["step"]["us_per_step"] == 60.0
    shared = [dict(r, distinct_sms=1) if r.get("check") == "adam_cluster_step" and r["cluster"] == 8 else r
              for r in lines]
    failed = kernel_cuda.summarize(shared, products=32)["failed_checks"]
    assert [(c["check"], c["cluster"]) for c in failed] == [("adam_cluster_step", 8)]
    # the moments: within their bound the check holds; beyond it, or NaN, it fails
    within = kernel_cuda.moment_bound(5) / 2
    moments = [dict(r, m_max_rel_err=[within], v_max_rel_err=[within]) if r.get("check") == "adam_grid_step" else r
               for r in lines]
    (c,) = [c for c in kernel_cuda.summarize(moments, products=32)["checks"]
            if c["check"] == "adam_grid_step" and c["threads"] == 256]
    assert c["ok"] and c["m_max_rel_err"] == within and c["moment_bound"] == kernel_cuda.moment_bound(5)
    for bad_m in (kernel_cuda.moment_bound(5) * 1.5, float("nan")):
        bad = [dict(r, m_max_rel_err=[bad_m]) if r.get("check") == "adam_grid_step" and r["threads"] == 512 else r
               for r in moments]
        assert [(c["check"], c["threads"]) for c in kernel_cuda.summarize(bad, products=32)["failed_checks"]] == [
            ("adam_grid_step", 512)]
    # a variant too large for shared memory is listed, not an error
    skipped = {"skipped": "cluster_step", "nsplit": 2, "threads": 256, "n": 40000, "reason": "too large"}
    assert kernel_cuda.summarize(lines + [skipped], products=32)["skipped"] == [skipped]


def _tf32(x):
    """cvt.rna.tf32.f32: float32 rounded to 10 mantissa bits, ties away from zero."""
    bits = np.asarray(x, np.float32).view(np.uint32)
    return ((bits + np.uint32(0x1000)) & np.uint32(0xFFFFE000)).view(np.float32)


@pytest.mark.parametrize("presplit", [False, True])
def test_moment_bound_holds_for_float32_adam_and_catches_a_stale_gradient(presplit):
    """The moments after five float32 Adam steps with the kernels' synthetic gradient (formed from
    w, or from its TF32 parts hi + lo as cluster_step_presplit forms it) lie within moment_bound of
    the float64 moments; a gradient one step stale does not."""
    rng = np.random.default_rng(3)
    w0 = (np.sqrt(2.0 / (1.0 + 0.2 ** 2) / 64) * rng.standard_normal(22_664)).astype(np.float32)
    c = lambda x, dt: dt(np.float32(x))  # noqa: E731  (the kernels' float32 constants)

    def run(dtype, stale=False, split=False):
        w, m, v, g_prev = w0.astype(dtype), np.zeros(w0.shape, dtype), np.zeros(w0.shape, dtype), None
        for s in range(5):
            ws = w
            if split:
                hi = _tf32(w.astype(np.float32))
                ws = hi + _tf32(w.astype(np.float32) - hi)
            g = c(1e-3, dtype) * np.abs(ws).astype(dtype) + c(1e-4, dtype)
            g, g_prev = (g_prev if stale and g_prev is not None else g), g
            m = c(0.9, dtype) * m + (dtype(1) - c(0.9, dtype)) * g
            v = c(0.999, dtype) * v + (dtype(1) - c(0.999, dtype)) * g * g
            c1 = dtype(1) / (dtype(1) - c(0.9, dtype) ** dtype(s + 1))
            c2 = dtype(1) / (dtype(1) - c(0.999, dtype) ** dtype(s + 1))
            w = w - c(1e-3, dtype) * (m * c1) / (np.sqrt(v * c2) + c(1e-8, dtype))
        return m, v

    m64, v64 = run(np.float64)
    rel = lambda a, ref: float(np.max(np.abs(a - ref)) / np.max(np.abs(ref)))  # noqa: E731
    m32, v32 = run(np.float32, split=presplit)
    bound = kernel_cuda.moment_bound(5)
    assert rel(m32, m64) <= bound and rel(v32, v64) <= bound
    m_stale, _ = run(np.float32, stale=True, split=presplit)
    assert rel(m_stale, m64) > 100 * bound


def test_one_seed_check_reports_scalars_and_a_nan_fails_it():
    bound = kernel_cuda.adam_bound(5, 0.4, 5e-3)
    (c,) = [c for c in kernel_cuda.summarize(_lines() + _seed_lines([bound / 10]), products=32)["checks"]
            if c["check"] == "adam_seed_steps"]
    assert c["ok"] and c["worst_seed"] == 0 and c["max_err_over_update"] == pytest.approx(bound / 10)
    # C's printf writes NaN as "nan" / "-nan": read as NaN, which fails its check (not the parse)
    line = ('{"check": "adam_seed_steps", "nsplit": 2, "threads": 256, "seeds": 2, "steps": 5, '
            '"max_err_over_update": [1.0e-05, -nan], "max_abs_w": [0.4, inf], "max_update": [5e-3, 5e-3]}')
    parsed = kernel_cuda.parse_lines(line + "\nnot json\n")
    assert len(parsed) == 1 and np.isinf(parsed[0]["max_abs_w"][1])
    assert kernel_cuda.parse_lines('{"a": -inf, "b": "info"}') == [{"a": -np.inf, "b": "info"}]
    bad = kernel_cuda.summarize(_lines() + parsed, products=32)
    assert [(c["check"], c["worst_seed"]) for c in bad["failed_checks"]] == [("adam_seed_steps", 1)]


def test_the_synthetic_gradient_keeps_adams_float32_error_within_its_bound():
    """Where the earlier gradient 1e-3·w + 1e-4 crosses zero (w = −0.1), Adam's update
    g / (|g| + ε) turns on float32's rounding of g, beyond ``adam_bound``; 1e-3·|w| + 1e-4 never
    nears zero. Two seeds of 1 000 weights, the second holding float32(−0.1)."""
    w0 = (0.17 * np.random.default_rng(1).standard_normal((2, 1000))).astype(np.float32)
    w0[1, 10] = np.float32(-0.1)
    for absolute, over in ((True, [False, False]), (False, [False, True])):
        err, abs_w, update = kernel_cuda.adam_float32_error(w0, 5, absolute)
        bounds = [kernel_cuda.adam_bound(5, a, u) for a, u in zip(abs_w, update)]
        assert [bool(e > b) for e, b in zip(err, bounds)] == over


def test_native_resolves_to_sm90a_on_hopper_only(monkeypatch):
    import subprocess

    def answers(stdout):
        return lambda *a, **k: subprocess.CompletedProcess(a, 0, stdout=stdout, stderr="")

    for stdout, arch in (("9.0\n", "sm_90a"), ("9.0\n9.0\n", "sm_90a"), ("9.0\n8.0\n", "native"),
                         ("8.9\n", "native"), ("", "native")):
        monkeypatch.setattr(kernel_cuda.subprocess, "run", answers(stdout))
        assert kernel_cuda.resolve_arch("native") == arch
    assert kernel_cuda.resolve_arch("sm_80") == "sm_80"

    def missing(*a, **k):
        raise FileNotFoundError("nvidia-smi")

    monkeypatch.setattr(kernel_cuda.subprocess, "run", missing)
    assert kernel_cuda.resolve_arch("native") == "native"
    assert kernel_cuda.nvcc_arch_flags("sm_90a")[-1] == "-DKERNEL_CUDA_WGMMA"
    assert kernel_cuda.nvcc_arch_flags("sm_90") == ["-arch=sm_90"]


def test_adam_bound_and_line_fit():
    # Adam's float32 update after 5 steps, weights of 0.4, updates of 5e-3: a few times 1e-4,
    # dominated by the bias correction's cancellation at the first step
    assert 1e-4 < kernel_cuda.adam_bound(5, 0.4, 5e-3) < 1e-3
    assert kernel_cuda.adam_bound(5, 0.4, 5e-3, b2=0.9) < kernel_cuda.adam_bound(5, 0.4, 5e-3)
    with pytest.raises(ValueError, match="two distinct chain lengths"):
        kernel_cuda.line_fit([(8, 1.0), (8, 2.0)])


def test_missing_compiler_and_bad_arguments_are_one_line(capsys):
    with pytest.raises(SystemExit, match="'/nonexistent/nvcc' was not found"):
        kernel_cuda.main(["--nvcc", "/nonexistent/nvcc"])
    with pytest.raises(SystemExit):
        kernel_cuda.main(["--chain", "8"])
    assert "at least two distinct positive lengths" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        kernel_cuda.main(["--seed-n", "4098"])
    assert "multiple of 4" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        kernel_cuda.main(["--seeds", "0,256"])
    assert "positive seed counts" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        kernel_cuda.main(["--seed-n", "4092"])
    assert "at least one 64 × 64 weight slot" in capsys.readouterr().err


def test_emulation_runs_without_a_gpu(tmp_path, capsys):
    out = tmp_path / "emulate.json"
    assert kernel_cuda.main(["--emulate", "--seeds", "2", "--seed-n", "4096", "--out", str(out)]) == 0
    assert "gradient 1e-3*|w|+1e-4: worst seed" in capsys.readouterr().out
    result = json.loads(out.read_text())["emulate"]
    assert result["1e-3*|w|+1e-4"]["seeds_over_bound"] == 0


@pytest.mark.skipif(shutil.which("nvcc") is None, reason="nvcc not installed")
@pytest.mark.parametrize("arch, wgmma", [("sm_90", False), ("sm_90a", True)])
def test_kernels_build_for_hopper_without_spills(tmp_path, arch, wgmma):
    exe, report = kernel_cuda.build("nvcc", arch, str(tmp_path), device_only=True)
    assert exe.exists()
    for kernel in ("chain_fma", "chain_mma", "chain_cluster", "grid_adam", "block_adam", "cluster_adam", "seed_steps"):
        assert kernel in report
    # the warpgroup products need the architecture-specific target
    assert ("chain_wgmma" in report) == wgmma
    assert kernel_cuda.spills(report) == 0

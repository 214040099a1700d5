"""Tolerances derived from float64 rounding and the conditioning of the computation.

Two programs that compute the same thing in different orders (jit vs eager, vmap vs a loop,
batched vs single factorisations, an unrolled vs a rolled loop, gmr_jax vs a numpy
transcription) are not bit-equal: each rounds differently, by up to ε = 2.2e-16 relative per
operation, and XLA chooses the order of sums, the fusions and the use of FMA per CPU vector ISA
and per program. A fixed tolerance that one CPU happens to meet fails on another. The tolerances
here come from the computation instead:

* ``linear_tol``: the forward-error bound of a backward-stable dense computation,
  c·n·ε·κ (n: the length of the longest sum or factorisation, κ: the condition number);
* ``measured_tol``: for iterative programs (EM, η search, Adam, rollouts, a whole GPS
  iteration) no closed-form bound is practical. Rounding differences anywhere in a program are,
  to first order, perturbations of relative size ε of its intermediate values, amplified on their
  way to the outputs like a perturbation of the inputs of the same size. So the program is run
  again on inputs perturbed by ε relative (two random perturbations), the spread of each output
  is measured, and the tolerance is that spread times a safety factor (for the number of
  operations that round differently and the few-ε size of each difference), plus the same factor
  times ε·|output| (the rounding of the output itself, which no input perturbation shows).

Comparisons are normwise per array: max|a − b| ≤ tol·(scale of the array), the measure that
backward-stable algorithms guarantee; an elementwise relative test fails on the small entries
that cancellation produces (e.g. one entry of 6336 of a policy's kernel, 1.8e-7 relative while
the array agrees to 6e-10 of its largest entry). NaN and ±inf must sit at the same places in both.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

EPS = float(np.finfo(np.float64).eps)

# XLA's default CPU code generator as compile options (``Lowered.compile(compiler_options=...)``),
# for the tests whose property is about it: the suite otherwise compiles with LLVM's level 0 and
# without XLA's CPU fusion emitters (tests/conftest.py).
XLA_DEFAULT_CPU_CODEGEN = {"xla_backend_optimization_level": 3, "xla_cpu_use_fusion_emitters": True}

# Safety factor of ``measured_tol``. Rounding differs between two programs at every operation,
# each by a few ε (a sum of n terms reassociated: up to n·ε, typically √n·ε), and those
# differences add up; measured on a 2-core AMD EPYC (AVX-512), whole GPS iterations jit vs eager
# and the numpy transcriptions vs gmr_jax differ by at most 4× the ε-perturbation spread of
# their outputs. 100 leaves a 25× margin for other vector ISAs and XLA versions while every
# tolerance stays far below a real defect (the tests check their tolerances' size).
SAFETY = 100.0


def _is_float(a) -> bool:
    dtype = getattr(a, "dtype", None)
    if dtype is None:  # a Python number, or an object such as a configuration
        dtype = np.asarray(a).dtype
    try:
        return bool(np.issubdtype(dtype, np.floating))
    except TypeError:  # PRNG key arrays have an extended dtype
        return False


def _key_data(a):
    if jnp.issubdtype(jnp.asarray(a).dtype, jax.dtypes.prng_key):
        return jax.random.key_data(a)
    return a


def linear_tol(kappa: float, n: int, c: float = 4.0) -> float:
    """Relative normwise forward error bound c·n·ε·κ of a backward-stable computation of size n
    (sums of n terms, an n×n factorisation or solve) with condition number κ ≥ 1."""
    return c * n * EPS * max(float(kappa), 1.0)


def perturb(tree, seed: int, rel: float = EPS):
    """Every floating-point leaf x → x·(1 + rel·u), u uniform in [−1, 1] (a fixed seed per call);
    other leaves (integers, booleans, PRNG keys) unchanged."""
    leaves, treedef = jax.tree_util.tree_flatten(tree)
    rng = np.random.default_rng(seed)
    out = []
    for a in leaves:
        if _is_float(a):
            a = jnp.asarray(a)
            u = rng.uniform(-1.0, 1.0, a.shape)
            a = a * (1.0 + rel * u).astype(a.dtype)
        out.append(a)
    return jax.tree_util.tree_unflatten(treedef, out)


def _max_abs_diff(a, b) -> float:
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    both = np.isfinite(a) & np.isfinite(b)
    return float(np.max(np.abs(np.where(both, a, 0.0) - np.where(both, b, 0.0)), initial=0.0))


def _scale(a) -> float:
    a = np.asarray(a, np.float64)
    return float(np.max(np.abs(a), where=np.isfinite(a), initial=0.0))


def measured_tol(f, args: tuple, factor: float, seeds=(101, 102)):
    """Run ``f(*args)`` and ``f(*perturb(args))``; return (the reference output, per-leaf
    absolute tolerances): factor·(the largest spread over the perturbations + ε·max|leaf|).

    ``f`` must be deterministic in ``args`` (the same keys go to every run)."""
    ref = f(*args)
    leaves = jax.tree_util.tree_leaves(ref)
    spread = [0.0] * len(leaves)
    for s in seeds:
        other = jax.tree_util.tree_leaves(f(*perturb(args, s)))
        for i, (a, b) in enumerate(zip(leaves, other)):
            if _is_float(a):
                spread[i] = max(spread[i], _max_abs_diff(a, b))
    tol = [factor * (sp + EPS * _scale(a)) if _is_float(a) else 0.0 for sp, a in zip(spread, leaves)]
    return ref, tol


def scale_tol(tree, rel: float = 1e-6) -> list:
    """Per-leaf absolute tolerances ``rel`` · max|leaf| (for ``assert_trees_within``): the
    tolerance of whole runs that differ by round-off only (a program split into parts, another
    process), far below what a change of the computation moves."""
    return [rel * _scale(a) for a in jax.tree_util.tree_leaves(tree)]


def assert_close(got, ref, tol: float, err_msg: str = ""):
    """Normwise: max|got − ref| ≤ tol·max|ref| (absolute ``tol`` where ref is all zeros), with NaN
    and ±inf at the same places."""
    got, ref = np.asarray(got, np.float64), np.asarray(ref, np.float64)
    assert got.shape == ref.shape, (got.shape, ref.shape, err_msg)
    np.testing.assert_array_equal(np.isnan(got), np.isnan(ref), err_msg=f"NaN pattern {err_msg}")
    inf = np.isinf(ref) | np.isinf(got)
    np.testing.assert_array_equal(got[inf], ref[inf], err_msg=f"inf entries {err_msg}")
    scale = _scale(ref) or 1.0
    err = _max_abs_diff(got, ref)
    assert err <= tol * scale, f"{err_msg}: max|Δ| = {err:.3e} > {tol:.3e}·{scale:.3e}"


def assert_trees_within(got, ref, tol):
    """Leaf by leaf: floating-point leaves within their absolute tolerance (a list as returned by
    ``measured_tol``, or one number for all), NaN/inf at the same places; integer, boolean and
    key leaves exactly equal (discrete decisions must not change)."""
    la, ta = jax.tree_util.tree_flatten(got)
    lb, tb = jax.tree_util.tree_flatten(ref)
    assert ta == tb
    tols = tol if isinstance(tol, (list, tuple)) else [tol] * len(lb)
    for i, (a, b, t) in enumerate(zip(la, lb, tols)):
        a, b = np.asarray(_key_data(a)), np.asarray(_key_data(b))
        path = f"leaf {i} of {tb}"[:300]
        if not _is_float(b):
            np.testing.assert_array_equal(a, b, err_msg=path)
            continue
        assert a.shape == b.shape, path
        np.testing.assert_array_equal(np.isnan(a), np.isnan(b), err_msg=f"NaN pattern, {path}")
        inf = np.isinf(a) | np.isinf(b)
        np.testing.assert_array_equal(a[inf], b[inf], err_msg=f"inf entries, {path}")
        err = _max_abs_diff(a, b)
        assert err <= t, f"max|Δ| = {err:.3e} > tolerance {t:.3e} (scale {_scale(b):.3e}), {path}"


def assert_tolerances_small(ref, tol, max_rel: float):
    """Every floating-point leaf's tolerance is at most ``max_rel`` of the leaf's largest entry:
    a measured tolerance must stay far below what a real defect would change (a perturbation
    that flipped a discrete decision of the program would show up here, not pass silently)."""
    for i, (a, t) in enumerate(zip(jax.tree_util.tree_leaves(ref), tol)):
        if _is_float(a) and _scale(a) > 0:
            assert t <= max_rel * _scale(a), f"leaf {i}: tolerance {t:.3e} > {max_rel:g}·{_scale(a):.3e}"


def affine_tol(K, x, k) -> float:
    """Absolute bound on the difference of two evaluations of K x + k (batched or not) that sum
    in different orders: c·(n + 1)·ε·max(|K||x| + |k|), n = len(x) (tests/tolerances.py)."""
    K, x, k = (np.asarray(a, np.float64) for a in (K, x, k))
    size = np.einsum("...ij,...j->...i", np.abs(K), np.abs(x)) + np.abs(k)
    return linear_tol(1.0, x.shape[-1] + 1) * float(size.max())

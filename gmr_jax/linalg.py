"""Small dense linear algebra: Cholesky factors and triangular solves, batched over leading axes.

Why not ``jnp.linalg.cholesky`` / ``jax.scipy.linalg.solve_triangular`` directly: on the CPU,
jaxlib runs a batched LAPACK call (potrf, trsm, …) of more than about 2·10⁵ flops by scheduling
chunks of the batch on XLA's intra-op thread pool and then *blocking a pool thread* until they
finish. When as many such calls run concurrently as the pool has threads (XLA:CPU executes
independent operations of one program in parallel; a 2-core machine has a 2-thread pool), every
pool thread waits for work that no thread is left to run, and the process hangs with all threads
idle. We observed exactly this (gdb: both ``tf_XLAEigen`` threads in ``jax::ParallelBatchMap``
of ``TriMatrixEquationSolver``) in vmapped MDGPS iterations on a 2-core CPU.

So on the CPU these functions use a column-by-column algorithm written in ``jax.numpy``
(``lax.fori_loop`` over the n ≤ ~30 columns, each step vectorised over the batch): no LAPACK
call, no thread pool, and the same arithmetic up to rounding (float64 results agree with LAPACK
to ~1e-15 relative; see tests/test_linalg.py). On other platforms (GPU) they lower to the
usual cuSOLVER/cuBLAS kernels through ``lax.platform_dependent``.

Conventions follow ``jnp.linalg.cholesky``: the input is symmetrised, and a matrix that is not
positive definite gives a factor that is NaN (callers test ``isfinite``).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jax import lax
from jax.scipy import linalg as jsl

Array = jnp.ndarray


def _mT(a: Array) -> Array:
    return jnp.swapaxes(a, -1, -2)


def sym(a: Array) -> Array:
    """The symmetric part ½(A + Aᵀ) of [..., n, n] (what must be symmetric is made so exactly)."""
    return 0.5 * (a + _mT(a))


def all_finite(tree) -> Array:
    """[] bool: every inexact leaf of a pytree (or an array) is finite."""
    leaves = [jnp.all(jnp.isfinite(x)) for x in jax.tree_util.tree_leaves(tree)
              if jnp.issubdtype(jnp.asarray(x).dtype, jnp.inexact)]
    return jnp.all(jnp.stack(leaves)) if leaves else jnp.asarray(True)


def cholesky_floor(a: Array) -> Array:
    """[..., n] per diagonal entry, the shift 2n(n+1)·ε·a_ii below which Cholesky of a [..., n, n]
    in its own precision (ε = machine epsilon of a.dtype) may break down on rounding alone.

    Why this size: with H = D⁻¹AD⁻¹, D² = diag(A), Cholesky in precision ε runs to completion if
    λ_min(H) > nγ_{n+1}/(1 − γ_{n+1}) ≈ n(n+1)ε (Demmel; Higham, *Accuracy and Stability of
    Numerical Algorithms*, 2002, Thm 10.7). Adding c·a_ii to every diagonal entry gives
    H' = (H + cI)/(1 + c), so λ_min(H') ≥ c/(1 + c) whatever A's conditioning; c = 2n(n+1)ε
    leaves a factor 2 for the rounding in forming A itself. A fitted covariance of rank-deficient
    data (the transitions of a deterministic plant) has λ_min(H) near its absolute ridge (1e-6):
    above the float64 floor (30×30: 4e-13) by far, below the float32 one (2e-4).
    """
    a = jnp.asarray(a)
    n = a.shape[-1]
    return 2.0 * n * (n + 1) * jnp.finfo(a.dtype).eps * jnp.diagonal(a, axis1=-2, axis2=-1)


def ridge(a: Array, value) -> Array:
    """a + diag(max(value, :func:`cholesky_floor` (a))) for [..., n, n]: the absolute ridge
    ``value``, raised per entry to what the precision needs for a Cholesky factorisation to
    succeed. In float64 the floor lies far below a 1e-6 ridge (for any a_ii < 10⁶), so the result
    is bitwise a + value·I; in float32 it is what keeps a rank-deficient fit factorisable.
    """
    a = jnp.asarray(a)
    shift = jnp.maximum(jnp.asarray(value, a.dtype), cholesky_floor(a))
    return a + shift[..., :, None] * jnp.eye(a.shape[-1], dtype=a.dtype)


def _cholesky_columns(a: Array) -> Array:
    """Lower Cholesky factor of a [..., n, n] by the left-looking column algorithm."""
    n = a.shape[-1]
    a = sym(a)
    rows = jnp.arange(n)

    def body(j, low):
        # Columns ≥ j of `low` are still zero, so row_j · row_i sums over k < j only.
        row_j = lax.dynamic_index_in_dim(low, j, axis=-2, keepdims=False)  # [..., n]
        a_j = lax.dynamic_index_in_dim(a, j, axis=-1, keepdims=False)  # [..., n]
        v = a_j - jnp.einsum("...ik,...k->...i", low, row_j, precision=lax.Precision.HIGHEST)
        pivot = jnp.sqrt(lax.dynamic_index_in_dim(v, j, axis=-1, keepdims=False))  # NaN if < 0
        col = jnp.where(rows >= j, v / pivot[..., None], 0.0)
        return low + col[..., :, None] * (rows == j).astype(a.dtype)

    low = lax.fori_loop(0, n, body, jnp.zeros_like(a))
    # A non-PD input gives an all-NaN factor, as LAPACK through jnp.linalg.cholesky does.
    ok = jnp.all(jnp.isfinite(low), axis=(-2, -1), keepdims=True)
    return jnp.where(ok, low, jnp.nan)


def _solve_lower_columns(low: Array, b: Array, forward: bool) -> Array:
    """x with low·x = b by substitution (forward: rows 0…n−1; else n−1…0). b [..., n, m]."""
    n = low.shape[-1]
    rows = jnp.arange(n)

    def body(s, x):
        i = s if forward else n - 1 - s
        row = lax.dynamic_index_in_dim(low, i, axis=-2, keepdims=False)  # [..., n]
        b_i = lax.dynamic_index_in_dim(b, i, axis=-2, keepdims=False)  # [..., m]
        diag = lax.dynamic_index_in_dim(row, i, axis=-1, keepdims=False)  # [...]
        # Rows of x not yet solved are zero, so the full row product is the partial sum.
        x_i = (b_i - jnp.einsum("...k,...km->...m", row, x, precision=lax.Precision.HIGHEST)) / diag[..., None]
        return x + (rows == i).astype(b.dtype)[:, None] * x_i[..., None, :]

    return lax.fori_loop(0, n, body, jnp.zeros_like(b))


def _solve_triangular_columns(a: Array, b: Array, lower: bool, trans: bool) -> Array:
    if trans:  # aᵀ is triangular of the other kind
        a, lower = _mT(a), not lower
    if lower:
        return _solve_lower_columns(a, b, forward=True)
    # An upper system U x = b is a lower one with rows and columns reversed.
    rev = lambda m: jnp.flip(m, axis=(-2, -1))  # noqa: E731
    return jnp.flip(_solve_lower_columns(rev(a), jnp.flip(b, axis=-2), forward=True), axis=-2)


def cholesky(a: Array) -> Array:
    """Lower Cholesky factor L of symmetric PD matrices, a = L Lᵀ.

    Args:
      a: [..., n, n]; symmetrised as ½(a + aᵀ) first.
    Returns:
      [..., n, n] lower triangular; all NaN for a matrix that is not positive definite.
    """
    a = jnp.asarray(a)
    return lax.platform_dependent(a, cpu=_cholesky_columns, default=jnp.linalg.cholesky)


def solve_triangular(a: Array, b: Array, *, lower: bool, trans: bool = False) -> Array:
    """x with op(a)·x = b for triangular a (op = transpose if ``trans``).

    Args:
      a: [..., n, n] lower (``lower=True``) or upper triangular; the other triangle is ignored.
      b: [..., n, m] right-hand sides (same leading axes as a).
      lower: which triangle of a holds the matrix.
      trans: solve aᵀ x = b instead.
    Returns:
      x [..., n, m].
    """
    a, b = jnp.asarray(a), jnp.asarray(b)
    if b.ndim != a.ndim or b.shape[-2] != a.shape[-1]:
        raise ValueError(f"solve_triangular: a {a.shape} and b {b.shape}: b must be [..., n, m]")
    tri = jnp.tril if lower else jnp.triu
    return lax.platform_dependent(
        tri(a), b,
        cpu=lambda a_, b_: _solve_triangular_columns(a_, b_, lower, trans),
        default=lambda a_, b_: jsl.solve_triangular(a_, b_, lower=lower, trans="T" if trans else 0))


def cho_solve(low: Array, b: Array) -> Array:
    """x with (L Lᵀ) x = b, given the lower Cholesky factor L [..., n, n]; b [..., n, m]."""
    return solve_triangular(low, solve_triangular(low, b, lower=True), lower=True, trans=True)

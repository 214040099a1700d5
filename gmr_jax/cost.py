"""Costs: ramps, l1/l2 and log-l2 norms, state / action / end-effector terms, quadratic expansion.

Numerics follow ``shared/reference/mdgps-toolbox.md`` §5 (cost terms) and §1.5 (expansion in
absolute coordinates, averaged over samples).

A cost is a :class:`CostFn`: calling it, ``cost_fn(x [dX], u [dU], t)``, gives the scalar per-step
cost ℓ_t(x, u) (``t`` a possibly traced integer index), and ``cost_fn.expand(x, u, t)`` gives its
local quadratic model at ŷ = [x; u] as ``(l [], c [dX + dU], C [dX + dU, dX + dU])``. Each term
supplies its own expansion so that the end-effector term can be Gauss–Newton (as the toolbox
does) while state and action terms give their exact derivatives; :func:`cost_sum` adds the
expansions. A plain function wrapped with :func:`from_function` is expanded by autodiff.

Every function here is jittable and vmappable; weights are Python/numpy constants that are cast
to the dtype of the state at evaluation time, so the same cost runs in float32 and float64.
"""

from __future__ import annotations

from typing import Callable, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from gmr_jax.types import QuadraticCost

Array = jax.Array

RAMP_MODES = ("constant", "linear", "quadratic", "final_only")
NORMS = ("l1l2", "logl2")


# ---------------------------------------------------------------------------------------------
# Ramps


def ramp(T: int, mode: str, final_multiplier: float = 1.0) -> np.ndarray:
    """Per-step multiplier of a term's weights (toolbox ``get_ramp_multiplier``).

    Args:
      T: horizon.
      mode: "constant" (ones), "linear" ((t+1)/T), "quadratic" (((t+1)/T)²) or "final_only"
        (one-hot at T−1).
      final_multiplier: the last entry is multiplied by it, for every mode.

    Returns:
      [T] float64 numpy array (a host constant; terms cast it to the state's dtype).
    """
    if mode not in RAMP_MODES:
        raise ValueError(f"ramp mode={mode!r}: allowed values are {RAMP_MODES}")
    if not isinstance(T, (int, np.integer)) or T < 1:
        raise ValueError(f"ramp T={T!r}: must be a positive integer")
    steps = np.arange(1, T + 1, dtype=np.float64) / T
    if mode == "constant":
        w = np.ones(T)
    elif mode == "linear":
        w = steps
    elif mode == "quadratic":
        w = steps**2
    else:
        w = np.zeros(T)
        w[-1] = 1.0
    # The toolbox computes linear/quadratic ramps in float32; we keep float64 on the host and
    # cast to the state's dtype when the cost is evaluated.
    w[-1] *= final_multiplier
    return w


# ---------------------------------------------------------------------------------------------
# Norms: value and derivatives with respect to the residual d


def _is_static_zero(value) -> bool:
    return isinstance(value, (int, float, np.floating, np.integer)) and float(value) == 0.0


def _l2_part(d: Array, wp: Array, l2):
    """The ½ l2 Σ wp_i d_i² part shared by both norms: (wp in d's dtype, (l, d1, d2))."""
    wp = jnp.asarray(wp, d.dtype)
    return wp, (0.5 * l2 * jnp.sum(wp * d * d), l2 * wp * d, l2 * jnp.diag(wp))


def l1l2_term(d: Array, wp: Array, l1, l2, alpha) -> tuple[Array, Array, Array]:
    """The toolbox ``evall1l2term`` for one time step (exact value, gradient and Hessian in d).

    With s = Σ (wp_i d_i)²:
      l  = ½ l2 Σ wp_i d_i² + l1 √(α + s)
      d1 = l2 wp⊙d + l1 (wp²⊙d)/√(α+s)
      d2 = l2 diag(wp) + l1 [diag(wp²)/√(α+s) − (wp²⊙d)(wp²⊙d)ᵀ/(α+s)^{3/2}]

    Args:
      d: [D] residual.
      wp: [D] ramp-weighted weights of this step.
      l1, l2, alpha: scalars (α > 0 whenever l1 ≠ 0).

    Returns:
      (l [], d1 [D], d2 [D, D]).
    """
    wp, (l, d1, d2) = _l2_part(d, wp, l2)
    if not _is_static_zero(l1):
        # Skipped when l1 is a literal 0 so that α = 0 cannot produce 0/0 at d = 0.
        w2d = wp * wp * d
        root = jnp.sqrt(alpha + jnp.sum((wp * d) ** 2))
        l = l + l1 * root
        d1 = d1 + l1 * w2d / root
        d2 = d2 + l1 * (jnp.diag(wp * wp) / root - jnp.outer(w2d, w2d) / root**3)
    return l, d1, d2


def logl2_term(d: Array, wp: Array, l1, l2, alpha) -> tuple[Array, Array, Array]:
    """The toolbox ``evallogl2term`` for one time step, with the exact Hessian.

    With s = Σ (wp_i d_i)²:
      l  = ½ l2 Σ wp_i d_i² + ½ l1 log(α + s)
      d1 = l2 wp⊙d + l1 (wp²⊙d)/(α+s)
      d2 = l2 diag(wp) + l1 [diag(wp²)/(α+s) − 2 (wp²⊙d)(wp²⊙d)ᵀ/(α+s)²]

    The toolbox omits the factor 2 on the outer product (it has a TODO there); the factor is
    restored here so that d2 is the true Hessian of l.

    Args / Returns: as :func:`l1l2_term`.
    """
    wp, (l, d1, d2) = _l2_part(d, wp, l2)
    if not _is_static_zero(l1):
        w2d = wp * wp * d
        denom = alpha + jnp.sum((wp * d) ** 2)
        l = l + 0.5 * l1 * jnp.log(denom)
        d1 = d1 + l1 * w2d / denom
        d2 = d2 + l1 * (jnp.diag(wp * wp) / denom - 2.0 * jnp.outer(w2d, w2d) / denom**2)
    return l, d1, d2


_NORM_FNS = {"l1l2": l1l2_term, "logl2": logl2_term}


def _norm_fn(norm: str):
    if norm not in _NORM_FNS:
        raise ValueError(f"norm={norm!r}: allowed values are {NORMS}")
    return _NORM_FNS[norm]


# ---------------------------------------------------------------------------------------------
# The cost container


Expansion = tuple[Array, Array, Array]


class CostFn:
    """A per-step cost ℓ_t(x, u) together with its local quadratic expansion.

    ``cost_fn(x [dX], u [dU], t) -> []`` is the true cost; ``cost_fn.expand(x, u, t)`` returns
    ``(l [], c [dX + dU], C [dX + dU, dX + dU])``: the value, the gradient and the (exact or
    Gauss–Newton) Hessian at ŷ = [x; u], in coordinates relative to ŷ. Instances hash by
    identity, so a cost may be a static argument of ``jax.jit``.
    """

    def __init__(self, value: Callable, expand: Callable | None = None):
        self.value = value
        self.expand = expand if expand is not None else _autodiff_expansion(value)

    def __call__(self, x: Array, u: Array, t) -> Array:
        return self.value(x, u, t)


def _autodiff_expansion(value: Callable) -> Callable:
    """Exact second-order expansion of ``value(x, u, t)`` in y = [x; u] by autodiff."""

    def expand(x, u, t):
        dX = x.shape[-1]
        y = jnp.concatenate([x, u.astype(x.dtype)])
        f = lambda y_: value(y_[:dX], y_[dX:], t)
        l, c = jax.value_and_grad(f)(y)
        C = jax.hessian(f)(y)
        return l, c, 0.5 * (C + C.T)

    return expand


def from_function(fn: Callable) -> CostFn:
    """Wrap a plain ``fn(x [dX], u [dU], t) -> []`` as a :class:`CostFn` expanded by autodiff."""
    return fn if isinstance(fn, CostFn) else CostFn(fn)


def _as_cost(fn) -> CostFn:
    return from_function(fn)


def _pad_x_block(gx: Array, Hx: Array, dU: int) -> tuple[Array, Array]:
    """Embed a state-block gradient [dX] and Hessian [dX, dX] into y = [x; u] coordinates."""
    c = jnp.concatenate([gx, jnp.zeros((dU,), gx.dtype)])
    C = jnp.pad(Hx, ((0, dU), (0, dU)))
    return c, C


# ---------------------------------------------------------------------------------------------
# Terms


def wrap_angles(d: Array, entries: Sequence[int]) -> Array:
    """d [..., dX] with the entries ``entries`` (angle differences of continuous joints) wrapped to
    [−π, π), the shortest way round; the other entries unchanged. ∂/∂d is 1 wherever the wrap is
    continuous (everywhere except at ±π), so a quadratic expansion in d stays exact there."""
    if not entries:
        return d
    d = jnp.asarray(d)
    idx = np.asarray(entries)
    two_pi = jnp.asarray(2 * np.pi, d.dtype)
    wrapped = d[..., idx] - two_pi * jnp.floor((d[..., idx] + two_pi / 2) / two_pi)
    # unique only if no two entries name the same element (negative entries count from the end)
    return d.at[..., idx].set(wrapped, unique_indices=len(np.unique(idx % d.shape[-1])) == len(idx))


def state_cost(target, wp, l1, l2, alpha, ramp_w, norm: str = "l1l2",
               wrapped: Sequence[int] = ()) -> CostFn:
    """Toolbox ``CostState``: a norm of d = x − target (Jd = I, Jdd = 0, so its expansion is exact).

    Args:
      target: [dX] target state.
      wp: [dX] per-entry weights (0 leaves an entry out).
      l1, l2, alpha: norm parameters (see :func:`l1l2_term`).
      ramp_w: [T] ramp (see :func:`ramp`); step t uses weights wp · ramp_w[t].
      norm: "l1l2" (toolbox default of CostState) or "logl2".
      wrapped: entries of d wrapped to [−π, π) (:func:`wrap_angles`; the toolbox wraps none).

    Returns:
      A :class:`CostFn`.
    """
    norm_fn = _norm_fn(norm)
    target = np.asarray(target) if not isinstance(target, jax.Array) else target
    wp = np.asarray(wp, dtype=np.float64)
    ramp_w = np.asarray(ramp_w, dtype=np.float64)
    if wp.shape != tuple(np.shape(target)):
        raise ValueError(f"state_cost: wp has shape {wp.shape}, target has shape {np.shape(target)}")

    def terms(x, t):
        dtype = x.dtype
        w = jnp.asarray(wp, dtype) * jnp.asarray(ramp_w, dtype)[t]
        return norm_fn(wrap_angles(x - jnp.asarray(target, dtype), wrapped), w, l1, l2, alpha)

    def value(x, u, t):
        return terms(x, t)[0]

    def expand(x, u, t):
        l, d1, d2 = terms(x, t)
        c, C = _pad_x_block(d1, d2, u.shape[-1])
        return l, c, C

    return CostFn(value, expand)


def action_cost(wu) -> CostFn:
    """Toolbox ``CostAction``: ℓ = ½ Σ wu u², lu = wu⊙u, luu = diag(wu) (no ramp).

    Args:
      wu: [dU] per-joint weights.
    """
    wu = np.asarray(wu, dtype=np.float64)

    def value(x, u, t):
        u = u.astype(x.dtype)
        return 0.5 * jnp.sum(jnp.asarray(wu, x.dtype) * u * u)

    def expand(x, u, t):
        dtype = x.dtype
        u = u.astype(dtype)
        w = jnp.asarray(wu, dtype)
        dX = x.shape[-1]
        l = 0.5 * jnp.sum(w * u * u)
        c = jnp.concatenate([jnp.zeros((dX,), dtype), w * u])
        C = jnp.pad(jnp.diag(w), ((dX, 0), (dX, 0)))
        return l, c, C

    return CostFn(value, expand)


def end_effector_cost(ee_fn: Callable, target_ee, wp, l1, l2, alpha, ramp_w,
                      norm: str = "l1l2", n_joints: int = 6) -> CostFn:
    """Toolbox ``CostFK``: a norm of d = ee_fn(q) − target_ee, q = x[:n_joints].

    The expansion is Gauss–Newton in q, as in the toolbox (Jdd = 0):
    lq = Jᵀ d1, lqq = Jᵀ d2 J with J = ∂ee/∂q [3, n_joints] by forward-mode autodiff; d1, d2 are
    the norm's exact derivatives in d (for "logl2" with the factor 2 the toolbox omits). The
    derivatives go only into the joint-angle block of x; velocities and actions get zeros.

    Args:
      ee_fn: q [n_joints] -> [3], differentiable (e.g. ``gmr_jax.sim.end_effector``).
      target_ee: [3] target end-effector position.
      wp: [3] weights per coordinate.
      l1, l2, alpha: norm parameters.
      ramp_w: [T] ramp.
      norm: "l1l2" or "logl2" (the toolbox's CostFK default).
      n_joints: the joint angles are the first n_joints entries of x.

    Returns:
      A :class:`CostFn`.
    """
    norm_fn = _norm_fn(norm)
    wp = np.asarray(wp, dtype=np.float64)
    ramp_w = np.asarray(ramp_w, dtype=np.float64)
    if not isinstance(target_ee, jax.Array):
        target_ee = np.asarray(target_ee)
    if wp.shape != tuple(np.shape(target_ee)):
        raise ValueError(f"end_effector_cost: wp has shape {wp.shape}, "
                         f"target_ee has shape {np.shape(target_ee)}")

    def weights(dtype, t):
        return jnp.asarray(wp, dtype) * jnp.asarray(ramp_w, dtype)[t]

    def value(x, u, t):
        dtype = x.dtype
        d = ee_fn(x[:n_joints]).astype(dtype) - jnp.asarray(target_ee, dtype)
        return norm_fn(d, weights(dtype, t), l1, l2, alpha)[0]

    def expand(x, u, t):
        dtype = x.dtype
        q = x[:n_joints]
        def point(q_):
            e = ee_fn(q_)
            return e, e

        # One forward-mode pass gives both the point and its Jacobian (ee_fn is called once).
        J, ee = jax.jacfwd(point, has_aux=True)(q)
        d = ee.astype(dtype) - jnp.asarray(target_ee, dtype)
        J = J.astype(dtype)
        l, d1, d2 = norm_fn(d, weights(dtype, t), l1, l2, alpha)
        gq = J.T @ d1
        Hq = J.T @ d2 @ J
        Hq = 0.5 * (Hq + Hq.T)
        dX = x.shape[-1]
        gx = jnp.concatenate([gq, jnp.zeros((dX - n_joints,), dtype)])
        Hx = jnp.pad(Hq, ((0, dX - n_joints), (0, dX - n_joints)))
        c, C = _pad_x_block(gx, Hx, u.shape[-1])
        return l, c, C

    return CostFn(value, expand)


def cost_sum(fns: Sequence, weights: Sequence | None = None) -> CostFn:
    """Toolbox ``CostSum``: Σ_i w_i ℓ_i, with the expansions summed the same way.

    Args:
      fns: costs (:class:`CostFn`, or plain functions, which are expanded by autodiff).
      weights: one weight per cost (default: ones).
    """
    costs = [_as_cost(f) for f in fns]
    if not costs:
        raise ValueError("cost_sum: needs at least one cost")
    weights = [1.0] * len(costs) if weights is None else list(weights)
    if len(weights) != len(costs):
        raise ValueError(f"cost_sum: {len(costs)} costs but {len(weights)} weights")

    def value(x, u, t):
        return sum(w * c(x, u, t) for w, c in zip(weights, costs))

    def expand(x, u, t):
        parts = [c.expand(x, u, t) for c in costs]
        l = sum(w * p[0] for w, p in zip(weights, parts))
        g = sum(w * p[1] for w, p in zip(weights, parts))
        H = sum(w * p[2] for w, p in zip(weights, parts))
        return l, g, H

    return CostFn(value, expand)


# ---------------------------------------------------------------------------------------------
# Evaluation and expansion over trajectories


def _time_index(T: int):
    return jnp.arange(T)


def evaluate_costs(cost_fn, X: Array, U: Array) -> Array:
    """True per-step costs ("cs") of trajectories.

    Args:
      cost_fn: a :class:`CostFn` or plain ``fn(x, u, t)``.
      X: [..., T, dX] states.
      U: [..., T, dU] actions.

    Returns:
      [..., T] costs, in X's dtype.
    """
    T, dX = X.shape[-2:]
    dU = U.shape[-1]
    batch = X.shape[:-2]
    Xf = X.reshape((-1, T, dX))
    Uf = U.reshape((-1, T, dU)).astype(X.dtype)
    per_step = jax.vmap(cost_fn, in_axes=(0, 0, 0))
    cs = jax.vmap(lambda x, u: per_step(x, u, _time_index(T)))(Xf, Uf)
    return cs.reshape(batch + (T,))


def quadratic_expansion(cost_fn, X: Array, U: Array) -> tuple[QuadraticCost, Array]:
    """Per-sample quadratic expansion, re-centred to absolute coordinates, averaged over samples.

    For each sample and step, at ŷ = [x̂; û] with (l, c, C) from ``cost_fn.expand``:
      cc = l − cᵀŷ + ½ ŷᵀCŷ,  cv = c − Cŷ,  Cm = C,
    so that ½ yᵀ Cm y + yᵀ cv + cc is the local model in absolute y; Cm, cv and cc are then
    averaged over the N samples (mdgps-toolbox.md §1.5).

    Args:
      cost_fn: a :class:`CostFn` or plain ``fn(x, u, t)`` (then expanded by autodiff).
      X: [..., N, T, dX] sampled states.
      U: [..., N, T, dU] sampled actions.

    Returns:
      (QuadraticCost with Cm [..., T, dX+dU, dX+dU], cv [..., T, dX+dU], cc [..., T],
       cs [..., N, T] the true per-step costs). NaNs in the samples propagate; check with
      :func:`expansion_is_finite`.
    """
    cost = _as_cost(cost_fn)
    N, T, dX = X.shape[-3:]
    dU = U.shape[-1]
    batch = X.shape[:-3]
    Xf = X.reshape((-1, N, T, dX))
    Uf = U.reshape((-1, N, T, dU)).astype(X.dtype)

    def one_step(x, u, t):
        l, c, C = cost.expand(x, u, t)
        C = 0.5 * (C + C.T)
        y = jnp.concatenate([x, u])
        Cy = C @ y
        cc = l - c @ y + 0.5 * y @ Cy
        cv = c - Cy
        return C, cv, cc, l

    over_t = jax.vmap(one_step, in_axes=(0, 0, 0))
    over_n = jax.vmap(lambda x, u: over_t(x, u, _time_index(T)))
    Cm, cv, cc, cs = jax.vmap(over_n)(Xf, Uf)  # [B, N, T, ...]
    dY = dX + dU
    qc = QuadraticCost(
        Cm=jnp.mean(Cm, axis=1).reshape(batch + (T, dY, dY)),
        cv=jnp.mean(cv, axis=1).reshape(batch + (T, dY)),
        cc=jnp.mean(cc, axis=1).reshape(batch + (T,)),
    )
    return qc, cs.reshape(batch + (N, T))


def expansion_is_finite(qc: QuadraticCost, cs: Array | None = None) -> Array:
    """[] bool: whether every entry of the expansion (and of cs, if given) is finite."""
    ok = jnp.all(jnp.isfinite(qc.Cm)) & jnp.all(jnp.isfinite(qc.cv)) & jnp.all(jnp.isfinite(qc.cc))
    if cs is not None:
        ok = ok & jnp.all(jnp.isfinite(cs))
    return ok

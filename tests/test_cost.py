"""Tests of gmr_jax.cost: ramps, norms, terms, Gauss–Newton EE expansion, absolute-coordinate expansion."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from tolerances import SAFETY, assert_close, assert_tolerances_small, assert_trees_within, linear_tol, measured_tol

from gmr_jax import cost
from gmr_jax.tasks.reach import TARGET as REACH_TARGET, CostConfig, reach_cost

dX, dU, T = 12, 6, 5


# ---------------------------------------------------------------------------------------------
# Independent numpy implementations and a toy end-effector


def np_l1l2(d, wp, l1, l2, alpha):
    s = np.sum((wp * d) ** 2)
    r = np.sqrt(alpha + s)
    v = wp**2 * d
    return (0.5 * l2 * np.sum(wp * d**2) + l1 * r,
            l2 * wp * d + l1 * v / r,
            l1 * (np.diag(wp**2) / r - np.outer(v, v) / r**3) + l2 * np.diag(wp))


def np_logl2(d, wp, l1, l2, alpha):
    a = alpha + np.sum((wp * d) ** 2)
    v = wp**2 * d
    return (0.5 * l2 * np.sum(wp * d**2) + 0.5 * l1 * np.log(a),
            l2 * wp * d + l1 * v / a,
            l1 * (np.diag(wp**2) / a - 2.0 * np.outer(v, v) / a**2) + l2 * np.diag(wp))


def toy_ee(q):
    """A nonlinear 'forward kinematics' q [6] -> [3] (planar-ish chain plus a height)."""
    a1 = q[0] + q[1]
    return jnp.stack([jnp.cos(q[0]) + 0.5 * jnp.cos(a1) + 0.1 * q[3],
                      jnp.sin(q[0]) + 0.5 * jnp.sin(a1) + 0.2 * q[4] * q[2],
                      0.3 * q[2] + 0.1 * jnp.sin(q[5])])


def toy_ee_jac(q):
    a1 = q[0] + q[1]
    J = np.zeros((3, 6))
    J[0, 0] = -np.sin(q[0]) - 0.5 * np.sin(a1)
    J[0, 1] = -0.5 * np.sin(a1)
    J[0, 3] = 0.1
    J[1, 0] = np.cos(q[0]) + 0.5 * np.cos(a1)
    J[1, 1] = 0.5 * np.cos(a1)
    J[1, 2] = 0.2 * q[4]
    J[1, 4] = 0.2 * q[2]
    J[2, 2] = 0.3
    J[2, 5] = 0.1 * np.cos(q[5])
    return J


def fd_grad(f, y, h=1e-6):
    g = np.zeros_like(y)
    for i in range(y.size):
        e = np.zeros_like(y)
        e[i] = h
        g[i] = (f(y + e) - f(y - e)) / (2 * h)
    return g


def fd_jac(g, y, h=1e-5):
    H = np.zeros((y.size, y.size))
    for i in range(y.size):
        e = np.zeros_like(y)
        e[i] = h
        H[:, i] = (g(y + e) - g(y - e)) / (2 * h)
    return H


rng = np.random.default_rng(0)
TARGET = np.concatenate([np.asarray(REACH_TARGET), np.zeros(6)])


# ---------------------------------------------------------------------------------------------
# Ramps


def test_ramps():
    Tr = 4
    np.testing.assert_allclose(cost.ramp(Tr, "constant", 1.0), np.ones(Tr))
    np.testing.assert_allclose(cost.ramp(Tr, "linear", 1.0), [0.25, 0.5, 0.75, 1.0])
    np.testing.assert_allclose(cost.ramp(Tr, "quadratic", 1.0), [0.0625, 0.25, 0.5625, 1.0])
    np.testing.assert_allclose(cost.ramp(Tr, "final_only", 1.0), [0, 0, 0, 1.0])
    np.testing.assert_allclose(cost.ramp(Tr, "constant", 10.0), [1, 1, 1, 10.0])
    np.testing.assert_allclose(cost.ramp(Tr, "linear", 3.0), [0.25, 0.5, 0.75, 3.0])
    np.testing.assert_allclose(cost.ramp(Tr, "final_only", 7.0), [0, 0, 0, 7.0])
    with pytest.raises(ValueError, match="allowed values"):
        cost.ramp(Tr, "cubic", 1.0)


# ---------------------------------------------------------------------------------------------
# Norm formulas against numpy


@pytest.mark.parametrize("norm", ["l1l2", "logl2"])
def test_norm_terms_match_numpy(norm):
    fn = cost.l1l2_term if norm == "l1l2" else cost.logl2_term
    ref = np_l1l2 if norm == "l1l2" else np_logl2
    for _ in range(3):
        d = rng.normal(size=5)
        wp = rng.uniform(0.1, 2.0, size=5)
        l1, l2, alpha = 0.7, 1.3, 0.05
        got = fn(jnp.asarray(d), jnp.asarray(wp), l1, l2, alpha)
        # Tolerance from the computation (tests/tolerances.py): the numpy formulas rerun on
        # inputs perturbed by ε relative, SAFETY times the spread (d2 subtracts an outer product
        # from a diagonal: cancellation shows up in the spread).
        want, tol = measured_tol(lambda dd, ww: ref(dd, ww, l1, l2, alpha), (d, wp), SAFETY)
        assert_tolerances_small(want, tol, 1e-10)
        assert_trees_within(tuple(got), tuple(want), tol)
        # d1, d2 are the exact derivatives of l (this is where the log-l2 factor 2 matters).
        f = lambda dd: float(fn(jnp.asarray(dd), jnp.asarray(wp), l1, l2, alpha)[0])
        np.testing.assert_allclose(fd_grad(f, d), np.asarray(got[1]), rtol=1e-6, atol=1e-8)
        g1 = lambda dd: np.asarray(fn(jnp.asarray(dd), jnp.asarray(wp), l1, l2, alpha)[1])
        np.testing.assert_allclose(fd_jac(g1, d), np.asarray(got[2]), rtol=1e-6, atol=1e-7)


# ---------------------------------------------------------------------------------------------
# Terms: value, gradient, Hessian against finite differences of the value


def _jitted(cfn):
    """(value(y, t), expand(y, t)) on y = [x; u], compiled once (eager op-by-op is slow)."""
    value = jax.jit(lambda y, t: cfn(y[:dX], y[dX:], t))
    expand = jax.jit(lambda y, t: cfn.expand(y[:dX], y[dX:], t))
    return value, expand


def _check_expansion_fd(cfn, x, u, t, exact_hessian=True):
    value, expand = _jitted(cfn)
    y = np.concatenate([x, u])
    l, c, C = (np.asarray(a) for a in expand(y, t))
    f = lambda yy: float(value(yy, t))
    # The value and the expansion are two programs: tolerance from the computation
    # (tests/tolerances.py), the value rerun at y perturbed by ε relative, SAFETY times the spread.
    assert_trees_within(l, *measured_tol(lambda yy: value(yy, t), (y,), SAFETY))
    np.testing.assert_allclose(c, fd_grad(f, y), rtol=1e-6, atol=1e-8)
    np.testing.assert_allclose(C, C.T, atol=1e-14)
    if exact_hessian:
        g = lambda yy: np.asarray(expand(yy, t)[1])
        np.testing.assert_allclose(C, fd_jac(g, y), rtol=1e-6, atol=1e-7)
    return l, c, C


@pytest.mark.parametrize("norm", ["l1l2", "logl2"])
def test_state_cost_expansion_is_exact(norm):
    wp = rng.uniform(0.0, 2.0, size=dX)
    r = cost.ramp(T, "linear", 4.0)
    cfn = cost.state_cost(TARGET, wp, 0.5, 1.5, 1e-2, r, norm=norm)
    x = TARGET + 0.3 * rng.normal(size=dX)
    u = rng.normal(size=dU)
    for t in (0, T - 1):
        l, c, C = _check_expansion_fd(cfn, x, u, t)
        np_fn = np_l1l2 if norm == "l1l2" else np_logl2
        # Tolerance from the computation, as in test_norm_terms_match_numpy.
        ref, tol = measured_tol(lambda xx, ww: np_fn(xx - TARGET, ww * r[t], 0.5, 1.5, 1e-2), (x, wp), SAFETY)
        assert_tolerances_small(ref, tol, 1e-10)
        assert_trees_within((l, c[:dX], C[:dX, :dX]), tuple(ref), tol)
        assert np.all(c[dX:] == 0) and np.all(C[dX:] == 0) and np.all(C[:, dX:] == 0)


def test_wrap_angles_is_the_shortest_way_round():
    d = np.concatenate([np.linspace(-4 * np.pi, 4 * np.pi, 41), [np.pi, -np.pi]])
    x = np.stack([d, d, d], axis=-1)  # [43, 3]; wrap entries 0 and 2
    w = np.asarray(cost.wrap_angles(jnp.asarray(x), (0, 2)))
    np.testing.assert_array_equal(w[:, 1], d)  # an entry not named is untouched
    ref = np.angle(np.exp(1j * d))  # an independent wrap, to (−π, π]
    ref[np.isclose(ref, np.pi, atol=1e-12)] = -np.pi  # ours is [−π, π)
    # d − 2πk with k exact: |d| ≤ 4π, so one rounding of 2πk and one of the difference.
    for k in (0, 2):
        np.testing.assert_allclose(w[:, k], ref, rtol=0, atol=linear_tol(4 * np.pi, 2))
        assert np.all((w[:, k] >= -np.pi) & (w[:, k] < np.pi))
    np.testing.assert_array_equal(cost.wrap_angles(jnp.asarray(x), ()), x)


@pytest.mark.parametrize("entries, unique", [((0, 2), True), ((-1, 2), False), ((0, 0), False)])
def test_wrap_angles_marks_its_scatter_unique_only_when_no_two_entries_name_one_element(entries, unique):
    """A scatter marked unique whose indices repeat is undefined on a GPU; -1 and 2 name the same
    entry of a 3-vector."""
    jaxpr = jax.make_jaxpr(lambda d: cost.wrap_angles(d, entries))(jnp.zeros((5, 3)))
    flags = [e.params["unique_indices"] for e in jaxpr.jaxpr.eqns if e.primitive.name == "scatter"]
    assert flags == [unique]


@pytest.mark.parametrize("norm", ["l1l2", "logl2"])
def test_wrapped_state_cost_is_the_raw_cost_of_the_wrapped_state(norm):
    """Wrapping joint 0 and 3: at x, the cost and its expansion equal the raw cost's at the
    state moved by whole turns onto the target's side (the wrap's derivative is 1 there)."""
    wp = rng.uniform(0.5, 2.0, size=dX)
    r = cost.ramp(T, "constant", 1.0)
    wrapped = cost.state_cost(TARGET, wp, 0.5, 1.5, 1e-2, r, norm=norm, wrapped=(0, 3))
    raw = cost.state_cost(TARGET, wp, 0.5, 1.5, 1e-2, r, norm=norm)
    x = TARGET + 0.3 * rng.normal(size=dX)
    turns = np.zeros(dX)
    turns[0], turns[3] = 2 * np.pi, -4 * np.pi
    u = rng.normal(size=dU)
    got = jax.jit(wrapped.expand, static_argnums=2)(x + turns, u, 1)
    want = jax.jit(raw.expand, static_argnums=2)(x, u, 1)
    # The wrapped difference equals x − target up to two roundings at magnitude |x| + 4π (x + turns,
    # then the subtraction of 2πk): the tolerance is the raw expansion's spread when x moves by
    # that much, SAFETY times (tests/tolerances.py).
    delta = linear_tol(1.0, 2) * (np.max(np.abs(x)) + 4 * np.pi)
    moved = [raw.expand(x + delta * np.random.default_rng(s).uniform(-1, 1, dX), u, 1) for s in (1, 2)]
    tol = [SAFETY * (max(np.max(np.abs(np.asarray(m[i]) - np.asarray(want[i]))) for m in moved)
                     + np.finfo(np.float64).eps * np.max(np.abs(np.asarray(want[i])))) for i in range(3)]
    assert_tolerances_small(tuple(want), tol, 1e-10)
    assert_trees_within(tuple(got), tuple(want), tol)
    # The raw cost sees the whole turns.
    assert float(raw(x + turns, u, 1)) > float(raw(x, u, 1)) + 1.0


def test_action_cost():
    wu = rng.uniform(0.1, 1.0, size=dU)
    cfn = cost.action_cost(wu)
    x, u = rng.normal(size=dX), rng.normal(size=dU)
    l, c, C = _check_expansion_fd(cfn, x, u, 2)
    # A sum of dU positive terms (c·(dU + 2)·ε relative, tests/tolerances.py), a product (one
    # rounding), the weights themselves (exact).
    assert_close(l, 0.5 * np.sum(wu * u**2), linear_tol(1.0, dU + 2))
    assert_close(c[dX:], wu * u, linear_tol(1.0, 1))
    np.testing.assert_array_equal(C[dX:, dX:], np.diag(wu))
    assert np.all(C[:dX] == 0) and np.all(c[:dX] == 0)


def test_cost_sum_and_autodiff_wrapper():
    wu = rng.uniform(0.1, 1.0, size=dU)
    wp = rng.uniform(0.5, 1.0, size=dX)
    plain = lambda x, u, t: jnp.sum(jnp.sin(x[:3])) * (t + 1) + jnp.sum(u**4)
    a, b = cost.action_cost(wu), cost.state_cost(TARGET, wp, 0.3, 1.0, 1e-2, cost.ramp(T, "constant", 1.0))
    s = cost.cost_sum([a, b, plain], [2.0, 0.5, 3.0])
    x, u = TARGET + rng.normal(size=dX), rng.normal(size=dU)
    # The sum's expansion is the weighted sum of the parts' (one compiled call for all of them).
    parts = jax.jit(lambda x_, u_: [c.expand(x_, u_, 1) for c in (a, b, cost.from_function(plain))])

    def weighted(x_, u_):
        p = parts(x_, u_)
        return tuple(2 * p[0][k] + 0.5 * p[1][k] + 3 * p[2][k] for k in range(3))

    l, c, C = _check_expansion_fd(s, x, u, 1)  # value, gradient, Hessian vs finite differences
    # Two programs: tolerance from the computation (tests/tolerances.py), the weighted parts
    # rerun at (x, u) perturbed by ε relative, SAFETY times the spread.
    want, tol = measured_tol(weighted, (x, u), SAFETY)
    assert_tolerances_small(want, tol, 1e-10)
    assert_trees_within((l, c, C), want, tol)


# ---------------------------------------------------------------------------------------------
# End-effector term: Gauss–Newton in q


@pytest.mark.parametrize("norm", ["l1l2", "logl2"])
def test_ee_cost_is_gauss_newton(norm):
    target_ee = np.array([0.4, 0.9, 0.2])
    wp = np.array([1.0, 2.0, 0.5])
    l1, l2, alpha = 0.8, 1.2, 1e-3
    r = cost.ramp(T, "quadratic", 2.0)
    cfn = cost.end_effector_cost(toy_ee, target_ee, wp, l1, l2, alpha, r, norm=norm)
    x, u = rng.normal(size=dX), rng.normal(size=dU)
    t = T - 1
    value, expand = _jitted(cfn)
    y = np.concatenate([x, u])
    l, c, C = (np.asarray(a) for a in expand(y, t))
    np_fn = np_l1l2 if norm == "l1l2" else np_logl2

    def gauss_newton(q):
        J = toy_ee_jac(q)
        d = np.asarray(toy_ee(jnp.asarray(q))) - target_ee
        ref = np_fn(d, wp * r[t], l1, l2, alpha)
        return ref[0], J.T @ ref[1], J.T @ ref[2] @ J

    # Tolerance from the computation (tests/tolerances.py): the numpy Gauss–Newton terms rerun
    # at q perturbed by ε relative, SAFETY times the spread.
    want, tol = measured_tol(gauss_newton, (x[:6],), SAFETY)
    assert_tolerances_small(want, tol, 1e-10)
    assert_trees_within((l, c[:6], C[:6, :6]), want, tol)
    # Derivatives only in the joint-angle block.
    assert np.all(c[6:] == 0) and np.all(C[6:] == 0) and np.all(C[:, 6:] == 0)
    # The gradient is exact; the Hessian is Gauss–Newton, not the exact one (toy_ee is curved).
    np.testing.assert_allclose(c, fd_grad(lambda yy: float(value(yy, t)), y), rtol=1e-6, atol=1e-8)
    exact = np.asarray(jax.jit(jax.hessian(value))(y, t))
    assert np.max(np.abs(exact[:6, :6] - C[:6, :6])) > 1e-3


def test_ee_cost_linear_map_expansion_is_exact():
    # With a linear ee_fn, Gauss–Newton equals the exact Hessian; with logl2 and l1 > 0 this fails
    # if the outer-product factor 2 is dropped (the toolbox's omission).
    A = rng.normal(size=(3, 6))
    ee = lambda q: A @ q
    cfn = cost.end_effector_cost(ee, np.zeros(3), np.ones(3), 1.0, 0.5, 1e-2,
                                 cost.ramp(T, "constant", 1.0), norm="logl2")
    x, u = 0.2 * rng.normal(size=dX), rng.normal(size=dU)
    _check_expansion_fd(cfn, x, u, 0, exact_hessian=True)


# ---------------------------------------------------------------------------------------------
# Expansion over trajectories


def _quadratic_cost():
    wp = rng.uniform(0.0, 2.0, size=dX)
    return cost.cost_sum([
        cost.action_cost(rng.uniform(0.1, 1.0, size=dU)),
        cost.state_cost(TARGET, wp, 0.0, 1.0, 1e-2, cost.ramp(T, "linear", 1.0)),
        cost.state_cost(TARGET, np.ones(dX), 0.0, 2.0, 1e-5, cost.ramp(T, "final_only", 10.0)),
    ])


def _eval_quadratic(qc, X, U):
    Y = np.concatenate([X, U], axis=-1)
    return (0.5 * np.einsum("...ti,tij,...tj->...t", Y, np.asarray(qc.Cm), Y)
            + np.einsum("...ti,ti->...t", Y, np.asarray(qc.cv)) + np.asarray(qc.cc))


def test_quadratic_cost_expansion_is_exact_in_absolute_coordinates():
    cfn = _quadratic_cost()
    N = 3
    X = TARGET + rng.normal(size=(N, T, dX))
    U = rng.normal(size=(N, T, dU))
    qc, cs = jax.jit(cost.quadratic_expansion, static_argnums=0)(cfn, X, U)
    assert qc.Cm.shape == (T, dX + dU, dX + dU) and qc.cv.shape == (T, dX + dU) and qc.cc.shape == (T,)
    assert cs.shape == (N, T)
    # The re-centred quadratic reproduces the cost at the expansion points and far from them.
    X2 = np.concatenate([X, TARGET + 3.0 * rng.normal(size=(N, T, dX))])
    U2 = np.concatenate([U, 3.0 * rng.normal(size=(N, T, dU))])
    # Tolerances from the computation (tests/tolerances.py): each side rerun on inputs perturbed
    # by ε relative, SAFETY times the spread. Far from the expansion points the quadratic's
    # terms cancel, which its spread shows.
    true, tol_true = measured_tol(lambda x_, u_: jax.jit(cost.evaluate_costs, static_argnums=0)(cfn, x_, u_),
                                  (X2, U2), SAFETY)
    assert_trees_within(cs, true[:N], tol_true)
    quad, tol_quad = measured_tol(lambda q_, x_, u_: _eval_quadratic(q_, x_, u_), (qc, X2, U2), SAFETY)
    assert_tolerances_small(quad, tol_quad, 1e-10)
    assert_trees_within(quad, true, tol_true[0] + tol_quad[0])


def test_expansion_averages_over_samples():
    cfn = cost.cost_sum([
        cost.action_cost(np.full(dU, 0.1)),
        cost.state_cost(TARGET, np.ones(dX), 1.0, 1.0, 1e-2, cost.ramp(T, "constant", 1.0)),
        cost.end_effector_cost(toy_ee, np.array([0.5, 0.5, 0.5]), np.ones(3), 0.5, 1.0, 1e-5,
                               cost.ramp(T, "constant", 1.0), norm="logl2"),
    ])
    M, N = 2, 3  # a leading condition axis is mapped over
    X = TARGET + rng.normal(size=(M, N, T, dX))
    U = rng.normal(size=(M, N, T, dU))
    qexp = jax.jit(cost.quadratic_expansion, static_argnums=0)
    qc, cs = qexp(cfn, X, U)
    assert qc.Cm.shape == (M, T, dX + dU, dX + dU) and cs.shape == (M, N, T)
    assert bool(cost.expansion_is_finite(qc, cs))
    _, expand = _jitted(cfn)

    def recentred(Xm, Um):
        """Independent per-sample re-centring in numpy, then the mean over samples."""
        Cm = np.zeros((T, dX + dU, dX + dU)); cv = np.zeros((T, dX + dU)); cc = np.zeros(T)
        ls = np.zeros((N, T))
        for n in range(N):
            for t in range(T):
                y = np.concatenate([Xm[n, t], Um[n, t]])
                l, c, C = (np.asarray(a) for a in expand(y, t))
                Cm[t] += C / N
                cv[t] += (c - C @ y) / N
                cc[t] += (l - c @ y + 0.5 * y @ C @ y) / N
                ls[n, t] = l
        return ls, Cm, cv, cc

    for m in range(M):
        # Tolerance from the computation (tests/tolerances.py): the numpy re-centring rerun on
        # the samples perturbed by ε relative, SAFETY times the spread.
        want, tol = measured_tol(recentred, (X[m], U[m]), SAFETY)
        assert_tolerances_small(want, tol, 1e-10)
        assert_trees_within((cs[m], qc.Cm[m], qc.cv[m], qc.cc[m]), want, tol)
    # A NaN sample is flagged.
    Xn = X.copy(); Xn[0, 0, 0, 0] = np.nan
    assert not bool(cost.expansion_is_finite(*qexp(cfn, Xn, U)))


def test_follows_float32_dtype():
    cfn = reach_cost(dataclasses.replace(CostConfig(), ee_weight=1.0, state_l1=0.1), TARGET, T,
                          ee_fn=toy_ee)
    X = jnp.asarray(TARGET + rng.normal(size=(2, T, dX)), jnp.float32)
    U = jnp.asarray(rng.normal(size=(2, T, dU)), jnp.float32)
    qc, cs = jax.jit(cost.quadratic_expansion, static_argnums=0)(cfn, X, U)
    assert qc.Cm.dtype == qc.cv.dtype == qc.cc.dtype == cs.dtype == jnp.float32
    assert bool(cost.expansion_is_finite(qc, cs))


# ---------------------------------------------------------------------------------------------
# Reach cost


def test_reach_cost_default():
    cfg = CostConfig()
    evaluate = jax.jit(cost.evaluate_costs, static_argnums=0)
    # Row 0: at the target with zero action; row 1: a random nearby trajectory.
    X = np.stack([np.broadcast_to(TARGET, (T, dX)), TARGET + 0.1 * rng.normal(size=(T, dX))])
    U = np.stack([np.zeros((T, dU)), rng.normal(size=(T, dU))])
    cs = np.asarray(evaluate(reach_cost(cfg, TARGET, T), X, U))
    assert np.all(np.isfinite(cs)) and np.all(np.abs(cs[0]) < 1e-12)
    d = X[1] - TARGET
    want = 0.5 * np.sum(np.asarray(cfg.action_weight) * U[1] ** 2, -1)
    want += 0.5 * np.sum(np.asarray(cfg.state_wp) * d**2, -1)
    want[-1] += 0.5 * cfg.final_multiplier * np.sum(np.asarray(cfg.final_wp) * d[-1] ** 2)
    # Sums of dX + dU + dX positive terms per step after one subtraction each (x − target, which
    # the two programs round alike): c·n·ε relative with n = 2dX + dU + 2 (tests/tolerances.py).
    n_terms = 2 * dX + dU + 2
    assert_close(cs[1], want, linear_tol(1.0, n_terms))
    # With an end-effector term: still zero at the target, and it adds ½ w ‖ee − ee*‖².
    cfg_ee = dataclasses.replace(cfg, ee_weight=2.0)
    cs_ee = np.asarray(evaluate(reach_cost(cfg_ee, TARGET, T, ee_fn=toy_ee), X, U))
    assert np.all(np.abs(cs_ee[0]) < 1e-12)
    ee_d = np.asarray(jax.vmap(toy_ee)(X[1, :, :6])) - np.asarray(toy_ee(TARGET[:6]))
    # The end-effector difference cancels (nearby points): its error is c·ε·|ee| per coordinate,
    # not relative to the difference; the squared term's error is 2·|ee_d|·that.
    ee_err = 2 * np.abs(ee_d).max() * linear_tol(1.0, 8) * np.abs(np.asarray(toy_ee(TARGET[:6]))).max()
    want_ee = want + np.sum(ee_d**2, -1)
    assert_close(cs_ee[1], want_ee, linear_tol(1.0, n_terms + 3) + 3 * ee_err / np.abs(want_ee).max())
    with pytest.raises(ValueError, match="ee_fn"):
        reach_cost(cfg_ee, TARGET, T)
    with pytest.raises(ValueError, match="target_x"):
        reach_cost(cfg, TARGET[:6], T)

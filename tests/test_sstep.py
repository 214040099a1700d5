"""The S-step: weight rule, input normalisation, objective, fit of a linear-Gaussian teacher,
closed-form variance, jit/vmap consistency and dtypes."""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from tolerances import SAFETY, assert_close, assert_tolerances_small, assert_trees_within, linear_tol, measured_tol

from gmr_jax.config import MLPConfig, SStepConfig
from gmr_jax.policies import make_policy, make_sstep_data
from gmr_jax.sstep import normalize_weights, set_normalization, sstep

dX, dU, B = 4, 2, 100
X_SCALE = np.array([0.1, 1.0, 3.0, 10.0])
X_SHIFT = np.array([1.0, -2.0, 0.0, 5.0])

_sstep = jax.jit(sstep, static_argnums=(0, 4))  # one compiled function per (policy, cfg, shapes)


@pytest.fixture(scope="module")
def policy():
    return make_policy("mlp", MLPConfig(hidden=(32, 32)))


def _np_weights(w):
    """Independent numpy version of the toolbox weight rule."""
    w = np.asarray(w, float) * len(w) / np.sum(w)
    mn = np.median(w[w > 1e-2])
    return np.minimum(w, 2 * mn) / mn


def _np_forward(net, scale, bias, x):
    layers = net["params"]
    h = x * scale + bias
    for i in range(len(layers)):
        h = h @ np.asarray(layers[f"Dense_{i}"]["kernel"]) + np.asarray(layers[f"Dense_{i}"]["bias"])
        if i < len(layers) - 1:
            h = np.maximum(h, 0.0)
    return h


def _teacher(seed=0, n=B, wt=None):
    """Linear-Gaussian teacher u = K x + k with per-row SPD precisions."""
    rng = np.random.default_rng(seed)
    K = rng.normal(size=(dU, dX))
    k = rng.normal(size=dU)
    x = rng.normal(size=(n, dX)) * X_SCALE + X_SHIFT
    A = rng.normal(size=(n, dU, dU))
    P = A @ np.transpose(A, (0, 2, 1)) / dU + np.eye(dU)
    return make_sstep_data(x, x @ K.T + k, P, wt=wt), (K, k)


def test_normalize_weights_hand_cases():
    # w·n/Σw, a median, a clip and a division: a sum of n terms and three roundings per entry,
    # c·(n + 3)·ε relative (tests/tolerances.py)
    np.testing.assert_allclose(normalize_weights(jnp.array([1.0, 1, 1, 4, 0])), [1, 1, 1, 2, 0],
                               rtol=linear_tol(1.0, 5 + 3))
    # even count: numpy's median averages the middle pair (2/3 and 1) → 5/6; clip at 5/3
    np.testing.assert_allclose(normalize_weights(jnp.array([1.0, 2, 3, 6])), [0.4, 0.8, 1.2, 2.0],
                               rtol=linear_tol(1.0, 4 + 3))
    # the toolbox's constant weight 0.01 becomes 1
    np.testing.assert_allclose(normalize_weights(jnp.full(7, 0.01)), np.ones(7), rtol=linear_tol(1.0, 7 + 3))


def test_normalize_weights_matches_numpy():
    rng = np.random.default_rng(5)
    for n in (9, 10):
        w = rng.exponential(size=n)
        w[:2] = [0.0, 1e-4]  # below the median floor after rescaling
        # two programs, each c·(n + 3)·ε relative per entry (tests/tolerances.py)
        np.testing.assert_allclose(jax.jit(normalize_weights)(jnp.asarray(w)), _np_weights(w),
                                   rtol=2 * linear_tol(1.0, n + 3))


def test_set_normalization_fixed_after_first_call(policy):
    params = policy.init(jax.random.key(0), dX, dU)
    data, _ = _teacher(1)
    x = np.array(data.x)
    x[:, 0] = 3.0  # a constant input: std 0 → floor 1e-3
    p1 = set_normalization(params, jnp.asarray(x))
    std = np.maximum(x.std(axis=0), 1e-3)
    # A mean and a std of n = B values (sums of n terms, c·2n·ε relative each, two programs;
    # tests/tolerances.py); the bias −mean·scale carries both.
    rel = 2 * linear_tol(1.0, 2 * B)
    np.testing.assert_allclose(p1.norm.scale, 1.0 / std, rtol=rel)
    assert_close(p1.norm.bias, -x.mean(axis=0) / std, 2 * rel)
    assert bool(p1.norm.set)
    p2 = set_normalization(p1, jnp.asarray(5.0 * x + 1.0))  # new data: statistics stay
    np.testing.assert_array_equal(p2.norm.scale, p1.norm.scale)
    np.testing.assert_array_equal(p2.norm.bias, p1.norm.bias)
    # zero-weight (padding) rows are left out of the statistics
    w = np.ones(B)
    w[50:] = 0.0
    p3 = set_normalization(params, data.x, jnp.asarray(w))
    np.testing.assert_allclose(p3.norm.scale, 1.0 / np.asarray(data.x)[:50].std(axis=0), rtol=rel)


def test_objective_equals_numpy_and_nan_flag(policy):
    """With a vanishing learning rate the epoch-0 objective is the full-data objective."""
    rng = np.random.default_rng(2)
    wt = rng.uniform(0.5, 1.5, B)
    wt[3], wt[7] = 0.0, 10.0  # a dropped row and a clipped one
    data, _ = _teacher(2, wt=wt)
    params = policy.init(jax.random.key(1), dX, dU)
    cfg = SStepConfig(epochs=1, batch_size=20, lr=1e-30, weight_decay=2e-4)
    new, metrics = _sstep(policy, params, data, jax.random.key(3), cfg)

    w = _np_weights(wt)

    def np_objective(net, x, tgt_mu, P):
        x = np.asarray(x)
        valid = x[wt > 0]  # the zero-weight row is left out of the input statistics
        scale = 1.0 / valid.std(axis=0)
        bias = -valid.mean(axis=0) * scale
        d = _np_forward(net, scale, bias, x) - np.asarray(tgt_mu)
        data_term = 0.5 * np.mean([w[b] * d[b] @ np.asarray(P[b]) @ d[b] for b in range(B)])
        theta = np.concatenate([np.ravel(v) for v in jax.tree_util.tree_leaves(net)])
        return data_term, data_term + 2e-4 * np.sum(np.asarray(theta) ** 2)

    assert metrics["loss"].shape == (1,)
    # Tolerance from the computation (tests/tolerances.py): the numpy objective rerun on inputs
    # perturbed by ε relative, SAFETY times the spread.
    ref, tol = measured_tol(np_objective, (params.net, data.x, data.tgt_mu, data.tgt_prc), SAFETY)
    assert_tolerances_small(ref, tol, 1e-10)
    assert_trees_within((metrics["data_loss"][0], metrics["loss"][0]), ref, tol)
    P = np.asarray(data.tgt_prc)
    assert bool(metrics["finite"]) and bool(metrics["weights_ok"])
    # variance rule: 1/diag of the weighted mean precision (= mean precision for constant weights)
    A = np.einsum("b,bij->ij", w, P) / w.sum()
    # weighted means of B positive diagonals and a reciprocal, two programs: c·2(B + 2)·ε relative
    assert_close(new.var, 1.0 / np.diag(A), 2 * linear_tol(1.0, 2 * (B + 2)))

    bad = data._replace(tgt_mu=data.tgt_mu.at[5, 0].set(jnp.nan))
    _, bad_metrics = _sstep(policy, params, bad, jax.random.key(3), cfg)
    assert not bool(bad_metrics["finite"])


def test_fits_linear_gaussian_teacher(policy):
    data, (K, k) = _teacher(0)
    params = policy.init(jax.random.key(0), dX, dU)
    cfg = SStepConfig(epochs=100, batch_size=20, lr=1e-2, weight_decay=0.0)
    new, metrics = _sstep(policy, params, data, jax.random.key(1), cfg)
    assert metrics["loss"].shape == (100,)
    assert float(metrics["loss"][-1]) < 1e-3 * float(metrics["loss"][0])
    err = np.asarray(policy.mean(new, data.x)) - np.asarray(data.tgt_mu)
    rel = np.sqrt(np.mean(err ** 2)) / np.std(np.asarray(data.tgt_mu))
    assert rel < 0.03, rel
    # the fit generalises to fresh states of the same distribution
    xt = np.random.default_rng(9).normal(size=(200, dX)) * X_SCALE + X_SHIFT
    ut = np.asarray(policy.mean(new, jnp.asarray(xt)))
    assert np.sqrt(np.mean((ut - (xt @ K.T + k)) ** 2)) / np.std(np.asarray(data.tgt_mu)) < 0.08
    assert_close(new.var, 1.0 / np.diag(np.asarray(data.tgt_prc).mean(0)), 2 * linear_tol(1.0, 2 * (B + 2)))
    # warm start: a second S-step on shifted data keeps the first statistics
    shifted = data._replace(x=data.x + 100.0)
    again, _ = _sstep(policy, new, shifted, jax.random.key(2), cfg)
    np.testing.assert_array_equal(again.norm.scale, new.norm.scale)
    np.testing.assert_array_equal(again.norm.bias, new.norm.bias)


def test_jit_equals_nojit_and_vmap_equals_loop(policy):
    data, _ = _teacher(3)
    cfg = SStepConfig(epochs=3, batch_size=20)
    keys = jax.random.split(jax.random.key(7), 3)
    inits = [policy.init(k, dX, dU) for k in keys]

    # Tolerances from the computation (tests/tolerances.py): the jitted S-step rerun from
    # parameters and data perturbed by ε relative shows how far the rounding differences of
    # another program (eager, vmapped) travel through the Adam steps; SAFETY times that spread.
    def single(i):
        return measured_tol(lambda p, d: _sstep(policy, p, d, keys[i], cfg), (inits[i], data), SAFETY)

    eager = sstep(policy, inits[0], data, keys[0], cfg)
    jitted, tol = single(0)
    assert_tolerances_small(jitted, tol, 1e-6)
    assert_trees_within(eager, jitted, tol)

    batched_params = jax.tree_util.tree_map(lambda *a: jnp.stack(a), *inits)
    run = jax.jit(jax.vmap(functools.partial(sstep, policy, data=data, cfg=cfg)))
    vp, vm = run(batched_params, key=keys)
    for i in range(3):
        ref, tol = single(i)
        assert_trees_within(jax.tree_util.tree_map(lambda a: a[i], (vp, vm)), ref, tol)
    # different seeds give different networks
    w0 = vp.net["params"]["Dense_0"]["kernel"]
    assert not np.allclose(w0[0], w0[1])


def test_unrolled_loop_takes_the_same_steps(policy):
    """``SStepConfig.unroll`` only changes how the loop is compiled: the same minibatch steps in
    the same order (B = 100 rows: 5 minibatches per epoch, so unroll 3 also leaves a remainder)."""
    data, _ = _teacher(5)
    params = policy.init(jax.random.key(1), dX, dU)
    # Unrolling lets XLA fuse (and so round) across steps differently: tolerance from the
    # computation, as in test_jit_equals_nojit_and_vmap_equals_loop.
    cfg1 = SStepConfig(epochs=4, unroll=1)
    ref, tol = measured_tol(lambda p, d: _sstep(policy, p, d, jax.random.key(2), cfg1), (params, data), SAFETY)
    assert_tolerances_small(ref, tol, 1e-6)
    for unroll in (3, 5):
        got = _sstep(policy, params, data, jax.random.key(2), SStepConfig(epochs=4, unroll=unroll))
        assert_trees_within(got, ref, tol)
    with pytest.raises(ValueError, match="sstep.unroll"):
        SStepConfig(unroll=0)


def test_float32_follows_input_dtype(policy):
    data, _ = _teacher(4)
    data32 = jax.tree_util.tree_map(lambda a: a.astype(jnp.float32), data)
    params = policy.init(jax.random.key(0), dX, dU, dtype=jnp.float32)
    new, metrics = _sstep(policy, params, data32, jax.random.key(0), SStepConfig(epochs=2))
    dtypes = {leaf.dtype for leaf in jax.tree_util.tree_leaves(new)}
    assert dtypes == {jnp.dtype(jnp.float32), jnp.dtype(bool)}
    assert metrics["loss"].dtype == jnp.float32 and bool(metrics["finite"])


def test_too_few_rows_and_bad_config(policy):
    data, _ = _teacher(0, n=10)
    params = policy.init(jax.random.key(0), dX, dU)
    with pytest.raises(ValueError, match="batch_size"):
        sstep(policy, params, data, jax.random.key(0), SStepConfig(batch_size=20))
    with pytest.raises(ValueError, match="sstep.epochs"):
        SStepConfig(epochs=0)

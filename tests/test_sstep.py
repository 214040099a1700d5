"""The S-step: weight rule, input normalisation, objective, fit of a linear-Gaussian teacher,
closed-form variance, jit/vmap consistency and dtypes; the packed form against the reference
form and GMR's kernel form against the packed form (same minibatches, noise and loss; equal to
round-off), Adam against optax, packing."""

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest
from jax.flatten_util import ravel_pytree

from tolerances import SAFETY, XLA_DEFAULT_CPU_CODEGEN, assert_close, assert_tolerances_small, assert_trees_within, linear_tol, measured_tol

from gmr_jax.config import GMRConfig, MLPConfig, SStepConfig
from gmr_jax.policies import Policy, base, make_policy, make_sstep_data
from gmr_jax.policies.base import column_blocks, join_columns, split_columns, target_logdet
from gmr_jax.sstep import (adam_corrections, adam_update, default_impl, normalize_weights,
                           set_normalization, sstep)

dX, dU, B = 4, 2, 100
X_SCALE = np.array([0.1, 1.0, 3.0, 10.0])
X_SHIFT = np.array([1.0, -2.0, 0.0, 5.0])
IMPLS = ("reference", "packed")

# one compiled function per (policy, cfg, impl, shapes)
_sstep = jax.jit(sstep, static_argnums=(0, 4), static_argnames="impl")


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


@pytest.mark.parametrize("impl", IMPLS)
def test_objective_equals_numpy_and_nan_flag(policy, impl):
    """With a vanishing learning rate the epoch-0 objective is the full-data objective."""
    rng = np.random.default_rng(2)
    wt = rng.uniform(0.5, 1.5, B)
    wt[3], wt[7] = 0.0, 10.0  # a dropped row and a clipped one
    data, _ = _teacher(2, wt=wt)
    params = policy.init(jax.random.key(1), dX, dU)
    cfg = SStepConfig(epochs=1, batch_size=20, lr=1e-30, weight_decay=2e-4)
    new, metrics = _sstep(policy, params, data, jax.random.key(3), cfg, impl=impl)

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
    _, bad_metrics = _sstep(policy, params, bad, jax.random.key(3), cfg, impl=impl)
    assert not bool(bad_metrics["finite"])


def test_fits_linear_gaussian_teacher(policy):
    data, (K, k) = _teacher(0)
    params = policy.init(jax.random.key(0), dX, dU)
    cfg = SStepConfig(epochs=100, batch_size=20, lr=1e-2, weight_decay=0.0, statistics_epochs="all")
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


@pytest.mark.parametrize("impl", IMPLS)
def test_jit_equals_nojit_and_vmap_equals_loop(policy, impl):
    data, _ = _teacher(3)
    cfg = SStepConfig(epochs=3, batch_size=20)
    keys = jax.random.split(jax.random.key(7), 3)
    inits = [policy.init(k, dX, dU) for k in keys]

    # Tolerances from the computation (tests/tolerances.py): the jitted S-step rerun from
    # parameters and data perturbed by ε relative shows how far the rounding differences of
    # another program (eager, vmapped) travel through the Adam steps; SAFETY times that spread.
    def single(i):
        return measured_tol(lambda p, d: _sstep(policy, p, d, keys[i], cfg, impl=impl), (inits[i], data),
                            SAFETY)

    eager = sstep(policy, inits[0], data, keys[0], cfg, impl=impl)
    jitted, tol = single(0)
    assert_tolerances_small(jitted, tol, 1e-6)
    assert_trees_within(eager, jitted, tol)

    batched_params = jax.tree_util.tree_map(lambda *a: jnp.stack(a), *inits)
    run = jax.jit(jax.vmap(functools.partial(sstep, policy, data=data, cfg=cfg, impl=impl)))
    vp, vm = run(batched_params, key=keys)
    for i in range(3):
        ref, tol = single(i)
        assert_trees_within(jax.tree_util.tree_map(lambda a: a[i], (vp, vm)), ref, tol)
    # different seeds give different networks
    w0 = vp.net["params"]["Dense_0"]["kernel"]
    assert not np.allclose(w0[0], w0[1])


@pytest.mark.parametrize("impl", IMPLS)
def test_unrolled_loop_takes_the_same_steps(policy, impl):
    """``SStepConfig.unroll`` only changes how the loop is compiled: the same minibatch steps in
    the same order (B = 100 rows: 5 minibatches per epoch, so unroll 3 also leaves a remainder;
    the packed form's iterations also straddle epochs)."""
    data, _ = _teacher(5)
    params = policy.init(jax.random.key(1), dX, dU)
    # Unrolling lets XLA fuse (and so round) across steps differently: tolerance from the
    # computation, as in test_jit_equals_nojit_and_vmap_equals_loop.
    cfg1 = SStepConfig(epochs=4, unroll=1)
    ref, tol = measured_tol(lambda p, d: _sstep(policy, p, d, jax.random.key(2), cfg1, impl=impl),
                            (params, data), SAFETY)
    assert_tolerances_small(ref, tol, 1e-6)
    for unroll in (3, 5):
        got = _sstep(policy, params, data, jax.random.key(2), SStepConfig(epochs=4, unroll=unroll), impl=impl)
        assert_trees_within(got, ref, tol)
    with pytest.raises(ValueError, match="sstep.unroll"):
        SStepConfig(unroll=0)


@pytest.mark.parametrize("impl", IMPLS)
def test_float32_follows_input_dtype(policy, impl):
    data, _ = _teacher(4)
    data32 = jax.tree_util.tree_map(lambda a: a.astype(jnp.float32), data)
    params = policy.init(jax.random.key(0), dX, dU, dtype=jnp.float32)
    new, metrics = _sstep(policy, params, data32, jax.random.key(0), SStepConfig(epochs=2), impl=impl)
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


# ------------------------------------------------ the packed form against the reference form

EPS = {jnp.dtype(jnp.float64): np.finfo(np.float64).eps, jnp.dtype(jnp.float32): np.finfo(np.float32).eps}
GMR_SMALL = GMRConfig(latent=2, encoder_hidden=(16, 16), decoder_hidden=(16, 16), translation_hidden=(16, 16))
# name: (policy, configuration, the data's non-symmetric matrix in the gradient test)
POLICY_CFGS = {
    "mlp": ("mlp", MLPConfig(hidden=(32, 32)), "P"),
    "gmr": ("gmr", GMR_SMALL, "P"),
    "gmr_raw": ("gmr", GMRConfig(latent=2, encoder_hidden=(16,), decoder_hidden=(16,), translation_hidden=(16,),
                                 head_coordinates="raw"), "S"),
    # decoder and translation network of different depths: one after the other, not side by side
    "gmr_uneven": ("gmr", GMRConfig(latent=3, encoder_hidden=(16,), decoder_hidden=(8,), translation_hidden=(16, 12)),
                   None),
    # a head (dU·dX + dU + dU² = 14 columns) wider than every other layer: held as column blocks,
    # three side by side with the decoder (6 + 6 + 2), two after it (8 + 6)
    "gmr_narrow": ("gmr", GMRConfig(latent=2, encoder_hidden=(6,), decoder_hidden=(6,), translation_hidden=(6,)), "P"),
    "gmr_narrow_uneven": ("gmr", GMRConfig(latent=3, encoder_hidden=(8,), decoder_hidden=(5,),
                                           translation_hidden=(8, 6)), None),
}


def _n_path(cfg, bs: int) -> int:
    """The summed lengths of the sums on the longest chain of one minibatch step: the layers'
    fan-ins (+1, the bias) forward and backward, the loss's per-row sums (GMR: the head's two
    products of 1 + dX and 1 + dX + dU terms and the gain's dU·dX terms), the batch mean and the
    weight gradient's sum over the batch.

    Two orders of a sum of n terms differ by at most 2·γ_n·Σ|terms| (γ_n = nε/(1 − nε)), and
    the errors of successive sums add up to first order, so n_path·ε bounds the relative
    difference of two evaluations that sum in different orders, for values that are not the
    result of a cancellation (the test data keep every term of the loss of the order of the
    loss, and gradients of the order of their largest entry).
    """
    if cfg.__class__ is MLPConfig:
        fan_ins, loss_sums = (dX,) + cfg.hidden, dU * dU
    else:
        deepest = max(cfg.decoder_hidden, cfg.translation_hidden, key=len)
        fan_ins = (dX,) + cfg.encoder_hidden + (cfg.latent,) + deepest
        loss_sums = (1 + dX) + (1 + dX + dU) + dU * dX
    return 2 * sum(f + 1 for f in fan_ins) + loss_sums + 2 * bs


def _full_data(seed, n=B, skew=None):
    """A data set with every field (GMR's gains and state covariances too), weights around 1
    with one padding row; ``skew`` "P" or "S" adds a small skew-symmetric part to the precisions
    or to the state covariances (the loss sees only the symmetric part of one while the other is
    symmetric)."""
    rng = np.random.default_rng(seed)
    x = rng.normal(size=(n, dX)) * X_SCALE + X_SHIFT
    K = rng.normal(size=(n, dU, dX)) / X_SCALE
    k = rng.normal(size=(n, dU))
    A = rng.normal(size=(n, dU, dU))
    P = A @ np.swapaxes(A, -1, -2) / dU + np.eye(dU)
    C = rng.normal(size=(n, dX, dX)) * X_SCALE[:, None]  # state covariances of the states' scale
    S = 0.3 * C @ np.swapaxes(C, -1, -2) / dX + 1e-3 * np.eye(dX)
    E = rng.normal(size=(n, dX, dX))
    if skew == "P":
        P = P + 1e-2 * (E[:, :dU, :dU] - np.swapaxes(E[:, :dU, :dU], -1, -2))
    elif skew == "S":
        S = S + 1e-2 * np.max(S) * (E - np.swapaxes(E, -1, -2))
    tgt = np.einsum("bux,bx->bu", K, x) + k + 0.3 * rng.normal(size=(n, dU))
    w = rng.uniform(0.5, 1.5, n)
    w[3] = 0.0
    return make_sstep_data(x, tgt, P, wt=w, K=K, k=k, state_cov=S)


def _policy(name):
    kind, cfg, _ = POLICY_CFGS[name]
    return make_policy(kind, cfg), cfg


def _train_batch(pol, data, rows=20, key=0):
    """What the S-step hands the loss: params with the normalisation set, and the first ``rows``
    rows with the normalised weight folded into the precision."""
    wn = normalize_weights(data.wt)
    params = set_normalization(pol.init(jax.random.key(key), dX, dU), data.x, wn)
    train = data._replace(tgt_prc=wn[:, None, None] * data.tgt_prc, wt=wn,
                          tgt_logdet=target_logdet(data.tgt_prc, wn))
    return params, jax.tree_util.tree_map(lambda a: a[:rows], train)


@pytest.mark.parametrize("name", list(POLICY_CFGS))
def test_training_form_gradient_equals_autodiff(name):
    """One minibatch: the packed form's value, aux and gradient against autodiff of
    ``policy.loss`` through the Flax weights, within n_path·ε; padding gets an exact zero."""
    pol, cfg = _policy(name)
    params, batch = _train_batch(pol, _full_data(11, skew=POLICY_CFGS[name][2]))
    form, key = pol.training, jax.random.key(4)
    flat, unravel = ravel_pytree(params.net)
    (v_ref, aux_ref), g_ref = jax.jit(jax.value_and_grad(
        lambda f: pol.loss(params._replace(net=unravel(f)), batch, key), has_aux=True))(flat)
    theta = form.pack(params)
    noise = form.noise(key, 20, theta.dtype) if form.noise is not None else None
    (value, aux), grad = jax.jit(form.value_and_grad)(params, theta, form.rows(params, batch), noise)

    tol = _n_path(cfg, 20) * EPS[theta.dtype]
    assert abs(value - v_ref) <= tol * abs(v_ref), (value, v_ref)
    assert aux.keys() == aux_ref.keys()
    for k in aux:
        assert abs(aux[k] - aux_ref[k]) <= tol * abs(v_ref), (k, aux[k], aux_ref[k])
    g_packed = np.asarray(form.pack(params._replace(net=unravel(g_ref))))
    assert np.max(np.abs(np.asarray(grad) - g_packed)) <= tol * np.max(np.abs(g_packed))
    padding = np.asarray(form.pack(params._replace(net=jax.tree_util.tree_map(jnp.ones_like, params.net)))) == 0
    assert padding.any() and np.all(np.asarray(grad)[padding] == 0.0)


def _forms_agree(name: str, ref_impl: str, new_impl: str, dtype, run=_sstep, batch_size: int = 20):
    """Two forms' S-steps (``run``: the jitted ``sstep``) from the same params, data and key
    (float64: 3 epochs, unroll 2; float32: 2 epochs; minibatches of ``batch_size`` rows);
    asserts the weights' bound 8·δ·lr·S
    (``test_packed_sstep_equals_reference``) and the dtypes, and that the weights moved; returns
    (new form's metrics, reference metrics, δ)."""
    pol, cfg = _policy(name)
    wide = jnp.dtype(dtype) == jnp.float64
    data = jax.tree_util.tree_map(lambda a: a.astype(dtype), _full_data(12 if wide else 13))
    params = pol.init(jax.random.key(2), dX, dU, dtype)
    # every epoch's statistics, so that the forms' curves are compared, not only their last epochs
    scfg = (SStepConfig(epochs=3, batch_size=batch_size, unroll=2, statistics_epochs="all") if wide
            else SStepConfig(epochs=2, batch_size=batch_size, statistics_epochs="all"))
    ref, ref_m = run(pol, params, data, jax.random.key(3), scfg, impl=ref_impl)
    new, new_m = run(pol, params, data, jax.random.key(3), scfg, impl=new_impl)
    delta = _n_path(cfg, scfg.batch_size) * EPS[jnp.dtype(dtype)]
    steps = scfg.epochs * (B // scfg.batch_size)
    assert jax.tree_util.tree_structure(new) == jax.tree_util.tree_structure(ref)
    for a, b in zip(jax.tree_util.tree_leaves(new), jax.tree_util.tree_leaves(ref)):
        assert a.dtype == b.dtype and (a.dtype == dtype or not jnp.issubdtype(a.dtype, jnp.floating))
        np.testing.assert_allclose(a, b, rtol=0, atol=8 * delta * scfg.lr * steps)
    assert new_m["loss"].dtype == dtype
    # the weights moved: the comparison is not of two untrained networks
    assert not np.allclose(ravel_pytree(new.net)[0], ravel_pytree(params.net)[0], atol=1e-3)
    return new_m, ref_m, delta


def _metrics_agree(new_m, ref_m, delta):
    """The metrics (epoch means of the step's losses) within δ of the loss (and the weights' drift)."""
    assert jax.tree_util.tree_structure(new_m) == jax.tree_util.tree_structure(ref_m)
    for a, b in zip(jax.tree_util.tree_leaves(new_m), jax.tree_util.tree_leaves(ref_m)):
        np.testing.assert_allclose(a, b, rtol=2 * delta, atol=2 * delta * float(ref_m["loss"][0]))


@pytest.mark.parametrize("name", ["mlp", "gmr"])
def test_packed_sstep_equals_reference(name):
    """The whole S-step: the same minibatches, noise, loss and Adam steps, so the two forms agree
    to round-off. Bound: a relative change δ = n_path·ε of a gradient changes an Adam step,
    lr·m̂/(√v̂ + eps) with |m̂|/√v̂ ≤ (1 − b1)/√(1 − b2) < 3.2, by at most 2δ·3.2·lr < 8δ·lr, so
    after S steps the weights differ by at most 8δ·lr·S (to first order: over a few steps the
    weights' difference feeds back into the gradients far below δ)."""
    _metrics_agree(*_forms_agree(name, "reference", "packed", jnp.float64))


@pytest.mark.parametrize("name", ["mlp", "gmr", "gmr_narrow_uneven"])
def test_products_as_reductions_give_the_same_gradient(name):
    """``base.products_as_reductions`` (the packed forms' products as sums of broadcast
    products, as a GPU traces GMR for one seed per device): the packed form's value, aux and
    gradient for one minibatch against the same form with dots, within n_path·ε; GMR's products
    are then no dots at all, while the MLP's form keeps its dots (it declines the reductions)."""
    pol, cfg = _policy(name)
    params, batch = _train_batch(pol, _full_data(11, skew=POLICY_CFGS[name][2]))
    form, key = pol.training, jax.random.key(4)
    theta = form.pack(params)
    noise = form.noise(key, 20, theta.dtype) if form.noise is not None else None
    rows = form.rows(params, batch)
    outputs, dots = [], []
    for reduced in (False, True):
        # a new function per mode: a jit cache is keyed on the function, not on the mode
        step = lambda t, r, n: form.value_and_grad(params, t, r, n)  # noqa: E731
        with base.products_as_reductions(reduced):
            dots.append(str(jax.make_jaxpr(step)(theta, rows, noise)).count("dot_general"))
            outputs.append(jax.jit(step)(theta, rows, noise))
    (v_dot, aux_dot), g_dot = outputs[0]
    (v_red, aux_red), g_red = outputs[1]
    tol = _n_path(cfg, 20) * EPS[theta.dtype]
    assert abs(v_red - v_dot) <= tol * abs(v_dot), (v_red, v_dot)
    for k in aux_dot:
        assert abs(aux_red[k] - aux_dot[k]) <= tol * abs(v_dot), (k, aux_red[k], aux_dot[k])
    assert np.max(np.abs(np.asarray(g_red - g_dot))) <= tol * np.max(np.abs(np.asarray(g_dot)))
    assert dots[0] >= 7 and dots[1] == (dots[0] if name == "mlp" else 0), dots


def test_packed_sstep_with_products_as_reductions_equals_reference():
    """The whole GMR S-step traced with its products as reductions against the reference form,
    with the bound of ``test_packed_sstep_equals_reference`` (float64)."""
    with base.products_as_reductions():
        _metrics_agree(*_forms_agree("gmr", "reference", "packed", jnp.float64,
                                     run=jax.jit(lambda *a, **k: sstep(*a, **k), static_argnums=(0, 4),
                                                 static_argnames="impl")))


def test_packed_sstep_equals_reference_float32():
    """As above in float32 (ε = 1.2e-7), for GMR."""
    new_m, ref_m, delta = _forms_agree("gmr", "reference", "packed", jnp.float32)
    np.testing.assert_allclose(new_m["loss"], ref_m["loss"], rtol=2 * delta)


@pytest.mark.parametrize("name", ["mlp", "gmr", "gmr_uneven", "gmr_narrow", "gmr_narrow_uneven"])
def test_trained_entries_cover_every_weight(name):
    """``TrainingForm.trained``: sorted, unique indices of θ that include every entry a weight
    packs into (the 1s of a packed all-ones network), while every entry outside them is padding
    (0 in that packing)."""
    pol, _ = _policy(name)
    params = pol.init(jax.random.key(7), dX, dU)
    ones = np.asarray(pol.training.pack(params._replace(net=jax.tree_util.tree_map(jnp.ones_like, params.net))))
    trained = np.asarray(pol.training.trained(params))
    assert trained.ndim == 1 and np.all(np.diff(trained) > 0) and 0 <= trained[0] and trained[-1] < ones.size
    assert set(np.flatnonzero(ones)) <= set(trained.tolist())
    outside = np.ones(ones.size, bool)
    outside[trained] = False
    assert outside.any() and np.all(ones[outside] == 0)


def _packed_variant_agrees(name, cfg_ref: SStepConfig, cfg: SStepConfig):
    """The packed S-step with ``cfg`` against ``cfg_ref`` (same data, weights and key), within
    the tolerance measured from ``cfg_ref``'s sensitivity to ε-perturbed inputs; returns
    (``cfg``'s (params, metrics), the initial params)."""
    pol, _ = _policy(name)
    data = _full_data(12)
    params = pol.init(jax.random.key(2), dX, dU)
    ref, tol = measured_tol(lambda p, d: _sstep(pol, p, d, jax.random.key(3), cfg_ref, impl="packed"),
                            (params, data), SAFETY)
    assert_tolerances_small(ref, tol, 1e-6)
    got = _sstep(pol, params, data, jax.random.key(3), cfg, impl="packed")
    assert_trees_within(got, ref, tol)
    return got, params


@pytest.mark.parametrize("name", ["mlp", "gmr"])
def test_adam_on_trained_entries_takes_the_same_steps(name):
    """``SStepConfig.adam_entries="trained"`` (Adam carries the trained entries only and θ is
    formed from them each step) against "all": the same arithmetic on every weight, so the same
    S-step up to how XLA fuses (and rounds) the two programs: tolerance from the computation, as
    in ``test_unrolled_loop_takes_the_same_steps``."""
    got, params = _packed_variant_agrees(name, SStepConfig(epochs=3, batch_size=20),
                                         SStepConfig(epochs=3, batch_size=20, adam_entries="trained"))
    assert not np.allclose(ravel_pytree(got[0].net)[0], ravel_pytree(params.net)[0], atol=1e-3)
    with pytest.raises(ValueError, match="sstep.adam_entries"):
        SStepConfig(adam_entries="padding")


@pytest.mark.parametrize("name", ["mlp", "gmr"])
def test_statistics_per_epoch_equal_those_of_every_step(name):
    """``SStepConfig.statistics="epoch"`` (the steps compute the gradient alone and keep their
    weights; each epoch's statistics come from one batched evaluation of its steps afterwards)
    against "step" (inside every step): the same steps on the same weights, minibatches and
    noise, so the same S-step up to how XLA fuses and sums the two programs; tolerance from the
    computation, as in ``test_adam_on_trained_entries_takes_the_same_steps``. Every epoch's
    metrics are compared, not only the last."""
    every = dict(epochs=3, batch_size=20, statistics_epochs="all")
    got, _ = _packed_variant_agrees(name, SStepConfig(statistics="step", **every),
                                    SStepConfig(statistics="epoch", **every))
    assert got[1]["loss"].shape == (3,) and len(set(np.asarray(got[1]["loss"]).tolist())) == 3
    with pytest.raises(ValueError, match="sstep.statistics"):
        SStepConfig(statistics="never")


@pytest.mark.parametrize("name,statistics,extra", [
    ("mlp", "step", {}), ("gmr", "step", {}), ("mlp", "epoch", {}), ("gmr", "epoch", {}),
    ("gmr", "epoch", {"unroll": 2, "adam_entries": "trained"})])
def test_last_epoch_statistics_equal_the_last_of_all(name, statistics, extra):
    """``SStepConfig.statistics_epochs="last"`` against "all": with the statistics per epoch
    (the buffer of one epoch's weights, evaluated after the loop; also unrolled, with Adam on the
    trained entries) and per step (the last epoch sliced). The same steps on the same weights,
    so the same weights and the same last-epoch statistics up to how XLA fuses the two programs
    (tolerance from the computation, as in ``test_adam_on_trained_entries_takes_the_same_steps``),
    each statistic as a [1] array."""
    pol, _ = _policy(name)
    data = _full_data(12)
    params = pol.init(jax.random.key(2), dX, dU)
    cfg = SStepConfig(epochs=3, batch_size=20, statistics=statistics, statistics_epochs="all", **extra)
    (ref_params, ref_m), tol = measured_tol(
        lambda p, d: _sstep(pol, p, d, jax.random.key(3), cfg, impl="packed"), (params, data), SAFETY)
    assert_tolerances_small((ref_params, ref_m), tol, 1e-6)
    last = lambda tree: jax.tree_util.tree_map(lambda a: a[-1:] if a.ndim else a, tree)  # noqa: E731
    got_params, got_m = _sstep(pol, params, data, jax.random.key(3),
                               dataclasses.replace(cfg, statistics_epochs="last"), impl="packed")
    assert got_m["loss"].shape == (1,) and jax.tree_util.tree_all(
        jax.tree_util.tree_map(lambda a: a.shape == (1,), got_m["aux"]))
    assert_trees_within((got_params, got_m), (ref_params, last(ref_m)), tol)  # one tolerance per leaf
    assert bool(got_m["finite"])
    with pytest.raises(ValueError, match="sstep.statistics_epochs"):
        SStepConfig(statistics_epochs="first")
    if statistics == "step":  # once per policy: the reference form returns the last epoch of its curve
        # Two programs again, so a tolerance from the computation: they are the same to the bit
        # with XLA's default CPU code generator, not always with the suite's (tests/conftest.py).
        ref_all, tol_all = measured_tol(lambda p, d: _sstep(pol, p, d, jax.random.key(3), cfg, impl="reference")[1],
                                        (params, data), SAFETY)
        ref_last = _sstep(pol, params, data, jax.random.key(3), dataclasses.replace(cfg, statistics_epochs="last"),
                          impl="reference")[1]
        assert_trees_within(ref_last, last(ref_all), tol_all)


# ------------------------------------------------ the kernel form against the packed form

@pytest.mark.parametrize("name", ["gmr", "gmr_raw", "gmr_uneven"])
def test_kernel_sstep_equals_packed(name):
    """GMR's kernel (``gmr_kernel``, here in Pallas's interpreter) against the packed form: the
    same minibatches, noise and Adam steps with the sums in another order, so the bound of
    ``test_packed_sstep_equals_reference`` holds, 8·δ·lr·S with δ = n_path·ε.

    n_path is the unpadded one. The kernel pads every width to a power of two ≥ 16 and the
    minibatch to 32 rows, but each padding term is an exact zero (zero weights, biases and
    inputs; LeakyReLU(0) = 0; the padded rows' cotangents are 0·(finite) with ρ = 0; the Adam
    update of a zero weight with a zero gradient is 0), and adding an exact zero rounds nothing:
    a padded sum is the same nonzero terms summed in some order, within the same γ_n. The kernel's
    longest loss chain (ΔK Σ over dX, then P· over dU, then the dU·dX terms of the gain) is no
    longer than n_path's (1 + dX) + (1 + dX + dU) + dU·dX. Three configurations: the kernel's
    layout and its head input differ for standardised and raw head coordinates and for a decoder
    and a translation network of different depths. (The packed programs are those of
    ``test_packed_sstep_equals_reference``, compiled already.)"""
    new_m, ref_m, delta = _forms_agree(name, "packed", "kernel", jnp.float64)
    _metrics_agree(new_m, ref_m, delta)
    assert bool(new_m["finite"]) and bool(new_m["weights_ok"])


def test_kernel_sstep_equals_packed_float32():
    """As above in float32 (ε = 1.2e-7), for GMR. In Pallas's interpreter the kernel's products
    are ``Precision.HIGHEST`` whatever ``gmr_kernel.DOT`` says (XLA:CPU has no TF32), and
    training traces the packed form with full float32 products too (``mdgps.iteration``).
    The GPU's "tf32x3" products are measured by ``benchmarks.sstep --kernel-dot``."""
    new_m, ref_m, delta = _forms_agree("gmr", "packed", "kernel", jnp.float32)
    np.testing.assert_allclose(new_m["loss"], ref_m["loss"], rtol=2 * delta)


def test_kernel_product_precision():
    """``gmr_kernel``'s product forms: "tf32x3" means three TF32 products in float32 on a GPU
    only; float64 and the interpreter get IEEE products; an unknown form is refused by name."""
    from jax import lax

    from gmr_jax.policies import gmr_kernel

    assert gmr_kernel._precision("tf32x3", jnp.float32, False) == lax.DotAlgorithmPreset.TF32_TF32_F32_X3
    for dot, dtype, interpret in (("tf32x3", jnp.float64, False), ("tf32x3", jnp.float32, True),
                                  ("ieee", jnp.float32, False)):
        assert gmr_kernel._precision(dot, dtype, interpret) == lax.Precision.HIGHEST
    with pytest.raises(ValueError, match="dot must be one of"):
        gmr_kernel._precision("tf32", jnp.float32, False)


def test_kernel_without_a_kernel_runs_packed(policy):
    """impl="kernel" for a policy without ``Policy.kernel`` (the MLP of "mdgps") is not refused:
    as documented (``sstep``, ``SStepConfig.impl``) it runs the packed form, bit for bit."""
    assert policy.kernel is None and policy.training is not None
    data, _ = _teacher(6)
    params = policy.init(jax.random.key(0), dX, dU)
    cfg = SStepConfig(epochs=2)
    ref = _sstep(policy, params, data, jax.random.key(1), cfg, impl="packed")
    got = _sstep(policy, params, data, jax.random.key(1), cfg, impl="kernel")
    for a, b in zip(jax.tree_util.tree_leaves(ref), jax.tree_util.tree_leaves(got)):
        np.testing.assert_array_equal(a, b)


def test_adam_update_equals_optax():
    """The S-step's Adam is optax.adam operation for operation: bit for bit, float64 and float32,
    with XLA's default CPU code generator. Without its fusion emitters (the runner's CPU option,
    ``sharding.CPU_COMPILER_OPTIONS``, which the suite uses elsewhere: tests/conftest.py), a few
    entries of the two sequences round differently (measured at LLVM's levels 0 and 2)."""
    cfg = SStepConfig()
    rng = np.random.default_rng(0)
    for dtype in (jnp.float64, jnp.float32):
        theta = jnp.asarray(rng.normal(size=300), dtype)
        grads = jnp.asarray(rng.normal(size=(12, 300)) * np.logspace(-12, 2, 300), dtype)
        opt = optax.adam(cfg.lr, b1=cfg.b1, b2=cfg.b2, eps=cfg.eps)

        @jax.jit
        def both(theta, grads):
            c1, c2 = adam_corrections(cfg, len(grads), theta.dtype)
            ref, state = theta, opt.init(theta)
            new, mu, nu = theta, jnp.zeros_like(theta), jnp.zeros_like(theta)
            for t, g in enumerate(grads):
                updates, state = opt.update(g, state, ref)
                ref = optax.apply_updates(ref, updates)
                new, mu, nu = adam_update(cfg, new, mu, nu, g, c1[t], c2[t])
            return ref, new

        ref, new = both.lower(theta, grads).compile(compiler_options=XLA_DEFAULT_CPU_CODEGEN)(theta, grads)
        assert new.dtype == dtype
        np.testing.assert_array_equal(new, ref)


@pytest.mark.parametrize("name", list(POLICY_CFGS))
def test_packing_keeps_the_initial_weights(name):
    """pack/unpack: the Flax initialisation comes back bit for bit (same tree, dtypes), and the
    packed vector holds every weight once, the rest zeros."""
    pol, _ = _policy(name)
    for dtype in (jnp.float64, jnp.float32):
        params = pol.init(jax.random.key(7), dX, dU, dtype)
        theta = pol.training.pack(params)
        assert theta.dtype == dtype and theta.ndim == 1
        back = pol.training.unpack(params, theta)
        assert jax.tree_util.tree_structure(back) == jax.tree_util.tree_structure(params.net)
        for a, b in zip(jax.tree_util.tree_leaves(back), jax.tree_util.tree_leaves(params.net)):
            assert a.dtype == b.dtype
            np.testing.assert_array_equal(a, b)
        ones = pol.training.pack(params._replace(net=jax.tree_util.tree_map(jnp.ones_like, params.net)))
        assert float(jnp.sum(ones)) == sum(a.size for a in jax.tree_util.tree_leaves(params.net))
        assert np.sum(np.abs(np.asarray(theta))) == pytest.approx(
            sum(float(jnp.sum(jnp.abs(a))) for a in jax.tree_util.tree_leaves(params.net)), rel=1e-6)


def test_column_blocks_split_and_join():
    """A layer's outputs as column blocks of at most ``width``: the shapes, and split/join as
    inverses."""
    assert column_blocks((5, 14), 6) == [(5, 6), (5, 6), (5, 2)]
    assert column_blocks((5, 12), 6) == [(5, 6), (5, 6)]
    assert column_blocks((5, 4), 6) == [(5, 4)]
    kernel, bias = jnp.arange(70.0).reshape(5, 14), jnp.arange(14.0)
    blocks = split_columns((kernel, bias), column_blocks((5, 14), 6))
    assert [k.shape for k, _ in blocks] == [(5, 6), (5, 6), (5, 2)]
    np.testing.assert_array_equal(blocks[2][0], kernel[:, 12:])
    back = join_columns(blocks)
    np.testing.assert_array_equal(back[0], kernel)
    np.testing.assert_array_equal(back[1], bias)


@pytest.mark.parametrize("hidden, head_slots", [(64, 2), (40, 3), (128, 1)])
def test_gmr_head_is_held_in_slots_as_wide_as_the_other_layers(hidden, head_slots):
    """GMR's packed θ for the reach task's shapes (dX = 12, dU = 6: a head of 72 + 6 + 36 = 114
    columns): the slot width is the widest layer other than the head, and the head takes
    ceil(114 / width) slots, so θ has (3 + 3 + 2 + head_slots)·(I + 1)·O entries."""
    cfg = GMRConfig(encoder_hidden=(hidden, hidden), decoder_hidden=(hidden, hidden),
                    translation_hidden=(hidden, hidden))
    pol = make_policy("gmr", cfg)
    # shapes only (the packing tests above check the values)
    params = jax.eval_shape(lambda: pol.init(jax.random.key(0), 12, 6))
    width = max(hidden, 12)  # the decoder's output (dX = 12) is the widest non-hidden layer
    assert head_slots == -(-114 // width)
    theta = jax.eval_shape(pol.training.pack, params)
    assert theta.shape == ((8 + head_slots) * (hidden + 1) * width,)
    back = jax.eval_shape(pol.training.unpack, params, theta)
    assert jax.tree_util.tree_map(lambda a: a.shape, back) == jax.tree_util.tree_map(lambda a: a.shape, params.net)


def test_impl_choice_and_fallback(policy):
    """The CPU defaults to the reference form; a policy without a TrainingForm runs the
    reference form under impl="packed"; an unknown impl is refused."""
    assert default_impl() == ("reference" if jax.default_backend() == "cpu" else "packed")
    data, _ = _teacher(6)
    params = policy.init(jax.random.key(0), dX, dU)
    cfg = SStepConfig(epochs=2)
    bare = Policy(*policy[:5])
    assert bare.training is None
    ref = _sstep(policy, params, data, jax.random.key(1), cfg, impl="reference")
    got = _sstep(bare, params, data, jax.random.key(1), cfg, impl="packed")
    for a, b in zip(jax.tree_util.tree_leaves(ref), jax.tree_util.tree_leaves(got)):
        np.testing.assert_array_equal(a, b)
    with pytest.raises(ValueError, match="impl"):
        sstep(policy, params, data, jax.random.key(1), cfg, impl="fast")


def test_the_benchmark_refuses_a_batch_size_below_one(capsys):
    from benchmarks import sstep as benchmark
    with pytest.raises(SystemExit):
        benchmark.parse_args(["--batch-size", "0"])
    assert "--batch-size: must be a positive integer, got '0'" in capsys.readouterr().err

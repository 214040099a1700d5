"""The policy interface and the MDGPS baseline MLP: forward pass, loss, variance rule, dtypes."""


import jax
import jax.numpy as jnp
import numpy as np
import pytest

from tolerances import SAFETY, assert_close, assert_tolerances_small, assert_trees_within, linear_tol, measured_tol

from gmr_jax.config import MLPConfig
from gmr_jax.policies import PolicyParams, l2_penalty, make_policy, make_sstep_data, noisy_action
from gmr_jax.policies.base import Normalization, SStepData
from gmr_jax.policies.mlp import closed_form_variance

dX, dU = 5, 3


def _spd(rng, n, count):
    A = rng.normal(size=(count, n, n))
    return A @ np.transpose(A, (0, 2, 1)) / n + 0.5 * np.eye(n)


def _numpy_forward(params: PolicyParams, x, squash: float = 0.0):
    """Independent forward pass: normalise (and bound by c·tanh(·/c)), Dense + ReLU per hidden
    layer, linear output."""
    layers = params.net["params"]
    h = np.asarray(x) * np.asarray(params.norm.scale) + np.asarray(params.norm.bias)
    if squash > 0:
        h = squash * np.tanh(h / squash)
    names = sorted(layers, key=lambda s: int(s.split("_")[1]))
    for i, name in enumerate(names):
        h = h @ np.asarray(layers[name]["kernel"]) + np.asarray(layers[name]["bias"])
        if i < len(names) - 1:
            h = np.maximum(h, 0.0)
    return h


@pytest.fixture(scope="module")
def policy():
    return make_policy("mlp", MLPConfig(hidden=(16, 8)))


def _init(policy, key, dx, du, dtype=None):
    return policy.init(jax.random.key(key), dx, du, dtype)


def _params_with_norm(policy, key=0):
    rng = np.random.default_rng(key)
    params = _init(policy, key, dX, dU)
    norm = Normalization(scale=jnp.asarray(rng.uniform(0.5, 2.0, dX)),
                         bias=jnp.asarray(rng.normal(size=dX)), set=jnp.asarray(True))
    return params._replace(norm=norm)


def test_init_shapes_dtypes_and_defaults(policy):
    params = _init(policy, 0, dX, dU)
    shapes = jax.tree_util.tree_map(jnp.shape, params.net["params"])
    assert shapes == {"Dense_0": {"kernel": (dX, 16), "bias": (16,)},
                      "Dense_1": {"kernel": (16, 8), "bias": (8,)},
                      "Dense_2": {"kernel": (8, dU), "bias": (dU,)}}
    for leaf in jax.tree_util.tree_leaves(params):
        assert leaf.dtype in (jnp.float64, jnp.bool_)  # float64 is the default under x64
    np.testing.assert_array_equal(params.var, np.full(dU, 0.1))
    np.testing.assert_array_equal(params.norm.scale, np.ones(dX))
    np.testing.assert_array_equal(params.norm.bias, np.zeros(dX))
    assert not bool(params.norm.set)
    p32 = _init(policy, 0, dX, dU, jnp.float32)
    assert {leaf.dtype for leaf in jax.tree_util.tree_leaves(p32)} == {jnp.dtype(jnp.float32), jnp.dtype(bool)}
    u32 = policy.mean(p32, jnp.ones(dX, jnp.float32))
    assert u32.dtype == jnp.float32 and u32.shape == (dU,)


def test_paper_default_architecture():
    params = _init(make_policy("mlp"), 0, 12, 6)
    kernels = [params.net["params"][f"Dense_{i}"]["kernel"].shape for i in range(3)]
    assert kernels == [(12, 64), (64, 64), (64, 6)]


def test_toolbox_normal_init():
    params = _init(make_policy("mlp", MLPConfig(init="normal", init_std=0.01)), 3, 12, 6)
    layers = params.net["params"]
    w = np.concatenate([np.ravel(layers[n]["kernel"]) for n in layers])
    assert abs(np.std(w) - 0.01) < 0.001  # 4992 draws: the std is within ~1% of 0.01
    assert all(np.all(np.asarray(layers[n]["bias"]) == 0) for n in layers)


def test_mean_matches_numpy_and_batches(policy):
    params = _params_with_norm(policy)
    x = np.random.default_rng(1).normal(size=(7, dX))
    u_batch = policy.mean(params, jnp.asarray(x))
    u_rows = jax.vmap(policy.mean, in_axes=(None, 0))(params, jnp.asarray(x))
    # Tolerance from the computation (tests/tolerances.py): the numpy forward pass rerun on
    # parameters and states perturbed by ε relative, SAFETY times the spread; the rows against
    # the batch are two programs around the same reference.
    ref, tol = measured_tol(_numpy_forward, (params, x), SAFETY)
    assert_tolerances_small(ref, tol, 1e-10)
    assert_trees_within(u_batch, ref, tol)
    assert_trees_within(u_rows, u_batch, 2 * tol[0])


def test_loss_equals_numpy(policy):
    rng = np.random.default_rng(2)
    params = _params_with_norm(policy)
    B = 9
    x = rng.normal(size=(B, dX))
    tgt = rng.normal(size=(B, dU))
    prc = _spd(rng, dU, B)
    data = make_sstep_data(x, tgt, prc)
    value, aux = policy.loss(params, data, jax.random.key(0))

    def np_loss(params, x, tgt, prc):
        d = _numpy_forward(params, np.asarray(x)) - np.asarray(tgt)
        return 0.5 * np.mean([d[b] @ np.asarray(prc[b]) @ d[b] for b in range(B)]), np.mean(d ** 2)

    # Tolerance from the computation (tests/tolerances.py), as in test_mean_matches_numpy.
    ref, tol = measured_tol(np_loss, (params, x, tgt, prc), SAFETY)
    assert_tolerances_small(ref, tol, 1e-10)
    assert_trees_within((value, aux["action_mse"]), ref, tol)
    # β·Σθ² over all weights and biases: a sum of n positive terms, c·n·ε relative
    theta = np.concatenate([np.ravel(leaf) for leaf in jax.tree_util.tree_leaves(params.net)])
    assert_close(l2_penalty(params.net), np.sum(theta ** 2), 2 * linear_tol(1.0, theta.size))


def test_covariance_and_variance_rule(policy):
    rng = np.random.default_rng(4)
    params = _init(policy, 0, dX, dU)
    B = 11
    prc = _spd(rng, dU, B)
    data = make_sstep_data(rng.normal(size=(B, dX)), rng.normal(size=(B, dU)), prc)
    fin = policy.finalize(params, data)  # constant weights: 1/diag(mean precision)
    # a mean of B positive diagonals and a reciprocal in each program: c·(B + 1)·ε relative
    # (tests/tolerances.py)
    assert_close(fin.var, 1.0 / np.diag(prc.mean(axis=0)), 2 * linear_tol(1.0, B + 1))
    cov = policy.covariance(fin, jnp.zeros(dX))
    assert_close(cov, np.diag(1.0 / np.diag(prc.mean(axis=0))), 2 * linear_tol(1.0, B + 1))
    # a zero-weight (padding) row drops out; ent_reg adds 2·ent_reg to the diagonal
    w = np.ones(B)
    w[0] = 0.0
    var = closed_form_variance(jnp.asarray(prc), jnp.asarray(w), ent_reg=0.3)
    assert_close(var, 1.0 / (np.diag(prc[1:].mean(axis=0)) + 0.6), 2 * linear_tol(1.0, B + 2))


def test_noisy_action_covariance(policy):
    params = _params_with_norm(policy)._replace(var=jnp.array([0.5, 2.0, 1.5]))
    x = jnp.ones(dX)
    eps = jax.random.normal(jax.random.key(1), (20000, dU))
    u = jax.vmap(lambda e: noisy_action(policy, params, x, e))(eps)
    np.testing.assert_allclose(u.mean(0), policy.mean(params, x), atol=0.05)
    np.testing.assert_allclose(np.var(np.asarray(u), axis=0), [0.5, 2.0, 1.5], rtol=0.05)


def test_make_policy_cache_and_errors():
    assert make_policy("mlp", MLPConfig()) is make_policy("mlp", MLPConfig())
    assert make_policy("mlp") is make_policy("mlp", MLPConfig())
    assert make_policy("mlp") is not make_policy("mlp", MLPConfig(hidden=(8,)))
    with pytest.raises(ValueError, match="allowed values"):
        make_policy("linear")
    with pytest.raises(ValueError, match="mlp.activation"):
        MLPConfig(activation="sigmoid")


def test_sstep_data_fill_zeros():
    data = make_sstep_data(np.ones((4, dX)), np.ones((4, dU)), np.ones((4, dU, dU)))
    assert isinstance(data, SStepData)
    assert data.K.shape == (4, dU, dX) and data.k.shape == (4, dU) and data.state_cov.shape == (4, dX, dX)
    np.testing.assert_array_equal(data.wt, np.ones(4))


def test_input_squash_bounds_what_the_network_sees():
    """``MLPConfig.input_squash`` (the ablation of GMR's encoder bound): the mean and the packed
    S-step rows both see c·tanh(x̃/c)."""
    squashed = make_policy("mlp", MLPConfig(hidden=(16, 8), input_squash=0.5))
    params = _params_with_norm(squashed)
    x = 4.0 * np.random.default_rng(2).normal(size=(7, dX))  # far out: the bound matters
    ref, tol = measured_tol(lambda p, xx: _numpy_forward(p, xx, 0.5), (params, x), SAFETY)
    assert_trees_within(squashed.mean(params, jnp.asarray(x)), ref, tol)
    plain = make_policy("mlp", MLPConfig(hidden=(16, 8)))
    assert not np.allclose(np.asarray(plain.mean(params, jnp.asarray(x))), ref)
    data = make_sstep_data(jnp.asarray(x), jnp.zeros((7, dU)), jnp.broadcast_to(jnp.eye(dU), (7, dU, dU)))
    rows = squashed.training.rows(params, data)
    xn = np.asarray(x) * np.asarray(params.norm.scale) + np.asarray(params.norm.bias)
    np.testing.assert_allclose(np.asarray(rows)[:, :dX], 0.5 * np.tanh(xn / 0.5), rtol=1e-14)
    with pytest.raises(ValueError, match="input_squash"):
        MLPConfig(input_squash=-1.0)

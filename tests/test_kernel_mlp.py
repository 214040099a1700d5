"""benchmarks.kernel_mlp: its Pallas kernels compute what their XLA reference computes.

Off a GPU the kernels run in Pallas's interpreter, so this checks the arithmetic of the benchmark's
kernels (the device's timings are benchmarks/RESULTS.md's): the minibatch steps of plain MLPs with
the backward pass written out, weights in global memory or in the loop's carry, and the chain of
dependent products.
"""

import jax.numpy as jnp
import numpy as np
import pytest

from benchmarks import kernel_mlp
from gmr_jax.config import SStepConfig

STEPS = 4
EPS32 = float(np.finfo(np.float32).eps)


@pytest.mark.parametrize("weights", ["global", "carry"])
@pytest.mark.parametrize("update", ["sgd", "adam"])
def test_kernel_steps_equal_the_xla_steps(weights, update):
    nets = 2
    prob = kernel_mlp.problem(nets, STEPS, update, jnp.float32, rows=60)
    ref = kernel_mlp.reference_call(nets, STEPS, update, jnp.float32)(*prob)
    out = kernel_mlp.kernel_call(nets, STEPS, weights, update, 4, "tf32x3", jnp.dtype(jnp.float32), True)(*prob)
    n = 6 * nets
    assert len(out) == len(ref) == n + (2 * n if update == "adam" else 0) + 1
    # the steps moved the weights, so the comparison below is not of the initial state
    assert kernel_mlp.relative_difference(ref[:n], prob[5]) > 1e-4
    cfg = SStepConfig()
    if update == "sgd":
        # the same operations in float32: per step, each gradient entry is a sum of at most 64
        # products (the widest layer), so it carries at most 64 roundings; SGD adds lr·g to a
        # weight larger than lr·g, so per step the relative error grows by at most 64·eps
        bound = STEPS * 64 * EPS32
        assert kernel_mlp.relative_difference(out[:n], ref[:n]) <= bound
    else:
        # Adam's step is at most lr·(1−b1)/√(1−b2) per entry whatever the gradient (Kingma and Ba,
        # §2.1), so two runs whose gradients differ by round-off cannot drift apart by more than
        # twice that per step, even where a tiny gradient changes sign
        per_step = cfg.lr * (1 - cfg.b1) / np.sqrt(1 - cfg.b2)
        a, b = (np.concatenate([np.ravel(np.asarray(t)) for t in x[:n]]) for x in (out, ref))
        assert np.max(np.abs(a - b)) <= 2 * STEPS * per_step
    # the losses before each step: the same forward pass
    np.testing.assert_allclose(np.asarray(out[-1]), np.asarray(ref[-1]), rtol=64 * EPS32 * STEPS)
    assert np.all(np.diff(np.asarray(ref[-1])) != 0)


def test_chain_kernel_is_the_chain_of_products():
    rng = np.random.default_rng(1)
    h = rng.normal(size=(kernel_mlp.PADDED_BATCH, 64)).astype(np.float32)
    w = np.linalg.qr(rng.normal(size=(64, 64)))[0].astype(np.float32)
    chain, steps = 3, 2
    out = np.asarray(kernel_mlp.chain_call(chain, steps, 4, "tf32x3", True)(jnp.asarray(h), jnp.asarray(w)))
    expect = h.astype(np.float64)
    for _ in range(chain * steps):
        pre = expect @ w.astype(np.float64)
        expect = np.where(pre >= 0, pre, kernel_mlp.SLOPE * pre)
    # six products of 64 terms in float32 against float64, with an orthogonal W (no growth)
    assert np.max(np.abs(out - expect)) <= chain * steps * 64 * EPS32 * np.max(np.abs(expect))

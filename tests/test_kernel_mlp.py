"""benchmarks.kernel_mlp: its Pallas kernels compute what their XLA reference computes.

Off a GPU the kernels run in Pallas's interpreter, so this checks the arithmetic of the benchmark's
kernels (the device's timings are benchmarks/RESULTS.md's): the minibatch steps of plain MLPs with
the backward pass written out, weights in global memory or in the loop's carry, and the chain of
dependent products.
"""

import json
import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from benchmarks import kernel_mlp
from gmr_jax.config import SStepConfig

STEPS = 4
EPS32 = float(np.finfo(np.float32).eps)


def _flat(arrays):
    return np.concatenate([np.ravel(np.asarray(a)) for a in arrays])


def _assert_same_steps(out, ref, W_init, update, n):
    """``out`` and ``ref`` (params…, moments…, losses) are the same ``STEPS`` minibatch steps from
    the initial weights ``W_init``, to round-off."""
    assert len(out) == len(ref) == n + (2 * n if update == "adam" else 0) + 1
    # Round-off of one step's gradient: the longest chain is five dependent products (three
    # forward, two back), each a sum of at most 64 float32 terms, so each gradient entry is within
    # 5·64 roundings of the other form's; an update adds lr·g, far below |W|, so the weights' and
    # the moments' relative difference grows by at most that per step.
    roundoff = STEPS * 5 * 64 * EPS32
    W_out, W_ref, W_init = _flat(out[:n]), _flat(ref[:n]), _flat(W_init)
    scale = np.max(np.abs(W_ref))
    if update == "sgd":
        assert np.max(np.abs(W_out - W_ref)) <= roundoff * scale
        moved = np.max(np.abs(W_ref - W_init))
    else:
        # the moments are smooth in the gradients: μ linear, ν quadratic (twice the relative error)
        mu_out, mu_ref = _flat(out[n:3 * n:2]), _flat(ref[n:3 * n:2])
        nu_out, nu_ref = _flat(out[n + 1:3 * n:2]), _flat(ref[n + 1:3 * n:2])
        assert np.max(np.abs(mu_out - mu_ref)) <= roundoff * np.max(np.abs(mu_ref))
        assert np.max(np.abs(nu_out - nu_ref)) <= 2 * roundoff * np.max(np.abs(nu_ref))
        # Adam's step m̂/(√v̂ + ε) is about ±1 for a gradient near 0 whatever its size, so an entry
        # whose tiny gradient differs in sign by round-off may part by up to twice the largest
        # step, lr·(1−b1)/√(1−b2) (Kingma and Ba, §2.1), per step; every other entry agrees to
        # round-off, which the median checks
        cfg = SStepConfig()
        per_step = cfg.lr * (1 - cfg.b1) / np.sqrt(1 - cfg.b2)
        assert np.max(np.abs(W_out - W_ref)) <= 2 * STEPS * per_step
        assert np.median(np.abs(W_out - W_ref)) <= roundoff * scale
        moved = np.median(np.abs(W_ref - W_init))
    # the steps moved the weights far beyond those bounds, so they compare trained weights
    assert moved >= 10 * roundoff * scale
    # the losses before each step: the same forward passes
    np.testing.assert_allclose(np.asarray(out[-1]), np.asarray(ref[-1]), rtol=roundoff)


@pytest.mark.parametrize("weights", ["global", "carry"])
@pytest.mark.parametrize("update", ["sgd", "adam"])
def test_kernel_steps_equal_the_xla_steps(weights, update):
    nets, n = 2, 12
    prob = kernel_mlp.problem(nets, STEPS, update, jnp.float32, rows=60)
    ref = kernel_mlp.reference_call(nets, STEPS, update, jnp.float32)(*prob)
    # off a GPU the kernel runs in the interpreter with IEEE products whatever ``dot`` says
    out = kernel_mlp.kernel_call(nets, STEPS, weights, update, 4, "ieee", jnp.dtype(jnp.float32), True)(*prob)
    _assert_same_steps(out, ref, prob[5], update, n)


def test_kernel_rejects_an_unknown_product_form():
    with pytest.raises(ValueError, match="dot"):
        kernel_mlp.kernel_call(1, 2, "global", "sgd", 4, "fp8", jnp.dtype(jnp.float32), True)


def test_chain_kernel_is_the_chain_of_products():
    rng = np.random.default_rng(1)
    h = rng.normal(size=(kernel_mlp.PADDED_BATCH, 64)).astype(np.float32)
    w = np.linalg.qr(rng.normal(size=(64, 64)))[0].astype(np.float32)
    chain, steps = 3, 2
    out = np.asarray(kernel_mlp.chain_call(chain, steps, 4, "ieee", True)(jnp.asarray(h), jnp.asarray(w)))
    expect = h.astype(np.float64)
    for _ in range(chain * steps):
        pre = expect @ w.astype(np.float64)
        expect = np.where(pre >= 0, pre, kernel_mlp.SLOPE * pre)
    # six products of 64 terms in float32 against float64, with an orthogonal W (no growth)
    assert np.max(np.abs(out - expect)) <= chain * steps * 64 * EPS32 * np.max(np.abs(expect))


def _command(argv: list[str], out, monkeypatch) -> dict:
    """``python -m benchmarks.kernel_mlp ARGV --out OUT`` in this process: its JSON record. The command
    sets float32 and XLA_FLAGS for the process; both are restored for the next tests."""
    monkeypatch.setenv("XLA_FLAGS", os.environ.get("XLA_FLAGS", ""))
    x64 = jax.config.jax_enable_x64
    try:
        assert kernel_mlp.main(argv + ["--out", str(out)]) == 0
    finally:
        jax.config.update("jax_enable_x64", x64)
    return json.loads(out.read_text())


def test_the_command_off_a_gpu_checks_and_skips_the_mosaic_chain(tmp_path, capsys, monkeypatch):
    """Off a GPU: the Triton kernels run in the interpreter, the Mosaic ones are skipped in one line,
    and the JSON records every row with its comparison against the XLA steps."""
    rec = _command(["--nets", "1", "--weights", "carry", "--update", "sgd", "--num-warps", "4",
                    "--chain", "1,2", "--mosaic-chain", "1", "--steps", "3", "--repeats", "1"],
                   tmp_path / "k.json", monkeypatch)
    printed = capsys.readouterr().out
    assert "--mosaic-chain: skipped" in printed
    kernel = [r for r in rec["rows"] if r["form"] == "kernel"]
    assert len(kernel) == 1 and kernel[0]["max_rel_diff_vs_reference"] <= 3 * 5 * 64 * EPS32
    assert kernel[0]["first_step_loss_differs"] is None
    assert [c["chain"] for c in rec["chains"]] == [1, 2] and rec["mosaic_chains"] == []


def test_seeds_side_by_side_are_the_separate_seeds():
    """``--seeds``: the kernel mapped over seeds (a grid axis of one launch) computes, per seed, what
    that seed's problem computes alone; the seeds' data and weights differ."""
    nets, seeds, update = 1, 3, "adam"
    n = 6 * nets
    prob = kernel_mlp.problem(nets, STEPS, update, jnp.float32, rows=60, seeds=seeds)
    call = kernel_mlp.kernel_call(nets, STEPS, "carry", update, 4, "ieee", jnp.dtype(jnp.float32), True)
    out = kernel_mlp.over_seeds(call, seeds)(*prob)
    assert np.asarray(out[0]).shape[0] == seeds
    for s in range(seeds):
        # the seed alone: its own data and weights, the shared minibatch rows
        alone = kernel_mlp.problem(nets, STEPS, update, jnp.float32, rows=60, seed=s)
        own = kernel_mlp.seed_of(prob, s)
        for x, y in zip(jax.tree_util.tree_leaves(own[3:]), jax.tree_util.tree_leaves(alone[3:])):
            np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
        _assert_same_steps([np.asarray(a)[s] for a in out], call(prob[0], *alone[1:]), alone[5], update, n)
    # the seeds differ: different data and initial weights give different trained weights
    assert not np.allclose(_flat([np.asarray(w)[0] for w in out[:n]]), _flat([np.asarray(w)[1] for w in out[:n]]))


def test_the_command_checks_many_seeds_against_each_seed_alone(tmp_path, monkeypatch):
    rec = _command(["--nets", "1", "--weights", "carry", "--update", "sgd", "--num-warps", "4", "--dot", "ieee",
                    "--seeds", "3", "--steps", "2", "--repeats", "1"], tmp_path / "k.json", monkeypatch)
    kernel = [r for r in rec["rows"] if r["form"] == "kernel"]
    assert len(kernel) == 1 and kernel[0]["seeds"] == 3
    # the same interpreter program for a seed of three and for the seed alone: round-off of two
    # steps at most (0 where XLA compiles both the same way)
    assert kernel[0]["max_rel_diff_from_the_seeds_alone"] <= 2 * 5 * 64 * EPS32
    assert kernel[0]["seeds_rel_diff_above_1e-4"] == 0 and kernel[0]["seeds_whose_losses_part"] == 0

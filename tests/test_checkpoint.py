"""Checkpoints: exact round trips, step bookkeeping, clear errors, no loss of earlier checkpoints."""

import glob
import json
import os

import jax
import jax.numpy as jnp
import numpy as np
import orbax.checkpoint as ocp
import pytest

from gmr_jax import checkpoint as ck
from gmr_jax.policies.base import Normalization, PolicyParams


def _state(seed=0):
    rng = np.random.default_rng(seed)
    params = PolicyParams(
        net={"params": {"Dense_0": {"kernel": jnp.asarray(rng.normal(size=(3, 4))),
                                    "bias": jnp.asarray(rng.normal(size=4), jnp.float32)}}},
        norm=Normalization(scale=jnp.asarray(rng.uniform(size=3)), bias=jnp.zeros(3),
                           set=jnp.asarray(True)),
        var=jnp.asarray(rng.uniform(size=2)))
    return {
        "params": params,
        "key": jax.random.split(jax.random.key(seed), 3),          # typed keys
        "raw_key": jax.random.PRNGKey(seed + 1),                    # raw uint32 key
        "buffer": (jnp.asarray(rng.normal(size=(2, 5, 3))), jnp.arange(4, dtype=jnp.int32),
                   jnp.asarray([True, False])),
        "empty": jnp.zeros((0, 3)),
        "iteration": np.int64(seed + 3),
        "eta": 0.5 + seed,
    }


def _assert_same(a, b):
    assert jax.tree_util.tree_structure(a) == jax.tree_util.tree_structure(b)
    for x, y in zip(jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b)):
        assert type(x) is type(y)
        if jax.dtypes.issubdtype(getattr(x, "dtype", np.float64), jax.dtypes.prng_key):
            assert x.dtype == y.dtype and jax.random.key_impl(x) == jax.random.key_impl(y)
            x, y = jax.random.key_data(x), jax.random.key_data(y)
        assert np.asarray(x).dtype == np.asarray(y).dtype
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


def test_round_trip_and_steps(tmp_path):
    path = tmp_path / "ckpt"
    assert ck.latest(path) is None and not path.exists()
    s1, s2 = _state(0), _state(1)
    ck.save(path, s1, 1, {"config": {"T": 80, "hidden": (64, 64)}, "note": "first"})
    ck.save(path, s2, 5, {"config": {"T": 80, "hidden": (64, 64)}})
    assert ck.latest(path) == 5 and ck.all_steps(path) == [1, 5]

    out, meta = ck.restore(path, s1)  # latest by default; the template only gives the structure
    _assert_same(out, s2)
    assert meta == {"config": {"T": 80, "hidden": [64, 64]}}
    out1, meta1 = ck.restore(path, s2, step=1, expect={"config": {"T": 80, "hidden": (64, 64)}})
    _assert_same(out1, s1)
    assert meta1["note"] == "first"
    # an abstract template works too
    out_abs, _ = ck.restore(path, jax.eval_shape(lambda: _state(0)), step=1)
    np.testing.assert_array_equal(out_abs["params"].net["params"]["Dense_0"]["kernel"],
                                  s1["params"].net["params"]["Dense_0"]["kernel"])
    with pytest.raises(ck.CheckpointError, match="step 3 not found.*available steps: \\[1, 5\\]"):
        ck.restore(path, s1, step=3)
    with pytest.raises(ck.CheckpointError, match="no checkpoint found"):
        ck.restore(tmp_path / "nothing", s1)


def test_incompatible_templates_and_settings(tmp_path):
    path = tmp_path / "ckpt"
    state = _state(0)
    ck.save(path, state, 2, {"config": {"task": {"T": 80}, "iterations": 10}})

    extra = dict(state, extra=jnp.ones(2))
    with pytest.raises(ck.CheckpointError, match="different tree structure.*only in the template: \\['extra'\\]"):
        ck.restore(path, extra)
    fewer = {k: v for k, v in state.items() if k != "eta"}
    with pytest.raises(ck.CheckpointError, match="only in the checkpoint: \\['eta'\\]"):
        ck.restore(path, fewer)
    wrong_shape = dict(state, buffer=(jnp.zeros((2, 6, 3)),) + state["buffer"][1:])
    with pytest.raises(ck.CheckpointError, match=r"\['buffer'\]\[0\]: checkpoint \(2, 5, 3\) float64, template \(2, 6, 3\) float64"):
        ck.restore(path, wrong_shape)
    wrong_dtype = dict(state, params=state["params"]._replace(var=state["params"].var.astype(jnp.float32)))
    with pytest.raises(ck.CheckpointError, match=r"\.var: checkpoint \(2,\) float64, template \(2,\) float32"):
        ck.restore(path, wrong_dtype)
    raw_instead_of_typed = dict(state, key=jax.random.key_data(state["key"]))
    with pytest.raises(ck.CheckpointError, match="key type key<fry> in the checkpoint"):
        ck.restore(path, raw_instead_of_typed)
    with pytest.raises(ck.CheckpointError, match="different settings: config.task.T: checkpoint 80, expected 20"):
        ck.restore(path, state, expect={"config": {"task": {"T": 20}, "iterations": 10}})
    ck.restore(path, state, expect={"config": {"task": {"T": 80}, "iterations": 10}})  # matches


def test_corrupt_checkpoints_are_reported_and_others_survive(tmp_path):
    path = tmp_path / "ckpt"
    old, new = _state(0), _state(1)
    ck.save(path, old, 1)
    ck.save(path, new, 2)

    # 1. the arrays' files overwritten with garbage
    for f in glob.glob(str(path / "2" / "state" / "**"), recursive=True):
        if os.path.isfile(f):
            with open(f, "wb") as fh:
                fh.write(b"garbage")
    with pytest.raises(ck.CheckpointError, match="step 2 .* is corrupt.*other steps available: \\[1\\]"):
        ck.restore(path, old)
    _assert_same(ck.restore(path, old, step=1)[0], old)

    # 2. metadata unreadable
    ck.save(path, new, 3)
    with open(path / "3" / "meta" / "metadata", "w") as fh:
        fh.write("{not json")
    with pytest.raises(ck.CheckpointError, match="step 3 .* is corrupt: its metadata cannot be read"):
        ck.restore(path, old)

    # 3. data that no longer matches its checksum (tampered manifest entry)
    ck.save(path, new, 4)
    meta_file = path / "4" / "meta" / "metadata"
    meta = json.loads(meta_file.read_text())
    meta["leaves"][0]["sha256"] = "0" * 64
    meta_file.write_text(json.dumps(meta))
    with pytest.raises(ck.CheckpointError, match="corrupt: data of .* does not match the stored checksum"):
        ck.restore(path, old, step=4)
    assert ck.all_steps(path) == [1, 2, 3, 4]
    _assert_same(ck.restore(path, old, step=1)[0], old)


def test_failed_save_keeps_previous(tmp_path, monkeypatch):
    path = tmp_path / "ckpt"
    old, new = _state(0), _state(1)
    ck.save(path, old, 1, {"n": 1})

    async def disk_full(self, *args, **kwargs):
        raise OSError("No space left on device")

    with monkeypatch.context() as m:  # the write fails after orbax created its temporary directory
        m.setattr(ocp.StandardCheckpointHandler, "async_save", disk_full)
        with pytest.raises(ck.CheckpointError, match="saving checkpoint step 2 .* failed.*No space left"):
            ck.save(path, new, 2)
    assert ck.latest(path) == 1 and not (path / "2").exists()
    _assert_same(ck.restore(path, old)[0], old)

    with pytest.raises(ck.CheckpointError, match="not JSON-serialisable"):
        ck.save(path, new, 2, {"bad": object()})
    with pytest.raises(ck.CheckpointError, match="cannot be saved"):
        ck.save(path, dict(new, fn="text"), 2)
    with pytest.raises(ck.CheckpointError, match="already exists"):
        ck.save(path, new, 1)
    assert ck.latest(path) == 1
    _assert_same(ck.restore(path, old)[0], old)

    ck.save(path, new, 2)  # a later save succeeds and cleans the failed attempt's leftovers
    assert ck.all_steps(path) == [1, 2]
    assert sorted(os.listdir(path)) == ["1", "2"]
    with pytest.raises(ck.CheckpointError, match="older than the latest step 2"):
        ck.save(path, new, 0)
    _assert_same(ck.restore(path, old, step=2)[0], new)


_CORRUPT_SCRIPT = r"""
import gc, glob, os, sys, time
import numpy as np
from gmr_jax import checkpoint
d = sys.argv[1]
state = {"x": np.arange(1000.0), "y": np.ones((50, 50))}
checkpoint.save(d, state, step=1)
checkpoint.save(d, state, step=2)
for f in glob.glob(os.path.join(d, "2", "state", "**"), recursive=True):
    if os.path.isfile(f) and os.sep + "d" + os.sep in f:  # the array data files
        b = bytearray(open(f, "rb").read()); b[len(b) // 2] ^= 0xFF; open(f, "wb").write(bytes(b))
for _ in range(8):
    try:
        checkpoint.restore(d, state, step=2)
    except checkpoint.CorruptCheckpointError as err:
        print("corrupt:", str(err)[:40])
gc.collect(); time.sleep(0.5); gc.collect()
"""


def test_a_corrupt_checkpoint_reports_one_error_and_no_stray_tracebacks(tmp_path):
    """A flipped byte in the array data: CorruptCheckpointError, and nothing else on stderr (the
    failed read used to leave tensorstore callbacks that printed "Event loop is closed"
    tracebacks after the error). Run in a fresh interpreter, as a user's CLI would be."""
    import subprocess
    import sys

    out = subprocess.run([sys.executable, "-c", _CORRUPT_SCRIPT, str(tmp_path / "ckpt")],
                         capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.count("corrupt: checkpoint step 2") == 8, out.stdout
    assert "Traceback" not in out.stderr and "Event loop is closed" not in out.stderr, out.stderr[-2000:]

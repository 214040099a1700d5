"""The program store (gmr_jax.program_store): a stored program is lowered without tracing and
computes what the traced program computes; every input of the trace is part of its key; what
cannot be stored or read is traced as before."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gmr_jax import mdgps, program_store, runner, sharding
from test_mdgps import small


def _program():
    return sharding.seed_program(mdgps.part_program(("model",)), sharding.seed_mesh(1), (True, False))


@pytest.fixture(scope="module")
def model_inputs():
    """A one-seed GMR run's carry before its model part (samples of the first iteration)."""
    cfg = runner.program_config(small("gmr"))
    mesh = sharding.seed_mesh(1)
    k_init, it_keys = runner.seed_keys(cfg, [0])
    state = runner._program("init", mesh)(cfg, k_init)
    carry = {"state": state, "key": it_keys[:, 0]}
    first = jnp.asarray(True)
    carry.update(sharding.seed_program(mdgps.part_program(("rollouts",)), mesh, (True, False))(cfg, carry, first))
    return cfg, carry, first


def _equal(a, b):
    la, ta = jax.tree_util.tree_flatten(a)
    lb, tb = jax.tree_util.tree_flatten(b)
    assert ta == tb
    for x, y in zip(la, lb):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


def test_a_stored_program_is_lowered_without_tracing_and_computes_the_same(model_inputs, tmp_path, monkeypatch):
    cfg, carry, first = model_inputs
    traced = _program()(cfg, carry, first)
    stored = program_store.ProgramStore(tmp_path).lower("model", _program(), cfg, (carry, first), "cpu")
    assert len(list(tmp_path.glob("*.exported"))) == 1
    _equal(stored.compile()(carry, first), traced)  # on the CPU also bit for bit
    # A later process: a fresh store on the same folder and no jitted program in memory. The
    # part's Python must not run again.
    jax.clear_caches()
    monkeypatch.setitem(mdgps.ITERATION_PARTS, "model", lambda *a: pytest.fail("traced again"))
    again = program_store.ProgramStore(tmp_path).lower("model", _program(), cfg, (carry, first), "cpu")
    _equal(again.compile()(carry, first), traced)
    shapes = jax.tree_util.tree_map(lambda a: jax.ShapeDtypeStruct(a.shape, a.dtype), traced)
    assert jax.tree_util.tree_structure(again.out_info) == jax.tree_util.tree_structure(shapes)
    with pytest.raises(ValueError, match="stored program called with arguments"):
        again.compile()(carry)


def test_every_input_of_the_trace_is_in_the_key(model_inputs):
    cfg, carry, first = model_inputs
    base = program_store.program_key("model", cfg, (carry, first), "cpu")
    assert program_store.program_key("model", cfg, (carry, first), "cpu") == base
    assert program_store.program_key("cstep", cfg, (carry, first), "cpu") != base
    assert program_store.program_key("model", cfg, (carry, first), "gpu") != base
    other = runner.program_config(small("gmr", dynamics__em_iterations=11))
    assert program_store.program_key("model", other, (carry, first), "cpu") != base
    shorter = {**carry, "key": carry["key"].astype(jnp.int32)}
    assert program_store.program_key("model", cfg, (shorter, first), "cpu") != base
    with jax.enable_x64(False):  # a setting of TRACE_SETTINGS
        assert program_store.program_key("model", cfg, (carry, first), "cpu") != base
    assert len(program_store.code_version()) == 64


def test_programs_that_cannot_be_stored_or_read_are_traced(model_inputs, tmp_path, monkeypatch):
    cfg, carry, first = model_inputs
    store = program_store.ProgramStore(tmp_path)
    # a host callback: jax.export cannot serialize it; the marker spares the next attempt
    rollouts = sharding.seed_program(mdgps.part_program(("rollouts",)), sharding.seed_mesh(1), (True, False))
    state_only = {"state": carry["state"], "key": carry["key"]}
    assert store.lower("rollouts", rollouts, cfg, (state_only, first), "cpu") is None
    (marker,) = tmp_path.glob("*.none")
    assert "host_callbacks" in marker.read_text()
    monkeypatch.setattr(jax.export, "export", lambda *a, **k: pytest.fail("exported again"))
    assert store.lower("rollouts", rollouts, cfg, (state_only, first), "cpu") is None
    monkeypatch.undo()
    # a damaged file: traced and written again
    store.lower("model", _program(), cfg, (carry, first), "cpu")
    (path,) = tmp_path.glob("*.exported")
    path.write_bytes(path.read_bytes()[:100])
    again = program_store.ProgramStore(tmp_path).lower("model", _program(), cfg, (carry, first), "cpu")
    _equal(again.compile()(carry, first), _program()(cfg, carry, first))
    assert path.stat().st_size > 100 and not list(tmp_path.glob("*.tmp"))


def test_a_run_from_the_store_equals_the_traced_run(tmp_path):
    """The runner with a store: the first run stores its programs (those without host
    callbacks), a second run lowers them all from the store; both equal the run without one."""
    cfg = small("gmr", iterations=2)
    results = {}
    for name, store in (("traced", None), ("storing", tmp_path / "store"), ("stored", tmp_path / "store")):
        jax.clear_caches()
        with runner.Scheduler(compile_jobs=1, devices=1, iteration_programs="parts",
                              program_store=None if store is None else program_store.ProgramStore(store)) as s:
            results[name] = runner.run(cfg, [0], tmp_path / name, scheduler=s, stability=False)
        if name == "storing":  # init, model, catch-up, C-step, S-step; rollouts and evaluation have callbacks
            assert len(list(store.glob("*.exported"))) == 5 and not list(store.glob("*.none"))
    for name in ("storing", "stored"):
        for metric, value in results["traced"]["history"].items():
            np.testing.assert_array_equal(results[name]["history"][metric], value, err_msg=f"{name} {metric}")
        np.testing.assert_array_equal(results[name]["robustness"]["X"], results["traced"]["robustness"]["X"])

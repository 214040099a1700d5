"""The program store (gmr_jax.program_store): a stored program is lowered without tracing and
computes what the traced program computes; every input of the trace is part of its key; what
cannot be stored or read is traced as before."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gmr_jax import mdgps, program_store, runner, sharding
from test_mdgps import small
from tolerances import SAFETY, assert_trees_within, measured_tol, scale_tol


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
    assert_trees_within(a, b, 0.0)  # bit for bit, NaN and inf at the same places


def test_a_stored_program_is_lowered_without_tracing_and_computes_the_same(model_inputs, tmp_path, monkeypatch):
    cfg, carry, first = model_inputs
    # The stored module is the traced program's; XLA compiles it inside another module, so the
    # two agree to round-off (a tolerance measured from ε-perturbed inputs, tests/tolerances.py).
    traced, tol = measured_tol(lambda c: _program()(cfg, c, first), (carry,), SAFETY)
    stored = program_store.ProgramStore(tmp_path).lower("model", _program(), cfg, (carry, first), "cpu")
    assert len(list(tmp_path.glob("*.exported"))) == 1
    first_out = stored.compile()(carry, first)
    assert_trees_within(first_out, traced, tol)
    # It takes only the leaves that the traced program reads (JAX drops the others from both), so
    # that a call neither copies nor waits for the rest of the carry.
    reads = stored.compile().reads
    assert reads == runner._reads(_program().trace(cfg, carry, first).lower().compile()) and not all(reads)
    # A later process: a fresh store on the same folder and no jitted program in memory. The
    # part's Python must not run again, and the same module computes the same values.
    jax.clear_caches()
    monkeypatch.setitem(mdgps.ITERATION_PARTS, "model", lambda *a: pytest.fail("traced again"))
    again = program_store.ProgramStore(tmp_path).lower("model", _program(), cfg, (carry, first), "cpu")
    _equal(again.compile()(carry, first), first_out)
    shapes = jax.tree_util.tree_map(lambda a: jax.ShapeDtypeStruct(a.shape, a.dtype), traced)
    assert jax.tree_util.tree_structure(again.out_info) == jax.tree_util.tree_structure(shapes)
    with pytest.raises(ValueError, match="stored program called with arguments"):
        again.compile()(carry)


def test_the_key_changes_with_each_input_of_the_trace(model_inputs, monkeypatch):
    cfg, carry, first = model_inputs
    base = program_store.program_key("model", cfg, (carry, first), "cpu")
    assert program_store.program_key("model", cfg, (carry, first), "cpu") == base
    assert program_store.program_key("cstep", cfg, (carry, first), "cpu") != base
    monkeypatch.setattr(jax.export, "default_export_platform", lambda: "cuda")  # a GPU host's
    assert program_store.program_key("model", cfg, (carry, first), "gpu") != base
    monkeypatch.undo()
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
    first_out = store.lower("model", _program(), cfg, (carry, first), "cpu").compile()(carry, first)
    (path,) = tmp_path.glob("*.exported")
    path.write_bytes(path.read_bytes()[:100])
    again = program_store.ProgramStore(tmp_path).lower("model", _program(), cfg, (carry, first), "cpu")
    _equal(again.compile()(carry, first), first_out)
    assert path.stat().st_size > 100 and not list(tmp_path.glob("*.tmp"))


def test_a_store_that_cannot_be_written_warns_and_serves_the_program(model_inputs, tmp_path):
    cfg, carry, first = model_inputs
    blocker = tmp_path / "a_file"
    blocker.write_text("")
    store = program_store.ProgramStore(blocker / "store")  # below a file: mkdir fails
    with pytest.warns(UserWarning, match="cannot write"):
        stored = store.lower("model", _program(), cfg, (carry, first), "cpu")
    out = stored.compile()(carry, first)
    assert jax.tree_util.tree_structure(out) == jax.tree_util.tree_structure(_program()(cfg, carry, first))


def test_a_run_from_the_store_equals_the_traced_run(tmp_path):
    """The runner with a store: the first run stores its programs (those without host
    callbacks), a second run lowers them all from the store and equals it bit for bit (the same
    modules); both equal the run without a store to round-off (within 1e-6 of each array's scale,
    as in test_runner.py's runs in parts; on the CPU they are identical)."""
    cfg = small("gmr", iterations=2)
    results = {}
    for name, store in (("traced", None), ("storing", tmp_path / "store"), ("stored", tmp_path / "store")):
        jax.clear_caches()
        with runner.Scheduler(compile_jobs=1, devices=1, iteration_programs="parts",
                              program_store=None if store is None else program_store.ProgramStore(store)) as s:
            results[name] = runner.run(cfg, [0], tmp_path / name, scheduler=s, stability=False)
        if name == "storing":  # init, model, catch-up, C-step, S-step; rollouts and evaluation have callbacks
            assert len(list(store.glob("*.exported"))) == 5 and not list(store.glob("*.none"))
    for metric, value in results["storing"]["history"].items():
        np.testing.assert_array_equal(results["stored"]["history"][metric], value, err_msg=metric)
    np.testing.assert_array_equal(results["stored"]["robustness"]["X"], results["storing"]["robustness"]["X"])
    ref = results["traced"]["history"]
    assert_trees_within(results["storing"]["history"], ref, scale_tol(ref))

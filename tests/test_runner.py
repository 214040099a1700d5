"""The library's resumable training loop (gmr_jax.runner): an interrupted, resumed and extended
run equals an uninterrupted one, progress reaches the callback, other settings are refused."""

import concurrent.futures
import dataclasses
import json
import shutil
import sys
import threading
import time

import jax
import numpy as np
import pytest

from gmr_jax import checkpoint, runner, sharding
from test_mdgps import small

SEEDS = [0, 1]


@pytest.fixture(scope="module")
def whole(tmp_path_factory, scheduler):
    """An uninterrupted 3-iteration MDGPS run of two seeds, with its progress events."""
    cfg = small("mdgps", iterations=3)
    root = tmp_path_factory.mktemp("runs")
    events = []
    result = runner.run(cfg, SEEDS, root / "whole", progress_fn=events.append, scheduler=scheduler,
                        label="w")
    return cfg, root, result, events


def _final_state(cfg, path):
    return checkpoint.restore(path / "checkpoints", runner.initial_state(cfg, SEEDS))[0]


def test_progress_reaches_the_callback_after_every_iteration(whole):
    cfg, root, result, events = whole
    its = [e for e in events if "iteration" in e]
    assert [e["iteration"] for e in its] == [1, 2, 3]
    assert all(e["run"] == "w" and e["iterations"] == 3 for e in its)
    for i, e in enumerate(its):  # the callback's metrics are the history's rows
        np.testing.assert_array_equal(e["metrics"]["sample_cost"], result["history"]["sample_cost"][i])
    assert result["history"]["sample_cost"].shape == (3, 2, 1)  # [iteration, seed, condition]
    assert result["robustness"]["success"].shape == (2, 50)
    assert (root / "whole" / "config.json").is_file()


def test_finished_run_keeps_its_policy_rollouts_for_pictures(whole):
    """The kept rollouts are the robustness program's own (the random states' exactly, the
    training states' starting at those states), and ``experiments.video`` takes them instead of
    executing the policy again (which agrees up to the rounding of another batch)."""
    from experiments import video
    from tolerances import SAFETY, assert_tolerances_small, assert_trees_within, measured_tol

    from gmr_jax import evaluate, policies, tasks

    cfg, root, result, _ = whole
    with np.load(root / "whole" / runner.ROLLOUTS_FILE) as f:
        kept = {k: f[k] for k in f.files}
    np.testing.assert_array_equal(kept["seeds"], SEEDS)
    np.testing.assert_array_equal(kept["random"], result["robustness"]["X"][:, :runner.PICTURE_RANDOM_STATES])
    assert kept["training"].shape == (2, 1, cfg.task.T, 12)
    np.testing.assert_array_equal(kept["training"][:, :, 0], np.broadcast_to(tasks.initial_states(cfg.task), (2, 1, 12)))
    got_cfg, seed, rows = video.rollouts(root / "whole", seed_index=1, random_states=2)
    assert got_cfg == cfg and seed == 1 and [label for label, _ in rows] == ["from A", "random state 0", "random state 1"]
    params = jax.tree_util.tree_map(lambda a: a[1], _final_state(cfg, root / "whole").policy.params)
    x0 = np.concatenate([tasks.initial_states(cfg.task), evaluate.robustness_states(cfg)[:2]])
    again = jax.jit(lambda p, x: evaluate.execute(cfg, policies.mean_fn(policies.for_config(cfg), p), x).X)
    ref, tol = measured_tol(again, (params, x0), SAFETY)
    assert_tolerances_small(ref, tol, 1e-8)
    assert_trees_within(np.stack([X for _, X in rows]), ref, tol)


def test_interrupted_resumed_and_extended_run_equals_an_uninterrupted_one(whole, scheduler):
    """Stopped after 1 of 2 iterations, resumed to 2, then extended to 3: the same programs on
    the same device from bit-identical checkpoints, so the result is bit-identical too."""
    cfg, root, result, _ = whole
    short = dataclasses.replace(cfg, iterations=2)
    part = root / "part"
    runner.run(short, SEEDS, part, stop_after=1, scheduler=scheduler)
    assert checkpoint.latest(part / "checkpoints") == 1
    events = []
    done = runner.run(short, SEEDS, part, resume=True, scheduler=scheduler, progress_fn=events.append)
    assert events[0]["message"] == "resumed from iteration 1"
    assert checkpoint.latest(part / "checkpoints") == 2 and "robustness" in done
    extended = runner.run(cfg, SEEDS, part, resume=True, scheduler=scheduler)
    assert checkpoint.latest(part / "checkpoints") == 3
    for name, value in result["history"].items():
        np.testing.assert_array_equal(extended["history"][name], value, err_msg=name)
        assert extended["history"][name].dtype == value.dtype, name
    jax.tree_util.tree_map(np.testing.assert_array_equal, _final_state(cfg, part), _final_state(cfg, root / "whole"))
    np.testing.assert_array_equal(extended["robustness"]["mse"], result["robustness"]["mse"])


def test_a_run_with_its_iteration_in_parts_equals_the_whole_program_run(whole, tmp_path):
    """``iteration_programs="parts"``: each group of ``runner.ITERATION_PARTS`` compiled as a
    program of its own (the groups in parallel threads), called in turn by the training loop.
    The parts equal the whole iteration to round-off (tested against measured tolerances in
    ``test_mdgps.py``); here, the whole runner: every metric within 1e-6 of its array's scale (on
    the CPU the two differ by about 1e-15 relative, and ε-perturbed inputs move one iteration's
    outputs by at most 5e-9 of their scale, test_mdgps.py), integer and boolean metrics equal."""
    from tolerances import assert_trees_within, scale_tol

    cfg, root, result, _ = whole
    with runner.Scheduler(compile_jobs=1, devices=1, iteration_programs="parts") as own:
        parts = runner.run(cfg, SEEDS, tmp_path / "parts", scheduler=own, stability=False)
        (step,) = [p for name, p in own.programs.items() if name[0] == "step"]
    assert isinstance(step, runner._PartsStep) and len(step.programs) == len(runner.ITERATION_PARTS)
    assert parts["timing"]["compile_s"] > 0 and parts["timing"]["trace_s"] > 0
    assert_trees_within(parts["history"], result["history"], scale_tol(result["history"]))
    final = _final_state(cfg, root / "whole")
    assert_trees_within(_final_state(cfg, tmp_path / "parts"), final, scale_tol(final))
    assert_trees_within(parts["robustness"], result["robustness"], scale_tol(result["robustness"]))


def test_seed_keys_are_each_seeds_own_derivation_on_the_host():
    """``seed_keys`` (one program on the host CPU) gives, bit for bit, what each seed's key gives
    through ``mdgps.iteration_keys`` one operation at a time, as host arrays; the iteration keys
    of a shorter run are the first ones of a longer run's."""
    from gmr_jax import mdgps

    cfg = small("mdgps", iterations=3)
    seeds = [0, 7, 2**31 - 1]
    k_init, it_keys = runner.seed_keys(cfg, seeds)
    assert isinstance(k_init, np.ndarray) and isinstance(it_keys, np.ndarray)
    assert k_init.shape == (3, 2) and it_keys.shape == (3, cfg.iterations, 2)
    for i, seed in enumerate(seeds):
        want_init, want_keys = mdgps.iteration_keys(jax.random.PRNGKey(seed), cfg.iterations)
        np.testing.assert_array_equal(k_init[i], np.asarray(want_init))
        np.testing.assert_array_equal(it_keys[i], np.asarray(want_keys))
    longer = runner.seed_keys(dataclasses.replace(cfg, iterations=5), seeds)[1]
    np.testing.assert_array_equal(longer[:, :3], it_keys)


def test_gc_paused_nests_across_threads_and_restores_the_collector():
    """``runner.gc_paused``: the collector is off inside, stays off until the last of nested or
    concurrent blocks (threads) ends, also after an exception, and comes back only if it was on."""
    import gc

    deadline = time.monotonic() + 30  # a background trace of an earlier test may still hold a pause
    while not gc.isenabled() and time.monotonic() < deadline:
        time.sleep(0.05)
    assert gc.isenabled()
    entered, leave = threading.Event(), threading.Event()

    def other():
        with runner.gc_paused():
            entered.set()
            leave.wait(10)
    thread = threading.Thread(target=other)
    with runner.gc_paused():
        assert not gc.isenabled()
        thread.start()
        assert entered.wait(10)
        with pytest.raises(ZeroDivisionError), runner.gc_paused():
            1 / 0
        assert not gc.isenabled()
    assert not gc.isenabled()  # the other thread's block is still open
    leave.set()
    thread.join(10)
    assert gc.isenabled()
    gc.disable()
    try:
        with runner.gc_paused():
            pass
        assert not gc.isenabled()  # off before: left off
    finally:
        gc.enable()


def test_a_split_run_copies_its_parts_between_two_devices(whole, tmp_path, monkeypatch):
    """``iteration_programs="split"``: the groups of ``runner.SPLIT_PARTS`` in ``runner.HOST_PARTS``
    compiled for the host's CPU, the others for the run's device. Here a second CPU device stands
    in for the host beside the run's device (split itself applies to runs on a GPU), so the carry
    is copied between two devices: a run of one seed equals that seed of the whole-program run of
    two seeds to round-off (the tolerance of the parts test above). The new state's entries lie
    where their parts computed them (the controllers on the host's device, the policy on the
    run's); the rollouts read only the controllers and the key of the state, so the next
    iteration's rollouts, called as soon as the C-step has finished, give the samples that the
    next call would compute; the learning curve is computed on the host's device, from a worker
    thread (the metrics are a future)."""
    from tolerances import assert_trees_within, scale_tol

    if len(jax.devices()) < 2:
        pytest.skip("needs two devices (XLA_FLAGS=--xla_force_host_platform_device_count=2)")
    cfg, root, result, _ = whole
    run_device, host_device = jax.devices()[:2]
    host = jax.make_mesh((1,), (sharding.AXIS,), axis_types=(jax.sharding.AxisType.Auto,),
                         devices=[host_device])
    monkeypatch.setattr(runner, "iteration_programs_for", lambda *args: "split")
    with runner.Scheduler(compile_jobs=1, devices=1, iteration_programs="split") as own:
        monkeypatch.setattr(own, "host_mesh", lambda: host)
        split = runner.run(cfg, SEEDS[:1], tmp_path / "split", scheduler=own)
        (step,) = [p for name, p in own.programs.items() if name[0] == "step"]
        state0, all_keys = runner.initial_state(cfg, SEEDS[:1]), runner.seed_keys(cfg, SEEDS[:1])[1]
        keys, next_keys = all_keys[:, 0], all_keys[:, 1]
        prefetched: dict = {}
        state, metrics = step(state0, keys, jax.numpy.asarray(True), next_keys=next_keys, prefetched=prefetched)
        assert isinstance(metrics, concurrent.futures.Future)
        metrics = metrics.result()
        # The next iteration's rollouts were called as soon as the C-step had computed the
        # controllers; the next call takes their samples and computes what it computes without.
        assert prefetched["traj"] is state.traj and prefetched["keys"] is next_keys
        ahead = step(state, next_keys, jax.numpy.asarray(False), prefetched=prefetched)
        assert not prefetched
        direct = step(state, next_keys, jax.numpy.asarray(False))
        assert_trees_within((ahead[0], ahead[1].result()), (direct[0], direct[1].result()), 0.0)
    assert step.devices == tuple(host_device if names in runner.HOST_PARTS else run_device
                                 for names in runner.SPLIT_PARTS)
    devices = lambda tree: {d for leaf in jax.tree_util.tree_leaves(tree) for d in leaf.devices()}  # noqa: E731
    assert devices((state.traj, state.eta, state.prev)) == {host_device}  # the C-step's
    assert devices((state.policy, state.dyn_prior)) == {run_device}  # the S-step's, the dynamics fit's
    assert devices(metrics["final_state_mse_policy"]) == {host_device}  # the learning curve's
    assert devices(metrics["sstep_loss"]) == {run_device}
    paths = [jax.tree_util.keystr(path) for path, _ in
             jax.tree_util.tree_flatten_with_path(({"state": state0, "key": keys}, True))[0]]
    rollouts_read = {path for path, read in zip(paths, step.reads[0], strict=True) if read}
    assert rollouts_read and all(p.startswith(("[0]['state'].traj.", "[0]['key']")) for p in rollouts_read)
    first = jax.tree_util.tree_map(lambda a: a[:, :1], result["history"])
    assert_trees_within(split["history"], first, scale_tol(first))
    robust = jax.tree_util.tree_map(lambda a: a[:1], result["robustness"])
    assert_trees_within(split["robustness"], robust, scale_tol(robust))
    stable = jax.tree_util.tree_map(lambda a: a[:1], result["stability"])
    assert_trees_within(split["stability"], stable, scale_tol(stable))


def test_iteration_programs_resolve_per_run_and_platform():
    gmr, lqr = small("gmr"), small("lqr")
    assert gmr.sim.backend == "mujoco"
    assert runner.iteration_programs_for("auto", gmr, "gpu") == "split"  # one seed on one device
    assert runner.iteration_programs_for("auto", gmr, "gpu", 2) == "parts"
    assert runner.iteration_programs_for("auto", gmr, "gpu", 1, 2) == "parts"
    mjx = dataclasses.replace(gmr, sim=dataclasses.replace(gmr.sim, backend="mjx"))
    assert runner.iteration_programs_for("auto", mjx, "gpu") == "parts"  # MJX's rollouts stay on the GPU
    assert runner.iteration_programs_for("split", gmr, "gpu") == "split"
    assert runner.iteration_programs_for("split", gmr, "cpu") == "parts"  # nothing to move elsewhere
    assert runner.iteration_programs_for("split", gmr, "gpu", 4) == "parts"
    assert runner.iteration_programs_for("split", mjx, "gpu") == "parts"
    with runner.Scheduler(devices=1) as s:  # one seed: one host device, however many the host has
        assert len(jax.devices("cpu")) > 1 and s.host_mesh().devices.tolist() == [jax.devices("cpu")[0]]
    assert runner.iteration_programs_for("auto", gmr, "cpu") == "whole"
    assert runner.iteration_programs_for("auto", lqr, "gpu") == "whole"  # no policy: no S-steps to split
    assert runner.iteration_programs_for("parts", gmr, "cpu") == "parts"
    assert runner.iteration_programs_for("whole", gmr, "gpu") == "whole"
    with pytest.raises(ValueError, match="iteration_programs: 'some' is not one of auto, whole, parts, split"):
        runner.Scheduler(iteration_programs="some")


class _RecordedStep:
    """An asynchronous step (as a split run's) of recorded calls: state {"x": [S]} → x + 1, metrics
    a future whose reading is recorded, "ok" False for the (iteration, seed) pairs in ``bad``."""

    asynchronous = True

    def __init__(self, seeds: int, bad=()):
        self.seeds, self.bad, self.events, self.inputs = seeds, set(bad), [], []

    def __call__(self, state, keys, first, next_keys=None, prefetched=None):
        i = len(self.inputs)
        self.inputs.append(np.asarray(state["x"]).tolist())
        self.events.append(("call", i, bool(first), next_keys is not None))
        ok = np.array([[(i, s) not in self.bad] * 2 for s in range(self.seeds)])
        events = self.events

        class Metrics(concurrent.futures.Future):
            def result(self, timeout=None):
                events.append(("read", i))
                return super().result(timeout)

        metrics = Metrics()
        metrics.set_result({"ok": ok, "cost": np.full((self.seeds, 2), float(i))})
        return {"x": np.asarray(state["x"]) + 1}, metrics


def _recorded_loop(step, scheduler, path, iterations, progress_fn=None, checkpoint_every=1, last_write=None):
    """``runner._train_loop`` over a recorded step; (state, history, iteration_s) once the last
    checkpoint is written (its future is appended to ``last_write`` where that is a list)."""
    cfg = small("mdgps", iterations=iterations)
    state, history, iteration_s, write = runner._train_loop(
        cfg, step, {"x": np.zeros(step.seeds, int)}, [], np.zeros((step.seeds, iterations, 2), np.uint32),
        iterations, path, {"seeds": list(range(step.seeds))}, runner._Layout(scheduler.mesh_for(None), step.seeds),
        runner.Timer(), scheduler, progress_fn, "", time.perf_counter(), checkpoint_every)
    if last_write is not None:
        last_write.append(write)
    elif write is not None:
        write.result()
    return state, history, iteration_s


def test_the_loop_calls_each_iteration_before_it_reads_the_one_before(tmp_path, scheduler):
    """``runner._train_loop`` with an asynchronous step calls iteration i + 1 (with iteration i's
    new state and the keys of iteration i + 2) before it reads iteration i's metrics, and never
    calls beyond the last iteration: the devices get the next iteration's programs while the host
    waits, writes checkpoints and reports."""
    step = _RecordedStep(1)
    state, history, iteration_s = _recorded_loop(step, scheduler, tmp_path / "ckpt", 3)
    assert step.events == [("call", 0, True, True), ("call", 1, False, True), ("read", 0),
                           ("call", 2, False, False), ("read", 1), ("read", 2)]
    assert step.inputs == [[0], [1], [2]] and int(state["x"][0]) == 3
    assert [float(h["cost"][0, 0]) for h in history] == [0, 1, 2]
    assert len(iteration_s) == 3 and checkpoint.all_steps(tmp_path / "ckpt") == [1, 2, 3]


def test_a_seed_that_fails_while_the_next_iteration_runs_is_frozen_from_then_on(tmp_path, scheduler):
    """Seed 1 fails in iteration 2, which is read after iteration 3 was called from its failed
    state: iteration 3's part of seed 1 is replaced by its kept state and metrics, and iteration 4
    is called with that kept state; seed 0 goes on as it would alone."""
    step, messages = _RecordedStep(2, bad=[(1, 1)]), []
    state, history, _ = _recorded_loop(step, scheduler, tmp_path / "ckpt", 4,
                                       lambda e: messages.append(e.get("message")))
    assert step.inputs == [[0, 0], [1, 1], [2, 2], [3, 1]]
    assert np.asarray(state["x"]).tolist() == [4, 1]
    assert [h["seed_failed"].tolist() for h in history] == [[False, False], [False, True], [False, True],
                                                            [False, True]]
    assert [h["cost"][:, 0].tolist() for h in history] == [[0, 0], [1, 0], [2, 0], [3, 0]]
    assert any(m and "seed 1 failed in iteration 2" in m for m in messages)


def test_a_stop_finishes_the_iteration_under_way(tmp_path):
    """A stop requested at iteration 1's report: iteration 2, already called, is finished, reported
    and checkpointed, and nothing more is called."""
    step = _RecordedStep(1)
    with runner.Scheduler(compile_jobs=1, devices=1) as own:
        stop_at_first = lambda e: own.request_stop() if e.get("iteration") == 1 else None  # noqa: E731
        with pytest.raises(runner.Interrupted, match="stopped after iteration 2 of 4"):
            _recorded_loop(step, own, tmp_path / "ckpt", 4, stop_at_first)
    assert len(step.inputs) == 2 and checkpoint.all_steps(tmp_path / "ckpt") == [1, 2]


def test_checkpoints_of_every_nth_iteration_the_last_and_a_stops(tmp_path, scheduler):
    """checkpoint_every = 2 over 5 iterations: checkpoints 2, 4 and 5 (the last), each holding its
    own iteration's state; a stop at iteration 3's report (iteration 4 already called) writes
    iteration 4's (a scheduled one); a stop at iteration 2's writes iteration 3's, which no
    schedule names; a value that is not a positive integer is refused in one line."""
    state, history, _ = _recorded_loop(_RecordedStep(1), scheduler, tmp_path / "a", 5, checkpoint_every=2)
    assert checkpoint.all_steps(tmp_path / "a") == [2, 4, 5]
    template = {"x": np.zeros(1, int)}
    for step in (2, 4, 5):
        restored, meta = checkpoint.restore(tmp_path / "a", template, step=step)
        assert np.asarray(restored["x"]).tolist() == [step]
    for stop_at, written in ((3, [2, 4]), (2, [2, 3])):
        with runner.Scheduler(compile_jobs=1, devices=1) as own:
            stop = lambda e, own=own, at=stop_at: own.request_stop() if e.get("iteration") == at else None  # noqa: E731
            with pytest.raises(runner.Interrupted, match=f"stopped after iteration {stop_at + 1} of 6"):
                _recorded_loop(_RecordedStep(1), own, tmp_path / f"stop{stop_at}", 6, stop, checkpoint_every=2)
        assert checkpoint.all_steps(tmp_path / f"stop{stop_at}") == written
    for bad in (0, -1, 1.5, True, "2", np.int64(0)):
        with pytest.raises(ValueError, match=r"^checkpoint_every: .* is not a positive integer"):
            runner.check_checkpoint_every(bad)
    runner.check_checkpoint_every(np.int64(3))
    with pytest.raises(ValueError, match="checkpoint_every: 0"):
        runner.run_all({}, [0], tmp_path / "none", checkpoint_every=0)


def _disk_full_at_checkpoint_2(monkeypatch):
    real = checkpoint.save

    def full_at_2(path, state, step, metadata=None):
        if step == 2:
            raise checkpoint.CheckpointError("checkpoint step 2: No space left on device")
        return real(path, state, step, metadata)

    monkeypatch.setattr(checkpoint, "save", full_at_2)


def test_a_failed_checkpoint_write_beside_the_loop_stops_it(tmp_path, scheduler, monkeypatch):
    """The write of checkpoint 2 fails in its thread while the loop goes on: the next write raises
    its error, and no later checkpoint is written."""
    _disk_full_at_checkpoint_2(monkeypatch)
    with pytest.raises(checkpoint.CheckpointError, match="step 2"):
        _recorded_loop(_RecordedStep(1), scheduler, tmp_path / "ckpt", 4)
    assert checkpoint.all_steps(tmp_path / "ckpt") == [1]


def test_a_failed_write_during_a_failure_becomes_its_note(tmp_path, scheduler, monkeypatch):
    """Checkpoint 2's write fails in its thread while iteration 3 fails: the TrainingError is
    raised (the user's one line names the iteration) and the write's error is its note."""
    _disk_full_at_checkpoint_2(monkeypatch)
    with pytest.raises(runner.TrainingError, match="iteration 3") as info:
        _recorded_loop(_RecordedStep(1, bad=[(2, 0)]), scheduler, tmp_path / "ckpt", 5)
    assert any("writing a checkpoint failed" in note and "step 2" in note for note in info.value.__notes__)
    assert checkpoint.all_steps(tmp_path / "ckpt") == [1]


def test_checkpoints_of_every_nth_iteration_after_a_failure_or_a_failed_write(tmp_path, scheduler, monkeypatch):
    """checkpoint_every = 2: every seed fails in iteration 4, so iteration 3's checkpoint, which no
    schedule names, is written as the last good one beside 2; where checkpoint 2's write fails,
    the next scheduled write (4) raises its error and neither 3 nor 4 is written."""
    with pytest.raises(runner.TrainingError, match="iteration 4"):
        _recorded_loop(_RecordedStep(1, bad=[(3, 0)]), scheduler, tmp_path / "fail", 6, checkpoint_every=2)
    assert checkpoint.all_steps(tmp_path / "fail") == [2, 3]
    _disk_full_at_checkpoint_2(monkeypatch)
    with pytest.raises(checkpoint.CheckpointError, match="step 2"):
        _recorded_loop(_RecordedStep(1), scheduler, tmp_path / "full", 6, checkpoint_every=2)
    assert checkpoint.all_steps(tmp_path / "full") == []


def test_the_last_checkpoint_is_written_beside_the_callers_next_work(tmp_path, scheduler, monkeypatch):
    """After the last iteration the loop returns while its checkpoint is written: the write's
    future, waited for by ``runner._written_after`` when the caller's block (the policies'
    evaluation) ends, which raises the write's error, or adds it as a note to the block's own.
    A stop or an error writes before the loop returns (the tests above)."""
    real, release = checkpoint.save, threading.Event()

    def held_at_3(path, state, step, metadata=None):
        if step == 3:
            assert release.wait(60)
        return real(path, state, step, metadata)

    monkeypatch.setattr(checkpoint, "save", held_at_3)
    writes = []
    _recorded_loop(_RecordedStep(1), scheduler, tmp_path / "a", 3, last_write=writes)
    (write,) = writes
    assert not write.done() and checkpoint.all_steps(tmp_path / "a") == [1, 2]
    with runner._written_after(write):
        release.set()
    assert write.done() and checkpoint.all_steps(tmp_path / "a") == [1, 2, 3]
    with runner._written_after(None):
        pass

    def full_at_3(path, state, step, metadata=None):
        if step == 3:
            raise checkpoint.CheckpointError("checkpoint step 3: No space left on device")
        return real(path, state, step, metadata)

    monkeypatch.setattr(checkpoint, "save", full_at_3)
    for root, block_error in (("b", None), ("c", RuntimeError("evaluation failed"))):
        writes = []
        _recorded_loop(_RecordedStep(1), scheduler, tmp_path / root, 3, last_write=writes)
        with pytest.raises(type(block_error) if block_error else checkpoint.CheckpointError) as info:
            with runner._written_after(writes[0]):
                if block_error:
                    raise block_error
        if block_error:
            assert any("writing a checkpoint failed" in note and "step 3" in note for note in info.value.__notes__)
        assert checkpoint.all_steps(tmp_path / root) == [1, 2]


def test_a_failure_with_the_next_iteration_under_way_keeps_the_checkpoints_before(tmp_path, scheduler):
    """Every seed fails in iteration 3 while iteration 4 runs: TrainingError names iteration 3,
    checkpoints 1 and 2 are written, and iteration 4 was waited for."""
    step = _RecordedStep(1, bad=[(2, 0)])
    with pytest.raises(runner.TrainingError, match=r"iteration 3: .* iterations ≤ 2"):
        _recorded_loop(step, scheduler, tmp_path / "ckpt", 5)
    assert len(step.inputs) == 4 and checkpoint.all_steps(tmp_path / "ckpt") == [1, 2]


def test_history_keeps_its_dtypes_through_a_checkpoint():
    """A checkpoint stores the metrics as JSON numbers; restored, they have their own dtypes
    again, so that a resumed float32 run's means (float32 sums) are the uninterrupted run's."""
    rng = np.random.default_rng(0)
    history = [{"sample_cost": rng.normal(size=(2, 3)).astype(np.float32) * 100,
                "kl": np.array([np.inf, 1.5], np.float32), "iters": np.array([3, 4], np.int32),
                "seed_failed": np.array([False, True])} for _ in range(2)]
    saved = json.loads(json.dumps(runner.history_metadata(history)))
    restored = runner.history_from_metadata(saved)
    for got, want in zip(restored, history):
        for name, value in want.items():
            assert got[name].dtype == value.dtype, name
            # non-finite floats are stored as NaN (runner.jsonable)
            np.testing.assert_array_equal(got[name], np.where(np.isfinite(value), value, np.nan)
                                          if value.dtype.kind == "f" else value, err_msg=name)
    # the mean over conditions, as the report takes it, is the same to the last bit
    assert np.mean(restored[0]["sample_cost"], axis=-1).tobytes() == np.mean(history[0]["sample_cost"],
                                                                                 axis=-1).tobytes()
    # a checkpoint written before the dtypes were kept restores with numpy's defaults
    del saved["history_dtypes"]
    assert runner.history_from_metadata(saved)[0]["sample_cost"].dtype == np.float64


def test_a_checkpoint_from_before_a_configuration_field_existed_resumes(whole, scheduler, tmp_path):
    """A checkpoint written before a configuration field was added (here ``sstep.statistics``,
    removed from its stored configuration) holds that field's default: the run resumes, with
    the same history; a field the checkpoint holds with another value is still refused."""
    cfg, root, result, _ = whole
    shutil.copytree(root / "whole", tmp_path / "old")
    for meta in (tmp_path / "old" / "checkpoints").glob("*/meta/metadata"):
        stored = json.loads(meta.read_text())
        del stored["metadata"]["config"]["sstep"]["statistics"]
        meta.write_text(json.dumps(stored))
    resumed = runner.run(cfg, SEEDS, tmp_path / "old", resume=True, scheduler=scheduler)
    for name, value in result["history"].items():
        np.testing.assert_array_equal(resumed["history"][name], value, err_msg=name)
    with pytest.raises(checkpoint.CheckpointError, match="config.sstep.statistics: checkpoint 'auto', expected 'step'"):
        runner.run(dataclasses.replace(cfg, sstep=dataclasses.replace(cfg.sstep, statistics="step")), SEEDS,
                   tmp_path / "old", resume=True, scheduler=scheduler)


def test_a_failed_run_is_not_reported_as_an_interruption():
    """A study stopped on request whose runs ended in different ways: a run's failure is raised
    (with where every run stands as a note), never taken for an interruption; otherwise one
    Interrupted says where each run stands."""
    def ended(err=None):
        f = concurrent.futures.Future()
        f.set_result(None) if err is None else f.set_exception(err)
        return f

    stopped = runner.Interrupted("stopped after iteration 2 of 10; its checkpoint is in x")
    failed = runner.TrainingError("iteration 3: non-finite values")
    err = runner.stopped_study_error({"A/gmr": ended(stopped), "A/mdgps": ended(failed), "AB/gmr": ended()})
    assert err is failed
    assert err.__notes__ == ["A/gmr stopped after iteration 2 of 10; its checkpoint is in x; A/mdgps failed: "
                             "TrainingError: iteration 3: non-finite values; AB/gmr finished"]
    err = runner.stopped_study_error({"A/gmr": ended(stopped), "AB/gmr": ended()})
    assert isinstance(err, runner.Interrupted)
    assert str(err) == "A/gmr stopped after iteration 2 of 10; its checkpoint is in x; AB/gmr finished"


def test_other_settings_and_fewer_iterations_are_refused(whole, scheduler):
    cfg, root, _, _ = whole
    with pytest.raises(checkpoint.CheckpointError, match="num_samples"):
        runner.run(dataclasses.replace(cfg, num_samples=3), SEEDS, root / "whole", resume=True,
                   scheduler=scheduler)
    with pytest.raises(checkpoint.CheckpointError, match="holds 3 iterations, more than iterations=2"):
        runner.run(dataclasses.replace(cfg, iterations=2), SEEDS, root / "whole", resume=True,
                   scheduler=scheduler)
    with pytest.raises(checkpoint.CheckpointError, match="seeds"):
        runner.run(cfg, [0, 2], root / "whole", resume=True, scheduler=scheduler)
    with pytest.raises(runner.FolderTaken, match="already hold"):
        runner.run(cfg, SEEDS, root / "whole", scheduler=scheduler)


def test_tracing_turns_follow_the_tickets():
    """Runs trace one at a time in ticket order, whatever order their threads arrive in."""
    turns = runner.TracingTurns()
    entered, inside = [], []

    def run(ticket, delay):
        time.sleep(delay)
        with turns(ticket):
            inside.append(ticket)
            assert len(inside) == 1  # nobody else is tracing
            entered.append(ticket)
            time.sleep(0.01)
            inside.remove(ticket)

    threads = [threading.Thread(target=run, args=(t, d)) for t, d in ((2, 0.0), (0, 0.05), (1, 0.0), (3, 0.02))]
    for th in threads:
        th.start()
    for th in threads:
        th.join(timeout=10)
    assert entered == [0, 1, 2, 3]
    # an exception inside a turn still passes the turn on
    turns.reset()
    with pytest.raises(RuntimeError):
        with turns(0):
            raise RuntimeError("trace failed")
    with turns(1):
        pass


def test_scheduler_switch_interval_is_checked():
    """A switch interval that is not a positive number is refused in one line, before any
    thread starts; None leaves Python's."""
    with pytest.raises(ValueError, match="switch_interval=0: must be a positive number"):
        runner.Scheduler(switch_interval=0)
    before = sys.getswitchinterval()
    with runner.switch_interval(None):
        assert sys.getswitchinterval() == before
    with runner.switch_interval(1e-3):
        assert sys.getswitchinterval() == pytest.approx(1e-3)
    assert sys.getswitchinterval() == before


def test_tracing_turns_second_round_and_released_tickets():
    """With ``reset(runs)`` every run's second ticket (``later``) comes after all first ones, and
    a ticket released without a turn (a run that failed before it) holds nobody up. Runs that
    do not all start at once (``reset(0)``) get no second round."""
    turns = runner.TracingTurns()
    turns.reset(2)
    assert (turns.later(0), turns.later(1), turns.later(None)) == (2, 3, None)
    entered = []

    def run(ticket, delay):
        time.sleep(delay)
        with turns(ticket):
            entered.append(ticket)

    threads = [threading.Thread(target=run, args=(t, d)) for t, d in ((3, 0.0), (2, 0.0), (0, 0.03))]
    for th in threads:
        th.start()
    time.sleep(0.1)
    assert entered == [0]  # 2 and 3 wait for ticket 1
    turns.release(1)
    for th in threads:
        th.join(timeout=10)
    assert entered == [0, 2, 3]
    turns.release(1, None)  # idempotent
    turns.release(5)  # a run that failed after queueing work for its later turn
    with turns(5):  # takes a free turn instead of waiting for one that has passed
        pass
    turns.reset(0)
    assert turns.later(0) is None


def test_programs_are_compiled_for_the_mesh_of_their_run(scheduler):
    """A run placed on other devices than the default one (``run``'s ``platform``: the host CPU
    beside a GPU) gets programs compiled for its mesh, also where every argument is given as a
    shape (the evaluation program): here a mesh of the fourth CPU device."""
    if len(jax.local_devices()) < 4:
        pytest.skip("needs four devices (XLA_FLAGS=--xla_force_host_platform_device_count=4)")
    cfg = small("mdgps", task__T=4)
    mesh = jax.make_mesh((1,), ("seeds",), devices=jax.local_devices()[3:4])
    params = jax.vmap(lambda k: runner.mdgps.init(cfg, k).policy.params)(jax.random.PRNGKey(0)[None])
    shapes = jax.tree_util.tree_map(lambda a: jax.ShapeDtypeStruct(a.shape, a.dtype), params)
    timer = runner.Timer()
    lowered = runner._lowered("robustness", cfg, (shapes,), timer, scheduler, mesh)
    program = runner._compiled("robustness", cfg, 1, lowered, timer, scheduler, slot=False, mesh=mesh)
    layout = runner._Layout(mesh, 1)
    out = runner.evaluate_robustness(cfg, layout.device(params), timer, program, layout)
    assert np.isfinite(out["robustness"]["mse"]).all()
    assert {d.id for d in program.input_shardings[0][0].net["params"]["Dense_0"]["bias"].device_set} == {3}

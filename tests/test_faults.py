"""Fault injection: every expected failure of a training run ends in a clear message, keeps what
was written before, and a resumed run continues correctly.

| fault | what must happen | test |
| --- | --- | --- |
| NaN from the plant in the middle of a run | TrainingError naming the iteration; earlier checkpoints intact | test_nan_from_the_plant_stops_the_run |
| NaN from the plant for one seed of several | that seed frozen at its last good iteration and named; the others run on unchanged | test_a_failed_seed_is_frozen_while_the_others_go_on |
| a checkpoint write that fails half-way | CheckpointError; the previous checkpoint intact, resume continues | test_failed_checkpoint_write_keeps_the_previous_one |
| stop request (Ctrl-C, SIGTERM) | the iteration in flight finishes and is checkpointed; resume equals an uninterrupted run | test_stop_request_checkpoints_and_resumes |
| stop request before the first iteration, several runs | no checkpoint; the message says where each run stands | test_a_stopped_study_says_where_each_run_stands |
| the process killed (kill -9) between iterations | resume equals an uninterrupted run | test_runner.py::test_interrupted_resumed_and_extended_run_equals_an_uninterrupted_one |
| a corrupt newest checkpoint | set aside (renamed) and reported; resume from the one before | test_corrupt_newest_checkpoint_falls_back |
| a missing MJCF scene | one line naming the file, exit 1 | test_missing_mjcf_is_one_line |
| a config.json with an unknown field | one line naming the field | test_config_json_with_an_unknown_field |
| Ctrl-C / SIGTERM reach the CLI | the scheduler's stop is requested | test_signals_request_a_stop |
| a run in a process of its own | the same records as here; its progress and errors reach the parent | test_a_run_in_its_own_process_equals_the_run_here |
| a run of several side by side fails before its tracing turn | its turns pass on; the others are not held up, the error is raised | test_side_by_side_runs_take_their_turns_and_a_failed_one_holds_nobody_up |
"""

import dataclasses
import json
import os
import shutil
import signal
import subprocess
import sys
import threading

import jax
import numpy as np
import orbax.checkpoint as ocp
import pytest

from experiments import cli, diagnose, reach
from gmr_jax import checkpoint, process_server, runner, sim, timeline
from test_mdgps import small

SEEDS = [0, 1]


@pytest.fixture(scope="module")
def cfg():
    return small("mdgps", iterations=3)


@pytest.fixture(scope="module")
def whole(cfg, tmp_path_factory, scheduler):
    root = tmp_path_factory.mktemp("faults")
    return root, runner.run(cfg, SEEDS, root / "whole", scheduler=scheduler)


def _same_history(a, b):
    for name, value in b["history"].items():
        np.testing.assert_array_equal(a["history"][name], value, err_msg=name)


def test_nan_from_the_plant_stops_the_run(cfg, whole, scheduler, monkeypatch):
    """The plant returns NaN from the second iteration on (the first iteration runs alone, then the
    run resumes with the faulty plant: the runner calls an iteration before the one before it
    has been reported, so a progress event comes too late to change the next iteration)."""
    root, _ = whole
    clean = sim._HostStepper.rollout

    def nan_plant(self, *args, **kwargs):
        X, U, xT = clean(self, *args, **kwargs)
        return X * np.nan, U, xT * np.nan

    runner.run(cfg, SEEDS, root / "nan", scheduler=scheduler, stop_after=1)
    monkeypatch.setattr(sim._HostStepper, "rollout", nan_plant)
    with pytest.raises(runner.TrainingError, match=r"iteration 2: non-finite .* iterations ≤ 1 .* are intact"):
        runner.run(cfg, SEEDS, root / "nan", scheduler=scheduler, resume=True)
    assert checkpoint.all_steps(root / "nan" / "checkpoints") == [1]
    checkpoint.restore(root / "nan" / "checkpoints", runner.initial_state(cfg, SEEDS))  # intact


def test_a_failed_seed_is_frozen_while_the_others_go_on(cfg, whole, scheduler, monkeypatch):
    root, result = whole
    clean = sim._HostStepper.rollout

    def nan_for_second_seed(self, x0, *args, **kwargs):
        X, U, xT = clean(self, x0, *args, **kwargs)
        if x0.ndim >= 2 and x0.shape[0] == len(SEEDS):  # the seed axis leads (vmap over seeds)
            X, xT = X.copy(), xT.copy()
            X[1], xT[1] = np.nan, np.nan
        return X, U, xT

    messages = []
    runner.run(cfg, SEEDS, root / "one_nan", scheduler=scheduler, stop_after=1)  # as in the test above
    monkeypatch.setattr(sim._HostStepper, "rollout", nan_for_second_seed)
    out = runner.run(cfg, SEEDS, root / "one_nan", scheduler=scheduler, resume=True,
                     progress_fn=lambda event: messages.append(event.get("message")))
    hist, ref = out["history"], result["history"]
    np.testing.assert_array_equal(hist["seed_failed"], [[False, False], [False, True], [False, True]])
    assert any(m and "seed 1 failed in iteration 2" in m for m in messages)
    for name, value in ref.items():
        if name == "seed_failed":
            continue
        # seed 0 as in the run without the fault; seed 1 repeats its iteration-1 metrics
        np.testing.assert_array_equal(hist[name][:, 0], value[:, 0], err_msg=name)
        np.testing.assert_array_equal(hist[name][1:, 1], np.broadcast_to(value[0, 1], hist[name][1:, 1].shape),
                                      err_msg=name)
    # the frozen seed's final state is its state after iteration 1
    template = runner.initial_state(cfg, SEEDS)
    first, _ = checkpoint.restore(root / "one_nan" / "checkpoints", template, step=1)
    final, _ = checkpoint.restore(root / "one_nan" / "checkpoints", template, step=3)

    def raw(leaf):
        return np.asarray(jax.random.key_data(leaf) if jax.dtypes.issubdtype(leaf.dtype, jax.dtypes.prng_key) else leaf)

    for a, b in zip(jax.tree_util.tree_leaves(first), jax.tree_util.tree_leaves(final)):
        np.testing.assert_array_equal(raw(a)[1], raw(b)[1])


def test_failed_checkpoint_write_keeps_the_previous_one(cfg, whole, scheduler, monkeypatch):
    root, result = whole
    saves = []
    real = ocp.StandardCheckpointHandler.async_save

    async def disk_full_on_second(self, *args, **kwargs):
        saves.append(1)
        if len(saves) == 2:
            raise OSError("No space left on device")
        return await real(self, *args, **kwargs)

    monkeypatch.setattr(ocp.StandardCheckpointHandler, "async_save", disk_full_on_second)
    with pytest.raises(checkpoint.CheckpointError, match="step 2 .* failed .*No space left.* untouched"):
        runner.run(cfg, SEEDS, root / "full", scheduler=scheduler)
    assert checkpoint.all_steps(root / "full" / "checkpoints") == [1]
    monkeypatch.setattr(ocp.StandardCheckpointHandler, "async_save", real)
    _same_history(runner.run(cfg, SEEDS, root / "full", resume=True, scheduler=scheduler), result)


def test_stop_request_checkpoints_and_resumes(cfg, whole, scheduler):
    root, result = whole
    stop_after_first = lambda e: scheduler.request_stop() if e.get("iteration") == 1 else None  # noqa: E731
    try:
        with pytest.raises(runner.Interrupted, match="stopped after iteration 1 of 3"):
            runner.run(cfg, SEEDS, root / "stop", scheduler=scheduler, progress_fn=stop_after_first)
    finally:
        scheduler.stop.clear()
    assert checkpoint.all_steps(root / "stop" / "checkpoints") == [1]
    _same_history(runner.run(cfg, SEEDS, root / "stop", resume=True, scheduler=scheduler), result)


def test_a_stopped_study_says_where_each_run_stands(cfg, whole, scheduler, tmp_path):
    """A stop requested before the runs' first iteration (Ctrl-C during the compilation): no run
    writes a checkpoint, and the study's message names every run and points at no checkpoint
    that does not exist."""
    configs = {("A", "mdgps"): cfg, ("B", "mdgps"): cfg}
    scheduler.request_stop()
    try:
        with pytest.raises(runner.Interrupted) as info:
            runner.run_all(configs, SEEDS, tmp_path, scheduler=scheduler)
    finally:
        scheduler.stop.clear()
    first = "stopped before its first iteration, with no checkpoint (--resume starts it from the beginning)"
    assert str(info.value) == f"A/mdgps {first}; B/mdgps {first}"
    for key in configs:
        assert checkpoint.all_steps(runner.run_folder(tmp_path, *key) / "checkpoints") == []


def test_corrupt_newest_checkpoint_falls_back(cfg, whole, scheduler):
    root, result = whole
    run_dir = root / "corrupt"
    shutil.copytree(root / "whole", run_dir)
    for dirpath, _, files in os.walk(run_dir / "checkpoints" / "3" / "state"):
        for name in files:
            if "/d" in dirpath or name.startswith("d"):  # the array data files
                path = os.path.join(dirpath, name)
                data = bytearray(open(path, "rb").read())
                data[len(data) // 2] ^= 0xFF
                open(path, "wb").write(bytes(data))
    events = []
    resumed = runner.run(cfg, SEEDS, run_dir, resume=True, scheduler=scheduler, progress_fn=events.append)
    messages = [e["message"] for e in events if "message" in e]
    assert messages[0].startswith("checkpoint step 3 is corrupt") and "set aside as 3.corrupt" in messages[0]
    assert messages[1] == "resumed from iteration 2"
    assert (run_dir / "checkpoints" / "3.corrupt").is_dir() and checkpoint.all_steps(run_dir / "checkpoints") == [1, 2, 3]
    _same_history(resumed, result)


def test_side_by_side_runs_take_their_turns_and_a_failed_one_holds_nobody_up(cfg, whole, scheduler, tmp_path):
    """``run_all``: two runs side by side trace in their turns (both iteration programs, then both
    robustness programs, ``TracingTurns.later``) and each equals the run alone; Python's switch
    interval is the scheduler's while they train, and restored after. A run that fails
    before its turn (placed on a platform this process does not have) releases both its turns:
    the other run is not held up, and ``run_all`` raises the failure instead of waiting."""
    root, result = whole
    configs = {("A", "mdgps"): cfg, ("B", "mdgps"): cfg}  # the same programs as ``whole``: compiled
    intervals, before = set(), sys.getswitchinterval()
    runs = runner.run_all(configs, SEEDS, tmp_path / "both", scheduler=scheduler,
                          progress_fn=lambda event: intervals.add(sys.getswitchinterval()))
    assert intervals == {scheduler.switch_interval} and sys.getswitchinterval() == before
    for run in runs.values():
        _same_history(run, result)
        for name, value in result["robustness"].items():
            np.testing.assert_array_equal(run["robustness"][name], value, err_msg=name)
    outcome = {}

    def failing():
        try:
            runner.run_all(configs, SEEDS, tmp_path / "failing", scheduler=scheduler,
                           platforms={("A", "mdgps"): "tpu"})
        except BaseException as err:  # noqa: BLE001 (handed to the test's thread)
            outcome["error"] = err

    thread = threading.Thread(target=failing, daemon=True)
    thread.start()
    thread.join(timeout=600)
    scheduler.stop.clear()
    assert not thread.is_alive(), "run_all waits for the turn of a run that failed before it"
    assert isinstance(outcome.get("error"), ValueError) and "platform 'tpu'" in str(outcome["error"])


def test_a_run_in_its_own_process_equals_the_run_here(cfg, whole, scheduler, tmp_path, monkeypatch):
    """``runner.run_all(..., processes=...)``: a run trained in a process of its own (forked from
    the server that has imported the package, ``process_server.start``; JAX on the CPU
    only, this process's precision) gives the same history and robustness as the run here, its
    progress events arrive here, its checkpoints are in its folder, and its exception is raised
    here, also from a spawned child where the platform has no forkserver; SIGTERM stops it after
    its iteration in flight, and leaves the server that the children fork from alive. The
    process's niceness is this one's plus the run's ``niceness``; it writes the checkpoints that
    ``checkpoint_every`` names."""
    from tolerances import assert_trees_within, scale_tol

    root, result = whole
    events, nice = [], []
    mine = os.getpriority(os.PRIO_PROCESS, 0)

    def progress(event):
        events.append(event)
        if event.get("iteration") == 1:  # the child is alive: its niceness
            import multiprocessing as mp

            child = next(p for p in mp.active_children() if p.name == "gmr-jax A/mdgps")
            nice.append(os.getpriority(os.PRIO_PROCESS, child.pid))
    # there the scheduler's "auto" compiles the policy's iteration in parts (here: one program),
    # which differ by round-off (test_runner.py's parts test, whose tolerance this is)
    assert runner.in_process_iteration_programs("auto", cfg) == "parts"
    monkeypatch.setenv(timeline.VARIABLE, str(tmp_path / "timeline"))  # passed to the child
    runs = runner.run_all({("A", "mdgps"): cfg}, SEEDS, tmp_path, scheduler=scheduler,
                          progress_fn=progress, processes=[("A", "mdgps")],
                          platforms={("A", "mdgps"): "cpu"}, niceness={("A", "mdgps"): 3},
                          checkpoint_every=2)
    monkeypatch.delenv(timeline.VARIABLE)
    marks = [(pid == os.getpid(), label) for _, pid, label in timeline.read(tmp_path / "timeline")
             if label != "runner imported"]  # the server's, where it started in this test
    assert marks == [(True, "process asked A/mdgps"), (True, "process started A/mdgps"),
                     (False, "process entry A/mdgps"), (False, "run entry A/mdgps"), (False, "run clock A/mdgps"),
                     (False, "run end A/mdgps"), (True, "result received A/mdgps")]
    assert nice == [min(mine + 3, 19)]
    run = runs[("A", "mdgps")]
    for got, want in ((run["history"], result["history"]), (run["robustness"], result["robustness"])):
        assert_trees_within(got, want, scale_tol(want))
    assert run["history"].keys() == result["history"].keys()
    assert [e["iteration"] for e in events if "iteration" in e] == [1, 2, 3]
    # checkpoint_every=2 reached the child: iteration 2's and the last
    assert checkpoint.all_steps(runner.run_folder(tmp_path, "A", "mdgps") / "checkpoints") == [2, 3]
    import multiprocessing.forkserver

    server = multiprocessing.forkserver._forkserver._forkserver_pid  # started by run_all, SIGTERM ignored
    os.kill(server, signal.SIGTERM)  # as a SIGTERM to the whole process group would
    for platform in ("cpu", None):  # None: on this process's devices (the CPU here too)
        with pytest.raises(runner.FolderTaken, match="already hold"):  # the child's error, raised here
            runner.run_in_process(cfg, SEEDS, runner.run_folder(tmp_path, "A", "mdgps"), scheduler=scheduler,
                                  platform=platform)
    assert multiprocessing.forkserver._forkserver._forkserver_pid == server  # the same server
    monkeypatch.setattr(multiprocessing, "get_all_start_methods", lambda: ["fork", "spawn"])  # no forkserver
    assert process_server.context().get_start_method() == "spawn"
    with pytest.raises(runner.FolderTaken, match="already hold"):  # a spawned child, its own imports
        runner.run_in_process(cfg, SEEDS, runner.run_folder(tmp_path, "A", "mdgps"), scheduler=scheduler)
    monkeypatch.undo()

    def terminate_child(event):  # SIGTERM to the child alone: a stop request there
        if event.get("iteration") == 1:
            child = next(p for p in multiprocessing.active_children() if p.name == "gmr-jax sigterm")
            os.kill(child.pid, signal.SIGTERM)
    with pytest.raises(runner.Interrupted):
        runner.run_in_process(dataclasses.replace(cfg, iterations=20), SEEDS, tmp_path / "sigterm",
                              scheduler=scheduler, label="sigterm", progress_fn=terminate_child)
    assert 1 <= checkpoint.latest(tmp_path / "sigterm" / "checkpoints") < 20  # the iteration in flight's
    with pytest.raises(ValueError, match="platform: 'gpu' is neither"):
        runner.run_in_process(cfg, SEEDS, tmp_path / "x", scheduler=scheduler, platform="gpu")
    with pytest.raises(ValueError, match="processes: B/mdgps not among the runs"):
        runner.run_all({("A", "mdgps"): cfg}, SEEDS, tmp_path / "other", scheduler=scheduler,
                       processes=[("B", "mdgps")])
    with pytest.raises(ValueError, match="niceness: A/mdgps not trained in a process of its own"):
        runner.run_all({("A", "mdgps"): cfg}, SEEDS, tmp_path / "other", scheduler=scheduler,
                       niceness={("A", "mdgps"): 1})
    for bad in (20, -1, 1.5, True):
        with pytest.raises(ValueError, match="niceness: .* is not an integer from 0 to 19"):
            runner.run_in_process(cfg, SEEDS, tmp_path / "x", scheduler=scheduler, niceness=bad)
        with pytest.raises(ValueError, match="niceness: .* is not an integer from 0 to 19"):
            runner.run_all({("A", "mdgps"): cfg}, SEEDS, tmp_path / "other", scheduler=scheduler,
                           processes=[("A", "mdgps")], platforms={("A", "mdgps"): "cpu"},
                           niceness={("A", "mdgps"): bad})
    assert runner.niceness_by_order("abcd", (0, 4)) == {"a": 0, "b": 4, "c": 4, "d": 4}


def test_missing_mjcf_is_one_line(tmp_path, capsys):
    code = reach.main(["--out", str(tmp_path), "--algorithm", "lqr", "--scenario", "A", "--no-plots",
                       "--set", "sim__scene=/no/such/scene.xml", "--compilation-cache", "none"])
    err = capsys.readouterr().err.strip()
    assert code == cli.EXIT_FAILED
    assert len(err.splitlines()) == 1 and "/no/such/scene.xml" in err and "does not exist" in err, err


def test_config_json_with_an_unknown_field(tmp_path, capsys):
    cfg = dataclasses.asdict(small("gmr"))
    cfg["gmr"]["alfa"] = 0.5
    (tmp_path / "config.json").write_text(json.dumps({"seeds": [0], "runs": {"A/gmr": cfg}}))
    assert diagnose.main([str(tmp_path)]) == cli.EXIT_FAILED
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "alfa" in err and "config.json" in err, err


def test_diagnose_with_an_unknown_override(tmp_path, capsys):
    cfg = dataclasses.asdict(small("gmr"))
    (tmp_path / "config.json").write_text(json.dumps({"seeds": [0], "runs": {"A/gmr": cfg}}))
    assert diagnose.main([str(tmp_path), "--set", "sim__float_32=True"]) == cli.EXIT_FAILED
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "float_32" in err, err


def test_float32_stages_outside_a_float64_run_is_one_line(tmp_path):
    # A process of its own: the CLI sets JAX's precision for the whole process.
    out = tmp_path / "out"
    proc = subprocess.run([sys.executable, "-m", "experiments.reach", "--precision", "float32",
                           "--set", "float32_stages=('dynamics',)", "--out", str(out)],
                          capture_output=True, text=True, timeout=300)
    errors = [line for line in proc.stderr.splitlines() if "error" in line]  # JAX may warn too
    assert proc.returncode == 2, proc.stderr
    assert len(errors) == 1 and errors[0].startswith("python -m experiments.reach: error: --set float32_stages")
    assert "--precision float64" in errors[0], proc.stderr
    assert not out.exists()  # nothing written


def test_diagnose_output_names_stay_in_the_folder():
    assert diagnose.file_suffix({}) == ""
    assert diagnose.file_suffix({"sim__float32": True}) == "_sim__float32=True"
    suffix = diagnose.file_suffix({"sim__scene": "/some/dir/scene.xml", "mlp__hidden": (8, 8)})
    assert "/" not in suffix and " " not in suffix and suffix.startswith("_sim__scene=")


def test_signals_request_a_stop():
    with runner.Scheduler() as own:
        before = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
        try:
            cli._stop_on_signals(own)
            os.kill(os.getpid(), signal.SIGTERM)
            assert own.stop.wait(timeout=5)
        finally:
            for s, handler in before.items():
                signal.signal(s, handler)


def test_comma_separated_positive_integers_are_parsed_or_refused_in_one_line():
    import argparse

    assert cli.positive_int_list("1, 132,256") == (1, 132, 256)
    assert cli.positive_int_list("") == ()
    for bad in ("0,4", "1,x", "-2"):
        with pytest.raises(argparse.ArgumentTypeError, match="comma-separated positive integers") as err:
            cli.positive_int_list(bad)
        assert "\n" not in str(err.value)

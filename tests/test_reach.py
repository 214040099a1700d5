"""The study command line (experiments.cli through experiments.reach): arguments are checked by
the configuration and named, the backend choice, one-line failures."""

import json

import numpy as np
import pytest

from experiments import cli, reach
from gmr_jax import checkpoint, runner


@pytest.mark.parametrize("argv, needle", [
    (["--scenario", "C"], "task.scenario='C'"),
    (["--scenario", "A,C"], "task.scenario='C'"),
    (["--algorithm", "ppo"], "algorithm='ppo'"),
    (["--seeds", "0"], "--seeds: must be a positive integer"),
    (["--samples", "1"], "the dynamics fit needs at least 2 samples"),
    (["--iterations", "0"], "iterations=0: must be a positive integer"),
    (["--T", "-3"], "task.T=-3"),
    (["--jobs", "-1"], "--jobs: must be an integer ≥ 0"),
    (["--compile-jobs", "0"], "--compile-jobs: must be a positive integer"),
    (["--checkpoint-every", "0"], "--checkpoint-every: must be a positive integer"),
    (["--set", "novalue"], "GROUP__FIELD=VALUE"),
    (["--set", "gmr__alph=1"], "unknown field(s) ['alph'] in configuration group 'gmr'"),
    (["--set", "gmr__alpha=-1"], "gmr.alpha=-1"),
    (["--set", "iterations=3"], "--set: use --iterations"),
])
def test_bad_arguments_end_with_one_line_naming_them(argv, needle, capsys):
    with pytest.raises(SystemExit) as exit_info:
        cli.parse_args("reach", argv)
    assert exit_info.value.code == cli.EXIT_USAGE
    err = capsys.readouterr().err
    assert needle in err, err
    assert "Traceback" not in err


def test_auto_backend_on_a_cpu_is_c_mujoco():
    args = cli.parse_args("reach", ["--seeds", "100"])
    assert all(c.sim.backend == "mujoco" for c in args.configs.values())  # the test machine has no GPU
    args = cli.parse_args("reach", ["--backend", "mjx", "--scenario", "AB", "--algorithm", "lqr"])
    assert [c.sim.backend for c in args.configs.values()] == ["mjx"]


def test_adam_on_the_trained_entries_from_256_seeds_per_gpu(monkeypatch):
    """On a GPU the CLI's S-steps carry only the trained weights from TRAINED_ENTRIES_MIN_SEEDS
    seeds per device on (counted over --devices), unless --set chooses; elsewhere the default."""
    import jax

    def entries(argv):
        return {c.sstep.adam_entries for c in cli.parse_args("reach", argv + ["--backend", "mujoco"]).configs.values()}

    assert entries(["--seeds", "1024"]) == {"all"}  # the test machine's CPU
    monkeypatch.setattr(jax, "default_backend", lambda: "gpu")
    monkeypatch.setattr(jax, "local_devices", lambda: ["gpu0", "gpu1"])
    n = cli.TRAINED_ENTRIES_MIN_SEEDS
    assert entries(["--seeds", str(n), "--devices", "1"]) == {"trained"}
    assert entries(["--seeds", str(n)]) == {"all"}  # both devices: n/2 per device
    assert entries(["--seeds", str(2 * n - 1)]) == {"trained"}  # ⌈(2n−1)/2⌉ = n per device
    assert entries(["--seeds", str(n - 1), "--devices", "1"]) == {"all"}
    assert entries(["--seeds", str(n), "--devices", "1", "--set", "sstep__adam_entries='all'"]) == {"all"}


def test_cpu_runs_on_a_gpu(monkeypatch, capsys):
    """--cpu-runs: on a GPU with one seed, "auto" places the MLP runs (C MuJoCo) on the host CPU
    and leaves GMR on the GPU; more seeds or MJX keep every run on the GPU; "none", "all" and a
    list of runs choose; a name that is not a run of the study is refused in one line. Without
    a GPU nothing is placed (everything is on the host already)."""
    import jax

    def placed(argv):
        return sorted(f"{s}/{a}" for s, a in cli.parse_args("reach", argv).platforms)

    assert placed(["--backend", "mujoco"]) == []  # the test machine's CPU
    monkeypatch.setattr(jax, "default_backend", lambda: "gpu")
    assert placed(["--backend", "mujoco"]) == ["A/mdgps", "AB/mdgps"]
    assert placed(["--backend", "mujoco", "--seeds", "2"]) == []
    assert placed(["--backend", "mjx"]) == []
    assert placed(["--backend", "mujoco", "--cpu-runs", "none"]) == []
    assert placed(["--backend", "mujoco", "--cpu-runs", "all"]) == ["A/gmr", "A/mdgps", "AB/gmr", "AB/mdgps"]
    assert placed(["--backend", "mujoco", "--cpu-runs", "A/gmr, AB/mdgps"]) == ["A/gmr", "AB/mdgps"]
    with pytest.raises(SystemExit) as exit_info:
        cli.parse_args("reach", ["--backend", "mujoco", "--cpu-runs", "A/gmr,B/lqr"])
    assert exit_info.value.code == cli.EXIT_USAGE
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].endswith("--cpu-runs: B/lqr not among this study's runs (A/gmr, A/mdgps, AB/gmr, "
                            "AB/mdgps); or use auto, none, all")


def test_gpu_runs_in_process_on_a_gpu(monkeypatch, capsys):
    """--gpu-runs-in-process: on one GPU with one seed, "auto" trains every GPU run but the one
    started first (the longest, ``runner.run_order``) in a process of its own; more seeds, more
    GPUs, one run at a time (--jobs 1) or no GPU (a CPU, a TPU) train them here; "none", "all"
    and a list choose among the GPU runs (a run on the host CPU stays there); a name that is not
    a run of the study is refused in one line."""
    import jax

    def apart(argv, devices=1):
        monkeypatch.setattr(jax, "local_devices", lambda *a, **k: [object()] * devices)
        return [f"{s}/{a}" for s, a in cli.parse_args("reach", ["--backend", "mujoco"] + argv).gpu_processes]

    assert apart([]) == []  # the test machine's CPU
    monkeypatch.setattr(jax, "default_backend", lambda: "gpu")
    assert apart([]) == ["A/gmr"]  # AB/gmr starts first; the MLP runs are on the host CPU
    assert apart(["--cpu-runs", "none"]) == ["A/gmr", "AB/mdgps", "A/mdgps"]
    assert apart(["--seeds", "2"]) == [] and apart([], devices=2) == []
    assert apart(["--devices", "1"], devices=2) == ["A/gmr"]
    assert apart(["--jobs", "1"]) == [] and apart(["--jobs", "2"]) == ["A/gmr"]  # one run at a time: no gain
    assert apart(["--gpu-runs-in-process", "none"]) == []
    assert apart(["--gpu-runs-in-process", "all"]) == ["AB/gmr", "A/gmr"]
    assert apart(["--gpu-runs-in-process", "AB/gmr,A/mdgps"]) == ["AB/gmr"]  # A/mdgps is on the CPU
    monkeypatch.setattr(jax, "default_backend", lambda: "tpu")
    assert apart(["--gpu-runs-in-process", "all"]) == []  # GPUs only: a TPU is one process's
    with pytest.raises(SystemExit) as exit_info:
        cli.parse_args("reach", ["--backend", "mujoco", "--gpu-runs-in-process", "B/gmr"])
    assert exit_info.value.code == cli.EXIT_USAGE
    assert capsys.readouterr().err.strip().splitlines()[-1].endswith(
        "--gpu-runs-in-process: B/gmr not among this study's runs (A/gmr, A/mdgps, AB/gmr, AB/mdgps); "
        "or use auto, none, all")


def test_a_child_run_starts_with_its_platform_environment():
    """``runner.child_environment``: a run on the host in a process of its own sees the CPU only;
    one on this process's GPU takes no preallocated pool (the parent's holds most of the GPU);
    one on this process's CPU devices changes nothing; a policy's run on the host compiles its
    iteration in parts, on a GPU as the child resolves "auto" (as this process would)."""
    from test_mdgps import small

    assert runner.child_environment("cpu", "gpu") == {"JAX_PLATFORMS": "cpu"}
    assert runner.child_environment("cpu", "cpu") == {"JAX_PLATFORMS": "cpu"}
    assert runner.child_environment(None, "gpu") == {"XLA_PYTHON_CLIENT_PREALLOCATE": "false"}
    assert runner.child_environment(None, "cpu") == {} and runner.child_environment(None, "tpu") == {}
    assert runner.in_process_iteration_programs("auto", small("gmr"), "gpu") == "auto"
    assert runner.in_process_iteration_programs("auto", small("gmr"), "cpu") == "parts"
    assert runner.in_process_iteration_programs("whole", small("gmr"), "cpu") == "whole"
    from gmr_jax import program_store

    # a child takes every setting that changes a trace (and the compilation cache's) from here
    assert set(program_store.TRACE_SETTINGS) <= set(runner._CHILD_JAX_CONFIG)
    assert {"jax_compilation_cache_dir", "jax_persistent_cache_min_compile_time_secs"} <= set(runner._CHILD_JAX_CONFIG)


def test_fresh_run_into_a_folder_with_checkpoints_is_refused(tmp_path, capsys):
    """Without --resume, an --out that holds a run's checkpoints is refused before anything is
    written: the earlier run's config.json and checkpoints stay as they were."""
    ckpt = runner.run_folder(tmp_path, "A", "lqr") / "checkpoints"
    checkpoint.save(ckpt, {"x": np.zeros(2)}, step=1)
    (tmp_path / "config.json").write_text("earlier run")
    assert reach.main(["--out", str(tmp_path), "--scenario", "A", "--algorithm", "lqr",
                       "--compilation-cache", "none"]) == cli.EXIT_USAGE
    err = capsys.readouterr().err
    assert "already hold" in err and str(ckpt) in err and "--resume" in err
    assert len(err.strip().splitlines()) == 1
    assert (tmp_path / "config.json").read_text() == "earlier run"
    assert checkpoint.latest(ckpt) == 1


def test_checkpoint_every_reaches_the_runs_and_config_json(tmp_path):
    """--checkpoint-every 2 over three iterations: the run keeps checkpoints 2 and 3 (the last),
    and the study's config.json records the setting."""
    assert reach.main(["--out", str(tmp_path), "--scenario", "A", "--algorithm", "lqr", "--iterations", "3",
                       "--checkpoint-every", "2", "--devices", "1", "--no-plots", "--compilation-cache", "none"]) == 0
    assert checkpoint.all_steps(runner.run_folder(tmp_path, "A", "lqr") / "checkpoints") == [2, 3]
    assert json.loads((tmp_path / "config.json").read_text())["checkpoint_every"] == 2


def test_config_json_records_how_each_run_compiles_its_iteration():
    """``cli._iteration_programs``: what config.json records per run is what the runner resolves
    there: on a GPU, split for a one-seed GMR run with C MuJoCo, parts for more seeds; a run on
    the host in a process of its own compiles in parts (``runner.in_process_iteration_programs``),
    in this process as one program."""
    import types

    from test_mdgps import small

    gmr, mdgps = small("gmr"), small("mdgps")
    gpu = [types.SimpleNamespace(platform="gpu")]
    args = types.SimpleNamespace(platforms={("A", "mdgps"): "cpu"}, iteration_programs="auto", seeds=1,
                                 cpu_runs_in_process=True)
    assert cli._iteration_programs(args, "A", "gmr", gmr, gpu) == "split"
    assert cli._iteration_programs(args, "A", "mdgps", mdgps, gpu) == "parts"
    args.cpu_runs_in_process = False
    assert cli._iteration_programs(args, "A", "mdgps", mdgps, gpu) == "whole"
    assert cli._iteration_programs(args, "A", "gmr", gmr, gpu * 2) == "parts"  # one seed, two GPUs
    args.seeds = 2
    assert cli._iteration_programs(args, "A", "gmr", gmr, gpu) == "parts"
    args.iteration_programs = "whole"
    assert cli._iteration_programs(args, "A", "gmr", gmr, gpu) == "whole"

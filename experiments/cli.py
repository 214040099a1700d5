"""The command line shared by the studies (``python -m experiments.reach``, …): arguments →
configurations → ``gmr_jax.runner`` → ``experiments.report``.

Every expected failure (a bad argument, a corrupt or mismatched checkpoint, a run that diverges,
an MJCF error, a full disk, Ctrl-C) ends with one line on stderr naming the problem and the way
out, and a non-zero exit code; ``--debug`` shows the traceback instead.
"""

from __future__ import annotations

import argparse
import ast
import concurrent.futures
import contextlib
import json
import os
import pathlib
import platform
import signal
import sys
import time
import traceback

from experiments import xla_flags
from gmr_jax import checkpoint, config, mps, policies, process_server, runner, sharding, sstep, tasks, timeline
from gmr_jax.program_store import ProgramStore
from gmr_jax.sim import MJCFError

# Programs (iterations, evaluations) compiled at once (--compile-jobs): 2 and 4 were equally fast
# on an H100, 3 slower, and 4 was slower on the 2-core CPU (benchmarks/RESULTS.md).
DEFAULT_COMPILE_JOBS = 2
DEFAULT_COMPILATION_CACHE = os.environ.get("JAX_COMPILATION_CACHE_DIR") or str(
    pathlib.Path("~/.cache/gmr_jax/xla").expanduser())
# Exit codes: 1 a run failed, 2 bad usage (argparse's), 130 interrupted (128 + SIGINT).
EXIT_FAILED, EXIT_USAGE, EXIT_INTERRUPTED = 1, 2, 130


def _int_at_least(low: int, what: str):
    """An argparse type: an integer ≥ ``low``, else one message naming what it must be."""
    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            value = low - 1
        if value < low:
            raise argparse.ArgumentTypeError(f"must be {what}, got {text!r}")
        return value
    return parse


positive_int = _int_at_least(1, "a positive integer")
"""argparse's ``type`` for a positive integer (the command line's and the benchmarks')."""


def positive_int_list(text: str) -> tuple[int, ...]:
    """argparse's ``type`` for comma-separated positive integers ("1,132,256"; empty: none)."""
    parts = [v.strip() for v in text.split(",") if v.strip()]
    try:
        return tuple(positive_int(v) for v in parts)
    except argparse.ArgumentTypeError:
        raise argparse.ArgumentTypeError(f"must be comma-separated positive integers such as 1,256, "
                                         f"got {text!r}") from None


_nonnegative_int = _int_at_least(0, "an integer ≥ 0")


def _niceness_choice(text: str):
    """An argparse type for ``--process-niceness``: "auto", "off" or a tuple of niceness
    increments (``runner.check_niceness``)."""
    text = text.strip()
    if text in ("auto", "off"):
        return text
    try:
        values = tuple(int(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be auto, off or comma-separated integers from 0 to "
                                         f"{runner.MAX_NICENESS}, got {text!r}") from None
    try:
        for value in values:
            runner.check_niceness(value)
    except ValueError as err:
        raise argparse.ArgumentTypeError(str(err)) from None
    return values


def build_parser(task: tasks.Task, description: str | None = None) -> argparse.ArgumentParser:
    base = task.default_config(task.default_scenarios[0])
    p = argparse.ArgumentParser(prog=f"python -m experiments.{task.name}", description=description,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--algorithm", default="gmr,mdgps",
                   help=f"comma-separated list of {tuple(policies.ALGORITHMS)} (default: %(default)s)")
    p.add_argument("--scenario", default=",".join(task.default_scenarios),
                   help=f"comma-separated list of {tuple(task.scenarios)} (default: %(default)s)")
    p.add_argument("--iterations", type=int, default=base.iterations, help="GPS iterations (default: %(default)s)")
    p.add_argument("--samples", type=int, default=base.num_samples,
                   help="samples per condition per iteration (default: %(default)s)")
    p.add_argument("--seeds", type=positive_int, default=1, help="seeds trained in parallel (default: 1)")
    p.add_argument("--first-seed", type=int, default=0, help="first seed (default: 0)")
    p.add_argument("--T", type=int, default=base.task.T, help="horizon (default: %(default)s)")
    p.add_argument("--backend", default="auto", choices=config.BACKENDS,
                   help="physics backend (default: %(default)s: C MuJoCo on a CPU; on a GPU, "
                        + (f"MJX when a rollout batch holds at least {task.mjx_min_rollouts} rollouts "
                           "(seeds × conditions × samples), C MuJoCo below that, where MJX's "
                           "per-step latency dominates" if task.mjx_min_rollouts is not None else
                           "C MuJoCo too: MJX steps this scene's contacts slower at every measured "
                           "batch size (benchmarks/RESULTS.md)")
                        + "; the choice is written to config.json)")
    p.add_argument("--out", default=f"results/{task.name}", help="output folder (default: %(default)s)")
    p.add_argument("--resume", action="store_true",
                   help="continue from the newest intact checkpoints in --out (same settings; a "
                        "larger --iterations extends finished runs)")
    p.add_argument("--checkpoint-every", type=positive_int, default=1, metavar="N",
                   help="write the runs' checkpoints after every N-th iteration and the last (a stop "
                        "or an error writes the last finished one too; default: %(default)s). Many "
                        "seeds' checkpoints are large (about 1.6 MB per seed for GMR on A,B) and "
                        "writing them slows the iterations")
    add_precision_argument(p)
    p.add_argument("--no-plots", action="store_true", help="skip the PNG figures")
    p.add_argument("--video", action="store_true",
                   help="render MP4s of every policy run's first seed from the training conditions and "
                        "three random states into OUT/videos/ (MuJoCo offscreen: EGL or OSMesa; "
                        "pip install 'gmr-jax[video]'); without it only the still-frame grid frames.png")
    p.add_argument("--no-stability", action="store_true",
                   help="skip the closed-loop stability of the trained policies (gmr_jax.stability: "
                        "spectral radius of the one-step Jacobian at the target and along the "
                        "robustness rollouts). Its C MuJoCo finite differences take about 0.17 s "
                        "per seed on 16 host cores (40-48 s for 256 seeds)")
    p.add_argument("--jobs", type=_nonnegative_int, default=0,
                   help="runs (scenario × algorithm) trained side by side: they compile concurrently "
                        "and share the device (default 0: all of them)")
    p.add_argument("--compile-jobs", type=positive_int, default=DEFAULT_COMPILE_JOBS,
                   help="programs (iterations, evaluations) compiled at once (default: %(default)s; an iteration "
                        "in parts, --iteration-programs, counts as one and compiles its parts in "
                        "parallel). XLA spreads one compilation over the cores, so more at once mostly slow "
                        "each other")
    p.add_argument("--iteration-programs", default="auto", choices=runner.ITERATION_PROGRAMS,
                   help="compile each run's iteration as one program (whole), as the programs of its "
                        "parts, which compile in parallel (parts), or as parts of which the C MuJoCo "
                        "rollouts, the learning curve and the C-step run on the host's CPU (split; for "
                        "one seed on one GPU with C MuJoCo, else parts). Default %(default)s: split where "
                        "it applies and parts otherwise for the policy runs on a GPU, parts for those in "
                        "processes of their own on the host, whole elsewhere (runner.ITERATION_PARTS, "
                        "runner.SPLIT_PARTS, runner.HOST_PARTS; benchmarks/RESULTS.md, twenty-third and "
                        "twenty-fifth sessions); the choice is written to config.json")
    p.add_argument("--autotune", action="store_true",
                   help="let XLA time kernel variants on the GPU while compiling. Off by default: "
                        "runs that compile while others train make those timings slow and noisy, "
                        "and kernels chosen by timing make results differ from call to call")
    p.add_argument("--nondeterministic", action="store_true",
                   help="let XLA use GPU kernels whose floating-point sums depend on thread timing "
                        "(atomic scatters and reductions). Off by default: with them, two runs of "
                        "the same key and configuration on the same GPU differ from the first "
                        "iterations on (benchmarks/RESULTS.md)")
    p.add_argument("--compilation-cache", default=DEFAULT_COMPILATION_CACHE, metavar="DIR",
                   help="persistent XLA compilation cache: a repeated run skips most of its "
                        "compilation (default: $JAX_COMPILATION_CACHE_DIR or %(default)s; "
                        "'none' disables it)")
    p.add_argument("--program-store", action=argparse.BooleanOptionalAction, default=True,
                   help="keep the runs' programs, once traced, as serialized JAX modules beside the "
                        "compilation cache (DIR_programs), so that a repeated run lowers them instead of "
                        "tracing them again (default; programs with host callbacks are traced every time; "
                        "gmr_jax.program_store). Off with --compilation-cache none")
    p.add_argument("--set", action="append", default=[], metavar="GROUP__FIELD=VALUE",
                   help="override a configuration field for every run, e.g. --set gmr__alpha=0.1 "
                        "or --set sstep__epochs=100 (repeatable; values are Python literals)")
    p.add_argument("--devices", type=positive_int, default=None,
                   help="split the seeds over this many local devices (default: all of them; a "
                        "seed count they do not divide is padded, the padding dropped)")
    p.add_argument("--cpu-runs", default="auto", metavar="auto|none|all|SCENARIO/ALGORITHM,…",
                   help="runs that compute on the host CPU instead of the GPU (default: %(default)s: "
                        "on a GPU with one seed, the MLP policy's runs (mdgps) with C MuJoCo, "
                        "whose S-steps are faster on the host than on an H100 and leave the GPU to "
                        "the GMR runs; benchmarks/RESULTS.md; none under MPS, --mps, where all four "
                        "runs share the GPU at once). Ignored without a GPU; the choice "
                        "is written to config.json; a name that is not a run is refused on any machine")
    p.add_argument("--cpu-runs-in-process", action=argparse.BooleanOptionalAction, default=True,
                   help="train the --cpu-runs in a process of their own (default), so that their "
                        "Python work does not share the GIL with the GPU runs' host callbacks "
                        "(runner.run_in_process; benchmarks/RESULTS.md, twentieth session)")
    p.add_argument("--gpu-runs-in-process", default="auto", metavar="auto|none|all|SCENARIO/ALGORITHM,…",
                   help="runs on the GPU trained in a process of their own beside this one, which "
                        "share the GPU (default: %(default)s: with one seed on one GPU and runs side "
                        "by side, every GPU run but the longest, so that the runs trace, compile and "
                        "drive their loops without sharing one GIL; benchmarks/RESULTS.md, "
                        "twenty-eighth session; under MPS, --mps, every GPU run). Such a run takes "
                        "GPU memory from what this process's pool leaves free (a quarter of the GPU; "
                        "more with XLA_PYTHON_CLIENT_MEM_FRACTION; all of it under MPS, where this "
                        "process keeps no pool). Runs on the host CPU (--cpu-runs) stay "
                        "there; ignored without a GPU; the choice is written to config.json")
    p.add_argument("--mps", default="auto", choices=MPS_CHOICES,
                   help="run the processes of the runs on one GPU under a private CUDA Multi-Process "
                        "Service daemon (gmr_jax.mps), so that their kernels share the GPU at once "
                        "instead of in time slices (default: %(default)s: where nvidia-cuda-mps-control "
                        "is on PATH, with one seed on one GPU and runs side by side in processes of "
                        "their own, --gpu-runs-in-process not none; every run then trains on the GPU in "
                        "a process of its own, unless --cpu-runs or --gpu-runs-in-process say "
                        "otherwise; benchmarks/RESULTS.md, twenty-ninth session). An MPS daemon "
                        "already running for this process (CUDA_MPS_PIPE_DIRECTORY or /tmp/nvidia-mps) "
                        "is used as it is. 'on': wherever JAX may use a GPU (where runs do not share "
                        "one, place them with --gpu-runs-in-process), and one line and exit 2 where no "
                        "daemon can start")
    p.add_argument("--process-niceness", default="auto", type=_niceness_choice, metavar="auto|off|N,N,…",
                   help="niceness added to the processes of the runs trained on the GPU in a process of "
                        "their own (to this command's; the sum capped at 19), in the order the runs start "
                        "(runner.run_order: the longest first; the last value for every later run), so "
                        "that the longest run gets the host's cores first while the processes compile "
                        "(default: %(default)s: "
                        f"{','.join(map(str, runner.PROCESS_NICENESS))} where every run of the study is "
                        "such a process, as under MPS, else none; benchmarks/RESULTS.md, thirtieth "
                        "session). Runs placed on the host CPU (--cpu-runs) keep this command's niceness: "
                        "their training fills its cores, and a lower priority slowed it (twenty-eighth "
                        "session). Each process's added niceness is written to config.json")
    p.add_argument("--debug", action="store_true", help="show tracebacks of failures")
    return p


def parse_overrides(p: argparse.ArgumentParser, items: list[str]) -> dict:
    """``--set GROUP__FIELD=VALUE`` items → {name: value} (Python literals, else the bare word);
    a malformed item is a usage error of ``p``."""
    out = {}
    for item in items:
        name, sep, text = item.partition("=")
        if not sep or not name.strip():
            p.error(f"--set {item!r}: expected GROUP__FIELD=VALUE")
        try:
            value = ast.literal_eval(text)
        except (ValueError, SyntaxError):
            value = text  # a bare word, e.g. --set gmr__exploration=fixed
        out[name.strip()] = value
    return out


def _iteration_programs(args, scenario: str, algorithm: str, cfg, used) -> str:
    """How run (scenario, algorithm) compiles its iteration (``runner.iteration_programs_for``
    of ``--iteration-programs``, for a run in a process of its own as that process resolves it)."""
    where = args.platforms.get((scenario, algorithm), used[0].platform)
    choice = args.iteration_programs
    if (scenario, algorithm) in args.platforms and args.cpu_runs_in_process:
        choice = runner.in_process_iteration_programs(choice, cfg)
    return runner.iteration_programs_for(choice, cfg, where, args.seeds,
                                         len(used) if where == used[0].platform else 1)


MPS_CHOICES = ("auto", "on", "off")


def shares_one_gpu(args, gpus: int) -> bool:
    """Whether the study's runs share one GPU side by side: one seed, more than one run,
    ``--jobs`` not 1, and one device used (``--devices``, else the ``gpus`` there are)."""
    return (args.seeds == 1 and len(args.scenarios) * len(args.algorithms) > 1 and args.jobs != 1
            and (args.devices or gpus) == 1)


def start_mps(args) -> str | None:
    """``--mps`` before JAX starts its backend: "started" (a private daemon, ``args.mps_daemon``,
    whose clients are the processes that this one starts once :func:`parse_args` has started the
    backend; not this one, so the daemon can stop as soon as they have exited), "running" (a
    daemon already serves this process) or None.
    auto: where runs share one GPU (:func:`shares_one_gpu`) in processes of their own
    (``--gpu-runs-in-process`` not none), a GPU may be used (``JAX_PLATFORMS``) and the control
    program exists; a daemon that cannot start is skipped with one line on stderr. on: wherever
    a GPU may be used; raises ``mps.Unavailable`` where none runs or can start. Where every GPU
    run will train in a process of its own, this process keeps no GPU memory pool.
    A daemon started here is still being checked by its client (``mps.launch``) when this
    returns, so that the client's CUDA start overlaps this process's own backend;
    :func:`_resolved` waits for it (:func:`_mps_checked`). The GPUs are counted here by CUDA's
    driver (``mps.device_count``)."""
    args.mps_daemon = None
    if args.mps == "off":
        return None
    if not process_server.gpu_allowed():
        if args.mps == "on":
            raise mps.Unavailable(f"JAX_PLATFORMS={os.environ.get('JAX_PLATFORMS')} leaves JAX no GPU")
        return None
    if args.mps == "auto" and (args.gpu_runs_in_process == "none" or not shares_one_gpu(args, 1)):
        return None
    starting, gpus = None, 1
    if mps.running_elsewhere():
        state = "running"
    else:
        control = mps.find_control()
        if control is None and args.mps == "auto":
            return None
        try:
            starting = mps.launch(control)
        except mps.Unavailable as err:
            if args.mps == "on":
                raise
            _no_mps_note(err)
            return None
        try:
            gpus = mps.device_count() or 1  # none: JAX finds no GPU either, and _resolved stops the daemon
        except BaseException:  # Ctrl-C too: no daemon left behind
            mps.abandon(starting)
            raise
        if args.mps == "auto" and not shares_one_gpu(args, gpus):
            mps.abandon(starting)  # one seed on several GPUs: the runs do not share one
            return None
        state = "started"
    apart = args.gpu_runs_in_process == "all" or (args.gpu_runs_in_process == "auto" and shares_one_gpu(args, gpus))
    if apart and "XLA_PYTHON_CLIENT_PREALLOCATE" not in os.environ:
        # every GPU run trains in a process of its own: this one computes nothing there (and
        # where the daemon's client then fails, this process allocates as it needs)
        os.environ["XLA_PYTHON_CLIENT_PREALLOCATE"] = "false"
    args.mps_daemon = starting
    return state


def _no_mps_note(err: Exception) -> None:
    print(f"note: no CUDA MPS ({err}); runs on one GPU take turns on it (--mps off hides this)", file=sys.stderr)


def _mps_checked(args) -> str | None:
    """``args.mps_state`` once the client of a daemon that :func:`start_mps` started has
    finished: "started" (``args.mps_daemon`` the running ``mps.Daemon``), or None where it
    failed under ``--mps auto`` (one line on stderr); raises ``mps.Unavailable`` under on."""
    if not isinstance(getattr(args, "mps_daemon", None), mps.Starting):
        return args.mps_state
    starting, args.mps_daemon = args.mps_daemon, None
    try:
        args.mps_daemon = mps.finish(starting)
    except mps.Unavailable as err:
        if args.mps == "on":
            raise
        _no_mps_note(err)
        return None
    timeline.mark("MPS daemon ready")
    return args.mps_state


def stop_mps(args) -> None:
    """Stop the private MPS daemon that :func:`start_mps` started (or is still checking), if any."""
    daemon, args.mps_daemon = getattr(args, "mps_daemon", None), None
    if isinstance(daemon, mps.Starting):
        mps.abandon(daemon)
    elif daemon is not None:
        mps.stop(daemon)


def resolve_backend(args, task: tasks.Task) -> str:
    """``--backend``: "auto" is "mujoco" on a CPU, and on a GPU "mjx" when the sampling batch
    (seeds × conditions × samples, the largest scenario) reaches the task's
    ``mjx_min_rollouts`` (never for a task without one)."""
    import jax

    if args.backend != "auto":
        return args.backend
    if jax.default_backend() != "gpu":
        return "mujoco"
    conditions = max(len(task.scenarios[s]) for s in args.scenarios if s in task.scenarios)
    if task.mjx_min_rollouts is None:
        return "mujoco"
    return "mjx" if args.seeds * conditions * args.samples >= task.mjx_min_rollouts else "mujoco"


# Seeds per GPU from which the CLI's S-steps let Adam carry only the trained weights
# (``SStepConfig.adam_entries = "trained"``): on an H100 the GMR and MLP S-steps are 21 % and 10 %
# faster with 256 seeds, and between 5 % faster and 11 % slower with 16 and 64 seeds
# (benchmarks/RESULTS.md, tenth and eleventh sessions).
TRAINED_ENTRIES_MIN_SEEDS = 256


def resolve_adam_entries(args) -> dict:
    """The S-step's ``adam_entries`` for the CLI's runs: ``{"sstep__adam_entries": "trained"}`` on
    a GPU with at least ``TRAINED_ENTRIES_MIN_SEEDS`` seeds per device, else {} (the
    configuration's default); a ``--set sstep__adam_entries=…`` wins."""
    import jax

    if "sstep__adam_entries" in args.overrides or jax.default_backend() != "gpu":
        return {}
    devices = min(args.devices or len(jax.local_devices()), len(jax.local_devices()))
    per_device = sharding.seeds_per_device(args.seeds, devices)
    return {"sstep__adam_entries": "trained"} if per_device >= TRAINED_ENTRIES_MIN_SEEDS else {}


# Algorithms whose runs ``--cpu-runs auto`` places on the host CPU when a GPU trains one seed:
# the MLP's S-step takes 37 µs per Adam step on a 2-core CPU against 50-55 µs on an H100 (where
# each of its kernels costs ~1.7 µs however small), and the default run's MDGPS runs finish in
# 20-26 s on the host while the GMR runs, alone on the GPU, end 14-15 s sooner than when all
# four share it (benchmarks/RESULTS.md, sixteenth session). GMR's S-step is three times faster
# on the GPU; "lqr" was not measured.
CPU_RUN_ALGORITHMS = ("mdgps",)


def _chosen_runs(option: str, value: str, args, auto) -> list:
    """The study's runs that ``option``'s ``value`` names: "none", "all", "auto" (the list
    ``auto``) or comma-separated SCENARIO/ALGORITHM names. Raises ValueError for a name that is
    not one of the study's runs."""
    value = value.strip()
    if value == "none":
        return []
    if value == "auto":
        return list(auto)
    if value == "all":
        return list(args.configs)
    names = {f"{s}/{a}": (s, a) for s, a in args.configs}
    given = [n.strip() for n in value.split(",") if n.strip()]
    unknown = [n for n in given if n not in names]
    if unknown:
        raise ValueError(f"{option}: {', '.join(unknown)} not among this study's runs "
                         f"({', '.join(names)}); or use auto, none, all")
    return [names[n] for n in given]


def resolve_cpu_runs(args) -> dict:
    """``--cpu-runs`` → {(scenario, algorithm): "cpu"} for the runs to place on the host CPU
    (``runner.run_all``'s ``platforms``): none without a GPU (everything is on the host then),
    "auto" as ``CPU_RUN_ALGORITHMS`` says for one seed with the C MuJoCo backend (none under
    MPS, ``args.mps_state``: every run on the GPU then), or the named runs. Raises ValueError for
    a name that is not one of the study's runs."""
    import jax

    auto = [key for key, cfg in args.configs.items()
            if args.seeds == 1 and cfg.algorithm in CPU_RUN_ALGORITHMS and cfg.sim.backend == "mujoco"
            and not (getattr(args, "mps_state", None) and args.gpu_runs_in_process != "none")]
    chosen = _chosen_runs("--cpu-runs", args.cpu_runs, args, auto)
    return {} if jax.default_backend() == "cpu" else {key: "cpu" for key in chosen}


def resolve_gpu_processes(args) -> list:
    """``--gpu-runs-in-process`` → the runs on the GPU (those not in ``args.platforms``) to train
    in a process of their own (``runner.run_all``'s ``processes``): none without a GPU; "auto":
    with one seed on one GPU and runs side by side (``--jobs`` not 1) every GPU run but the one
    ``runner.run_order`` starts first (the longest: it starts at once here, the others while
    their processes start), and under MPS (``args.mps_state``) every GPU run; or the named runs
    (a named run placed on the host CPU stays there).
    Raises ValueError for a name that is not one of the study's runs."""
    import jax

    on_gpu = [key for key in runner.run_order(args.configs) if key not in args.platforms]
    auto = on_gpu if getattr(args, "mps_state", None) else on_gpu[1:]
    chosen = _chosen_runs("--gpu-runs-in-process", args.gpu_runs_in_process, args,
                          auto if shares_one_gpu(args, len(jax.local_devices())) else [])
    return [key for key in on_gpu if key in chosen] if jax.default_backend() == "gpu" else []


def resolve_niceness(args) -> dict:
    """``--process-niceness`` → {(scenario, algorithm): niceness} for the runs on the GPU in a
    process of their own (``args.gpu_processes``, in ``runner.run_order``; ``runner.run_all``'s
    ``niceness``) by ``runner.niceness_by_order``: "auto" ``runner.PROCESS_NICENESS`` where every
    run of the study is one of them (and there are several), else none; "off" none; or the
    values given."""
    chosen = args.process_niceness
    if chosen == "off" or (chosen == "auto" and (len(args.gpu_processes) < 2
                                                 or len(args.gpu_processes) != len(args.configs))):
        return {}
    return runner.niceness_by_order(args.gpu_processes, runner.PROCESS_NICENESS if chosen == "auto" else chosen)


def process_runs(args) -> list:
    """The runs trained in a process of their own (``runner.run_all``'s ``processes``): the
    ``--cpu-runs`` with ``--cpu-runs-in-process``, and the ``--gpu-runs-in-process``."""
    return (list(args.platforms) if args.cpu_runs_in_process else []) + list(args.gpu_processes)


def parse_args(task_name: str, argv=None, description: str | None = None,
               start_daemons: bool = False) -> argparse.Namespace:
    """The arguments, with ``args.configs``: {(scenario, algorithm): Config}. Every setting is
    validated by the configuration itself; a bad one ends argparse's way (usage, exit 2). With
    ``start_daemons`` (the command, not a caller that only parses), ``--mps`` may start a private
    MPS daemon before JAX's backend starts (``args.mps_state``; stop it with :func:`stop_mps`)."""
    task = tasks.get(task_name)
    p = build_parser(task, description)
    args = p.parse_args(argv)
    args.task = task
    args.overrides = parse_overrides(p, args.set)
    args.algorithms = [a.strip() for a in args.algorithm.split(",") if a.strip()]
    args.scenarios = [s.strip() for s in args.scenario.split(",") if s.strip()]
    dedicated = {"iterations": "--iterations", "num_samples": "--samples", "task__T": "--T",
                 "sim__backend": "--backend", "algorithm": "--algorithm", "task__scenario": "--scenario"}
    clash = sorted(dedicated[k] for k in set(dedicated) & set(args.overrides))
    if clash:
        p.error(f"--set: use {', '.join(clash)} for these settings")
    try:
        args.mps_state = start_mps(args) if start_daemons else None
    except mps.Unavailable as err:
        p.error(f"--mps on: {err}; use --mps auto or off")
    try:
        return _resolved(p, args, task)
    except BaseException:
        stop_mps(args)
        raise


def _resolved(p: argparse.ArgumentParser, args, task: tasks.Task) -> argparse.Namespace:
    """``parse_args`` after the arguments are read: configurations and run placements."""
    import jax

    try:
        backend = resolve_backend(args, task)
        if args.mps_state and jax.default_backend() != "gpu":  # a daemon, but JAX has no GPU backend here
            stop_mps(args)
            args.mps_state = None
            if args.mps == "on":
                p.error("--mps on: JAX has no GPU backend here; use --mps auto or off")
        try:
            args.mps_state = _mps_checked(args)
        except mps.Unavailable as err:
            p.error(f"--mps on: {err}; use --mps auto or off")
        if args.mps_state == "started":  # started outside the daemon: only the runs' processes use it
            mps.activate(args.mps_daemon)
        overrides = {**resolve_adam_entries(args), **args.overrides}
        args.configs = {(s, a): config.make(task.name, s, a, iterations=args.iterations,
                                            num_samples=args.samples, task__T=args.T,
                                            sim__backend=backend, **overrides)
                        for s in args.scenarios for a in args.algorithms}
    except (ValueError, TypeError) as err:
        p.error(str(err))
    if not args.configs:
        p.error("no runs: give at least one --scenario and one --algorithm")
    try:
        args.platforms = resolve_cpu_runs(args)
        args.gpu_processes = resolve_gpu_processes(args)
        args.niceness = resolve_niceness(args)
    except ValueError as err:
        p.error(str(err))
    return args


def progress_printer(prefix_runs: bool):
    """A runner progress callback printing one line per iteration (and the runner's messages)."""
    def mean(m, name):
        return float(m[name].mean()) if name in m else float("nan")

    def show(event: dict) -> None:
        label = f"[{event['run']}]" if prefix_runs else ""
        if "message" in event:
            print(f"{label}  {event['message']}", flush=True)
            return
        m = event["metrics"]
        line = (f"{label}  iter {event['iteration']:2d}/{event['iterations']}  cost {mean(m, 'sample_cost'):10.3f}"
                f"  KL {mean(m, 'kl'):8.3f}  eps {mean(m, 'epsilon'):7.2f}  eta {mean(m, 'eta'):9.3g}"
                f"  step {mean(m, 'step_mult'):6.3f}  mse(lqr) {mean(m, 'final_state_mse_lqr'):.4g}")
        if "final_state_mse_policy" in m:
            line += f"  mse(policy) {mean(m, 'final_state_mse_policy'):.4g}"
        print(line, flush=True)
    return show


PRECISIONS = ("auto", "float32", "float64")


def add_precision_argument(p: argparse.ArgumentParser) -> None:
    """``--precision`` (auto, float32, float64), shared by the studies and the benchmarks."""
    p.add_argument("--precision", default="auto", choices=PRECISIONS,
                   help="floating-point precision of the whole run (default: %(default)s, float32 "
                        "on a GPU and float64 elsewhere; float32 on GPUs was soaked and checked "
                        "against float64 over 32 seeds, benchmarks/RESULTS.md)")


def setup_jax(precision: str, autotune: bool = False, deterministic: bool = True,
              compilation_cache: str = "none") -> str:
    """Check XLA's GPU flags and set JAX's precision before the first computation; returns the
    precision used ("auto" resolved: float32 on a GPU, float64 elsewhere).

    The flags (``xla_flags.with_cli_flags``: autotuning off unless ``autotune``, deterministic
    GPU kernels if ``deterministic``; XLA_FLAGS already naming a flag wins) must be in XLA_FLAGS
    before JAX is imported, which ``import experiments`` does for the command line's arguments.
    Raises RuntimeError on a GPU where they came after JAX's import: XLA would not see them (a
    CPU ignores them).
    """
    import jax

    current = os.environ.get("XLA_FLAGS", "").strip()
    wanted = xla_flags.with_cli_flags(current, autotune, deterministic)
    late = f"{xla_flags.added_after_jax} {wanted[len(current):]}".strip()
    os.environ["XLA_FLAGS"] = wanted
    if compilation_cache != "none":
        jax.config.update("jax_compilation_cache_dir", compilation_cache)
        # Every program, not only those compiling for a second or more (JAX's default): a warm
        # run's small programs (keys, checks, the stability's Jacobians) then load instead of
        # compiling, each a tenth of a second or more beside the other runs (RESULTS.md,
        # twenty-sixth session).
        jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    backend = jax.default_backend()  # starts the backend
    if late and backend == "gpu":
        raise RuntimeError(f"XLA_FLAGS got {late!r} after JAX was imported, so XLA on the GPU does "
                           "not see it: import experiments before jax, or start the process with "
                           f"XLA_FLAGS={wanted!r}")
    if precision == "auto":
        precision = "float32" if backend == "gpu" else "float64"
    jax.config.update("jax_enable_x64", precision == "float64")
    return precision


def host_cpu(cpuinfo: str | None = None) -> dict:
    """The host CPU as ``config.json`` records it: {"model": model name, "family", "model_number",
    "avx512": bool} from Linux's /proc/cpuinfo (``cpuinfo``: that file's text, for tests), or
    {"model": platform.processor()} where there is none.

    XLA:CPU compiles for the host's vector instructions, so float64 round-off, and what training
    amplifies from it, can differ between CPU families (benchmarks/RESULTS.md, twenty-first
    session): records are comparable bit for bit only between runs on the same CPU."""
    if cpuinfo is None:
        try:
            cpuinfo = pathlib.Path("/proc/cpuinfo").read_text()
        except OSError:
            return {"model": platform.processor() or platform.machine()}
    first = {}
    for line in cpuinfo.splitlines():
        if not line.strip():
            if first:
                break  # the first processor's block describes the CPU
            continue
        key, _, value = line.partition(":")
        first.setdefault(key.strip(), value.strip())
    return {"model": first.get("model name", platform.processor() or platform.machine()),
            "family": first.get("cpu family"), "model_number": first.get("model"),
            "avx512": any(flag.startswith("avx512") for flag in first.get("flags", "").split())}


def _stop_on_signals(scheduler: runner.Scheduler):
    """Ctrl-C / SIGTERM: the runs finish the iteration in flight and write its checkpoint; a
    second Ctrl-C aborts at once."""
    def handler(signum, frame):
        print(f"\n{signal.Signals(signum).name}: stopping after the iteration in flight "
              "(Ctrl-C again aborts without its checkpoint)", file=sys.stderr, flush=True)
        scheduler.request_stop()
        signal.signal(signal.SIGINT, signal.default_int_handler)
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, handler)


def program_store(args) -> ProgramStore | None:
    """The study's program store: beside the compilation cache (``DIR_programs``), unless that
    is off or ``--no-program-store``."""
    if args.compilation_cache == "none" or not args.program_store:
        return None
    cache = pathlib.Path(args.compilation_cache).expanduser().resolve()
    return ProgramStore(cache.parent / (cache.name + "_programs"))


def _devices_and_compiler_options(args) -> list:
    """The devices the study uses; also settles XLA's compiler options for its programs
    (``sharding.compiler_options``, cached: a first compilation on the device)."""
    import jax

    used = jax.local_devices()[: args.devices or len(jax.local_devices())]
    sharding.compiler_options(sharding.seeds_per_device(args.seeds, len(used)))
    return used


def run_study(args, t_start: float) -> int:
    """Train, evaluate and report (the part of ``main`` after the arguments)."""
    import jax

    out = pathlib.Path(args.out)
    if not args.resume:
        runner.check_fresh([runner.run_folder(out, *key) for key in args.configs])
    # The compiler options are probed (a first compilation) in a thread while this one imports
    # the reporting code (SciPy): the one waits on XLA, the other holds the GIL
    # (benchmarks/RESULTS.md, twenty-third session).
    with concurrent.futures.ThreadPoolExecutor(1) as pool:
        devices = pool.submit(_devices_and_compiler_options, args)
        from experiments import report
        used = devices.result()
    out.mkdir(parents=True, exist_ok=True)
    seeds = list(range(args.first_seed, args.first_seed + args.seeds))
    store = program_store(args)
    device = f"{used[0].platform}: {used[0].device_kind}" + (f" × {len(used)}" if len(used) > 1 else "")
    on_cpu = [f"{s}/{a}" for (s, a) in args.configs if (s, a) in args.platforms]
    if on_cpu:
        device += f"; {', '.join(on_cpu)} on the host CPU"
    apart = [f"{s}/{a}" for (s, a) in args.gpu_processes]
    if apart:
        device += f"; {', '.join(apart)} in a process of {'its' if len(apart) == 1 else 'their'} own"
    if args.mps_state:
        device += "; under CUDA MPS"
    print(f"gmr-jax {args.task.name} study -> {out}  (device {device}, seeds {seeds})")
    (out / "config.json").write_text(json.dumps({
        "command": " ".join([f"python -m experiments.{args.task.name}"] + list(args.argv)),
        "seeds": seeds, "device": device, "precision": args.precision,
        "compilation_cache": args.compilation_cache, "compile_jobs": args.compile_jobs,
        "checkpoint_every": args.checkpoint_every,
        "program_store": None if store is None else str(store.directory),
        "XLA_FLAGS": os.environ.get("XLA_FLAGS", ""),
        "compiler_options": sharding.compiler_options(sharding.seeds_per_device(args.seeds, len(used))),
        # GMR's packed S-step traced with its products as reductions (sharding.seed_block)
        "gmr_products_as_reductions": sharding.reduced_products_for(
            sharding.seeds_per_device(args.seeds, len(used)), used[0].platform),
        # per run, where the packed S-step evaluates its statistics (SStepConfig.statistics as
        # resolved for the run's platform; the reference form, a CPU's, does so in every step)
        "sstep_statistics": {f"{s}/{a}": sstep.resolve_statistics(
            c.sstep.statistics, sharding.seeds_per_device(args.seeds, len(used)),
            args.platforms.get((s, a), used[0].platform)) for (s, a), c in args.configs.items()},
        # per run: its iteration compiled as one program, in parts, or in parts some of which run
        # on the host (--iteration-programs)
        "iteration_programs": {f"{s}/{a}": _iteration_programs(args, s, a, c, used)
                               for (s, a), c in args.configs.items()},
        "cpu_runs": on_cpu,
        "cpu_runs_in_process": bool(on_cpu) and args.cpu_runs_in_process,
        # runs on the GPU trained in a process of their own (--gpu-runs-in-process)
        "gpu_runs_in_process": apart,
        # --mps: "started" (a private MPS daemon for this command), "running" (one was already running) or null
        "mps": args.mps_state,
        # niceness of the runs in processes of their own on the GPU (--process-niceness)
        "process_niceness": {f"{s}/{a}": n for (s, a), n in args.niceness.items()},
        "host_cpu": host_cpu(),
        "python": platform.python_version(),
        "jax": jax.__version__,
        "runs": {f"{s}/{a}": config.to_dict(c) for (s, a), c in args.configs.items()}}, indent=2))
    for (scenario, algorithm), cfg in args.configs.items():
        print(f"[{scenario} / {algorithm}] {cfg.iterations} iterations, {cfg.num_samples} samples, "
              f"T={cfg.task.T}, {len(seeds)} seed(s)", flush=True)
    with (runner.Scheduler(args.compile_jobs, args.devices, iteration_programs=args.iteration_programs,
                           program_store=store) as scheduler, contextlib.ExitStack() as stack):
        _stop_on_signals(scheduler)
        figures = None if args.no_plots else report.figure_workers()
        if figures is not None:  # on an error too: the figures not yet drawn are dropped
            stack.callback(figures.shutdown, wait=True, cancel_futures=True)
        plotting = None if args.no_plots or figures else scheduler.pool.submit(report.preload_plotting)
        t_runs = time.perf_counter()
        timeline.mark("runs start")
        runs = runner.run_all(args.configs, seeds, out, resume=args.resume, jobs=args.jobs,
                              scheduler=scheduler, progress_fn=progress_printer(len(args.configs) > 1),
                              stability=not args.no_stability, platforms=args.platforms,
                              processes=process_runs(args), niceness=args.niceness,
                              checkpoint_every=args.checkpoint_every)
        total = time.perf_counter() - t_runs
        timeline.mark("runs done")
        if not args.no_plots:
            if plotting is not None:
                plotting.result()
            report.plot_all(out, args.configs, runs, figures)
            timeline.mark("figures drawn")
    results = report.write_results(out, args.configs, runs, seeds, device, total,
                                   command_s=time.perf_counter() - t_start, start_s=t_runs - t_start)
    timeline.mark("results written")
    report.write_summary(out / "summary.md", args.configs, runs, seeds, device, total, results)
    print((out / "summary.md").read_text())
    write_pictures(args, out)
    timeline.mark("command end")
    return 0


def write_pictures(args, out: pathlib.Path) -> None:
    """The policy runs' still-frame grid ``frames.png`` (unless ``--no-plots``) and, with
    ``--video``, their MP4s (``experiments.video``); where MuJoCo cannot render, one line on
    stderr instead (the study's results are complete without them)."""
    if args.no_plots and not args.video:
        return
    names = [runner.run_folder(out, s, a).name for s, a in args.configs if a != "lqr"]
    if not names:
        return
    t0 = time.perf_counter()
    from experiments import video
    from gmr_jax import render

    try:
        files = video.write(out, names, video=args.video)
    except render.RenderingUnavailable as err:
        print(f"No rollout pictures: {err}", file=sys.stderr)
        return
    print(f"Rollout pictures ({time.perf_counter() - t0:.1f} s): " + ", ".join(str(f) for f in files))


def main(task_name: str, argv=None, description: str | None = None, t_start: float | None = None) -> int:
    """``python -m experiments.<task_name>``: returns the exit code."""
    t_start = time.perf_counter() if t_start is None else t_start
    argv = list(sys.argv[1:] if argv is None else argv)
    args = parse_args(task_name, argv, description, start_daemons=True)
    timeline.mark("arguments read")
    try:
        return _main(task_name, args, argv, t_start)
    finally:
        stop_mps(args)


def _main(task_name: str, args, argv: list, t_start: float) -> int:
    args.argv = argv
    if process_runs(args):
        process_server.start()  # it imports while this process prepares the runs (if not yet started)
    prog = f"python -m experiments.{task_name}"
    args.precision = setup_jax(args.precision, args.autotune, not args.nondeterministic,
                               args.compilation_cache)
    if args.precision != "float64" and any(c.float32_stages for c in args.configs.values()):
        print(f"{prog}: error: --set float32_stages runs stages of a float64 run in float32: "
              f"add --precision float64 (this run is {args.precision})", file=sys.stderr)
        return 2
    try:
        return run_study(args, t_start)
    except runner.Interrupted as err:
        print(f"{prog}: interrupted: {err}. Continue with: {prog} {' '.join(argv)}"
              f"{'' if args.resume else ' --resume'}", file=sys.stderr)
        return EXIT_INTERRUPTED
    except KeyboardInterrupt:
        print(f"{prog}: aborted; the checkpoints written before are intact (--resume continues)",
              file=sys.stderr)
        return EXIT_INTERRUPTED
    except (runner.FolderTaken, runner.TrainingError, checkpoint.CheckpointError, MJCFError,
            FileNotFoundError, OSError, ValueError) as err:
        if args.debug:
            traceback.print_exc()
        print(f"{prog}: error: {err}", file=sys.stderr)
        return EXIT_USAGE if isinstance(err, runner.FolderTaken) else EXIT_FAILED

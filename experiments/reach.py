"""The reaching study on the simulated Jaco 2: ``python -m experiments.reach``.

Trains the chosen algorithms on the chosen scenarios for several seeds in parallel (``jax.vmap``
over PRNG keys), one jitted iteration at a time so that progress is shown and the whole training
state is checkpointed after every iteration (``--resume`` continues an interrupted run and reaches
the same result as an uninterrupted one). Writes into ``--out``: ``config.json``,
``results.json``, ``summary.md``, ``learning_curves.png``, ``paths.png`` and ``checkpoints/``.
"""

from __future__ import annotations

import time

_T_START = time.perf_counter()  # before the heavy imports: the command's total wall time

import argparse
import ast
import concurrent.futures
import contextlib
import json
import os
import pathlib
import platform
import sys
import threading

import jax
import jax.numpy as jnp
import numpy as np

from experiments import report
from gmr_jax import checkpoint, config, evaluate, mdgps

DEFAULT_ALGORITHMS = "gmr,mdgps"
DEFAULT_SCENARIOS = "A,AB"
SWEEP_RADII = (0.0, 0.25, 0.5, 1.0, 1.5, 2.0, 3.0)  # rad, disturbance of the training joint angles
SWEEP_PER_RADIUS = 10
# Fewest parallel rollouts for which "auto" picks MJX on a GPU. On an H100 in float64 a call of
# 10 rollouts took 0.11 s with C MuJoCo against 0.18 s with MJX, 60 rollouts 0.26 s against
# 0.17 s (benchmarks/RESULTS.md): MJX costs about the same for any batch, C MuJoCo grows with it.
MJX_MIN_ROLLOUTS = 32
# Iteration programs compiled at once (--compile-jobs). The default run (4 programs) took 97.7 s
# with 2 and 96.3/98.3 s with 4 on an H100 (cold), and 312 s with 2 against 331 s with 4 on the
# 2-core CPU (benchmarks/RESULTS.md).
DEFAULT_COMPILE_JOBS = 2
DEFAULT_COMPILATION_CACHE = os.environ.get("JAX_COMPILATION_CACHE_DIR") or str(
    pathlib.Path("~/.cache/gmr_jax/xla").expanduser())


def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(prog="python -m experiments.reach", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--algorithm", default=DEFAULT_ALGORITHMS,
                   help=f"comma-separated list of {config.ALGORITHMS} (default: %(default)s)")
    p.add_argument("--scenario", default=DEFAULT_SCENARIOS,
                   help=f"comma-separated list of {tuple(config.SCENARIOS)} (default: %(default)s)")
    p.add_argument("--iterations", type=int, default=config.Config.iterations,
                   help="GPS iterations (default: %(default)s)")
    p.add_argument("--samples", type=int, default=config.Config.num_samples,
                   help="samples per condition per iteration (default: %(default)s)")
    p.add_argument("--seeds", type=int, default=1, help="seeds trained in parallel (default: 1)")
    p.add_argument("--first-seed", type=int, default=0, help="first seed (default: 0)")
    p.add_argument("--T", type=int, default=config.TaskConfig.T, help="horizon (default: %(default)s)")
    p.add_argument("--backend", default="auto", choices=("auto", "mjx", "mujoco"),
                   help="physics backend (default: %(default)s: C MuJoCo on a CPU; on a GPU, MJX "
                        f"when a rollout batch holds at least {MJX_MIN_ROLLOUTS} rollouts (seeds × "
                        "conditions × samples), C MuJoCo below that, where MJX's per-step latency "
                        "dominates; the choice is written to config.json)")
    p.add_argument("--out", default="results/reach", help="output folder (default: %(default)s)")
    p.add_argument("--resume", action="store_true",
                   help="continue from the checkpoints in --out (same settings required)")
    p.add_argument("--precision", default="float64", choices=("float32", "float64"),
                   help="floating-point precision of the whole run (default: %(default)s; float32 "
                        "can make the dynamics fit fail on GPUs, see benchmarks/RESULTS.md)")
    p.add_argument("--no-plots", action="store_true", help="skip the PNG figures")
    p.add_argument("--jobs", type=int, default=0,
                   help="runs (scenario × algorithm) trained side by side: they compile concurrently "
                        "and share the device (default 0: all of them)")
    p.add_argument("--compile-jobs", type=int, default=DEFAULT_COMPILE_JOBS,
                   help="iteration programs compiled at once (default: %(default)s). XLA spreads "
                        "one compilation over the cores, so more at once mostly slow each other")
    p.add_argument("--autotune", action="store_true",
                   help="let XLA time kernel variants on the GPU while compiling. Off by default: "
                        "runs that compile while others train make those timings slow and noisy, "
                        "and kernels chosen by timing make results differ from call to call")
    p.add_argument("--compilation-cache", default=DEFAULT_COMPILATION_CACHE, metavar="DIR",
                   help="persistent XLA compilation cache: a repeated run skips most of its "
                        "compilation (default: $JAX_COMPILATION_CACHE_DIR or %(default)s; "
                        "'none' disables it)")
    p.add_argument("--set", action="append", default=[], metavar="GROUP__FIELD=VALUE",
                   help="override a configuration field for every run, e.g. --set gmr__alpha=0.1 "
                        "or --set sstep__epochs=100 (repeatable; values are Python literals)")
    args = p.parse_args(argv)
    args.overrides = {}
    for item in args.set:
        name, sep, text = item.partition("=")
        if not sep or not name.strip():
            p.error(f"--set {item!r}: expected GROUP__FIELD=VALUE")
        try:
            value = ast.literal_eval(text)
        except (ValueError, SyntaxError):
            value = text  # a bare word, e.g. --set gmr__exploration=fixed
        args.overrides[name.strip()] = value
    args.algorithms = [a.strip() for a in args.algorithm.split(",") if a.strip()]
    args.scenarios = [s.strip() for s in args.scenario.split(",") if s.strip()]
    for a in args.algorithms:
        if a not in config.ALGORITHMS:
            p.error(f"--algorithm {a!r}: allowed values are {config.ALGORITHMS}")
    for s in args.scenarios:
        if s not in config.SCENARIOS:
            p.error(f"--scenario {s!r}: allowed values are {tuple(config.SCENARIOS)}")
    if args.compile_jobs < 1:
        p.error(f"--compile-jobs must be a positive integer, got {args.compile_jobs}")
    if args.jobs < 0:
        p.error(f"--jobs must be ≥ 0 (0: automatic), got {args.jobs}")
    for name in ("iterations", "samples", "seeds", "T"):
        if getattr(args, name) < 1:
            p.error(f"--{name} must be a positive integer, got {getattr(args, name)}")
    if args.samples < 2:
        p.error("--samples must be at least 2 (the dynamics fit needs two samples)")
    return args


def resolve_backend(args) -> str:
    """The physics backend of ``--backend`` for this run: "auto" becomes "mujoco" on a CPU, and
    on a GPU "mjx" when the sampling batch (seeds × conditions × samples, the largest of the
    scenarios) reaches ``MJX_MIN_ROLLOUTS``, else "mujoco"."""
    if args.backend != "auto":
        return args.backend
    if jax.default_backend() != "gpu":
        return "mujoco"
    conditions = max(config.reach(s, "lqr").task.num_conditions for s in args.scenarios)
    return "mjx" if args.seeds * conditions * args.samples >= MJX_MIN_ROLLOUTS else "mujoco"


def make_config(args, scenario: str, algorithm: str) -> config.Config:
    base = dict(iterations=args.iterations, num_samples=args.samples, task__T=args.T,
                sim__backend=resolve_backend(args))
    clash = sorted(set(base) & set(args.overrides))
    if clash:
        raise SystemExit(f"--set {clash}: use the dedicated command-line options for these")
    try:
        return config.reach(scenario, algorithm, **base, **args.overrides)
    except (ValueError, TypeError) as err:
        raise SystemExit(f"--set: {err}") from None


def _host(tree):
    return jax.tree_util.tree_map(np.asarray, tree)


def _format_progress(it: int, total: int, m: dict) -> str:
    def mean(name):
        return float(np.mean(m[name])) if name in m else float("nan")
    line = (f"  iter {it:2d}/{total}  cost {mean('sample_cost'):10.3f}  KL {mean('kl'):8.3f}"
            f"  eps {mean('epsilon'):7.2f}  eta {mean('eta'):9.3g}  step {mean('step_mult'):6.3f}"
            f"  mse(lqr) {mean('final_state_mse_lqr'):.4g}")
    if "final_state_mse_policy" in m:
        line += f"  mse(policy) {mean('final_state_mse_policy'):.4g}"
    return line


# One jitted function each for the whole process, so that repeated and resumed runs of the same
# configuration reuse the compiled executables instead of compiling them again. The first-iteration
# flag is a run-time scalar shared by all seeds: one program serves every iteration (compiling
# is most of a short run's time on a GPU).
init_fn = jax.jit(jax.vmap(mdgps.init, in_axes=(None, 0)), static_argnums=0)
step_fn = jax.jit(jax.vmap(mdgps.iteration, in_axes=(None, 0, 0, None)), static_argnums=0)


class _Timer(dict):
    """Wall seconds per phase name (``with timer("compile"): ...``); repeated phases add up."""

    def __call__(self, name: str):
        timer = self

        class _Phase:
            def __enter__(self):
                self.t = time.perf_counter()

            def __exit__(self, *exc):
                timer[name] = timer.get(name, 0.0) + time.perf_counter() - self.t
        return _Phase()


# Compiled iteration programs of this process, per (config, number of seeds): a resumed or
# repeated run of the same configuration reuses its executable.
_compiled: dict = {}


class _TracingTurns:
    """Side-by-side runs trace one at a time, in the order of their tickets.

    Tracing and lowering are Python work under the GIL: concurrent traces only delay each other.
    One at a time, the first run's compilation (which releases the GIL) starts sooner, and with
    tickets the runs that train longest go first. ``ticket=None`` only excludes the others.
    """

    def __init__(self):
        self._cv = threading.Condition()
        self._next = 0
        self._busy = False

    def reset(self):
        with self._cv:
            self._next = 0

    @contextlib.contextmanager
    def __call__(self, ticket: int | None):
        with self._cv:
            self._cv.wait_for(lambda: not self._busy and (ticket is None or self._next == ticket))
            self._busy = True
        try:
            yield
        finally:
            with self._cv:
                self._busy = False
                if ticket is not None:
                    self._next += 1
                self._cv.notify_all()


_tracing = _TracingTurns()
# Iteration programs compiled at once. XLA's GPU compiler spreads one compilation over the cores,
# so a dozen at once only slow each other down; the runs that trace first (the longest) compile
# first, and each run's robustness program compiles after its iteration program.
_compile_slots = threading.BoundedSemaphore(DEFAULT_COMPILE_JOBS)


def set_compile_jobs(n: int) -> None:
    """Let ``n`` iteration programs compile at once (``--compile-jobs``)."""
    global _compile_slots
    _compile_slots = threading.BoundedSemaphore(n)


def lower_iteration(cfg: config.Config, state, keys, timer: _Timer):
    """``step_fn`` for ``cfg`` and this seed batch, traced and lowered (``state``: the batched
    TrainState, arrays or ``ShapeDtypeStruct``s; ``keys``: [seeds] iteration keys), or the
    compiled program if this process has one already. The phases are timed separately."""
    key = (cfg, keys.shape[0])
    if key in _compiled:
        return _compiled[key]
    with timer("trace_s"):
        traced = step_fn.trace(cfg, state, keys, jnp.asarray(True))
    with timer("lower_s"):
        return traced.lower()


def compile_iteration(cfg: config.Config, state, keys, timer: _Timer, lowered=None):
    """The compiled ``step_fn`` for ``cfg`` and this seed batch (see :func:`lower_iteration`;
    ``lowered``: its result, if already at hand)."""
    program = lower_iteration(cfg, state, keys, timer) if lowered is None else lowered
    if isinstance(program, jax.stages.Lowered):
        with _compile_slots, timer("compile_s"):
            program = _compiled[(cfg, keys.shape[0])] = program.compile()
    return program


def run_one(cfg: config.Config, seeds: list[int], run_dir: pathlib.Path, resume: bool,
            stop_after: int | None = None, label: str = "", ticket: int | None = None) -> dict:
    """Train ``cfg`` for ``seeds`` in parallel; checkpoint after every iteration.

    ``stop_after`` ends the loop after that many iterations (as an interruption would); a later
    call with ``resume=True`` continues from the checkpoint. ``label`` prefixes the progress
    lines (runs may execute side by side). ``ticket``: this run's place in the order in which
    side-by-side runs trace their programs (0, 1, …; None: any order).

    Returns:
      dict with the stacked metrics history (leading axes [iteration, seed, ...]), ``wall_s``
      and ``timing``: seconds per phase (init, trace, lower, compile, iterations, checkpoints,
      and for policies the robustness evaluation's trace/lower/compile/run).
    """
    run_dir.mkdir(parents=True, exist_ok=True)
    keys = jnp.stack([jax.random.PRNGKey(s) for s in seeds])
    k_init, it_keys = jax.vmap(lambda k: mdgps.iteration_keys(k, cfg.iterations))(keys)
    ckpt_dir = run_dir / "checkpoints"
    meta = {"config": config.to_dict(cfg), "seeds": list(seeds)}

    t0 = time.perf_counter()
    timer = _Timer()

    def initial_state():
        with timer("init_s"):
            return jax.block_until_ready(init_fn(cfg, k_init))
    state_future = _background.submit(initial_state)
    state, history, start = None, [], 0
    stop = cfg.iterations if stop_after is None else min(stop_after, cfg.iterations)
    lowered_step = lowered_robustness = None
    with _tracing(ticket):
        if resume and checkpoint.latest(ckpt_dir) is not None:  # validated before compiling
            state, saved = checkpoint.restore(ckpt_dir, state_future.result(),
                                              expect=report.jsonable(meta))
            history = [{k: np.asarray(v) for k, v in h.items()} for h in saved["history"]]
            start = len(history)
            print(f"{label}  resumed from iteration {start}", flush=True)
        # The programs are built from the state's shapes while init compiles and runs beside them.
        shapes = jax.eval_shape(lambda k: init_fn(cfg, k), k_init)
        if start < stop:
            lowered_step = lower_iteration(cfg, shapes, it_keys[:, 0], timer)
        if mdgps.uses_policy(cfg) and stop == cfg.iterations:
            lowered_robustness = lower_robustness(cfg, shapes.policy, timer)
    if lowered_step is not None:
        step = compile_iteration(cfg, shapes, it_keys[:, 0], timer, lowered_step)
    robustness = None if lowered_robustness is None else compile_robustness(lowered_robustness, timer)
    if state is None:
        state = state_future.result()
    iteration_s = []

    def save(done: int, st, hist):
        with timer("checkpoint_s"):
            checkpoint.save(ckpt_dir, st, step=done,
                            metadata={**meta, "history": [report.jsonable(h) for h in hist]})

    # Each iteration's checkpoint is written while the next iteration runs on the device (the
    # call below returns before the device has finished); an exception or an interruption still
    # writes the last finished iteration's checkpoint.
    pending = None
    try:
        for it in range(start, stop):
            t_it = time.perf_counter()
            if it == start:  # the run's start-up (waits for its turns and slots included)
                timer["training_start_s"] = t_it - t0
            new_state, metrics = step(state, it_keys[:, it], jnp.asarray(it == 0))
            if pending is not None:
                save(*pending)
                pending = None
            metrics = _host(metrics)
            iteration_s.append(time.perf_counter() - t_it)
            if not np.all(metrics["ok"]):
                bad = np.argwhere(~np.asarray(metrics["ok"]))
                raise FloatingPointError(
                    f"iteration {it + 1}: the C-step failed (non-finite controller or η reached "
                    f"max_eta) for (seed index, condition) {bad.tolist()}")
            state = new_state
            history.append(metrics)
            pending = (it + 1, state, list(history))
            print(label + _format_progress(it + 1, cfg.iterations, metrics), flush=True)
    finally:
        if pending is not None:
            save(*pending)
    timer["iterations_s"] = float(np.sum(iteration_s))
    stacked = {k: np.stack([np.asarray(h[k]) for h in history]) for k in history[0]} if history else {}
    result = {"history": stacked, "iteration_s": iteration_s}
    if mdgps.uses_policy(cfg) and len(history) == cfg.iterations:
        result.update(evaluate_robustness(cfg, state.policy, timer, robustness))
    result["wall_s"] = time.perf_counter() - t0
    result["timing"] = dict(timer)
    return result


def _robustness_fn(cfg: config.Config):
    def both(p):  # the fixed random states and the disturbance sweep: one program
        return (evaluate.robustness(cfg, p),
                evaluate.disturbance_sweep(cfg, p, SWEEP_RADII, SWEEP_PER_RADIUS)[:2])
    return jax.jit(jax.vmap(both))


def lower_robustness(cfg: config.Config, params, timer: _Timer):
    """The robustness program for ``params`` (arrays or ``ShapeDtypeStruct``s with a leading
    seed axis), traced and lowered."""
    with timer("robustness_trace_s"):
        traced = _robustness_fn(cfg).trace(params)
    with timer("robustness_lower_s"):
        return traced.lower()


def compile_robustness(lowered, timer: _Timer):
    """Compile a lowered robustness program in a background thread (a run compiles it while it
    trains); returns a future of the compiled program."""
    def compile_():
        with timer("robustness_compile_s"):
            return lowered.compile()
    return _background.submit(compile_)


_background = concurrent.futures.ThreadPoolExecutor(max_workers=8, thread_name_prefix="compile")


def evaluate_robustness(cfg: config.Config, params, timer: _Timer | None = None,
                        compiled=None) -> dict:
    """Robustness of every seed's policy (leading seed axis of ``params``): the fixed random
    states and the disturbance sweep. ``compiled``: a future from :func:`compile_robustness`
    (default: compile here)."""
    timer = _Timer() if timer is None else timer
    if compiled is None:
        with _tracing(None):
            lowered = lower_robustness(cfg, params, timer)
        compiled = compile_robustness(lowered, timer)
    with timer("robustness_wait_s"):
        program = compiled.result()
    with timer("robustness_run_s"):
        rob, (rate, rate_loose) = _host(program(params))
    return {"robustness": rob._asdict(), "sweep": {"radii": list(SWEEP_RADII),
            "success_rate": np.asarray(rate), "success_rate_loose": np.asarray(rate_loose)}}


def run_folder(out: pathlib.Path, scenario: str, algorithm: str) -> pathlib.Path:
    """The folder of one run (its checkpoints) inside ``--out``."""
    return out / f"{scenario}_{algorithm}"


def main(argv=None) -> int:
    args = parse_args(argv)
    flags = os.environ.get("XLA_FLAGS", "")
    if not args.autotune and "xla_gpu_autotune_level" not in flags:
        # Read when the backend starts (the first device query below), so set before it.
        os.environ["XLA_FLAGS"] = f"{flags} --xla_gpu_autotune_level=0".strip()
    jax.config.update("jax_enable_x64", args.precision == "float64")
    if args.compilation_cache != "none":
        jax.config.update("jax_compilation_cache_dir", args.compilation_cache)
    out = pathlib.Path(args.out)
    configs = {(s, a): make_config(args, s, a) for s in args.scenarios for a in args.algorithms}
    if not args.resume:
        # Checked before anything is written or compiled: a fresh run never replaces a run's files.
        taken = [str(run_folder(out, *key) / "checkpoints") for key in configs
                 if checkpoint.latest(run_folder(out, *key) / "checkpoints") is not None]
        if taken:
            print(f"python -m experiments.reach: error: --out {out} already holds checkpoints "
                  f"({', '.join(taken)}); pass --resume to continue those runs, or choose another "
                  "--out", file=sys.stderr)
            return 2
    out.mkdir(parents=True, exist_ok=True)
    seeds = list(range(args.first_seed, args.first_seed + args.seeds))
    device = f"{jax.devices()[0].platform}: {jax.devices()[0].device_kind}"
    print(f"gmr-jax reach study -> {out}  (device {device}, seeds {seeds})")
    if not args.no_plots:
        plotting = _background.submit(report.preload_plotting)
    (out / "config.json").write_text(json.dumps({
        "command": " ".join(["python -m experiments.reach"] + list(sys.argv[1:] if argv is None else argv)),
        "seeds": seeds, "device": device, "precision": args.precision,
        "compilation_cache": args.compilation_cache, "compile_jobs": args.compile_jobs,
        "XLA_FLAGS": os.environ.get("XLA_FLAGS", ""), "python": platform.python_version(),
        "jax": jax.__version__,
        "runs": {f"{s}/{a}": config.to_dict(c) for (s, a), c in configs.items()}}, indent=2))
    jobs = args.jobs or len(configs)
    for (scenario, algorithm), cfg in configs.items():
        print(f"[{scenario} / {algorithm}] {cfg.iterations} iterations, {cfg.num_samples} samples, "
              f"T={cfg.task.T}, {len(seeds)} seed(s)", flush=True)
    if jobs > 1:
        print(f"{min(jobs, len(configs))} runs side by side", flush=True)
    set_compile_jobs(args.compile_jobs)
    t_all = time.perf_counter()
    # Side by side, the runs' XLA compilations (most of a short GPU run) use several CPU cores and
    # their iterations interleave on the device; progress lines carry the run's name.
    with concurrent.futures.ThreadPoolExecutor(max_workers=jobs) as pool:
        # The longest runs (GMR's S-step is the slowest, and more conditions mean more data)
        # start first: they trace first and reach the device first.
        order = sorted(configs, key=lambda k: (configs[k].algorithm != "gmr",
                                               -configs[k].task.num_conditions))
        _tracing.reset()
        futures = {key: pool.submit(run_one, configs[key], seeds, run_folder(out, *key),
                                    args.resume, label=f"[{key[0]}/{key[1]}]" if len(configs) > 1 else "",
                                    ticket=i)
                   for i, key in enumerate(order)}
        runs = {key: futures[key].result() for key in configs}
    total = time.perf_counter() - t_all
    if not args.no_plots:
        plotting.result()
        report.plot_learning_curves(out / "learning_curves.png", configs, runs)
        report.plot_paths(out / "paths.png", configs, runs)
        report.plot_robustness(out / "robustness.png", configs, runs)
    results = report.write_results(out, configs, runs, seeds, device, total,
                                   command_s=time.perf_counter() - _T_START)
    report.write_summary(out / "summary.md", configs, runs, seeds, device, total, results)
    print((out / "summary.md").read_text())
    return 0


if __name__ == "__main__":
    sys.exit(main())

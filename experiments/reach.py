"""The reaching study on the simulated Jaco 2: ``python -m experiments.reach``.

Trains the chosen algorithms on the chosen scenarios for several seeds in parallel (``jax.vmap``
over PRNG keys), one jitted iteration at a time so that progress is shown and the whole training
state is checkpointed after every iteration (``--resume`` continues an interrupted run and reaches
the same result as an uninterrupted one). Writes into ``--out``: ``config.json``,
``results.json``, ``summary.md``, ``learning_curves.png``, ``paths.png`` and ``checkpoints/``.
"""

from __future__ import annotations

import argparse
import ast
import concurrent.futures
import dataclasses
import json
import pathlib
import platform
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

from experiments import report
from gmr_jax import checkpoint, config, evaluate, mdgps

DEFAULT_ALGORITHMS = "gmr,mdgps"
DEFAULT_SCENARIOS = "A,AB"
SWEEP_RADII = (0.0, 0.25, 0.5, 1.0, 1.5, 2.0, 3.0)  # rad, disturbance of the training joint angles
SWEEP_PER_RADIUS = 10


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
    p.add_argument("--backend", default=config.SimConfig.backend, choices=("auto", "mjx", "mujoco"),
                   help="physics backend (default: %(default)s)")
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
    if args.jobs < 0:
        p.error(f"--jobs must be ≥ 0 (0: automatic), got {args.jobs}")
    for name in ("iterations", "samples", "seeds", "T"):
        if getattr(args, name) < 1:
            p.error(f"--{name} must be a positive integer, got {getattr(args, name)}")
    if args.samples < 2:
        p.error("--samples must be at least 2 (the dynamics fit needs two samples)")
    return args


def make_config(args, scenario: str, algorithm: str) -> config.Config:
    base = dict(iterations=args.iterations, num_samples=args.samples, task__T=args.T,
                sim__backend=args.backend)
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


def run_one(cfg: config.Config, seeds: list[int], run_dir: pathlib.Path, resume: bool,
            stop_after: int | None = None, label: str = "") -> dict:
    """Train ``cfg`` for ``seeds`` in parallel; checkpoint after every iteration.

    ``stop_after`` ends the loop after that many iterations (as an interruption would); a later
    call with ``resume=True`` continues from the checkpoint. ``label`` prefixes the progress
    lines (runs may execute side by side).

    Returns:
      dict with the stacked metrics history (leading axes [iteration, seed, ...]) and timing.
    """
    run_dir.mkdir(parents=True, exist_ok=True)
    keys = jnp.stack([jax.random.PRNGKey(s) for s in seeds])
    k_init, it_keys = jax.vmap(lambda k: mdgps.iteration_keys(k, cfg.iterations))(keys)
    ckpt_dir = run_dir / "checkpoints"
    meta = {"config": config.to_dict(cfg), "seeds": list(seeds)}

    t0 = time.perf_counter()
    state = init_fn(cfg, k_init)
    history: list[dict] = []
    start = 0
    if resume and checkpoint.latest(ckpt_dir) is not None:
        state, saved = checkpoint.restore(ckpt_dir, state, expect=report.jsonable(meta))
        history = [{k: np.asarray(v) for k, v in h.items()} for h in saved["history"]]
        start = len(history)
        print(f"{label}  resumed from iteration {start}", flush=True)
    compile_s = None
    for it in range(start, cfg.iterations if stop_after is None else min(stop_after, cfg.iterations)):
        t_it = time.perf_counter()
        state, metrics = step_fn(cfg, state, it_keys[:, it], jnp.asarray(it == 0))
        metrics = _host(metrics)
        if compile_s is None:
            compile_s = time.perf_counter() - t_it
        if not np.all(metrics["ok"]):
            bad = np.argwhere(~np.asarray(metrics["ok"]))
            raise FloatingPointError(
                f"iteration {it + 1}: the C-step failed (non-finite controller or η reached max_eta) "
                f"for (seed index, condition) {bad.tolist()}")
        history.append(metrics)
        checkpoint.save(ckpt_dir, state, step=it + 1,
                        metadata={**meta, "history": [report.jsonable(h) for h in history]})
        print(label + _format_progress(it + 1, cfg.iterations, metrics), flush=True)
    wall = time.perf_counter() - t0
    stacked = {k: np.stack([np.asarray(h[k]) for h in history]) for k in history[0]} if history else {}
    result = {"history": stacked, "wall_s": wall, "first_iteration_s": compile_s}
    if mdgps.uses_policy(cfg) and len(history) == cfg.iterations:
        result.update(evaluate_robustness(cfg, state.policy))
    return result


def evaluate_robustness(cfg: config.Config, params) -> dict:
    """Robustness of every seed's policy (leading seed axis of ``params``): the fixed random
    states and the disturbance sweep."""
    def both(p):  # one program: one compilation
        return (evaluate.robustness(cfg, p),
                evaluate.disturbance_sweep(cfg, p, SWEEP_RADII, SWEEP_PER_RADIUS)[:2])
    rob, (rate, rate_loose) = jax.jit(jax.vmap(both))(params)
    return {"robustness": _host(rob._asdict()), "sweep": {"radii": list(SWEEP_RADII),
            "success_rate": np.asarray(rate), "success_rate_loose": np.asarray(rate_loose)}}


def main(argv=None) -> int:
    args = parse_args(argv)
    jax.config.update("jax_enable_x64", args.precision == "float64")
    out = pathlib.Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    seeds = list(range(args.first_seed, args.first_seed + args.seeds))
    device = f"{jax.devices()[0].platform}: {jax.devices()[0].device_kind}"
    print(f"gmr-jax reach study -> {out}  (device {device}, seeds {seeds})")
    configs = {(s, a): make_config(args, s, a) for s in args.scenarios for a in args.algorithms}
    (out / "config.json").write_text(json.dumps({
        "command": " ".join(["python -m experiments.reach"] + list(sys.argv[1:] if argv is None else argv)),
        "seeds": seeds, "device": device, "precision": args.precision, "python": platform.python_version(), "jax": jax.__version__,
        "runs": {f"{s}/{a}": config.to_dict(c) for (s, a), c in configs.items()}}, indent=2))
    jobs = args.jobs or len(configs)
    for (scenario, algorithm), cfg in configs.items():
        print(f"[{scenario} / {algorithm}] {cfg.iterations} iterations, {cfg.num_samples} samples, "
              f"T={cfg.task.T}, {len(seeds)} seed(s)", flush=True)
    if jobs > 1:
        print(f"{min(jobs, len(configs))} runs side by side", flush=True)
    t_all = time.perf_counter()
    # Side by side, the runs' XLA compilations (most of a short GPU run) use several CPU cores and
    # their iterations interleave on the device; progress lines carry the run's name.
    with concurrent.futures.ThreadPoolExecutor(max_workers=jobs) as pool:
        futures = {key: pool.submit(run_one, cfg, seeds, out / f"{key[0]}_{key[1]}", args.resume,
                                    label=f"[{key[0]}/{key[1]}]" if len(configs) > 1 else "")
                   for key, cfg in configs.items()}
        runs = {key: f.result() for key, f in futures.items()}
    total = time.perf_counter() - t_all
    results = report.write_results(out, configs, runs, seeds, device, total)
    if not args.no_plots:
        report.plot_learning_curves(out / "learning_curves.png", configs, runs)
        report.plot_paths(out / "paths.png", configs, runs)
        report.plot_robustness(out / "robustness.png", configs, runs)
    report.write_summary(out / "summary.md", configs, runs, seeds, device, total, results)
    print((out / "summary.md").read_text())
    return 0


if __name__ == "__main__":
    sys.exit(main())

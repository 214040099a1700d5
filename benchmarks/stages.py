"""Where an MDGPS iteration's time goes, stage by stage, for many seeds at once.

The runner compiles an iteration (``mdgps.iteration``) as one program, so its stages cannot be
timed apart inside it. This benchmark runs the same stages (``mdgps.sample_stage``,
``cost_stage``, ``dynamics_stage``, ``anchor_stage``, ``step_size.update``, ``c_step``,
``s_step``, ``learning_curve``) as separate programs, each mapped over the seeds and split over
the devices as the runner maps an iteration (``sharding.seed_program``, the runner's compiler
options), on the real values of a training run, and times each one to completion. It also times
the whole iteration program on the same states and checks that the composed stages reproduce
its new state (the largest difference relative to the largest entry, reported per iteration),
so the breakdown is of the computation the runner does::

    python -m benchmarks.stages --algorithm gmr --scenario AB --seeds 1,256 --out stages.json

``--profile DIR`` runs the stages of one more iteration under JAX's profiler and lists each
stage's kernels (count, busy time, the costliest), assigned to stages by the host annotation
around each stage's run.

The first iteration runs the catch-up S-step inside the anchor stage and compiles every
program; later iterations are the steady state (``--iterations``, default 3). Separate programs
lose XLA's optimisations across stage boundaries and add one dispatch per stage, so the stages'
sum can differ a little from the whole iteration's time; both are reported.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time

import jax
import jax.numpy as jnp
import numpy as np

from benchmarks import trace
from experiments import cli
from gmr_jax import config, mdgps, policies, sharding, step_size, tasks
from gmr_jax.tasks import reach as reach_task

PROFILE_PREFIX = "stage "
"""The host annotation around each stage's run (``--profile``: kernels are assigned to stages by it)."""

STAGES = ("rollouts", "cost", "dynamics", "anchor", "step_size", "cstep", "sstep", "learning_curve")
"""The stages in the order an iteration runs them (``mdgps.iteration``)."""


def _in_precision(fn):
    """``fn`` traced under training's matrix-product precision (``mdgps.MATMUL_PRECISION``)."""
    def traced(*args):
        with jax.default_matmul_precision(mdgps.MATMUL_PRECISION):
            return fn(*args)
    return traced


def _rollouts(cfg, state, key, first):
    x0 = tasks.initial_states(cfg.task, state.eta.dtype)
    return mdgps.sample_stage(cfg, state, x0, key, first)


def _step_size(cfg, step_mult, first, prev, traj, model):
    return step_size.update(cfg.step, step_mult, first, prev, traj, model)


def _learning_curve(cfg, traj, policy, eta):
    return mdgps.learning_curve(cfg, traj, policy, tasks.initial_states(cfg.task, eta.dtype))


# name -> (fn(cfg, *args), which positional arguments after cfg carry the seed axis); the
# first-iteration flag is shared by all seeds, as in the runner's iteration program.
_PROGRAMS = {
    "rollouts": (_rollouts, (True, True, False)),
    "cost": (mdgps.cost_stage, (True,)),
    "dynamics": (mdgps.dynamics_stage, (True, True, True)),
    "anchor": (mdgps.anchor_stage, (True, True, False, True, True)),
    "step_size": (_step_size, (True, False, True, True, True)),
    "cstep": (mdgps.c_step, (True, True, True, True, True)),
    "sstep": (mdgps.s_step, (True, True, True, True, True)),
    "learning_curve": (_learning_curve, (True, True, True)),
}


class StageTimer:
    """Runs stages as separate seed-mapped programs on ``mesh``, compiling each once (lowering and
    compilation timed apart from the runs), and records the seconds of every run."""

    def __init__(self, cfg: config.Config, mesh, num_seeds: int):
        self.cfg, self.mesh, self.record = cfg, mesh, True
        self.options = sharding.compiler_options(sharding.seeds_per_device(num_seeds, mesh.size))
        self.compiled, self.compile_s, self.run_s = {}, {}, {}

    def __call__(self, name: str, *args):
        fn, batched = _PROGRAMS[name]
        if name not in self.compiled:
            t0 = time.perf_counter()
            program = sharding.seed_program(_in_precision(fn), self.mesh, batched)
            self.compiled[name] = program.lower(self.cfg, *args).compile(compiler_options=self.options or None)
            self.compile_s[name] = time.perf_counter() - t0
        with jax.profiler.TraceAnnotation(PROFILE_PREFIX + name):
            t0 = time.perf_counter()
            out = jax.block_until_ready(self.compiled[name](*args))
            seconds = time.perf_counter() - t0
        if self.record:
            self.run_s.setdefault(name, []).append(seconds)
        return out


def iteration_by_stages(cfg: config.Config, state: mdgps.TrainState, keys, first,
                        run) -> mdgps.TrainState:
    """``mdgps.iteration``'s new state, each stage run by ``run(name, *args)`` on seed-batched
    values (keys [S, 2]). The composition is ``mdgps.update``'s, outside a program."""
    stage_keys = jax.vmap(mdgps.stage_keys)(keys)  # (sample, dynamics, linearisation, catch-up, S-step)
    samples = run("rollouts", state, stage_keys[0], first)
    cost, sample_costs = run("cost", samples)
    dyn_prior, dyn = run("dynamics", state.dyn_prior, samples, stage_keys[1])
    policy, anchor, _ = run("anchor", state, samples, first, stage_keys[3], stage_keys[2])
    model = mdgps.LocalModel(anchor=anchor, dyn=dyn, cost=cost, sample_cost=jnp.mean(sample_costs, axis=-1))
    step_mult, _, _ = run("step_size", state.step_mult, first, state.prev, state.traj, model)
    traj, marginals, eta, _, _, _ = run("cstep", dyn, cost, anchor, state.eta, step_mult)
    policy, _, _ = run("sstep", policy, traj, samples, marginals, stage_keys[4])
    run("learning_curve", traj, policy, eta)
    return mdgps.TrainState(iteration=state.iteration + 1, traj=traj, eta=eta, step_mult=step_mult,
                            dyn_prior=dyn_prior, prev=model, policy=policy)


def relative_difference(a, b) -> float:
    """max |a − b| / max |a| over the floating-point leaves of two pytrees: 0 where they are
    equal (non-finite entries included), inf where only one of them is non-finite."""
    num, den = 0.0, 0.0
    for x, y in zip(jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b), strict=True):
        x, y = np.asarray(x), np.asarray(y)
        if not np.issubdtype(x.dtype, np.floating):
            continue
        same = (x == y) | (np.isnan(x) & np.isnan(y))
        with np.errstate(invalid="ignore"):
            d = np.where(same, 0.0, np.abs(x - y))
        num = max(num, float(np.max(np.where(np.isnan(d), np.inf, d), initial=0.0)))
        den = max(den, float(np.max(np.abs(x[np.isfinite(x)]), initial=0.0)))
    return num / den if den else num


def stage_profiles(profile, top: int = 8) -> dict:
    """{stage: kernel summary (``trace.kernel_summary`` of one run)} of a profile of one
    ``iteration_by_stages`` whose stages ran inside ``PROFILE_PREFIX`` annotations."""
    events = trace.device_events(profile)
    split = trace.split_by_windows(events, trace.host_windows(profile, PROFILE_PREFIX))
    out = {name[len(PROFILE_PREFIX):]: trace.kernel_summary(evs, 1, top) for name, evs in split.items() if name}
    out["outside stages"] = {"kernels": len(split.get(None, [])), "busy_us": trace.busy_ns(split.get(None, [])) / 1e3}
    return out


def measure(cfg: config.Config, num_seeds: int, iterations: int, mesh, profile_dir: str | None = None) -> dict:
    """Time ``iterations`` iterations of ``num_seeds`` seeds stage by stage and as whole
    iteration programs; returns the row of ``main``'s table. With ``profile_dir``, the stages
    of one more iteration run under JAX's profiler (not timed) and the row gets each stage's
    kernels (``stage_profiles``)."""
    layout = lambda tree: sharding.place(sharding.pad(tree, num_seeds, mesh), mesh)  # noqa: E731
    keys = jnp.stack([jax.random.PRNGKey(s) for s in range(num_seeds)])
    init_keys, it_keys = jax.vmap(lambda k: mdgps.iteration_keys(k, iterations))(keys)
    state = sharding.seed_program(mdgps.init, mesh, (True,))(cfg, layout(init_keys))
    whole = sharding.seed_program(mdgps.iteration, mesh, (True, True, False))
    timer = StageTimer(cfg, mesh, num_seeds)
    whole_s, whole_compile_s, differences, compiled = [], None, [], None
    for it in range(iterations):
        k, first = layout(it_keys[:, it]), jnp.asarray(it == 0)
        new_state = iteration_by_stages(cfg, state, k, first, timer)
        if compiled is None:
            t0 = time.perf_counter()
            compiled = whole.lower(cfg, state, k, first).compile(compiler_options=timer.options or None)
            whole_compile_s = time.perf_counter() - t0
        t0 = time.perf_counter()
        reference, _ = jax.block_until_ready(compiled(state, k, first))
        whole_s.append(time.perf_counter() - t0)
        differences.append(relative_difference(reference, new_state))
        state = reference
    profiles = None
    if profile_dir:
        timer.record = False
        with trace.recorded(os.path.join(profile_dir, f"seeds{num_seeds}")) as rec:
            iteration_by_stages(cfg, state, layout(it_keys[:, -1]), jnp.asarray(False), timer)
        profiles = stage_profiles(rec[0])
    steady = slice(1, None) if iterations > 1 else slice(None)
    per_stage = {name: float(np.median(timer.run_s[name][steady])) for name in STAGES}
    return {"seeds": num_seeds, "stage_s": per_stage, "stage_first_s": {n: timer.run_s[n][0] for n in STAGES},
            "stage_runs_s": timer.run_s,
            "stage_compile_s": timer.compile_s, "stages_sum_s": float(sum(per_stage.values())),
            "iteration_s": float(np.median(whole_s[steady])), "iteration_first_s": whole_s[0],
            "iteration_compile_s": whole_compile_s, "state_rel_diff": differences, "profile": profiles}


def parse_args(argv=None):
    p = argparse.ArgumentParser(prog="python -m benchmarks.stages", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--algorithm", default="gmr", choices=tuple(policies.ALGORITHMS))
    p.add_argument("--scenario", default="AB", choices=tuple(reach_task.SCENARIOS))
    p.add_argument("--seeds", default="1", help="comma-separated seed counts")
    p.add_argument("--iterations", type=int, default=3, help="iterations per seed count (the "
                   "first compiles and runs the catch-up S-step; the median of the rest is reported)")
    p.add_argument("--backend", default="auto", choices=("auto", "mjx", "mujoco"))
    p.add_argument("--adam-entries", default=None, choices=config.SSTEP_ADAM_ENTRIES,
                   help="sstep.adam_entries (default: the configuration's)")
    p.add_argument("--set", action="append", default=[], metavar="GROUP__FIELD=VALUE",
                   help="configuration override (a Python literal)")
    cli.add_precision_argument(p)
    p.add_argument("--profile", metavar="DIR", help="also run one more iteration's stages under JAX's "
                   "profiler (traces under DIR) and report each stage's kernels (GPU; benchmarks.trace)")
    p.add_argument("--out", help="write the results as JSON to this file")
    args = p.parse_args(argv)
    if args.iterations < 1:
        p.error("--iterations must be at least 1")
    args.overrides = cli.parse_overrides(p, args.set)
    if args.adam_entries:
        args.overrides["sstep__adam_entries"] = args.adam_entries
    return args


def main(argv=None) -> int:
    args = parse_args(argv)
    args.precision = cli.setup_jax(args.precision)
    cfg = config.reach(args.scenario, args.algorithm, sim__backend=args.backend, **args.overrides)
    mesh = sharding.seed_mesh()
    dev = jax.devices()[0]
    env = {"date": time.strftime("%Y-%m-%dT%H:%M:%S%z"), "device": dev.device_kind, "backend": dev.platform,
           "devices": mesh.size, "precision": args.precision, "jax": jax.__version__,
           "python": platform.python_version(), "XLA_FLAGS": os.environ.get("XLA_FLAGS", "")}
    print(f"Device: {env['device']} ({env['backend']}) × {mesh.size}, jax {env['jax']}, {env['date']}")
    print(f"{args.algorithm} on {args.scenario}, sim backend {args.backend}, {args.iterations} iterations "
          "per seed count", flush=True)
    rows = []
    for n in [int(s) for s in args.seeds.split(",") if s]:
        row = measure(cfg, n, args.iterations, mesh, args.profile)
        rows.append(row)
        print(f"# seeds={n}: iteration {row['iteration_s']:.3f} s, stages {row['stages_sum_s']:.3f} s, "
              f"state difference {max(row['state_rel_diff']):.2e}", flush=True)
    print("\n| stage | " + " | ".join(f"{r['seeds']} seed(s): s" for r in rows) + " |")
    print("| --- |" + " ---: |" * len(rows))
    for name in STAGES + ("stages_sum", "iteration"):
        cells = [r["stage_s"][name] if name in STAGES else r[name + "_s"] for r in rows]
        print(f"| {name} | " + " | ".join(f"{c:.4f}" for c in cells) + " |")
    if args.out:
        with open(args.out, "w") as f:
            json.dump({"environment": env, "args": vars(args), "config": config.to_dict(cfg), "rows": rows},
                      f, indent=2)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

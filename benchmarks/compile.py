"""Where the compilation of one MDGPS iteration goes: each stage compiled on its own.

``mdgps.iteration`` is a straight composition of stages (sample, cost, dynamics, anchor with the
policy linearisation and the first iteration's catch-up S-step, C-step, S-step, learning curve).
This benchmark lowers and compiles every stage as its own program, with the abstract shapes the
stage sees inside the iteration, and then the whole iteration and the whole ``train``, and
reports per program the lowering and compilation seconds and the size of its optimised HLO
(instructions, while loops)::

    python -m benchmarks.compile --algorithm gmr --scenario AB --out compile.json

Compilation times of separate programs do not add up exactly to the whole program's (XLA
optimises across stage boundaries there), but they show which stage dominates. Run it with an
empty persistent compilation cache (it sets none).
"""

from __future__ import annotations

import argparse
import functools
import json
import os
import platform
import re
import time

import jax
import jax.numpy as jnp

from benchmarks import trace
from experiments import cli
from gmr_jax import config, evaluate, mdgps, policies, sharding, sim, tasks


def _abstract(tree):
    return jax.tree_util.tree_map(lambda a: jax.ShapeDtypeStruct(jnp.shape(a), jnp.result_type(a)), tree)


def _hlo_size(compiled) -> dict:
    text = compiled.as_text() or ""
    instructions = sum(1 for line in text.splitlines() if re.match(r"\s*(ROOT )?%?[\w.\-]+ = ", line))
    return {"hlo_instructions": instructions, "while_loops": len(re.findall(r"\swhile\(", text))}


def profile(fn, *args, trace_dir: str | None = None) -> dict:
    """Lower and compile ``jax.jit(fn)`` for abstract ``args``: seconds and HLO size; with
    ``trace_dir``, the compilation runs under JAX's profiler and ``phases`` lists XLA's compiler
    phases and passes by total time (``benchmarks.trace.host_event_totals``)."""
    t0 = time.perf_counter()
    with jax.default_matmul_precision(mdgps.MATMUL_PRECISION):  # as mdgps.iteration traces its stages
        lowered = jax.jit(fn).lower(*args)
    t1 = time.perf_counter()
    if trace_dir is None:
        compiled = lowered.compile()
    else:
        with trace.recorded(trace_dir) as rec:
            compiled = lowered.compile()
    t2 = time.perf_counter()
    row = {"lower_s": t1 - t0, "compile_s": t2 - t1, **_hlo_size(compiled)}
    if trace_dir is not None:
        row["phases"] = trace.host_event_totals(rec[0])
    return row


def stage_programs(cfg: config.Config, seeds: tuple[int, ...] = ()):
    """[(name, fn, abstract args)]: one control step of the plant (and, with MJX, the forward
    kinematics of one of its physics substeps), then the stages of one iteration in their order,
    the iteration (also as the runner's program for one seed, and vmapped over one seed) and
    ``train`` (and, for each count in ``seeds``, ``train`` over that many seeds as
    ``sharding.train`` maps it on one device: "train, N seeds"), and for a policy the evaluation after training
    (``evaluate.evaluation``, one batch of rollouts) beside the same rollouts as two batches
    (``evaluate.robustness`` and ``evaluate.disturbance_sweep``)."""
    key = jax.random.PRNGKey(0)
    state = jax.eval_shape(lambda k: mdgps.init(cfg, k), key)
    x0 = tasks.initial_states(cfg.task, state.eta.dtype)
    first = jax.ShapeDtypeStruct((), jnp.bool_)
    k = _abstract(key)
    samples = jax.eval_shape(lambda s, kk, f: mdgps.sample_stage(cfg, s, x0, kk, f), state, k, first)
    cost, _ = jax.eval_shape(lambda sm: mdgps.cost_stage(cfg, sm), samples)
    _, dyn = jax.eval_shape(lambda p, sm, kk: mdgps.dynamics_stage(cfg, p, sm, kk), state.dyn_prior, samples, k)
    plant = sim.make_sim(cfg.sim)
    x, u = jax.ShapeDtypeStruct((plant.dX,), x0.dtype), jax.ShapeDtypeStruct((plant.dU,), x0.dtype)
    progs = [("simulator step (one control step)", lambda xx, uu: sim.step(plant, xx, uu), (x, u))]
    if plant.backend == "mjx":
        from mujoco.mjx._src import smooth  # MJX's forward kinematics, one of the step's parts

        mx, d0 = plant.mjx_model_and_data()
        progs.append(("MJX kinematics (one physics substep)", lambda d: smooth.kinematics(mx, d),
                      (_abstract(d0),)))
    progs += [
        ("sample", lambda s, kk, f: mdgps.sample_stage(cfg, s, x0, kk, f), (state, k, first)),
        ("cost", lambda sm: mdgps.cost_stage(cfg, sm), (samples,)),
        ("dynamics", lambda p, sm, kk: mdgps.dynamics_stage(cfg, p, sm, kk), (state.dyn_prior, samples, k)),
        ("anchor (linearisation + catch-up S-step)",
         lambda s, sm, f, k1, k2: mdgps.anchor_stage(cfg, s, sm, f, k1, k2), (state, samples, first, k, k)),
    ]
    anchor = state.traj
    if state.policy is not None:
        _, anchor, _ = jax.eval_shape(lambda s, sm, f, k1, k2: mdgps.anchor_stage(cfg, s, sm, f, k1, k2),
                                      state, samples, first, k, k)
    progs.append(("C-step (η search)", lambda d, c, a, e, m: mdgps.c_step(cfg, d, c, a, e, m),
                  (dyn, cost, anchor, state.eta, state.step_mult)))
    traj, marginals, *_ = jax.eval_shape(lambda d, c, a, e, m: mdgps.c_step(cfg, d, c, a, e, m),
                                         dyn, cost, anchor, state.eta, state.step_mult)
    if state.policy is not None:
        progs.append(("S-step", lambda p, t, sm, mg, kk: mdgps.s_step(cfg, p, t, sm, mg, kk),
                      (state.policy, traj, samples, marginals, k)))
    progs.append(("learning curve", lambda t, p: mdgps.learning_curve(cfg, t, p, x0), (traj, state.policy)))
    progs.append(("rollouts of train's step (samples + learning curve)",
                  lambda s, kk, f: mdgps.rollout_stage(cfg, s, x0, kk, f), (state, k, first)))
    progs.append(("iteration", lambda s, kk, f: mdgps.iteration(cfg, s, kk, f), (state, k, first)))
    # The iteration as the runner compiles it for a run of one seed: its seed program
    # (sharding.over_seed_axis, the plain iteration on the squeezed seed), beside the same program
    # vmapped over a seed axis of size one, which the runner compiled before.
    one = lambda tree: jax.tree_util.tree_map(lambda a: jax.ShapeDtypeStruct((1, *a.shape), a.dtype), tree)  # noqa: E731
    step = functools.partial(mdgps.iteration, cfg)
    progs.append(("runner's iteration program (one seed)",
                  sharding.over_seed_axis(step, (True, True, False)), (one(state), one(k), first)))
    progs.append(("runner's iteration program before: vmapped over one seed",
                  jax.vmap(step, in_axes=(0, 0, None)), (one(state), one(k), first)))
    progs.append(("train", lambda kk: mdgps.train(cfg, kk), (k,)))
    for n in seeds:
        progs.append((f"train, {n} seeds", sharding.over_seed_axis(lambda kk: mdgps.train(cfg, kk), (True,)),
                      (jax.ShapeDtypeStruct((n,) + key.shape, key.dtype),)))
    if state.policy is not None:  # the program that evaluates a trained policy after training
        params = state.policy.params
        progs.append(("evaluation (one batch of rollouts)", lambda pp: evaluate.evaluation(cfg, pp), (params,)))
        progs.append(("evaluation as two batches (robustness, sweep)",
                      lambda pp: (evaluate.robustness(cfg, pp), evaluate.disturbance_sweep(cfg, pp)), (params,)))
    return progs


def selection(only: str) -> set[str]:
    """``--only``'s beginnings of program names: split at commas, except a comma followed by a
    space, which program names hold ("train, 256 seeds")."""
    return {s.strip() for s in re.split(r",(?! )", only) if s.strip()}


def chosen(programs: list, only: str) -> list:
    """The ``(name, fn, args)`` of ``programs`` whose names begin with one of ``--only``'s (all
    for an empty ``only``). Raises ValueError, naming the programs, where none does."""
    names = selection(only)
    picked = [prog for prog in programs if not names or any(prog[0].startswith(o) for o in names)]
    if not picked:
        raise ValueError(f"--only {only!r} names no program; the programs: {'; '.join(n for n, *_ in programs)}")
    return picked


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks.compile", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--algorithm", default="gmr", choices=tuple(policies.ALGORITHMS))
    p.add_argument("--scenario", default="AB")
    p.add_argument("--backend", default="mjx", choices=("auto", "mjx", "mujoco"))
    cli.add_precision_argument(p)
    p.add_argument("--only", default="", help="comma-separated beginnings of the names of the programs to "
                   "compile (default: all); a comma followed by a space belongs to a name, as in "
                   "\"train, 256 seeds\"")
    p.add_argument("--set", action="append", default=[], metavar="GROUP__FIELD=VALUE",
                   help="configuration override (a Python literal)")
    p.add_argument("--profile", metavar="DIR", help="compile under JAX's profiler (traces under DIR) and "
                   "list XLA's compiler phases and passes by time (inclusive, summed over threads; with "
                   "the profiler on, compilation is somewhat slower)")
    p.add_argument("--seeds", type=cli.positive_int_list, default=(), help="comma-separated seed counts: also compile `train` mapped over "
                   "that many seeds on one device (\"train, N seeds\"; --only train selects them too)")
    p.add_argument("--out", help="write the results as JSON to this file")
    args = p.parse_args(argv)
    args.precision = cli.setup_jax(args.precision)
    overrides = cli.parse_overrides(p, args.set)
    cfg = config.reach(args.scenario, args.algorithm, sim__backend=args.backend, **overrides)
    dev = jax.devices()[0]
    env = {"date": time.strftime("%Y-%m-%dT%H:%M:%S%z"), "device": dev.device_kind, "platform": dev.platform,
           "precision": args.precision, "jax": jax.__version__, "python": platform.python_version(),
           "XLA_FLAGS": os.environ.get("XLA_FLAGS", "")}
    print(f"Device: {env['device']}, {args.precision}, jax {env['jax']}, {args.scenario}/{args.algorithm}", flush=True)
    try:
        programs = chosen(stage_programs(cfg, args.seeds), args.only)
    except ValueError as e:
        p.error(str(e))
    rows = {}
    for name, fn, fargs in programs:
        tdir = os.path.join(args.profile, re.sub(r"\W+", "_", name)) if args.profile else None
        rows[name] = r = profile(fn, *fargs, trace_dir=tdir)
        print(f"  {name:42s} lower {r['lower_s']:6.1f} s  compile {r['compile_s']:6.1f} s  "
              f"{r['hlo_instructions']:6d} HLO instructions, {r['while_loops']} while loops", flush=True)
        for ph in r.get("phases", [])[:25]:
            print(f"      {ph['s']:8.2f} s  ×{ph['count']:5d}  {ph['name'][:90]}", flush=True)
        if args.out:
            with open(args.out, "w") as f:
                json.dump({"environment": env, "args": vars(args), "programs": rows}, f, indent=2)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

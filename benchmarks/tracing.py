"""How long a run's iteration takes to trace and lower, with and without the garbage collector.

A cold run traces and lowers its iteration's programs (Python under the GIL) before they can
compile; the runner pauses Python's cyclic garbage collector meanwhile (``runner.gc_paused``).
This benchmark traces and lowers the iteration as ``runner.run`` does for one seed on this
machine's default device with C MuJoCo (as ``--iteration-programs auto`` chooses: one program on
a CPU, split between the GPU and the host on a GPU; no program store), ``--repeats`` times per setting,
alternating, each after ``jax.clear_caches()``::

    python -m benchmarks.tracing --algorithm gmr --scenario AB --out tracing.json

"paused" is the runner's own path; "collecting" the same with the collector left on. A full
collection after each trace (``collect_s``) counts the garbage that the pause leaves for later.
"""

from __future__ import annotations

import argparse
import contextlib
import functools
import gc
import json
import os
import platform
import statistics
import time

import jax
import jax.numpy as jnp

from experiments import cli
from gmr_jax import config, policies, runner

SETTINGS = ("paused", "collecting")


def traced_and_lowered_s(cfg: config.Config, scheduler: runner.Scheduler) -> dict:
    """One trace and lowering of ``cfg``'s iteration for one seed as the runner does it: seconds
    in all, the runner's own ``trace_s`` and ``lower_s``, and ``collect_s``, a full collection
    right after it (the garbage that a paused collector leaves for later)."""
    jax.clear_caches()
    gc.collect()
    layout = runner._Layout(scheduler.mesh_for(None), 1)
    k_init, it_keys = (layout.device(k) for k in runner.seed_keys(cfg, [0]))
    init = functools.partial(runner._program("init", layout.mesh), runner.program_config(cfg))
    shapes = jax.eval_shape(init, k_init)
    timer = runner.Timer()
    t0 = time.perf_counter()
    runner._lowered("step", cfg, (shapes, it_keys[:, 0], jnp.asarray(True)), timer, scheduler, layout.mesh)
    t1 = time.perf_counter()
    gc.collect()
    return {"total_s": t1 - t0, "collect_s": time.perf_counter() - t1, **{k: float(v) for k, v in timer.items()}}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks.tracing", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--algorithm", default="gmr", choices=tuple(policies.ALGORITHMS))
    p.add_argument("--scenario", default="AB")
    cli.add_precision_argument(p)
    p.add_argument("--repeats", type=int, default=3, help="traces per setting (default: %(default)s)")
    p.add_argument("--out", help="write the results as JSON to this file")
    args = p.parse_args(argv)
    if args.repeats < 1:
        p.error(f"--repeats must be a positive integer, got {args.repeats}")
    args.precision = cli.setup_jax(args.precision)
    cfg = config.reach(args.scenario, args.algorithm, sim__backend="mujoco")  # the one-seed runs' physics
    dev = jax.devices()[0]
    env = {"date": time.strftime("%Y-%m-%dT%H:%M:%S%z"), "device": dev.device_kind, "platform": dev.platform,
           "precision": args.precision, "jax": jax.__version__, "python": platform.python_version(),
           "XLA_FLAGS": os.environ.get("XLA_FLAGS", "")}
    mode = runner.iteration_programs_for("auto", cfg, dev.platform)
    print(f"Device: {env['device']}, {args.precision}, jax {env['jax']}, {args.scenario}/{args.algorithm}, "
          f"iteration {mode}", flush=True)
    rows = {s: [] for s in SETTINGS}
    paused = runner.gc_paused
    with runner.Scheduler() as scheduler:
        traced_and_lowered_s(cfg, scheduler)  # imports and first-use caches outside the measurement
        for _ in range(args.repeats):
            for setting in SETTINGS:
                runner.gc_paused = paused if setting == "paused" else contextlib.nullcontext
                try:
                    rows[setting].append(traced_and_lowered_s(cfg, scheduler))
                finally:
                    runner.gc_paused = paused
                r = rows[setting][-1]
                print(f"  {setting:10s} {r['total_s']:6.2f} s (trace {r.get('trace_s', 0):.2f}, "
                      f"lower {r.get('lower_s', 0):.2f}), then a full collection {r['collect_s']:.2f} s", flush=True)
    for setting in SETTINGS:
        totals = [r["total_s"] for r in rows[setting]]
        with_collect = [r["total_s"] + r["collect_s"] for r in rows[setting]]
        print(f"{setting:10s} median {statistics.median(totals):.2f} s, min {min(totals):.2f} s; with the "
              f"collection after it median {statistics.median(with_collect):.2f} s", flush=True)
    if args.out:
        with open(args.out, "w") as f:
            json.dump({"environment": env, "args": vars(args), "iteration_programs": mode, "runs": rows}, f,
                      indent=2)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""Wall time of whole training runs, many seeds in parallel: ``jax.vmap(gmr_jax.train)``.

For each seed count S, one jitted ``jax.vmap(mdgps.train, in_axes=(None, 0))`` over S keys
(for one seed per device the plain ``mdgps.train``, ``sharding.over_seed_axis``),
split over ``--devices`` local devices (``gmr_jax.sharding``; default all), runs the full
configured training (default: MDGPS on scenario AB, i.e. 2 conditions, 5 samples,
T = 80, 10 iterations), compiled with the XLA options the runner uses for that many seeds per
device (``sharding.compiler_options``; ``--compiler-options none`` for XLA's defaults). Compile
time (lower + compile, and the lowering alone: ``lower_s``) and run time (median over repeats,
after compilation) are reported separately, with the final-state MSE reached, so that speed is never
quoted for a run that did not learn; ``results_sha256`` (of the metrics history and the final
state) tells whether two runs, e.g. of two versions of the code, computed the same bits. Example::

    python -m benchmarks.train --algorithm mdgps --seeds 1,8,64,256 --out train.json
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import platform
import statistics
import time

import jax
import jax.numpy as jnp
import numpy as np

from experiments import cli
from gmr_jax import config, mdgps, policies, sharding
from gmr_jax.tasks import reach as reach_task


def parse_args(argv=None):
    p = argparse.ArgumentParser(prog="python -m benchmarks.train", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--algorithm", default="mdgps", choices=tuple(policies.ALGORITHMS))
    p.add_argument("--scenario", default="AB", choices=tuple(reach_task.SCENARIOS))
    p.add_argument("--seeds", default="1,8,64,256", help="comma-separated seed counts")
    p.add_argument("--iterations", type=int, default=config.Config.iterations)
    p.add_argument("--samples", type=int, default=config.Config.num_samples)
    p.add_argument("--T", type=int, default=config.TaskConfig.T)
    p.add_argument("--backend", default="auto", choices=("auto", "mjx", "mujoco"))
    p.add_argument("--repeats", type=int, default=1, help="timed runs per seed count (median)")
    p.add_argument("--adam-entries", default=config.SStepConfig.adam_entries, choices=config.SSTEP_ADAM_ENTRIES,
                   help="sstep.adam_entries (default: %(default)s; \"trained\" is faster with many seeds)")
    p.add_argument("--sstep-impl", default=config.SStepConfig.impl, choices=config.SSTEP_IMPLS,
                   help="sstep.impl, the S-step's form (default: %(default)s; \"cuda\": GMR's hand-written "
                        "CUDA kernel, float32 on an NVIDIA GPU with nvcc)")
    cli.add_precision_argument(p)
    p.add_argument("--devices", type=int, default=None, help="local devices to split the seeds over "
                   "(default: all)")
    p.add_argument("--compiler-options", default="runner", choices=("runner", "none"),
                   help="XLA compile options: the runner's for this many seeds per device "
                        "(sharding.compiler_options) or none")
    p.add_argument("--out", help="write the results as JSON to this file")
    return p.parse_args(argv)


def main(argv=None) -> int:
    args = parse_args(argv)
    args.precision = cli.setup_jax(args.precision)
    cfg = config.reach(args.scenario, args.algorithm, iterations=args.iterations,
                       num_samples=args.samples, task__T=args.T, sim__backend=args.backend,
                       sstep__adam_entries=args.adam_entries, sstep__impl=args.sstep_impl)
    mesh = sharding.seed_mesh(args.devices)
    dev = jax.devices()[0]
    env = {"date": time.strftime("%Y-%m-%dT%H:%M:%S%z"), "device": dev.device_kind,
           "precision": args.precision,
           "backend": dev.platform, "devices": mesh.size, "jax": jax.__version__, "python": platform.python_version(),
           "XLA_FLAGS": os.environ.get("XLA_FLAGS", ""), "sstep_impl": args.sstep_impl,
           "adam_entries": args.adam_entries}
    print(f"Device: {env['device']} ({env['backend']}) × {mesh.size}, jax {env['jax']}, {env['date']}")
    print(f"{args.algorithm} on {args.scenario}: {cfg.iterations} iterations, {cfg.num_samples} samples, "
          f"T = {cfg.task.T}, {cfg.task.num_conditions} condition(s)", flush=True)
    fn = sharding.seed_program(mdgps.train, mesh, (True,))
    rows = []
    for n in [int(s) for s in args.seeds.split(",") if s]:
        keys = sharding.place(sharding.pad(jnp.stack([jax.random.PRNGKey(s) for s in range(n)]), n, mesh), mesh)
        t0 = time.perf_counter()
        options = sharding.compiler_options(sharding.seeds_per_device(n, mesh.size)) if args.compiler_options == "runner" else {}
        lowered = fn.lower(cfg, keys)
        lower_s = time.perf_counter() - t0
        compiled = lowered.compile(compiler_options=options or None)
        compile_s = time.perf_counter() - t0  # lowering included (lower_s of it)
        times = []
        for _ in range(max(1, args.repeats)):
            t0 = time.perf_counter()
            final, hist = compiled(keys)
            jax.block_until_ready(hist)
            times.append(time.perf_counter() - t0)
        hist = sharding.unpad(hist, n)
        curve = "final_state_mse_policy" if "final_state_mse_policy" in hist else "final_state_mse_lqr"
        mse = np.asarray(hist[curve])[:, -1].max(axis=-1)  # [seeds], worst condition, last iteration
        ok = bool(np.all(np.asarray(hist["ok"])))
        digest = hashlib.sha256()
        for leaf in jax.tree_util.tree_leaves((hist, sharding.unpad(final, n))):
            digest.update(np.ascontiguousarray(np.asarray(leaf)).tobytes())
        row = {"seeds": n, "results_sha256": digest.hexdigest(), "compiler_options": options, "compile_s": compile_s, "lower_s": lower_s, "run_s": statistics.median(times),
               "curve": curve, "final_mse_median": float(np.median(mse)),
               "success_0.01": int((mse < cfg.task.success_threshold).sum()), "all_ok": ok}
        rows.append(row)
        print(f"# seeds={n}: run {row['run_s']:.2f} s, compile {compile_s:.1f} s (lowering {lower_s:.1f} s), "
              f"{curve} median {row['final_mse_median']:.3g}, success {row['success_0.01']}/{n}, ok {ok}",
              flush=True)
    base = rows[0]["run_s"]
    print("\n| seeds | run s | × one-seed time | compile s | final MSE (median) | success < 0.01 |")
    print("| ---: | ---: | ---: | ---: | ---: | ---: |")
    for r in rows:
        print(f"| {r['seeds']} | {r['run_s']:.2f} | {r['run_s'] / base:.2f} | {r['compile_s']:.1f} | "
              f"{r['final_mse_median']:.3g} | {r['success_0.01']}/{r['seeds']} |")
    if args.out:
        with open(args.out, "w") as f:
            json.dump({"environment": env, "args": vars(args), "config": config.to_dict(cfg),
                       "rows": rows}, f, indent=2)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""Wall time of one S-step (the supervised policy fit), per Adam step.

The S-step is 400 epochs of minibatch Adam steps, strictly sequential, so on a GPU its time is
set by the latency of one step (kernel launches), not by arithmetic. This benchmark times one
S-step of the chosen policy on a data set of the reach study's size (scenario A: B = 400 sampled
states, GMR adds the 80 forward-pass means; AB doubles both) for several loop unroll factors::

    python -m benchmarks.sstep --algorithm gmr,mdgps --scenario A,AB --unroll 1,4,16 --out s.json

The data are synthetic (random states, gains, symmetric positive-definite precisions and state
covariances) with the shapes of the real ones: the time of a step does not depend on the values.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import time

import jax
import jax.numpy as jnp

from gmr_jax import config, mdgps, policies, sstep, tasks


def synthetic_data(cfg: config.Config, key, dtype) -> policies.SStepData:
    """An S-step data set with the reach study's shapes for ``cfg`` (values are arbitrary)."""
    M, N, T = cfg.task.num_conditions, cfg.num_samples, cfg.task.T
    B = M * (N + (cfg.algorithm == "gmr")) * T
    dX = tasks.initial_states(cfg.task).shape[-1]
    dU = dX // 2  # one torque per joint; the state is (joint angles, joint velocities)
    kx, kK, kk, kp, ks = jax.random.split(key, 5)
    x = jax.random.normal(kx, (B, dX), dtype)
    K = 0.1 * jax.random.normal(kK, (B, dU, dX), dtype)
    k = jax.random.normal(kk, (B, dU), dtype)
    a = jax.random.normal(kp, (B, dU, dU), dtype)
    prc = a @ jnp.swapaxes(a, -1, -2) + dU * jnp.eye(dU, dtype=dtype)
    c = 0.1 * jax.random.normal(ks, (B, dX, dX), dtype)
    cov = c @ jnp.swapaxes(c, -1, -2) + 1e-3 * jnp.eye(dX, dtype=dtype)
    return policies.SStepData(x=x, tgt_mu=jnp.einsum("bux,bx->bu", K, x) + k, tgt_prc=prc,
                              wt=jnp.ones((B,), dtype), K=K, k=k, state_cov=cov)


def parse_args(argv=None):
    p = argparse.ArgumentParser(prog="python -m benchmarks.sstep", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--algorithm", default="gmr,mdgps", help="comma-separated: gmr, mdgps")
    p.add_argument("--scenario", default="A", help="comma-separated scenarios (data size)")
    p.add_argument("--unroll", default="1", help="comma-separated unroll factors")
    p.add_argument("--epochs", type=int, default=config.SStepConfig.epochs)
    p.add_argument("--repeats", type=int, default=3, help="timed S-steps (median)")
    p.add_argument("--precision", default="float64", choices=("float32", "float64"))
    p.add_argument("--out", help="write the results as JSON to this file")
    p.add_argument("--hlo-dir", help="also write each compiled program's HLO text here")
    return p.parse_args(argv)


def main(argv=None) -> int:
    args = parse_args(argv)
    jax.config.update("jax_enable_x64", args.precision == "float64")
    dtype = jnp.float64 if args.precision == "float64" else jnp.float32
    dev = jax.devices()[0]
    env = {"date": time.strftime("%Y-%m-%dT%H:%M:%S%z"), "device": dev.device_kind,
           "platform": dev.platform, "precision": args.precision, "jax": jax.__version__,
           "python": platform.python_version(), "XLA_FLAGS": os.environ.get("XLA_FLAGS", "")}
    print(f"Device: {env['device']}, jax {env['jax']}, XLA_FLAGS={env['XLA_FLAGS']!r}", flush=True)
    rows = []
    for algorithm in args.algorithm.split(","):
        for scenario in args.scenario.split(","):
            for unroll in [int(u) for u in args.unroll.split(",")]:
                cfg = config.reach(scenario, algorithm, sstep__epochs=args.epochs,
                                   sstep__unroll=unroll)
                params = mdgps.init(cfg, jax.random.PRNGKey(0)).policy.params
                data = synthetic_data(cfg, jax.random.PRNGKey(1), dtype)
                pol = policies.for_config(cfg)
                fn = jax.jit(lambda p, d, k: sstep.sstep(pol, p, d, k, cfg.sstep))
                t0 = time.perf_counter()
                compiled = fn.lower(params, data, jax.random.PRNGKey(2)).compile()
                compile_s = time.perf_counter() - t0
                if args.hlo_dir:
                    os.makedirs(args.hlo_dir, exist_ok=True)
                    with open(os.path.join(args.hlo_dir, f"{algorithm}_{scenario}_u{unroll}.hlo"), "w") as f:
                        f.write(compiled.as_text())
                times = []
                for r in range(args.repeats):
                    t0 = time.perf_counter()
                    out, info = compiled(params, data, jax.random.PRNGKey(3 + r))
                    jax.block_until_ready(out)
                    times.append(time.perf_counter() - t0)
                steps = args.epochs * (data.x.shape[0] // cfg.sstep.batch_size)
                run_s = statistics.median(times)
                row = {"algorithm": algorithm, "scenario": scenario, "unroll": unroll,
                       "rows": int(data.x.shape[0]), "adam_steps": steps, "compile_s": compile_s,
                       "run_s": run_s, "us_per_step": 1e6 * run_s / steps,
                       "finite": bool(info["finite"])}
                rows.append(row)
                print(f"{algorithm:5s} {scenario:2s} unroll {unroll:3d}: {run_s:7.3f} s for {steps} steps "
                      f"= {row['us_per_step']:6.1f} µs/step (compile {compile_s:.1f} s)", flush=True)
    if args.out:
        with open(args.out, "w") as f:
            json.dump({"env": env, "rows": rows}, f, indent=1)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

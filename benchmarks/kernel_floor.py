"""The latency floor of a chain of dependent GPU kernels: what one kernel of a sequential loop
costs however little it computes.

The S-step's minibatch steps are strictly sequential and each step's kernels depend on one
another, so its time per Adam step is at least (kernels per step) × (time of one dependent
kernel). This benchmark measures that time directly: a ``lax.fori_loop`` whose body is a chain
of ``--chain`` dependent products ``h ← leaky_relu(h W_i)`` of GMR's sizes (a minibatch of 20
rows, width 128), for several chain lengths. The slope of the time per loop iteration over the
kernels per iteration (counted in the profile, ``benchmarks.trace``) is the floor per dependent
kernel; the intercept is the loop's own cost::

    python -m benchmarks.kernel_floor --chain 1,8,32,64 --out floor.json

Run it with the same XLA flags as the study (``experiments.cli.setup_jax``: command buffers on,
autotuning off) to compare with ``benchmarks.sstep --profile``.
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
import numpy as np

from benchmarks import trace
from experiments import cli


def chain_program(chain: int, steps: int):
    """jitted (h [rows, width], W [chain, width, width]) -> h after ``steps`` loop iterations of
    ``chain`` dependent products each."""
    def run(h, w):
        def body(_, h):
            for i in range(chain):
                pre = jnp.dot(h, w[i], precision=jax.lax.Precision.HIGHEST)
                h = jnp.where(pre >= 0, pre, 0.01 * pre)
            return h
        return jax.lax.fori_loop(0, steps, body, h)
    return jax.jit(run)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks.kernel_floor", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--chain", default="1,8,32,64", help="comma-separated products per loop iteration")
    p.add_argument("--steps", type=int, default=1000, help="loop iterations per call")
    p.add_argument("--rows", type=int, default=20)
    p.add_argument("--width", type=int, default=128)
    p.add_argument("--repeats", type=int, default=3, help="timed calls (median)")
    cli.add_precision_argument(p)
    p.add_argument("--profile", default="/tmp/kernel_floor_trace", metavar="DIR", help="trace folder")
    p.add_argument("--out", help="write the results as JSON to this file")
    args = p.parse_args(argv)
    args.precision = cli.setup_jax(args.precision)
    dtype = jnp.float64 if args.precision == "float64" else jnp.float32
    dev = jax.devices()[0]
    env = {"date": time.strftime("%Y-%m-%dT%H:%M:%S%z"), "device": dev.device_kind, "platform": dev.platform,
           "precision": args.precision, "jax": jax.__version__, "python": platform.python_version(),
           "XLA_FLAGS": os.environ.get("XLA_FLAGS", "")}
    print(f"Device: {env['device']}, {args.precision}, jax {env['jax']}, XLA_FLAGS={env['XLA_FLAGS']!r}", flush=True)
    rng = np.random.default_rng(0)
    rows = []
    for chain in [int(c) for c in args.chain.split(",")]:
        h = jnp.asarray(rng.normal(size=(args.rows, args.width)), dtype)
        # orthogonal-ish weights keep h's scale over thousands of products
        w = jnp.asarray(np.linalg.qr(rng.normal(size=(chain, args.width, args.width)))[0], dtype)
        fn = chain_program(chain, args.steps)
        t0 = time.perf_counter()
        compiled = fn.lower(h, w).compile()
        compile_s = time.perf_counter() - t0
        times = []
        for _ in range(args.repeats):
            t0 = time.perf_counter()
            jax.block_until_ready(compiled(h, w))
            times.append(time.perf_counter() - t0)
        with trace.recorded(os.path.join(args.profile, f"chain{chain}")) as rec:
            jax.block_until_ready(compiled(h, w))
        prof = trace.kernel_summary(trace.device_events(rec[0]), args.steps)
        row = {"chain": chain, "us_per_iteration": 1e6 * statistics.median(times) / args.steps,
               "compile_s": compile_s, "profile": prof}
        rows.append(row)
        k = prof.get("kernels_per_step", float("nan"))
        print(f"chain {chain:3d}: {row['us_per_iteration']:8.2f} µs per loop iteration, {k:.1f} kernels per "
              f"iteration" + (f", busy {prof['busy_us_per_step']:.2f} µs, median kernel "
                              f"{prof['kernel_us_median']:.2f} µs" if prof["kernels"] else ""), flush=True)
    fit = None
    ks = [r["profile"].get("kernels_per_step") for r in rows]
    if len(rows) >= 2 and all(ks):
        slope, intercept = np.polyfit(ks, [r["us_per_iteration"] for r in rows], 1)
        fit = {"us_per_kernel": float(slope), "us_per_iteration_at_zero_kernels": float(intercept)}
        print(f"floor: {slope:.2f} µs per dependent kernel, {intercept:.2f} µs per loop iteration besides",
              flush=True)
    if args.out:
        with open(args.out, "w") as f:
            json.dump({"env": env, "args": vars(args), "rows": rows, "fit": fit}, f, indent=1)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

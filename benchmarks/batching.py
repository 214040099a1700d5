"""How much of tracing a seed-vmapped ``train`` is batching loop bodies more than once.

``jax.vmap`` batches a loop (``lax.scan``, ``lax.while_loop``) by batching its body's jaxpr; a
carry that starts the same for every seed but comes out of the body seed-dependent makes it
batch the whole body again with that carry batched (the loop rule's fixpoint). This benchmark
traces ``mdgps.train`` mapped over each ``--seeds`` count on one device (``sharding.seed_program``,
the keys placed on the device as the runner places them), each in a fresh process state
(``jax.clear_caches()``), and counts every loop batching by JAX and the seconds of the passes that
a later pass of the same loop replaced::

    python -m benchmarks.batching --algorithm gmr --scenario AB --seeds 1,256 --out batching.json

It reads JAX's private ``batching.batch_jaxpr`` (wrapped for the count): a JAX that renames it
fails here with an AttributeError, not with a wrong figure.
"""

from __future__ import annotations

import argparse
import collections
import json
import platform
import sys
import time

import jax
import jax.numpy as jnp
from jax._src.interpreters import batching

from experiments import cli
from gmr_jax import config, mdgps, policies, sharding

LOOP_RULES = ("_scan_batching_rule", "_while_loop_batching_rule")


def traced(cfg: config.Config, seeds: int) -> dict:
    """Trace ``train`` over ``seeds`` seeds: seconds, loop batchings, and the repeated passes
    (every pass of a loop's fixpoint but its last) with their seconds, outermost ones only
    (a repeated pass holds the passes of the loops inside it)."""
    calls, stack = [], []
    original = batching.batch_jaxpr

    def counting(closed_jaxpr, axis_data, in_batched, instantiate):
        frame = sys._getframe(1)
        record = {"rule": frame.f_code.co_name, "frame": id(frame), "eqns": len(closed_jaxpr.jaxpr.eqns),
                  "parent": stack[-1] if stack else None, "t0": time.perf_counter()}
        calls.append(record)
        stack.append(len(calls) - 1)
        try:
            return original(closed_jaxpr, axis_data, in_batched, instantiate)
        finally:
            stack.pop()
            record["t1"] = time.perf_counter()

    jax.clear_caches()
    mesh = sharding.seed_mesh(1)
    fn = sharding.seed_program(mdgps.train, mesh, (True,))
    keys = sharding.place(jnp.stack([jax.random.PRNGKey(s) for s in range(seeds)]), mesh)
    batching.batch_jaxpr = counting
    try:
        t0 = time.perf_counter()
        fn.trace(cfg, keys)
        trace_s = time.perf_counter() - t0
    finally:
        batching.batch_jaxpr = original
    groups = collections.defaultdict(list)
    for i, c in enumerate(calls):
        if c["rule"] in LOOP_RULES:  # consecutive passes of one loop share the rule's frame
            groups[(c["frame"], c["parent"])].append(i)
    repeated = {i for idx in groups.values() for i in idx[:-1]}

    def inside_repeated(i):
        p = calls[i]["parent"]
        while p is not None:
            if p in repeated:
                return True
            p = calls[p]["parent"]
        return False

    outermost = [i for i in repeated if not inside_repeated(i)]
    by_body = collections.Counter()
    for i in outermost:
        by_body[f"{calls[i]['rule'].strip('_').split('_batching')[0]}, {calls[i]['eqns']} equations"] += \
            calls[i]["t1"] - calls[i]["t0"]
    return {"seeds": seeds, "trace_s": trace_s, "loop_batchings": sum(len(v) for v in groups.values()),
            "repeated_passes": len(repeated), "repeated_s": sum(by_body.values()),
            "repeated_s_by_body": dict(by_body.most_common(8))}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks.batching", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--algorithm", default="gmr", choices=tuple(policies.ALGORITHMS))
    p.add_argument("--scenario", default="AB")
    p.add_argument("--backend", default="mjx", choices=("auto", "mjx", "mujoco"))
    p.add_argument("--seeds", default="1,256", help="comma-separated seed counts")
    cli.add_precision_argument(p)
    p.add_argument("--out", help="write the results as JSON to this file")
    args = p.parse_args(argv)
    args.precision = cli.setup_jax(args.precision)
    cfg = config.reach(args.scenario, args.algorithm, sim__backend=args.backend, sstep__adam_entries="trained")
    dev = jax.devices()[0]
    env = {"date": time.strftime("%Y-%m-%dT%H:%M:%S%z"), "device": dev.device_kind, "backend": dev.platform,
           "jax": jax.__version__, "python": platform.python_version(), "precision": args.precision}
    print(f"Device: {env['device']} ({env['backend']}), jax {env['jax']}, {env['date']}", flush=True)
    rows = []
    for n in [int(s) for s in args.seeds.split(",") if s]:
        row = traced(cfg, n)
        rows.append(row)
        print(f"# seeds={n}: trace {row['trace_s']:.2f} s, {row['loop_batchings']} loop batchings, "
              f"{row['repeated_passes']} repeated, {row['repeated_s']:.2f} s of them outermost: "
              + ", ".join(f"{k} {v:.2f} s" for k, v in list(row["repeated_s_by_body"].items())[:4]), flush=True)
    if args.out:
        with open(args.out, "w") as f:
            json.dump({"environment": env, "args": vars(args), "config": config.to_dict(cfg), "rows": rows}, f, indent=2)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

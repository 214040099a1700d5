"""Do the default run's four S-steps overlap when one program puts them on separate GPU streams?

The four runs of the default study (GMR and MLP, scenarios A and A,B) run their S-steps one
after another on the GPU's one compute stream, each bound by its kernels' latency, not by the
GPU's width. This benchmark times the four S-steps (synthetic data of the study's shapes, as
``benchmarks.sstep``) alone, then pairs and all four in one jitted program, once on one stream
and once with each S-step wrapped as one call annotated for its own stream (``compute_on``'s
``gpu_stream:N``), and the programs of the S-steps alone called at once from threads of their
own (as the CLI's side-by-side runs call theirs). It also reports whether every variant trains
the same weights as the S-step alone::

    python -m benchmarks.streams --epochs 40 --out streams.json

JAX's public ``compute_on`` annotates every call nested inside the region as well, and XLA
accepts stream annotations on top-level calls only, so the wrapper here traces the S-step
outside that context and binds ``compute_on``'s primitive directly (``jax._src.compute_on``, a
private API: a measurement tool, not library code). Results: benchmarks/RESULTS.md, sixteenth
session (streams) and twenty-fifth (threads).
"""

from __future__ import annotations

import argparse
import concurrent.futures
import hashlib
import json
import time

import jax
import jax.numpy as jnp
import numpy as np
from jax.flatten_util import ravel_pytree

from benchmarks.sstep import synthetic_data
from experiments import cli
from gmr_jax import config, mdgps, policies, sstep

RUNS = (("gmr", "A"), ("gmr", "AB"), ("mdgps", "A"), ("mdgps", "AB"))


def on_stream(fn, n: int):
    """``fn`` as one call annotated for GPU stream ``n``, the calls nested in it unannotated."""
    from jax._src import compute_on as co
    from jax._src import core

    def wrapped(*args):
        flat, tree = jax.tree_util.tree_flatten(args)
        closed, shape = jax.make_jaxpr(lambda *f: fn(*jax.tree_util.tree_unflatten(tree, f)), return_shape=True)(*flat)
        outs = co.compute_on_p.bind(*flat, jaxpr=closed, compute_type=f"gpu_stream:{n}",
                                    out_memory_spaces=tuple(core.MemorySpace.Device for _ in closed.out_avals),
                                    compiler_options_json=None)
        return jax.tree_util.tree_unflatten(jax.tree_util.tree_structure(shape), outs)
    return wrapped


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks.streams", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--epochs", type=int, default=40, help="S-step epochs (default: %(default)s)")
    p.add_argument("--out", help="write the results as JSON to this file")
    args = p.parse_args(argv)
    cli.setup_jax("float32")
    items = []
    for algorithm, scenario in RUNS:
        cfg = config.reach(scenario, algorithm, sstep__epochs=args.epochs)
        items.append((cfg, policies.for_config(cfg), mdgps.init(cfg, jax.random.PRNGKey(0)).policy.params,
                      synthetic_data(cfg, jax.random.PRNGKey(1), jnp.float32)))

    def one(i):
        cfg, pol, _, _ = items[i]
        return jax.jit(lambda prm, d, k: sstep.sstep(pol, prm, d, k, cfg.sstep, impl="packed")[0].net)

    def group(idx, streams):
        def f(ps, ds, k):
            return [(on_stream(one(i), j + 1) if streams else one(i))(ps[j], ds[j], k) for j, i in enumerate(idx)]
        return jax.jit(f)

    def flat(net):
        return ravel_pytree(net)[0]

    def median_s(run, repeats=3):
        times = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            out = jax.block_until_ready(run())
            times.append(time.perf_counter() - t0)
        return sorted(times)[repeats // 2], out

    compiled_alone = {}

    def timed(fn, fargs, alone_index=None):
        with jax.default_matmul_precision(mdgps.MATMUL_PRECISION):
            t0 = time.perf_counter()
            compiled = fn.lower(*fargs).compile()
            compile_s = time.perf_counter() - t0
        if alone_index is not None:
            compiled_alone[alone_index] = compiled
        s, out = median_s(lambda: compiled(*fargs))
        text = compiled.as_text() or ""
        return s, compile_s, out, text.count("async-start") + text.count("call-start")

    def from_threads(idx, key):
        """The S-steps' own programs called at once, each from a thread of its own."""
        with concurrent.futures.ThreadPoolExecutor(len(idx)) as pool:
            return median_s(lambda: list(pool.map(
                lambda i: jax.block_until_ready(compiled_alone[i](items[i][2], items[i][3], key)), idx)))

    dev = jax.devices()[0]
    res = {"device": dev.device_kind, "jax": jax.__version__, "epochs": args.epochs, "rows": []}
    key = jax.random.PRNGKey(3)
    alone, alone_s = {}, {}
    for i, (algorithm, scenario) in enumerate(RUNS):
        alone_s[i], compile_s, alone[i], _ = timed(one(i), (items[i][2], items[i][3], key), alone_index=i)
        res["rows"].append({"what": f"{algorithm} {scenario} alone", "s": alone_s[i], "compile_s": compile_s,
                            "sha": hashlib.sha256(np.asarray(flat(alone[i])).tobytes()).hexdigest()[:16]})
        print(res["rows"][-1], flush=True)

    def max_rel_diff(out, idx):
        return max(float(jnp.max(jnp.abs(flat(o) - flat(alone[i]))) / jnp.max(jnp.abs(flat(alone[i]))))
                   for o, i in zip(out, idx))

    for idx in ([0, 1], [2, 3], [0, 1, 2, 3]):
        names = ' + '.join(' '.join(RUNS[i]) for i in idx)
        s, out = from_threads(idx, key)
        res["rows"].append({"what": f"{names}, own programs from threads", "s": s,
                            "sum_alone_s": sum(alone_s[i] for i in idx), "max_alone_s": max(alone_s[i] for i in idx),
                            "max_rel_diff": max_rel_diff(out, idx)})
        print(res["rows"][-1], flush=True)
        fargs = ([items[i][2] for i in idx], [items[i][3] for i in idx], key)
        for streams in (False, True):
            name = f"{names}, {'own streams' if streams else 'one stream'}"
            try:
                s, compile_s, out, async_ops = timed(group(idx, streams), fargs)
            except Exception as err:  # noqa: BLE001 (XLA refuses some annotated programs: report it)
                res["rows"].append({"what": name, "error": str(err)[:2000]})
                print(name, "FAILED:", str(err)[:300], flush=True)
                continue
            res["rows"].append({"what": name, "s": s, "compile_s": compile_s,
                                "sum_alone_s": sum(alone_s[i] for i in idx), "max_rel_diff": max_rel_diff(out, idx),
                                "async_ops": async_ops})
            print(res["rows"][-1], flush=True)
    if args.out:
        with open(args.out, "w") as f:
            json.dump(res, f, indent=1)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

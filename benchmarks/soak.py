"""Soak test: many seeds of the four reach runs, counting the runs that fail or turn non-finite.

For each run (scenario × algorithm, default A and AB × GMR and MDGPS) the whole training
(``mdgps.train``, the study's settings) runs for ``--seeds`` seeds in chunks of ``--chunk``
(``gmr_jax.sharding``: split over the local devices), one compiled program per run. A seed
*fails* when any iteration reports ``ok = False`` (a C-step or S-step produced non-finite
values, or η reached its limit); it is *non-finite* when any entry of its metrics history or of
its final policy parameters is NaN or infinite. Also reported: the final-state MSE of the policy
(median over seeds) and how many seeds end below 0.01, so that a soak never passes on runs that
did not learn. Example::

    python -m benchmarks.soak --seeds 1024 --chunk 256 --out soak.json
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

from experiments import cli
from gmr_jax import config, mdgps, sharding


def _finite_per_seed(tree) -> np.ndarray:
    """[S] bool: every float leaf of the seed's slice is finite."""
    ok = None
    for leaf in jax.tree_util.tree_leaves(tree):
        a = np.asarray(leaf)
        if not np.issubdtype(a.dtype, np.floating):
            continue
        f = np.isfinite(a.reshape(a.shape[0], -1)).all(axis=1)
        ok = f if ok is None else ok & f
    return ok


def _row(failed, nonfinite, mse, first_seed, compile_s, run_s) -> dict:
    """The soak's counts over the chunks done so far (lists of per-chunk arrays)."""
    failed, nonfinite, mse = np.concatenate(failed), np.concatenate(nonfinite), np.concatenate(mse)
    return {"seeds": int(failed.size), "first_seed": first_seed, "failed": int(failed.sum()),
            "nonfinite": int(nonfinite.sum()),
            "failed_seeds": (np.flatnonzero(failed) + first_seed).tolist()[:50],
            "nonfinite_seeds": (np.flatnonzero(nonfinite) + first_seed).tolist()[:50],
            "final_mse_median": float(np.nanmedian(mse)), "success_0.01": int((mse < 0.01).sum()),
            "compile_s": compile_s, "run_s": run_s}


def soak_run(cfg: config.Config, num_seeds: int, chunk: int, mesh, first_seed: int = 0,
             on_chunk=None) -> dict:
    """Train ``num_seeds`` seeds of ``cfg`` in chunks; counts of failed and non-finite seeds.

    ``on_chunk(row)``, if given, receives the counts over the seeds done so far after every chunk
    (so that a call cut short keeps its finished chunks).
    """
    program = sharding.seed_program(mdgps.train, mesh, (True,))
    size = sharding.padded_count(min(chunk, num_seeds), mesh)
    compiled, compile_s, run_s = None, 0.0, 0.0
    failed, nonfinite, mse = [], [], []
    for start in range(first_seed, first_seed + num_seeds, chunk):
        n = min(chunk, first_seed + num_seeds - start)
        # every chunk padded to the first one's size: one compiled program for all
        keys = jnp.stack([jax.random.PRNGKey(s) for s in range(start, start + n)] +
                         [jax.random.PRNGKey(start + n - 1)] * (size - n))
        keys = sharding.place(keys, mesh)
        if compiled is None:
            t0 = time.perf_counter()
            compiled = program.lower(cfg, keys).compile()
            compile_s = time.perf_counter() - t0
        t0 = time.perf_counter()
        final, hist = jax.block_until_ready(compiled(keys))
        run_s += time.perf_counter() - t0
        final, hist = sharding.unpad((final, hist), n)
        ok = np.asarray(hist["ok"]).reshape(n, -1).all(axis=1)
        failed.append(~ok)
        nonfinite.append(~(_finite_per_seed(hist) & _finite_per_seed(final.policy.params if final.policy else final.traj)))
        curve = "final_state_mse_policy" if "final_state_mse_policy" in hist else "final_state_mse_lqr"
        mse.append(np.asarray(hist[curve])[:, -1].max(axis=-1))
        print(f"  seeds {start}-{start + n - 1}: {int(failed[-1].sum())} failed, "
              f"{int(nonfinite[-1].sum())} non-finite; {run_s:.1f} s so far", flush=True)
        if on_chunk is not None:
            on_chunk(_row(failed, nonfinite, mse, first_seed, compile_s, run_s))
    return _row(failed, nonfinite, mse, first_seed, compile_s, run_s)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks.soak", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--seeds", type=int, default=1024)
    p.add_argument("--chunk", type=int, default=256, help="seeds per compiled call")
    p.add_argument("--first-seed", type=int, default=0,
                   help="first seed (to split a long soak over several calls)")
    p.add_argument("--runs", default="A/gmr,A/mdgps,AB/gmr,AB/mdgps", help="scenario/algorithm pairs")
    cli.add_precision_argument(p)
    p.add_argument("--backend", default="mjx", choices=("auto", "mjx", "mujoco"))
    p.add_argument("--devices", type=int, default=None)
    p.add_argument("--set", action="append", default=[], metavar="GROUP__FIELD=VALUE",
                   help="configuration override for every run (a Python literal)")
    p.add_argument("--out", help="write the results as JSON to this file")
    args = p.parse_args(argv)
    args.precision = cli.setup_jax(args.precision)
    overrides = cli.parse_overrides(p, args.set)
    mesh = sharding.seed_mesh(args.devices)
    dev = jax.devices()[0]
    env = {"date": time.strftime("%Y-%m-%dT%H:%M:%S%z"), "device": dev.device_kind, "devices": mesh.size,
           "platform": dev.platform, "precision": args.precision, "jax": jax.__version__,
           "python": platform.python_version(), "XLA_FLAGS": os.environ.get("XLA_FLAGS", "")}
    print(f"Device: {env['device']} × {mesh.size}, {args.precision}, jax {env['jax']}, {env['date']}", flush=True)
    rows = {}

    def write(name, row):
        rows[name] = row
        if args.out:  # after every chunk, so that a call cut short keeps what it finished
            with open(args.out, "w") as f:
                json.dump({"environment": env, "args": vars(args), "runs": rows}, f, indent=2)

    for name in args.runs.split(","):
        scenario, algorithm = name.split("/")
        cfg = config.reach(scenario, algorithm, sim__backend=args.backend, **overrides)
        row = soak_run(cfg, args.seeds, args.chunk, mesh, args.first_seed,
                       on_chunk=lambda r, name=name: write(name, r))
        write(name, row)
        print(f"{name}: {row['failed']} failed, {row['nonfinite']} non-finite of {row['seeds']} seeds; "
              f"final MSE median {row['final_mse_median']:.3g}, {row['success_0.01']} below 0.01; "
              f"compile {row['compile_s']:.1f} s, run {row['run_s']:.1f} s", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""Are the runner's programs compiled deterministically? Compile the one-seed iteration program
several times in this process (each time traced, lowered and compiled anew, with JAX's caches
cleared), run every executable on the same inputs and compare the outputs bit for bit, for the
runner's program (the plain iteration on the squeezed seed) and for the same program vmapped over
one seed (what the runner compiled before)::

    python -m benchmarks.determinism --algorithm gmr --scenario AB --compiles 3

Runs on any backend (the CLI's precision and XLA flags, ``experiments.cli.setup_jax``) with the C
MuJoCo backend that the CLI picks for one seed. Prints, per program and compile, the seconds,
the number of output leaves that differ from the first compile's and whether the optimised HLO
text is identical.
"""

from __future__ import annotations

import argparse
import functools
import time

import jax
import numpy as np

from experiments import cli
from gmr_jax import config, mdgps, policies, runner, sharding


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks.determinism", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--algorithm", default="gmr", choices=tuple(policies.ALGORITHMS))
    p.add_argument("--scenario", default="AB")
    p.add_argument("--compiles", type=int, default=3)
    cli.add_precision_argument(p)
    args = p.parse_args(argv)
    args.precision = cli.setup_jax(args.precision)
    cfg = runner.program_config(config.reach(args.scenario, args.algorithm, sim__backend="mujoco"))
    init_keys, it_keys = runner.seed_keys(cfg, [0])
    state = runner._program("init", sharding.seed_mesh(1))(cfg, init_keys)
    vmapped = jax.jit(lambda c, s, k, f: jax.vmap(functools.partial(mdgps.iteration, c), in_axes=(0, 0, None))(s, k, f),
                      static_argnums=0)
    print(f"Device: {jax.devices()[0].device_kind}, {args.precision}, jax {jax.__version__}, "
          f"{args.scenario}/{args.algorithm}", flush=True)
    for name, prog in (("runner's program (one seed)", runner._program("step", sharding.seed_mesh(1))),
                       ("vmapped over one seed", vmapped)):
        outs, texts = [], []
        for r in range(args.compiles):
            t0 = time.perf_counter()
            jax.clear_caches()
            with jax.default_matmul_precision(mdgps.MATMUL_PRECISION):
                compiled = prog.lower(cfg, state, it_keys[:, 0], True).compile()
            texts.append(compiled.as_text())
            outs.append(jax.tree_util.tree_leaves(jax.device_get(compiled(state, it_keys[:, 0], True))))
            differ = sum(not np.array_equal(np.asarray(a), np.asarray(b), equal_nan=True)
                         for a, b in zip(outs[0], outs[-1]))
            print(f"  {name}, compile {r}: {time.perf_counter() - t0:5.1f} s, {differ} of {len(outs[0])} "
                  f"output leaves differ from compile 0, HLO text identical: {texts[-1] == texts[0]}", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""Are the runner's programs deterministic? Two checks, printed as lines of "k of n output leaves
differ" against a reference run:

1. Repeated compilation (default): compile the one-seed iteration program several times in this
   process (traced, lowered and compiled anew each time, JAX's caches cleared), run every
   executable on the same inputs and compare the outputs bit for bit with the first compile's,
   for the runner's program (the plain iteration on the squeezed seed) and for the same program
   vmapped over one seed (what the runner compiled before)::

       python -m benchmarks.determinism --algorithm gmr --scenario AB --compiles 3

2. Side by side (``--side-by-side``), as the default run compiles and trains its runs: the
   iteration programs of scenarios A and A,B, each compiled and run alone (the reference), then
   compiled at the same time in two threads and each run alone, then the reference executables
   run at the same time in two threads (``--repeats`` times)::

       python -m benchmarks.determinism --algorithm gmr --side-by-side

Runs on any backend (the CLI's precision and XLA flags, ``experiments.cli.setup_jax``) with the C
MuJoCo backend that the CLI picks for one seed.
"""

from __future__ import annotations

import argparse
import concurrent.futures
import functools
import time

import jax
import numpy as np

from experiments import cli
from gmr_jax import config, mdgps, policies, runner, sharding


def _inputs(scenario: str, algorithm: str):
    """(cfg, initial state [1], first iteration's keys [1]) of a one-seed run."""
    cfg = runner.program_config(config.reach(scenario, algorithm, sim__backend="mujoco"))
    init_keys, it_keys = runner.seed_keys(cfg, [0])
    return cfg, runner._program("init", sharding.seed_mesh(1))(cfg, init_keys), it_keys[:, 0]


def _lower(prog, cfg, state, keys):
    with jax.default_matmul_precision(mdgps.MATMUL_PRECISION):
        return prog.lower(cfg, state, keys, True)


def _run(compiled, state, keys) -> list:
    return jax.tree_util.tree_leaves(jax.device_get(compiled(state, keys, True)))


def _differ(ref: list, got: list) -> str:
    n = sum(not np.array_equal(np.asarray(a), np.asarray(b), equal_nan=True) for a, b in zip(ref, got))
    return f"{n} of {len(ref)} output leaves differ"


def repeated_compiles(algorithm: str, scenario: str, compiles: int) -> None:
    cfg, state, keys = _inputs(scenario, algorithm)
    vmapped = jax.jit(lambda c, s, k, f: jax.vmap(functools.partial(mdgps.iteration, c), in_axes=(0, 0, None))(s, k, f),
                      static_argnums=0)
    for name, prog in (("runner's program (one seed)", runner._program("step", sharding.seed_mesh(1))),
                       ("vmapped over one seed", vmapped)):
        outs, texts = [], []
        for r in range(compiles):
            t0 = time.perf_counter()
            jax.clear_caches()
            compiled = _lower(prog, cfg, state, keys).compile()
            texts.append(compiled.as_text())
            outs.append(_run(compiled, state, keys))
            print(f"  {name}, compile {r}: {time.perf_counter() - t0:5.1f} s, {_differ(outs[0], outs[-1])} "
                  f"from compile 0, HLO text identical: {texts[-1] == texts[0]}", flush=True)


def side_by_side(algorithm: str, repeats: int) -> None:
    prog = runner._program("step", sharding.seed_mesh(1))
    runs = {sc: _inputs(sc, algorithm) for sc in ("A", "AB")}
    ref, alone = {}, {}
    for sc, (cfg, state, keys) in runs.items():
        jax.clear_caches()
        alone[sc] = _lower(prog, cfg, state, keys).compile()
        ref[sc] = _run(alone[sc], state, keys)
    jax.clear_caches()
    lowered = {sc: _lower(prog, *args) for sc, args in runs.items()}
    with concurrent.futures.ThreadPoolExecutor(2) as pool:
        futures = {sc: pool.submit(low.compile) for sc, low in lowered.items()}
        together = {sc: f.result() for sc, f in futures.items()}
        for sc, (cfg, state, keys) in runs.items():
            print(f"  {sc}/{algorithm} compiled side by side, run alone: "
                  f"{_differ(ref[sc], _run(together[sc], state, keys))} from the reference", flush=True)
        for r in range(repeats):
            futures = {sc: pool.submit(_run, alone[sc], args[1], args[2]) for sc, args in runs.items()}
            for sc, f in futures.items():
                print(f"  {sc}/{algorithm} compiled alone, run side by side ({r}): "
                      f"{_differ(ref[sc], f.result())} from the reference", flush=True)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks.determinism", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--algorithm", default="gmr", choices=tuple(policies.ALGORITHMS))
    p.add_argument("--scenario", default="AB", help="scenario of the repeated compilations")
    p.add_argument("--compiles", type=int, default=3)
    p.add_argument("--side-by-side", action="store_true", help="the side-by-side check instead")
    p.add_argument("--repeats", type=int, default=3, help="side-by-side executions")
    cli.add_precision_argument(p)
    args = p.parse_args(argv)
    args.precision = cli.setup_jax(args.precision)
    print(f"Device: {jax.devices()[0].device_kind}, {args.precision}, jax {jax.__version__}, {args.algorithm}",
          flush=True)
    if args.side_by_side:
        side_by_side(args.algorithm, args.repeats)
    else:
        repeated_compiles(args.algorithm, args.scenario, args.compiles)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

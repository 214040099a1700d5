"""What Adam's update alone costs per step on the CPU, against the same memory traffic without
its divisions and square root.

``gmr_jax.adam.adam_update`` repeats ``optax.adam`` operation for operation: per entry three
divisions and a square root (μ/c1, ν/c2, √, the quotient), which a CPU's vector units run far
more slowly than multiplications and additions. This benchmark times a ``lax.scan`` of
``--steps`` updates of a vector of ``--entries`` weights (default: GMR's 21 687) in two forms,
each step's gradient a cheap function of the weights so that the steps stay sequential:

- ``adam``: ``adam_update`` as the S-step runs it;
- ``no_division``: the same loop with multiplications and additions only: μ and ν updated as
  Adam updates them, θ moved by μ·ν instead of Adam's quotient (θ, μ, ν read and written every
  step, and all three returned, so that XLA keeps them in the loop).

Their difference is what the divisions and the square root cost per Adam step::

    python -m benchmarks.adam_cost --out adam.json
    PJRT_NPROC=1 taskset -c 0 python -m benchmarks.adam_cost   # XLA's pool one thread wide
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import platform
import time

import jax
import jax.numpy as jnp

from experiments import cli
from gmr_jax.adam import adam_corrections, adam_update
from gmr_jax.config import SStepConfig

FORMS = ("adam", "no_division")
GMR_WEIGHTS = 21_687
"""The number of GMR's network weights at the paper's sizes (``benchmarks.sstep``'s loop body)."""


def update_loop(form: str, steps: int, cfg: SStepConfig = SStepConfig()):
    """A jitted ``fn(theta [n]) -> (theta, mu, nu)`` after ``steps`` updates of ``form``."""
    if form not in FORMS:
        raise ValueError(f"form {form!r}: choose one of {', '.join(FORMS)}")
    dtype = jnp.zeros(()).dtype
    c1, c2 = adam_corrections(cfg, steps, dtype)

    def body(carry, corrections):
        theta, mu, nu = carry
        grad = 1e-3 * theta + 1e-4  # depends on the weights: the steps stay sequential
        if form == "adam":
            return adam_update(cfg, theta, mu, nu, grad, *corrections), None
        mu = (1 - cfg.b1) * grad + cfg.b1 * mu
        nu = (1 - cfg.b2) * grad ** 2 + cfg.b2 * nu
        return (theta - cfg.lr * mu * nu, mu, nu), None

    def run(theta):
        zeros = jnp.zeros_like(theta)
        return jax.lax.scan(body, (theta, zeros, zeros), (c1, c2))[0]

    return jax.jit(run)


def time_form(form: str, entries: int, steps: int, repeats: int) -> float:
    """The fastest of ``repeats`` timed runs, µs per step (after one run that compiles)."""
    fn = update_loop(form, steps)
    theta = jnp.ones(entries)
    jax.block_until_ready(fn(theta))
    best = float("inf")
    for _ in range(repeats):
        t = time.perf_counter()
        jax.block_until_ready(fn(theta))
        best = min(best, time.perf_counter() - t)
    return best / steps * 1e6


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks.adam_cost", description=__doc__.split("\n\n")[0])
    p.add_argument("--entries", type=cli.positive_int, default=GMR_WEIGHTS, help="weights updated (default: GMR's)")
    p.add_argument("--steps", type=cli.positive_int, default=4000, help="Adam steps per timed run")
    p.add_argument("--repeats", type=cli.positive_int, default=3, help="timed runs per form (the fastest counts)")
    cli.add_precision_argument(p)
    p.add_argument("--out", help="write the results as JSON to this file")
    args = p.parse_args(argv)
    if args.out and not os.path.isdir(os.path.dirname(os.path.abspath(args.out))):
        p.error(f"--out {args.out}: its folder does not exist; create it first")
    args.precision = cli.setup_jax(args.precision)
    dev = jax.devices()[0]
    env = {"date": time.strftime("%Y-%m-%dT%H:%M:%S%z"), "device": dev.device_kind, "platform": dev.platform,
           "cpu": cli.host_cpu()["model"], "precision": args.precision, "jax": jax.__version__,
           "python": platform.python_version(), "XLA_FLAGS": os.environ.get("XLA_FLAGS", ""),
           "PJRT_NPROC": os.environ.get("PJRT_NPROC"), "affinity": sorted(os.sched_getaffinity(0))}
    print(f"Device: {env['device']} ({env['cpu']}), {args.precision}, jax {env['jax']}, "
          f"{args.entries} weights, {args.steps} steps", flush=True)
    rows = {form: time_form(form, args.entries, args.steps, args.repeats) for form in FORMS}
    for form, us in rows.items():
        print(f"{form:12s} {us:8.2f} µs per step", flush=True)
    print(f"divisions and square root: {rows['adam'] - rows['no_division']:.2f} µs per step", flush=True)
    if args.out:
        pathlib.Path(args.out).write_text(json.dumps({"environment": env, "args": vars(args),
                                                      "us_per_step": rows}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

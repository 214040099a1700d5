"""What each part of GMR's CUDA S-step costs: the step's time with that part left out.

The CUDA kernel (``gmr_jax/policies/gmr_cuda.cu``) can be built with *ablations*
(``gmr_cuda.ABLATIONS``, ``$GMR_JAX_CUDA_ABLATE``), each of which leaves one part of the step's
work out: Adam's moments in global memory, the weight gradients' sums over the minibatch, the
forward and input-gradient products, the head, the barriers between phases. The step's time
without a part, against the full step's, is what that part costs on the critical path (parts that
overlap share their cost, so the savings need not add up). The trained weights of an ablated
build are wrong: only its time is measured.

Each variant runs ``python -m benchmarks.sstep --impl cuda`` in its own process (the library is
built once per set of ablations, and a process registers one build)::

    python -m benchmarks.sstep_ablation --variants none,moments,wgrad_sums,all --out a.json

A variant is ``none``, ``all`` or ablations joined by ``+`` (``moments+wgrad_sums``). Needs an
NVIDIA GPU and nvcc.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile

from gmr_jax.policies import gmr_cuda


def parse_variant(text: str) -> tuple[str, ...]:
    """A variant's ablations: ``none`` -> (), ``all`` -> every one, else names joined by ``+``
    (one clear error for an unknown name)."""
    text = text.strip()
    if text == "none":
        return ()
    if text == "all":
        return gmr_cuda.ABLATIONS
    names = tuple(n.strip() for n in text.split("+"))
    unknown = [n for n in names if n not in gmr_cuda.ABLATIONS]
    if unknown or not all(names):
        raise SystemExit(f"sstep_ablation: unknown ablation {'+'.join(unknown) or text!r} in --variants: use none, "
                         f"all, or names joined by '+' from {', '.join(gmr_cuda.ABLATIONS)}")
    return names


def variant_name(names: tuple[str, ...]) -> str:
    """A variant as ``--variants`` spells it (``none`` for the full step)."""
    return "+".join(names) or "none"


def parse_args(argv=None):
    p = argparse.ArgumentParser(prog="python -m benchmarks.sstep_ablation", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--variants", default="none," + ",".join(gmr_cuda.ABLATIONS) + ",all",
                   help="comma-separated: none, all, or ablations joined by '+'")
    p.add_argument("--scenario", default="AB", help="the data size (benchmarks.sstep's --scenario)")
    p.add_argument("--seeds", type=int, default=1, help="seeds side by side (a block or a cluster each)")
    p.add_argument("--epochs", type=int, help="benchmarks.sstep's --epochs (default: the S-step's)")
    p.add_argument("--cuda-form", default="auto", help="the kernel's launch form (benchmarks.sstep's --cuda-forms)")
    p.add_argument("--timeout", type=float, default=300.0, help="seconds per variant")
    p.add_argument("--out", help="write the results as JSON to this file")
    return p.parse_args(argv)


def run_variant(names: tuple[str, ...], args, out_dir: str) -> dict:
    """One variant's ``benchmarks.sstep`` row (µs per step and the kernel's phases)."""
    out = os.path.join(out_dir, f"{variant_name(names)}.json")
    cmd = [sys.executable, "-m", "benchmarks.sstep", "--algorithm", "gmr", "--scenario", args.scenario,
           "--impl", "cuda", "--cuda-forms", args.cuda_form, "--seeds", str(args.seeds), "--out", out]
    if args.epochs is not None:
        cmd += ["--epochs", str(args.epochs)]
    env = dict(os.environ, GMR_JAX_CUDA_ABLATE=",".join(names))
    try:
        res = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=args.timeout)
    except subprocess.TimeoutExpired:
        raise SystemExit(f"sstep_ablation: variant {variant_name(names)} took more than --timeout "
                         f"{args.timeout:g} s: raise --timeout (the variants measured before it are in --out)") from None
    if res.returncode != 0:
        raise SystemExit(f"sstep_ablation: variant {variant_name(names)} failed ({' '.join(cmd)}):\n"
                         f"{res.stderr[-2000:]}")
    with open(out) as f:
        data = json.load(f)
    return {"env": data["env"], **data["rows"][0]}


def main(argv=None) -> int:
    args = parse_args(argv)
    variants = [parse_variant(v) for v in args.variants.split(",")]
    rows, env = [], {}
    with tempfile.TemporaryDirectory() as tmp:
        for names in variants:
            row = run_variant(names, args, tmp)
            variant_env = row.pop("env")
            env = env or dict(variant_env, nvcc=_nvcc_version())
            row["ablations"] = list(names)
            rows.append(row)
            print(f"{variant_name(names):>48}: {row['us_per_step']:7.2f} µs/step"
                  f"{'' if row['finite'] else ' (non-finite weights)'}", flush=True)
            if args.out:  # after every variant: a later failure keeps what was measured
                with open(args.out, "w") as f:
                    json.dump({"env": env, "args": vars(args), "rows": rows}, f, indent=1)
    full = next((r["us_per_step"] for r in rows if not r["ablations"]), None)
    if full is not None:
        print(f"\nfull step {full:.2f} µs; each variant's saving:")
        for r in rows:
            if r["ablations"]:
                print(f"{variant_name(r['ablations']):>48}: {full - r['us_per_step']:7.2f} µs "
                      f"({(full - r['us_per_step']) / full:6.1%})")
    return 0


def _nvcc_version() -> str:
    try:
        return subprocess.run(["nvcc", "--version"], capture_output=True, text=True).stdout.strip().splitlines()[-1]
    except (OSError, IndexError):
        return ""


if __name__ == "__main__":
    raise SystemExit(main())

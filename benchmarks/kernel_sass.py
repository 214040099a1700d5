"""The GMR kernel's machine code without a GPU: registers, stack, spills, instructions per line.

The S-step's kernel form (``gmr_jax.policies.gmr_kernel``) is lowered for CUDA on this machine
(Pallas emits Triton IR without a device), compiled with the ``triton`` package's compiler and
its ptxas for sm_90a (H100), and disassembled with line information, so that the Python lines
of the kernel that cost the most instructions and spills show up without device time::

    pip install triton          # not a dependency of gmr-jax; its wheel brings ptxas and nvdisasm
    python -m benchmarks.kernel_sass --scenario A --num-warps 8 --kernel-dot tf32x3 --out sass.json

It reports ptxas's registers, stack and spill bytes per thread, and the kernel's instructions
(nearly all of them in the body of its step loop, which a warp runs once per Adam step) by
opcode and by source line of ``gmr_kernel.py``, with their local-memory loads and stores (LDL,
STL: spills). Triton's version differs from the one inside XLA, so these are estimates; for the
H100 they matched Nsight Compute's registers (32 and 255 per thread) and came within 5–20 % of
its stack size (``benchmarks/RESULTS.md``, tenth session).

The Triton IR is captured from a private JAX function (the Pallas lowering), so this tool may
need updating with JAX.
"""

from __future__ import annotations

import argparse
import collections
import contextlib
import json
import os
import re
import subprocess
import tempfile

import jax
import jax.numpy as jnp

from gmr_jax import config, mdgps, policies, sstep
from gmr_jax.policies import gmr_kernel

SASS_INSTRUCTION = re.compile(r"/\*[0-9a-f]{4,}\*/\s+(?:@!?U?P\w+\s+)?([A-Z][A-Z0-9_]*)")
SASS_LINE = re.compile(r'//## File "([^"]+)", line (\d+)')
PTXAS_STATS = re.compile(r"(\d+) bytes stack frame, (\d+) bytes spill stores, (\d+) bytes spill loads")
PTXAS_REGISTERS = re.compile(r"Used (\d+) registers")
IR_LOCATION = re.compile(r'loc\("([^"]+)":(\d+):')
FILE_STRIDE = 100_000
"""Triton's line information keeps the line of every operation but one file name per kernel, so
the IR's lines are renumbered FILE_STRIDE·(file index) + line before compiling and decoded after."""


def parse_args(argv=None):
    p = argparse.ArgumentParser(prog="python -m benchmarks.kernel_sass", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--scenario", default="A", help="reach scenario (data size)")
    p.add_argument("--num-warps", type=int, default=gmr_kernel.NUM_WARPS)
    p.add_argument("--kernel-dot", default=gmr_kernel.DOT, choices=gmr_kernel.DOTS)
    p.add_argument("--epochs", type=int, default=10, help="S-step epochs (the loop's length only)")
    p.add_argument("--top", type=int, default=15, help="source lines to print")
    p.add_argument("--keep", metavar="DIR", help="keep the Triton IR, PTX, cubin and SASS here")
    p.add_argument("--out", help="write the results as JSON to this file")
    return p.parse_args(argv)


def triton_ir(scenario: str, num_warps: int, dot: str, epochs: int) -> str:
    """The Triton IR (text, with source locations) of the float32 GMR S-step kernel."""
    from jax._src.pallas.triton import lowering

    from benchmarks.sstep import synthetic_data

    captured = []
    original = lowering.lower_jaxpr_to_triton_module

    def capture(*args, **kwargs):
        result = original(*args, **kwargs)
        captured.append(result.module.operation.get_asm(enable_debug_info=True, pretty_debug_info=False))
        return result

    cfg = config.reach(scenario, "gmr", sstep__epochs=epochs)
    pol = policies.for_config(cfg)
    params = mdgps.init(cfg, jax.random.PRNGKey(0)).policy.params  # float32: x64 is off (main)
    data = synthetic_data(cfg, jax.random.PRNGKey(1), jnp.float32)
    fit = gmr_kernel.fit

    def fit_on_gpu(*args, **kwargs):
        return fit(*args, **{**kwargs, "interpret": False, "num_warps": num_warps, "dot": dot})

    lowering.lower_jaxpr_to_triton_module, gmr_kernel.fit = capture, fit_on_gpu
    try:
        fn = jax.jit(lambda p, d, k: sstep.sstep(pol, p, d, k, cfg.sstep, impl="kernel"))
        with jax.default_matmul_precision(mdgps.MATMUL_PRECISION):
            fn.trace(params, data, jax.random.PRNGKey(2)).lower(lowering_platforms=("cuda",))
    finally:
        lowering.lower_jaxpr_to_triton_module, gmr_kernel.fit = original, fit
    if not captured:
        raise RuntimeError("kernel_sass: the S-step did not lower a Pallas kernel")
    return captured[-1]


def encode_files(ir: str) -> tuple[str, list[str]]:
    """The IR with each location's line renumbered FILE_STRIDE·k + line (k: 1 + the file's index
    in the returned list of files)."""
    files: list[str] = []

    def renumber(m):
        if m.group(1) not in files:
            files.append(m.group(1))
        return f'loc("{m.group(1)}":{FILE_STRIDE * (files.index(m.group(1)) + 1) + int(m.group(2))}:'

    return IR_LOCATION.sub(renumber, ir), files


def _tool(triton_dir: str, names) -> str:
    for name in names:
        path = os.path.join(triton_dir, "backends", "nvidia", "bin", name)
        if os.path.exists(path):
            return path
    raise FileNotFoundError(f"kernel_sass: none of {names} in the triton package ({triton_dir})")


def compile_kernel(ir: str, num_warps: int, workdir: str) -> dict:
    """Triton IR -> PTX (``triton.compile`` for sm_90), then ptxas -v -lineinfo and nvdisasm -g.
    Returns {"ptxas": stats, "sass": disassembly text}."""
    try:
        import triton
        from triton.backends.compiler import GPUTarget
    except ImportError as e:
        raise SystemExit("kernel_sass: needs the triton package (pip install triton)") from e
    ir_path = os.path.join(workdir, "kernel.ttir")
    with open(ir_path, "w") as f:
        f.write(ir)
    os.environ.setdefault("TRITON_DEFAULT_FP_FUSION", "1")  # Triton's default, stated
    compiled = triton.compile(ir_path, target=GPUTarget("cuda", 90, 32),
                              options={"num_warps": num_warps, "num_stages": 1})
    ptx_path, cubin_path = os.path.join(workdir, "kernel.ptx"), os.path.join(workdir, "kernel.cubin")
    with open(ptx_path, "w") as f:
        f.write(compiled.asm["ptx"])
    triton_dir = os.path.dirname(triton.__file__)
    # the newest ptxas of the wheel reads the PTX version that this Triton writes
    ptxas = _tool(triton_dir, ("ptxas-blackwell", "ptxas"))
    out = subprocess.run([ptxas, "-arch=sm_90a", "-v", "-lineinfo", ptx_path, "-o", cubin_path],
                         capture_output=True, text=True, check=True)
    sass = subprocess.run([_tool(triton_dir, ("nvdisasm",)), "-g", "-c", cubin_path],
                          capture_output=True, text=True, check=True).stdout
    return {"ptxas": ptxas_stats(out.stdout + out.stderr), "sass": sass}


def ptxas_stats(text: str) -> dict:
    """ptxas -v output -> {registers, stack_bytes, spill_store_bytes, spill_load_bytes}."""
    stats, regs = PTXAS_STATS.search(text), PTXAS_REGISTERS.search(text)
    if stats is None or regs is None:
        raise ValueError(f"kernel_sass: no register or stack line in ptxas's output: {text[:300]!r}")
    stack, stores, loads = (int(g) for g in stats.groups())
    return {"registers": int(regs.group(1)), "stack_bytes": stack, "spill_store_bytes": stores,
            "spill_load_bytes": loads}


def sass_by_line(sass: str, files: list[str]) -> dict:
    """nvdisasm -g text of a kernel compiled from ``encode_files``'s IR -> instruction counts:
    "opcodes" (all), and "lines": for each "file:line" the instructions, LDL and STL attributed
    to it ("?" before any line information)."""
    opcodes = collections.Counter()
    lines = collections.defaultdict(collections.Counter)
    line = "?"
    for text in sass.splitlines():
        m = SASS_LINE.search(text)
        if m:
            k, n = divmod(int(m.group(2)), FILE_STRIDE)
            line = f"{os.path.basename(files[k - 1])}:{n}" if 0 < k <= len(files) else "?"
            continue
        m = SASS_INSTRUCTION.search(text)
        if m:
            op = m.group(1)
            opcodes[op] += 1
            lines[line]["instructions"] += 1
            if op in ("LDL", "STL"):
                lines[line][op] += 1
    return {"opcodes": dict(opcodes.most_common()), "lines": {k: dict(v) for k, v in lines.items()}}


def main(argv=None) -> int:
    args = parse_args(argv)
    jax.config.update("jax_enable_x64", False)
    ir, files = encode_files(triton_ir(args.scenario, args.num_warps, args.kernel_dot, args.epochs))
    with (contextlib.nullcontext(args.keep) if args.keep else tempfile.TemporaryDirectory()) as workdir:
        os.makedirs(workdir, exist_ok=True)
        print(f"compiling the kernel's Triton IR ({len(ir) // 1000} kB) for sm_90a (a minute or two) ...", flush=True)
        result = compile_kernel(ir, args.num_warps, workdir)
        if args.keep:
            with open(os.path.join(workdir, "kernel.sass"), "w") as f:
                f.write(result["sass"])
    counts = sass_by_line(result["sass"], files)
    total = sum(counts["opcodes"].values())
    stats = result["ptxas"]
    print(f"GMR kernel, scenario {args.scenario}, {args.num_warps} warps, {args.kernel_dot} products (sm_90a, "
          f"triton {__import__('triton').__version__}): {stats['registers']} registers, stack "
          f"{stats['stack_bytes']} B, spill stores {stats['spill_store_bytes']} B, loads "
          f"{stats['spill_load_bytes']} B per thread")
    print(f"{total} instructions in the kernel, by opcode: "
          + ", ".join(f"{k} {v}" for k, v in list(counts["opcodes"].items())[:14]))
    sources = {os.path.basename(f): f for f in files}
    print("costliest source lines (instructions, LDL, STL):")
    ranked = sorted(counts["lines"].items(), key=lambda kv: -kv[1]["instructions"])
    for where, c in ranked[: args.top]:
        name, _, n = where.partition(":")
        text = ""
        if name in sources and os.path.exists(sources[name]):
            with open(sources[name]) as f:
                src = f.read().splitlines()
            text = src[int(n) - 1].strip() if 0 < int(n) <= len(src) else ""
        print(f"  {where:24s} {c['instructions']:6d} {c.get('LDL', 0):5d} {c.get('STL', 0):5d}  {text[:70]}")
    if args.out:
        with open(args.out, "w") as f:
            json.dump({"args": vars(args), "triton": __import__("triton").__version__, "jax": jax.__version__,
                       "ptxas": stats, **counts}, f, indent=1)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

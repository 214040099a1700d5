"""Wall time of one S-step (the supervised policy fit), per Adam step.

The S-step is 400 epochs of minibatch Adam steps, strictly sequential, so on a GPU its time is
set by the latency of one step (kernel launches), not by arithmetic. This benchmark times one
S-step of the chosen policy on a data set of the reach study's size (scenario A: B = 400 sampled
states, GMR adds the 80 forward-pass means; AB doubles both) for several loop unroll factors::

    python -m benchmarks.sstep --algorithm gmr,mdgps --scenario A,AB --unroll 1,4,16 --out s.json

The S-step is traced with full float32 matrix products, as training traces it
(``mdgps.MATMUL_PRECISION``; a GPU's float32 default is TF32). The data are synthetic (random
states, gains, symmetric positive-definite precisions and state covariances) with the shapes of
the real ones: the time of a step does not depend on the values. ``--adam-entries all,trained``
times the packed form with Adam over the whole packed vector and over its trained entries only
(``SStepConfig.adam_entries``) in the same run, ``--statistics epoch,step`` with the loss's
statistics evaluated per epoch from the kept weights and inside every step
(``SStepConfig.statistics``), ``--statistics-epochs last,all`` with the statistics of the last
epoch only and of every epoch (``SStepConfig.statistics_epochs``). ``--profile DIR`` adds the
GPU's view (``benchmarks.trace``): kernels per Adam step, the device's busy and idle time, the
costliest kernels.

``--impl packed,cuda`` times GMR's hand-written CUDA kernel (``impl="cuda"``, nvcc needed) beside
the packed form and adds, to the JSON and the printout, the kernel's own clock cycles per phase of
its program as µs per Adam step (``cuda_phases``: their shares of the measured step).
``--impl packed,reference`` times the S-step's packed form (``gmr_jax.sstep`` ``impl="packed"``,
the default on a GPU; the benchmark's default) beside the reference form it is tested against
(autodiff of the policy's loss in a loop per epoch; the default on a CPU), in the same run.
Each S-step is traced and compiled as the runner does for that many seeds on one device
(``sharding.seed_block``, ``sharding.compiler_options``);
``--compiler-options runner,none`` adds XLA's defaults (traced plainly) in the same run.
``--against-float64`` also trains each S-step in float64 from the same data and initial weights,
and reports how far the measured precision's trained weights lie from those: the forms' and
options' round-off, measured against the exact arithmetic's result rather than against each
other. Every row also counts the operations of the compiled
minibatch loop's body (the while-loop body of the optimised HLO that launches the most matrix
products; ``body_ops`` by opcode, ``ops_per_step`` = all but parameters, tuples, constants and
bitcasts, divided by the steps per iteration). On a GPU each of those operations is a kernel
launch; on a CPU the count is only a guide (XLA fuses differently there, and the CPU runs the
random number generator as a loop where a GPU runs one kernel).
"""

from __future__ import annotations

import argparse
import collections
import contextlib
import functools
import hashlib
import json
import os
import platform
import re
import statistics
import time

import jax
import jax.numpy as jnp
import numpy as np

from benchmarks import trace
from experiments import cli
from jax.flatten_util import ravel_pytree

from gmr_jax import config, mdgps, policies, sharding, sstep, tasks
from gmr_jax.policies import gmr_cuda, gmr_kernel


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


# HLO instructions that launch nothing: they name or regroup buffers.
FREE_OPS = frozenset({"parameter", "get-tuple-element", "tuple", "constant", "bitcast"})


def _hlo_computations(text: str) -> dict[str, list[str]]:
    """Optimised HLO text -> {computation name: its instruction lines}."""
    comps, name = {}, None
    for line in text.splitlines():
        if name is None:
            m = re.match(r"^(?:ENTRY )?%?([\w.\-]+) .*\{\s*$", line)
            if m:
                name, comps[m.group(1)] = m.group(1), []
        elif line.startswith("}"):
            name = None
        else:
            comps[name].append(line)
    return comps


def _hlo_opcode(line: str) -> str | None:
    """The opcode of one HLO instruction line (None for other lines)."""
    m = re.match(r"\s*(?:ROOT )?%?[\w.\-]+ = (.*)$", line)
    if not m:
        return None
    rest = m.group(1)
    if rest.startswith("("):  # a tuple shape: skip to its closing parenthesis
        depth = 0
        for i, c in enumerate(rest):
            depth += (c == "(") - (c == ")")
            if depth == 0:
                rest = rest[i + 1:]
                break
    else:
        rest = rest.split(" ", 1)[1]
    return rest.strip().split("(", 1)[0]


def _count_ops(comps: dict[str, list[str]], name: str) -> collections.Counter:
    """Operations by opcode of one computation, without FREE_OPS, counting a ``call`` of a GPU
    command buffer (XLA outlines launch sequences into computations named command_buffer…) as
    the operations of the computation it calls."""
    ops = collections.Counter()
    for line in comps[name]:
        op = _hlo_opcode(line)
        if op is None or op in FREE_OPS:
            continue
        callee = re.search(r"to_apply=%?(command_buffer[\w.\-]*)", line) if op == "call" else None
        if callee and callee.group(1) in comps:
            ops += _count_ops(comps, callee.group(1))
        else:
            ops[op] += 1
    return ops


def _products(comps: dict[str, list[str]], name: str) -> int:
    """Matrix products launched by one computation: dots, GEMM custom calls (cuBLAS) and fusions
    around a dot (Triton GEMMs, the CPU's dot fusions), not those inside nested loops."""
    count = 0
    for line in comps[name]:
        op = _hlo_opcode(line)
        callee = re.search(r"calls=%?([\w.\-]+)", line)
        if (op == "dot" or (op == "custom-call" and "gemm" in line.lower())
                or (op == "fusion" and callee and any(_hlo_opcode(x) == "dot" for x in comps.get(callee.group(1), [])))):
            count += 1
    return count


def loop_body_ops(hlo_text: str) -> dict[str, int]:
    """Operations by opcode in the body of an optimised HLO module's S-step loop, without
    FREE_OPS: the while loop whose body launches the most matrix products (the networks'),
    {} if there is none."""
    comps = _hlo_computations(hlo_text)
    best, best_key = {}, (0, 0)
    for lines in comps.values():
        for line in lines:
            if _hlo_opcode(line) == "while":
                body = re.search(r"body=%?([\w.\-]+)", line).group(1)
                ops = _count_ops(comps, body)
                key = (_products(comps, body), sum(ops.values()))
                if key > best_key:
                    best, best_key = ops, key
    return dict(sorted(best.items(), key=lambda kv: (-kv[1], kv[0])))


def parse_args(argv=None):
    p = argparse.ArgumentParser(prog="python -m benchmarks.sstep", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--algorithm", default="gmr,mdgps", help="comma-separated: gmr, mdgps")
    p.add_argument("--scenario", default="A", help="comma-separated scenarios (data size)")
    p.add_argument("--unroll", default="1", help="comma-separated unroll factors")
    p.add_argument("--impl", default="packed", help="comma-separated S-step forms: cuda, kernel, packed, reference")
    p.add_argument("--num-warps", default=str(gmr_kernel.NUM_WARPS),
                   help="comma-separated warps per thread block of the kernel form")
    p.add_argument("--kernel-dot", default=gmr_kernel.DOT,
                   help=f"comma-separated matrix-product forms of the kernel form ({', '.join(gmr_kernel.DOTS)})")
    p.add_argument("--cuda-forms", default="auto",
                   help="comma-separated launch forms of impl cuda (gmr_cuda.FORMS, BLOCKSxTHREADS: blocks per "
                        "seed, 1 or a thread-block cluster, and threads per block), or auto (the library's choice)")
    p.add_argument("--epochs", type=int, default=config.SStepConfig.epochs)
    p.add_argument("--batch-size", type=cli.positive_int, default=config.SStepConfig.batch_size,
                   help="rows per minibatch (default: the paper's %(default)s); with several values in "
                        "separate runs, the time per Adam step against the rows tells a step's fixed cost "
                        "from its cost per row")
    p.add_argument("--statistics", default=config.SStepConfig.statistics,
                   help=f"comma-separated sstep.statistics of the packed form ({', '.join(config.SSTEP_STATISTICS)}): "
                        "the loss's statistics per epoch from the kept weights, or inside every step")
    p.add_argument("--statistics-epochs", default=config.SStepConfig.statistics_epochs,
                   help=f"comma-separated sstep.statistics_epochs ({', '.join(config.SSTEP_STATISTICS_EPOCHS)}): "
                        "the statistics of the last epoch only, or of every epoch (default: %(default)s)")
    p.add_argument("--adam-entries", default=config.SStepConfig.adam_entries,
                   help=f"comma-separated sstep.adam_entries of the packed form ({', '.join(config.SSTEP_ADAM_ENTRIES)}; "
                        "default: %(default)s)")
    p.add_argument("--repeats", type=int, default=3, help="timed S-steps (median)")
    p.add_argument("--seeds", type=int, default=1,
                   help="S-steps side by side (jax.vmap over params and data, as over seeds)")
    cli.add_precision_argument(p)
    p.add_argument("--matmul-precision", default=mdgps.MATMUL_PRECISION,
                   help="comma-separated jax.default_matmul_precision values to trace the S-step "
                        "under (default: training's, %(default)s; e.g. TF32_TF32_F32_X3: three "
                        "TF32 tensor-core products per product, about float32's accuracy)")
    p.add_argument("--compiler-options", default="runner",
                   help="comma-separated: runner (the XLA options the runner compiles --seeds seeds "
                        "per device with, sharding.compiler_options), none (XLA's defaults), or "
                        "options of your own as NAME=VALUE joined by '+', e.g. "
                        "xla_gpu_enable_triton_gemm=false")
    p.add_argument("--against-float64", action="store_true",
                   help="also train each S-step in float64 from the same data and initial weights "
                        "(generated in float64, rounded to the measured precision) and report "
                        "max |θ - θ64| / max |θ64| of the trained weights")
    p.add_argument("--out", help="write the results as JSON to this file")
    p.add_argument("--hlo-dir", help="also write each compiled program's HLO text here")
    p.add_argument("--profile", metavar="DIR", help="also run each S-step once under JAX's profiler "
                   "(trace written under DIR) and report its kernels per Adam step, their busy time and "
                   "the device's idle share (GPU only; benchmarks.trace)")
    args = p.parse_args(argv)
    for flag, value, allowed in (("--adam-entries", args.adam_entries, config.SSTEP_ADAM_ENTRIES),
                                 ("--statistics", args.statistics, config.SSTEP_STATISTICS),
                                 ("--statistics-epochs", args.statistics_epochs, config.SSTEP_STATISTICS_EPOCHS),
                                 ("--kernel-dot", args.kernel_dot, gmr_kernel.DOTS)):
        bad = [v for v in value.split(",") if v not in allowed]
        if bad:
            p.error(f"{flag}: {', '.join(bad)} not among {', '.join(allowed)}")
    for value in args.compiler_options.split(","):
        try:
            compiler_options(value, 1)
        except ValueError as err:
            p.error(f"--compiler-options {value!r}: {err}")
    for value in args.matmul_precision.split(","):
        try:
            with jax.default_matmul_precision(value):
                pass
        except ValueError as err:
            p.error(f"--matmul-precision {value!r}: {err}")
    return args


def measure(algorithm: str, scenario: str, unroll: int, impl: str, args, dtype,
            adam_entries: str = config.SStepConfig.adam_entries,
            matmul_precision: str = mdgps.MATMUL_PRECISION, options: str = "runner",
            stats_at: str = config.SStepConfig.statistics,
            stats_epochs: str = config.SStepConfig.statistics_epochs,
            cuda_form: str | None = None) -> tuple[dict, jax.Array]:
    """Compile and time one S-step configuration (``options``: the runner's XLA options or
    none); returns its result row (and prints it) and the trained weights of the first timed
    S-step, [seeds, n]."""
    tag = (f"{algorithm}_{scenario}_u{unroll}_{impl}" + (f"_{adam_entries}_{stats_at}" if impl == "packed" else "")
           + ("" if stats_epochs == config.SStepConfig.statistics_epochs else f"_{stats_epochs}")
           + ("" if matmul_precision == mdgps.MATMUL_PRECISION else f"_{matmul_precision}")
           + ("" if options == "runner" else f"_{options}")
           + ("" if args.batch_size == config.SStepConfig.batch_size else f"_b{args.batch_size}")
           + ("" if cuda_form in (None, "auto") else f"_{cuda_form}"))
    options_given = compiler_options(options, args.seeds)
    # the runner traces a program of n seeds per device under its choices for n (seed_block)
    traced_as = (functools.partial(sharding.seed_block, args.seeds) if options == "runner"
                 else contextlib.nullcontext)
    cfg = config.reach(scenario, algorithm, sstep__epochs=args.epochs, sstep__unroll=unroll,
                       sstep__adam_entries=adam_entries, sstep__statistics=stats_at,
                       sstep__statistics_epochs=stats_epochs, sstep__batch_size=args.batch_size)
    pol = policies.for_config(cfg)
    # with --against-float64, the data and initial weights are made in float64 and rounded
    made = jnp.float64 if args.against_float64 else dtype
    if args.seeds == 1:
        params = mdgps.init(cfg, jax.random.PRNGKey(0)).policy.params
        data = synthetic_data(cfg, jax.random.PRNGKey(1), made)
        fn = jax.jit(lambda p, d, k: sstep.sstep(pol, p, d, k, cfg.sstep, impl=impl))
    else:
        keys = jax.random.split(jax.random.PRNGKey(0), args.seeds)
        params = jax.vmap(lambda k: mdgps.init(cfg, k).policy.params)(keys)
        data = jax.vmap(lambda k: synthetic_data(cfg, k, made))(keys)
        fn = jax.jit(lambda p, d, k: jax.vmap(lambda p, d, k: sstep.sstep(pol, p, d, k, cfg.sstep, impl=impl))(
            p, d, jax.random.split(k, args.seeds)))
    if data.x.shape[-2] < cfg.sstep.batch_size:
        raise SystemExit(f"--batch-size {cfg.sstep.batch_size}: more than the {data.x.shape[-2]} rows of "
                         f"{algorithm} {scenario}'s data set; use at most {data.x.shape[-2]}")
    exact = None
    if args.against_float64:
        params, data = _as_float(params, jnp.float64), _as_float(data, jnp.float64)
        with jax.default_matmul_precision(matmul_precision), traced_as():
            net64 = fn.lower(params, data, jax.random.PRNGKey(2)).compile(
                compiler_options=options_given or None)(params, data, jax.random.PRNGKey(3))[0].net
        exact = _flat_weights(net64, args.seeds)
        params, data = _as_float(params, dtype), _as_float(data, dtype)
    clocks = []  # the CUDA form's profile: clock cycles per phase of each S-step run
    t0 = time.perf_counter()
    with jax.default_matmul_precision(matmul_precision), traced_as(), _cuda_clocks(clocks, impl == "cuda"):
        compiled = fn.lower(params, data, jax.random.PRNGKey(2)).compile(compiler_options=options_given or None)
    compile_s = time.perf_counter() - t0
    with traced_as():
        resolved = sstep.resolve_statistics(stats_at, sharding.block_seeds(), sharding.target_platform())
    hlo = compiled.as_text()
    if args.hlo_dir:
        os.makedirs(args.hlo_dir, exist_ok=True)
        with open(os.path.join(args.hlo_dir, f"{tag}.hlo"), "w") as f:
            f.write(hlo)
    times = []
    for r in range(args.repeats):
        t0 = time.perf_counter()
        out, info = compiled(params, data, jax.random.PRNGKey(3 + r))
        jax.block_until_ready(out)
        times.append(time.perf_counter() - t0)
        if r == 0:
            weights = _flat_weights(out.net, args.seeds)
            finite = bool(jnp.all(info["finite"]))
    nb = data.x.shape[-2] // cfg.sstep.batch_size
    steps = args.epochs * nb
    # steps per iteration of the minibatch loop: "packed" loops over all steps, "reference"
    # over one epoch's
    per_iteration = min(unroll, steps if impl == "packed" else nb)
    body = loop_body_ops(hlo)
    run_s = statistics.median(times)
    profile = None
    if args.profile:
        with trace.recorded(os.path.join(args.profile, tag)) as rec:
            jax.block_until_ready(compiled(params, data, jax.random.PRNGKey(3)))
        profile = trace.kernel_summary(trace.device_events(rec[0]), steps)
        profile["device_lines"] = trace.device_lines(rec[0])
    row = {"algorithm": algorithm, "scenario": scenario, "unroll": unroll, "impl": impl,
           "matmul_precision": matmul_precision, "compiler_options": options_given,
           "adam_entries": adam_entries if impl == "packed" else None,
           "statistics": stats_at if impl == "packed" else None,
           "statistics_resolved": resolved if impl == "packed" else None,
           "statistics_epochs": stats_epochs,
           "num_warps": gmr_kernel.NUM_WARPS if impl == "kernel" else None,
           "dot": gmr_kernel.DOT if impl == "kernel" else None,
           "cuda_form": cuda_form,
           # the form the kernel reports it ran (for "auto", the library's choice for these seeds)
           "cuda_form_used": _cuda_form_used(clocks),
           "rows": int(data.x.shape[-2]), "batch_size": cfg.sstep.batch_size, "adam_steps": steps, "compile_s": compile_s,
           "run_s": run_s, "us_per_step": 1e6 * run_s / steps, "finite": finite, "seeds": args.seeds,
           "body_ops": body, "ops_per_step": sum(body.values()) / per_iteration, "profile": profile,
           # to tell whether two processes (e.g. other XLA_FLAGS) trained bit-identical weights
           "weights_sha256": hashlib.sha256(np.asarray(weights).tobytes()).hexdigest()}
    if exact is not None:
        row.update({f"{k}_vs_float64": v for k, v in _relative_differences(weights, exact).items()})
    if clocks:
        row["cuda_phases"] = _cuda_phases(cfg, data, clocks, steps, row["us_per_step"])
    name = (f"{impl}/{row['num_warps']}/{row['dot']}" if impl == "kernel"
            else f"{impl}/{adam_entries}/{stats_at}" if impl == "packed"
            else f"{impl}/{cuda_form}" + ("" if cuda_form == row["cuda_form_used"] else f"={row['cuda_form_used']}")
            if impl == "cuda" else impl)
    if stats_epochs != config.SStepConfig.statistics_epochs:
        name += f"/{stats_epochs}"
    if matmul_precision != mdgps.MATMUL_PRECISION:
        name += f"/{matmul_precision}"
    if options != "runner":
        name += f"/{options}"
    print(f"{algorithm:5s} {scenario:2s} seeds {args.seeds} unroll {unroll:3d} {name:16s}: {run_s:7.3f} s for {steps} steps "
          f"= {row['us_per_step']:6.1f} µs/step (compile {compile_s:.1f} s), "
          f"{row['ops_per_step']:.1f} ops/step in the loop body {body}", flush=True)
    if profile and profile["kernels"]:
        print(f"    profile: {profile['kernels_per_step']:.1f} kernels/step, device busy "
              f"{profile['busy_us_per_step']:.1f} of {profile['span_us_per_step']:.1f} µs/step "
              f"(idle {100 * profile['idle_fraction']:.0f} %), median kernel {profile['kernel_us_median']:.2f} µs, "
              f"median gap {profile['gap_us_median']:.2f} µs", flush=True)
        for k in profile["top"][:6]:
            print(f"      {k['us_per_step']:7.2f} µs/step  ×{k['count']:6d}  {k['name'][:90]}", flush=True)
    elif profile is not None:
        print("    profile: no device kernels in the trace (not a GPU)", flush=True)
    if exact is not None:
        print(f"    max |θ - θ64| / max |θ64|: {_describe(row, '_vs_float64', args.seeds)}", flush=True)
    for ph in sorted(row.get("cuda_phases") or [], key=lambda p: -p["us_per_step"])[:8]:
        print(f"    phase {ph['phase']:2d}: {ph['us_per_step']:6.2f} µs/step  {', '.join(ph['tasks'])}", flush=True)
    return row, weights


@contextlib.contextmanager
def _cuda_clocks(out: list, on: bool):
    """While tracing: the CUDA form's launches also return their clock cycles per phase and the
    launch form that ran, which each run of the program appends to ``out`` ((program ints, cycles
    [phases + 1], form) per launch)."""
    if not on:
        yield
        return
    launch = gmr_cuda.launch

    def profiled(inp, smem_bytes):
        theta, stats, cycles, form = launch(inp, smem_bytes, cycles=True)
        jax.debug.callback(lambda c, f: out.append((inp.program, np.asarray(c), np.asarray(f))), cycles, form)
        return theta, stats
    gmr_cuda.launch = profiled
    try:
        yield
    finally:
        gmr_cuda.launch = launch


def _cuda_form_used(clocks) -> str | None:
    """The launch form the first timed run reports (every seed's; one form per launch)."""
    if not clocks:
        return None
    codes = {int(c) for c in np.asarray((clocks[1] if len(clocks) > 1 else clocks[0])[2]).reshape(-1)}
    return ",".join(gmr_cuda.form_name(c) for c in sorted(codes))


def _cuda_phases(cfg, data, clocks, steps: int, us_per_step: float) -> list[dict]:
    """The first timed run's clock cycles per phase as µs per Adam step (the cycles' shares of
    the measured step) with each phase's tasks. Seeds side by side: the first seed's block."""
    ints, cycles, _ = clocks[1] if len(clocks) > 1 else clocks[0]
    cycles = np.asarray(cycles).reshape(-1, np.asarray(cycles).shape[-1])[0]
    dX, dU = data.x.shape[-1], data.tgt_mu.shape[-1]
    names = [L.name for L in gmr_cuda.compact(gmr_kernel.layout(cfg.gmr, dX, dU, cfg.sstep.batch_size))]
    tasks = gmr_cuda.phase_tasks(np.asarray(ints), names) + [["statistics"]]
    total = float(np.sum(cycles))
    return [{"phase": p, "tasks": t, "cycles_per_step": float(c) / steps, "us_per_step": us_per_step * float(c) / total}
            for p, (t, c) in enumerate(zip(tasks, cycles))]


def compiler_options(spec: str, seeds: int) -> dict:
    """One ``--compiler-options`` entry as XLA options: "runner" (``sharding.compiler_options``
    for ``seeds`` seeds on one device), "none" ({}), or NAME=VALUE pairs joined by "+" (VALUE
    true/false, an integer, or a string)."""
    if spec == "runner":
        return sharding.compiler_options(seeds)
    if spec == "none":
        return {}
    options = {}
    for pair in spec.split("+"):
        name, sep, value = pair.partition("=")
        if not sep or not name:
            raise ValueError(f"{pair!r} is not NAME=VALUE (or runner, none)")
        low = value.lower()
        options[name] = (low == "true" if low in ("true", "false")
                         else int(value) if value.lstrip("-").isdigit() else value)
    return options


def _as_float(tree, dtype):
    """``tree`` with its floating-point leaves cast to ``dtype`` (other leaves as they are)."""
    return jax.tree_util.tree_map(
        lambda a: a.astype(dtype) if jnp.issubdtype(a.dtype, jnp.floating) else a, tree)


def _flat_weights(net, seeds: int) -> jax.Array:
    """[seeds, n]: each seed's trained weights as one vector (in their own dtype)."""
    return ravel_pytree(net)[0][None] if seeds == 1 else jax.vmap(lambda n: ravel_pytree(n)[0])(net)


def per_seed_relative_differences(weights, reference):
    """[seeds]: each seed's max |weights − reference| / max |reference| ([seeds, n] each, computed in
    the reference's dtype)."""
    weights = weights.astype(reference.dtype)
    return jnp.max(jnp.abs(weights - reference), axis=1) / jnp.max(jnp.abs(reference), axis=1)


def _relative_differences(weights, reference) -> dict:
    """``per_seed_relative_differences``: the largest and the median over seeds, and the count of
    seeds above 1e-4."""
    per_seed = per_seed_relative_differences(weights, reference)
    return {"max_rel_diff": float(jnp.max(per_seed)), "median_rel_diff": float(jnp.median(per_seed)),
            "seeds_rel_diff_above_1e-4": int(jnp.sum(per_seed > 1e-4))}


def _describe(row: dict, suffix: str, seeds: int) -> str:
    return (f"{row['max_rel_diff' + suffix]:.2e} (median over seeds {row['median_rel_diff' + suffix]:.2e}, "
            f"{row['seeds_rel_diff_above_1e-4' + suffix]} of {seeds} above 1e-4)")


def main(argv=None) -> int:
    args = parse_args(argv)
    args.precision = cli.setup_jax(args.precision)
    dtype = jnp.float64 if args.precision == "float64" else jnp.float32
    if args.against_float64:
        # float64 arrays beside the measured precision's: each S-step follows its inputs' dtype
        jax.config.update("jax_enable_x64", True)
    dev = jax.devices()[0]
    env = {"date": time.strftime("%Y-%m-%dT%H:%M:%S%z"), "device": dev.device_kind,
           "platform": dev.platform, "precision": args.precision, "jax": jax.__version__,
           "python": platform.python_version(), "XLA_FLAGS": os.environ.get("XLA_FLAGS", "")}
    print(f"Device: {env['device']}, jax {env['jax']}, XLA_FLAGS={env['XLA_FLAGS']!r}", flush=True)
    rows = []
    for algorithm in args.algorithm.split(","):
        for scenario in args.scenario.split(","):
            for unroll in [int(u) for u in args.unroll.split(",")]:
                first = None
                for impl in args.impl.split(","):
                    variants = ([(int(w), d, None) for w in args.num_warps.split(",") for d in args.kernel_dot.split(",")]
                                if impl == "kernel" else [(None, None, (e, st)) for e in args.adam_entries.split(",")
                                                          for st in args.statistics.split(",")]
                                if impl == "packed" else [(None, None, None)])
                    forms = args.cuda_forms.split(",") if impl == "cuda" else [None]
                    variants = [v + (se,) for v in variants for se in args.statistics_epochs.split(",")]
                    variants = [v + (mp, o) for v in variants for mp in args.matmul_precision.split(",")
                                for o in args.compiler_options.split(",")]
                    variants = [v + (f,) for v in variants for f in forms]
                    for warps, dot, entries, stats_epochs, matmul_precision, options, form in variants:
                        if warps:
                            gmr_kernel.NUM_WARPS, gmr_kernel.DOT = warps, dot
                        entries, stats = entries or (config.SStepConfig.adam_entries, config.SStepConfig.statistics)
                        with gmr_cuda.launch_form(form):
                            row, weights = measure(algorithm, scenario, unroll, impl, args, dtype, entries,
                                                   matmul_precision, options, stats, stats_epochs, form)
                        # every form trains the same weights to round-off: per seed, the largest
                        # difference from the first form listed relative to that seed's largest
                        # weight; the row reports the largest and the median over seeds
                        first = weights if first is None else first
                        row.update({f"{k}_vs_first": v for k, v in _relative_differences(weights, first).items()})
                        print(f"    max |Δθ| / max |θ| against the first form listed: "
                              f"{_describe(row, '_vs_first', args.seeds)}", flush=True)
                        rows.append(row)
    if args.out:
        with open(args.out, "w") as f:
            json.dump({"env": env, "rows": rows}, f, indent=1)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""Throughput of ``gmr_jax.sim.rollout`` against a bare ``lax.scan`` of ``mjx.step``.

Two measurements (``--mode``):

* ``sweep`` (default on a GPU): for each batch size, physics steps per second of a vmapped
  ``sim.rollout`` of time-varying linear-Gaussian controllers (MJX backend, T control steps of
  ``substeps`` physics steps each, end-effector positions included), and of a bare vmapped
  ``lax.scan`` of ``mjx.step`` over the same number of physics steps on the same model, in the
  same process; the ratio rollout / bare is the figure that matters (the overhead of the
  rollout layer). Compile times are reported separately (lower + compile).
* ``compare`` (default on a CPU): ``--cpu-rollouts`` rollouts (10) of T steps with the ``mujoco``
  backend (C MuJoCo through a host callback) and with the ``mjx`` backend; wall time per
  call after compilation, compile time, and the speed-up.

Prints a markdown table to stdout and writes everything as JSON to ``--out``. Examples::

    python -m benchmarks.rollout --help
    python -m benchmarks.rollout --mode sweep --batch-sizes 1,64,1024,8192,32768 --out sweep.json
    python -m benchmarks.rollout --mode compare --out cpu.json
    python -m benchmarks.rollout --task block_in_hole --batch-sizes 1,64,1024,4096 --out bih.json
    python -m benchmarks.rollout --task block_in_hole --mode sweep --backend mujoco --batch-sizes 1,10,100

``--task`` takes the scene, the physics substeps, the initial states (around the task's first
condition) and the controllers' target (the task's) from a registered task, so that the
block-in-hole rollouts push the block into the fixture (contacts) as training does.

On NVIDIA GPUs, ``XLA_FLAGS=--xla_gpu_triton_gemm_any=true`` may help (MJX docs); the flags in
effect are recorded in the JSON.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import statistics
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

from gmr_jax import config, noise, sim, tasks, types

DEFAULT_BATCHES = "1,8,64,512,2048,8192,16384,32768"


def parse_args(argv=None):
    p = argparse.ArgumentParser(prog="python -m benchmarks.rollout", description=__doc__.split("\n\n")[0],
                                epilog="\n\n".join(__doc__.split("\n\n")[1:]),
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--mode", choices=("auto", "sweep", "compare", "both"), default="auto",
                   help="sweep: rollout vs bare mjx.step scan over batch sizes; compare: mujoco vs mjx "
                        "backend for --cpu-rollouts rollouts; auto: sweep on a GPU, compare otherwise")
    p.add_argument("--batch-sizes", default=DEFAULT_BATCHES, help=f"comma-separated (default {DEFAULT_BATCHES})")
    p.add_argument("--T", type=int, default=80, help="control steps per rollout (default 80)")
    p.add_argument("--task", default="reach", choices=tuple(tasks.TASKS),
                   help="the task whose scene, substeps, conditions and target are used (default reach)")
    p.add_argument("--substeps", type=int, default=None, help="physics steps per control step (default: the task's)")
    p.add_argument("--scene", default=None, help="MJCF scene (default: the task's)")
    p.add_argument("--backend", choices=("mjx", "mujoco"), default="mjx",
                   help="sweep: the backend timed over the batch sizes (default mjx; mujoco skips the bare scan)")
    p.add_argument("--repeats", type=int, default=5, help="timed calls per measurement (median reported)")
    p.add_argument("--dtype", choices=("float32", "float64"), default="float32",
                   help="simulation precision (float64 enables jax_enable_x64)")
    p.add_argument("--cpu-rollouts", type=int, default=10, help="rollouts in compare mode (default 10)")
    p.add_argument("--no-ee", action="store_true", help="rollout without end-effector positions")
    p.add_argument("--skip-bare", action="store_true", help="sweep: do not time the bare mjx.step scan")
    p.add_argument("--out", default=None, help="write results as JSON to this file")
    args = p.parse_args(argv)
    task_cfg = config.make(args.task)
    args.scene = args.scene or task_cfg.sim.scene
    args.substeps = args.substeps or task_cfg.sim.substeps
    args.x0 = np.asarray(tasks.initial_states(task_cfg.task, jnp.float64))[0]
    args.target = np.asarray(tasks.target_state(task_cfg.task, jnp.float64))[:6]
    return args


# ---------------------------------------------------------------------------------------------
# Inputs


def make_inputs(s: sim.Sim, B: int, T: int, dtype, x0: np.ndarray, tgt: np.ndarray, seed: int = 0):
    """A batch of LG controllers (PD towards the target joint angles ``tgt`` plus random gains),
    initial states near ``x0`` [12] and smoothed noise; all on the device."""
    rng = np.random.default_rng(seed)
    kp = np.array([20, 20, 10, 3, 3, 0.5])
    kd = np.array([8, 5, 3, 1, 1, 0.1])
    K0 = np.concatenate([-np.diag(kp), -np.diag(kd)], axis=1)
    K = K0 + 0.1 * rng.normal(size=(B, T, s.dU, s.dX))
    k = np.broadcast_to(kp * tgt, (B, T, s.dU))
    chol = np.broadcast_to(np.eye(s.dU) * 0.5, (B, T, s.dU, s.dU))
    pol = types.LinearGaussianPolicy(*(jnp.asarray(a, dtype) for a in (K, k, chol @ chol, chol, np.linalg.inv(chol @ chol))))
    x0 = np.concatenate([x0[:6] + 0.05 * rng.normal(size=(B, 6)), np.zeros((B, 6))], axis=1)
    keys = jax.random.split(jax.random.key(seed), B)
    eps = jax.jit(jax.vmap(lambda kk: noise.smooth_noise(kk, T, s.dU, config.NoiseConfig(), dtype=dtype)))(keys)
    return pol, jnp.asarray(x0, dtype), eps


def timed(fn, args, repeats):
    """(compile s, median run s, first call s = compile + first run, output) of jit(fn)(*args)."""
    t0 = time.perf_counter()
    compiled = jax.jit(fn).lower(*args).compile()
    t_compile = time.perf_counter() - t0
    out = jax.block_until_ready(compiled(*args))  # warm-up
    t_first = time.perf_counter() - t0
    runs = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(compiled(*args))
        runs.append(time.perf_counter() - t0)
    return t_compile, statistics.median(runs), t_first, out


def rollout_fn(s: sim.Sim, with_ee: bool):
    return jax.vmap(lambda p, x, e: sim.rollout_with_final(s, p, x, e, with_ee=with_ee))


def bare_scan_fn(s: sim.Sim, n_physics: int):
    """vmap over the batch of a lax.scan of mjx.step: the floor the rollout is compared with."""
    from mujoco import mjx

    mx, d0 = s.mjx_model_and_data()

    def one(x, u):
        fdt = d0.qpos.dtype
        d = d0.replace(qpos=x[: s.nq].astype(fdt), qvel=x[s.nq:].astype(fdt), ctrl=u.astype(fdt))
        d, _ = jax.lax.scan(lambda dd, _: (mjx.step(mx, dd), None), d, None, length=n_physics)
        return jnp.concatenate([d.qpos, d.qvel])

    return jax.vmap(one)


# ---------------------------------------------------------------------------------------------
# Modes


def sweep(args, dtype):
    cfg = config.SimConfig(scene=args.scene, substeps=args.substeps, backend=args.backend)
    s = sim.make_sim(cfg)
    T, n_phys = args.T, args.T * args.substeps
    rows = []
    for B in [int(b) for b in args.batch_sizes.split(",") if b]:
        pol, x0, eps = make_inputs(s, B, T, dtype, args.x0, args.target)
        c_roll, t_roll, _, out = timed(rollout_fn(s, not args.no_ee), (pol, x0, eps), args.repeats)
        nan = bool(jnp.any(sim.diverged(*out)))
        row = {"batch": B, "backend": args.backend, "T": T, "substeps": args.substeps, "physics_steps": B * n_phys,
               "rollout_s": t_roll, "rollout_compile_s": c_roll,
               "rollout_steps_per_s": B * n_phys / t_roll, "rollout_diverged": nan}
        if not args.skip_bare and args.backend == "mjx":
            u = jnp.asarray(np.random.default_rng(1).uniform(-1, 1, size=(B, s.dU)), dtype)
            c_bare, t_bare, _, _ = timed(bare_scan_fn(s, n_phys), (x0, u), args.repeats)
            row.update({"bare_s": t_bare, "bare_compile_s": c_bare,
                        "bare_steps_per_s": B * n_phys / t_bare, "ratio": t_bare / t_roll})
        rows.append(row)
        print(f"# B={B}: rollout {row['rollout_steps_per_s'] / 1e6:.4g} M steps/s"
              + (f", bare {row['bare_steps_per_s'] / 1e6:.4g} M steps/s, ratio {row['ratio']:.3f}"
                 if "ratio" in row else ""), file=sys.stderr, flush=True)
    return rows


def compare(args, dtype):
    T, n = args.T, args.cpu_rollouts
    res = {}
    for backend in ("mujoco", "mjx"):
        s = sim.make_sim(config.SimConfig(scene=args.scene, substeps=args.substeps, backend=backend))
        pol, x0, eps = make_inputs(s, n, T, dtype, args.x0, args.target)
        c, t, first, out = timed(rollout_fn(s, not args.no_ee), (pol, x0, eps), args.repeats)
        res[backend] = {"compile_s": c, "run_s": t, "first_call_s": first,
                        "steps_per_s": n * T * args.substeps / t, "X": np.asarray(out[0].X, np.float64)}
        print(f"# {backend}: {t * 1e3:.1f} ms per call, compile {c:.1f} s", file=sys.stderr, flush=True)
    diff = float(np.max(np.abs(res["mujoco"].pop("X") - res["mjx"].pop("X"))))
    return {"rollouts": n, "T": T, "substeps": args.substeps, **{f"{b}_{k}": v for b in res for k, v in res[b].items()},
            "speedup_run": res["mjx"]["run_s"] / res["mujoco"]["run_s"],
            "speedup_first_call": res["mjx"]["first_call_s"] / res["mujoco"]["first_call_s"],
            "max_abs_state_difference": diff}


def environment():
    import mujoco

    dev = jax.devices()[0]
    return {"date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
            "jax": jax.__version__, "mujoco": mujoco.__version__, "backend": jax.default_backend(),
            "device": getattr(dev, "device_kind", str(dev)), "device_count": jax.device_count(),
            "cpu_count": os.cpu_count(), "python": platform.python_version(),
            "XLA_FLAGS": os.environ.get("XLA_FLAGS", ""),
            "JAX_DEFAULT_MATMUL_PRECISION": os.environ.get("JAX_DEFAULT_MATMUL_PRECISION", "")}


def markdown(env, rows, cmp):
    lines = [f"Device: {env['device']} ({env['backend']}), jax {env['jax']}, mujoco {env['mujoco']}, {env['date']}; "
             f"scene {env['scene']}, {env['substeps']} substeps", ""]
    if rows:
        lines += ["| batch | rollout M steps/s | bare mjx.step scan M steps/s | ratio | rollout s | rollout compile s | bare compile s |",
                  "| ---: | ---: | ---: | ---: | ---: | ---: | ---: |"]
        for r in rows:
            bare = (f"{r['bare_steps_per_s'] / 1e6:.4g} | {r['ratio']:.3f}" if "ratio" in r else "– | –")
            lines.append(f"| {r['batch']} | {r['rollout_steps_per_s'] / 1e6:.4g} | {bare} | {r['rollout_s']:.4f} | "
                         f"{r['rollout_compile_s']:.1f} | {r.get('bare_compile_s', float('nan')):.1f} |")
        lines.append("")
    if cmp:
        lines += [f"{cmp['rollouts']} rollouts of T = {cmp['T']} ({cmp['substeps']} substeps):", "",
                  "| backend | per call (s) | physics steps/s | compile (s) |", "| --- | ---: | ---: | ---: |"]
        for b in ("mujoco", "mjx"):
            lines.append(f"| {b} | {cmp[b + '_run_s']:.4f} | {cmp[b + '_steps_per_s']:.0f} | {cmp[b + '_compile_s']:.1f} |")
        lines += ["", f"Speed-up of mujoco over mjx: {cmp['speedup_run']:.0f}× per call after compilation, "
                      f"{cmp['speedup_first_call']:.0f}× including compilation; "
                      f"max |state difference| {cmp['max_abs_state_difference']:.2e}."]
    return "\n".join(lines)


def main(argv=None):
    args = parse_args(argv)
    if args.dtype == "float64":
        jax.config.update("jax_enable_x64", True)
    dtype = jnp.float64 if args.dtype == "float64" else jnp.float32
    mode = args.mode
    if mode == "auto":
        mode = "sweep" if jax.default_backend() == "gpu" else "compare"
    env = {**environment(), "scene": args.scene, "substeps": args.substeps}
    rows = sweep(args, dtype) if mode in ("sweep", "both") else []
    cmp = compare(args, dtype) if mode in ("compare", "both") else None
    print(markdown(env, rows, cmp))
    if args.out:
        with open(args.out, "w") as f:
            json.dump({"environment": env, "args": {k: v for k, v in vars(args).items() if k not in ("x0", "target")},
                       "mode": mode, "sweep": rows, "compare": cmp}, f, indent=2)


if __name__ == "__main__":
    main()

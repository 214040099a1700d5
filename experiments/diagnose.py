"""Why does a trained policy fail from some robustness states? ``python -m experiments.diagnose OUT``.

Reads a folder written by a study (``python -m experiments.reach``; its ``config.json`` and the final
checkpoint of every policy run), executes each seed's policy noiselessly from the 50 fixed
robustness states, and reports per seed, separately for the successful and the failed states:

- ``sat``: fraction of steps with at least one torque at its limit;
- ``|x̃|₀``: the largest entry of the policy's standardised input at the initial state, i.e. how
  many training standard deviations the state lies from the training data;
- ``‖∂u/∂x‖``: Frobenius norm of the policy's state Jacobian, averaged over the path;
- ``|q̇_T|``: joint-speed norm at the last step (an arm still moving vs one at rest off target);
- the joints whose final error exceeds 0.1 rad, counted over the failures;
- at the target state x*: ‖u(x*)‖ (non-zero means a steady-state offset) and ρ, the spectral
  radius of the closed loop x' = f(x, u(x)) linearised there (``gmr_jax.stability``; ρ ≥ 1: the
  policy cannot hold the target).

Below the table, each run's successes over seeds (mean, 95 % interval). ``--set GROUP__FIELD=VALUE``
evaluates under a changed configuration, e.g. ``--set sim__float32=True`` executes float64
policies on the plant stepped in float32 (then it writes ``diagnostics_<overrides>.json`` and
``.md``, so the study's own diagnostics stay).

Writes ``diagnostics.json`` and ``diagnostics.md`` into OUT and prints the table.
"""

from __future__ import annotations

import argparse
import json
import pathlib
import re
import sys

import jax
import jax.numpy as jnp
import numpy as np

from experiments.cli import parse_overrides
from gmr_jax import checkpoint, config, evaluate, policies, runner, stability, stats, tasks
from gmr_jax import sim as sim_lib
from gmr_jax.policies.base import normalize_input

JOINT_TOLERANCE = 0.1  # rad: a joint "failed" when its final error is above this


def diagnose_seed(cfg: config.Config, params) -> dict:
    """Per-state diagnostics of one seed's policy (params without a seed axis): arrays only, so
    that it can be jitted and vmapped over seeds."""
    s = sim_lib.make_sim(cfg.sim)
    dtype = jax.tree_util.tree_leaves(params)[0].dtype
    x0 = evaluate.robustness_states(cfg, dtype=dtype)
    traj = evaluate.execute_policy(cfg, params, x0)
    rob = evaluate.summarize_robustness(cfg, x0, traj)
    policy = policies.for_config(cfg)
    mean_fn = policies.mean_fn(policy, params)
    limit = jnp.asarray(s.torque_limit, dtype)
    sat = jnp.mean(jnp.any(jnp.abs(traj.U) >= limit * (1 - 1e-9), axis=-1), axis=-1)
    xin0 = jnp.max(jnp.abs(normalize_input(params.norm, x0)), axis=-1)
    jac = jax.vmap(jax.vmap(jax.jacfwd(lambda x: policy.mean(params, x))))(traj.X)  # [S, T, dU, dX]
    gain = jnp.mean(jnp.sqrt(jnp.sum(jac ** 2, axis=(-2, -1))), axis=-1)
    target = tasks.target_state(cfg.task, dtype)
    final = rob.final_x
    joint_err = jnp.abs(evaluate.task_error(cfg, final)[:, : s.dU])
    speed = jnp.linalg.norm(final[:, s.dU:], axis=-1)
    u_star = mean_fn(0, target, jnp.zeros(s.dU, dtype))
    return {"success": rob.success, "mse": rob.mse, "sat": sat, "xin0": xin0, "gain": gain,
            "speed": speed, "joint_err": joint_err, "u_star_norm": jnp.linalg.norm(u_star),
            "norm_scale": params.norm.scale}


def _split(values, ok):
    def med(v):
        return f"{np.median(v):.3g}" if v.size else "–"
    return f"{med(values[ok])} / {med(values[~ok])}"


def diagnose_run(ckpt: pathlib.Path, name: str, cfg: config.Config, seeds: list[int]) -> tuple[list[dict], str]:
    state, _ = checkpoint.restore(ckpt, runner.initial_state(cfg, seeds))
    rows, out_rows = [], []
    every = jax.tree_util.tree_map(np.asarray, jax.jit(jax.vmap(lambda p: diagnose_seed(cfg, p)))(state.policy.params))
    # ρ of the closed loop at the target (gmr_jax.stability), per seed on the host
    target = tasks.target_state(cfg.task, jax.tree_util.tree_leaves(state.policy.params)[0].dtype)
    every["rho_target"] = np.array([stability.spectral_radius(stability.closed_loop_jacobians(
        cfg, jax.tree_util.tree_map(lambda a: a[i], state.policy.params), target[None]))[0]
        for i in range(len(seeds))])
    for i, seed in enumerate(seeds):
        d = {k: v[i] for k, v in every.items()}
        ok = d["success"]
        failed_joints = np.sum(d["joint_err"][~ok] > JOINT_TOLERANCE, axis=0)
        rows.append({"seed": seed, **{k: v.tolist() for k, v in d.items()}})
        out_rows.append(
            f"| {name} | {seed} | {int(ok.sum())} | {_split(d['sat'], ok)} | {_split(d['xin0'], ok)} "
            f"| {_split(d['gain'], ok)} | {_split(d['speed'], ok)} | {failed_joints.tolist()} "
            f"| {float(d['u_star_norm']):.3g} | {float(d['rho_target']):.3f} | "
            f"{np.array2string(1 / d['norm_scale'][:6], precision=2, separator=',')} |")
    return rows, "\n".join(out_rows)


def file_suffix(overrides: dict) -> str:
    """The suffix of the output files for ``--set`` overrides, one path component whatever the
    values hold (e.g. a scene path): "" without overrides, else "_sim__float32=True" and the like."""
    if not overrides:
        return ""
    return "_" + re.sub(r"[^\w.=,+-]+", "-", "_".join(f"{k}={v}" for k, v in overrides.items()))


HEADER = ("| run | seed | successes /50 | sat (ok / fail) | \\|x̃\\|₀ (ok / fail) | ‖∂u/∂x‖ (ok / fail) "
          "| \\|q̇_T\\| (ok / fail) | failures with joint error > 0.1, joints 1–6 | ‖u(x*)‖ | ρ at x* "
          "| input std of q (training) |\n|" + "---|" * 11)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m experiments.diagnose", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("out", help="output folder of a study (python -m experiments.reach, …)")
    p.add_argument("--set", action="append", default=[], metavar="GROUP__FIELD=VALUE",
                   help="evaluate under a changed configuration, e.g. --set sim__float32=True "
                        "(repeatable; values are Python literals)")
    args = p.parse_args(argv)
    overrides = parse_overrides(p, args.set)
    out = pathlib.Path(args.out)
    meta_path = out / "config.json"
    if not meta_path.is_file():
        p.error(f"{meta_path} not found: give the output folder of a study")
    meta = json.loads(meta_path.read_text())
    jax.config.update("jax_enable_x64", meta.get("precision", "float64") == "float64")
    seeds = list(meta["seeds"])
    try:
        configs = {name: config.from_dict(d) for name, d in meta["runs"].items()}
        configs = {name: config.override(cfg, **overrides) for name, cfg in configs.items()}
    except (ValueError, TypeError) as err:
        print(f"python -m experiments.diagnose: error: {meta_path}: {err}", file=sys.stderr)
        return 1
    results, tables, totals = {}, [], []
    for name, cfg in configs.items():
        if policies.for_config(cfg) is None:
            continue
        ckpt = runner.run_folder(out, *name.split("/")) / "checkpoints"
        if checkpoint.latest(ckpt) != cfg.iterations:
            print(f"{name}: no final checkpoint, skipped", file=sys.stderr)
            continue
        try:
            rows, table = diagnose_run(ckpt, name, cfg, seeds)
        except checkpoint.CheckpointError as err:  # e.g. --set changed the network's shape
            print(f"python -m experiments.diagnose: error: {name}: {err}", file=sys.stderr)
            return 1
        results[name] = rows
        tables.append(table)
        counts = [int(np.sum(r["success"])) for r in rows]
        totals.append(f"- {name}: successes of 50, {stats.over_seeds(counts).format()}")
    changed = "".join(f" {k}={v!r}" for k, v in overrides.items())
    text = ("# Robustness diagnostics" + (f" with{changed}" if changed else "") + "\n\nmedians over the "
            "successful / failed states\n\n" + HEADER + "\n" + "\n".join(tables) + "\n\n"
            + "\n".join(totals) + "\n")
    suffix = file_suffix(overrides)
    (out / f"diagnostics{suffix}.json").write_text(json.dumps(results))
    (out / f"diagnostics{suffix}.md").write_text(text)
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())

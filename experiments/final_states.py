"""Where do a study's policies end from the random states? ``python -m experiments.final_states OUT RUN…``.

Restores each run's last checkpoint from a study's output folder (e.g. ``C_gmr`` in the folder of
``python -m experiments.block_in_hole``), executes every seed's policy from the robustness test's
50 random states and prints per seed: the paper's successes (final-state MSE < 0.01), the task's
further measures (for block-in-hole "inserted": tip in the hole, at least 45 mm deep), and for the
states that meet one but not the other, and those that meet neither, the median joint error
|q − q*| per joint and the median largest joint speed — e.g. a block below the rim's height beside the fixture with the arm still
spinning, or an arm near q* in joint space with the block not in the hole.

``--without-contacts`` also executes every policy from the same states in a copy of the scene
with contacts disabled (the block passes through the table and the fixture): the difference in
successes measures how much of the failures the obstruction by table and fixture explains.
"""

from __future__ import annotations

import argparse
import dataclasses
import pathlib
import tempfile

import jax
import mujoco
import numpy as np

from gmr_jax import config, evaluate, runner, sim as sim_lib


def without_contacts(cfg: config.Config, folder: pathlib.Path) -> config.Config:
    """``cfg`` with its scene copied into ``folder`` with every contact disabled."""
    spec = mujoco.MjSpec.from_file(str(sim_lib.scene_path(cfg.sim.scene)))
    spec.option.disableflags |= int(mujoco.mjtDisableBit.mjDSBL_CONTACT)
    path = folder / f"{sim_lib.scene_path(cfg.sim.scene).stem}_no_contacts.xml"
    path.write_text(spec.to_xml())
    return dataclasses.replace(cfg, sim=dataclasses.replace(cfg.sim, scene=str(path)))


def describe(cfg: config.Config, params) -> list[str]:
    """Lines about one policy's final states from the robustness states."""
    rob = evaluate.robustness(cfg, params)
    fx = np.asarray(rob.final_x)
    err_all = np.abs(np.asarray(evaluate.task_error(cfg, rob.final_x)))
    nq = fx.shape[-1] // 2
    success = np.asarray(rob.success)
    lines = [f"MSE < {cfg.task.success_threshold}: {int(success.sum())}/{success.size}"]
    for name, ok in rob.extra.items():
        ok = np.asarray(ok)
        lines[0] += f"; {name}: {int(ok.sum())}/{ok.size}"
        for label, sel in ((f"{name}, MSE too large", ok & ~success), (f"MSE below, not {name}", success & ~ok),
                           ("neither", ~success & ~ok)):
            if sel.any():
                err = np.median(err_all[sel, :nq], axis=0)
                speed = np.median(np.abs(fx[sel, nq:]).max(axis=1))
                lines.append(f"  {label} ({int(sel.sum())}): median |q - q*| per joint "
                             f"{np.array2string(err, precision=3)} rad, median largest |q̇| {speed:.3g} rad/s")
    return lines


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m experiments.final_states", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("out", type=pathlib.Path, help="a study's output folder")
    p.add_argument("runs", nargs="+", help="run folders in it, e.g. C_gmr CD_mdgps")
    p.add_argument("--without-contacts", action="store_true",
                   help="also execute the policies in the scene with contacts disabled")
    args = p.parse_args(argv)
    scratch = tempfile.TemporaryDirectory()
    jax.config.update("jax_enable_x64", True)
    for name in args.runs:
        try:
            cfg, seeds, state = runner.restore_run(args.out / name)
        except ValueError as err:
            p.error(str(err))
        for i, seed in enumerate(seeds):
            params = jax.tree_util.tree_map(lambda a: a[i], state.policy.params)
            lines = describe(cfg, params)
            print(f"{name} seed {seed}: {lines[0]}")
            for line in lines[1:]:
                print(line)
            if args.without_contacts:
                free = describe(without_contacts(cfg, pathlib.Path(scratch.name)), params)
                print(f"  without contacts: {free[0]}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

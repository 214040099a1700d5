"""Where do a study's policies end from the random states? ``python -m experiments.final_states OUT RUN…``.

Restores each run's last checkpoint from a study's output folder (e.g. ``C_gmr`` in the folder of
``python -m experiments.block_in_hole``), executes every seed's policy from the robustness test's
50 random states and prints per seed: the paper's successes (final-state MSE < 0.01), the task's
further measures (for block-in-hole "inserted": tip in the hole, at least 45 mm deep), and for the
states that meet one but not the other, and those that meet neither, the median joint error
|q − q*| per joint and the median largest joint speed — e.g. a block below the rim's height beside the fixture with the arm still
spinning, or an arm near q* in joint space with the block not in the hole.
"""

from __future__ import annotations

import argparse
import pathlib

import jax
import numpy as np

from gmr_jax import config, evaluate, runner, tasks


def describe(cfg: config.Config, params) -> list[str]:
    """Lines about one policy's final states from the robustness states."""
    rob = evaluate.robustness(cfg, params)
    fx = np.asarray(rob.final_x)
    target = np.asarray(tasks.target_state(cfg.task))
    nq = fx.shape[-1] // 2
    success = np.asarray(rob.success)
    lines = [f"MSE < {cfg.task.success_threshold}: {int(success.sum())}/{success.size}"]
    for name, ok in rob.extra.items():
        ok = np.asarray(ok)
        lines[0] += f"; {name}: {int(ok.sum())}/{ok.size}"
        for label, sel in ((f"{name}, MSE too large", ok & ~success), (f"MSE below, not {name}", success & ~ok),
                           ("neither", ~success & ~ok)):
            if sel.any():
                err = np.median(np.abs(fx[sel, :nq] - target[:nq]), axis=0)
                speed = np.median(np.abs(fx[sel, nq:]).max(axis=1))
                lines.append(f"  {label} ({int(sel.sum())}): median |q - q*| per joint "
                             f"{np.array2string(err, precision=3)} rad, median largest |q̇| {speed:.3g} rad/s")
    return lines


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m experiments.final_states", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("out", type=pathlib.Path, help="a study's output folder")
    p.add_argument("runs", nargs="+", help="run folders in it, e.g. C_gmr CD_mdgps")
    args = p.parse_args(argv)
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
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

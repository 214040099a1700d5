"""How deep did the block go? ``python -m experiments.insertion_depths OUT``.

Reads a folder written by ``python -m experiments.block_in_hole`` (its ``config.json`` and every
run's checkpoints) and prints, per run, iteration, seed and condition, the insertion depth (mm
below the rim; negative above it) of the block's tip at the end of the noiseless execution of
the local controllers (the "LQR base layer"), of the policy where there is one, and of each
noisy sample. "inserted" in the study's summary is a depth of at least 45 mm with the tip inside
the hole.
"""

from __future__ import annotations

import argparse
import json
import pathlib
import sys

import jax
import numpy as np

from gmr_jax import checkpoint, config, runner, sim
from gmr_jax.tasks import block_in_hole


def depths(cfg: config.Config, history: list[dict]) -> list[dict]:
    """Per iteration: {"lqr": [S, M], "policy": [S, M] or absent, "samples": [S, M, N]} in mm."""
    s = sim.make_sim(cfg.sim)
    depth = lambda x: 1e3 * np.asarray(block_in_hole.insertion_depth(s, jax.numpy.asarray(np.asarray(x)[..., :6])))  # noqa: E731
    out = []
    for h in history:
        row = {"lqr": depth(h["eval_final_x"]), "samples": depth(h["sample_final_x"])}
        if "policy_eval_final_x" in h:
            row["policy"] = depth(h["policy_eval_final_x"])
        out.append(row)
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m experiments.insertion_depths", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("out", type=pathlib.Path, help="output folder of python -m experiments.block_in_hole")
    args = p.parse_args(argv)
    meta_path = args.out / "config.json"
    if not meta_path.is_file():
        p.error(f"{meta_path} not found: give the output folder of a block-in-hole study")
    meta = json.loads(meta_path.read_text())
    jax.config.update("jax_enable_x64", meta.get("precision", "float64") == "float64")
    for name, d in meta["runs"].items():
        cfg = config.from_dict(d)
        if cfg.task.name != "block_in_hole":
            print(f"{name}: not a block-in-hole run, skipped", file=sys.stderr)
            continue
        ckpt = runner.run_folder(args.out, *name.split("/")) / "checkpoints"
        if checkpoint.latest(ckpt) is None:
            print(f"{name}: no checkpoint, skipped", file=sys.stderr)
            continue
        history = checkpoint.read_metadata(ckpt)["history"]
        for it, row in enumerate(depths(cfg, history), start=1):
            for i, seed in enumerate(meta["seeds"]):
                for m, cond in enumerate(block_in_hole.SCENARIOS[cfg.task.scenario]):
                    pol = f"  policy {row['policy'][i, m]:6.1f}" if "policy" in row else ""
                    samples = " ".join(f"{v:6.1f}" for v in row["samples"][i, m])
                    print(f"{name} iteration {it:2d} seed {seed} {cond}: base layer {row['lqr'][i, m]:6.1f}{pol}"
                          f"  samples {samples}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

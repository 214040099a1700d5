"""Pictures of trained policies: ``python -m experiments.video OUT [RUN …] [--video]``.

Takes one seed's noiseless policy rollouts from the training conditions and from a few of the
robustness test's random states in each run folder of a study's output folder (default: every
run folder in it that trains a policy): the rollouts the run kept after training
(``gmr_jax.runner.ROLLOUTS_FILE``, the first ``PICTURE_SEEDS`` seeds), or else executed from
the run's newest checkpoint. Writes

- ``frames.png``: a still-frame grid, one row per rollout (six frames from 0 to 4 s);
- with ``--video``: one MP4 per rollout, ``videos/<run>_seed<k>_<start>.mp4`` (20 frames per
  second, real time; imageio's ffmpeg plugin, ``pip install 'gmr-jax[video]'``).

The studies call this after training (``--video``; without it only the grid). Where MuJoCo
cannot render (no EGL or OSMesa), it says so in one line and writes nothing.
"""

from __future__ import annotations

import argparse
import json
import pathlib
import sys

import jax
import numpy as np

from gmr_jax import config, evaluate, policies, render, runner, tasks


def policy_runs(out: pathlib.Path) -> list[str]:
    """The run folders of a study that hold a policy's checkpoints (``<scenario>_<gmr|mdgps>``)."""
    return sorted(p.name for p in out.iterdir()
                  if p.is_dir() and (p / "checkpoints").is_dir() and p.name.rsplit("_", 1)[-1] in policies.ALGORITHMS
                  and p.name.rsplit("_", 1)[-1] != "lqr")


def _kept_rollouts(run_dir: pathlib.Path, seed_index: int, random_states: int):
    """(configuration, seed, states [M + random_states, T, dX]) from the rollouts the run kept
    (``runner.ROLLOUTS_FILE``), or None where they do not cover the request."""
    kept = run_dir / runner.ROLLOUTS_FILE
    if not kept.is_file() or random_states > runner.PICTURE_RANDOM_STATES:
        return None
    with np.load(kept) as f:
        if seed_index >= f["seeds"].shape[0]:
            return None
        X = np.concatenate([f["training"][seed_index], f["random"][seed_index, :random_states]])
        seed = int(f["seeds"][seed_index])
    meta = json.loads((run_dir / "config.json").read_text())
    return config.from_dict(meta["config"]), seed, X


def rollouts(run_dir: pathlib.Path, seed_index: int = 0, random_states: int = 3):
    """[(label, states [T, dX])] of one seed's policy from the training conditions and the first
    ``random_states`` robustness states, and the run's configuration and seed: the rollouts the
    run kept where they cover the request, else executed here from the newest checkpoint."""
    run_dir = pathlib.Path(run_dir)
    kept = _kept_rollouts(run_dir, seed_index, random_states)
    if kept is not None:
        cfg, seed, X = kept
    else:
        cfg, seeds, state = runner.restore_run(run_dir)
        params = jax.tree_util.tree_map(lambda a: a[seed_index], state.policy.params)
        x0 = np.concatenate([np.asarray(tasks.initial_states(cfg.task)),
                             np.asarray(evaluate.robustness_states(cfg))[:random_states]])
        X = np.asarray(evaluate.execute_policy(cfg, params, jax.numpy.asarray(x0)).X)
        seed = seeds[seed_index]
    conds = tasks.of(cfg).scenarios[cfg.task.scenario]
    labels = [f"from {c}" for c in conds] + [f"random state {i}" for i in range(random_states)]
    return cfg, seed, list(zip(labels, X))


def write(out: pathlib.Path, runs: list[str], seed_index: int = 0, random_states: int = 3,
          video: bool = False, log=print) -> list[pathlib.Path]:
    """Render the runs' rollouts into ``out``: ``frames.png`` and, with ``video``, MP4s.

    Returns the files written. Raises render.RenderingUnavailable (with a one-line reason).
    """
    reason = render.available()
    if reason is not None:
        raise render.RenderingUnavailable(reason)
    rows, written = [], []
    # Every rollout first, then every picture: no XLA compilation after an OpenGL context exists
    # in the process (Mesa's software EGL brings its own LLVM).
    done = [(name, *rollouts(out / name, seed_index, random_states)) for name in runs]
    for name, cfg, seed, rolls in done:
        for label, X in rolls:
            steps = render.grid_times(X.shape[0])
            if video:  # every frame; the grid takes its columns from them
                fr = render.frames(cfg.sim, X)
                slug = label.replace("from ", "").replace("random state ", "random")
                written.append(render.write_video(out / "videos" / f"{name}_seed{seed}_{slug}.mp4", fr))
                fr = fr[steps]
            else:
                fr = render.frames(cfg.sim, X[steps])
            rows.append((f"{name}, seed {seed}\n{label}", fr, steps))
        log(f"  rendered {name} (seed {seed}): {len(rolls)} rollouts")
    written.insert(0, render.grid_png(out / "frames.png", rows, title=f"{out.name}: noiseless policy rollouts"))
    return written


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m experiments.video", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("out", type=pathlib.Path, help="a study's output folder")
    p.add_argument("runs", nargs="*", help="run folders in it (default: every policy run)")
    p.add_argument("--seed-index", type=int, default=0, help="which of the run's seeds (default: the first)")
    p.add_argument("--random-states", type=int, default=3, help="random states to start from (default 3)")
    p.add_argument("--video", action="store_true", help="also write MP4s under OUT/videos/")
    args = p.parse_args(argv)
    jax.config.update("jax_enable_x64", True)
    if not args.out.is_dir():
        p.error(f"{args.out}: no such study folder")
    runs = args.runs or policy_runs(args.out)
    if not runs:
        p.error(f"{args.out}: no run folder with a policy's checkpoints")
    try:
        files = write(args.out, runs, args.seed_index, args.random_states, args.video)
    except render.RenderingUnavailable as err:
        print(f"error: {err}", file=sys.stderr)
        return 1
    except ValueError as err:
        p.error(str(err))
    for f in files:
        print(f)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

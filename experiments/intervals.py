"""Confidence intervals of a finished study: ``python -m experiments.intervals RESULTS_JSON …``.

Reads the ``results.json`` of one or more studies (reach or block-in-hole, any number of seeds)
and prints, per run (scenario, algorithm), the robustness successes over seeds as the summaries
now write them: the mean with its 95 % bootstrap confidence interval, the interquartile mean and
the range (``gmr_jax.stats``), for the paper's threshold, the loose one and the task's further
measures (e.g. "inserted"), and the learning speed (``experiments.report.success_iterations``:
the first iteration from which the final-state MSE from every training condition stays below
``--threshold``) of the LQR base layer and the policy, and the policy's lag. For results written
before the summaries carried them.

``--by-distance`` prints, per study and run, the fraction of the random states' rollouts (over
all seeds) that succeed, binned by the state's distance from the nearest training state (rad,
``Robustness.distance``).

``--compact`` prints one table for all the studies instead, a row per study and run: the
successes at both thresholds and the fraction of contracting states (``gmr_jax.stability``),
each over seeds (e.g. the ablation table of ``experiments/ablations.sh``).
"""

from __future__ import annotations

import argparse
import collections
import os
import pathlib

import numpy as np

from experiments import report
from gmr_jax import stats


def table(results: dict, threshold: float = 0.01) -> list[str]:
    """Markdown rows, one per run and measure."""
    per_run = collections.defaultdict(lambda: collections.defaultdict(list))
    curves = collections.defaultdict(lambda: collections.defaultdict(list))
    for rec in results["runs"]:
        for curve in ("final_state_mse_lqr", "final_state_mse_policy"):
            if curve + "_per_condition" in rec:
                curves[(rec["scenario"], rec["algorithm"])][curve].append(rec[curve + "_per_condition"])
        rob = rec.get("robustness")
        if rob is None:
            continue
        for key, value in rob.items():
            if key.startswith("successes"):
                per_run[(rec["scenario"], rec["algorithm"])][key].append(value)
    lines = ["| run | measure | seeds | mean [95 % CI], IQM (range) |", "|---|---|---|---|"]
    for (scenario, algorithm), measures in per_run.items():
        for key, values in measures.items():
            lines.append(f"| {scenario}/{algorithm} | {key} | {len(values)} | {stats.over_seeds(values).format()} |")
    for (scenario, algorithm), h in curves.items():
        # [seeds, iterations, M] -> [iterations, seeds, M], as in a run's history
        run = {"history": {c: np.swapaxes(np.asarray(v, float), 0, 1) for c, v in h.items()}}
        for name, values in report.success_iterations(run, threshold).items():
            lines.append(f"| {scenario}/{algorithm} | learning speed: {name} | {len(values)} | "
                         f"{stats.over_seeds(values).format()} |")
    return lines


COMPACT_HEADER = ("| study | run | seeds | successes, MSE < 0.01 | successes, MSE < 0.1 | contracting states |\n"
                  "|---|---|---|---|---|---|")


def compact_rows(label: str, results: dict) -> list[str]:
    """Markdown rows of ``COMPACT_HEADER``, one per run (scenario, algorithm) of a study."""
    per_run = collections.defaultdict(lambda: collections.defaultdict(list))
    for rec in results["runs"]:
        rob, stab = rec.get("robustness") or {}, rec.get("stability") or {}
        row = per_run[(rec["scenario"], rec["algorithm"])]
        for key in ("successes", "successes_loose"):
            if key in rob:
                row[key].append(rob[key])
        if "contracting" in stab:
            row["contracting"].append(stab["contracting"])
    lines = []
    for (scenario, algorithm), m in per_run.items():
        cells = [stats.over_seeds(m[k]).format(digits) if m[k] else "–"
                 for k, digits in (("successes", 1), ("successes_loose", 1), ("contracting", 2))]
        lines.append(f"| {label} | {scenario}/{algorithm} | {len(m['successes'])} | " + " | ".join(cells) + " |")
    return lines


DISTANCE_BINS = (0.0, 3.0, 4.0, 5.0, 6.0, 8.0, np.inf)


def distance_rows(label: str, results: dict, bins=DISTANCE_BINS) -> list[str]:
    """Markdown rows, one per run: per distance bin [lo, hi), the number of random states in it
    and the percentage of their rollouts over all seeds with MSE < 0.01 / < 0.1."""
    per_run = collections.defaultdict(lambda: ([], []))
    for rec in results["runs"]:
        rob = rec.get("robustness") or {}
        if "mse" in rob and "distance" in rob:
            mse, dist = per_run[(rec["scenario"], rec["algorithm"])]
            mse.append(rob["mse"])
            dist.append(rob["distance"])
    lines = []
    for (scenario, algorithm), (mse, dist) in per_run.items():
        mse, dist = np.asarray(mse, float), np.asarray(dist, float)  # [seeds, states]
        cells = []
        for lo, hi in zip(bins[:-1], bins[1:]):
            sel = (dist[0] >= lo) & (dist[0] < hi)  # the states are the same for every seed
            cells.append(f"{int(sel.sum())}: {100 * np.mean(mse[:, sel] < 0.01):.0f} % / "
                         f"{100 * np.mean(mse[:, sel] < 0.1):.0f} %" if sel.any() else "–")
        lines.append(f"| {label} | {scenario}/{algorithm} | {len(mse)} | " + " | ".join(cells) + " |")
    return lines


def distance_header(bins=DISTANCE_BINS) -> str:
    names = [f"[{lo:g}, {hi:g})" for lo, hi in zip(bins[:-1], bins[1:])]
    return ("Per bin of distance from the nearest training state (rad): the random states in it: % of "
            "their rollouts over all seeds with MSE < 0.01 / < 0.1.\n\n"
            "| study | run | seeds | " + " | ".join(names) + " |\n|" + "---|" * (3 + len(names)))


def _folder(path: pathlib.Path) -> pathlib.Path:
    return (path if path.is_dir() else path.parent).resolve()


def labels(paths: list[pathlib.Path]) -> list[str]:
    """The studies' names in the compact table: their folders relative to the folder all share."""
    folders = [_folder(p) for p in paths]
    if len(folders) == 1:
        return [folders[0].name]
    common = pathlib.Path(os.path.commonpath(folders))
    return [str(f.relative_to(common)) or f.name for f in folders]


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m experiments.intervals", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("results", nargs="+", type=pathlib.Path,
                   help="results.json (or results.json.gz) files or folders of finished studies")
    p.add_argument("--threshold", type=float, default=0.01,
                   help="final-state MSE of a success, for the learning speed (default: the paper's 0.01)")
    p.add_argument("--compact", action="store_true",
                   help="one table, a row per study and run (successes at both thresholds, contracting states)")
    p.add_argument("--by-distance", action="store_true",
                   help="successes binned by the random state's distance from the training states")
    args = p.parse_args(argv)
    if args.compact:
        print(COMPACT_HEADER)
    if args.by_distance:
        print(distance_header())
    for path, label in zip(args.results, labels(args.results)):
        try:
            results = report.read_results(path)
        except (OSError, ValueError) as err:
            p.error(f"{path}: cannot read a results.json ({err})")
        if args.compact or args.by_distance:
            rows = compact_rows if args.compact else distance_rows
            print("\n".join(rows(label, results)))
            continue
        print(f"## {path}\n")
        print("\n".join(table(results, args.threshold)) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

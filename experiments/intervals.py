"""Confidence intervals of a finished study: ``python -m experiments.intervals RESULTS_JSON …``.

Reads the ``results.json`` of one or more studies (reach or block-in-hole, any number of seeds)
and prints, per run (scenario, algorithm), the robustness successes over seeds as the summaries
now write them: the mean with its 95 % bootstrap confidence interval, the interquartile mean and
the range (``gmr_jax.stats``), for the paper's threshold, the loose one and the task's further
measures (e.g. "inserted"). For results written before the summaries carried intervals.
"""

from __future__ import annotations

import argparse
import collections
import json
import pathlib

from gmr_jax import stats


def table(results: dict) -> list[str]:
    """Markdown rows, one per run and measure."""
    per_run = collections.defaultdict(lambda: collections.defaultdict(list))
    for rec in results["runs"]:
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
    return lines


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m experiments.intervals", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("results", nargs="+", type=pathlib.Path, help="results.json files of finished studies")
    args = p.parse_args(argv)
    for path in args.results:
        try:
            results = json.loads(path.read_text())
        except (OSError, json.JSONDecodeError) as err:
            p.error(f"{path}: cannot read a results.json ({err})")
        print(f"## {path}\n")
        print("\n".join(table(results)) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

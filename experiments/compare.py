"""Do two study outputs hold the same results? ``python -m experiments.compare OLD NEW``.

Compares the per-run records of two ``results.json`` files (scenario, algorithm, seed: every
per-iteration metric, the robustness counts and MSEs, the disturbance sweep) entry by entry and
prints the records and fields that differ, with the largest relative difference of each. Wall
times are not compared. Exit code 0 when every record is bit-identical, 1 otherwise.
"""

from __future__ import annotations

import argparse
import pathlib
import sys

import numpy as np

from experiments import report


def _records(path: pathlib.Path) -> dict:
    try:
        runs = report.read_results(path)["runs"]
    except (OSError, ValueError) as err:
        raise SystemExit(f"python -m experiments.compare: error: {path}: no readable results ({err})")
    return {(r["scenario"], r["algorithm"], r["seed"]): r for r in runs}


def _largest_difference(a, b) -> str:
    try:
        x, y = np.asarray(a, float), np.asarray(b, float)
        if x.shape != y.shape:
            return f"shapes {x.shape} vs {y.shape}"
        rel = np.abs(x - y) / np.maximum(np.abs(x), np.finfo(float).tiny)
        return f"largest relative difference {np.nanmax(rel):.3g}"
    except (TypeError, ValueError):
        return f"{str(a)[:60]} vs {str(b)[:60]}"


def compare(old: dict, new: dict) -> list[str]:
    """Lines describing every difference between two sets of run records (empty: identical)."""
    lines = [f"only in the first: {k}" for k in sorted(set(old) - set(new))]
    lines += [f"only in the second: {k}" for k in sorted(set(new) - set(old))]
    for key in sorted(set(old) & set(new)):
        a, b = old[key], new[key]
        for field in sorted(set(a) | set(b)):
            if a.get(field) != b.get(field):
                lines.append(f"{'/'.join(map(str, key))} {field}: {_largest_difference(a.get(field), b.get(field))}")
    return lines


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m experiments.compare", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("old", type=pathlib.Path, help="output folder or results.json")
    p.add_argument("new", type=pathlib.Path, help="output folder or results.json")
    args = p.parse_args(argv)
    old, new = _records(args.old), _records(args.new)
    lines = compare(old, new)
    print("\n".join(lines) if lines else f"{len(old)} run records, bit-identical")
    return 1 if lines else 0


if __name__ == "__main__":
    sys.exit(main())

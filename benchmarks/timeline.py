"""A command's timeline: when its processes reached each mark, from the command's start.

Run a study with ``GMR_JAX_TIMELINE=FILE`` in its environment (``gmr_jax.timeline``), then::

    GMR_JAX_TIMELINE=/tmp/tl.txt python -m experiments.reach --no-plots --out /tmp/study
    python -m benchmarks.timeline /tmp/tl.txt

prints every mark (seconds from the command's start, the process, the label; the process
server's "runner imported" is when its imports were done) and, per run in a process of its own,
the seconds from the command asking for its process to the process's start, to the run's
clock (``timing``'s zero) and to the run's end. ``--out`` writes the same as JSON.
"""

from __future__ import annotations

import argparse
import json
import sys

from gmr_jax import timeline

START = "command start"
STEPS = (("process asked", "process started"), ("process started", "process entry"),
         ("process entry", "run clock"), ("run clock", "run end"), ("run end", "result received"))


def summary(marks) -> dict:
    """The marks as seconds from the first ``command start`` (else the first mark): ``marks``
    [[s, pid, label]] and per run ``runs`` {run: {"asked→started": s, …}} where both marks exist."""
    if not marks:
        raise ValueError("the timeline holds no marks")
    t0 = next((t for t, _, label in marks if label == START), marks[0][0])
    first: dict = {}
    for t, _, label in marks:
        first.setdefault(label, t - t0)
    runs: dict = {}
    for label in first:
        for a, b in STEPS:
            if label.startswith(a + " "):
                run = label[len(a) + 1:]
                if f"{b} {run}" in first:
                    runs.setdefault(run, {})[f"{a} → {b}"] = first[f"{b} {run}"] - first[label]
    return {"marks": [[round(t - t0, 6), pid, label] for t, pid, label in marks], "runs": runs}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m benchmarks.timeline", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("file", help="a timeline file written with GMR_JAX_TIMELINE")
    p.add_argument("--out", help="write the summary as JSON to this file")
    args = p.parse_args(argv)
    try:
        result = summary(timeline.read(args.file))
    except (OSError, ValueError) as err:
        print(f"python -m benchmarks.timeline: error: {args.file}: {err}", file=sys.stderr)
        return 2
    for t, pid, label in result["marks"]:
        print(f"{t:9.3f} s  {pid:>8}  {label}")
    for run, steps in result["runs"].items():
        print(f"{run}: " + ", ".join(f"{step} {s:.2f} s" for step, s in steps.items()))
    if args.out:
        with open(args.out, "w") as f:
            json.dump(result, f, indent=1)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

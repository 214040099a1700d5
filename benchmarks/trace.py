"""Profiles from JAX's profiler: where a GPU program's time goes, kernel by kernel, and where
XLA's compilation of a program goes, phase by phase.

``jax.profiler.trace`` records CUPTI's kernel events on the device planes and XLA's own trace
annotations (compiler phases and passes) on the host planes of an XSpace; this module reads that
XSpace back with ``jax.profiler.ProfileData`` and summarises it. Used by ``benchmarks.sstep
--profile`` and ``benchmarks.compile --profile``.
"""

from __future__ import annotations

import bisect
import collections
import contextlib
import glob
import os
from typing import Iterator

import jax

# Lines of a device plane that repeat the stream lines' kernels under another grouping.
_DERIVED_LINES = frozenset({"XLA Modules", "XLA Ops", "Steps", "TensorFlow Ops", "TensorFlow Name Scope",
                            "Source", "Launch Stats", "XLA TraceMe"})


@contextlib.contextmanager
def recorded(trace_dir: str) -> Iterator[list]:
    """Record a profile of the enclosed code into ``trace_dir``; the yielded list holds the
    ``ProfileData`` once the block has finished."""
    os.makedirs(trace_dir, exist_ok=True)
    before = set(glob.glob(os.path.join(trace_dir, "**", "*.xplane.pb"), recursive=True))
    out = []
    with jax.profiler.trace(trace_dir):
        yield out
    new = sorted(set(glob.glob(os.path.join(trace_dir, "**", "*.xplane.pb"), recursive=True)) - before,
                 key=os.path.getmtime)
    if not new:
        raise RuntimeError(f"jax.profiler.trace wrote no .xplane.pb under {trace_dir}")
    out.append(jax.profiler.ProfileData.from_file(new[-1]))


def device_events(profile) -> list[tuple[str, int, int]]:
    """[(name, start ns, duration ns)] of every kernel and memory copy on the device planes
    (``/device:GPU:n``), sorted by start; [] where the device records none (the CPU)."""
    events = []
    for plane in profile.planes:
        if not plane.name.startswith("/device:") or plane.name.startswith("/device:CUSTOM"):
            continue
        for line in plane.lines:
            if line.name in _DERIVED_LINES:
                continue
            events.extend((ev.name, ev.start_ns, ev.duration_ns) for ev in line.events)
    return sorted(events, key=lambda e: e[1])


def device_lines(profile) -> dict[str, list[str]]:
    """{device plane: its line names} (to check what ``device_events`` counted)."""
    return {p.name: [line.name for line in p.lines] for p in profile.planes if p.name.startswith("/device:")}


def busy_ns(events: list[tuple[str, int, int]]) -> int:
    """Length of the union of the events' intervals: the time the device was doing anything."""
    total, end = 0, None
    for _, start, dur in events:
        stop = start + dur
        if end is None or start >= end:
            total += dur
            end = stop
        elif stop > end:
            total += stop - end
            end = stop
    return total


def kernel_summary(events: list[tuple[str, int, int]], steps: int, top: int = 12) -> dict:
    """The device time of a program that ran ``steps`` loop iterations: kernels per step, busy
    time per step, the wall span of the first to the last kernel per step, the idle share, and
    the ``top`` kernels by total time."""
    if not events:
        return {"kernels": 0}
    span = events[-1][1] + events[-1][2] - events[0][1]
    busy = busy_ns(events)
    by_name = collections.defaultdict(lambda: [0, 0])
    for name, _, dur in events:
        by_name[name][0] += 1
        by_name[name][1] += dur
    durs = sorted(d for _, _, d in events)
    gaps = sorted(max(0, b[1] - (a[1] + a[2])) for a, b in zip(events, events[1:]))
    return {
        "kernels": len(events), "kernels_per_step": len(events) / steps,
        "span_us_per_step": span / steps / 1e3, "busy_us_per_step": busy / steps / 1e3,
        "idle_fraction": 1 - busy / span if span else 0.0,
        "kernel_us_median": durs[len(durs) // 2] / 1e3,
        "gap_us_median": gaps[len(gaps) // 2] / 1e3 if gaps else 0.0,
        "top": [{"name": n[:120], "count": c, "us_per_step": t / steps / 1e3}
                for n, (c, t) in sorted(by_name.items(), key=lambda kv: -kv[1][1])[:top]],
    }


def host_windows(profile, prefix: str) -> list[tuple[str, int, int]]:
    """[(name, start ns, duration ns)] of the host trace annotations whose name starts with
    ``prefix`` (e.g. ``jax.profiler.TraceAnnotation``s that a benchmark put around its steps),
    sorted by start, on the clock of :func:`device_events`."""
    windows = [(ev.name, ev.start_ns, ev.duration_ns) for plane in profile.planes if plane.name.startswith("/host:")
               for line in plane.lines for ev in line.events if ev.name.startswith(prefix)]
    return sorted(windows, key=lambda w: w[1])


def split_by_windows(events: list[tuple[str, int, int]], windows: list[tuple[str, int, int]]) -> dict:
    """{window name: the events that start inside that window}; events inside no window are
    listed under None. Windows must not overlap (a benchmark that waits for each step's results
    before starting the next guarantees that its device work lies inside its window)."""
    out = collections.defaultdict(list)
    starts = [w[1] for w in windows]
    for ev in events:
        i = bisect.bisect_right(starts, ev[1]) - 1
        name = windows[i][0] if i >= 0 and ev[1] < windows[i][1] + windows[i][2] else None
        out[name].append(ev)
    return dict(out)


def host_event_totals(profile, top: int = 40) -> list[dict]:
    """The ``top`` host trace annotations (XLA's compiler phases and passes, not Python frames)
    by total inclusive time, summed over threads: nested annotations are counted in their
    parents too, and phases that run on several threads add up their threads' times."""
    total, count = collections.Counter(), collections.Counter()
    for plane in profile.planes:
        if not plane.name.startswith("/host:"):
            continue
        for line in plane.lines:
            for ev in line.events:
                if not ev.name.startswith("$"):  # "$file:line function": Python frames
                    total[ev.name] += ev.duration_ns
                    count[ev.name] += 1
    return [{"name": n[:120], "count": count[n], "s": t / 1e9} for n, t in total.most_common(top)]

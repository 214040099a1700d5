"""benchmarks.trace: the busy time of overlapping kernels against a count of covered instants,
the per-step summary's arithmetic, and a real profile of a compilation on the CPU."""

import time

import jax
import jax.numpy as jnp
import numpy as np

from benchmarks import trace


def _covered(events):
    """Instants (integer ns) covered by at least one event: an independent busy time."""
    covered = set()
    for _, start, dur in events:
        covered.update(range(start, start + dur))
    return len(covered)


def test_busy_time_is_the_union_of_the_intervals():
    rng = np.random.default_rng(0)
    for _ in range(50):
        starts = np.sort(rng.integers(0, 400, size=rng.integers(1, 20)))
        events = [("k", int(s), int(d)) for s, d in zip(starts, rng.integers(0, 60, size=len(starts)))]
        assert trace.busy_ns(events) == _covered(events)
    # nested, touching and disjoint intervals
    events = [("a", 0, 100), ("b", 10, 20), ("c", 100, 5), ("d", 200, 10)]
    assert trace.busy_ns(events) == 115


def test_kernel_summary_per_step():
    # two steps of three kernels, 1 µs each, with 0.5 µs gaps: span 8.5 µs, busy 6 µs
    events, t = [], 0
    for _ in range(2):
        for name in ("gemm", "gemm", "add"):
            events.append((name, t, 1000))
            t += 1500
    s = trace.kernel_summary(events, steps=2)
    assert s["kernels"] == 6 and s["kernels_per_step"] == 3
    assert np.isclose(s["busy_us_per_step"], 3.0) and np.isclose(s["span_us_per_step"], 4.25)
    assert np.isclose(s["idle_fraction"], 1 - 6 / 8.5)
    assert np.isclose(s["gap_us_median"], 0.5) and np.isclose(s["kernel_us_median"], 1.0)
    assert s["top"][0] == {"name": "gemm", "count": 4, "us_per_step": 2.0}
    assert trace.kernel_summary([], steps=3) == {"kernels": 0}


def test_a_compilation_profile_on_the_cpu(tmp_path):
    def f(x):
        for i in range(5):
            x = jnp.tanh(x @ x.T) + i
        return x

    lowered = jax.jit(f).lower(jnp.ones((16, 16)))
    t0 = time.perf_counter()
    with trace.recorded(str(tmp_path)) as rec:
        lowered.compile()
    wall = time.perf_counter() - t0
    profile = rec[0]
    assert trace.device_events(profile) == []  # the CPU records no device kernels
    phases = trace.host_event_totals(profile, top=1000)
    assert phases and all(p["s"] >= 0 and p["count"] >= 1 for p in phases)
    assert not any(p["name"].startswith("$") for p in phases)  # no Python frames
    # XLA's single compile call of this program is annotated and lies inside the recorded block
    once = [p for p in phases if "compile" in p["name"].lower() and p["count"] == 1]
    assert once and all(p["s"] <= wall for p in once)


def test_events_are_split_by_the_windows_they_start_in():
    windows = [("stage a", 100, 50), ("stage b", 200, 100)]
    events = [("k1", 90, 5), ("k2", 100, 10), ("k3", 149, 30), ("k4", 150, 1), ("k5", 250, 5), ("k6", 300, 1)]
    split = trace.split_by_windows(events, windows)
    assert [e[0] for e in split["stage a"]] == ["k2", "k3"]  # a window is [start, start + duration)
    assert [e[0] for e in split["stage b"]] == ["k5"]
    assert [e[0] for e in split[None]] == ["k1", "k4", "k6"]

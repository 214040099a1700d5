"""gmr_jax.stats against closed forms: the IQM by hand, the bootstrap interval of a large sample
against the normal approximation, the degenerate cases."""

import pathlib
import subprocess
import sys

import numpy as np
import pytest

from gmr_jax import stats


def test_iqm_is_the_mean_of_the_middle_half():
    assert stats.iqm(np.arange(8)) == pytest.approx(3.5)  # mean of 2, 3, 4, 5
    assert stats.iqm([0, 0, 50, 50, 50, 50, 50, 50]) == pytest.approx(50.0)  # two outlying seeds cut
    assert stats.iqm([0.1]) == 0.1 and stats.over_seeds([7.0]).iqm == 7.0  # one value: itself


def test_a_one_seed_study_does_not_import_scipy_stats():
    """The CLI and its report import ``scipy.stats`` (about a second) only when statistics over
    several seeds are computed: a one-seed summary and the command's start do without it."""
    code = ("import sys, numpy as np; from experiments import cli, reach, report; from gmr_jax import stats; "
            "assert stats.over_seeds([3.0]).format() == '3.0 (1 seed)'; "
            "print('scipy.stats' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                         cwd=pathlib.Path(__file__).parents[1])
    assert out.stdout.strip() == "False", out.stdout + out.stderr


def test_bootstrap_interval_of_a_large_sample_matches_the_normal_approximation():
    """For n = 400 draws the mean's 95 % interval is mean ± 1.96 σ/√n to within a few percent of
    its width (the central limit theorem; the percentile bootstrap converges to it at O(1/√n))."""
    x = np.random.default_rng(1).normal(10.0, 2.0, 400)
    s = stats.over_seeds(x)
    half = 1.96 * x.std(ddof=1) / np.sqrt(x.size)
    assert s.low < s.mean < s.high
    assert s.mean == pytest.approx(x.mean())
    assert (s.high - s.low) / 2 == pytest.approx(half, rel=0.1)
    assert (s.low + s.high) / 2 == pytest.approx(x.mean(), abs=0.1 * half)


def test_interval_is_reproducible_and_degenerate_cases_are_explicit():
    counts = [27, 50, 48, 50, 45, 50]
    a, b = stats.over_seeds(counts), stats.over_seeds(counts)
    assert a == b  # fixed generator
    assert a.low <= a.mean <= a.high and 27 <= a.low and a.high <= 50
    assert (a.n, a.min, a.max) == (6, 27.0, 50.0)
    same = stats.over_seeds([50] * 6)
    assert (same.low, same.high, same.iqm) == (50.0, 50.0, 50.0)
    one = stats.over_seeds([12])
    assert np.isnan(one.low) and np.isnan(one.high) and one.format() == "12.0 (1 seed)"
    assert a.format().startswith("45.0 [")
    with pytest.raises(ValueError, match="non-finite"):
        stats.over_seeds([1.0, float("nan")])

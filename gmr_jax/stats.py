"""Statistics over seeds: how sure a study's numbers are.

A study trains each configuration for several seeds; its per-seed results (a success count out
of 50, a final-state MSE) are a small sample. :func:`over_seeds` summarises one such sample the
way rliable (Agarwal et al., 2021, "Deep RL at the edge of the statistical precipice")
recommends: the mean with a 95 % bootstrap confidence interval, and the interquartile mean (IQM,
the mean of the middle 50 %, robust to a few outlying seeds), with scipy's maintained bootstrap
and trimmed mean rather than hand-written ones.

The interval is the percentile bootstrap with a fixed generator, so the same per-seed values
always give the same interval. Percentile rather than scipy's default BCa: BCa's acceleration
is undefined for the ties that success counts are full of (e.g. every seed 50/50), and
percentile is what rliable uses. With one seed there is no interval (NaN); when every seed has
the same value the interval is that value.

``scipy.stats`` is imported where it is first needed, not with this module: its import takes
about a second, and a one-seed study (the default run) needs none of it.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

CONFIDENCE = 0.95
RESAMPLES = 10_000


class SeedStats(NamedTuple):
    """Summary of one per-seed sample: ``n`` seeds, their ``mean`` with the bootstrap interval
    [``low``, ``high``], the interquartile mean ``iqm``, and the range [``min``, ``max``]."""

    n: int
    mean: float
    low: float
    high: float
    iqm: float
    min: float
    max: float

    def format(self, digits: int = 1) -> str:
        """"46.2 [38.5, 50.0], IQM 48.0 (27–50)"; without an interval "46.0 (1 seed)"."""
        f = f"{{:.{digits}f}}"
        if self.n < 2:
            return f"{f.format(self.mean)} (1 seed)"
        ends = lambda v: f"{v:g}" if float(v).is_integer() else f.format(v)  # noqa: E731
        return (f"{f.format(self.mean)} [{f.format(self.low)}, {f.format(self.high)}], "
                f"IQM {f.format(self.iqm)} ({ends(self.min)}–{ends(self.max)})")


def iqm(values) -> float:
    """Interquartile mean: the mean of the values between the 25th and 75th percentile
    (``scipy.stats.trim_mean`` with 25 % cut from each end; that of one value is the value)."""
    x = np.asarray(values, np.float64).reshape(-1)
    if x.size == 1:
        return float(x[0])
    import scipy.stats  # noqa: PLC0415 (slow to import; see the module docstring)

    return float(scipy.stats.trim_mean(x, 0.25))


def over_seeds(values, confidence: float = CONFIDENCE, resamples: int = RESAMPLES, seed: int = 0) -> SeedStats:
    """Mean, bootstrap interval, IQM and range of per-seed values [S].

    Args:
      values: one number per seed (non-finite values are an error: a failed seed must be
        counted, e.g. as 0 successes, by the caller).
      confidence: coverage of the interval (0.95).
      resamples: bootstrap resamples.
      seed: the resampling generator's seed (fixed: the interval is reproducible).
    """
    x = np.asarray(values, np.float64).reshape(-1)
    if x.size == 0:
        raise ValueError("over_seeds: no values")
    if not np.all(np.isfinite(x)):
        raise ValueError(f"over_seeds: non-finite per-seed values {x.tolist()}")
    mean = float(x.mean())
    if x.size < 2:
        low = high = float("nan")
    elif np.all(x == x[0]):
        low = high = mean
    else:
        import scipy.stats  # noqa: PLC0415 (slow to import; see the module docstring)

        ci = scipy.stats.bootstrap((x,), np.mean, confidence_level=confidence, n_resamples=resamples,
                                   method="percentile", rng=np.random.default_rng(seed)).confidence_interval
        low, high = float(ci.low), float(ci.high)
    return SeedStats(int(x.size), mean, low, high, iqm(x), float(x.min()), float(x.max()))

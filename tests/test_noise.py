"""Smoothed exploration noise: the toolbox rule (scipy reference) and its statistics."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.ndimage

from tolerances import assert_close, linear_tol

from gmr_jax import noise
from gmr_jax.config import NoiseConfig

CFG = NoiseConfig()


@pytest.mark.parametrize("T", [1, 2, 5, 9, 17, 80])
def test_filter_matches_scipy(T):
    """Same filter as the toolbox's scipy call (σ = 2, mode 'reflect', truncate 4), also for
    horizons shorter than the kernel radius (8), where the signal is reflected repeatedly."""
    x = np.random.default_rng(T).normal(size=(T, 6))
    ours = np.asarray(noise.gaussian_filter_time(jnp.asarray(x), 2.0, 4.0))
    ref = scipy.ndimage.gaussian_filter1d(x, 2.0, axis=0, mode="reflect", truncate=4.0)
    # A convex combination of 2·8 + 1 = 17 samples with weights that are themselves computed
    # (exp and a normalising sum of 17 terms): |Δ| ≤ c·n·ε·max|x| with n = 2·17 for each program
    # (tests/tolerances.py), relative to the filtered signal's largest entry.
    assert_close(ours, ref, 2 * linear_tol(1.0, 2 * 17) * np.abs(x).max() / np.abs(ref).max())


@pytest.fixture(scope="module")
def sample():
    return jax.jit(jax.vmap(lambda k: noise.smooth_noise(k, 80, 6, CFG)))


def test_smooth_noise_is_the_toolbox_rule():
    """The whole pipeline equals scipy applied to the same raw draws, divided by the population
    std of each column."""
    key = jax.random.key(0)
    eps = np.asarray(noise.smooth_noise(key, 80, 6, CFG))
    raw = np.asarray(jax.random.normal(key, (80, 6)))
    ref = scipy.ndimage.gaussian_filter1d(raw, 2.0, axis=0, mode="reflect", truncate=4.0)
    filtered = ref
    ref = ref / np.std(ref, axis=0)
    # The filter as in test_filter_matches_scipy, then a division by a population std of 80
    # values (a sum of 80 squares and a root: c·2·80·ε relative, tests/tolerances.py); the
    # filter's error enters both the numerator and the std.
    rel_filter = 2 * linear_tol(1.0, 2 * 17) * np.abs(raw).max() / np.abs(filtered).max()
    assert_close(eps, ref, 2 * rel_filter + 2 * linear_tol(1.0, 2 * 80))


def test_statistics(sample):
    eps = np.asarray(sample(jax.random.split(jax.random.key(1), 2000)))  # [2000, 80, 6]
    # unit (population) variance per rollout and dimension: exact by the renormalisation
    # (the renormalisation in jax and numpy's var each round at c·2·80·ε relative, tests/tolerances.py)
    assert_close(eps.var(axis=1), np.ones((2000, 6)), 2 * linear_tol(1.0, 2 * 80))
    # not re-centred: the column means spread around 0 (a smoothed walk has a wide sample mean)
    means = eps.mean(axis=1)
    assert abs(means.mean()) < 0.05 and means.std() > 0.1
    # correlation across neighbouring steps: a Gaussian filter of std σ makes white noise into a
    # process with autocorrelation ρ(k) = exp(-k² / (4σ²)) (0.939, 0.779, 0.105 at k = 1, 2, 6).
    # The empirical within-rollout estimate is biased low by ~(1 - ρ(k)) / 2 for T = 80 since each
    # rollout is centred on its own mean; compare the pooled, globally-centred estimate instead.
    flat = eps.reshape(-1, 80, 6)
    for k in (1, 2, 6):
        rho = np.mean(flat[:, k:] * flat[:, :-k]) / np.mean(flat * flat)
        assert abs(rho - math.exp(-k * k / 16)) < 0.03, (k, rho)
    # independent across action dimensions
    c = np.corrcoef(eps.transpose(2, 0, 1).reshape(6, -1))
    assert np.max(np.abs(c - np.eye(6))) < 0.03


def test_same_key_same_noise(sample):
    keys = jax.random.split(jax.random.key(2), 2000)  # the batch size compiled above
    a, b = np.asarray(sample(keys)), np.asarray(sample(keys))
    np.testing.assert_array_equal(a, b)
    assert np.max(np.abs(a[0] - a[1])) > 0.5


def test_options_and_dtypes():
    key = jax.random.key(3)
    raw = noise.smooth_noise(key, 40, 6, NoiseConfig(smooth=False))
    np.testing.assert_array_equal(np.asarray(raw), np.asarray(jax.random.normal(key, (40, 6))))
    unnorm = np.asarray(noise.smooth_noise(key, 40, 6, NoiseConfig(renormalize=False)))
    assert np.all(unnorm.std(axis=0) < 0.7)  # smoothing alone shrinks the variance (to ~1/(2σ√π))
    assert noise.smooth_noise(key, 10, 6, CFG, dtype=jnp.float32).dtype == jnp.float32
    one = np.asarray(noise.smooth_noise(key, 1, 6, CFG))  # T = 1: nothing to renormalise by
    assert np.all(np.isfinite(one))
    with pytest.raises(ValueError, match="sigma"):
        noise.smooth_noise(key, 10, 6, NoiseConfig(sigma=0.0))

"""Smoothed exploration noise, the toolbox rule (mdgps-toolbox.md §6, ``generate_noise``).

ε = randn(T, dU); each action dimension is filtered over time with a Gaussian of standard
deviation ``sigma`` time steps (the toolbox's ``smooth_noise_var`` is passed to
``scipy.ndimage.gaussian_filter`` as a *standard deviation*, a naming quirk kept here), mode
'reflect' (half-sample symmetric: d c b a | a b c d | d c b a), kernel truncated at
``truncate``·sigma; then each dimension is divided by its population standard deviation over T
(not re-centred), so every dimension has unit empirical variance again.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np

from gmr_jax.config import NoiseConfig

Array = jax.Array


def gaussian_kernel(sigma: float, truncate: float = 4.0) -> np.ndarray:
    """scipy's 1-D Gaussian filter weights, [2r + 1] with r = int(truncate·sigma + 0.5)."""
    radius = int(truncate * float(sigma) + 0.5)
    x = np.arange(-radius, radius + 1, dtype=np.float64)
    w = np.exp(-0.5 * (x / float(sigma)) ** 2)
    return w / w.sum()


def _reflect_index(n: int, radius: int) -> np.ndarray:
    """Indices of a length-n signal padded by ``radius`` on each side in scipy 'reflect' mode.

    Works for any radius (also radius ≥ n, where the signal is reflected repeatedly).
    """
    idx = np.arange(-radius, n + radius)
    period = 2 * n
    idx = np.mod(idx, period)
    return np.where(idx < n, idx, period - 1 - idx)


def gaussian_filter_time(x: Array, sigma: float, truncate: float = 4.0) -> Array:
    """``scipy.ndimage.gaussian_filter1d(x, sigma, axis=0, mode='reflect', truncate=truncate)``.

    x: [T, ...] → [T, ...], filtered along the leading (time) axis; follows x's dtype.
    """
    T = x.shape[0]
    w = gaussian_kernel(sigma, truncate)
    radius = (w.shape[0] - 1) // 2
    xp = x[_reflect_index(T, radius)]  # [T + 2r, ...]
    # Sum of shifted copies: 2r + 1 static slices, cheap for the small radii used here and
    # exact (no FFT rounding).
    out = sum(jnp.asarray(w[j], x.dtype) * xp[j:j + T] for j in range(w.shape[0]))
    return out


def smooth_noise(key: Array, T: int, dU: int, cfg: NoiseConfig = NoiseConfig(), dtype=None) -> Array:
    """Exploration noise ε [T, dU] for one rollout, toolbox rule.

    Args:
      key: PRNG key (same key → same noise).
      T, dU: horizon and action size (static).
      cfg: ``NoiseConfig`` (smooth, sigma, renormalize, truncate).
      dtype: float dtype (default: JAX's default float).

    With ``cfg.smooth`` the columns are Gaussian-filtered over time and, with
    ``cfg.renormalize``, divided by their population std over T (each column then has empirical
    variance exactly 1). With T = 1 there is no spread to renormalise by, and the column is
    left as filtered (the toolbox would divide by zero).
    """
    dtype = jnp.result_type(float) if dtype is None else dtype
    eps = jax.random.normal(key, (T, dU), dtype=dtype)
    if not cfg.smooth:
        return eps
    if not (cfg.sigma > 0 and math.isfinite(cfg.sigma)):
        raise ValueError(f"noise.sigma={cfg.sigma!r}: must be a positive number")
    eps = gaussian_filter_time(eps, cfg.sigma, cfg.truncate)
    if cfg.renormalize and T > 1:
        eps = eps / jnp.std(eps, axis=0)
    return eps

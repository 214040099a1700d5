"""The pytrees every stage exchanges.

Axis conventions (leading axes first): condition M, sample N, time T, then features.
dX = 12 (6 joint angles, 6 joint velocities), dU = 6 joint torques for the Jaco 2, but no
function here assumes those sizes. Each container is a ``NamedTuple`` so that it is a pytree,
works under ``jit``/``vmap``/``lax.scan`` and has no mutable state. Shapes below are for one
condition; batched versions carry extra leading axes.
"""

from __future__ import annotations

from typing import NamedTuple

import jax


Array = jax.Array


class LinearGaussianPolicy(NamedTuple):
    """Time-varying linear-Gaussian controller u_t ~ N(K_t x_t + k_t, pol_covar_t).

    Attributes:
      K: [T, dU, dX] feedback gains.
      k: [T, dU] open-loop offsets.
      pol_covar: [T, dU, dU] action covariance.
      chol_pol_covar: [T, dU, dU] *upper* Cholesky factor U with pol_covar = Uᵀ U (the
        toolbox convention, so a sample is u = K x + k + Uᵀ ε).
      inv_pol_covar: [T, dU, dU] precision (the Q_uu of the backward pass).
    """

    K: Array
    k: Array
    pol_covar: Array
    chol_pol_covar: Array
    inv_pol_covar: Array


class Dynamics(NamedTuple):
    """Time-varying linear-Gaussian dynamics x_{t+1} ~ N(Fm_t [x_t; u_t] + fv_t, dyn_covar_t).

    Attributes:
      Fm: [T, dX, dX + dU] (the entry at t = T-1 is unused and zero).
      fv: [T, dX].
      dyn_covar: [T, dX, dX].
      x0mu: [dX] initial-state mean.
      x0sigma: [dX, dX] initial-state covariance.
    """

    Fm: Array
    fv: Array
    dyn_covar: Array
    x0mu: Array
    x0sigma: Array


class QuadraticCost(NamedTuple):
    """Per-step quadratic cost ℓ_t(y) ≈ ½ yᵀ Cm_t y + yᵀ cv_t + cc_t in absolute coordinates, y = [x; u].

    Attributes:
      Cm: [T, dX + dU, dX + dU].
      cv: [T, dX + dU].
      cc: [T].
    """

    Cm: Array
    cv: Array
    cc: Array


class Marginals(NamedTuple):
    """Gaussian state-action marginals of a controller under linear dynamics (LQR forward pass).

    Attributes:
      mu: [T, dX + dU].
      sigma: [T, dX + dU, dX + dU].
    """

    mu: Array
    sigma: Array


class Trajectories(NamedTuple):
    """Rollouts. Leading batch axes (e.g. [M, N]) precede the ones listed.

    Attributes:
      X: [T, dX] states x_0 … x_{T-1} (x_t is the state at which u_t was chosen).
      U: [T, dU] actions actually applied (after torque clipping).
      ee: [T, 3] end-effector site positions at x_t (world frame, m).
    """

    X: Array
    U: Array
    ee: Array


class GMM(NamedTuple):
    """Gaussian mixture with a fixed capacity of K_max clusters; inactive clusters are masked.

    Attributes:
      mu: [K_max, D] means.
      sigma: [K_max, D, D] covariances.
      logmass: [K_max] log mixing weights (−inf for inactive clusters).
      active: [K_max] bool, which clusters are in use.
      n_points: [] number of (valid) points at the last (re-)initialisation, which sets the
        prior's n₀ (toolbox behaviour, mdgps-toolbox.md §3.2).
      initialized: [] bool, whether EM has ever run (otherwise the next update initialises).
    """

    mu: Array
    sigma: Array
    logmass: Array
    active: Array
    n_points: Array
    initialized: Array

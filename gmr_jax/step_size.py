"""The KL step size of the C-step and its adaptation (mdgps-toolbox.md §1.1, §1.3).

The C-step bounds KL(p_new ‖ anchor) by ε = kl_step · step_mult · T. After every iteration the
toolbox compares the improvement the previous iteration's model predicted with the one that
happened and rescales step_mult (``_set_new_mult``). Both are estimated with the Laplace cost of
a controller under fitted dynamics (``lqr.estimate_cost``), or, with ``step_rule="mc"``, the
actual improvement is the sample cost's.

The anchor is the KL anchor of the C-step: the previous local controller for trajectory
optimisation, the linearised global policy for MDGPS; the same rule serves both.

All functions are per condition or batched over a leading condition axis.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from gmr_jax import lqr
from gmr_jax.config import StepConfig
from gmr_jax.types import Dynamics, LinearGaussianPolicy, QuadraticCost

Array = jax.Array


def kl_epsilon(step_mult, T: int, cfg: StepConfig = StepConfig()):
    """KL budget of the C-step, ε = kl_step·step_mult·T (summed over the horizon). [] → []."""
    return cfg.kl_step * step_mult * T


def step_multiplier(predicted, actual, step_mult, cfg: StepConfig = StepConfig()):
    """Toolbox ``_set_new_mult`` (§1.3).

    Models the improvement as a·KL + b·KL² and takes its maximiser:
    new_mult = predicted / (2·max(1e-4, predicted − actual)) clipped to [0.1, 5.0];
    returns clip(new_mult·step_mult, min_step_mult, max_step_mult).

    Args:
      predicted, actual: [...] predicted and actual cost improvement.
      step_mult: [...] current multiplier.
    Returns:
      [...] new step multiplier (dtype of the inputs).
    """
    predicted = jnp.asarray(predicted)
    dtype = jnp.result_type(predicted, actual, step_mult)
    predicted = predicted.astype(dtype)
    actual = jnp.asarray(actual, dtype)
    step_mult = jnp.asarray(step_mult, dtype)
    new_mult = predicted / (2.0 * jnp.maximum(1e-4, predicted - actual))
    new_mult = jnp.clip(new_mult, 0.1, 5.0)
    return jnp.clip(new_mult * step_mult, cfg.min_step_mult, cfg.max_step_mult)


def laplace_total(policy: LinearGaussianPolicy, dyn: Dynamics, cost: QuadraticCost) -> Array:
    """Σ_t of the Laplace cost estimate per condition: policy, dyn, cost [M, T, ...] → [M]."""
    return jnp.sum(jax.vmap(lqr.estimate_cost)(policy, dyn, cost), axis=-1)


class LocalModel(NamedTuple):
    """What one iteration's C-step was based on, per condition (leading axis M); the next
    iteration's step-size rule compares against it.

    Attributes:
      anchor: LinearGaussianPolicy [M, T, ...], the KL anchor of the C-step.
      dyn: Dynamics [M, ...], the fitted dynamics.
      cost: QuadraticCost [M, ...], the cost expansion.
      sample_cost: [M] the mean total cost of the samples.
    """

    anchor: LinearGaussianPolicy
    dyn: Dynamics
    cost: QuadraticCost
    sample_cost: Array


def improvements(cfg: StepConfig, prev: LocalModel, executed: LinearGaussianPolicy,
                 cur: LocalModel) -> tuple[Array, Array]:
    """Predicted and actual improvement of the previous C-step (§1.3), per condition [M].

    predicted = L(prev.anchor; prev) − L(executed; prev), where ``executed`` are the controllers
    the previous C-step produced (and this iteration sampled); actual = L(prev.anchor; prev) −
    L(cur.anchor; cur) ("laplace"), or the change of the mean sample cost ("mc"). L(π; m) is
    :func:`laplace_total` of π under m's dynamics and cost.
    """
    prev_laplace = laplace_total(prev.anchor, prev.dyn, prev.cost)
    prev_predicted = laplace_total(executed, prev.dyn, prev.cost)
    if cfg.step_rule == "laplace":
        return prev_laplace - prev_predicted, prev_laplace - laplace_total(cur.anchor, cur.dyn, cur.cost)
    return prev.sample_cost - prev_predicted, prev.sample_cost - cur.sample_cost


def update(cfg: StepConfig, step_mult: Array, first: Array, prev: LocalModel,
           executed: LinearGaussianPolicy, cur: LocalModel) -> tuple[Array, Array, Array]:
    """The step multiplier of this iteration's C-step: kept in the first iteration (there is no
    previous one), else rescaled by :func:`step_multiplier`.

    Returns: (step_mult [M], predicted [M], actual [M]).
    """
    predicted, actual = improvements(cfg, prev, executed, cur)
    adjusted = step_multiplier(predicted, actual, step_mult, cfg)
    return jnp.where(first, step_mult, adjusted), predicted, actual

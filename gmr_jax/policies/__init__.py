"""Global policies of MDGPS: the interface (``base``), the baseline MLP (``mlp``) and GMR (``gmr``).

The one registry of policies and algorithms:

- :data:`POLICIES`: name -> :class:`PolicySpec`, where the policy's module and factory are, which
  field of the run's ``Config`` holds its settings, and what its S-step data contain;
- :data:`ALGORITHMS`: algorithm -> the name of its global policy (None: trajectory optimisation
  only, the paper's "LQR base layer").

A new policy is a module with a factory ``(cfg) -> Policy``, its settings dataclass as a field of
``Config``, and one line in each table. ``make_policy(name, cfg)`` is cached per (name, cfg), so
equal configurations give the *same* Policy object and jitted functions that take it as a static
argument compile once.
"""

from __future__ import annotations

import functools
import importlib
from typing import TYPE_CHECKING, NamedTuple

from gmr_jax.policies.base import (Normalization, Policy, PolicyParams, SStepData, l2_penalty,
                                   make_sstep_data, noisy_action, normalize_input)

if TYPE_CHECKING:
    from gmr_jax.config import Config


class PolicySpec(NamedTuple):
    """Where a policy is defined and how MDGPS feeds it.

    Attributes:
      module: the module that defines the policy.
      factory: the name of its ``(cfg) -> Policy`` function.
      config_field: the field of ``Config`` holding the policy's settings (a frozen dataclass).
      sstep_marginals: whether its S-step data also hold the LQR forward pass's mean states with
        their state covariances (GMR: decision §3.6 of gmr-method.md).
    """

    module: str
    factory: str
    config_field: str
    sstep_marginals: bool


POLICIES = {
    "mlp": PolicySpec("gmr_jax.policies.mlp", "make_mlp_policy", "mlp", sstep_marginals=False),
    "gmr": PolicySpec("gmr_jax.policies.gmr", "make_gmr_policy", "gmr", sstep_marginals=True),
}
ALGORITHMS = {"lqr": None, "mdgps": "mlp", "gmr": "gmr"}

__all__ = ["ALGORITHMS", "POLICIES", "Normalization", "Policy", "PolicyParams", "PolicySpec",
           "SStepData", "for_config", "l2_penalty", "make_policy", "make_sstep_data", "mean_fn",
           "noisy_action", "normalize_input", "sampling_fn", "spec_for"]


def make_policy(name: str, cfg=None) -> Policy:
    """The policy ``name`` built from its (frozen, hashable) configuration (default: the
    configuration dataclass's defaults). Equal configurations give the same object."""
    if name not in POLICIES:
        raise ValueError(f"policy name={name!r}: allowed values are {tuple(POLICIES)}")
    if cfg is None:  # the defaults of the dataclass in that field of Config
        import dataclasses

        from gmr_jax.config import Config
        cfg = next(f.default_factory for f in dataclasses.fields(Config)
                   if f.name == POLICIES[name].config_field)()
    return _make_policy(name, cfg)


@functools.lru_cache(maxsize=None)
def _make_policy(name: str, cfg) -> Policy:
    spec = POLICIES[name]
    return getattr(importlib.import_module(spec.module), spec.factory)(cfg)


def spec_for(cfg: "Config") -> PolicySpec | None:
    """The spec of the configured algorithm's global policy (None for trajectory optimisation)."""
    name = ALGORITHMS[cfg.algorithm]
    return None if name is None else POLICIES[name]


def for_config(cfg: "Config") -> Policy | None:
    """The configured algorithm's global policy (None for trajectory optimisation)."""
    name = ALGORITHMS[cfg.algorithm]
    return None if name is None else make_policy(name, getattr(cfg, POLICIES[name].config_field))


def mean_fn(policy: Policy, params: PolicyParams):
    """The policy's deterministic action as a rollout callable ``(t, x, eps_t) -> u``."""
    return lambda t, x, e: policy.mean(params, x)


def sampling_fn(policy: Policy, params: PolicyParams):
    """The policy with exploration noise as a rollout callable: u = mean(x) + chol(cov(x)) eps_t."""
    return lambda t, x, e: noisy_action(policy, params, x, e)

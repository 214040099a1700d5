"""Global policies of MDGPS: the interface (``base``), the baseline MLP (``mlp``) and GMR (``gmr``).

``make_policy(name, cfg)`` returns a :class:`~gmr_jax.policies.base.Policy`. It is cached per
(name, cfg), so equal configurations give the *same* Policy object and jitted functions that take
it as a static argument compile once.

The GMR module plugs in by defining ``make_gmr_policy(cfg) -> Policy`` in ``policies/gmr.py``.
"""

from __future__ import annotations

import functools
import importlib

from gmr_jax.policies.base import (Normalization, Policy, PolicyParams, SStepData, l2_penalty,
                                   make_sstep_data, noisy_action, normalize_input)

POLICIES = ("mlp", "gmr")

__all__ = ["POLICIES", "Normalization", "Policy", "PolicyParams", "SStepData", "l2_penalty",
           "make_policy", "make_sstep_data", "noisy_action", "normalize_input"]


def make_policy(name: str, cfg=None) -> Policy:
    """The policy ``name`` ("mlp" or "gmr") built from its (frozen, hashable) configuration.

    Args:
      name: "mlp" (MDGPS baseline, cfg: MLPConfig, default MLPConfig()) or "gmr" (cfg: the GMR
        configuration of ``policies/gmr.py``, default its own).
    Returns: the cached Policy for (name, cfg): equal configurations give the same object.
    Raises:
      ValueError: unknown name. NotImplementedError: "gmr" before ``policies/gmr.py`` exists.
    """
    if name == "mlp" and cfg is None:
        from gmr_jax.config import MLPConfig
        cfg = MLPConfig()
    return _make_policy(name, cfg)


@functools.lru_cache(maxsize=None)
def _make_policy(name: str, cfg) -> Policy:
    if name == "mlp":
        from gmr_jax.policies.mlp import make_mlp_policy
        return make_mlp_policy(cfg)
    if name == "gmr":
        try:
            gmr = importlib.import_module("gmr_jax.policies.gmr")
        except ModuleNotFoundError as err:
            if err.name != "gmr_jax.policies.gmr":
                raise
            raise NotImplementedError("the GMR policy (gmr_jax/policies/gmr.py) is not available yet") from err
        if not hasattr(gmr, "make_gmr_policy"):
            raise NotImplementedError("gmr_jax.policies.gmr defines no make_gmr_policy(cfg)")
        return gmr.make_gmr_policy(cfg) if cfg is not None else gmr.make_gmr_policy()
    raise ValueError(f"policy name={name!r}: allowed values are {POLICIES}")

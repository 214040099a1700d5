"""The policy interface of the S-step: a bundle of pure functions and the data they train on.

A global policy π(u | x) is described by a :class:`Policy`, a ``NamedTuple`` of pure functions
built from a (static, hashable) configuration at trace time, and by its parameters, a
:class:`PolicyParams` pytree. The S-step (``gmr_jax.sstep``) only needs this interface, so the
MDGPS baseline MLP (``policies/mlp.py``) and the GMR policy (``policies/gmr.py``) plug into the
same trainer.

Contract for a policy implementation:

- ``init(key, dX, dU, dtype=None) -> PolicyParams``. ``dtype`` defaults to JAX's default float
  type (float64 under ``jax_enable_x64``, else float32); every array of the params follows it.
  The normalisation starts as the identity with ``set = False``.
- ``mean(params, x [dX]) -> u [dU]``: the deterministic (test-time) action. The policy applies
  the input normalisation itself: x̃ = x·scale + bias.
- ``covariance(params, x [dX]) -> [dU, dU]``: the exploration covariance (symmetric PD).
- ``loss(params, batch: SStepData, key) -> (scalar, aux)``: the data term of the S-step
  objective for a minibatch, **without** the L2 term β·Σθ², which the S-step adds for all
  policies over ``params.net``. In ``batch``, ``tgt_prc`` already carries the normalised weight
  (w·P, toolbox §4.3 step 1) and ``wt`` holds that normalised weight (for terms that do not
  involve the precision). ``key`` drives reparameterised sampling (GMR latent); deterministic
  losses ignore it. ``aux`` is a dict of scalars (averaged per epoch into the S-step metrics).
- ``finalize(params, data: SStepData) -> params``: runs after the optimisation on the *whole*
  data set, with ``tgt_prc`` unweighted and ``wt`` the normalised weights (e.g. the MLP's
  closed-form variance rule).

The S-step optimises ``params.net`` only; ``params.norm`` and ``params.var`` are never touched by
the optimiser. A policy that needs more non-trained state may put any pytree in ``var``.

Everything is pure, so a policy is used unchanged under ``jit`` and ``vmap`` (e.g. over a leading
seed axis of the params). Pass a ``Policy`` to jitted functions as a static argument (it is a
tuple of functions, hashable by identity; ``make_policy`` caches it per configuration so the same
configuration gives the same object and reuses compiled code) or close over it.
"""

from __future__ import annotations

from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp

from gmr_jax import linalg


Array = jax.Array
PyTree = Any


class Normalization(NamedTuple):
    """Affine input normalisation x̃ = x·scale + bias, fixed at the first S-step.

    Attributes:
      scale: [dX] 1/max(std, floor).
      bias: [dX] −mean·scale.
      set: [] bool, whether the statistics were computed (then they are never changed again).
    """

    scale: Array
    bias: Array
    set: Array


class PolicyParams(NamedTuple):
    """Parameters of a global policy.

    Attributes:
      net: pytree of the trainable network weights (the only part the S-step optimises).
      norm: :class:`Normalization` of the inputs.
      var: exploration variance (MLP: [dU], the diagonal of a state-independent covariance;
        other policies: any non-trained pytree).
    """

    net: PyTree
    norm: Normalization
    var: PyTree


class SStepData(NamedTuple):
    """One S-step data set; rows flattened over condition, sample and time (B = M·N·T).

    Attributes:
      x: [B, dX] states (raw, not normalised).
      tgt_mu: [B, dU] target actions, the new local controller's mean K_t x + k_t at x.
      tgt_prc: [B, dU, dU] target precisions (the local controller's Q_uu, symmetric PD).
      wt: [B] weights (toolbox: a constant; 0 marks a padding row).
      K: [B, dU, dX] local controller gains K_p (used by GMR; zeros are fine for the MLP).
      k: [B, dU] local controller offsets k_p (GMR).
      state_cov: [B, dX, dX] state covariance Σ_t of the local controller's forward pass (GMR).
      tgt_logdet: optional [B] log|tgt_prc| of the unweighted target precisions (0 on zero-weight
        rows), a constant of the GMR loss; ``sstep`` fills it once per S-step so that no minibatch
        step factorises a matrix (None: the loss computes it).
    """

    x: Array
    tgt_mu: Array
    tgt_prc: Array
    wt: Array
    K: Array
    k: Array
    state_cov: Array
    tgt_logdet: Array | None = None


class Policy(NamedTuple):
    """A global policy as a bundle of pure functions (see the module docstring for the contract).

    Attributes:
      init: (key, dX, dU, dtype=None) -> PolicyParams.
      mean: (params, x [dX]) -> u [dU], deterministic action.
      covariance: (params, x [dX]) -> [dU, dU], exploration covariance.
      loss: (params, batch: SStepData, key) -> (scalar, dict of scalars), data term of the S-step.
      finalize: (params, data: SStepData) -> params, after the S-step's optimisation.
    """

    init: Callable[..., PolicyParams]
    mean: Callable[[PolicyParams, Array], Array]
    covariance: Callable[[PolicyParams, Array], Array]
    loss: Callable[[PolicyParams, SStepData, Array], tuple[Array, dict]]
    finalize: Callable[[PolicyParams, SStepData], PolicyParams]


def default_float():
    """JAX's default float dtype: float64 under ``jax_enable_x64``, else float32."""
    return jnp.zeros(()).dtype


def identity_normalization(dX: int, dtype) -> Normalization:
    """The normalisation before the first S-step: scale [dX] = 1, bias [dX] = 0, set = False."""
    return Normalization(scale=jnp.ones((dX,), dtype), bias=jnp.zeros((dX,), dtype),
                         set=jnp.asarray(False))


def normalize_input(norm: Normalization, x: Array) -> Array:
    """x̃ = x·scale + bias for x [..., dX] (same shape out)."""
    return x * norm.scale + norm.bias


def make_sstep_data(x, tgt_mu, tgt_prc, wt=None, K=None, k=None, state_cov=None) -> SStepData:
    """Build :class:`SStepData` from the MLP's fields, filling the GMR-only fields with zeros.

    Args:
      x: [B, dX]; tgt_mu: [B, dU]; tgt_prc: [B, dU, dU]; wt: [B] (default ones);
      K: [B, dU, dX]; k: [B, dU]; state_cov: [B, dX, dX] (default zeros).
    """
    x = jnp.asarray(x)
    B, dX = x.shape
    dU = tgt_mu.shape[-1]
    dt = x.dtype
    return SStepData(
        x=x,
        tgt_mu=jnp.asarray(tgt_mu, dt),
        tgt_prc=jnp.asarray(tgt_prc, dt),
        wt=jnp.ones((B,), dt) if wt is None else jnp.asarray(wt, dt),
        K=jnp.zeros((B, dU, dX), dt) if K is None else jnp.asarray(K, dt),
        k=jnp.zeros((B, dU), dt) if k is None else jnp.asarray(k, dt),
        state_cov=jnp.zeros((B, dX, dX), dt) if state_cov is None else jnp.asarray(state_cov, dt),
    )


def gaussian_logdet(P: Array) -> Array:
    """log|P| of symmetric PD matrices [..., n, n] -> [...] (Cholesky; NaN if P is not PD)."""
    chol = linalg.cholesky(P)
    return 2.0 * jnp.sum(jnp.log(jnp.diagonal(chol, axis1=-2, axis2=-1)), axis=-1)


def target_logdet(tgt_prc: Array, wt: Array) -> Array:
    """``SStepData.tgt_logdet``: log|tgt_prc| [B] for rows with wt > 0, 0 for the others."""
    valid = (wt > 0)[:, None, None]
    eye = jnp.eye(tgt_prc.shape[-1], dtype=tgt_prc.dtype)
    return gaussian_logdet(jnp.where(valid, tgt_prc, eye))


def l2_penalty(tree: PyTree) -> Array:
    """Σθ² over every leaf of ``tree`` (weights and biases alike): a scalar."""
    # Start from the first leaf (not a literal 0.0) so float32 stays float32 under x64.
    sums = [jnp.sum(jnp.square(leaf)) for leaf in jax.tree_util.tree_leaves(tree)]
    if not sums:
        return jnp.zeros(())
    total = sums[0]
    for s in sums[1:]:
        total = total + s
    return total


def weighted_action_error(u: Array, tgt_mu: Array, tgt_prc: Array) -> Array:
    """½·(u − û)ᵀ P (u − û) averaged over rows: u, tgt_mu [B, dU], tgt_prc [B, dU, dU] -> scalar."""
    d = u - tgt_mu
    return 0.5 * jnp.mean(jnp.einsum("bi,bij,bj->b", d, tgt_prc, d))


def noisy_action(policy: Policy, params: PolicyParams, x: Array, noise: Array) -> Array:
    """u = mean(x) + L·ε with L Lᵀ = covariance(x): x [dX], noise ε [dU] (standard normal) -> [dU].

    Used to roll out the global policy with the toolbox's (smoothed) exploration noise.
    """
    cov = policy.covariance(params, x)
    chol = linalg.cholesky(cov)
    return policy.mean(params, x) + chol @ noise

"""The MDGPS baseline policy: a fully connected network with a state-independent Gaussian.

π(u | x) = N(f_θ(x̃), diag(var)), x̃ = x·scale + bias (statistics fixed at the first S-step),
f_θ = 12 → 64 → 64 → 6 with ReLU (paper). The S-step minimises
½·(u − f_θ(x̃))ᵀ w·P (u − f_θ(x̃)) averaged over the minibatch (+ β·Σθ², added by the S-step),
and afterwards sets var = 1/diag(A + 2·ent_reg) in closed form, A the weighted mean of the
target precisions (mdgps-toolbox.md §4.3, steps 4 and 5).

Initialisation (MLPConfig.init): "lecun_normal" (the default, Flax's: N(0, 1/fan_in) truncated,
biases 0) keeps the hidden activations of standardised inputs at unit scale, so the 400 epochs of
the paper start from a useful gradient; "normal" is the toolbox's N(0, 0.01²), biases 0.
"""

from __future__ import annotations

from typing import Any, Callable, NamedTuple

import flax.linen as nn
import jax
import jax.numpy as jnp

from gmr_jax.config import MLPConfig
from gmr_jax.policies.base import (Policy, PolicyParams, SStepData, TrainingForm, default_float,
                                   dense_chain, dense_entries, dense_layout, dense_stack, dense_value_and_grad,
                                   flax_dense_layers, flax_dense_params, identity_normalization,
                                   normalize_input, pack_dense, pack_rows, products_as_reductions,
                                   quadratic_rows, squash, symmetrize, unpack_dense, unpack_rows,
                                   weighted_action_error)


ACTIVATION_FNS: dict[str, Callable] = {
    "relu": nn.relu,
    "leaky_relu": nn.leaky_relu,
    "tanh": jnp.tanh,
    "elu": nn.elu,
    "swish": nn.swish,
}


class MLP(nn.Module):
    """Fully connected network: [..., dX] -> [..., dU], hidden layers with ``activation``."""

    hidden: tuple[int, ...]
    out: int
    activation: str = "relu"
    weight_init: str = "lecun_normal"
    init_std: float = 0.01
    param_dtype: Any = jnp.float32

    @nn.compact
    def __call__(self, x):
        kernel_init = (nn.initializers.lecun_normal() if self.weight_init == "lecun_normal"
                       else nn.initializers.normal(self.init_std))
        act = ACTIVATION_FNS[self.activation]
        for width in self.hidden:
            x = act(nn.Dense(width, kernel_init=kernel_init, bias_init=nn.initializers.zeros,
                             param_dtype=self.param_dtype)(x))
        return nn.Dense(self.out, kernel_init=kernel_init, bias_init=nn.initializers.zeros,
                        param_dtype=self.param_dtype)(x)


class LossRows(NamedTuple):
    """The per-datum constants of the MLP loss in the S-step's packed form (shapes per row; a
    batch adds a leading axis).

    Attributes:
      xn: [dX] the normalised state x̃; tgt_mu: [dU] target action; prc: [dU, dU] w·P,
        symmetrised (the loss sees only the symmetric part; ``quadratic_rows`` needs it).
    """

    xn: jax.Array
    tgt_mu: jax.Array
    prc: jax.Array


def closed_form_variance(tgt_prc, wt, ent_reg: float = 0.0):
    """Toolbox variance rule: var [dU] = 1/diag(A + 2·ent_reg·11ᵀ), A = Σ_b w_b P_b / Σ_b w_b.

    Args:
      tgt_prc: [B, dU, dU] unweighted target precisions.
      wt: [B] normalised weights.

    The toolbox divides the *unweighted* sum of precisions by the sum of the normalised weights;
    with constant weights (the only case MDGPS produces) both forms give 1/diag(mean precision).
    The weighted mean used here also lets zero-weight (padding) rows drop out.
    """
    A = jnp.einsum("b,bij->ij", wt, tgt_prc) / jnp.sum(wt)
    return 1.0 / (jnp.diagonal(A) + 2.0 * ent_reg)


def make_mlp_policy(cfg: MLPConfig = MLPConfig()) -> Policy:
    """The MDGPS baseline MLP policy for a configuration (see the module docstring)."""

    def module(dU: int, dtype=jnp.float32) -> MLP:
        return MLP(hidden=tuple(cfg.hidden), out=dU, activation=cfg.activation, weight_init=cfg.init,
                   init_std=cfg.init_std, param_dtype=dtype)

    def init(key, dX: int, dU: int, dtype=None) -> PolicyParams:
        """Params: net (Flax weights), identity normalisation, var [dU] = init_var."""
        dtype = default_float() if dtype is None else jnp.dtype(dtype)
        net = module(dU, dtype).init(key, jnp.zeros((dX,), dtype))
        return PolicyParams(net=net, norm=identity_normalization(dX, dtype),
                            var=jnp.full((dU,), cfg.init_var, dtype))

    def network_input(norm, x):
        """What the network sees: x̃, or c·tanh(x̃/c) with c = input_squash > 0 (an ablation:
        GMR's encoder bound on the plain MLP)."""
        return squash(normalize_input(norm, x), cfg.input_squash)

    def mean(params: PolicyParams, x):
        """Deterministic action: x [..., dX] -> u [..., dU]."""
        dU = params.var.shape[-1]
        return module(dU).apply(params.net, network_input(params.norm, x))

    def covariance(params: PolicyParams, x):
        """State-independent covariance diag(var): x [dX] -> [dU, dU]."""
        del x
        return jnp.diag(params.var)

    def loss(params: PolicyParams, batch: SStepData, key):
        """½·mean_b (u_b − û_b)ᵀ (w·P)_b (u_b − û_b); the key is unused (deterministic net)."""
        del key
        u = mean(params, batch.x)
        value = weighted_action_error(u, batch.tgt_mu, batch.tgt_prc)
        return value, {"action_mse": jnp.mean(jnp.square(u - batch.tgt_mu))}

    # ---- the S-step's packed form (TrainingForm): the same loss, fewer operations per step.
    n_layers = len(cfg.hidden) + 1

    def layout(params: PolicyParams):
        return dense_layout(dense_chain(params.norm.scale.shape[-1], cfg.hidden, params.var.shape[-1]))

    def pack(params: PolicyParams):
        """params.net (Flax) -> θ [S·(I+1)·O], the S-step's flat weight vector."""
        return pack_dense(layout(params), flax_dense_layers(params.net["params"], n_layers)).reshape(-1)

    def unpack(params: PolicyParams, theta):
        """θ -> params.net (Flax), the inverse of ``pack``."""
        lay = layout(params)
        return {"params": flax_dense_params(unpack_dense(lay, theta.reshape(lay.array_shape)))}

    def rows(params: PolicyParams, data: SStepData):
        return pack_rows(LossRows(xn=network_input(params.norm, data.x), tgt_mu=data.tgt_mu,
                                  prc=symmetrize(data.tgt_prc)))

    def packed_value_and_grad(params: PolicyParams, theta, rows, noise):
        """TrainingForm.value_and_grad: θ, rows [b, F] -> ((value, aux), grad); noise unused."""
        del noise
        lay = layout(params)
        dX, dU = params.norm.scale.shape[-1], params.var.shape[-1]
        W = theta.reshape(lay.array_shape)
        batch = unpack_rows(rows, LossRows(xn=(dX,), tgt_mu=(dU,), prc=(dU, dU)))

        def f(deltas):
            out, inputs = dense_stack(W, lay, 0, 1, n_layers, batch.xn, ACTIVATION_FNS[cfg.activation], deltas)
            du = out[0][:, :dU] - batch.tgt_mu
            value = 0.5 * jnp.mean(quadratic_rows(du, batch.prc))
            return value, ({"action_mse": jnp.mean(jnp.square(du))}, inputs)

        # Its products stay dots even for few seeds on a GPU (``sharding.seed_block``):
        # as reductions the MLP's Adam step has 13 operations instead of 20 but is slower
        # (benchmarks/RESULTS.md, nineteenth session), unlike GMR's.
        with products_as_reductions(False):
            (value, aux), grad = dense_value_and_grad(f, W, rows.shape[0])
        return (value, aux), grad.reshape(-1)

    training = TrainingForm(pack=pack, unpack=unpack, rows=rows, noise=None,
                            value_and_grad=packed_value_and_grad,
                            trained=lambda params: dense_entries(layout(params)))

    def finalize(params: PolicyParams, data: SStepData) -> PolicyParams:
        """Closed-form variance after the S-step (data: unweighted precisions, normalised wt)."""
        var = closed_form_variance(data.tgt_prc, data.wt, cfg.ent_reg)
        return params._replace(var=var.astype(params.var.dtype))

    return Policy(init=init, mean=mean, covariance=covariance, loss=loss, finalize=finalize,
                  training=training)

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
- ``training`` (optional): a :class:`TrainingForm`, the same data term in the form the S-step's
  loop runs fastest (one flat weight vector, one matrix of per-datum constants, the random
  numbers drawn before the loop, the weight gradients of all layers as one batched product).
  Without it the S-step differentiates ``loss`` through ``params.net``.

The S-step optimises ``params.net`` only; ``params.norm`` and ``params.var`` are never touched by
the optimiser. A policy that needs more non-trained state may put any pytree in ``var``.

Everything is pure, so a policy is used unchanged under ``jit`` and ``vmap`` (e.g. over a leading
seed axis of the params). Pass a ``Policy`` to jitted functions as a static argument (it is a
tuple of functions, hashable by identity; ``make_policy`` caches it per configuration so the same
configuration gives the same object and reuses compiled code) or close over it.
"""

from __future__ import annotations

import contextlib
import contextvars
import math
from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

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


class TrainingForm(NamedTuple):
    """A policy's S-step data term in the form that needs the fewest kernels per Adam step.

    On a GPU the S-step's minibatch steps are bound by their number of dependent kernels (each
    costs about 1.7 µs however small), not arithmetic, so this
    form trades memory and padding for fewer operations: the trained weights are one flat vector θ
    in a layout of the policy's choice, the per-datum constants of the loss are the rows of one
    matrix (a minibatch is one gather), the random numbers of every minibatch are drawn before the
    loop, and ``value_and_grad`` may compute the gradient any way it likes (e.g. all layers' weight
    gradients as one batched product, see :func:`dense_value_and_grad`). It must give ``loss``'s
    value, aux and gradient for the same minibatch and key, up to round-off.

    Attributes:
      pack: (params) -> θ [n], ``params.net`` in the form's layout. Entries that no output depends
        on (padding) must be 0 and get a zero gradient, so Adam leaves them at 0.
      unpack: (params, θ [n]) -> net, the inverse of ``pack`` (``params.net``'s pytree).
      rows: (params, data: SStepData) -> [B, F], the per-datum constants of ``data`` as the loss
        sees it (``tgt_prc`` = w·P, ``wt`` = w); computed once per S-step.
      noise: (key, n, dtype) -> [n, ...], the random numbers ``loss`` draws from ``key`` for a
        minibatch of n rows (None: the loss is deterministic).
      value_and_grad: (params, θ [n], rows [b, F], noise [b, ...] or None) -> ((value, aux),
        grad [n]), the data term of a minibatch of b rows (``loss``'s value and aux dict) and its
        gradient with respect to θ.
      trained: (params) -> the sorted indices [m] (numpy, static) of θ's entries that are not
        padding, or None: every entry. The S-step then trains these m entries only (θ is formed
        from them with zeros in the padding), so Adam's update reads and writes m entries of
        each array, not n (with many seeds side by side that update is bound by memory traffic).
    """

    pack: Callable[[PolicyParams], Array]
    unpack: Callable[[PolicyParams, Array], PyTree]
    rows: Callable[[PolicyParams, SStepData], Array]
    noise: Callable[..., Array] | None
    value_and_grad: Callable[..., tuple[tuple[Array, dict], Array]]
    trained: Callable[[PolicyParams], np.ndarray] | None = None


class Policy(NamedTuple):
    """A global policy as a bundle of pure functions (see the module docstring for the contract).

    Attributes:
      init: (key, dX, dU, dtype=None) -> PolicyParams.
      mean: (params, x [dX]) -> u [dU], deterministic action.
      covariance: (params, x [dX]) -> [dU, dU], exploration covariance.
      loss: (params, batch: SStepData, key) -> (scalar, dict of scalars), data term of the S-step.
      finalize: (params, data: SStepData) -> params, after the S-step's optimisation.
      training: optional :class:`TrainingForm` of ``loss`` for the S-step (None: autodiff of
        ``loss``).
      kernel: optional, the S-step's whole Adam loop as one GPU kernel: (params, train:
        SStepData (``tgt_prc`` = w·P, ``wt`` = w), idx [steps, b], noise [steps, b, ...], c1, c2
        [steps] (Adam's bias corrections), cfg: SStepConfig) -> (net, (total, value, aux)) with
        [steps] per-step values; the same steps as ``training``'s loop (needs ``training`` for
        its noise).
      cuda: optional, the same as ``kernel`` written in CUDA (``impl="cuda"``; float32 on an NVIDIA
        GPU).
    """

    init: Callable[..., PolicyParams]
    mean: Callable[[PolicyParams, Array], Array]
    covariance: Callable[[PolicyParams, Array], Array]
    loss: Callable[[PolicyParams, SStepData, Array], tuple[Array, dict]]
    finalize: Callable[[PolicyParams, SStepData], PolicyParams]
    training: TrainingForm | None = None
    kernel: Callable | None = None
    cuda: Callable | None = None


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


def squash(xn: Array, c: float) -> Array:
    """c·tanh(x̃/c) elementwise: the standardised state x̃ bounded to (−c, c), linear near 0;
    c = 0 leaves x̃ as it is (the paper's networks see x̃ unbounded)."""
    return xn if c <= 0 else c * jnp.tanh(xn / c)


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


def symmetrize(A: Array) -> Array:
    """½(A + Aᵀ) over the last two axes (A itself, bit for bit, if A is symmetric)."""
    return 0.5 * (A + jnp.swapaxes(A, -1, -2))


def _quadratic_rows_fwd(d, P):
    Pd = jnp.einsum("bij,bj->bi", P, d)
    return jnp.sum(d * Pd, axis=-1), Pd


def _quadratic_rows_bwd(Pd, ct):
    return (2.0 * ct)[..., None] * Pd, None


@jax.custom_vjp
def quadratic_rows(d: Array, P: Array) -> Array:
    """dᵀ P d per row: d [b, n], P [b, n, n] symmetric -> [b], with its gradient 2·P d in closed
    form (one product for value and gradient; autodiff of the einsum forms three). P is treated
    as a constant."""
    return _quadratic_rows_fwd(d, P)[0]


quadratic_rows.defvjp(_quadratic_rows_fwd, _quadratic_rows_bwd)


def noisy_action(policy: Policy, params: PolicyParams, x: Array, noise: Array) -> Array:
    """u = mean(x) + L·ε with L Lᵀ = covariance(x): x [dX], noise ε [dU] (standard normal) -> [dU].

    Used to roll out the global policy with the toolbox's (smoothed) exploration noise.
    """
    cov = policy.covariance(params, x)
    chol = linalg.cholesky(cov)
    return policy.mean(params, x) + chol @ noise


# ------------------------------------------------------------------ the S-step's packed layouts
#
# The S-step's Adam step runs one kernel per operation on a GPU and nearly every operation is
# tiny, so the layout below serves one purpose: few operations per step. All dense layers of a
# policy live in one zero-padded array, networks of equal depth that read the same input run as
# one batched product per layer, and the weight gradients of all layers come out of a single
# batched product (``dense_value_and_grad``) instead of one product per layer. A last layer
# wider than the others (GMR's head) is held as column blocks in several slots that read the
# same input (``column_blocks``), so that the padding of every other slot stays small.


class DenseLayout(NamedTuple):
    """Dense layers ("slots") of one or several networks stored in one array W [S, I+1, O].

    Slot s holds a layer of fan-in a and fan-out b: W[s, :a, :b] is its kernel, W[s, I, :b] its
    bias and every other entry is 0. The padding changes no output: padded inputs are 0, padded
    outputs are cut off or feed zero weights, and a padded hidden unit has a zero
    pre-activation, so its activation act(0) = 0 (true of every activation used here). For the
    same reasons every padded entry has a zero gradient.

    Attributes:
      shapes: ((fan_in, fan_out), …), one pair per slot.
      width_in: I, the largest fan-in.
      width_out: O, the largest fan-out.
    """

    shapes: tuple[tuple[int, int], ...]
    width_in: int
    width_out: int

    @property
    def array_shape(self) -> tuple[int, int, int]:
        """The shape of W: (S, I+1, O)."""
        return (len(self.shapes), self.width_in + 1, self.width_out)


def dense_layout(shapes) -> DenseLayout:
    """The :class:`DenseLayout` of slots with the given ((fan_in, fan_out), …)."""
    shapes = tuple((int(a), int(b)) for a, b in shapes)
    return DenseLayout(shapes, max(a for a, _ in shapes), max(b for _, b in shapes))


def dense_chain(d_in: int, hidden, d_out: int) -> list[tuple[int, int]]:
    """The (fan_in, fan_out) of each layer of a network d_in → hidden… → d_out."""
    widths = (d_in,) + tuple(hidden) + (d_out,)
    return list(zip(widths[:-1], widths[1:]))


def flax_dense_layers(net: dict, count: int) -> list[tuple[Array, Array]]:
    """[(kernel, bias)] of the Flax layers Dense_0 … Dense_{count-1} of ``net``."""
    return [(net[f"Dense_{i}"]["kernel"], net[f"Dense_{i}"]["bias"]) for i in range(count)]


def flax_dense_params(layers) -> dict:
    """[(kernel, bias)] -> {"Dense_i": {"kernel", "bias"}}, the inverse of ``flax_dense_layers``."""
    return {f"Dense_{i}": {"kernel": k, "bias": b} for i, (k, b) in enumerate(layers)}


def pack_dense(layout: DenseLayout, layers) -> Array:
    """[(kernel [a, b], bias [b]) per slot] -> W [S, I+1, O] (zero padding)."""
    I, O = layout.width_in, layout.width_out
    blocks = []
    for (a, b), (kernel, bias) in zip(layout.shapes, layers, strict=True):
        assert kernel.shape == (a, b) and bias.shape == (b,), (kernel.shape, bias.shape, (a, b))
        rows = jnp.concatenate([kernel, jnp.zeros((I - a, b), kernel.dtype), bias[None]], axis=0)
        blocks.append(jnp.pad(rows, ((0, 0), (0, O - b))))
    return jnp.stack(blocks)


def dense_entries(layout: DenseLayout) -> np.ndarray:
    """The sorted flat indices into W [S, I+1, O].reshape(-1) of the entries that are not padding:
    each slot's kernel W[s, :a, :b] and bias W[s, I, :b]."""
    I, O = layout.width_in, layout.width_out
    mask = np.zeros(layout.array_shape, dtype=bool)
    for s, (a, b) in enumerate(layout.shapes):
        mask[s, :a, :b] = True
        mask[s, I, :b] = True
    return np.flatnonzero(mask)


def unpack_dense(layout: DenseLayout, W: Array) -> list[tuple[Array, Array]]:
    """W [S, I+1, O] -> [(kernel [a, b], bias [b]) per slot], the inverse of ``pack_dense``."""
    I = layout.width_in
    return [(W[s, :a, :b], W[s, I, :b]) for s, (a, b) in enumerate(layout.shapes)]


def column_blocks(shape: tuple[int, int], width: int) -> list[tuple[int, int]]:
    """A layer's (fan_in, fan_out) -> the (fan_in, fan_out) of the slots that hold its outputs
    as consecutive column blocks of at most ``width`` outputs each (one slot if it fits)."""
    a, b = shape
    return [(a, min(width, b - start)) for start in range(0, b, width)]


def split_columns(layer: tuple[Array, Array], blocks) -> list[tuple[Array, Array]]:
    """(kernel [a, b], bias [b]) -> one (kernel, bias) per column block of ``blocks``
    (``column_blocks``' shapes, in order)."""
    kernel, bias = layer
    ends = np.cumsum([fan_out for _, fan_out in blocks])
    return [(kernel[:, e - o: e], bias[e - o: e]) for e, (_, o) in zip(ends, blocks)]


def join_columns(layers) -> tuple[Array, Array]:
    """The inverse of ``split_columns``: [(kernel, bias) per column block] -> (kernel, bias)."""
    return (jnp.concatenate([k for k, _ in layers], axis=1), jnp.concatenate([b for _, b in layers]))


def fit_width(h: Array, width: int) -> Array:
    """h [..., d] -> [..., width]: cut off or zero-padded on the last axis."""
    d = h.shape[-1]
    if d >= width:
        return h[..., :width]
    return jnp.pad(h, [(0, 0)] * (h.ndim - 1) + [(0, width - d)])


_PRODUCTS_AS_REDUCTIONS = contextvars.ContextVar("products_as_reductions", default=False)


@contextlib.contextmanager
def products_as_reductions(on: bool = True):
    """Trace the packed forms' small matrix products (``small_product``, ``dense_stack``,
    ``dense_value_and_grad``) as broadcast products summed over the contracted axis instead of
    dots. XLA fuses such a sum with the elementwise operations around it (a dot is a kernel of
    its own): on a GPU, GMR's Adam step of one seed has 28 operations instead of 44 and is 20 %
    faster, and up to 32 seeds per GPU also faster than dots (``sharding.seed_block`` turns it on
    there; the MLP's form declines it, for which it is slower). With many seeds side by side the
    same products are large batches, for which dots are faster. The same multiplies, summed in another order.

    The choice is read while tracing, so a function traced under it must not be cached across
    choices by its arguments alone: a ``custom_vjp`` takes it as an argument (``fused_head``)."""
    token = _PRODUCTS_AS_REDUCTIONS.set(bool(on))
    try:
        yield
    finally:
        _PRODUCTS_AS_REDUCTIONS.reset(token)


def reduced_products() -> bool:
    """Whether the packed forms' small products are being traced as reductions
    (``products_as_reductions``)."""
    return _PRODUCTS_AS_REDUCTIONS.get()


def small_product(a: Array, b: Array, reduced: bool | None = None) -> Array:
    """a [..., m, k] @ b [..., k, n] -> [..., m, n] (batch axes broadcast), as a dot or as a sum
    of broadcast products (``reduced``; None: ``reduced_products()``)."""
    if reduced_products() if reduced is None else reduced:
        return jnp.sum(a[..., :, :, None] * b[..., None, :, :], axis=-2)
    return jnp.matmul(a, b)


def dense_stack(W: Array, layout: DenseLayout, first: int, n: int, depth: int, x: Array,
                act: Callable, deltas: Array, parts=None):
    """n networks of equal depth side by side on the same input, one batched product per layer.

    Layer l < depth − 1 of network k is slot ``first + l·n + k`` of W [S, I+1, O] (``layout``);
    the last layers follow, network k's as ``parts[k]`` slots holding its outputs as column
    blocks (``column_blocks``), each reading that network's input. ``deltas`` [S, b, O] is added
    to every pre-activation (zeros: it is the point at which ``dense_value_and_grad``
    differentiates). Each layer multiplies by the part of its kernels that can be nonzero (the
    widest fan-in and fan-out among its slots), so that no activation has to be padded or cut
    inside the network.

    Args:
      x: [b, a] the input, a the first layer's widest fan-in.
      act: the hidden activation (act(0) = 0).
      parts: slots of each network's last layer (default one each).
    Returns:
      (outs, inputs): outs, per network its last layer's pre-activations [b, parts[k]·o] (the
      column blocks side by side; o the last layer's widest slot, columns beyond a block's own
      fan-out are 0); inputs [slots, b, I], every slot's input in slot order, zero-padded to I.
    """
    I = layout.width_in
    parts = (1,) * n if parts is None else tuple(parts)
    if len(parts) != n or min(parts) < 1:
        raise ValueError(f"parts={parts}: expected {n} counts of at least 1")
    h = x
    inputs = []
    for layer in range(depth):
        s = first + layer * n
        last = layer == depth - 1
        m = sum(parts) if last else n
        a = max(fan_in for fan_in, _ in layout.shapes[s: s + m])
        o = max(fan_out for _, fan_out in layout.shapes[s: s + m])
        if h.shape[-1] != a:
            raise ValueError(f"slot {s}: input of width {h.shape[-1]}, expected {a}")
        kernel = W[s: s + m, :a, :o]
        if layer == 0:
            # the shared input is not copied m times: the product's gradient with respect to x
            # then contracts over the m slots too, with no separate sum. x is the product's left
            # operand, so that its rows stay the major axis of the product ([b, m, o], each row's
            # outputs contiguous, as every later layer's): jnp.einsum would make x the right
            # operand and form [m, o, b], whose consumers then need transposes
            inputs.append(jnp.broadcast_to(fit_width(x, I), (m,) + x.shape[:-1] + (I,)))
            if reduced_products():
                product = small_product(x[None], kernel)
            else:
                product = jnp.swapaxes(lax.dot_general(x, kernel, (((1,), (1,)), ((), ()))), 0, 1)
        else:
            if last and m != n:
                # static broadcasts, not jnp.repeat: its gradient would be a scatter-add
                h = jnp.concatenate([jnp.broadcast_to(h[k], (p,) + h.shape[1:]) for k, p in enumerate(parts)])
            inputs.append(fit_width(h, I))
            product = small_product(h, kernel)
        pre = product + W[s: s + m, I:, :o] + deltas[s: s + m, :, :o]
        if last:
            starts = np.cumsum((0,) + parts)
            outs = [pre[starts[k]] if parts[k] == 1 else
                    jnp.concatenate(list(pre[starts[k]: starts[k + 1]]), axis=-1) for k in range(n)]
            return outs, jnp.concatenate(inputs, axis=0)
        h = act(pre)


def dense_value_and_grad(f: Callable, W: Array, batch: int):
    """Value and gradient with respect to W [S, I+1, O] of a loss that reads W only through
    ``dense_stack`` pre-activations.

    ``f(deltas [S, batch, O]) -> (value, (aux, inputs [S, batch, I]))`` evaluates the loss with
    ``deltas`` added to the pre-activations and returns every slot's input. Autodiff with
    respect to ``deltas`` at 0 gives each slot's pre-activation gradient D_s [batch, O], and then
    ∂value/∂W_s = [inputs_s, 1]ᵀ D_s for all slots in one batched product (the ones column gives
    the bias row). These are the products autodiff with respect to W would form one layer at a
    time, so the result agrees with it to round-off.

    Returns: ((value, aux), grad [S, I+1, O]).
    """
    S, _, O = W.shape
    (value, (aux, inputs)), D = jax.value_and_grad(f, has_aux=True)(jnp.zeros((S, batch, O), W.dtype))
    ones = jnp.ones(inputs.shape[:-1] + (1,), inputs.dtype)
    X = jnp.concatenate([inputs, ones], axis=-1)
    if reduced_products():
        # X and D are materialised first: left to itself, XLA:GPU fuses their producers (the
        # minibatch's gather, the activations) into the reduction and into Adam's update after it,
        # recomputing them for every weight, a kernel several times slower than the rest
        # (benchmarks/RESULTS.md, twenty-first session). The barrier changes no arithmetic.
        X, D = lax.optimization_barrier((X, D))
        grad = jnp.sum(X[:, :, :, None] * D[:, :, None, :], axis=1)
    else:
        grad = jnp.einsum("sbi,sbo->sio", X, D)
    return (value, aux), grad


def pack_rows(fields: NamedTuple) -> Array:
    """A NamedTuple of per-datum arrays [B, ...] -> one matrix [B, F] (fields side by side)."""
    return jnp.concatenate([f.reshape(f.shape[0], -1) for f in fields], axis=1)


def unpack_rows(rows: Array, shapes: NamedTuple) -> NamedTuple:
    """rows [b, F] -> the NamedTuple ``shapes`` (per-row shapes of its fields) of arrays [b, ...],
    the inverse of ``pack_rows``."""
    out, start = [], 0
    for shape in shapes:
        size = math.prod(shape)
        out.append(rows[:, start: start + size].reshape((rows.shape[0],) + tuple(shape)))
        start += size
    assert start == rows.shape[1], (start, rows.shape)
    return type(shapes)(*out)

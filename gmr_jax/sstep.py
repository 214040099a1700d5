"""The supervised S-step of MDGPS: fit the global policy to the local controllers' actions.

Toolbox rules (mdgps-toolbox.md §4.3) with the paper's optimiser settings (gmr-method.md §1):

1. weights: w ← w·B/Σw; mn = median(w[w > 1e-2]); w ← min(w, 2·mn)/mn; the precision fed to the
   loss is w·P (``normalize_weights``);
2. input normalisation computed on the first S-step only and reused forever
   (``set_normalization``);
3. Adam with a fresh state at every S-step (parameters are warm-started: the caller passes the
   previous S-step's params), ``epochs`` epochs, each a new shuffle, minibatches of
   ``batch_size`` rows (the B mod batch_size leftover of each shuffle is dropped), objective =
   policy.loss + β·Σθ² over ``params.net``;
4. ``policy.finalize`` on the whole data set (MLP: closed-form variance).

The paper counts epochs (400) where the toolbox counts steps; we follow the paper.

Two forms of the same optimisation (``sstep``'s ``impl``), equal to round-off
(tests/test_sstep.py): "reference", autodiff of ``policy.loss`` through ``params.net`` in a loop
per epoch; and "packed", which runs the policy's ``TrainingForm`` in one loop over all minibatch
steps with everything that does not depend on the weights (shuffles, latent noise, per-datum
constants, Adam's bias corrections) prepared before the loop. A GPU runs each operation of a
step as a kernel, and each dependent kernel costs about 1.7 µs on an H100 however little it
computes (``benchmarks/kernel_floor.py``), so the packed form's far fewer operations (GMR: about
half) are what makes it faster there; on a CPU, where
a step costs arithmetic and memory traffic instead, its zero padding makes it slower, so the
backend picks the default (``default_impl``). GMR also has two single-kernel forms, opt-in:
"kernel" (Pallas) and "cuda" (hand-written CUDA through the XLA FFI, ``policies/gmr_cuda.py``),
each every minibatch step of an S-step in one GPU launch, equal to the packed form to round-off.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import optax
from jax.flatten_util import ravel_pytree
from jax import lax

from gmr_jax import linalg, sharding
from gmr_jax.adam import adam_corrections, adam_update  # noqa: F401 (part of this module's API)
from gmr_jax.config import SStepConfig
from gmr_jax.policies.base import (Normalization, Policy, PolicyParams, SStepData, TrainingForm,
                                   l2_penalty, target_logdet)


def set_normalization(params: PolicyParams, x, weights=None, std_floor: float = 1e-3) -> PolicyParams:
    """Fix the input normalisation from the data if it is not set yet (otherwise unchanged).

    scale = 1/max(std, std_floor), bias = −mean·scale (population statistics per input
    dimension, toolbox §4.3 step 2).

    Args:
      params: policy params with ``norm`` (scale [dX], bias [dX], set []).
      x: [B, dX] states.
      weights: optional [B]; rows with weight ≤ 0 (padding) are left out of the statistics
        (all rows count if none has a positive weight).
      std_floor: floor of the standard deviation (toolbox 1e-3).
    Returns: params with ``norm`` set (``norm.set`` True).
    """
    norm = params.norm
    dtype = norm.scale.dtype

    def compute(_):
        xf = x.astype(dtype)
        if weights is None:
            mask = jnp.ones(xf.shape[:1], dtype)
        else:
            valid = weights > 0
            mask = jnp.where(jnp.any(valid), valid, True).astype(dtype)
        n = jnp.sum(mask)
        mean = mask @ xf / n
        var = mask @ jnp.square(xf - mean) / n
        scale = 1.0 / jnp.maximum(jnp.sqrt(var), std_floor)
        return Normalization(scale=scale.astype(dtype), bias=(-mean * scale).astype(dtype),
                             set=jnp.asarray(True))

    def keep(_):
        return Normalization(scale=norm.scale, bias=norm.bias, set=jnp.asarray(True))

    return params._replace(norm=lax.cond(norm.set, keep, compute, None))


def normalize_weights(wt, median_floor: float = 1e-2, clip: float = 2.0):
    """Toolbox weight rule (§4.3 step 1): [B] -> [B].

    w ← w·B/Σw (mean 1); mn = median of the entries > median_floor (numpy's median: the mean of
    the two middle values for an even count); w ← min(w, clip·mn)/mn, so the robust median is 1.
    A non-positive Σw or no entry above the floor gives zeros / skips the median (then
    ``sstep``'s metrics report it through ``weights_ok``).
    """
    B = wt.shape[0]
    total = jnp.sum(wt)
    w = jnp.where(total > 0, wt * (B / jnp.where(total > 0, total, 1)), jnp.zeros_like(wt))
    mask = w > median_floor
    count = jnp.sum(mask)
    s = jnp.sort(jnp.where(mask, w, jnp.inf))
    lo = s[jnp.maximum((count - 1) // 2, 0)]
    hi = s[jnp.minimum(count // 2, B - 1)]
    mn = jnp.where(count > 0, 0.5 * (lo + hi), jnp.ones((), w.dtype))
    return jnp.minimum(w, clip * mn) / mn


IMPLS = ("packed", "reference", "kernel", "cuda")


def default_impl() -> str:
    """The S-step form for the platform being traced for (``sharding.target_platform``: JAX's
    default backend, or the host CPU for a run the runner placed there): "packed" on an
    accelerator, "reference" on a CPU.

    On a GPU a minibatch step is bound by its number of dependent kernels, which the packed form
    cuts. On a CPU
    it is bound by arithmetic and memory traffic, and there the packed form's zero padding (about
    twice GMR's weights in Adam's update and in the single weight-gradient product) costs
    more than the operations it saves (benchmarks/sstep.py measures both).
    """
    return "reference" if sharding.target_platform() == "cpu" else "packed"


def resolve_statistics(value: str, seeds_per_device: int | None, platform: str) -> str:
    """``SStepConfig.statistics`` as the packed form applies it to a program of
    ``seeds_per_device`` seeds per device (None: traced outside ``sharding.seed_block``) on
    ``platform``: "epoch" or "step" as given; "auto" is "epoch" with up to
    ``sharding.EPOCH_STATISTICS_MAX_SEEDS`` seeds per GPU, where a minibatch step is bound by
    its number of kernels and the statistics' own kernels take a third of its time, and "step"
    elsewhere (on a CPU, and for many seeds side by side, where the kept weights' traffic and
    the batched evaluation cost more than the statistics inside the step)."""
    if value != "auto":
        return value
    on = seeds_per_device is not None and sharding.epoch_statistics_for(seeds_per_device, platform)
    return "epoch" if on else "step"


def default_statistics() -> str:
    """``resolve_statistics("auto", …)`` for the program being traced (``sharding.block_seeds``,
    ``sharding.target_platform``)."""
    return resolve_statistics("auto", sharding.block_seeds(), sharding.target_platform())


def sstep(policy: Policy, params: PolicyParams, data: SStepData, key, cfg: SStepConfig = SStepConfig(),
          *, impl: str | None = None):
    """One S-step: train ``params.net`` on ``data`` and finalise the policy.

    Args:
      policy: the policy's functions (static under jit).
      params: current params (warm start; the normalisation is set here on the first call).
      data: SStepData with B rows (B ≥ cfg.batch_size); wt [B] raw weights (e.g. constant).
      key: PRNG key (typed or raw uint32) for the shuffles and the policy's loss.
      cfg: SStepConfig (static).
      impl: "kernel": the policy's GPU kernel (``Policy.kernel``: every step in one launch; Pallas's
        interpreter off a GPU; falls back to "packed" for a policy without one); "cuda": the
        policy's hand-written CUDA kernel (``Policy.cuda``: every step in one launch, float32 on an
        NVIDIA GPU only; falls back to "packed" for a policy without one); "packed": the
        policy's ``training`` form in one loop over all minibatch steps (falls back to
        "reference" for a policy without one); "reference": autodiff of ``policy.loss``
        through ``params.net`` in a loop per epoch; None: ``default_impl()``. Both take the same
        minibatches in the same order with the same random numbers; their results agree to
        round-off (tests/test_sstep.py).
    Returns:
      (params, metrics) with metrics:
        loss: [E] mean objective (data term + β·Σθ²) over each epoch's minibatches, each
          evaluated before its update: E = 1, the last epoch's, with
          ``cfg.statistics_epochs == "last"`` (the default), E = epochs with "all";
        data_loss: [E] the same without the L2 term;
        aux: dict of [E], the per-epoch means of the policy loss's aux entries;
        weights_ok: [] bool, the raw weights had a positive sum;
        finite: [] bool, every returned loss and every parameter after the S-step is finite (a
          False must stop the caller: the new params are unusable). A non-finite gradient
          before the returned epochs leaves non-finite weights (Adam carries it in its
          moments), so the parameters' check covers those epochs' steps; a non-finite loss
          value with a finite gradient there (e.g. a non-finite per-row constant in rows that
          the last epoch's shuffle leaves out) shows only with ``statistics_epochs="all"``.
    """
    impl = default_impl() if impl is None else impl
    if impl not in IMPLS:
        raise ValueError(f"sstep impl={impl!r}: allowed values are {IMPLS}")
    B = data.x.shape[0]
    bs = cfg.batch_size
    if B // bs < 1:
        raise ValueError(f"S-step data has B={B} rows, fewer than sstep.batch_size={bs}")

    wn = normalize_weights(data.wt, cfg.weight_median_floor, cfg.weight_clip)
    params = set_normalization(params, data.x, wn, cfg.obs_std_floor)
    # Fold the normalised weight into the precision (toolbox); keep it in wt for other terms.
    # log|P| is a constant of the GMR loss: factorised once here, not in every minibatch step.
    logdet = target_logdet(data.tgt_prc, wn) if data.tgt_logdet is None else data.tgt_logdet
    train = data._replace(tgt_prc=wn[:, None, None] * data.tgt_prc, wt=wn, tgt_logdet=logdet)

    if impl == "kernel" and policy.kernel is not None:
        net, (loss, data_loss, aux) = _fit_kernel(policy, policy.kernel, params, train, key, cfg)
    elif impl == "cuda" and policy.cuda is not None:
        net, (loss, data_loss, aux) = _fit_kernel(policy, policy.cuda, params, train, key, cfg)
    elif impl in ("packed", "kernel", "cuda") and policy.training is not None:
        net, (loss, data_loss, aux) = _fit_packed(policy.training, params, train, key, cfg)
    else:
        net, (loss, data_loss, aux) = _fit_reference(policy, params, train, key, cfg)

    params = policy.finalize(params._replace(net=net), data._replace(wt=wn))
    metrics = {
        "loss": loss,
        "data_loss": data_loss,
        "aux": aux,
        "weights_ok": jnp.sum(data.wt) > 0,
        "finite": jnp.all(jnp.isfinite(loss)) & linalg.all_finite(params),
    }
    return params, metrics


def _epoch_keys(key, cfg: SStepConfig):
    """The per-epoch keys: (shuffle keys [epochs], loss keys [epochs]) (the same split for both
    implementations, so they take the same minibatches and draw the same noise)."""
    keys = jax.vmap(jax.random.split)(jax.random.split(key, cfg.epochs))
    return keys[:, 0], keys[:, 1]


def _minibatches(k_perm, B: int, nb: int, bs: int):
    """One epoch's shuffle: [nb, bs] row indices (the B mod bs leftover is dropped)."""
    return jax.random.permutation(k_perm, B)[: nb * bs].reshape(nb, bs)


def _stats(total, value, aux):
    """A step's scalars as one vector (one write per step, not one per scalar) and its tree."""
    stats, treedef = jax.tree_util.tree_flatten((total, value, aux))
    return jnp.stack(stats), treedef


def _schedule(train: SStepData, key, cfg: SStepConfig, noise_fn, dtype):
    """What the minibatch steps need that does not depend on the weights: every step's rows
    idx [steps, batch_size] (every epoch's shuffle), its random numbers (``noise_fn(key, n,
    dtype)`` per step, stacked; None without a noise_fn) and Adam's bias corrections c1, c2
    [steps]. The same split of ``key`` as the reference form's, so all forms take the same
    minibatches and draw the same noise."""
    B = train.x.shape[0]
    bs = cfg.batch_size
    nb = B // bs
    steps = cfg.epochs * nb
    k_perm, k_loss = _epoch_keys(key, cfg)
    idx = jax.vmap(lambda k: _minibatches(k, B, nb, bs))(k_perm).reshape(steps, bs)
    if noise_fn is None:
        noise = None
    else:
        step_keys = jax.vmap(lambda k: jax.random.split(k, nb))(k_loss)
        step_keys = step_keys.reshape((steps,) + step_keys.shape[2:])
        noise = jax.vmap(lambda k: noise_fn(k, bs, dtype))(step_keys)
    c1, c2 = adam_corrections(cfg, steps, dtype)
    return idx, noise, c1, c2


def _epoch_means(epochs: int, per_step):
    """[steps] per-step values (a pytree) of ``epochs`` epochs -> [epochs] means over each
    epoch's steps."""
    return jax.tree_util.tree_map(
        lambda a: jnp.mean(a.reshape((epochs, -1) + a.shape[1:]), axis=1), per_step)


def _returned_epochs(cfg: SStepConfig, means):
    """Per-epoch statistics [epochs] (a pytree) -> the ones ``cfg.statistics_epochs`` returns."""
    return means if cfg.statistics_epochs == "all" else jax.tree_util.tree_map(lambda a: a[-1:], means)


def _fit_packed(form: TrainingForm, params: PolicyParams, train: SStepData, key, cfg: SStepConfig):
    """The Adam loop on ``form``: one scan over all epochs' minibatch steps.

    Everything that does not depend on the weights is done before the loop: the per-datum
    constants (one matrix, so a minibatch is one gather), every epoch's shuffle, every
    minibatch's random numbers and Adam's bias corrections (``_schedule``). The loop body is then
    the gather, ``form.value_and_grad``, the L2 term and Adam; the statistics (loss and aux, which
    the gradient does not need) are evaluated inside each step or per epoch from the epoch's
    kept weights (``cfg.statistics``), or, for the last epoch only (``cfg.statistics_epochs``),
    once after the loop.

    With ``cfg.adam_entries == "trained"`` (and a ``form.trained``), the loop carries only the
    trained entries w and Adam's moments of them: θ is formed from w each step by one gather
    (zeros in the padding), the gradient's trained entries by another. Adam's update then reads
    and writes those entries only, a large share of a step's memory traffic with many seeds side
    by side (a scatter of the updated entries into θ instead costs as much as it saves). Every
    trained entry sees the same arithmetic either way; only the L2 statistic sums in another
    order.
    Returns (net, (loss [E], data_loss [E], aux)): E = epochs, or 1 with
    ``cfg.statistics_epochs == "last"``. Then, with the statistics per epoch, no step computes
    them: the steps keep their weights in a buffer of one epoch, and one evaluation after the
    loop gives the last epoch's; with the statistics per step (many seeds per GPU, where that
    buffer's traffic costs more than the statistics), every step computes them as with "all".
    """
    theta0 = form.pack(params)
    idx, noise, c1, c2 = _schedule(train, key, cfg, form.noise, theta0.dtype)
    rows = form.rows(params, train)
    n = theta0.shape[-1]
    trained = (None if form.trained is None or cfg.adam_entries == "all"
               else np.asarray(form.trained(params)))
    if trained is not None and len(trained) == n:
        trained = None
    if trained is None:
        expand = lambda w: w  # noqa: E731
        w0 = theta0
    else:
        # θ = where(padding, 0, w[source]): each entry's position in w (0 in the padding)
        is_trained = np.zeros(n, dtype=bool)
        is_trained[trained] = True
        source = np.where(is_trained, np.cumsum(is_trained) - 1, 0)
        expand = lambda w: jnp.where(is_trained, w[source], 0)  # noqa: E731
        w0 = theta0[trained]
    stats_def = []

    def update(w, mu, nu, i, eps, c1, c2):
        """One minibatch step: (w, μ, ν) after Adam, and the step's loss value and aux."""
        (value, aux), grad = form.value_and_grad(params, expand(w), rows[i], eps)
        g = grad if trained is None else grad[trained]
        # d(β·Σθ²)/dθ as autodiff forms it, β·(2θ)
        w_new, mu, nu = adam_update(cfg, w, mu, nu, g + cfg.weight_decay * (2.0 * w), c1, c2)
        return w_new, mu, nu, value, aux

    def statistics(value, aux, l2):
        stats, treedef = _stats(value + cfg.weight_decay * l2, value, aux)
        stats_def.append(treedef)
        return stats

    zeros = jnp.zeros_like(w0)
    nb = len(idx) // cfg.epochs

    def evaluate_epoch(ws, i, eps):
        """The mean statistics of one epoch's steps from their kept weights ws [nb, len(w0)], each on
        its own weights, minibatch i [nb, bs] and noise eps (one batched forward pass)."""
        def evaluate(w, i, eps):
            (value, aux), _ = form.value_and_grad(params, expand(w), rows[i], eps)
            return statistics(value, aux, l2_penalty(w))
        return jnp.mean(jax.vmap(evaluate)(ws, i, eps), axis=0)

    per_step = resolve_statistics(cfg.statistics, sharding.block_seeds(), sharding.target_platform()) == "step"
    if cfg.statistics_epochs == "last" and not per_step:
        # One loop over every step without statistics (the gradient alone; XLA drops the loss's
        # other parts). Each step writes its weights into a buffer of one epoch's steps, which
        # after the loop holds the last epoch's: one evaluation of them gives its statistics.
        def step(carry, inputs):
            w, mu, nu, kept = carry
            j, *rest = inputs
            w_new, mu, nu, _, _ = update(w, mu, nu, *rest)
            return (w_new, mu, nu, lax.dynamic_update_index_in_dim(kept, w, j, 0)), None

        slot = jnp.arange(len(idx), dtype=jnp.int32) % nb
        kept0 = jnp.zeros((nb,) + w0.shape, w0.dtype)
        (w, _, _, kept), _ = lax.scan(step, (w0, zeros, zeros, kept0), (slot, idx, noise, c1, c2),
                                      unroll=min(cfg.unroll, len(idx)))
        means = evaluate_epoch(kept, idx[-nb:], None if noise is None else noise[-nb:])[None]
    elif per_step:  # (with statistics_epochs "last" too: the buffer would cost more than they do)
        def step(carry, inputs):
            w, mu, nu, l2 = carry
            w_new, mu, nu, value, aux = update(w, mu, nu, *inputs)
            # Σθ² of the next step's weights, summed as soon as they are made and carried over,
            # so that the next step does not start with this sum (the same sum of the same weights)
            return (w_new, mu, nu, l2_penalty(w_new)), statistics(value, aux, l2)

        (w, *_), stats = lax.scan(step, (w0, zeros, zeros, l2_penalty(w0)), (idx, noise, c1, c2),
                                  unroll=min(cfg.unroll, len(idx)))
        means = _epoch_means(cfg.epochs, stats)
    else:
        # The loss value only feeds the statistics: a step computes the gradient alone (XLA drops
        # the rest) and keeps its weights; after the epoch one batched forward pass evaluates
        # all of its steps.
        def step(carry, inputs):
            w, mu, nu = carry
            w_new, mu, nu, _, _ = update(w, mu, nu, *inputs)
            return (w_new, mu, nu), w

        def epoch(carry, inputs):
            carry, ws = lax.scan(step, carry, inputs, unroll=min(cfg.unroll, nb))
            return carry, evaluate_epoch(ws, inputs[0], inputs[1])

        by_epoch = jax.tree_util.tree_map(lambda a: a.reshape((cfg.epochs, nb) + a.shape[1:]),
                                          (idx, noise, c1, c2))
        (w, *_), means = lax.scan(epoch, (w0, zeros, zeros), by_epoch)
    means = jax.tree_util.tree_unflatten(stats_def[-1], list(means.T))
    return form.unpack(params, expand(w)), _returned_epochs(cfg, means)


def _fit_kernel(policy: Policy, kernel, params: PolicyParams, train: SStepData, key, cfg: SStepConfig):
    """The Adam loop as one of the policy's GPU kernels (``Policy.kernel`` or ``Policy.cuda``), on
    ``_schedule``'s steps. Returns (net, (loss [E], data_loss [E], aux)), E as ``_fit_packed``'s."""
    dtype = params.norm.scale.dtype
    idx, noise, c1, c2 = _schedule(train, key, cfg, policy.training.noise, dtype)
    net, per_step = kernel(params, train, idx, noise, c1, c2, cfg)
    return net, _returned_epochs(cfg, _epoch_means(cfg.epochs, per_step))


def _fit_reference(policy: Policy, params: PolicyParams, train: SStepData, key, cfg: SStepConfig):
    """The Adam loop on autodiff of ``policy.loss``: a scan over epochs of scans over minibatches,
    gathering each field and drawing the loss's random numbers inside the loop (the S-step's
    first form, kept as the reference of "packed" and for policies without a TrainingForm).
    Returns (net, (loss [E], data_loss [E], aux)), E as ``_fit_packed``'s."""
    B = train.x.shape[0]
    bs = cfg.batch_size
    nb = B // bs
    opt = optax.adam(cfg.lr, b1=cfg.b1, b2=cfg.b2, eps=cfg.eps)

    # The optimiser works on one flat parameter vector: Adam's update and the L2 term are then
    # one fused kernel each instead of one per weight matrix (a GPU step costs per kernel).
    flat0, unravel = ravel_pytree(params.net)

    def objective(flat, batch, k):
        value, aux = policy.loss(params._replace(net=unravel(flat)), batch, k)
        return value + cfg.weight_decay * l2_penalty(flat), (value, aux)

    grad_fn = jax.value_and_grad(objective, has_aux=True)

    stats_def = []  # the tree structure of (total, value, aux), recorded while tracing

    def batch_step(carry, inputs):
        net, opt_state = carry
        idx, k = inputs
        batch = jax.tree_util.tree_map(lambda a: a[idx], train)
        (total, (value, aux)), grads = grad_fn(net, batch, k)
        updates, opt_state = opt.update(grads, opt_state, net)
        stats, treedef = _stats(total, value, aux)
        stats_def.append(treedef)
        return (optax.apply_updates(net, updates), opt_state), stats

    def epoch(carry, keys):
        k_perm, k_loss = keys
        idx = _minibatches(k_perm, B, nb, bs)
        carry, stats = lax.scan(batch_step, carry, (idx, jax.random.split(k_loss, nb)),
                                unroll=min(cfg.unroll, nb))
        return carry, jnp.mean(stats, axis=0)

    # Fresh optimiser state at every S-step (the authors' practice); parameters are warm-started.
    carry = (flat0, opt.init(flat0))
    (flat, _), means = lax.scan(epoch, carry, _epoch_keys(key, cfg))
    return unravel(flat), _returned_epochs(cfg, jax.tree_util.tree_unflatten(stats_def[-1], list(means.T)))

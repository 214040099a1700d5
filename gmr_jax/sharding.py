"""Many seeds on several devices: the vmapped seed axis sharded over a 1-D device mesh.

Seeds are independent, so a program vmapped over seeds splits into per-device programs with no
communication: :func:`over_seeds` wraps a seed-vmapped function in ``jax.shard_map`` over the
mesh axis ``"seeds"``. Each device runs the same program on its block of seeds; host callbacks
(the C MuJoCo backend) run per device on that block, instead of gathering every seed onto one
device as a ``pure_callback`` under a global-view ``jit`` would.

A seed count that the device count does not divide is padded with copies of the last seed
(:func:`pad`); the padding is computed and dropped (:func:`unpad`), never reported or saved.
Checkpoints hold host copies of the real seeds only, so they restore onto any device count.

With one device every function here is the identity on the program: results are those of the
plain vmapped program (of the plain program for a single seed, :func:`over_seed_axis`).
"""

from __future__ import annotations

import contextlib
import contextvars
import functools
import os
import re
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

AXIS = "seeds"


def target_platform() -> str:
    """The platform that the program being traced will run on: that of ``jax.default_device``
    where one is set (the runner traces a run placed on the host CPU under it), else JAX's
    default backend. Trace-time choices that depend on the hardware (the S-step's form, the
    physics backend "auto") follow it."""
    device = jax.config.jax_default_device
    if device is None:
        return jax.default_backend()
    return device if isinstance(device, str) else device.platform


def seed_mesh(devices: int | None = None, platform: str | None = None) -> Mesh:
    """A 1-D mesh named ``"seeds"`` over the first ``devices`` local devices (default: all) of
    ``platform`` (default: JAX's default backend; e.g. "cpu" for the host)."""
    available = jax.local_devices(backend=platform)
    n = len(available) if devices is None else devices
    if not (isinstance(n, int) and 1 <= n <= len(available)):
        raise ValueError(f"devices={devices!r}: must be between 1 and the {len(available)} local "
                         f"device(s) ({available[0].platform})")
    # Auto axes: shardings stay out of the array types, so the seed-vmapped programs trace the
    # same on one device and on several.
    return jax.make_mesh((n,), (AXIS,), axis_types=(jax.sharding.AxisType.Auto,), devices=available[:n])


def seeds_per_device(num_seeds: int, devices: int) -> int:
    """The seeds each of ``devices`` devices holds (the padded block, :func:`padded_count`)."""
    return -(-num_seeds // max(devices, 1))


def padded_count(num_seeds: int, mesh: Mesh) -> int:
    """The seed count rounded up to a multiple of the mesh's device count."""
    return seeds_per_device(num_seeds, mesh.size) * mesh.size


def pad(tree, num_seeds: int, mesh: Mesh):
    """Leaves [S, ...] → [S', ...], S' = :func:`padded_count`, the extra rows copies of the last
    seed's (they compute what that seed computes and are dropped by :func:`unpad`)."""
    extra = padded_count(num_seeds, mesh) - num_seeds
    if extra == 0:
        return tree
    return jax.tree_util.tree_map(lambda a: jnp.concatenate([a, jnp.repeat(a[-1:], extra, axis=0)]), tree)


def unpad(tree, num_seeds: int):
    """Leaves [S', ...] → the real seeds' [S, ...] (no copy when nothing was padded).

    A padded leaf split over several devices comes back on one device, copied shard by shard
    (:func:`_real_rows`), with no program over the mesh; an unpadded leaf stays as it is.
    Slicing the global array instead runs a program over the mesh with an all-gather: two
    threads that unpad at once (the runner's loop and its checkpoint writer) then reach the
    devices in different orders, and XLA's rendezvous waits until it ends the process."""
    return jax.tree_util.tree_map(lambda a: a if a.shape[0] == num_seeds else _real_rows(a, num_seeds), tree)


def _real_rows(a, num_seeds: int):
    """The first ``num_seeds`` rows of ``a``. An array on several devices gives them on one
    device: split along its leading axis only (as :func:`place` puts it), from device-to-device
    copies of the shards that hold them onto the first one's device; replicated, from its first
    shard; in any other layout, through the host."""
    if not isinstance(a, jax.Array) or len(a.sharding.device_set) == 1:
        return a[:num_seeds]
    by_start = sorted(((s.index[0].start or 0, s) for s in a.addressable_shards), key=lambda pair: pair[0])
    first = by_start[0][1].device
    if a.sharding.is_fully_replicated:
        return by_start[0][1].data[:num_seeds]
    split_rows_only = len({start for start, _ in by_start}) == len(by_start) and all(
        index == slice(None) for _, s in by_start for index in s.index[1:])
    if not split_rows_only:
        return jax.device_put(np.asarray(a)[:num_seeds], first)
    return jnp.concatenate([jax.device_put(s.data[:num_seeds - start], first)
                            for start, s in by_start if start < num_seeds])


def place(tree, mesh: Mesh):
    """Put leaves [S', ...] on the mesh, split along the seed axis."""
    sharding = NamedSharding(mesh, PartitionSpec(AXIS))
    return jax.tree_util.tree_map(lambda a: jax.device_put(a, sharding), tree)


def over_seeds(fn: Callable, mesh: Mesh, batched: tuple[bool, ...]) -> Callable:
    """``fn`` (already vmapped over a leading seed axis) split over the mesh's devices.

    Args:
      fn: (*args) -> outputs, every output leaf with a leading seed axis (mapped over it, e.g.
        by :func:`over_seed_axis`; inside, each device's block of seeds).
      mesh: from :func:`seed_mesh`.
      batched: per positional argument, whether it carries the seed axis (True) or is shared by
        all seeds (False, replicated).
    Returns:
      The same function; with one device ``fn`` itself.
    """
    if mesh.size == 1:
        return fn
    seeds, shared = PartitionSpec(AXIS), PartitionSpec()
    return jax.shard_map(fn, mesh=mesh, in_specs=tuple(seeds if b else shared for b in batched),
                         out_specs=seeds, check_vma=False)


# XLA's CPU code generator without its newer "fusion emitters": the same arithmetic to round-off
# (tests/test_sharding.py), a faster S-step and iteration, and a faster compilation
# (benchmarks/RESULTS.md, eleventh session).
CPU_COMPILER_OPTIONS = {"xla_cpu_use_fusion_emitters": False}

# On a GPU, a program of one seed per device computes its small matrix products with XLA's own
# dot emitter, and the others as cuBLAS calls, never as Triton GEMMs. A product whose (m + n)·k
# is below the threshold stays an XLA dot: every product of the S-step's minibatch steps with the
# paper's networks (the largest, 20 rows through a 64-wide layer, (20 + 64)·64 = 5 376), each a
# kernel as short as the step's other operations, where a cuBLAS call takes about twice as long.
# The same products to round-off (float32 multiply-adds in another order). With more seeds per
# device the same products are larger batches, for which cuBLAS and Triton are faster
# (benchmarks/RESULTS.md: ninth, twelfth, fourteenth and nineteenth sessions).
GPU_ONE_SEED_COMPILER_OPTIONS = {"xla_gpu_enable_triton_gemm": False,
                                 "xla_gpu_gemm_rewrite_size_threshold": 10_000}


def wanted_compiler_options(backend: str, seeds_per_device: int, xla_flags: str) -> dict:
    """The options :func:`compiler_options` asks for: ``CPU_COMPILER_OPTIONS`` on a CPU,
    ``GPU_ONE_SEED_COMPILER_OPTIONS`` on a GPU for one seed per device, else none; without those
    that ``xla_flags`` names (the user's choice wins)."""
    options = {"cpu": CPU_COMPILER_OPTIONS,
               "gpu": GPU_ONE_SEED_COMPILER_OPTIONS if seeds_per_device == 1 else {}}.get(backend, {})
    # the flag itself, not one whose name it begins (xla_gpu_enable_triton_gemm_any)
    return {name: value for name, value in options.items()
            if not re.search(rf"--{name}(=|\s|$)", xla_flags)}


@functools.lru_cache(maxsize=None)
def _accepted(options: tuple, platform: str) -> dict:
    """``options`` if this XLA compiles with them for ``platform``, else {} (an unknown option in
    ``XLA_FLAGS`` would abort the process; as a compile option it is only refused)."""
    if not options:
        return {}
    x = jax.device_put(jnp.zeros((), jnp.float32), jax.local_devices(backend=platform)[0])
    try:
        jax.jit(lambda y: y + 1).lower(x).compile(compiler_options=dict(options))
    except jax.errors.JaxRuntimeError:
        return {}
    return dict(options)


def compiler_options(seeds_per_device: int = 1, platform: str | None = None) -> dict:
    """XLA options for compiling the programs of :func:`seed_program` with ``seeds_per_device``
    seeds on each device of ``platform`` (default: JAX's default backend; the runner passes
    them to ``Lowered.compile``; a ``jax.jit`` option would refuse nested tracing):
    :func:`wanted_compiler_options`, where this XLA knows them."""
    platform = jax.default_backend() if platform is None else platform
    wanted = wanted_compiler_options(platform, seeds_per_device, os.environ.get("XLA_FLAGS", ""))
    return _accepted(tuple(sorted(wanted.items())), platform)


REDUCED_PRODUCTS_MAX_SEEDS = 32
"""The most seeds per GPU whose programs trace GMR's products as reductions: measured per Adam step
of GMR A,B on an H100 in float32, reductions are faster than dots up to 32 seeds per GPU and
slower at 64 (the sums grow with the seed batch, a dot's time hardly does; benchmarks/RESULTS.md,
nineteenth to twenty-first sessions; 33–63 seeds and float64 beyond one seed not measured)."""


EPOCH_STATISTICS_MAX_SEEDS = 8
"""The most seeds per GPU whose programs evaluate the packed S-step's statistics per epoch
(``SStepConfig.statistics`` "auto"): measured per Adam step of GMR A,B on an H100 in float32,
faster per epoch at 1 and 8 seeds, slower at 16, 32 and 256 (the kept weights are written every
step, the batched evaluation grows with the seeds; benchmarks/RESULTS.md, twenty-second session;
9–15 seeds not measured)."""

_BLOCK_SEEDS = contextvars.ContextVar("block_seeds", default=None)


@contextlib.contextmanager
def seed_block(seeds: int):
    """Trace-time choices for a program of ``seeds`` seeds per device (``over_seed_axis``' block):
    with up to ``REDUCED_PRODUCTS_MAX_SEEDS`` of them on a GPU, the policies' packed S-step forms
    may trace their small products as sums of broadcast products
    (``policies.base.products_as_reductions``; GMR's does), which XLA fuses with the operations
    around them; and ``block_seeds`` tells the S-step how many seeds share the device
    (``epoch_statistics_for``). Every input of those choices (platform, seeds per block) is part
    of the program's jit cache key: the default device and the block's shapes."""
    from gmr_jax.policies import base

    token = _BLOCK_SEEDS.set(int(seeds))
    try:
        with base.products_as_reductions(reduced_products_for(seeds, target_platform())):
            yield
    finally:
        _BLOCK_SEEDS.reset(token)


def block_seeds() -> int | None:
    """The seeds per device of the program being traced under :func:`seed_block` (None outside)."""
    return _BLOCK_SEEDS.get()


def epoch_statistics_for(seeds_per_device: int, platform: str) -> bool:
    """Whether a program of ``seeds_per_device`` seeds per device on ``platform`` evaluates the
    packed S-step's statistics per epoch ("auto" of ``SStepConfig.statistics``)."""
    return platform == "gpu" and seeds_per_device <= EPOCH_STATISTICS_MAX_SEEDS


def reduced_products_for(seeds_per_device: int, platform: str) -> bool:
    """Whether a program of ``seeds_per_device`` seeds per device on ``platform`` traces the
    packed forms' products as reductions (:func:`seed_block`)."""
    return platform == "gpu" and seeds_per_device <= REDUCED_PRODUCTS_MAX_SEEDS


def over_seed_axis(fn: Callable, batched: tuple[bool, ...]) -> Callable:
    """``fn`` mapped over the leading seed axis of the ``batched`` positional arguments; every
    output leaf gets that axis, and the whole is traced under :func:`seed_block` of the axis'
    size. A block of one seed runs ``fn`` itself on the squeezed arguments instead of
    ``jax.vmap``: the same arithmetic up to round-off (XLA may pick other kernels for a batch of
    one), traced about four times faster (tracing under ``vmap`` passes every operation through
    the batching rules), and on a CPU also compiled faster (benchmarks/RESULTS.md, twelfth
    session)."""
    vmapped = jax.vmap(fn, in_axes=tuple(0 if b else None for b in batched))

    def mapped(*args):
        sizes = {leaf.shape[0] for a, b in zip(args, batched) if b for leaf in jax.tree_util.tree_leaves(a)}
        if len(sizes) != 1:
            raise ValueError("over_seed_axis: the batched arguments need one leading seed axis of one size, "
                             f"got sizes {sorted(sizes)}")
        (size,) = sizes
        with seed_block(size):
            if size != 1:
                return vmapped(*args)
            out = fn(*[jax.tree_util.tree_map(lambda x: x[0], a) if b else a for a, b in zip(args, batched)])
        return jax.tree_util.tree_map(lambda x: jnp.asarray(x)[None], out)
    return mapped


@functools.lru_cache(maxsize=None)
def seed_program(fn: Callable, mesh: Mesh, batched: tuple[bool, ...]) -> Callable:
    """``jax.jit`` of ``fn(cfg, *args)`` mapped over the seed axis of the ``batched`` arguments
    (:func:`over_seed_axis`) and split over ``mesh``; ``cfg`` (the first argument) is static.
    Cached per (fn, mesh, batched), so every caller shares one jitted function and its
    compilation cache."""

    def program(cfg, *args):
        return over_seeds(over_seed_axis(functools.partial(fn, cfg), batched), mesh, batched)(*args)
    return jax.jit(program, static_argnums=0)


def train(cfg, keys: jax.Array, mesh: Mesh | None = None):
    """``jax.vmap(mdgps.train)`` over ``keys`` [S] split over ``mesh`` (default: all local
    devices; one seed per device runs the plain ``mdgps.train``, :func:`over_seed_axis`); S need
    not be a multiple of the device count.

    Returns:
      (final TrainState, metrics history), leaves with a leading seed axis [S, ...]: split over
      the mesh when the device count divides S, else on the mesh's first device (:func:`unpad`).
    """
    from gmr_jax import mdgps

    mesh = seed_mesh() if mesh is None else mesh
    num = keys.shape[0]
    program = seed_program(mdgps.train, mesh, (True,))
    return unpad(program(cfg, place(pad(keys, num, mesh), mesh)), num)


def _scan_counts(params: dict) -> tuple[int, int]:
    """(constants, carries) of a ``scan`` equation's inputs: JAX up to 0.10 names the counts,
    later versions give the inputs' grouping (``ft_in``: constants, carries, xs)."""
    if "num_consts" in params:
        return params["num_consts"], params["num_carry"]
    consts, carry, _ = params["ft_in"].unpack()
    return len(list(consts)), len(list(carry))


def _carry_fixpoint(carry: list[bool], out_of: Callable) -> list[bool]:
    """The loop carries' flags grown by ``out_of`` (carry flags -> the body's carry-out flags)
    until they no longer change: the carries that vary after any number of iterations."""
    while True:
        grown = [a or b for a, b in zip(carry, out_of(carry))]
        if grown == carry:
            return carry
        carry = grown


def _depends(jaxpr, varying: list[bool]) -> list[bool]:
    """Which outputs of ``jaxpr`` (a Jaxpr or ClosedJaxpr) depend on the inputs flagged
    ``varying``, following ``jax.vmap``'s batching: through calls (jit, custom derivatives,
    remat) into their bodies, through ``scan`` and ``while`` to their carries' fixpoint, through
    ``cond`` per branch unless its index varies, through ``optimization_barrier`` operand by
    operand; every other operation's outputs vary where one of its inputs does. Constants (values
    a body closes over) count as not varying. ``custom_linear_solve``, whose sub-programs no rule
    here reads, raises KeyError (``scan_varying`` then leaves the batching to the vmap)."""
    from jax.extend import core as jex

    jaxpr = getattr(jaxpr, "jaxpr", jaxpr)
    var: set = {v for v, b in zip(jaxpr.invars, varying) if b}

    def of(atoms):
        return [not isinstance(a, jex.Literal) and a in var for a in atoms]

    for eqn in jaxpr.eqns:
        ins, name, p = of(eqn.invars), eqn.primitive.name, eqn.params
        if not any(ins):
            continue
        if name == "scan":
            c, n = _scan_counts(p)

            def body_out(carry):
                return _depends(p["jaxpr"], ins[:c] + carry + ins[c + n:])
            carry = _carry_fixpoint(ins[c:c + n], lambda carry: body_out(carry)[:n])
            outs = carry + body_out(carry)[n:]
        elif name == "while":
            cc, bc = p["cond_nconsts"], p["body_nconsts"]
            carry = _carry_fixpoint(ins[cc + bc:], lambda carry: _depends(p["body_jaxpr"], ins[cc:cc + bc] + carry))
            # a varying predicate runs every member's loop as long as the longest: all carries vary
            outs = [True] * len(carry) if any(_depends(p["cond_jaxpr"], ins[:cc] + carry)) else carry
        elif name == "optimization_barrier":
            outs = ins
        elif name == "cond":
            if ins[0]:
                outs = [True] * len(eqn.outvars)
            else:
                per = [_depends(b, ins[1:]) for b in p["branches"]]
                outs = [any(col) for col in zip(*per)]
        else:
            bodies = [v for v in p.values() if isinstance(v, (jex.ClosedJaxpr, jex.Jaxpr))
                      and len(getattr(v, "jaxpr", v).invars) == len(eqn.invars)
                      and len(getattr(v, "jaxpr", v).outvars) == len(eqn.outvars)]
            if bodies:
                outs = _depends(bodies[0], ins)
            elif name == "custom_linear_solve":
                raise KeyError(f"no rule for the sub-programs of {name!r}")
            else:  # including combiners (a scatter's, a reduction's)
                outs = [True] * len(eqn.outvars)
        var.update(v for v, b in zip(eqn.outvars, outs) if b)
    return of(jaxpr.outvars)


def varying_like(tree, anchor):
    """``tree`` unchanged, each leaf made to vary wherever ``anchor`` does under ``jax.vmap``: a
    select of the leaf or the leaf on a predicate read from ``anchor``, which XLA simplifies away
    (under the vmap, to the leaf broadcast over the batch, as the vmap's own batching of a loop
    carry is). Forward values are unchanged; a reverse-mode gradient through it turns a -0.0
    cotangent into +0.0. An empty ``anchor`` leaves ``tree`` as it is."""
    if jnp.size(anchor) == 0:
        return tree
    if jnp.issubdtype(anchor.dtype, jax.dtypes.prng_key):
        anchor = jax.random.key_data(anchor)
    first = jnp.ravel(anchor)[0]
    pred = first == first

    def vary(a):
        return jax.lax.select(jnp.broadcast_to(pred, jnp.shape(a)), a, a)
    return jax.tree_util.tree_map(vary, tree)


def scan_varying(body: Callable, init, xs, varying, anchor, length: int | None = None):
    """``jax.lax.scan(body, init, xs, length)`` whose carries start out varying under ``jax.vmap``
    wherever they come to vary, so that the vmap batches ``body`` once.

    A loop carry that starts the same for every member of a vmapped batch (an initial state of
    zeros, a template) but comes out of the body member-dependent makes the vmap batch the whole
    body once more, with that carry batched (``jax.lax.scan``'s batching fixpoint); for a large
    body that is seconds of tracing (benchmarks/RESULTS.md, fifty-first session). Here the scan
    is traced once without the vmap (``jax.make_jaxpr``), the carries that depend on the
    ``varying`` inputs are read from that trace (:func:`_depends`, the vmap's own rule), those
    leaves of ``init`` are made to vary with ``anchor`` (:func:`varying_like`), and the traced
    scan is evaluated on them: the same program, its body batched in one pass.

    Args:
      body, init, xs, length: as ``jax.lax.scan``'s.
      varying: ``(init flags, xs flags)``, pytrees of bools with the structures of ``init`` and
        ``xs``: the inputs that differ between the batch's members.
      anchor: an array that varies under exactly the vmaps where one of the ``varying`` inputs
        does (elsewhere a forced carry is batched where the vmap would not batch it: the same
        values, another program). Values that ``body`` closes over are not seen.
    """
    from jax.extend import core as jex

    def aval(a):
        t = jax.typeof(a)
        return jax.ShapeDtypeStruct(t.shape, t.dtype, weak_type=t.weak_type)

    init_leaves, x_leaves = jax.tree_util.tree_leaves(init), jax.tree_util.tree_leaves(xs)
    init_flags, x_flags = (jax.tree_util.tree_leaves(v) for v in varying)
    if len(init_flags) != len(init_leaves) or len(x_flags) != len(x_leaves):
        raise ValueError("scan_varying: varying needs one bool per leaf of init and of xs")
    closed, out_shape = jax.make_jaxpr(lambda c, x: jax.lax.scan(body, c, x, length=length), return_shape=True)(
        jax.tree_util.tree_map(aval, init), jax.tree_util.tree_map(aval, xs))
    # the scan's outputs are (final carry, ys): its carries' fixpoint is the final carry's flags
    try:
        carry = _depends(closed, list(init_flags) + list(x_flags))[:len(init_leaves)]
    except (KeyError, AttributeError, TypeError, ValueError):
        # a JAX whose loop equations this rule does not know: the scan as traced, batched as
        # the vmap does by itself
        carry = [False] * len(init_leaves)
    changed = varying_like([a for a, v in zip(init_leaves, carry) if v], anchor)[::-1] if any(carry) else []
    forced = [changed.pop() if v else a for a, v in zip(init_leaves, carry)]
    out = jex.jaxpr_as_fun(closed)(*forced, *x_leaves)
    return jax.tree_util.tree_unflatten(jax.tree_util.tree_structure(out_shape), out)


def seed_scan(body: Callable, init, xs, varying_xs):
    """``jax.lax.scan(body, init, xs)`` for a function that ``over_seed_axis`` maps over seeds:
    under a block of several seeds (``seed_block``), :func:`scan_varying` with the ``xs``
    leaves flagged in ``varying_xs`` (a pytree of bools, at least one True, e.g. the
    per-iteration keys) as the inputs that differ between seeds, so that the seeds' vmap
    batches the body once for the carries that come to depend on them; elsewhere
    ``jax.lax.scan`` itself."""
    if (block_seeds() or 1) == 1:
        return jax.lax.scan(body, init, xs)
    x_leaves, flags = jax.tree_util.tree_leaves(xs), jax.tree_util.tree_leaves(varying_xs)
    if len(flags) != len(x_leaves) or not any(flags):
        raise ValueError("seed_scan: varying_xs needs one bool per leaf of xs, at least one True")
    anchor = next(leaf for leaf, f in zip(x_leaves, flags) if f)[0]
    no = jax.tree_util.tree_map(lambda _: False, init)
    return scan_varying(body, init, xs, (no, varying_xs), anchor)

"""Programs traced once: serialized ``jax.export`` modules on disk, lowered instead of traced.

XLA's persistent compilation cache spares a repeated run the compilation of its programs, not
their tracing and lowering: Python work of seconds per program, under the GIL, before a run can
start (the default study's GMR iteration: 5–7 s on an H100's host; benchmarks/RESULTS.md,
twenty-third session). A :class:`ProgramStore` keeps every program it can as a serialized
``jax.export.Exported`` with its argument and result trees, and a later process lowers the
stored module (milliseconds) instead of tracing the program again.

A program is found by a key of everything its trace depends on: its name and static
configuration, its arguments' tree, shapes and dtypes, the platform, JAX's settings that change
tracing (``TRACE_SETTINGS``), the versions of the packages that tracing runs (JAX, jaxlib, MuJoCo,
MJX, Flax, Optax, NumPy, ml_dtypes, opt_einsum), and the bytes of this package's source and of the
arm's MJCF files. A program that ``jax.export`` cannot serialize (a host callback: the C MuJoCo
rollouts) is traced as before; a marker file records that, so the export is tried once per key.
A stored program is compiled from its exported module in the run that stores it too, so runs
that load it and the run that stored it compile the same module and compute the same values.
Files are written atomically; one that cannot be read or lowered is traced and written again; a
store that cannot be written warns once and the runs go on. The files are pickles (the trees):
keep the directory private, as the compilation cache.
"""

from __future__ import annotations

import contextlib
import functools
import hashlib
import importlib.metadata
import json
import os
import pathlib
import pickle
import threading
import warnings
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

from gmr_jax import config, sim

TRACE_SETTINGS = ("jax_enable_x64", "jax_default_matmul_precision", "jax_default_prng_impl",
                  "jax_threefry_partitionable", "jax_numpy_dtype_promotion", "jax_numpy_rank_promotion")
"""JAX settings that change what a trace produces (part of every key)."""

_VERSIONED = ("jax", "jaxlib", "mujoco", "mujoco-mjx", "flax", "optax", "numpy", "ml_dtypes", "opt_einsum")


@functools.cache
def code_version() -> str:
    """sha256 of this package's Python source, the arm's MJCF files and the versions of the
    packages that tracing depends on."""
    h = hashlib.sha256()
    root = pathlib.Path(__file__).resolve().parent
    files = [(f"gmr_jax/{p.relative_to(root).as_posix()}", p) for p in sorted(root.rglob("*.py"))]
    files += [(f"mjcf/{p.name}", p) for p in sorted(sim.MJCF_DIR.glob("*")) if p.is_file()]
    for name, path in files:
        h.update(name.encode() + b"\0" + path.read_bytes() + b"\0")
    for package in _VERSIONED:
        try:
            h.update(f"{package}={importlib.metadata.version(package)}\0".encode())
        except importlib.metadata.PackageNotFoundError:
            h.update(f"{package}=none\0".encode())
    return h.hexdigest()


def abstract(tree):
    """Arrays or shapes → their shapes (``jax.ShapeDtypeStruct``) without placement: lowered
    for the default device."""
    return jax.tree_util.tree_map(lambda leaf: jax.ShapeDtypeStruct(tuple(leaf.shape), leaf.dtype), tree)


def export_platform(platform: str) -> str:
    """``jax.export``'s name of a device platform: "cpu", or the GPU's ("cuda", "rocm")."""
    return "cpu" if platform == "cpu" else jax.export.default_export_platform()


def program_key(name: str, cfg: config.Config, args, platform: str) -> str:
    """The store's key of program ``name`` with static configuration ``cfg`` for ``args`` (arrays
    or shapes) on ``platform`` (a device platform, keyed by its ``export_platform``)."""
    platform = export_platform(platform)
    leaves, tree = jax.tree_util.tree_flatten(args)
    parts = {"name": name, "config": config.to_dict(cfg), "tree": str(tree), "platform": platform,
             "leaves": [[list(leaf.shape), str(leaf.dtype)] for leaf in leaves],
             "settings": {s: str(getattr(jax.config, s)) for s in TRACE_SETTINGS}, "code": code_version()}
    return hashlib.sha256(json.dumps(parts, sort_keys=True, default=str).encode()).hexdigest()


class StoredCompiled(NamedTuple):
    """A stored program compiled: called with the original argument trees, of which it takes the
    leaves that it reads (``kept``)."""

    compiled: Any
    in_tree: Any
    out_tree: Any
    kept: tuple[int, ...]

    @property
    def reads(self) -> tuple[bool, ...]:
        """Per argument leaf: whether the program reads it."""
        return tuple(i in self.kept for i in range(self.in_tree.num_leaves))

    def __call__(self, *args):
        leaves, tree = jax.tree_util.tree_flatten(args)
        if tree != self.in_tree:
            raise ValueError(f"stored program called with arguments {tree}, compiled for {self.in_tree}")
        return jax.tree_util.tree_unflatten(self.out_tree, self.compiled(*(leaves[i] for i in self.kept)))


class StoredLowered(NamedTuple):
    """A stored program lowered from its exported module (as ``jax.stages.Lowered``:
    ``compile``, ``out_info``)."""

    lowered: jax.stages.Lowered
    in_tree: Any
    out_tree: Any
    kept: tuple[int, ...]

    @property
    def out_info(self):
        return jax.tree_util.tree_unflatten(self.out_tree, self.lowered.out_info)

    def compile(self, compiler_options=None) -> StoredCompiled:
        return StoredCompiled(self.lowered.compile(compiler_options=compiler_options), self.in_tree, self.out_tree,
                              self.kept)


class ProgramStore:
    """Serialized programs in ``directory`` (created when first written). A store that cannot
    be written (a read-only or full disk) warns once and serves the programs of this process
    from memory; the runs go on."""

    def __init__(self, directory):
        self.directory = pathlib.Path(directory)
        self._warned = False

    def _path(self, key: str, suffix: str) -> pathlib.Path:
        return self.directory / f"{key}{suffix}"

    def _write(self, path: pathlib.Path, make_data) -> None:
        """``make_data()`` written atomically to ``path``; a failure warns (once) instead."""
        tmp = path.with_name(f"{path.name}.{os.getpid()}.{threading.get_ident()}.tmp")
        try:
            data = make_data()
            self.directory.mkdir(parents=True, exist_ok=True)
            tmp.write_bytes(data)
            tmp.replace(path)
        except (OSError, pickle.PicklingError, TypeError, AttributeError) as err:
            with contextlib.suppress(OSError):
                tmp.unlink(missing_ok=True)
            if not self._warned:
                self._warned = True
                warnings.warn(f"program store {self.directory}: cannot write ({err}); programs are traced "
                              "as before (--no-program-store turns it off)", stacklevel=3)

    def _load(self, key: str, in_tree):
        try:
            stored = pickle.loads(self._path(key, ".exported").read_bytes())
            if stored["in_tree"] != in_tree:
                return None
            return jax.export.deserialize(stored["exported"]), stored["out_tree"]
        except Exception:  # noqa: BLE001 (missing, partial or foreign: traced and written again)
            return None

    def _export(self, name: str, key: str, program, cfg, in_tree, avals, platform: str):
        """Trace ``program`` through ``jax.export`` and store it: (Exported, result tree), or
        None where it cannot be serialized: a marker is written where that will not change (a host
        callback, a custom call without stability guarantees), not for other failures (e.g. a
        missing serialization package)."""
        out_trees = []

        def flat(*leaves):
            out = program(cfg, *jax.tree_util.tree_unflatten(in_tree, leaves))
            out_leaves, out_tree = jax.tree_util.tree_flatten(out)
            out_trees.append(out_tree)
            return out_leaves

        try:
            blob = jax.export.export(jax.jit(flat), platforms=[export_platform(platform)])(*avals).serialize()
        except (NotImplementedError, ValueError) as err:  # host callbacks, custom calls: traced as before
            self._write(self._path(key, ".none"), lambda: f"{name}: {type(err).__name__}: {err}".encode())
            return None
        except Exception:  # noqa: BLE001 (anything else: traced as before, tried again next time)
            return None
        self._write(self._path(key, ".exported"), lambda: pickle.dumps(
            {"name": name, "exported": bytes(blob), "in_tree": in_tree, "out_tree": out_trees[-1]}))
        return jax.export.deserialize(blob), out_trees[-1]

    @staticmethod
    def _lowered(found, in_tree, avals) -> StoredLowered:
        """The exported module lowered as a program of the leaves that it reads (and of every
        PRNG key, which has no zeros): the others are zeros in the program, which the module
        drops, so that a call neither copies nor waits for them (as ``jax.jit`` drops a
        program's unread arguments)."""
        exported, out_tree = found
        kept = tuple(sorted(set(exported.module_kept_var_idx)
                            | {i for i, a in enumerate(avals) if jax.dtypes.issubdtype(a.dtype, jax.dtypes.prng_key)}))

        def call(*kept_leaves):
            leaves = [None if i in kept else jnp.zeros(a.shape, a.dtype) for i, a in enumerate(avals)]
            for i, leaf in zip(kept, kept_leaves, strict=True):
                leaves[i] = leaf
            return exported.call(*leaves)
        return StoredLowered(jax.jit(call).trace(*(avals[i] for i in kept)).lower(), in_tree, out_tree, kept)

    def lower(self, name: str, program, cfg: config.Config, args, platform: str, timer=None,
              prefix: str = "") -> StoredLowered | None:
        """``program(cfg, *args)`` (a ``jax.jit`` function with ``cfg`` static; ``args`` arrays
        or shapes) lowered from its stored module, exported and stored first if the store does
        not hold it yet; None for a program that cannot be stored (trace it as usual). Call it
        under the ``jax.default_device`` the program runs on. ``timer``: a ``runner.Timer``;
        reading or exporting the module counts as ``{prefix}trace_s``, lowering it as
        ``{prefix}lower_s``."""
        leaves, in_tree = jax.tree_util.tree_flatten(args)
        avals = abstract(leaves)
        key = program_key(name, cfg, args, platform)
        if self._path(key, ".none").exists():
            return None
        timed = (lambda phase: contextlib.nullcontext()) if timer is None else timer  # noqa: E731
        with timed(f"{prefix}trace_s"):
            found = self._load(key, in_tree)
        if found is not None:
            try:
                with timed(f"{prefix}lower_s"):
                    return self._lowered(found, in_tree, avals)
            except Exception:  # noqa: BLE001 (a module this JAX cannot lower: exported again)
                pass
        with timed(f"{prefix}trace_s"):
            found = self._export(name, key, program, cfg, in_tree, avals, platform)
        if found is None:
            return None
        with timed(f"{prefix}lower_s"):
            return self._lowered(found, in_tree, avals)

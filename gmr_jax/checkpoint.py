"""Save and restore the whole training state with orbax, safely.

Layout: ``path/<step>/`` per checkpoint (an orbax ``CheckpointManager`` directory), each holding

- ``state``: the leaves of the state pytree as a flat dict of arrays (orbax ``StandardSave``);
- ``meta``: JSON with the caller's metadata and a manifest: for every leaf its tree path, shape,
  dtype, PRNG-key type and a SHA-256 of its bytes, plus the tree structure.

Safety:

- atomic: orbax writes a step into a temporary directory and renames it to ``path/<step>`` only
  after everything (both items and their commit markers) is written; a failed or interrupted
  save leaves no ``<step>`` directory behind, and the earlier steps are never touched;
- previous checkpoints are kept (no rotation), an existing step is never overwritten;
- on restore the manifest is checked against the template (tree paths, shapes, dtypes, key
  types) and optionally the metadata against expected values (e.g. the configuration), and every
  leaf's bytes against its checksum; any problem raises :class:`CheckpointError` naming it.

PRNG keys: raw ``uint32`` keys are ordinary arrays; typed ``jax.random.key`` arrays are stored as
their key data and re-wrapped with the stored implementation. Zero-size leaves are recorded in
the manifest only (orbax cannot write them). These functions run on the host, outside ``jit``;
single-process use (one host) is assumed.
"""

from __future__ import annotations

import hashlib
import json
import logging
import sys
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

FORMAT = "gmr_jax.checkpoint/1"
_STATE, _META = "state", "meta"


class CheckpointError(RuntimeError):
    """A checkpoint cannot be written, found, read or matched to the expected state."""


class CorruptCheckpointError(CheckpointError):
    """A checkpoint's files are damaged: unreadable metadata or arrays, or a failed checksum."""


def _ocp():
    # Imported lazily: orbax is heavy and only needed when checkpointing.
    import orbax.checkpoint as ocp
    return ocp


def _manager(path, create: bool):
    ocp = _ocp()
    options = ocp.CheckpointManagerOptions(max_to_keep=None, create=create,
                                           enable_async_checkpointing=False,
                                           cleanup_tmp_directories=create)
    return ocp.CheckpointManager(_abspath(path), options=options)


def _abspath(path):
    import os
    return os.path.abspath(os.fspath(path))


def _is_key(dtype) -> bool:
    return jax.dtypes.issubdtype(dtype, jax.dtypes.prng_key)


def _leaf_spec(leaf) -> tuple[tuple[int, ...], str, str | None]:
    """(shape of the stored data, its dtype name, key dtype or None) of a concrete or abstract leaf."""
    dtype = getattr(leaf, "dtype", None)
    if dtype is not None and _is_key(dtype):
        data = jax.eval_shape(jax.random.key_data, leaf)
        return tuple(data.shape), np.dtype(data.dtype).name, str(dtype)
    if dtype is not None and hasattr(leaf, "shape"):  # arrays and ShapeDtypeStructs: no copy
        return tuple(leaf.shape), np.dtype(dtype).name, None
    arr = np.asarray(leaf)
    return tuple(arr.shape), arr.dtype.name, None


def _sha256(arr: np.ndarray) -> str:
    return hashlib.sha256(np.ascontiguousarray(arr).tobytes()).hexdigest()


def _leaf_name(i: int) -> str:
    return f"leaf_{i:06d}"


def _flatten(state) -> tuple[dict[str, np.ndarray], list[dict], str]:
    """Host copies of the leaves (keyed leaf_i), the manifest entries and the tree structure."""
    pairs, treedef = jax.tree_util.tree_flatten_with_path(state)
    arrays, entries = {}, []
    for i, (path, leaf) in enumerate(pairs):
        name = jax.tree_util.keystr(path)
        key_impl = key_dtype = None
        dtype = getattr(leaf, "dtype", None)
        if dtype is not None and _is_key(dtype):
            key_impl, key_dtype = str(jax.random.key_impl(leaf)), str(dtype)
            arr = np.asarray(jax.random.key_data(leaf))
        else:
            arr = np.asarray(leaf)
        if arr.dtype == object or not (np.issubdtype(arr.dtype, np.number) or arr.dtype == bool
                                       or arr.dtype.name == "bfloat16"):
            raise CheckpointError(f"state leaf {name} of type {type(leaf).__name__} cannot be saved "
                                  "(only numeric arrays, bools and PRNG keys)")
        entries.append({"path": name, "shape": list(arr.shape), "dtype": arr.dtype.name,
                        "key_dtype": key_dtype, "key_impl": key_impl, "sha256": _sha256(arr)})
        if arr.size:
            arrays[_leaf_name(i)] = arr
    return arrays, entries, str(treedef)


def save(path, state, step: int, metadata: dict | None = None) -> None:
    """Write ``state`` (any pytree of arrays / PRNG keys) as checkpoint ``step`` under ``path``.

    Args:
      path: checkpoint directory (created if missing); steps live in ``path/<step>``.
      state: the pytree to save (jax or numpy arrays, Python scalars, typed or raw PRNG keys).
      step: non-negative int, larger than every step already in ``path``.
      metadata: JSON-serialisable dict stored alongside (e.g. ``{"config": config.to_dict(cfg)}``).
    Raises:
      CheckpointError: bad step or metadata, unsavable leaf, or a failed write. In every case the
        checkpoints already in ``path`` are left as they were.
    """
    if isinstance(step, bool) or not isinstance(step, (int, np.integer)) or step < 0:
        raise CheckpointError(f"checkpoint step={step!r}: must be a non-negative integer")
    step = int(step)
    metadata = {} if metadata is None else metadata
    if not isinstance(metadata, dict):
        raise CheckpointError(f"checkpoint metadata must be a dict, got {type(metadata).__name__}")
    try:
        user = json.loads(json.dumps(metadata))
    except (TypeError, ValueError) as err:
        raise CheckpointError(f"checkpoint metadata is not JSON-serialisable: {err}") from err
    arrays, entries, treedef = _flatten(state)  # host copies before anything touches the disk
    meta = {"format": FORMAT, "step": step, "metadata": user, "leaves": entries, "treedef": treedef}

    ocp = _ocp()
    manager = _manager(path, create=True)
    try:
        steps = sorted(manager.all_steps())
        if step in steps:
            raise CheckpointError(f"checkpoint step {step} already exists in {_abspath(path)}; "
                                  "existing checkpoints are never overwritten")
        if steps and step < steps[-1]:
            raise CheckpointError(f"checkpoint step {step} is older than the latest step {steps[-1]} "
                                  f"in {_abspath(path)}")
        try:
            saved = manager.save(step, args=ocp.args.Composite(
                **{_STATE: ocp.args.StandardSave(arrays), _META: ocp.args.JsonSave(meta)}))
            manager.wait_until_finished()
        except Exception as err:  # orbax / tensorstore / file-system errors of many kinds
            raise CheckpointError(f"saving checkpoint step {step} in {_abspath(path)} failed "
                                  f"({type(err).__name__}: {err}); earlier checkpoints are "
                                  "untouched") from err
        if not saved:
            raise CheckpointError(f"orbax declined to save checkpoint step {step} in {_abspath(path)}")
    finally:
        manager.close()


def all_steps(path) -> list[int]:
    """Sorted steps of the complete checkpoints in ``path`` ([] if none or no directory)."""
    import os
    if not os.path.isdir(_abspath(path)):
        return []
    manager = _manager(path, create=False)
    try:
        return sorted(int(s) for s in manager.all_steps())
    finally:
        manager.close()


def latest(path) -> int | None:
    """The newest complete checkpoint step in ``path``, or None."""
    steps = all_steps(path)
    return steps[-1] if steps else None


def _json_diff(a, b, prefix: str) -> list[str]:
    """Dotted paths where two JSON values differ, each with both values."""
    if isinstance(a, dict) and isinstance(b, dict):
        out = []
        for k in sorted(set(a) | set(b), key=str):
            p = f"{prefix}.{k}"
            if k not in a:
                out.append(f"{p} (missing in the checkpoint)")
            elif k not in b:
                out.append(f"{p} (only in the checkpoint)")
            else:
                out.extend(_json_diff(a[k], b[k], p))
        return out
    return [] if a == b else [f"{prefix}: checkpoint {a!r}, expected {b!r}"]


def _listing(items: list[str], limit: int = 6) -> str:
    shown = ", ".join(items[:limit])
    return shown + (f", … ({len(items) - limit} more)" if len(items) > limit else "")


def _check_template(meta: dict, template, where: str) -> list:
    """Raise CheckpointError unless ``template`` has the stored structure, shapes and dtypes."""
    pairs, treedef = jax.tree_util.tree_flatten_with_path(template)
    entries = meta["leaves"]
    stored = [e["path"] for e in entries]
    wanted = [jax.tree_util.keystr(p) for p, _ in pairs]
    if stored != wanted:
        only_ckpt = [p for p in stored if p not in set(wanted)]
        only_tmpl = [p for p in wanted if p not in set(stored)]
        detail = []
        if only_ckpt:
            detail.append(f"only in the checkpoint: {_listing(only_ckpt)}")
        if only_tmpl:
            detail.append(f"only in the template: {_listing(only_tmpl)}")
        if not detail:
            detail.append("same leaves in a different order")
        raise CheckpointError(f"{where} has a different tree structure than the template "
                              f"({len(stored)} vs {len(wanted)} leaves; {'; '.join(detail)})")
    if meta.get("treedef") != str(treedef):
        raise CheckpointError(f"{where} has the template's leaf paths but different container "
                              f"types: checkpoint {meta.get('treedef')!s:.300}, template {treedef!s:.300}")
    problems = []
    for entry, (_, leaf) in zip(entries, pairs):
        shape, dtype, key_dtype = _leaf_spec(leaf)
        if key_dtype != entry["key_dtype"]:
            problems.append(f"{entry['path']}: key type {entry['key_dtype'] or 'none (plain array)'} "
                            f"in the checkpoint, {key_dtype or 'none (plain array)'} in the template")
        elif list(shape) != entry["shape"] or dtype != entry["dtype"]:
            problems.append(f"{entry['path']}: checkpoint {tuple(entry['shape'])} {entry['dtype']}, "
                            f"template {shape} {dtype}")
    if problems:
        raise CheckpointError(f"{where} does not match the template's shapes/dtypes: {_listing(problems)}")
    return [leaf for _, leaf in pairs]


def _rebuild(entry: dict, arr: np.ndarray, leaf):
    """The restored leaf in the template leaf's kind (typed key, jax array, numpy, Python scalar)."""
    if entry["key_dtype"] is not None:
        return jax.random.wrap_key_data(jnp.asarray(arr), impl=entry["key_impl"])
    if isinstance(leaf, (jax.Array, jax.ShapeDtypeStruct)):
        return jnp.asarray(arr, dtype=arr.dtype)
    if isinstance(leaf, (bool, int, float, complex)):
        return type(leaf)(arr.item())
    if isinstance(leaf, np.generic):
        return arr[()]
    return arr


def _quiet_closed_event_loop() -> None:
    """After a failed read, tensorstore still delivers callbacks to the asyncio loop that orbax
    has already closed; each would print a "RuntimeError: Event loop is closed" traceback on
    stderr beside the one clear CorruptCheckpointError. Drop exactly those (every other
    unraisable exception still reaches the current hook). Installed before every array read:
    installed after the failure, the first callbacks could come before it (seen on a loaded
    2-core machine)."""
    hook = sys.unraisablehook
    if getattr(hook, "_gmr_jax_quiet", False):
        return

    def quiet(unraisable):
        exc = unraisable.exc_value
        if isinstance(exc, RuntimeError) and str(exc) == "Event loop is closed":
            return
        hook(unraisable)
    quiet._gmr_jax_quiet = True
    sys.unraisablehook = quiet


class _OrphanedTaskFilter(logging.Filter):
    """Drops asyncio's "Task exception was never retrieved" records: after a failed read, the
    read's other tasks fail too and are collected unawaited, each logging a traceback of the
    same corruption."""

    def filter(self, record: logging.LogRecord) -> bool:
        return not str(record.msg).startswith("Task exception was never retrieved")


def _quiet_orphaned_read_tasks() -> None:
    """Installs :class:`_OrphanedTaskFilter` on the asyncio logger (once), after a failed read:
    the one CorruptCheckpointError says what happened."""
    log = logging.getLogger("asyncio")
    if not any(isinstance(f, _OrphanedTaskFilter) for f in log.filters):
        log.addFilter(_OrphanedTaskFilter())


def _read_meta(manager, step: int, where: str, hint: str) -> dict:
    """The stored manifest and metadata of ``step`` (CorruptCheckpointError if unreadable)."""
    ocp = _ocp()
    try:
        meta = manager.restore(step, args=ocp.args.Composite(**{_META: ocp.args.JsonRestore()}))[_META]
    except Exception as err:
        raise CorruptCheckpointError(f"{where} is corrupt: its metadata cannot be read "
                                     f"({type(err).__name__}: {err}){hint}") from err
    if not isinstance(meta, dict) or meta.get("format") != FORMAT or not isinstance(meta.get("leaves"), list):
        raise CorruptCheckpointError(f"{where} is corrupt or not a {FORMAT} checkpoint: bad metadata{hint}")
    return meta


def read_metadata(path, step: int | None = None) -> dict:
    """The metadata given to ``save`` for checkpoint ``step`` (default: the latest), without
    reading the arrays.

    Raises:
      CheckpointError: no such checkpoint. CorruptCheckpointError: unreadable metadata.
    """
    steps = all_steps(path)
    if not steps:
        raise CheckpointError(f"no checkpoint found in {_abspath(path)}")
    step = steps[-1] if step is None else step
    if step not in steps:
        raise CheckpointError(f"checkpoint step {step} not found in {_abspath(path)}; available steps: {steps}")
    manager = _manager(path, create=False)
    try:
        return _read_meta(manager, step, f"checkpoint step {step} in {_abspath(path)}", "").get("metadata", {})
    finally:
        manager.close()


def restore(path, template, step: int | None = None, expect: dict | None = None,
            fill: dict | None = None) -> tuple[Any, dict]:
    """Read checkpoint ``step`` (default: the latest) into the structure of ``template``.

    Args:
      path: checkpoint directory.
      template: a pytree like the saved state (concrete arrays or ``jax.ShapeDtypeStruct``); its
        tree structure, leaf shapes, dtypes and PRNG-key types must match the checkpoint.
      step: the step to read; None → the latest.
      expect: optional dict; each of its entries must equal the same entry of the stored
        metadata (compared as JSON, e.g. ``{"config": config.to_dict(cfg)}``).
      fill: optional {name: function}: the stored entry ``name`` passes through the function
        before the comparison (e.g. to give a configuration written before a field existed that
        field's default).
    Returns:
      (state, metadata): the state in the template's structure (jax arrays where the template
      has jax arrays) and the metadata dict given to ``save``.
    Raises:
      CheckpointError: no checkpoint, unknown step, corrupt files, failed checksum, different
        structure / shapes / dtypes / key types, or metadata differing from ``expect``.
    """
    steps = all_steps(path)
    where_dir = _abspath(path)
    if not steps:
        raise CheckpointError(f"no checkpoint found in {where_dir}")
    if step is None:
        step = steps[-1]
    if step not in steps:
        raise CheckpointError(f"checkpoint step {step} not found in {where_dir}; available steps: {steps}")
    where = f"checkpoint step {step} in {where_dir}"
    others = [s for s in steps if s != step]
    hint = f" (other steps available: {others})" if others else ""

    ocp = _ocp()
    manager = _manager(path, create=False)
    try:
        meta = _read_meta(manager, step, where, hint)
        leaves = _check_template(meta, template, where)
        if expect:
            stored = meta.get("metadata", {})
            diffs = []
            for name, value in expect.items():
                wanted = json.loads(json.dumps(value))
                if name not in stored:
                    diffs.append(f"{name} (missing in the checkpoint)")
                else:
                    have = stored[name] if name not in (fill or {}) else json.loads(json.dumps(fill[name](stored[name])))
                    diffs.extend(_json_diff(have, wanted, str(name)))
            if diffs:
                raise CheckpointError(f"{where} was written with different settings: {_listing(diffs)}")

        entries = meta["leaves"]
        targets = {_leaf_name(i): np.zeros(e["shape"], np.dtype(e["dtype"]))
                   for i, e in enumerate(entries) if int(np.prod(e["shape"]))}
        if targets:
            # before the read: a failing read's late callbacks can arrive before its exception
            _quiet_closed_event_loop()
            try:
                arrays = manager.restore(step, args=ocp.args.Composite(
                    **{_STATE: ocp.args.StandardRestore(targets)}))[_STATE]
            except Exception as err:
                _quiet_orphaned_read_tasks()
                raise CorruptCheckpointError(f"{where} is corrupt: its arrays cannot be read "
                                      f"({type(err).__name__}: {err}){hint}") from err
        else:
            arrays = {}
    finally:
        manager.close()

    out, bad = [], []
    for i, (entry, leaf) in enumerate(zip(entries, leaves)):
        name = _leaf_name(i)
        arr = (np.asarray(arrays[name]) if name in arrays
               else np.zeros(entry["shape"], np.dtype(entry["dtype"])))
        if list(arr.shape) != entry["shape"] or arr.dtype.name != entry["dtype"] \
                or _sha256(arr) != entry["sha256"]:
            bad.append(entry["path"])
            continue
        out.append(_rebuild(entry, arr, leaf))
    if bad:
        raise CorruptCheckpointError(f"{where} is corrupt: data of {_listing(bad)} does not match the "
                              f"stored checksum{hint}")
    treedef = jax.tree_util.tree_structure(template)
    return jax.tree_util.tree_unflatten(treedef, out), meta.get("metadata", {})


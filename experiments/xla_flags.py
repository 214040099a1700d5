"""XLA's GPU flags for the command line, set in ``XLA_FLAGS`` before JAX is imported.

XLA reads ``XLA_FLAGS`` once per process. With JAX's CUDA plugin that happens while ``import
jax`` loads the plugin, so a flag added to the environment after the import never reaches the
GPU compiler (measured on an H100, jax 0.11.2: autotuning ran, and two cold runs differed,
whatever ``XLA_FLAGS`` said by then; benchmarks/RESULTS.md). This module imports nothing of
JAX; ``experiments/__init__.py`` (and ``benchmarks/__init__.py``, through it) calls
``set_before_jax`` with the command's arguments, so that every ``python -m experiments.…`` and
``python -m benchmarks.…`` starts JAX with them.
"""

from __future__ import annotations

import os
import sys

# The flags that ``set_before_jax`` added while JAX was already imported (too late for a GPU).
added_after_jax = ""

AUTOTUNE_OFF = "--xla_gpu_autotune_level=0"
DETERMINISTIC = "--xla_gpu_deterministic_ops=true"


def with_cli_flags(flags: str, autotune: bool = False, deterministic: bool = True) -> str:
    """``flags`` (an XLA_FLAGS string) with the CLI's GPU flags added; a flag it already names wins.

    autotune=False turns GPU autotuning off (kernels chosen by timing differ from compile to
    compile, and more so while other runs train beside the compiler); deterministic=True makes
    XLA's GPU scatters and reductions deterministic (without it, atomics make repeated runs
    differ).
    """
    if not autotune and "xla_gpu_autotune_level" not in flags:
        flags = f"{flags} {AUTOTUNE_OFF}"
    if deterministic and "xla_gpu_deterministic_ops" not in flags:
        flags = f"{flags} {DETERMINISTIC}"
    return flags.strip()


def _given(argv: list[str], option: str) -> bool:
    """Whether ``argv`` names the store-true ``option`` (or an abbreviation, as argparse allows)."""
    return any(len(a) > 3 and option.startswith(a) for a in argv if a.startswith("--"))


def set_before_jax(argv: list[str]) -> str:
    """Put the CLI's GPU flags for the command-line arguments ``argv`` (``--autotune``,
    ``--nondeterministic``) into ``XLA_FLAGS``; returns the new value. Call before ``import jax``."""
    global added_after_jax
    before = os.environ.get("XLA_FLAGS", "").strip()
    flags = with_cli_flags(before, autotune=_given(argv, "--autotune"),
                           deterministic=not _given(argv, "--nondeterministic"))
    if flags != before and "jax" in sys.modules:
        added_after_jax = f"{added_after_jax} {flags[len(before):]}".strip()
    os.environ["XLA_FLAGS"] = flags
    return flags

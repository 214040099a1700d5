"""Releasing JAX's compiled programs between test modules while keeping its tracing caches."""

import re

import jax

# JAX's in-memory caches that hold compiled programs, by the name of the function each one caches
# (jax 0.10: ``jax._src.util`` registers every cache with its function). Lowering keeps a
# reference to the executable it compiles; an eager operation's program is
# ``xla_primitive_callable``'s.
COMPILED_PROGRAM_CACHES = frozenset({"_pjit_lower", "_cached_lowering_to_hlo", "_cached_compilation",
                                     "xla_primitive_callable"})


def _compiled_program_caches() -> list | None:
    """The registered caches named in COMPILED_PROGRAM_CACHES, or None where this JAX lacks one of
    them (another version: then only ``jax.clear_caches`` is safe)."""
    try:
        from jax._src import util  # noqa: PLC0415 (private: JAX has no public way to clear only these)
    except ImportError:
        return None
    found = {}
    for cache, what in list(getattr(util, "_caches", {}).items()):
        name = re.match(r"<function (\S+) at ", str(what))
        if name and name.group(1) in COMPILED_PROGRAM_CACHES:
            found.setdefault(name.group(1), []).append(cache)
    if set(found) != COMPILED_PROGRAM_CACHES:
        return None
    return [cache for caches in found.values() for cache in caches]


def release_compiled_programs() -> bool:
    """Drop every compiled program JAX holds in memory (jitted functions' executables, eager
    operations' programs) but keep the jaxprs it has traced; returns False where it fell back to
    ``jax.clear_caches()``, which drops both.

    ``jax.clear_caches()`` also empties the tracing caches of JAX's own functions and of ours
    (``jnp``'s jitted helpers, abstract evaluation, the traced library stages), so the next
    module traces everything cold again: lowering one MJX rollout took 6.7 s after it against
    0.6 s warm on a 2-core AMD EPYC (benchmarks/RESULTS.md, fiftieth session).
    """
    caches = _compiled_program_caches()
    try:
        from jax._src import pjit  # noqa: PLC0415
        from jax._src.lib import _jax  # noqa: PLC0415
    except ImportError:
        caches = None
    if caches is None:
        jax.clear_caches()
        return False
    for cache in caches:
        cache.cache_clear()
    # the C++ fast paths of jitted functions hold their executables too (as jax.clear_caches)
    pjit._cpp_pjit_cache_fun_only.clear()
    pjit._cpp_pjit_cache_explicit_attributes.clear()
    _jax.PjitFunctionCache.clear_all()
    return True

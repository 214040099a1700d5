"""tests/jax_caches.py: the conftest's release of compiled programs between modules drops the
executables and keeps the traced jaxprs (jax.clear_caches drops both)."""

import gc
import weakref

import jax
import jax.numpy as jnp
import numpy as np

from jax_caches import release_compiled_programs


def test_release_drops_executables_and_keeps_traces():
    traces = []

    def f(x):
        traces.append(None)
        return jnp.sin(x) * 2.0

    x = jnp.arange(3.0)
    g = jax.jit(f)
    want = np.asarray(g(x))
    executable = weakref.ref(g.lower(x).compile()._executable)
    assert executable() is not None and len(traces) == 1
    assert release_compiled_programs()  # this JAX has the caches named in jax_caches.py
    gc.collect()
    assert executable() is None  # no cache holds the compiled program any more
    np.testing.assert_array_equal(np.asarray(g(x)), want)
    assert len(traces) == 1  # compiled again from the kept jaxpr, not traced again
    jax.clear_caches()
    np.testing.assert_array_equal(np.asarray(g(x)), want)
    assert len(traces) == 2  # what the conftest avoids: jax.clear_caches traces again

"""The training program's scatters.

With ``--xla_gpu_deterministic_ops=true`` (the CLI's and the benchmarks' default) XLA rewrites
every scatter that may repeat an index (no ``unique_indices``, a floating-point or overwriting
combiner) into a form that sorts its indices: many more kernels to compile. The library gathers
where it can and marks its scatters with static or distinct indices ``unique_indices=True``
(benchmarks/RESULTS.md, forty-eighth session; the CUDA S-step's path is tested in
tests/test_gmr_cuda.py). MJX's own scatters (its tree scans' ``segment_sum``) remain; with the
C MuJoCo plant the program has none."""

import jax
import pytest

from gmr_jax import config, mdgps
from jaxprs import scatters_that_may_repeat_an_index


@pytest.mark.parametrize("task, scenario, algorithm",
                         [("reach", "AB", "gmr"), ("reach", "AB", "mdgps"), ("block_in_hole", "CD", "gmr")])
def test_train_has_no_scatter_that_may_repeat_an_index(task, scenario, algorithm):
    """``mdgps.train`` with the C MuJoCo plant, as traced: every scatter is marked unique."""
    cfg = config.make(task, scenario, algorithm, sim__backend="mujoco")
    with jax.default_matmul_precision(mdgps.MATMUL_PRECISION):
        jaxpr = jax.make_jaxpr(lambda key: mdgps.train(cfg, key))(jax.random.PRNGKey(0))
    assert scatters_that_may_repeat_an_index(jaxpr.jaxpr) == []

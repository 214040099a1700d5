"""The training program's scatters.

With ``--xla_gpu_deterministic_ops=true`` (the CLI's and the benchmarks' default) XLA rewrites
every scatter that may repeat an index (no ``unique_indices``, a floating-point or overwriting
combiner) into a form that sorts its indices: many more kernels to compile. The library gathers
where it can and marks its scatters with static or distinct indices ``unique_indices=True``; the
256-seed GMR program with the CUDA S-step compiled in 31 s instead of 43 s on an H200 once its
scatters were gone (benchmarks/RESULTS.md, forty-eighth session). MJX's own scatters (its tree
scans' ``segment_sum``) remain; with the C MuJoCo plant the program has none.
"""

import jax
import jax.extend.core
import pytest
from jax._src import source_info_util

from gmr_jax import config, mdgps


def _scatters_that_may_repeat_an_index(jaxpr) -> list[str]:
    """'file:line' of every scatter without ``unique_indices`` in a jaxpr and its sub-jaxprs."""
    found = []
    for eqn in jaxpr.eqns:
        if eqn.primitive.name.startswith("scatter") and not eqn.params.get("unique_indices", False):
            frame = source_info_util.user_frame(eqn.source_info.traceback)
            found.append(f"{frame.file_name}:{frame.start_line}" if frame else eqn.primitive.name)
        for sub in jax.extend.core.jaxprs_in_params(eqn.params):
            found += _scatters_that_may_repeat_an_index(sub)
    return found


@pytest.mark.parametrize("task, scenario, algorithm",
                         [("reach", "AB", "gmr"), ("reach", "AB", "mdgps"), ("block_in_hole", "CD", "gmr")])
def test_train_has_no_scatter_that_may_repeat_an_index(task, scenario, algorithm):
    """``mdgps.train`` with the C MuJoCo plant, as traced: every scatter is marked unique."""
    cfg = config.make(task, scenario, algorithm, sim__backend="mujoco")
    with jax.default_matmul_precision(mdgps.MATMUL_PRECISION):
        jaxpr = jax.make_jaxpr(lambda key: mdgps.train(cfg, key))(jax.random.PRNGKey(0))
    assert _scatters_that_may_repeat_an_index(jaxpr.jaxpr) == []

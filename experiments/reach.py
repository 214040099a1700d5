"""The reaching study on the simulated Jaco 2: ``python -m experiments.reach``.

Trains the chosen algorithms on the chosen scenarios (paper: A and A,B) for several seeds in
parallel (``jax.vmap`` over PRNG keys), one jitted iteration at a time so that progress is shown
and the whole training state is checkpointed after every iteration (``--resume`` continues an
interrupted run and reaches the same result as an uninterrupted one). Evaluates every policy
from the 50 fixed random initial states and the disturbance sweep. Writes into ``--out``:
``config.json``, ``results.json``, ``summary.md``, ``learning_curves.png``, ``paths.png``,
``robustness.png`` and, per run, ``<scenario>_<algorithm>/checkpoints/``.
"""

from __future__ import annotations

import time

_T_START = time.perf_counter()  # before the heavy imports: the command's total wall time

import sys  # noqa: E402

if __name__ == "__main__":
    # the server that the runs' processes fork from imports JAX while this process does
    from gmr_jax import process_server, timeline  # noqa: E402 (import no JAX)

    timeline.mark("command start", at=time.time() - (time.perf_counter() - _T_START))
    process_server.start_where_a_gpu_is(sys.argv[1:])

from experiments import cli  # noqa: E402


def main(argv=None) -> int:
    return cli.main("reach", argv, description=__doc__, t_start=_T_START)


if __name__ == "__main__":
    sys.exit(main())

"""The block-in-hole study on the simulated Jaco 2: ``python -m experiments.block_in_hole``.

The paper's contact-rich task (scenarios C and C,D; real robot only in the paper) in simulation:
the arm presses a block it holds rigidly into a hole with a light press fit
(``jaco_mjcf/block_in_hole.xml``, ``gmr_jax/tasks/block_in_hole.py``). Trains the chosen
algorithms on the chosen scenarios for several seeds in parallel, checkpointing after every
iteration (``--resume``), evaluates every policy from 50 fixed collision-free random initial
states and the disturbance sweep, and writes into ``--out`` what the reach study writes
(``config.json``, ``results.json``, ``summary.md`` with the paper's rows C and C,D, figures,
per-run checkpoints). Success is the paper's final-state MSE; how many runs end with the block
inserted (the tip inside the hole, at least 90 % of its depth below the rim) is reported beside it.
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
    return cli.main("block_in_hole", argv, description=__doc__, t_start=_T_START)


if __name__ == "__main__":
    sys.exit(main())

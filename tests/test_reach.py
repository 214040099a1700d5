"""The reach CLI's own logic (no training): argument checks, backend choice, tracing order."""

import threading
import time

import numpy as np
import pytest

from experiments import reach
from gmr_jax import checkpoint


def test_bad_arguments_are_named():
    for argv, needle in ((["--scenario", "C"], "--scenario 'C'"), (["--algorithm", "ppo"], "--algorithm 'ppo'"),
                         (["--seeds", "0"], "--seeds must be a positive integer"),
                         (["--samples", "1"], "at least 2"), (["--jobs", "-1"], "--jobs"),
                         (["--compile-jobs", "0"], "--compile-jobs"),
                         (["--set", "novalue"], "GROUP__FIELD=VALUE")):
        with pytest.raises(SystemExit):
            reach.parse_args(argv)


def test_bad_argument_message(capsys):
    with pytest.raises(SystemExit):
        reach.parse_args(["--scenario", "A,C"])
    assert "--scenario 'C'" in capsys.readouterr().err


def test_auto_backend_on_a_cpu_is_c_mujoco():
    args = reach.parse_args(["--seeds", "100"])
    assert reach.resolve_backend(args) == "mujoco"  # the test machine has no GPU
    assert reach.resolve_backend(reach.parse_args(["--backend", "mjx"])) == "mjx"


def test_tracing_turns_follow_the_tickets():
    """Runs trace one at a time in ticket order, whatever order their threads arrive in."""
    turns = reach._TracingTurns()
    entered, inside = [], []

    def run(ticket, delay):
        time.sleep(delay)
        with turns(ticket):
            inside.append(ticket)
            assert len(inside) == 1  # nobody else is tracing
            entered.append(ticket)
            time.sleep(0.01)
            inside.remove(ticket)

    threads = [threading.Thread(target=run, args=(t, d)) for t, d in ((2, 0.0), (0, 0.05), (1, 0.0), (3, 0.02))]
    for th in threads:
        th.start()
    for th in threads:
        th.join(timeout=10)
    assert entered == [0, 1, 2, 3]
    # an exception inside a turn still passes the turn on
    turns.reset()
    with pytest.raises(RuntimeError):
        with turns(0):
            raise RuntimeError("trace failed")
    with turns(1):
        pass


def test_fresh_run_into_a_folder_with_checkpoints_is_refused(tmp_path, capsys):
    """Without --resume, an --out that holds a run's checkpoints is refused before anything is
    written: the earlier run's config.json and checkpoints stay as they were."""
    ckpt = reach.run_folder(tmp_path, "A", "lqr") / "checkpoints"
    checkpoint.save(ckpt, {"x": np.zeros(2)}, step=1)
    (tmp_path / "config.json").write_text("earlier run")
    assert reach.main(["--out", str(tmp_path), "--scenario", "A", "--algorithm", "lqr"]) == 2
    err = capsys.readouterr().err
    assert "already holds checkpoints" in err and str(ckpt) in err and "--resume" in err
    assert (tmp_path / "config.json").read_text() == "earlier run"
    assert checkpoint.latest(ckpt) == 1

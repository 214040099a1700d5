"""benchmarks.adam_cost: its Adam loop ends where optax's does, and the command's output."""

import json

import jax.numpy as jnp
import numpy as np
import optax
import pytest

from benchmarks import adam_cost
from gmr_jax.config import SStepConfig


def test_the_adam_form_ends_where_optax_does():
    cfg, entries, steps = SStepConfig(), 7, 20
    theta0 = np.linspace(-1.0, 2.0, entries)
    got = np.asarray(adam_cost.update_loop("adam", steps, cfg)(jnp.asarray(theta0))[0])
    opt = optax.adam(cfg.lr, b1=cfg.b1, b2=cfg.b2, eps=cfg.eps)
    theta = jnp.asarray(theta0)
    state = opt.init(theta)
    for _ in range(steps):
        updates, state = opt.update(1e-3 * theta + 1e-4, state, theta)
        theta = optax.apply_updates(theta, updates)
    # Both are the same operations; the codegens may round each of the ~10 operations per entry
    # and step differently (1 ulp each), and Adam's steps do not amplify that.
    bound = 10 * steps * np.finfo(np.float64).eps * np.max(np.abs(theta0))
    np.testing.assert_allclose(got, np.asarray(theta), rtol=0, atol=bound)


def test_the_loop_without_divisions_keeps_its_moments():
    # All three vectors stay in the loop: the compiled loop carries three [n] arrays.
    theta = jnp.ones(5)
    text = adam_cost.update_loop("no_division", 3).lower(theta).compile().as_text()
    loops = [line for line in text.splitlines() if " while(" in line]
    assert len(loops) == 1 and loops[0].count("f64[5]") == 3, loops


def test_the_command_writes_both_forms(tmp_path, capsys):
    out = tmp_path / "adam.json"
    assert adam_cost.main(["--entries", "64", "--steps", "10", "--repeats", "1", "--out", str(out)]) == 0
    rows = json.loads(out.read_text())["us_per_step"]
    assert set(rows) == set(adam_cost.FORMS) and all(v > 0 for v in rows.values())
    assert "divisions and square root" in capsys.readouterr().out


def test_bad_arguments_get_one_line(tmp_path, capsys):
    with pytest.raises(SystemExit):
        adam_cost.main(["--steps", "0"])
    assert "--steps: must be a positive integer, got '0'" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        adam_cost.main(["--out", str(tmp_path / "missing" / "a.json")])
    assert "its folder does not exist" in capsys.readouterr().err
    with pytest.raises(ValueError, match="form 'sgd'"):
        adam_cost.update_loop("sgd", 4)

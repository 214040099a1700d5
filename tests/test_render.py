"""gmr_jax.render and experiments.video: frames of different states differ, a video reads back
with the frames written, the grid is a PNG, and a machine that cannot render gets one line."""

import numpy as np
import pytest

from gmr_jax import config, render, tasks

REASON = render.available()
needs_gl = pytest.mark.skipif(REASON is not None, reason=f"no offscreen rendering here: {REASON}")


@pytest.fixture(scope="module")
def reach_frames():
    cfg = config.reach("A", "gmr")
    x0 = np.asarray(tasks.initial_states(cfg.task))[0]
    xt = np.asarray(tasks.target_state(cfg.task))
    X = np.linspace(x0, xt, 6)
    return cfg, X, render.frames(cfg.sim, X, width=96, height=72)


@needs_gl
def test_frames_show_the_arm_moving(reach_frames):
    _, X, fr = reach_frames
    assert fr.shape == (6, 72, 96, 3) and fr.dtype == np.uint8
    moved = np.abs(fr[0].astype(int) - fr[-1].astype(int)).mean()
    assert moved > 1.0  # the arm is drawn where the joint states put it
    again = render.frames(config.reach("A", "gmr").sim, X[:1], width=96, height=72)
    np.testing.assert_array_equal(again[0], fr[0])  # deterministic


@needs_gl
def test_video_reads_back_and_grid_is_a_png(reach_frames, tmp_path):
    iio = pytest.importorskip("imageio.v2")
    _, X, fr = reach_frames
    path = render.write_video(tmp_path / "v.mp4", fr)
    back = np.stack(iio.mimread(path))
    assert back.shape == fr.shape
    # H.264 is lossy: the frames agree on average to a few grey levels of 255
    assert np.abs(back.astype(int) - fr.astype(int)).mean() < 8.0
    steps = render.grid_times(80)
    assert steps[0] == 0 and steps[-1] == 79 and len(steps) == render.GRID_COLUMNS
    png = render.grid_png(tmp_path / "g.png", [("row", fr, np.arange(6))], title="t")
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_no_rendering_is_one_line(monkeypatch, tmp_path, capsys):
    from experiments import cli

    monkeypatch.setattr(render, "available", lambda: "MuJoCo cannot render here (test)")
    args = type("Args", (), {"no_plots": False, "video": True,
                             "configs": {("A", "gmr"): config.reach("A", "gmr")}})()
    cli.write_pictures(args, tmp_path)  # returns: the study's results stand without pictures
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["No rollout pictures: MuJoCo cannot render here (test)"]

"""Pictures of rollouts: frames from MuJoCo's offscreen renderer, MP4 videos, still-frame grids.

MuJoCo chooses its OpenGL backend from ``MUJOCO_GL`` when it is first imported: ``egl`` on a
machine without a display (a GPU's EGL, or Mesa's software EGL on a CPU), ``osmesa`` where only
OSMesa exists. ``experiments`` sets ``egl`` by default on Linux; set the variable yourself before
importing ``gmr_jax`` in your own scripts. :func:`available` says whether rendering works here,
and why not.

Videos are written with imageio's ffmpeg plugin (``pip install 'gmr-jax[video]'``).
"""

from __future__ import annotations

import functools
import os
import pathlib

import mujoco
import numpy as np

from gmr_jax import sim as sim_lib
from gmr_jax.config import SimConfig

WIDTH, HEIGHT = 320, 240
FPS = 20  # one frame per control step (50 ms), so a video plays in real time


class RenderingUnavailable(RuntimeError):
    """MuJoCo cannot render here (no OpenGL context, or no video writer)."""


@functools.lru_cache(maxsize=None)
def available() -> str | None:
    """None if MuJoCo can render offscreen here, else one line saying why not and what to do."""
    try:
        model = mujoco.MjModel.from_xml_string("<mujoco><worldbody><geom size='1'/></worldbody></mujoco>")
        with mujoco.Renderer(model, 8, 8) as r:
            r.render()
    except Exception as err:  # any GL failure means: no pictures here
        first = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
        return (f"MuJoCo cannot render here (MUJOCO_GL={os.environ.get('MUJOCO_GL', '')!r}: {first}); "
                "set MUJOCO_GL=egl (GPU or Mesa) or osmesa before the first import of mujoco")
    return None


def _camera(model: mujoco.MjModel) -> mujoco.MjvCamera:
    """A free camera from the front and above, framing the arm's workspace (base at the origin,
    reach about 0.7 m)."""
    cam = mujoco.MjvCamera()
    mujoco.mjv_defaultFreeCamera(model, cam)
    cam.lookat[:] = (-0.15, -0.15, 0.3)
    cam.distance, cam.azimuth, cam.elevation = 1.1, 45.0, -20.0
    return cam


def _scene_option() -> mujoco.MjvOption:
    """Every geom group visible (the arm's collision capsules are in group 3)."""
    opt = mujoco.MjvOption()
    opt.geomgroup[:] = 1
    return opt


def frames(sim_config: SimConfig, X: np.ndarray, width: int = WIDTH, height: int = HEIGHT) -> np.ndarray:
    """Render the joint states of a trajectory.

    Args:
      sim_config: the run's plant (its scene).
      X: [T, dX] states [q, q̇] (only q is drawn).
    Returns:
      [T, height, width, 3] uint8 frames.
    Raises:
      RenderingUnavailable: with :func:`available`'s reason.
    """
    reason = available()
    if reason is not None:
        raise RenderingUnavailable(reason)
    s = sim_lib.make_sim(sim_config)
    model = s.model
    data = mujoco.MjData(model)
    cam, opt = _camera(model), _scene_option()
    X = np.asarray(X, np.float64)
    out = np.empty((X.shape[0], height, width, 3), np.uint8)
    with mujoco.Renderer(model, height, width) as r:
        for t, x in enumerate(X):
            data.qpos[: s.nq] = x[: s.nq]
            mujoco.mj_forward(model, data)
            r.update_scene(data, camera=cam, scene_option=opt)
            out[t] = r.render()
    return out


def write_video(path, frames_: np.ndarray, fps: int = FPS) -> pathlib.Path:
    """Write [T, H, W, 3] uint8 frames as an H.264 MP4 (imageio's ffmpeg plugin)."""
    try:
        import imageio.v2 as imageio
    except ImportError as err:
        raise RenderingUnavailable(f"no video writer ({err}); pip install 'gmr-jax[video]'") from err
    path = pathlib.Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    try:
        imageio.mimwrite(path, list(frames_), fps=fps, codec="libx264", macro_block_size=1,
                         pixelformat="yuv420p")
    except (ImportError, RuntimeError, OSError) as err:  # no ffmpeg backend or binary
        raise RenderingUnavailable(f"cannot write {path.name}: {str(err).splitlines()[0]}; "
                                   "pip install 'gmr-jax[video]'") from err
    return path


GRID_COLUMNS = 6


def grid_times(T: int, columns: int = GRID_COLUMNS) -> np.ndarray:
    """[columns] control steps of a still-frame grid: evenly spaced from the first to the last."""
    return np.linspace(0, T - 1, columns).round().astype(int)


def grid_png(path, rows: list[tuple[str, np.ndarray, np.ndarray]], title: str = "") -> pathlib.Path:
    """A still-frame grid written as a PNG (matplotlib): one row per (label, frames [C, H, W, 3],
    their control steps [C]), e.g. the frames at :func:`grid_times`."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    columns = max(fr.shape[0] for _, fr, _ in rows)
    height = 1.6 * len(rows) + 0.4
    fig, axes = plt.subplots(len(rows), columns, figsize=(2.0 * columns, height), squeeze=False)
    for (label, fr, steps), ax_row in zip(rows, axes):
        for j, ax in enumerate(ax_row):
            ax.set_xticks([])
            ax.set_yticks([])
            if j >= fr.shape[0]:
                ax.set_axis_off()
                continue
            ax.imshow(fr[j])
            if j == 0:
                ax.set_ylabel(label, fontsize=7)
            ax.set_title(f"t = {steps[j] / FPS:.2f} s", fontsize=7)
    if title:
        fig.suptitle(title, fontsize=9)
    fig.tight_layout(rect=(0, 0, 1, 1 - 0.4 / height))  # the top 0.4 in for the title
    path = pathlib.Path(path)
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path

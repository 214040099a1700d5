"""A wheel that works outside the checkout: the arm's MJCF files ship inside the package.

Builds the wheel with the environment's setuptools (the ``test`` extra installs setuptools ≥ 68
and wheel), installs it into a temporary folder, and loads the reach scene from another folder
in a fresh interpreter that sees the wheel, not the checkout.
"""

import os
import pathlib
import shutil
import site
import subprocess
import sys
import zipfile

REPO = pathlib.Path(__file__).resolve().parent.parent

# Run in the fresh interpreter: gmr_jax and the MJCF folder it uses must both come from the
# installed wheel (argv[1]), and the reach scene must load.
_LOAD = r"""
import pathlib, sys
root = pathlib.Path(sys.argv[1]).resolve()
import gmr_jax
from gmr_jax import config, sim
assert pathlib.Path(gmr_jax.__file__).resolve().is_relative_to(root), f"gmr_jax from {gmr_jax.__file__}"
assert sim.MJCF_DIR.is_relative_to(root), f"MJCF from {sim.MJCF_DIR}"
s = sim.make_sim(config.reach("A", "lqr").sim)
assert s.model.nu == 6, s.model.nu
print("LOADED", sim.MJCF_DIR)
"""


def _run(cmd, **kw):
    out = subprocess.run(cmd, capture_output=True, text=True, timeout=120, **kw)
    assert out.returncode == 0, f"{' '.join(map(str, cmd))} failed:\n{out.stdout}\n{out.stderr}"
    return out.stdout


def test_wheel_ships_the_mjcf_and_loads_the_reach_scene(tmp_path):
    # Build from a copy of the repository: an in-tree build writes build/ and *.egg-info into the
    # checkout, and setuptools packs whatever an earlier build left in build/lib.
    src = tmp_path / "src"
    shutil.copytree(REPO, src, ignore=shutil.ignore_patterns(
        ".git", ".venv", "build", "results", "docs", "*.egg-info", "__pycache__", ".pytest_cache", ".jax_cache"))
    dist = tmp_path / "dist"
    _run([sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", "--no-index", "--no-build-isolation",
          "-w", str(dist), "."], cwd=src)
    (wheel,) = dist.glob("gmr_jax-*.whl")

    names = set(zipfile.ZipFile(wheel).namelist())
    xmls = sorted(p.name for p in (REPO / "jaco_mjcf").glob("*.xml"))
    assert xmls, "no MJCF files in jaco_mjcf/"
    missing = [x for x in xmls if f"gmr_jax/jaco_mjcf/{x}" not in names]
    assert not missing, f"MJCF files missing from the wheel: {missing}"
    # the CUDA S-step's source, which gmr_cuda builds with nvcc on first use
    assert "gmr_jax/policies/gmr_cuda.cu" in names
    # pyproject.toml lists the packages (a mapped package cannot come from packages.find): every
    # package of the repository must be in the wheel.
    packages = [p.parent.relative_to(REPO).as_posix() for top in ("gmr_jax", "experiments")
                for p in (REPO / top).rglob("__init__.py")]
    missing = [p for p in packages if f"{p}/__init__.py" not in names]
    assert not missing, f"packages missing from the wheel (add them to pyproject.toml): {missing}"

    target = tmp_path / "installed"
    _run([sys.executable, "-m", "pip", "install", "-q", "--no-deps", "--no-index", "--target", str(target),
          str(wheel)])

    # The environment's site-packages holds the editable install of this checkout: a .pth file
    # that puts an import hook for gmr_jax on sys.meta_path. `python -S` skips the site module, so
    # no .pth file runs; PYTHONPATH then names the wheel's folder first and site-packages (jax,
    # mujoco, …) after it. The script checks where gmr_jax and its MJCF came from, so a
    # checkout that shadowed the wheel would fail, not pass.
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "GMR_JAX_MJCF_DIR")}
    env["PYTHONPATH"] = os.pathsep.join([str(target), *site.getsitepackages()])
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    out = _run([sys.executable, "-S", "-c", _LOAD, str(target)], cwd=elsewhere, env=env)
    assert "LOADED" in out

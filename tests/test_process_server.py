"""The server that runs in processes of their own fork from (gmr_jax.process_server): it imports
without JAX, and the command starts it early only where a GPU may be found."""

import os
import subprocess
import sys

from gmr_jax import process_server


def test_the_module_imports_without_jax():
    """A command can start the server before it imports JAX: the module (and the package's
    ``__init__``) import none of it; the package's ``types`` still loads when first used."""
    code = ("import sys, gmr_jax.process_server, gmr_jax.mps; assert 'jax' not in sys.modules, 'jax imported'; "
            "import gmr_jax; gmr_jax.types.LinearGaussianPolicy; assert 'jax' in sys.modules")
    subprocess.run([sys.executable, "-c", code], check=True, env={**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)})


def test_the_server_starts_early_only_where_a_gpu_may_be_found(tmp_path, monkeypatch):
    """``gpu_present``: a GPU's device file, ``JAX_PLATFORMS`` unset or naming CUDA and
    ``CUDA_VISIBLE_DEVICES`` not empty or -1; ``start_where_a_gpu_is`` starts the server exactly
    then, unless the command is asked for its help."""
    started = []
    monkeypatch.setattr(process_server, "start", lambda: started.append(True))
    for name in ("JAX_PLATFORMS", "CUDA_VISIBLE_DEVICES"):
        monkeypatch.delenv(name, raising=False)
    (tmp_path / "nvidiactl").touch()  # the driver's control file alone: no GPU
    assert not process_server.gpu_present(str(tmp_path))
    (tmp_path / "nvidia0").touch()
    assert process_server.gpu_present(str(tmp_path)) and process_server.gpu_allowed()
    for platforms, allowed in (("cpu", False), ("cuda,cpu", True), ("gpu", True), ("tpu", False)):
        monkeypatch.setenv("JAX_PLATFORMS", platforms)
        assert process_server.gpu_allowed() is allowed
        assert process_server.gpu_present(str(tmp_path)) is allowed
    monkeypatch.delenv("JAX_PLATFORMS")
    for visible, present in (("", False), ("-1", False), ("0", True), ("1,0", True)):
        monkeypatch.setenv("CUDA_VISIBLE_DEVICES", visible)
        assert process_server.gpu_present(str(tmp_path)) is present
    monkeypatch.setattr(process_server, "gpu_present", lambda: False)
    assert not process_server.start_where_a_gpu_is([]) and started == []
    monkeypatch.setattr(process_server, "gpu_present", lambda: True)
    for argv in (["--help"], ["--seeds", "2", "-h"]):
        assert not process_server.start_where_a_gpu_is(argv) and started == []
    assert process_server.start_where_a_gpu_is(["--seeds", "2"]) and started == [True]

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
    """``gpu_present``: a GPU's device file and ``JAX_PLATFORMS`` unset or naming CUDA;
    ``start_where_a_gpu_is`` starts the server exactly then."""
    started = []
    monkeypatch.setattr(process_server, "start", lambda: started.append(True))
    monkeypatch.delenv("JAX_PLATFORMS", raising=False)
    (tmp_path / "nvidiactl").touch()  # the driver's control file alone: no GPU
    assert not process_server.gpu_present(str(tmp_path))
    (tmp_path / "nvidia0").touch()
    assert process_server.gpu_present(str(tmp_path)) and process_server.gpu_allowed()
    for platforms, allowed in (("cpu", False), ("cuda,cpu", True), ("gpu", True), ("tpu", False)):
        monkeypatch.setenv("JAX_PLATFORMS", platforms)
        assert process_server.gpu_allowed() is allowed
        assert process_server.gpu_present(str(tmp_path)) is allowed
    monkeypatch.setattr(process_server, "gpu_present", lambda: False)
    assert not process_server.start_where_a_gpu_is() and started == []
    monkeypatch.setattr(process_server, "gpu_present", lambda: True)
    assert process_server.start_where_a_gpu_is() and started == [True]

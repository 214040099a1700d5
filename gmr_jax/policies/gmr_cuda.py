"""GMR's S-step as one hand-written CUDA kernel (``gmr_cuda.cu``), called through the XLA FFI.

The S-step's ``impl="cuda"``: every Adam step of an S-step in one launch, one thread block per
seed (under ``jax.vmap`` the seeds are the launch's blocks), float32 on an NVIDIA GPU. Where the
seeds' clusters all fit on the GPU at once (``cudaOccupancyMaxActiveClusters``), each seed runs
on a thread-block cluster of 8 (else 4, 2) blocks of 512 threads instead, which share each phase's
items and train the same weights bit for bit (``FORMS``; ``launch_form`` forces a form while
tracing, for profiles and tests). It computes
the packed form's step (the same minibatches, noise, closed forms and Adam steps as
``gmr_kernel``'s Pallas kernel, whose layout it shares) with the products summed in another order,
so it agrees with the packed form to round-off (``benchmarks.sstep --impl cuda,packed`` measures
both and the difference of their weights).

Layout. θ is ``gmr_kernel``'s padded vector cut down to its *compact* form: each layer keeps its
real input rows (a prefix of the padded ones) and its columns up to the last real one, then its
bias row (``compact``). In shared memory each layer's rows have an odd stride, so that the threads
of a warp reading one column each of a row, or one row each of a column, hit distinct banks.
Adam's moments live in global memory (the GPU's L2 cache holds them).

The kernel runs a per-step program built here (``program``): phases of tasks (see the .cu file's
header) whose items the block's threads share, a barrier after each phase. The decoder and the
translation network run side by side, level by level, forward and backward; a layer's weight
gradient and Adam step run one phase after its input gradient (which reads the weights Adam
then overwrites).

The library is built with nvcc on first use (``library``), for the GPU at hand, into
``$GMR_JAX_CUDA_CACHE`` (default ``~/.cache/gmr_jax/cuda``), named by a hash of the source and the
compiler, and registered as the FFI target ``gmr_sstep_cuda``.
"""

from __future__ import annotations

import contextlib
import contextvars
import ctypes
import functools
import hashlib
import math
import os
import shutil
import subprocess
import tempfile
import warnings
from pathlib import Path
from typing import NamedTuple

import jax
import jax.numpy as jnp
import jaxlib
import numpy as np

from gmr_jax import sharding
from gmr_jax.config import GMRConfig, SStepConfig
from gmr_jax.policies import gmr_kernel
from gmr_jax.policies.base import PolicyParams

SOURCE = Path(__file__).with_name("gmr_cuda.cu")
TARGET = "gmr_sstep_cuda"
THREADS = 1024  # NT in the .cu file
ROWS_PER_ITEM = 4  # RG
WEIGHT_ROWS_PER_ITEM = 4  # KG
STATS = gmr_kernel.STATS

# The names below list the .cu file's enums in their order (tests/test_gmr_cuda.py checks it).
TASKS = ("gather", "fwd", "ingrad", "wgrad", "latent", "head1", "head2", "head3", "head4", "latent_grad")
FIXED_BUFFERS = ("rows", "wrow", "xin", "mu", "lv", "z", "klt", "xhat", "gout", "cout", "dg", "dc", "dxh", "gz",
                 "gmu", "glv", "dk", "dks", "pdks", "L", "T", "pl", "ts", "srn", "rn", "du", "pdu", "tr",
                 "ldt", "rowstat", "red", "sig", "prc", "xe", "tgt", "ldp")
HEADER = ("dX", "dU", "X", "U", "lat", "bs", "B", "n_theta", "stats_from", "n_layers", "n_bufs", "n_tasks",
          "n_phases", "layers", "bufs", "tasks", "phases", "theta_smem", "l_gain", "l_chol", "l_xhat", "cycles",
          "program")
FLOATS = ("slope", "alpha", "s", "c", "half_log_init_var", "rho", "lr", "b1", "one_minus_b1", "b2",
          "one_minus_b2", "eps", "wd", "dU")
TASK_INTS = 9
# The launch forms the library is built with, BLOCKSxTHREADS: blocks per seed (1, or a
# thread-block cluster of 2, 4 or 8 blocks that share each phase's items) and threads per block.
FORMS = ("1x1024", "2x512", "4x512", "8x256", "8x512")
MAX_CLUSTER = 8
# an H100's / H200's shared memory per block, less the kernel's static part (the float
# parameters, the cluster's partial sums)
SMEM_LIMIT = 227 * 1024 - 4 * (len(FLOATS) + MAX_CLUSTER)
# The .cu file's ablations (GMR_CUDA_ABLATE_<NAME>), for profiles: each leaves one part of the step
# out, so that the step's time without it shows what the part costs (``benchmarks.sstep_ablation``).
ABLATIONS = ("moments", "wgrad_sums", "fwd_sums", "ingrad_sums", "head", "barriers")


# The launch form that ``launch`` puts into the programs it traces ("auto": the library's choice).
_FORM = contextvars.ContextVar("gmr_cuda_form", default="auto")


def form_code(form: str) -> int:
    """A launch form as the library's ``form`` attribute: blocks · 10000 + threads ("auto": 0)."""
    if form == "auto":
        return 0
    if form not in FORMS:
        raise ValueError(f"CUDA launch form {form!r}: the built forms are {', '.join(FORMS)} (or auto)")
    blocks, threads = form.split("x")
    return int(blocks) * 10000 + int(threads)


def form_name(code: int) -> str:
    """``form_code``'s inverse."""
    return "auto" if code == 0 else f"{code // 10000}x{code % 10000}"


@contextlib.contextmanager
def launch_form(form: str | None):
    """Within: the programs traced launch the kernel in ``form`` (one of ``FORMS``; "auto": the
    library's choice; None: as set outside). The form is part of the traced program: a jitted
    function traced before keeps the form it was traced with. The weights do not depend on it."""
    if form is None:
        yield
        return
    form_code(form)  # a clear error for an unknown form
    token = _FORM.set(form)
    try:
        yield
    finally:
        _FORM.reset(token)


def pad4(n: int) -> int:
    """n rounded up to a multiple of four."""
    return -(-n // 4) * 4


class CompactLayer(NamedTuple):
    """One layer of the compact θ: W [K, N] row-major at ``offset``, its bias [N] after it;
    ``index`` [(K + 1)·N]: the padded θ's entry of each compact entry."""

    name: str
    K: int
    N: int
    offset: int
    index: np.ndarray

    @property
    def stride(self) -> int:
        """The row stride in shared memory: N, or N + 1 if N is even."""
        return self.N | 1


def compact(lay: gmr_kernel.Layout) -> list[CompactLayer]:
    """``gmr_kernel``'s layout -> the compact layers, in θ's order."""
    out, offset = [], 0
    for name, blk in lay.blocks.items():
        real_rows = np.flatnonzero(blk.rows >= 0)
        K = len(real_rows)
        if not np.array_equal(real_rows, np.arange(K)):
            raise ValueError(f"gmr_cuda: layer {name}'s real inputs are not a prefix of its padded ones")
        N = int(np.flatnonzero(blk.cols >= 0).max()) + 1
        w = blk.offset + np.arange(K)[:, None] * blk.fan_out + np.arange(N)[None, :]
        index = np.concatenate([w.reshape(-1), blk.bias_offset + np.arange(N)])
        out.append(CompactLayer(name, K, N, offset, index))
        offset += (K + 1) * N
    return out


def compact_index(layers: list[CompactLayer]) -> np.ndarray:
    """[n] the padded θ's entry of every compact entry."""
    return np.concatenate([L.index for L in layers])


def compact_position(lay: gmr_kernel.Layout) -> np.ndarray:
    """[lay.size] the compact θ's entry of every padded entry (-1: padding, not in the compact θ),
    the inverse of ``compact_index``: ``gmr_kernel.unpack``'s ``position``."""
    held = compact_index(compact(lay))
    position = np.full(lay.size, -1)
    position[held] = np.arange(len(held))
    return position


class Program(NamedTuple):
    """The kernel's program (int32 [P]) and the dynamic shared memory it needs (bytes)."""

    ints: np.ndarray
    smem_bytes: int
    phases: list  # [[(task, items, args)]], for inspection and tests


def program(cfg: GMRConfig, lay: gmr_kernel.Layout, batch_size: int, rows: int, stats_from: int) -> Program:
    """The per-step program of ``gmr_cuda.cu`` for a layout, minibatch size and data set of
    ``rows`` rows; steps before ``stats_from`` skip the statistics."""
    layers = compact(lay)
    lid = {L.name: i for i, L in enumerate(layers)}
    by_name = {L.name: L for L in layers}
    dX, dU, lat, bs = lay.dX, lay.dU, cfg.latent, batch_size
    NG, NC = by_name["gain"].N, by_name["chol"].N
    rg = -(-bs // ROWS_PER_ITEM)

    # buffers: (name, floats, leading dimension); a product reads the rows of its operands four
    # floats at a time, so their rows are padded to a multiple of four
    def rows4(width):
        return bs * pad4(width), pad4(width)
    fixed = {"rows": (bs, 1), "wrow": (bs, 1), "xin": rows4(dX), "mu": (bs * lat, lat), "lv": (bs * lat, lat),
             "z": rows4(lat), "klt": (bs * lat, lat), "xhat": (bs * dX, dX), "gout": (bs * NG, NG),
             "cout": (bs * NC, NC), "dg": rows4(NG), "dc": rows4(NC), "dxh": rows4(dX),
             "gz": rows4(lat), "gmu": rows4(lat), "glv": rows4(lat)}
    fixed.update({k: (bs * dU * dX, dU * dX) for k in ("dk", "dks", "pdks")})
    fixed.update({k: (bs * dU * dU, dU * dU) for k in ("L", "T", "pl")})
    fixed.update({k: (bs * dU, dU) for k in ("ts", "srn", "rn", "du", "pdu", "tr", "ldt")})
    fixed.update({"rowstat": (bs * (len(STATS) - 2), len(STATS) - 2), "red": (THREADS // 32, 1)})
    # the head's per-row data, copied by the gather: Σ_t and P row by row, each row padded to a
    # multiple of four floats; x̃ (with its constant 1); the target; log|P|
    fixed.update({"sig": (bs * dX * pad4(dX), dX * pad4(dX)), "prc": (bs * dU * pad4(dU), dU * pad4(dU)),
                  "xe": rows4(dX + 1), "tgt": rows4(dU), "ldp": (bs, 1)})
    assert tuple(fixed) == FIXED_BUFFERS
    buffers = [(name, *fixed[name]) for name in FIXED_BUFFERS]
    bid = {name: i for i, name in enumerate(FIXED_BUFFERS)}

    bufs_width = {}

    def new_buffer(name, width):
        bid[name] = len(buffers)
        buffers.append((name, *rows4(width)))
        bufs_width[bid[name]] = width
        return bid[name]

    # [phases + 1] doubles: the kernel's profile (clock cycles per phase); its size is set below
    cycles = len(buffers)
    buffers.append(("cycles", 0, 1))
    enc, dec, trans = lay.encoder[:-2], lay.decoder[:-1], lay.translation[:-2]
    if not (enc and dec and trans):
        raise ValueError("sstep impl='cuda' needs a hidden layer in each of GMR's three networks: use impl='packed'")
    h = {name: new_buffer("h_" + name, by_name[name].N) for name in enc + dec + trans}
    d, done = {}, []
    for net in (dec, trans, enc):  # up to three rotating cotangent buffers per network
        width = max(by_name[n].N for n in net)
        need = min(3, len(net))
        if net is enc:
            # the encoder's backward pass starts after the other two networks' have ended: it
            # takes over their buffers where they are wide enough
            reuse = [b for b in done if bufs_width[b] >= width][:need]
        else:
            reuse = []
        slots = reuse + [new_buffer(f"d_{net[0]}_{i}", width) for i in range(len(reuse), need)]
        done += slots
        d.update({name: slots[i % 3] for i, name in enumerate(net)})

    def task(kind, items, *args):
        return (TASKS.index(kind), int(items), list(args) + [-1] * (TASK_INTS - 2 - len(args)))

    def fwd(name, src, dst, act):
        return task("fwd", by_name[name].N * rg, lid[name], src, dst, int(act))

    def ingrad(sources, dst, mask, accumulate):
        # an INGRAD task sums the products of at most two layers (each network has a hidden
        # layer, so at most two meet at g_z, and each top has two outputs)
        assert 1 <= len(sources) <= 2, sources
        (l1, d1), (l2, d2) = sources[0], (sources[1] if len(sources) > 1 else (None, -1))
        return task("ingrad", by_name[l1].K * rg, lid[l1], d1, -1 if l2 is None else lid[l2], d2, dst, mask,
                    int(accumulate))

    def wgrad(name, src, dd):
        L = by_name[name]
        return task("wgrad", L.N * -(-(L.K + 1) // WEIGHT_ROWS_PER_ITEM), lid[name], src, dd)

    gather_items = (bs * dX + fixed["gz"][0] + bs * dX * pad4(dX) // 4 + bs * dU * pad4(dU) // 4
                    + bs * pad4(dX + 1) // 4 + bs * pad4(dU) // 4)
    phases = [[task("gather", gather_items)]]
    src = bid["xin"]
    for name in enc:
        phases.append([fwd(name, src, h[name], True)])
        src = h[name]
    phases.append([task("latent", bs * lat, lid["mu"], lid["logvar"], src)])
    for j in range(max(len(dec), len(trans)) + 1):
        ts = []
        for net, outs in ((dec, (("xhat", bid["xhat"]),)), (trans, (("gain", bid["gout"]), ("chol", bid["cout"])))):
            below = bid["z"] if j == 0 else (h[net[j - 1]] if j - 1 < len(net) else None)
            if j < len(net):
                ts.append(fwd(net[j], below, h[net[j]], True))
            elif j == len(net):
                ts += [fwd(name, below, dst, False) for name, dst in outs]
        phases.append(ts)
    phases += [[task("head1", bs * dU + bs * dU * dX)],
               [task("head2", bs * dU * dX + bs * dU + bs * dU * dU)],
               [task("head3", bs * dU * dX + bs * dU)],
               [task("head4", bs * NG + bs * NC + bs * dX + bs)]]

    def groups(net, outs, bottom):
        """A network's backward groups, top first: ([(layer, cotangent buffer)], input buffer,
        the cotangent buffer of the layer below or None, its output buffer (the mask))."""
        out = []
        names = list(net)
        layers_down = [outs] + [[(n, d[n])] for n in reversed(names)]
        for g, sources in enumerate(layers_down):
            below = names[len(names) - 1 - g] if g < len(names) else None
            out.append((sources, h[below] if below else bottom, d[below] if below else None))
        return out

    def backward(nets, bottom_target):
        """Phases of the networks' backward passes side by side (aligned at their tops): group g's
        input gradient at stage g, its weight gradients and Adam at stage g + 1 (after the input
        gradient has read the weights). Input gradients into ``bottom_target`` (g_z, added to;
        None: not needed) of the same stage are one task, so no two tasks of a phase write it."""
        out = [[] for _ in range(max(len(gs) for gs in nets) + 1)]
        into_bottom: dict[int, list] = {}
        for gs in nets:
            for g, (sources, src, below) in enumerate(gs):
                out[g + 1] += [wgrad(name, src, dd) for name, dd in sources]
                if below is not None:
                    out[g].append(ingrad(sources, below, src, False))
                elif bottom_target is not None:
                    into_bottom.setdefault(g, []).extend(sources)
        for g, sources in into_bottom.items():
            out[g].append(ingrad(sources, bottom_target, -1, True))
        return [p for p in out if p]

    dec_groups = groups(dec, [("xhat", bid["dxh"])], bid["z"])
    trans_groups = groups(trans, [("gain", bid["dg"]), ("chol", bid["dc"])], bid["z"])
    # the latent cotangents need every input gradient into g_z: after the stages that place them
    back = backward([trans_groups, dec_groups], bid["gz"])
    back[-1].append(task("latent_grad", bs * lat))
    phases += back
    enc_groups = groups(enc, [("mu", bid["gmu"]), ("logvar", bid["glv"])], bid["xin"])
    phases += backward([enc_groups], None)

    # the program's ints: header, layers, buffers, tasks, phases; then shared memory offsets
    buffers[cycles] = ("cycles", 2 * (len(phases) + 1), 1)
    task_list = [t for p in phases for t in p]
    sizes = [len(HEADER), 5 * len(layers), 2 * len(buffers), TASK_INTS * len(task_list), 3 * len(phases)]
    total = sum(sizes)
    prog_floats = -(-total // 4) * 4
    offset = prog_floats
    layer_ints = []
    for L in layers:
        layer_ints += [L.offset, offset, L.K, L.N, L.stride]
        offset += (L.K + 1) * L.stride
    theta_smem = offset - prog_floats
    buf_ints = []
    for _, floats, width in buffers:
        offset = -(-offset // 4) * 4
        buf_ints += [offset, width]
        offset += floats
    smem_bytes = 4 * offset
    n_theta = sum((L.K + 1) * L.N for L in layers)
    tasks_ints, phase_ints, first = [], [], 0
    for p in phases:
        phase_ints += [first, len(p), sum(t[1] for t in p)]
        first += len(p)
        for kind, items, args in p:
            tasks_ints += [kind, items] + args
    starts = np.cumsum([0] + sizes)
    header = {"dX": dX, "dU": dU, "X": lay.X, "U": lay.U, "lat": lat, "bs": bs, "B": rows, "n_theta": n_theta,
              "stats_from": stats_from, "n_layers": len(layers), "n_bufs": len(buffers),
              "n_tasks": len(task_list), "n_phases": len(phases), "layers": starts[1], "bufs": starts[2],
              "tasks": starts[3], "phases": starts[4], "theta_smem": theta_smem, "l_gain": lid["gain"],
              "l_chol": lid["chol"], "l_xhat": lid["xhat"], "cycles": cycles, "program": total}
    ints = np.array([header[k] for k in HEADER] + layer_ints + buf_ints + tasks_ints + phase_ints, np.int32)
    assert len(ints) == total
    return Program(ints, smem_bytes, phases)


def phase_tasks(ints: np.ndarray, names: list[str]) -> list[list[str]]:
    """Each phase of a program as its tasks, "kind" or "kind layer" (``names``: the compact
    layers' names), for profiles."""
    h = dict(zip(HEADER, ints[:len(HEADER)].tolist()))
    tasks = ints[h["tasks"]: h["tasks"] + TASK_INTS * h["n_tasks"]].reshape(-1, TASK_INTS)
    phases = ints[h["phases"]: h["phases"] + 3 * h["n_phases"]].reshape(-1, 3)
    out = []
    for first, count, _ in phases:
        out.append([TASKS[t[0]] + (f" {names[t[2]]}" if TASKS[t[0]] in ("fwd", "ingrad", "wgrad", "latent") else "")
                    for t in tasks[first: first + count]])
    return out


def floats(cfg: GMRConfig, scfg: SStepConfig, dU: int, dtype=np.float32) -> np.ndarray:
    """The kernel's float parameters (``FLOATS``' order) in ``dtype`` (the kernel's float32: as the
    packed form rounds its Python constants)."""
    values = {"slope": cfg.negative_slope, "alpha": cfg.alpha, "s": math.log(cfg.cov_std_range),
              "c": cfg.cov_offdiag_bound, "half_log_init_var": 0.5 * math.log(cfg.init_var),
              "rho": 1.0 / scfg.batch_size, "lr": scfg.lr, "b1": scfg.b1, "one_minus_b1": 1 - scfg.b1,
              "b2": scfg.b2, "one_minus_b2": 1 - scfg.b2, "eps": scfg.eps, "wd": scfg.weight_decay, "dU": dU}
    return np.array([values[k] for k in FLOATS], dtype)


def check_supported(cfg: GMRConfig, dtype):
    """One-line errors for what the CUDA form does not run."""
    if jnp.dtype(dtype) != jnp.float32:
        raise ValueError(f"sstep impl='cuda' runs in float32 only (the params are {jnp.dtype(dtype).name}): "
                         "use impl='packed' for float64")
    if cfg.negative_slope <= 0:
        raise ValueError(f"sstep impl='cuda' needs gmr.negative_slope > 0 (got {cfg.negative_slope}): it reads the "
                         "leaky ReLU's derivative off the layer's output; use impl='packed'")
    platform = sharding.target_platform()
    if platform not in ("gpu", "cuda"):
        raise ValueError(f"sstep impl='cuda' needs an NVIDIA GPU (the program runs on {platform}): "
                         "use impl='packed' or 'reference'")


def ablations() -> tuple[str, ...]:
    """The ablations named in ``$GMR_JAX_CUDA_ABLATE`` (comma- or plus-separated ``ABLATIONS``;
    unset or empty: none). A build with any of them trains wrong weights: for profiles only."""
    names = {n.strip() for n in os.environ.get("GMR_JAX_CUDA_ABLATE", "").replace("+", ",").split(",")} - {""}
    unknown = sorted(names - set(ABLATIONS))
    if unknown:
        raise ValueError(f"GMR_JAX_CUDA_ABLATE names {', '.join(unknown)}: the ablations are {', '.join(ABLATIONS)} "
                         "(or leave it unset to train)")
    return tuple(sorted(names, key=ABLATIONS.index))


def _nvcc_flags() -> list[str]:
    arch = os.environ.get("GMR_JAX_CUDA_ARCH", "native")
    return ["-O3", "-std=c++17", "-shared", "-Xcompiler", "-fPIC", f"-arch={arch}",
            f"-I{jax.ffi.include_dir()}", *(f"-DGMR_CUDA_ABLATE_{n.upper()}" for n in ablations())]


def build(out: Path, flags: list[str] | None = None) -> str:
    """Compile ``gmr_cuda.cu`` into the shared library ``out`` (written atomically); returns the
    compiler's messages."""
    nvcc = shutil.which("nvcc")
    if nvcc is None:
        raise RuntimeError("sstep impl='cuda' needs nvcc (the CUDA toolkit) on PATH to build its kernel: "
                           "install it or use impl='packed'")
    out.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.NamedTemporaryFile(dir=out.parent, suffix=".so", delete=False) as tmp:
        pass
    try:
        res = subprocess.run([nvcc, *(flags or _nvcc_flags()), "-o", tmp.name, str(SOURCE)],
                             capture_output=True, text=True)
        if res.returncode != 0:
            raise RuntimeError(f"nvcc failed on {SOURCE.name} (use impl='packed'); its messages:\n"
                               f"{res.stderr[-4000:]}")
        os.replace(tmp.name, out)
    finally:
        if os.path.exists(tmp.name):
            os.unlink(tmp.name)
    return res.stderr


@functools.lru_cache(maxsize=None)
def library() -> ctypes.CDLL:
    """The built library (built on first use, then cached on disk), its FFI target registered."""
    nvcc = shutil.which("nvcc")
    version = subprocess.run([nvcc, "--version"], capture_output=True, text=True).stdout if nvcc else ""
    # "-arch=native" names no architecture: the GPU's compute capability and the FFI headers'
    # jaxlib go into the name too, so that a cache shared between machines or kept over an
    # upgrade never hands out another build
    gpu = getattr(jax.devices()[0], "compute_capability", "")
    extra = f"{gpu} {jaxlib.__version__} {' '.join(_nvcc_flags())}"
    key = hashlib.sha256(SOURCE.read_bytes() + version.encode() + extra.encode()).hexdigest()[:16]
    cache = Path(os.environ.get("GMR_JAX_CUDA_CACHE", Path.home() / ".cache" / "gmr_jax" / "cuda"))
    so = cache / f"gmr_cuda_{key}.so"
    if ablations():
        warnings.warn(f"gmr_cuda: the kernel is built with the ablations {', '.join(ablations())} "
                      "($GMR_JAX_CUDA_ABLATE): its weights are wrong, for profiles only", stacklevel=2)
    if not so.exists():
        build(so)
    lib = ctypes.cdll.LoadLibrary(str(so))
    jax.ffi.register_ffi_target(TARGET, jax.ffi.pycapsule(lib.GmrSstepCuda), platform="CUDA")
    return lib


class Inputs(NamedTuple):
    """What the kernel reads, per seed (``gmr_cuda.cu``'s ``Args`` in its order)."""

    idx: jax.Array      # [steps, bs] int32
    eps: jax.Array      # [steps, bs, latent]
    c1: jax.Array       # [steps]
    c2: jax.Array       # [steps]
    rows: gmr_kernel.KernelRows
    theta0: jax.Array   # [n] compact θ
    program: np.ndarray  # int32 [P]
    floats: np.ndarray   # float32 [len(FLOATS)]


def inputs(cfg: GMRConfig, scfg: SStepConfig, params: PolicyParams, rows, idx, noise, c1, c2):
    """``fit``'s arguments as the kernel's inputs (in the params' dtype) and the program's shared
    memory (bytes)."""
    dX, dU = params.norm.scale.shape[-1], params.var.shape[-1]
    lay = gmr_kernel.layout(cfg, dX, dU, scfg.batch_size)
    steps, bs = idx.shape
    if noise.shape != (steps, bs, cfg.latent):
        raise ValueError(f"gmr_cuda.fit: noise has shape {noise.shape}, expected {(steps, bs, cfg.latent)}")
    kr = gmr_kernel.kernel_rows(cfg, lay, params, rows)
    stats_from = steps - steps // scfg.epochs if scfg.statistics_epochs == "last" else 0
    prog = program(cfg, lay, bs, kr.xn.shape[0], stats_from)
    dtype = params.norm.scale.dtype
    theta0 = gmr_kernel.pack(cfg, lay, params.net).astype(dtype)[compact_index(compact(lay))]
    return Inputs(idx.astype(jnp.int32), noise.astype(dtype), c1.astype(dtype), c2.astype(dtype), kr, theta0,
                  prog.ints, floats(cfg, scfg, dU, dtype)), prog.smem_bytes


def launch(inp: Inputs, smem_bytes: int, *, cycles: bool = False):
    """The kernel on ``inp`` (float32, on the GPU) in the form that ``launch_form`` sets: (θ [n],
    stats [steps, len(STATS)]), and with ``cycles`` also the clock cycles of each phase of the
    program summed over the steps (the last entry: the statistics' reduction) [phases + 1] and the
    form that ran (int32 [1], ``form_code``)."""
    if smem_bytes > SMEM_LIMIT:
        raise ValueError(f"sstep impl='cuda': the networks need {smem_bytes} bytes of shared memory, more "
                         f"than {SMEM_LIMIT}: use impl='packed'")
    library()
    steps = inp.idx.shape[0]
    f32 = jnp.float32
    n = inp.theta0.shape[0]
    phases = int(inp.program[HEADER.index("n_phases")])
    call = jax.ffi.ffi_call(TARGET, (jax.ShapeDtypeStruct((n,), f32),) * 3
                            + (jax.ShapeDtypeStruct((steps, len(STATS)), f32), jax.ShapeDtypeStruct((phases + 1,), f32),
                               jax.ShapeDtypeStruct((1,), jnp.int32)),
                            vmap_method="broadcast_all")
    theta, _, _, stats, clocks, form = call(
        inp.idx, inp.eps.astype(f32), inp.c1.astype(f32), inp.c2.astype(f32), *(a.astype(f32) for a in inp.rows),
        inp.theta0.astype(f32), jnp.asarray(inp.program), jnp.asarray(inp.floats, f32), steps=np.int64(steps),
        smem_bytes=np.int64(smem_bytes), form=np.int64(form_code(_FORM.get())))
    return (theta, stats, clocks, form) if cycles else (theta, stats)


def fit(cfg: GMRConfig, scfg: SStepConfig, params: PolicyParams, rows, idx, noise, c1, c2, *, run=None):
    """All Adam steps of an S-step in one CUDA kernel (``gmr_kernel.fit``'s arguments and results).

    Args:
      cfg, scfg: the GMR and S-step configurations (static).
      params: the policy params (warm start; normalisation set), float32.
      rows: gmr's LossRows of the whole training set (B rows, ``tgt_prc`` = w·P).
      idx: [steps, batch_size] int, each step's rows; noise: [steps, batch_size, latent] ε.
      c1, c2: [steps] Adam's bias corrections.
      run: (Inputs, smem_bytes) -> (θ, stats) in place of ``launch`` (the tests' emulation of
        the kernel's program on the host, in the params' dtype).
    Returns: (net (Flax), stats [steps, len(STATS)]). With ``scfg.statistics_epochs == "last"``
    only the last epoch's steps compute their statistics (the others hold zeros).
    """
    dtype = params.norm.scale.dtype
    if run is None:
        check_supported(cfg, dtype)
        run = launch
    inp, smem_bytes = inputs(cfg, scfg, params, rows, idx, noise, c1, c2)
    theta, stats = run(inp, smem_bytes)
    dX, dU = params.norm.scale.shape[-1], params.var.shape[-1]
    lay = gmr_kernel.layout(cfg, dX, dU, scfg.batch_size)
    position = compact_position(lay)
    held = int(np.count_nonzero(position >= 0))
    if theta.shape != (held,):
        raise ValueError(f"gmr_cuda.fit: the kernel returned θ of shape {theta.shape}, expected {(held,)}")
    return gmr_kernel.unpack(cfg, lay, params.net, theta.astype(dtype), position), stats.astype(dtype)

"""GMR's CUDA S-step (``gmr_cuda``): its program and arithmetic, emulated on the host item for item
as the .cu file's tasks define them, against the packed form (same minibatches, noise and Adam
steps: equal to round-off); the program's phases free of races; the names of the .cu file's
enums; clear errors where the CUDA form does not run; and, where nvcc is present, that the kernel
builds for Hopper without spilling registers. The kernel itself runs on a GPU only
(``benchmarks.sstep --impl packed,cuda`` compares it with the packed form there)."""

import re
import shutil

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gmr_jax.config import GMRConfig, SStepConfig
from gmr_jax.policies import gmr_cuda, gmr_kernel, make_policy

import test_sstep
from test_sstep import _forms_agree, _metrics_agree

CU = gmr_cuda.SOURCE.read_text()


def _enum(name):
    body = re.search(r"enum " + name + r" \{(.*?)\};", CU, re.S).group(1)
    return [re.sub(r"\s*=.*", "", e).strip() for e in body.split(",") if e.strip()]


def test_the_python_names_follow_the_cu_files_enums():
    """Python builds the program the .cu file reads: the same order of task kinds, fixed
    buffers, header fields and float parameters."""
    assert [e.lower() for e in _enum("TaskKind")] == list(gmr_cuda.TASKS)
    assert _enum("FixedBuffer")[:-1] == ["B_" + b.upper() for b in gmr_cuda.FIXED_BUFFERS]
    assert _enum("Header")[:-1] == ["H_" + h.upper() for h in gmr_cuda.HEADER]
    assert _enum("Floats")[:-1] == ["F_" + f.upper() for f in gmr_cuda.FLOATS]
    assert f"constexpr int NT = {gmr_cuda.THREADS};" in CU
    assert f"constexpr int TASK_INTS = {gmr_cuda.TASK_INTS};" in CU
    assert f"constexpr int KG = {gmr_cuda.WEIGHT_ROWS_PER_ITEM};" in CU
    assert f"constexpr int RG = {gmr_cuda.ROWS_PER_ITEM};" in CU


# ------------------------------------------------ the host emulation of the kernel's program

def _reads_writes(kind, a):
    """(read, written) sets of a task: buffers by id, layers' weights as ("W", layer)."""
    F = {name: i for i, name in enumerate(gmr_cuda.FIXED_BUFFERS)}
    W = lambda lay: {("W", lay)} if lay >= 0 else set()  # noqa: E731
    if kind == "gather":
        return set(), {F[n] for n in ("xin", "rows", "wrow", "gz", "sig", "prc", "xe", "tgt", "ldp")}
    if kind == "fwd":
        return {a[1]} | W(a[0]), {a[2]}
    if kind == "ingrad":
        reads = {a[1]} | W(a[0]) | ({a[3]} | W(a[2]) if a[2] >= 0 else set()) | ({a[5]} if a[5] >= 0 else set())
        return reads | ({a[4]} if a[6] else set()), {a[4]}
    if kind == "wgrad":
        return {a[1], a[2]} | W(a[0]), W(a[0])
    if kind == "latent":
        return {a[2]} | W(a[0]) | W(a[1]), {F["mu"], F["lv"], F["z"], F["klt"]}
    names = {"head1": ("cout gout rows xe tgt", "T L ts srn rn ldt du dk"),
             "head2": ("dk du L rows sig prc", "dks pdu pl"),
             "head3": ("dks L pl rows prc", "pdks tr"),
             "head4": ("pdu pdks tr wrow pl rn srn T ts xin xhat du ldt dk klt rows xe ldp", "dg dc dxh rowstat"),
             "latent_grad": ("wrow mu lv gz", "gmu glv")}[kind]
    return tuple({F[n] for n in s.split()} for s in names)


def _phases_without_races(prog):
    """No task of a phase writes what another task of the same phase reads or writes."""
    for p, phase in enumerate(prog.phases):
        sets = [_reads_writes(gmr_cuda.TASKS[k], a) for k, _, a in phase]
        for i, (_, wi) in enumerate(sets):
            for j, (rj, wj) in enumerate(sets):
                if i != j:
                    assert not wi & (rj | wj), f"phase {p}: tasks {i} and {j} race on {wi & (rj | wj)}"


def emulate(inp: gmr_cuda.Inputs):
    """The kernel's program run on the host, each task on all of its items at once, in the
    inputs' dtype: (θ [n], stats [steps, 8])."""
    P = np.asarray(inp.program)
    h = dict(zip(gmr_cuda.HEADER, P[:len(gmr_cuda.HEADER)].tolist()))
    f = dict(zip(gmr_cuda.FLOATS, np.asarray(inp.floats)))
    layers = P[h["layers"]: h["layers"] + 5 * h["n_layers"]].reshape(-1, 5)
    bufs = P[h["bufs"]: h["bufs"] + 2 * h["n_bufs"]].reshape(-1, 2)
    tasks = P[h["tasks"]: h["tasks"] + gmr_cuda.TASK_INTS * h["n_tasks"]].reshape(-1, gmr_cuda.TASK_INTS)
    phases = P[h["phases"]: h["phases"] + 3 * h["n_phases"]].reshape(-1, 3)
    dX, dU, X, U, lat, bs = (h[k] for k in ("dX", "dU", "X", "U", "lat", "bs"))
    idx, eps, c1, c2 = (np.asarray(a) for a in (inp.idx, inp.eps, inp.c1, inp.c2))
    R = gmr_kernel.KernelRows(*(np.asarray(a) for a in inp.rows))
    theta = np.array(inp.theta0)
    dt = theta.dtype
    m, v = np.zeros_like(theta), np.zeros_like(theta)
    F = {name: i for i, name in enumerate(gmr_cuda.FIXED_BUFFERS)}
    buf = [np.zeros((bs, ldim), dt) for _, ldim in bufs]
    rows_of = lambda: buf[F["rows"]][:, 0].astype(int)  # noqa: E731
    slope = f["slope"]
    leaky = lambda x: np.where(x >= 0, x, slope * x)  # noqa: E731

    def weights(lay):
        coff, _, K, N, _ = layers[lay]
        return theta[coff: coff + (K + 1) * N].reshape(K + 1, N)  # a view: Adam writes through it

    def adam(lay, g, step):
        coff, _, K, N, _ = layers[lay]
        sl = slice(coff, coff + (K + 1) * N)
        th = theta[sl]
        g = g + f["wd"] * (2 * th)
        m[sl] = f["one_minus_b1"] * g + f["b1"] * m[sl]
        v[sl] = f["one_minus_b2"] * (g * g) + f["b2"] * v[sl]
        l2 = np.sum(th * th)
        # the kernel's form of Adam's update: the corrections as reciprocals, one division
        rc1, rc2 = 1 / c1[step], 1 / c2[step]
        theta[sl] = th + -f["lr"] * ((m[sl] * rc1) / (np.sqrt(v[sl] * rc2) + f["eps"]))
        return l2

    stats = np.zeros((len(idx), len(gmr_cuda.STATS)), dt)
    for step in range(len(idx)):
        l2 = 0.0
        for first, count, _ in phases:
            for t in tasks[first: first + count]:
                kind, a = gmr_cuda.TASKS[t[0]], t[2:]
                if kind == "gather":
                    r = idx[step]
                    buf[F["xin"]][:, :dX] = R.xn[r, :dX]
                    buf[F["rows"]][:, 0] = r
                    buf[F["wrow"]][:, 0] = R.wt[r]
                    buf[F["gz"]][:] = 0
                elif kind == "fwd":
                    W = weights(a[0])
                    K, N = W.shape[0] - 1, W.shape[1]
                    pre = buf[a[1]][:, :K] @ W[:K] + W[K]
                    buf[a[2]][:, :N] = leaky(pre) if a[3] else pre
                elif kind == "ingrad":
                    W = weights(a[0])
                    K = W.shape[0] - 1
                    g = buf[a[1]][:, :W.shape[1]] @ W[:K].T
                    if a[2] >= 0:
                        W2 = weights(a[2])
                        g = g + buf[a[3]][:, :W2.shape[1]] @ W2[:K].T
                    if a[6]:
                        g = buf[a[4]][:, :K] + g
                    if a[5] >= 0:
                        g = np.where(buf[a[5]][:, :K] >= 0, g, slope * g)
                    buf[a[4]][:, :K] = g
                elif kind == "wgrad":
                    W = weights(a[0])
                    K, N = W.shape[0] - 1, W.shape[1]
                    D = buf[a[2]][:, :N]
                    g = np.concatenate([buf[a[1]][:, :K].T @ D, D.sum(0)[None]]).reshape(-1)
                    l2 += adam(a[0], g, step)
                elif kind == "latent":
                    Wm, Wv = weights(a[0]), weights(a[1])
                    K = Wm.shape[0] - 1
                    x = buf[a[2]][:, :K]
                    mu, lv = x @ Wm[:K] + Wm[K], x @ Wv[:K] + Wv[K]
                    buf[F["mu"]][:, :lat], buf[F["lv"]][:, :lat] = mu, lv
                    buf[F["z"]][:, :lat] = mu + np.exp(0.5 * lv) * eps[step]
                    buf[F["klt"]][:, :lat] = mu * mu + np.exp(lv) - lv - 1
                elif kind == "head1":
                    C = buf[F["cout"]]
                    G = buf[F["gout"]]
                    r = rows_of()
                    tt = np.tanh(np.stack([C[:, i * U + i] for i in range(dU)], 1) / f["s"])
                    log_sigma = f["half_log_init_var"] + f["s"] * tt
                    T = np.tanh(np.stack([C[:, i * U: i * U + dU] for i in range(dU)], 1) / f["c"])
                    lower = np.tril(np.ones((dU, dU), bool), -1)
                    V = np.where(lower, f["c"] * T, 0) + np.eye(dU)
                    rn = np.sqrt(np.sum(V * V, axis=2))
                    srn = np.exp(log_sigma) / rn
                    buf[F["T"]][:] = T.reshape(bs, -1)
                    buf[F["L"]][:] = (srn[:, :, None] * V).reshape(bs, -1)
                    buf[F["ts"]][:], buf[F["srn"]][:], buf[F["rn"]][:] = tt, srn, rn
                    buf[F["ldt"]][:] = log_sigma - np.log(rn)
                    Gm = np.stack([G[:, i * X: i * X + dX + 1] for i in range(dU)], 1)
                    buf[F["du"]][:] = np.einsum("rij,rj->ri", Gm, R.xe[r, :dX + 1]) - R.tgt[r, :dU]
                    buf[F["dk"]][:] = (Gm[:, :, :dX] * R.scale[:dX] - R.K[r, :dU, :dX]).reshape(bs, -1)
                elif kind == "head2":
                    r = rows_of()
                    P_ = R.prc[r, :dU, :dU]
                    dK = buf[F["dk"]].reshape(bs, dU, dX)
                    buf[F["dks"]][:] = np.einsum("rik,rjk->rij", dK, R.sig[r, :dX, :dX]).reshape(bs, -1)
                    buf[F["pdu"]][:] = np.einsum("rij,rj->ri", P_, buf[F["du"]])
                    buf[F["pl"]][:] = (P_ @ buf[F["L"]].reshape(bs, dU, dU)).reshape(bs, -1)
                elif kind == "head3":
                    r = rows_of()
                    P_ = R.prc[r, :dU, :dU]
                    buf[F["pdks"]][:] = (P_ @ buf[F["dks"]].reshape(bs, dU, dX)).reshape(bs, -1)
                    buf[F["tr"]][:] = np.sum((buf[F["L"]] * buf[F["pl"]]).reshape(bs, dU, dU), axis=2)
                elif kind == "head4":
                    r = rows_of()
                    rho, w = f["rho"], buf[F["wrow"]][:, 0]
                    NG, NC = layers[h["l_gain"]][3], layers[h["l_chol"]][3]
                    gG = np.zeros((bs, dU, X), dt)
                    gG[:] = (rho * buf[F["pdu"]])[:, :, None] * R.xe[r][:, None, :]
                    gG[:, :, :dX] += (rho * buf[F["pdks"]].reshape(bs, dU, dX)) * R.scale[:dX]
                    buf[F["dg"]][:, :NG] = gG.reshape(bs, -1)[:, :NG]
                    q = rho * buf[F["tr"]] + (-rho) * w[:, None]
                    T = buf[F["T"]].reshape(bs, dU, dU)
                    V = np.where(np.tril(np.ones((dU, dU), bool), -1), f["c"] * T, 0) + np.eye(dU)
                    rn, srn, tt = buf[F["rn"]], buf[F["srn"]], buf[F["ts"]]
                    gV = srn[:, :, None] * (rho * buf[F["pl"]].reshape(bs, dU, dU)) - (q / (rn * rn))[:, :, None] * V
                    lower = np.tril(np.ones((dU, dU), bool), -1)
                    gfull = np.where(lower, gV * (1 - T * T), 0) + np.eye(dU) * (q * (1 - tt * tt))[:, :, None]
                    gc = np.zeros((bs, U, U), dt)
                    gc[:, :dU, :dU] = gfull
                    buf[F["dc"]][:, :NC] = gc.reshape(bs, -1)[:, :NC]
                    diff = buf[F["xin"]][:, :dX] - buf[F["xhat"]][:, :dX]
                    buf[F["dxh"]][:, :dX] = (-2 * rho * w)[:, None] * diff
                    du, pdu = buf[F["du"]], buf[F["pdu"]]
                    rs = buf[F["rowstat"]]
                    rs[:, 0] = np.sum(du * pdu, 1)
                    rs[:, 1] = np.sum(du * du, 1) / f["dU"]
                    rs[:, 2] = np.sum(buf[F["tr"]], 1) - w * (2 * np.sum(buf[F["ldt"]], 1) + f["dU"] + R.logdet[r])
                    rs[:, 3] = np.sum(buf[F["dk"]] * buf[F["pdks"]], 1)
                    rs[:, 4] = w * 0.5 * np.sum(buf[F["klt"]][:, :lat], 1)
                    rs[:, 5] = w * np.sum(diff * diff, 1)
                elif kind == "latent_grad":
                    w = buf[F["wrow"]][:, 0]
                    ct = (f["alpha"] * 0.5 * f["rho"] * w)[:, None]
                    mu, lv, gz = buf[F["mu"]][:, :lat], buf[F["lv"]][:, :lat], buf[F["gz"]][:, :lat]
                    buf[F["gmu"]][:, :lat] = gz + ct * (2 * mu)
                    buf[F["glv"]][:, :lat] = gz * eps[step] * (0.5 * np.exp(0.5 * lv)) + ct * (np.exp(lv) - 1)
        if step >= h["stats_from"]:
            aux = np.sum(f["rho"] * buf[F["rowstat"]], axis=0)
            aux[[0, 2, 3]] *= 0.5
            value = aux[5] + f["alpha"] * aux[4] + aux[0] + aux[3] + aux[2]
            stats[step] = np.concatenate([[value + f["wd"] * l2, value], aux])
    return theta, stats


def emulated_launch(inp: gmr_cuda.Inputs, smem_bytes):
    """``gmr_cuda.launch`` by ``emulate`` (a host callback, under jit and vmap)."""
    assert smem_bytes <= gmr_cuda.SMEM_LIMIT
    dt = inp.theta0.dtype
    shapes = (jax.ShapeDtypeStruct(inp.theta0.shape, dt), jax.ShapeDtypeStruct((inp.idx.shape[0], 8), dt))

    def host(idx, eps, c1, c2, rows, theta0):
        return tuple(np.asarray(a, dt) for a in emulate(inp._replace(idx=idx, eps=eps, c1=c1, c2=c2, rows=rows,
                                                                     theta0=theta0)))
    return jax.pure_callback(host, shapes, inp.idx, inp.eps, inp.c1, inp.c2, inp.rows, inp.theta0,
                             vmap_method="sequential")


@pytest.fixture
def emulated(monkeypatch):
    monkeypatch.setattr(gmr_cuda, "launch", emulated_launch)
    monkeypatch.setattr(gmr_cuda, "check_supported", lambda cfg, dtype: None)


@pytest.mark.parametrize("name", ["gmr", "gmr_uneven"])
def test_emulated_program_equals_the_packed_form(name, emulated):
    """The kernel's program, emulated on the host in float64, against the packed form: the same
    minibatches, noise and Adam steps with the sums in another order, so the bound of
    ``test_sstep.test_kernel_sstep_equals_packed`` holds (8·δ·lr·S on the weights, 2δ on the
    metrics), for GMR's standardised and raw head coordinates and for networks of different
    depths (the decoder's and the translation network's backward passes then end in different
    phases)."""
    new_m, ref_m, delta = _forms_agree(name, "packed", "cuda", jnp.float64)
    _metrics_agree(new_m, ref_m, delta)
    assert bool(new_m["finite"]) and bool(new_m["weights_ok"])


def test_emulated_program_keeps_only_the_last_epochs_statistics(emulated):
    """With ``statistics_epochs="last"`` the kernel computes the statistics of the last epoch's
    steps only; they equal those of the run that computes every epoch's."""
    pol, _ = test_sstep._policy("gmr")
    data = test_sstep._full_data(12)
    params = pol.init(jax.random.key(2), test_sstep.dX, test_sstep.dU)
    cfg = SStepConfig(epochs=2, batch_size=20, statistics_epochs="all")
    _, every = test_sstep._sstep(pol, params, data, jax.random.key(3), cfg, impl="cuda")
    _, last = test_sstep._sstep(pol, params, data, jax.random.key(3),
                                SStepConfig(epochs=2, batch_size=20, statistics_epochs="last"), impl="cuda")
    np.testing.assert_array_equal(last["loss"], every["loss"][-1:])
    np.testing.assert_array_equal(last["aux"]["cov"], every["aux"]["cov"][-1:])


@pytest.mark.parametrize("cfg", [GMRConfig(), GMRConfig(latent=3, encoder_hidden=(16,), decoder_hidden=(8,),
                                                        translation_hidden=(16, 12))])
def test_program_phases_have_no_races_and_fit_shared_memory(cfg):
    """Every phase's tasks touch disjoint data (the kernel runs them at once), a layer's Adam step
    comes after every read of its weights in the step, and the reach task's GMR (dX 12, dU 6,
    the paper's layers) fits one block's shared memory."""
    lay = gmr_kernel.layout(cfg, 12, 6, 20)
    prog = gmr_cuda.program(cfg, lay, 20, 960, 0)
    _phases_without_races(prog)
    updated_at = {}
    for p, phase in enumerate(prog.phases):
        for k, _, a in phase:
            if gmr_cuda.TASKS[k] == "wgrad":
                assert a[0] not in updated_at
                updated_at[a[0]] = p
    assert sorted(updated_at) == list(range(len(gmr_cuda.compact(lay))))
    for p, phase in enumerate(prog.phases):
        for k, _, a in phase:
            kind = gmr_cuda.TASKS[k]
            read = ([a[0]] if kind == "fwd" else [a[0]] + ([a[2]] if a[2] >= 0 else []) if kind == "ingrad"
                    else [a[0], a[1]] if kind == "latent" else [])
            assert all(p < updated_at[lay_] for lay_ in read), (p, kind)
    assert prog.smem_bytes <= gmr_cuda.SMEM_LIMIT


def test_compact_layout_holds_every_trained_weight():
    """The compact θ keeps every real weight and bias of the padded layout (and only padding
    beyond them): packing a network and gathering it loses nothing."""
    cfg = GMRConfig()
    pol = make_policy("gmr", cfg)
    params = pol.init(jax.random.key(0), 12, 6, jnp.float32)
    lay = gmr_kernel.layout(cfg, 12, 6, 20)
    padded = np.asarray(gmr_kernel.pack(cfg, lay, params.net))
    index = gmr_cuda.compact_index(gmr_cuda.compact(lay))
    assert len(set(index.tolist())) == len(index)
    outside = np.setdiff1d(np.arange(lay.size), index)
    assert np.all(padded[outside] == 0)
    assert np.count_nonzero(padded[index]) == np.count_nonzero(padded)


def test_cuda_form_refuses_what_it_does_not_run():
    """One-line errors: float64, a non-leaky ReLU, no GPU."""
    with pytest.raises(ValueError, match="float32 only"):
        gmr_cuda.check_supported(GMRConfig(), jnp.float64)
    with pytest.raises(ValueError, match="negative_slope > 0"):
        gmr_cuda.check_supported(GMRConfig(negative_slope=0.0), jnp.float32)
    if jax.default_backend() != "gpu":
        with pytest.raises(ValueError, match="needs an NVIDIA GPU"):
            gmr_cuda.check_supported(GMRConfig(), jnp.float32)
    with pytest.raises(ValueError, match="hidden layer in each"):
        gmr_cuda.program(GMRConfig(decoder_hidden=()), gmr_kernel.layout(GMRConfig(decoder_hidden=()), 12, 6, 20),
                         20, 960, 0)


@pytest.mark.skipif(shutil.which("nvcc") is None, reason="needs nvcc")
def test_kernel_builds_for_hopper_without_spills(tmp_path):
    """The .cu file compiles for sm_90 (with the FFI's headers) and its kernel spills no
    registers (a spill would put the step's accumulators in local memory)."""
    out = tmp_path / "gmr_cuda.so"
    flags = [f for f in gmr_cuda._nvcc_flags() if not f.startswith("-arch")] + ["-arch=sm_90", "-Xptxas", "-v"]
    messages = gmr_cuda.build(out, flags)
    assert out.stat().st_size > 0
    lines = [ln for ln in messages.splitlines() if "spill" in ln]
    assert lines and all("0 bytes spill stores, 0 bytes spill loads" in ln for ln in lines), lines

"""GMR's CUDA S-step (``gmr_cuda``): its program and arithmetic emulated on the host (``emulate``: the
.cu file's gather, latent and head items ported line by line onto a flat copy of shared memory laid
out by the program; the products on whole buffers) against the packed form (same minibatches,
noise and Adam steps: equal to round-off); the program's phases free of races; the names of the
.cu file's enums; clear errors where the CUDA form does not run; and, where nvcc is present, that
the kernel builds for Hopper without spilling registers. The kernel itself runs on a GPU only: a
test here compares it with the packed form where one is (skipped in CI), and
``benchmarks.sstep --impl packed,cuda`` measures both. The emulation is a port, so a change to the
.cu file's arithmetic needs the same change here to be checked in CI."""

import re
import shutil

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.flatten_util import ravel_pytree

from gmr_jax import mdgps, sstep
from gmr_jax.config import GMRConfig, SStepConfig
from gmr_jax.policies import gmr_cuda, gmr_kernel, make_policy

import jaxprs
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
    assert f"constexpr int NT_MAX = {gmr_cuda.THREADS};" in CU
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


def emulate(inp: gmr_cuda.Inputs, smem_bytes: int):
    """The kernel's program run on the host in the inputs' dtype: (θ [n], stats [steps, 8]).

    Shared memory is one flat array laid out by the program (θ's layers with their strides, every
    buffer at its offset with its leading dimension), so that buffers that share memory share it
    here too. Every task is the .cu file's item function line by line, with its index formulas (an
    index that reads past a row reads what lies there), run item by item as the kernel walks a
    phase's items over its tasks (the program's item counts); a product item's sums over k or
    rows run as one dot product (the same terms, in float64 round-off of another order)."""
    P = np.asarray(inp.program)
    h = dict(zip(gmr_cuda.HEADER, P[:len(gmr_cuda.HEADER)].tolist()))
    dt = np.asarray(inp.theta0).dtype
    f = {k: dt.type(v) for k, v in zip(gmr_cuda.FLOATS, np.asarray(inp.floats))}
    layers = P[h["layers"]: h["layers"] + 5 * h["n_layers"]].reshape(-1, 5)
    bufs = P[h["bufs"]: h["bufs"] + 2 * h["n_bufs"]].reshape(-1, 2)
    tasks = P[h["tasks"]: h["tasks"] + gmr_cuda.TASK_INTS * h["n_tasks"]].reshape(-1, gmr_cuda.TASK_INTS)
    phases = P[h["phases"]: h["phases"] + 3 * h["n_phases"]].reshape(-1, 3)
    dX, dU, X, U, lat, bs = (h[k] for k in ("dX", "dU", "X", "U", "lat", "bs"))
    idx, eps, c1, c2 = (np.asarray(a) for a in (inp.idx, inp.eps, inp.c1, inp.c2))
    R = gmr_kernel.KernelRows(*(np.asarray(a).reshape(-1) for a in inp.rows))  # flat, as the kernel reads them
    theta0 = np.asarray(inp.theta0)
    F = {name: i for i, name in enumerate(gmr_cuda.FIXED_BUFFERS)}
    sm = np.full(smem_bytes // 4, np.nan, dt)  # unwritten shared memory is NaN here: reading it shows
    m, v = np.zeros_like(theta0), np.zeros_like(theta0)
    off = lambda b: int(bufs[b][0])  # noqa: E731
    ld = lambda b: int(bufs[b][1])  # noqa: E731
    view = lambda b: sm[off(b): off(b) + bs * ld(b)].reshape(bs, ld(b))  # noqa: E731
    pad4 = gmr_cuda.pad4
    slope = f["slope"]
    leaky = lambda x: np.where(x >= 0, x, slope * x)  # noqa: E731

    def weights(lay):
        coff, soff, K, N, S = (int(x) for x in layers[lay])
        return sm[soff: soff + (K + 1) * S].reshape(K + 1, S)[:, :N]  # a view: Adam writes through it

    for lay, (coff, _, K, N, _) in enumerate(layers):
        weights(lay)[:] = theta0[coff: coff + (K + 1) * N].reshape(K + 1, N)
    NG, NC = int(layers[h["l_gain"]][3]), int(layers[h["l_chol"]][3])

    def B(name, i):  # the index of entry i of a fixed buffer in shared memory
        return off(F[name]) + i

    def gather(step, i):
        rows = idx[step]
        if i < bs * dX:
            r, j = divmod(i, dX)
            row = int(rows[r])
            sm[B("xin", r * ld(F["xin"]) + j)] = R.xn[row * X + j]
            if j == 0:
                sm[B("rows", r)], sm[B("wrow", r)], sm[B("ldp", r)] = row, R.wt[row], R.logdet[row]
            return
        i -= bs * dX
        if i < bs * ld(F["gz"]):
            sm[B("gz", i)] = 0
            return
        i -= bs * ld(F["gz"])
        qx, qu, qe = pad4(dX) // 4, pad4(dU) // 4, pad4(dX + 1) // 4
        if i < bs * dX * qx:
            r, j, q = i // (dX * qx), (i // qx) % dX, i % qx
            src, dst = (int(rows[r]) * X + j) * X + 4 * q, B("sig", r * ld(F["sig"]) + j * pad4(dX) + 4 * q)
            sm[dst: dst + 4] = R.sig[src: src + 4]
            return
        i -= bs * dX * qx
        if i < bs * dU * qu:
            r, a, q = i // (dU * qu), (i // qu) % dU, i % qu
            src, dst = (int(rows[r]) * U + a) * U + 4 * q, B("prc", r * ld(F["prc"]) + a * pad4(dU) + 4 * q)
            sm[dst: dst + 4] = R.prc[src: src + 4]
            return
        i -= bs * dU * qu
        if i < bs * qe:
            r, q = divmod(i, qe)
            src, dst = int(rows[r]) * X + 4 * q, B("xe", r * ld(F["xe"]) + 4 * q)
            sm[dst: dst + 4] = R.xe[src: src + 4]
            return
        i -= bs * qe
        r, q = divmod(i, qu)
        src, dst = int(rows[r]) * U + 4 * q, B("tgt", r * ld(F["tgt"]) + 4 * q)
        sm[dst: dst + 4] = R.tgt[src: src + 4]

    def latent(step, t, i):
        r, j = divmod(i, lat)
        Wm, Wv = weights(t[0]), weights(t[1])
        K = Wm.shape[0] - 1
        x = view(t[2])[r]
        mu, lv = dt.type(0), dt.type(0)
        for k in range(K):
            mu, lv = x[k] * Wm[k, j] + mu, x[k] * Wv[k, j] + lv
        mu, lv = mu + Wm[K, j], lv + Wv[K, j]
        e = eps[step, r, j]
        sm[B("mu", r * ld(F["mu"]) + j)], sm[B("lv", r * ld(F["lv"]) + j)] = mu, lv
        sm[B("z", r * ld(F["z"]) + j)] = mu + np.exp(dt.type(0.5) * lv) * e
        sm[B("klt", r * ld(F["klt"]) + j)] = mu * mu + np.exp(lv) - lv - 1

    def latent_grad(step, i):
        r, j = divmod(i, lat)
        w = sm[B("wrow", r)]
        ct = f["alpha"] * dt.type(0.5) * f["rho"] * w
        mu, lv, gz = (sm[B(n, r * ld(F[n]) + j)] for n in ("mu", "lv", "gz"))
        e = eps[step, r, j]
        sm[B("gmu", r * ld(F["gmu"]) + j)] = gz + ct * (2 * mu)
        sm[B("glv", r * ld(F["glv"]) + j)] = gz * e * (dt.type(0.5) * np.exp(dt.type(0.5) * lv)) + ct * (np.exp(lv) - 1)

    def head1(i):
        if i < bs * dU:
            r, a = divmod(i, dU)
            C, G = B("cout", r * ld(F["cout"])), B("gout", r * ld(F["gout"]))
            tt = np.tanh(sm[C + a * U + a] / f["s"])
            log_sigma = f["half_log_init_var"] + f["s"] * tt
            T = B("T", r * dU * dU + a * dU)
            ss = dt.type(0)
            for b in range(dU):
                Tb = np.tanh(sm[C + a * U + b] / f["c"])
                Vb = (f["c"] * Tb if b < a else 0) + (1 if b == a else 0)
                sm[T + b] = Tb
                ss = Vb * Vb + ss
            rn = np.sqrt(ss)
            srn = np.exp(log_sigma) / rn
            for b in range(dU):
                sm[B("L", r * dU * dU + a * dU + b)] = srn * ((f["c"] * sm[T + b] if b < a else 0) + (1 if b == a else 0))
            sm[B("ts", r * dU + a)], sm[B("srn", r * dU + a)], sm[B("rn", r * dU + a)] = tt, srn, rn
            sm[B("ldt", r * dU + a)] = log_sigma - np.log(rn)
            xe = B("xe", r * ld(F["xe"]))
            du = dt.type(0)
            for j in range(dX + 1):
                du = sm[G + a * X + j] * sm[xe + j] + du
            sm[B("du", r * dU + a)] = du - sm[B("tgt", r * ld(F["tgt"]) + a)]
        else:
            i -= bs * dU
            r, a, j = i // (dU * dX), (i // dX) % dU, i % dX
            row = int(sm[B("rows", r)])
            G = B("gout", r * ld(F["gout"]))
            sm[B("dk", r * dU * dX + a * dX + j)] = sm[G + a * X + j] * R.scale[j] - R.K[(row * U + a) * X + j]

    def p_row_times(r, a, Y, cols, j):
        Pr = B("prc", r * ld(F["prc"]) + a * pad4(dU))
        s = dt.type(0)
        for k in range(dU):
            s = sm[Pr + k] * sm[Y + k * cols + j] + s
        return s

    def head2(i):
        if i < bs * dU * dX:
            r, a, j = i // (dU * dX), (i // dX) % dU, i % dX
            dK, sg = B("dk", r * dU * dX + a * dX), B("sig", r * ld(F["sig"]) + j * pad4(dX))
            s = dt.type(0)
            for k in range(dX):
                s = sm[dK + k] * sm[sg + k] + s
            sm[B("dks", r * dU * dX + a * dX + j)] = s
            return
        i -= bs * dU * dX
        if i < bs * dU:
            r, a = divmod(i, dU)
            Pr, du = B("prc", r * ld(F["prc"]) + a * pad4(dU)), B("du", r * dU)
            s = dt.type(0)
            for b in range(dU):
                s = sm[Pr + b] * sm[du + b] + s
            sm[B("pdu", r * dU + a)] = s
            return
        i -= bs * dU
        r, a, b = i // (dU * dU), (i // dU) % dU, i % dU
        sm[B("pl", r * dU * dU + a * dU + b)] = p_row_times(r, a, B("L", r * dU * dU), dU, b)

    def head3(i):
        if i < bs * dU * dX:
            r, a, j = i // (dU * dX), (i // dX) % dU, i % dX
            sm[B("pdks", r * dU * dX + a * dX + j)] = p_row_times(r, a, B("dks", r * dU * dX), dX, j)
            return
        i -= bs * dU * dX
        r, a = divmod(i, dU)
        s = dt.type(0)
        for b in range(dU):
            s = sm[B("L", r * dU * dU + a * dU + b)] * sm[B("pl", r * dU * dU + a * dU + b)] + s
        sm[B("tr", r * dU + a)] = s

    def head4(i):
        rho = f["rho"]
        if i < bs * NG:
            r, n = divmod(i, NG)
            a, j = divmod(n, X)
            xe = sm[B("xe", r * ld(F["xe"]) + j)] if j <= dX else 0
            g = (rho * sm[B("pdu", r * dU + a)]) * xe
            if j < dX:
                g = g + (rho * sm[B("pdks", r * dU * dX + a * dX + j)]) * R.scale[j]
            sm[B("dg", r * ld(F["dg"]) + n)] = g
            return
        i -= bs * NG
        if i < bs * NC:
            r, n = divmod(i, NC)
            a, b = divmod(n, U)
            g = dt.type(0)
            if a < dU and b <= a:
                q = rho * sm[B("tr", r * dU + a)] + (-rho) * sm[B("wrow", r)]
                if b < a:
                    e = r * dU * dU + a * dU + b
                    rn = sm[B("rn", r * dU + a)]
                    gV = sm[B("srn", r * dU + a)] * (rho * sm[B("pl", e)]) - (q / (rn * rn)) * (f["c"] * sm[B("T", e)])
                    g = gV * (1 - sm[B("T", e)] ** 2)
                else:
                    g = q * (1 - sm[B("ts", r * dU + a)] ** 2)
            sm[B("dc", r * ld(F["dc"]) + n)] = g
            return
        i -= bs * NC
        if i < bs * dX:
            r, j = divmod(i, dX)
            diff = sm[B("xin", r * ld(F["xin"]) + j)] - sm[B("xhat", r * ld(F["xhat"]) + j)]
            sm[B("dxh", r * ld(F["dxh"]) + j)] = (-2 * rho * sm[B("wrow", r)]) * diff
            return
        r = i - bs * dX
        w = sm[B("wrow", r)]
        du, pdu = sm[B("du", r * dU): B("du", r * dU) + dU], sm[B("pdu", r * dU): B("pdu", r * dU) + dU]
        tr, ldt = sm[B("tr", r * dU): B("tr", r * dU) + dU], sm[B("ldt", r * dU): B("ldt", r * dU) + dU]
        dK = sm[B("dk", r * dU * dX): B("dk", r * dU * dX) + dU * dX]
        pdks = sm[B("pdks", r * dU * dX): B("pdks", r * dU * dX) + dU * dX]
        xin, xhat = sm[B("xin", r * ld(F["xin"])):][:dX], sm[B("xhat", r * ld(F["xhat"])):][:dX]
        klt = sm[B("klt", r * ld(F["klt"])):][:lat]
        out = B("rowstat", r * (len(gmr_cuda.STATS) - 2))
        sm[out: out + 6] = [np.sum(du * pdu), np.sum(du * du) / f["dU"],
                            np.sum(tr) - w * (2 * np.sum(ldt) + f["dU"] + sm[B("ldp", r)]),
                            np.sum(dK * pdks), w * dt.type(0.5) * np.sum(klt), w * np.sum((xin - xhat) ** 2)]

    RG, KG = gmr_cuda.ROWS_PER_ITEM, gmr_cuda.WEIGHT_ROWS_PER_ITEM

    def row(b, r, n):  # entries [0, n) of row r of buffer b
        return sm[off(b) + r * ld(b): off(b) + r * ld(b) + n]

    def fwd(a, i):
        _, soff, K, N, S = (int(x) for x in layers[a[0]])
        n, r0 = i % N, (i // N) * RG
        w = sm[soff + n: soff + K * S + n: S]  # W[k * S + n], k < K
        for j in range(RG):
            if r0 + j < bs:
                pre = row(a[1], min(r0 + j, bs - 1), K) @ w + sm[soff + K * S + n]
                sm[off(a[2]) + (r0 + j) * ld(a[2]) + n] = leaky(pre) if a[3] else pre

    def transposed_product(lay, d, k, r0):
        _, soff, _, N, S = (int(x) for x in layers[lay])
        w = sm[soff + k * S: soff + k * S + N]
        return [row(d, min(r0 + j, bs - 1), N) @ w for j in range(RG)]

    def ingrad(a, i):
        K = int(layers[a[0]][2])
        k, r0 = i % K, (i // K) * RG
        acc = transposed_product(a[0], a[1], k, r0)
        acc2 = transposed_product(a[2], a[3], k, r0) if a[2] >= 0 else None
        for j in range(RG):
            r = r0 + j
            if r >= bs:
                continue
            g = acc[j] + acc2[j] if a[2] >= 0 else acc[j]
            out = off(a[4]) + r * ld(a[4]) + k
            if a[6]:
                g = sm[out] + g
            if a[5] >= 0:
                g = g if sm[off(a[5]) + r * ld(a[5]) + k] >= 0 else slope * g
            sm[out] = g

    def wgrad(a, i, step):
        coff, soff, K, N, S = (int(x) for x in layers[a[0]])
        n, k0 = i % N, (i // N) * KG
        g0 = coff + k0 * N + n
        hs = lambda k: sm[off(a[1]) + k: off(a[1]) + (bs - 1) * ld(a[1]) + k + 1: ld(a[1])]  # noqa: E731
        D = sm[off(a[2]) + n: off(a[2]) + (bs - 1) * ld(a[2]) + n + 1: ld(a[2])]
        if k0 + KG <= K:
            acc = [hs(k0 + q) @ D for q in range(KG)]
        else:
            acc = [hs(k) @ D if k < K else (np.sum(D) if k == K else 0) for k in range(k0, k0 + KG)]
        l2 = dt.type(0)
        rc1, rc2 = 1 / c1[step], 1 / c2[step]
        for q in range(KG):
            k = k0 + q
            if k <= K:
                e, pos = g0 + q * N, soff + k * S + n
                th = sm[pos]
                l2 += th * th
                g = acc[q] + f["wd"] * (2 * th)
                m[e] = f["one_minus_b1"] * g + f["b1"] * m[e]
                v[e] = f["one_minus_b2"] * (g * g) + f["b2"] * v[e]
                # the kernel's form of Adam's update: the corrections as reciprocals, one division
                sm[pos] = th + -f["lr"] * ((m[e] * rc1) / (np.sqrt(v[e] * rc2) + f["eps"]))
        return l2

    stats = np.zeros((len(idx), len(gmr_cuda.STATS)), dt)
    for step in range(len(idx)):
        l2 = dt.type(0)
        items = {"gather": lambda a, i: gather(step, i), "fwd": fwd, "ingrad": ingrad,
                 "latent": lambda a, i: latent(step, a, i), "head1": lambda a, i: head1(i),
                 "head2": lambda a, i: head2(i), "head3": lambda a, i: head3(i), "head4": lambda a, i: head4(i),
                 "latent_grad": lambda a, i: latent_grad(step, i)}
        for first, _, total in phases:
            for i in range(total):  # the kernel's walk: item i of the phase -> its task and the item in it
                t, base = first, 0
                while i >= base + tasks[t][1]:
                    base += tasks[t][1]
                    t += 1
                kind, a = gmr_cuda.TASKS[tasks[t][0]], [int(x) for x in tasks[t][2:]]
                if kind == "wgrad":
                    l2 += wgrad(a, i - base, step)
                else:
                    items[kind](a, i - base)
        if step >= h["stats_from"]:
            aux = np.sum(f["rho"] * view(F["rowstat"])[:, :6], axis=0)
            aux[[0, 2, 3]] *= 0.5
            value = aux[5] + f["alpha"] * aux[4] + aux[0] + aux[3] + aux[2]
            stats[step] = np.concatenate([[value + f["wd"] * l2, value], aux])
    theta = np.concatenate([weights(lay).reshape(-1) for lay in range(len(layers))])
    return theta, stats


def emulated_launch(inp: gmr_cuda.Inputs, smem_bytes):
    """``gmr_cuda.launch`` by ``emulate`` (a host callback, under jit and vmap)."""
    assert smem_bytes <= gmr_cuda.SMEM_LIMIT
    dt = inp.theta0.dtype
    shapes = (jax.ShapeDtypeStruct(inp.theta0.shape, dt), jax.ShapeDtypeStruct((inp.idx.shape[0], 8), dt))

    def host(idx, eps, c1, c2, rows, theta0):
        return tuple(np.asarray(a, dt) for a in emulate(inp._replace(idx=idx, eps=eps, c1=c1, c2=c2, rows=rows,
                                                                     theta0=theta0), smem_bytes))
    return jax.pure_callback(host, shapes, inp.idx, inp.eps, inp.c1, inp.c2, inp.rows, inp.theta0,
                             vmap_method="sequential")


@pytest.fixture
def emulated(monkeypatch):
    monkeypatch.setattr(gmr_cuda, "launch", emulated_launch)
    monkeypatch.setattr(gmr_cuda, "check_supported", lambda cfg, dtype: None)


@pytest.mark.parametrize("name, batch_size", [("gmr", 20), ("gmr_uneven", 20), ("gmr", 18)])
def test_emulated_program_equals_the_packed_form(name, batch_size, emulated):
    """The kernel's program, emulated on the host in float64, against the packed form: the same
    minibatches, noise and Adam steps with the sums in another order, so the bound of
    ``test_sstep.test_kernel_sstep_equals_packed`` holds (8·δ·lr·S on the weights, 2δ on the
    metrics), for GMR's standardised and raw head coordinates, for networks of different
    depths (the decoder's and the translation network's backward passes then end in different
    phases), and for a minibatch that is not a whole number of the products' row groups (18
    rows: the last group's reads clamped to the last row, its writes skipped)."""
    new_m, ref_m, delta = _forms_agree(name, "packed", "cuda", jnp.float64, batch_size=batch_size)
    _metrics_agree(new_m, ref_m, delta)
    assert bool(new_m["finite"]) and bool(new_m["weights_ok"])


@pytest.mark.skipif(jax.default_backend() != "gpu" or shutil.which("nvcc") is None, reason="needs an NVIDIA GPU and nvcc")
@pytest.mark.parametrize("name", ["gmr", "gmr_uneven"])
def test_kernel_equals_the_packed_form_on_the_gpu(name):
    """The kernel itself (not its emulation) against the packed form in float32, within the bound
    above; skipped off a GPU (CI), run by hand where one is. The packed form is traced with full
    float32 products, as training traces it (``mdgps.MATMUL_PRECISION``): under a GPU's default,
    TF32, the packed form's products are less accurate than the kernel's, and the test failed (an
    H200: a weight 7 times the bound apart after ten steps)."""
    with jax.default_matmul_precision(mdgps.MATMUL_PRECISION):
        new_m, ref_m, delta = _forms_agree(name, "packed", "cuda", jnp.float32)
    _metrics_agree(new_m, ref_m, delta)


@pytest.mark.skipif(jax.default_backend() != "gpu" or shutil.which("nvcc") is None, reason="needs an NVIDIA GPU and nvcc")
@pytest.mark.parametrize("statistics_epochs", ["all", "last"])
def test_every_launch_form_trains_the_same_weights_on_the_gpu(monkeypatch, statistics_epochs):
    """A thread-block cluster's blocks run each phase's items as one block does, each item the
    same arithmetic in the same order, and keep identical copies of the state: every launch form
    (each reports the form it ran) trains bit-identical weights and statistics, with every
    epoch's statistics and with the last epoch's only (where the steps before skip the head's
    per-row loss terms). The one exception is the total loss's β·Σθ², whose sum the blocks
    split: any order of n positive terms lies within (n − 1)·ε of the sum, plus the rounding of
    the total itself."""
    pol, _ = test_sstep._policy("gmr")
    data = jax.tree_util.tree_map(lambda a: a.astype(jnp.float32), test_sstep._full_data(13))
    params = pol.init(jax.random.key(2), test_sstep.dX, test_sstep.dU, jnp.float32)
    scfg = SStepConfig(epochs=3, statistics_epochs=statistics_epochs)
    launch, ran = gmr_cuda.launch, []

    def reporting(inp, smem_bytes):
        theta, stats, _, form = launch(inp, smem_bytes, cycles=True)
        jax.debug.callback(lambda f: ran.append(gmr_cuda.form_name(int(np.asarray(f).reshape(-1)[0]))), form)
        return theta, stats

    monkeypatch.setattr(gmr_cuda, "launch", reporting)
    runs = {}
    for form in gmr_cuda.FORMS:
        with gmr_cuda.launch_form(form):
            # a new jit per form: the form is part of the program traced
            runs[form] = jax.block_until_ready(jax.jit(lambda p, d, k: test_sstep.sstep(pol, p, d, k, scfg, impl="cuda"))(
                params, data, jax.random.key(3)))
        jax.effects_barrier()  # the callback has run
        assert ran[-1] == form
    ref, ref_m = runs["1x1024"]
    assert not np.allclose(ravel_pytree(ref.net)[0], ravel_pytree(params.net)[0], atol=1e-3)
    n = ravel_pytree(ref.net)[0].size
    eps = float(jnp.finfo(jnp.float32).eps)
    for form, (new, new_m) in runs.items():
        for a, b in zip(jax.tree_util.tree_leaves(new), jax.tree_util.tree_leaves(ref)):
            np.testing.assert_array_equal(a, b, err_msg=form)
        for key in ("data_loss", "aux"):
            jax.tree_util.tree_map(lambda a, b: np.testing.assert_array_equal(a, b, err_msg=form), new_m[key], ref_m[key])
        l2_term = np.abs(np.asarray(ref_m["loss"]) - np.asarray(ref_m["data_loss"]))
        np.testing.assert_array_less(np.abs(np.asarray(new_m["loss"]) - np.asarray(ref_m["loss"])),
                                     (n - 1) * eps * l2_term + 2 * eps * np.abs(np.asarray(ref_m["loss"])) + 1e-30)


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


def test_cuda_sstep_unpacks_the_kernels_weights_by_gathers(monkeypatch):
    """``sstep(impl="cuda")`` over two seeds (``jax.vmap``) with a kernel that returns its starting
    θ: the returned networks are the starting ones bit for bit (compact θ -> Flax tree), and the
    S-step's program holds no scatter that may repeat an index. XLA's deterministic GPU options
    rewrite such a scatter into a sort of its indices: the 256-seed ``train`` program compiled
    in 43 s instead of 31 s with the scatters this path had (benchmarks/RESULTS.md, forty-eighth
    session)."""
    def unchanged(inp, smem_bytes):
        return inp.theta0, jnp.zeros((inp.idx.shape[0], len(gmr_cuda.STATS)), inp.theta0.dtype)

    monkeypatch.setattr(gmr_cuda, "launch", unchanged)
    monkeypatch.setattr(gmr_cuda, "check_supported", lambda cfg, dtype: None)
    pol, _ = test_sstep._policy("gmr")
    data = jax.tree_util.tree_map(lambda a: a.astype(jnp.float32), test_sstep._full_data(12))
    inits = [pol.init(jax.random.key(s), test_sstep.dX, test_sstep.dU, jnp.float32) for s in range(2)]
    params = jax.tree_util.tree_map(lambda *a: jnp.stack(a), *inits)
    keys = jax.random.split(jax.random.key(3), 2)
    run = jax.vmap(lambda p, k: sstep.sstep(pol, p, data, k, SStepConfig(epochs=1), impl="cuda"))
    new, _ = jax.jit(run)(params, keys)
    assert jax.tree_util.tree_structure(new.net) == jax.tree_util.tree_structure(params.net)
    for a, b in zip(jax.tree_util.tree_leaves(new.net), jax.tree_util.tree_leaves(params.net)):
        np.testing.assert_array_equal(a, b)
    program = jax.make_jaxpr(run)(params, keys).jaxpr
    assert any(e.primitive.name == "gather" for e in jaxprs.equations(program))
    assert jaxprs.scatters_that_may_repeat_an_index(program) == []


def test_unpack_refuses_positions_that_miss_a_weight():
    """``gmr_kernel.unpack`` with ``position``: one line naming the layer whose entry the other
    vector does not hold, not weights silently left at their old values."""
    cfg = GMRConfig()
    params = make_policy("gmr", cfg).init(jax.random.key(0), 12, 6, jnp.float32)
    lay = gmr_kernel.layout(cfg, 12, 6, 20)
    position = gmr_cuda.compact_position(lay)
    held = gmr_cuda.compact_index(gmr_cuda.compact(lay))
    np.testing.assert_array_equal(position[held], np.arange(len(held)))  # the inverse of compact_index
    assert np.count_nonzero(position >= 0) == len(held)
    position[held[0]] = -1  # the first layer's first weight
    with pytest.raises(ValueError, match="does not hold every entry of encoder's Dense_0"):
        gmr_kernel.unpack(cfg, lay, params.net, jnp.zeros(len(held)), position)


def test_cuda_form_refuses_what_it_does_not_run():
    """One-line errors: float64, a non-leaky ReLU, no GPU."""
    with pytest.raises(ValueError, match="float32 only"):
        gmr_cuda.check_supported(GMRConfig(), jnp.float64)
    with pytest.raises(ValueError, match="negative_slope > 0"):
        gmr_cuda.check_supported(GMRConfig(negative_slope=0.0), jnp.float32)
    with jax.default_device(jax.devices("cpu")[0]):  # a program placed on the host, GPU or not
        with pytest.raises(ValueError, match="needs an NVIDIA GPU"):
            gmr_cuda.check_supported(GMRConfig(), jnp.float32)
    with pytest.raises(ValueError, match="hidden layer in each"):
        gmr_cuda.program(GMRConfig(decoder_hidden=()), gmr_kernel.layout(GMRConfig(decoder_hidden=()), 12, 6, 20),
                         20, 960, 0)


def test_launch_forms_are_the_cu_files_and_set_only_within():
    """``FORMS`` are the launch forms the .cu file's dispatch builds (each case's code,
    cluster·10000 + threads, launches that template), the cluster forms' threads per block those
    its choice uses; ``launch_form`` sets the form of the programs traced within only, and an
    unknown form is one clear error."""
    built = sorted((int(code), int(b), int(t)) for code, b, t in re.findall(r"case (\d+): err = launch<(\d+), (\d+)>", CU))
    assert built == sorted((gmr_cuda.form_code(f), *map(int, f.split("x"))) for f in gmr_cuda.FORMS)
    assert all(code == b * 10000 + t for code, b, t in built)
    assert "1x1024" in gmr_cuda.FORMS and "constexpr int CLUSTER_NT = 512;" in CU
    assert {int(f.split("x")[0]) for f in gmr_cuda.FORMS} == {1, 2, 4, gmr_cuda.MAX_CLUSTER}
    assert gmr_cuda.form_code("auto") == 0 and gmr_cuda.form_name(0) == "auto"
    assert all(gmr_cuda.form_name(gmr_cuda.form_code(f)) == f for f in gmr_cuda.FORMS)
    assert gmr_cuda._FORM.get() == "auto"
    with gmr_cuda.launch_form("8x256"):
        assert gmr_cuda._FORM.get() == "8x256"
        with gmr_cuda.launch_form("auto"):
            assert gmr_cuda._FORM.get() == "auto"
        with gmr_cuda.launch_form(None):
            assert gmr_cuda._FORM.get() == "8x256"
    assert gmr_cuda._FORM.get() == "auto"
    with pytest.raises(ValueError, match=r"^CUDA launch form '8x1024': the built forms are 1x1024, .* \(or auto\)$"):
        with gmr_cuda.launch_form("8x1024"):
            pass


def test_ablations_are_the_cu_files_macros_and_bad_names_are_one_line(monkeypatch):
    """Each of ``ABLATIONS`` is a macro of the .cu file that the build's flags define when
    ``$GMR_JAX_CUDA_ABLATE`` names it (and only then: the training build has none); an unknown
    name is one clear error, in the library and in the benchmark's variants."""
    from benchmarks import sstep_ablation

    used = set(re.findall(r"^#ifn?def GMR_CUDA_ABLATE_(\w+)$", CU, re.M))
    listed = set(re.findall(r"^//   ([A-Z_]+) ", CU.split("// Ablations")[1].split("#include")[0], re.M))
    any_of = set(re.findall(r"defined\(GMR_CUDA_ABLATE_(\w+)\)", CU))  # GMR_CUDA_ABLATED: Adam's stand-in
    assert used == listed == any_of == {n.upper() for n in gmr_cuda.ABLATIONS}
    monkeypatch.delenv("GMR_JAX_CUDA_ABLATE", raising=False)
    assert gmr_cuda.ablations() == ()
    assert not any("ABLATE" in f for f in gmr_cuda._nvcc_flags())
    monkeypatch.setenv("GMR_JAX_CUDA_ABLATE", "head+moments, moments")
    assert gmr_cuda.ablations() == ("moments", "head")
    assert [f for f in gmr_cuda._nvcc_flags() if "ABLATE" in f] == ["-DGMR_CUDA_ABLATE_MOMENTS", "-DGMR_CUDA_ABLATE_HEAD"]
    monkeypatch.setenv("GMR_JAX_CUDA_ABLATE", "moments,adam")
    with pytest.raises(ValueError, match="GMR_JAX_CUDA_ABLATE names adam: the ablations are moments"):
        gmr_cuda.ablations()
    assert sstep_ablation.parse_variant("none") == ()
    assert sstep_ablation.parse_variant("all") == gmr_cuda.ABLATIONS
    assert sstep_ablation.parse_variant(" moments + head") == ("moments", "head")
    with pytest.raises(SystemExit, match="unknown ablation 'sums'"):
        sstep_ablation.parse_variant("moments+sums")


def test_ablation_benchmark_keeps_measured_variants_when_one_fails(tmp_path, monkeypatch):
    """``benchmarks.sstep_ablation``: each variant's process gets its ablations in the
    environment; a variant that runs over ``--timeout`` or fails is one clear error, and the
    variants measured before it stay in ``--out`` (the sstep processes are stood in for)."""
    import json
    import subprocess

    from benchmarks import sstep_ablation

    seen = []

    def fake_run(cmd, env=None, timeout=None, **kw):
        if cmd[0] == "nvcc":  # the version recorded beside the results
            return subprocess.CompletedProcess(cmd, 0, "Build stand-in\n", "")
        seen.append(env["GMR_JAX_CUDA_ABLATE"])
        if env["GMR_JAX_CUDA_ABLATE"] == "head":
            raise subprocess.TimeoutExpired(cmd, timeout)
        if env["GMR_JAX_CUDA_ABLATE"] == "barriers":
            return subprocess.CompletedProcess(cmd, 1, "", "Traceback ...\nRuntimeError: no GPU")
        out = cmd[cmd.index("--out") + 1]
        us = {"": 71.0, "moments": 65.5}[env["GMR_JAX_CUDA_ABLATE"]]
        with open(out, "w") as f:
            json.dump({"env": {"device": "stand-in"}, "rows": [{"us_per_step": us, "finite": True}]}, f)
        return subprocess.CompletedProcess(cmd, 0, "", "")

    monkeypatch.setattr(sstep_ablation.subprocess, "run", fake_run)
    out = tmp_path / "a.json"
    with pytest.raises(SystemExit, match=r"variant head took more than --timeout 5 s: raise --timeout"):
        sstep_ablation.main(["--variants", "none,moments,head", "--timeout", "5", "--out", str(out)])
    assert seen == ["", "moments", "head"]
    written = json.loads(out.read_text())
    assert [(r["ablations"], r["us_per_step"]) for r in written["rows"]] == [([], 71.0), (["moments"], 65.5)]
    assert written["env"] == {"device": "stand-in", "nvcc": "Build stand-in"}
    with pytest.raises(SystemExit, match="variant barriers failed") as failed:
        sstep_ablation.main(["--variants", "barriers"])
    assert str(failed.value).endswith("RuntimeError: no GPU")  # the process's own last words


@pytest.mark.skipif(shutil.which("nvcc") is None, reason="needs nvcc")
def test_kernel_builds_for_hopper_without_spills(tmp_path, monkeypatch):
    """The .cu file's device code compiles for sm_90 (with the FFI's headers) and its kernel
    spills no registers (a spill would put the step's accumulators in local memory). The host
    code (the FFI handler) is built with the library, by the GPU-only test."""
    monkeypatch.delenv("GMR_JAX_CUDA_ABLATE", raising=False)  # the training build, not a profile's
    out = tmp_path / "gmr_cuda.cubin"  # the device code alone: ptxas's report is that of the library's build
    host = ("-shared", "-Xcompiler", "-fPIC")
    flags = [f for f in gmr_cuda._nvcc_flags() if not f.startswith("-arch") and f not in host]
    flags += ["-arch=sm_90", "-cubin", "-Xptxas", "-v"]
    messages = gmr_cuda.build(out, flags)
    assert out.stat().st_size > 0
    lines = [ln for ln in messages.splitlines() if "spill" in ln]
    # one kernel per launch form, each without spills
    assert len(lines) == len(gmr_cuda.FORMS), messages
    assert all("0 bytes spill stores, 0 bytes spill loads" in ln for ln in lines), lines


@pytest.mark.skipif(shutil.which("nvcc") is None, reason="needs nvcc")
def test_kernel_builds_for_gpus_without_clusters(tmp_path, monkeypatch):
    """For a GPU before Hopper (sm_80: no thread-block clusters) the device code still compiles:
    its cluster forms become traps that the host never launches there."""
    monkeypatch.delenv("GMR_JAX_CUDA_ABLATE", raising=False)
    out = tmp_path / "gmr_cuda_sm80.cubin"
    host = ("-shared", "-Xcompiler", "-fPIC")
    flags = [f for f in gmr_cuda._nvcc_flags() if not f.startswith("-arch") and f not in host]
    gmr_cuda.build(out, flags + ["-arch=sm_80", "-cubin"])
    assert out.stat().st_size > 0

"""Seeds split over a device mesh (gmr_jax.sharding, the runner): on four XLA CPU devices
(tests/conftest.py) a sharded run equals the single-device run of the same keys, a seed count
the devices do not divide is padded and the padding dropped, and a run resumes on another device
count. The C MuJoCo backend's host callbacks run per device, and a program of them over several
CPU devices finishes."""

import os
import re
import subprocess
import sys
import textwrap

import jax
import numpy as np
import jax.numpy as jnp
import pytest

from tolerances import SAFETY, XLA_DEFAULT_CPU_CODEGEN, assert_trees_within, measured_tol

from gmr_jax import checkpoint, mdgps, runner, sharding
from test_mdgps import _run_from, small

SEEDS = [0, 1, 2, 3]


def four_cpu_devices_env(*flags: str) -> dict:
    """The environment of a test's child process: JAX on four CPU devices, with the suite's code
    generator (tests/conftest.py: the child then compiles as fast as this process) and ``flags``."""
    suite = re.sub(r"--xla_force_host_platform_device_count=\S*", "", os.environ.get("XLA_FLAGS", ""))
    return dict(os.environ, JAX_PLATFORMS="cpu",
                XLA_FLAGS=" ".join([suite.strip(), "--xla_force_host_platform_device_count=4", *flags]).strip())


@pytest.fixture(scope="module")
def cfg():
    return small("lqr", iterations=2)


@pytest.fixture(scope="module")
def four_devices():
    if len(jax.local_devices()) < 4:
        pytest.skip("needs four devices (XLA_FLAGS=--xla_force_host_platform_device_count=4)")
    with runner.Scheduler(compile_jobs=1, devices=4) as sched:
        yield sched


@pytest.fixture(scope="module")
def tolerances(cfg):
    """Per seed, (final state, history) tolerance trees from the computation
    (tests/tolerances.py): the seed's run, one jitted iteration at a time, rerun from its initial
    state perturbed by ε relative; SAFETY times the spread. A device's program runs the same
    operations on a smaller batch of seeds, which XLA may vectorise with other summation orders."""
    out = []
    for seed in SEEDS:
        k_init, keys = mdgps.iteration_keys(jax.random.PRNGKey(seed), cfg.iterations)
        ref, tol = measured_tol(lambda s: _run_from(cfg, s, keys), (mdgps.init(cfg, k_init),), SAFETY)
        out.append(jax.tree_util.tree_unflatten(jax.tree_util.tree_structure(ref), tol))
    return out


@pytest.fixture(scope="module")
def runs(cfg, four_devices, scheduler, tmp_path_factory):
    root = tmp_path_factory.mktemp("sharding")
    one = runner.run(cfg, SEEDS, root / "one", scheduler=scheduler)
    four = runner.run(cfg, SEEDS, root / "four", scheduler=four_devices)
    return root, one, four


def _same(a, b, tolerances):
    """The runs' histories agree seed by seed within the tolerances from the computation."""
    for name, value in a["history"].items():
        for i in range(value.shape[1]):
            if name not in tolerances[i][1]:  # the runner's own flags (seed_failed): exact
                np.testing.assert_array_equal(value[:, i], b["history"][name][:, i], err_msg=name)
                continue
            assert_trees_within(value[:, i], b["history"][name][:, i], tolerances[i][1][name])


def test_sharded_run_equals_the_single_device_run(runs, four_devices, tolerances):
    root, one, four = runs
    assert four_devices.mesh.size == 4
    _same(four, one, tolerances)


def test_uneven_seed_count_is_padded_and_the_padding_dropped(cfg, runs, four_devices, tolerances):
    root, _, four = runs
    three = runner.run(cfg, SEEDS[:3], root / "three", scheduler=four_devices)
    assert three["history"]["sample_cost"].shape[1] == 3
    _same(three, four, tolerances)
    saved, meta = checkpoint.restore(root / "three" / "checkpoints", runner.initial_state(cfg, SEEDS[:3]))
    assert meta["seeds"] == SEEDS[:3] and saved.eta.shape[0] == 3  # checkpoints hold the real seeds only


def test_unpad_copies_the_real_seeds_onto_one_device():
    """A padded array split over four devices comes back as its real rows on the first device,
    for 1–3 and 5–7 seeds (one to three rows of padding) and for the two layouts
    :func:`sharding.place` does not make (replicated, split along another axis). Slicing the
    global array instead gives an array on all four devices, from a program over the mesh whose
    all-gather is a rendezvous of every device (tests/test_sharding.py's runs unpad often)."""
    from jax.sharding import NamedSharding, PartitionSpec

    if len(jax.local_devices()) < 4:
        pytest.skip("needs four devices (XLA_FLAGS=--xla_force_host_platform_device_count=4)")
    mesh = sharding.seed_mesh(4)
    first = {jax.local_devices()[0]}
    for num in (1, 2, 3, 5, 6, 7):
        rows = np.arange(num * 6, dtype=np.float64).reshape(num, 2, 3)
        padded = sharding.place(sharding.pad(jnp.asarray(rows), num, mesh), mesh)
        assert len(padded.sharding.device_set) == 4
        real = sharding.unpad({"x": padded}, num)["x"]
        assert real.sharding.device_set == first
        np.testing.assert_array_equal(np.asarray(real), rows)
    table = np.arange(32.0).reshape(4, 8)
    for spec in (PartitionSpec(), PartitionSpec(None, sharding.AXIS)):
        real = sharding.unpad(jax.device_put(table, NamedSharding(mesh, spec)), 3)
        assert real.sharding.device_set == first
        np.testing.assert_array_equal(np.asarray(real), table[:3])


_UNPAD_FROM_TWO_THREADS = textwrap.dedent("""
    import concurrent.futures
    import jax, jax.numpy as jnp, numpy as np
    jax.config.update("jax_enable_x64", True)
    from gmr_jax import sharding
    mesh = sharding.seed_mesh(4)
    trees = [sharding.place(sharding.pad({j: jnp.arange(3.0 * (j + 1) * (i + 1)).reshape(3, -1) for j in range(30)},
                                         3, mesh), mesh) for i in range(2)]
    advance = jax.jit(lambda t: jax.tree.map(lambda x: jax.lax.fori_loop(0, 30, lambda _, y: jnp.tanh(y) + 0.5, x), t))

    def unpad_repeatedly(tree):  # as the runner's loop (metrics) and checkpoint writer (state) do
        want = jax.tree.map(lambda a: np.asarray(a)[:3], advance(tree))
        for _ in range(40):
            got = jax.tree.map(np.asarray, sharding.unpad(advance(tree), 3))
            jax.tree.map(np.testing.assert_array_equal, got, want)
        return True

    with concurrent.futures.ThreadPoolExecutor(2) as pool:
        print(all(pool.map(unpad_repeatedly, trees)))
""")


def test_unpad_from_two_threads_at_once_finishes():
    """Two threads unpadding four-device arrays at once, each right after a program that makes
    them: 2 × 40 × 30 leaves. When unpad sliced the global array, each slice was a program over
    the mesh with an all-gather; the two threads' programs reached the devices in different
    orders, every device waited in XLA's rendezvous for a different all-gather, and XLA ended the
    process (this test: 1 of 3 runs of that code on a 2-core host; benchmarks/RESULTS.md,
    thirty-seventh session; 0 of 8 on a 2-core AMD EPYC host in the forty-ninth, 4 with XLA's
    default code generator and 4 with the suite's). In a process of its own, so that such an end
    fails this test and not the suite, with XLA's rendezvous timeout at 10 s instead of 40 s."""
    env = four_cpu_devices_env("--xla_cpu_collective_call_terminate_timeout_seconds=10")
    try:
        done = subprocess.run([sys.executable, "-c", _UNPAD_FROM_TWO_THREADS], env=env, capture_output=True,
                              text=True, timeout=600)
    except subprocess.TimeoutExpired:
        pytest.fail("unpadding from two threads did not finish in 600 s")
    assert done.returncode == 0, done.stderr[-3000:]
    assert done.stdout.split() == ["True"]


def test_resume_on_another_device_count(cfg, runs, four_devices, scheduler, tolerances):
    root, one, _ = runs
    runner.run(cfg, SEEDS, root / "moved", stop_after=1, scheduler=four_devices)
    _same(runner.run(cfg, SEEDS, root / "moved", resume=True, scheduler=scheduler), one, tolerances)
    runner.run(cfg, SEEDS, root / "back", stop_after=1, scheduler=scheduler)
    _same(runner.run(cfg, SEEDS, root / "back", resume=True, scheduler=four_devices), one, tolerances)


def test_library_train_over_a_mesh(cfg, four_devices, tolerances):
    keys = jnp.stack([jax.random.PRNGKey(s) for s in SEEDS[:3]])
    sharded = sharding.train(cfg, keys, four_devices.mesh)
    single = jax.jit(jax.vmap(mdgps.train, in_axes=(None, 0)), static_argnums=0)(cfg, keys)
    for i in range(3):
        pick = lambda t: jax.tree_util.tree_map(lambda a: a[i], t)  # noqa: E731
        assert_trees_within(pick(sharded), pick(single), jax.tree_util.tree_leaves(tolerances[i]))


_HOST_ROLLOUTS_OVER_FOUR_CPU_DEVICES = textwrap.dedent("""
    import jax, jax.numpy as jnp, numpy as np
    jax.config.update("jax_enable_x64", True)
    from gmr_jax import config, sharding, sim, types
    s = sim.make_sim(config.SimConfig(backend="mujoco"))
    S, N, T = 4, 5, 80  # a device's K operand [1, 5, 80, 6, 12] is 230 KB
    k = jax.random.split(jax.random.PRNGKey(0), 3)
    K = 0.01 * jax.random.normal(k[0], (S, T, s.dU, s.dX))
    kk = 0.1 * jax.random.normal(k[1], (S, T, s.dU))
    chol = jnp.broadcast_to(0.1 * jnp.eye(s.dU), (S, T, s.dU, s.dU))
    eps = jax.random.normal(k[2], (S, N, T, s.dU))
    x0 = jnp.zeros((S, N, s.dX))

    def per_seed(K, kk, chol, x0, eps):  # two independent rollouts: XLA runs them side by side
        policy = types.LinearGaussianPolicy(K, kk, None, chol, None)
        roll = jax.vmap(lambda x, e: sim.rollout_with_final(s, policy, x, e, with_ee=False))
        return roll(x0, eps), roll(x0 + 0.1, eps)

    f = jax.vmap(per_seed)
    four = jax.jit(sharding.over_seeds(f, sharding.seed_mesh(4), (True,) * 5))(K, kk, chol, x0, eps)
    one = jax.jit(f)(K, kk, chol, x0, eps)
    for a, b in zip(jax.tree.leaves(four), jax.tree.leaves(one), strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    print("same", len(jax.tree.leaves(four)))
""")


def test_host_rollouts_over_four_cpu_devices_finish_with_the_single_device_bits():
    """C MuJoCo rollouts of 230 KB operands in a program split over four CPU devices, two per
    device side by side, finish and give the single-device program's bits (each member is stepped
    on its own, so the batch a callback receives does not change it). Through
    ``jax.pure_callback`` this program never finished (``sim._host_callback``): run in a process
    of its own, so that a hang fails this test instead of the suite."""
    env = four_cpu_devices_env()
    try:
        done = subprocess.run([sys.executable, "-c", _HOST_ROLLOUTS_OVER_FOUR_CPU_DEVICES], env=env,
                              capture_output=True, text=True, timeout=600)
    except subprocess.TimeoutExpired:
        pytest.fail("the sharded program with host callbacks did not finish in 600 s")
    assert done.returncode == 0, done.stderr[-3000:]
    assert done.stdout.split() == ["same", "6"]


def test_mesh_of_too_many_devices_is_refused():
    with pytest.raises(ValueError, match="devices=99: must be between 1 and the"):
        sharding.seed_mesh(99)


def test_cpu_compiler_options_change_only_round_off(monkeypatch):
    """The programs' CPU code-generator option (``sharding.CPU_COMPILER_OPTIONS``) gives the GMR
    S-step's loss and gradient of XLA's default code generator up to round-off (tolerance
    measured by rerunning the default on inputs perturbed by ε relative), and XLA_FLAGS naming
    the option leaves the choice to the user. Both programs are compiled with XLA's defaults
    otherwise (the rest of the suite is not: tests/conftest.py)."""
    from gmr_jax import config, policies
    from benchmarks import sstep as sstep_bench

    monkeypatch.setenv("XLA_FLAGS", "")
    if sharding.compiler_options() != sharding.CPU_COMPILER_OPTIONS:
        pytest.skip("not a CPU backend, or this XLA does not know the option")
    cfg = config.reach("AB", "gmr")
    pol = policies.for_config(cfg)
    params = pol.init(jax.random.PRNGKey(0), 12, 6)
    batch = jax.tree_util.tree_map(lambda a: a[:20], sstep_bench.synthetic_data(cfg, jax.random.PRNGKey(3), jnp.float64))

    def loss_and_grad(net, b):
        return jax.value_and_grad(lambda n: pol.loss(params._replace(net=n), b, jax.random.PRNGKey(1))[0])(net)

    def compiled(options):
        return jax.jit(loss_and_grad).lower(params.net, batch).compile(compiler_options=options)

    with jax.default_matmul_precision(mdgps.MATMUL_PRECISION):
        ref, tol = measured_tol(compiled(XLA_DEFAULT_CPU_CODEGEN), (params.net, batch), SAFETY)
        got = compiled({**XLA_DEFAULT_CPU_CODEGEN, **sharding.CPU_COMPILER_OPTIONS})(params.net, batch)
    assert_trees_within(got, ref, tol)

    monkeypatch.setenv("XLA_FLAGS", "--xla_cpu_use_fusion_emitters=true")
    assert sharding.compiler_options() == {}


def test_compiler_options_by_backend_and_seeds_per_device():
    """XLA's dots and cuBLAS products (no Triton GEMMs) on a GPU for one seed per device only;
    the CPU option for any seed count; an option XLA_FLAGS names is left to XLA_FLAGS."""
    wanted = sharding.wanted_compiler_options
    one_seed = {"xla_gpu_enable_triton_gemm": False, "xla_gpu_gemm_rewrite_size_threshold": 10_000}
    assert wanted("gpu", 1, "") == one_seed
    assert wanted("gpu", 2, "") == {} and wanted("gpu", 256, "") == {}
    assert wanted("gpu", 1, "--xla_gpu_enable_triton_gemm=true") == {"xla_gpu_gemm_rewrite_size_threshold": 10_000}
    assert wanted("gpu", 1, "--xla_gpu_gemm_rewrite_size_threshold=100 --xla_gpu_enable_triton_gemm=true") == {}
    assert wanted("gpu", 1, "--xla_gpu_enable_triton_gemm_any=true") == one_seed  # another flag
    assert wanted("cpu", 1, "") == wanted("cpu", 64, "") == sharding.CPU_COMPILER_OPTIONS
    assert wanted("tpu", 1, "") == {}


def test_benchmark_compiler_options_spec():
    """``benchmarks.sstep --compiler-options`` entries: the runner's options, none, or
    NAME=VALUE pairs joined by "+" (booleans and integers parsed); a malformed pair is refused."""
    from benchmarks import sstep as sstep_bench

    assert sstep_bench.compiler_options("runner", 1) == sharding.compiler_options(1)
    assert sstep_bench.compiler_options("none", 1) == {}
    assert sstep_bench.compiler_options("a=true+b=10000+c=x+d=False", 1) == {"a": True, "b": 10_000, "c": "x",
                                                                              "d": False}
    with pytest.raises(ValueError, match="is not NAME=VALUE"):
        sstep_bench.compiler_options("threshold", 1)


def test_trace_time_choices_follow_the_default_device():
    """A run the runner places on another platform is traced under ``jax.default_device`` of
    that platform: the S-step's form and the physics backend "auto" follow it (a GPU process's
    host-CPU runs trace the CPU's choices, and the other way round), and the simulator cache
    keeps one plant per resolved backend. A program of one seed per device traces the packed
    forms' products as reductions on a GPU only, and only up to ``REDUCED_PRODUCTS_MAX_SEEDS``
    seeds per device; its S-step's statistics per epoch up to ``EPOCH_STATISTICS_MAX_SEEDS``."""
    from gmr_jax import config, sim, sstep
    from gmr_jax.policies import base

    here = jax.default_backend()
    assert sharding.target_platform() == here
    for platform, impl, backend in (("gpu", "packed", "mjx"), ("cpu", "reference", "mujoco")):
        with jax.default_device(platform):  # only read while tracing, so no such device is needed
            assert sharding.target_platform() == platform
            assert sstep.default_impl() == impl
            assert sim.make_sim(config.SimConfig()).backend == backend
            most = sharding.REDUCED_PRODUCTS_MAX_SEEDS
            for seeds in (1, 2, most, most + 1):
                wanted = platform == "gpu" and seeds <= most
                with sharding.seed_block(seeds):
                    assert base.reduced_products() == wanted
                    assert sharding.block_seeds() == seeds
                assert sharding.reduced_products_for(seeds, platform) == wanted
            assert not base.reduced_products() and sharding.block_seeds() is None
            # the S-step's statistics per epoch up to EPOCH_STATISTICS_MAX_SEEDS seeds per GPU
            most = sharding.EPOCH_STATISTICS_MAX_SEEDS
            for seeds in (1, most, most + 1):
                wanted = platform == "gpu" and seeds <= most
                with sharding.seed_block(seeds):
                    assert sstep.default_statistics() == ("epoch" if wanted else "step")
                assert sharding.epoch_statistics_for(seeds, platform) == wanted
            assert sstep.default_statistics() == "step"  # outside the runner's seed blocks
    assert sharding.target_platform() == here
    assert sim.make_sim(config.SimConfig()).backend == ("mjx" if here == "gpu" else "mujoco")


def test_scheduler_mesh_for_a_platform(tmp_path):
    """The default backend's platform (or None) is the scheduler's own mesh; a platform this
    process does not have is refused in one line, and a run asked onto it writes nothing."""
    from gmr_jax import config, runner

    with runner.Scheduler() as s:
        assert s.mesh_for(None) is s.mesh
        assert s.mesh_for(jax.default_backend()) is s.mesh
        with pytest.raises(ValueError, match="platform 'tpu': no such devices here"):
            s.mesh_for("tpu")
        with pytest.raises(ValueError, match="platform 'tpu'"):
            runner.run(config.reach("A", "lqr"), [0], tmp_path / "run", scheduler=s, platform="tpu")
        assert not (tmp_path / "run").exists()


def test_one_seed_runs_the_plain_program_and_more_seeds_the_vmapped_one():
    """``over_seed_axis``: a block of one seed traces ``fn`` itself on the squeezed arguments (a
    ``lax.cond`` on a seed's own data stays a conditional, where ``vmap`` turns it into a select of
    both branches), with the seed axis put back on every output; more seeds are ``jax.vmap``.
    That the one-seed program computes what the vmapped one does is the sharded-run test above:
    its four devices each run one seed."""
    def fn(x, scale):
        y = jax.lax.cond(x.sum() > 0, lambda v: v * scale, lambda v: -v, x)
        return {"y": y, "total": y.sum()}

    mapped = sharding.over_seed_axis(fn, (True, False))
    prims = lambda f, *a: {e.primitive.name for e in jax.make_jaxpr(f)(*a).eqns}  # noqa: E731
    one, two = jnp.array([[1.0, 3.0]]), jnp.array([[1.0, 3.0], [-2.0, 1.0]])
    assert "cond" in prims(mapped, one, 2.0) and "cond" not in prims(mapped, two, 2.0)
    out = mapped(one, 2.0)
    assert out["y"].shape == (1, 2) and out["total"].shape == (1,)
    np.testing.assert_array_equal(out["y"], [[2.0, 6.0]])
    np.testing.assert_array_equal(mapped(two, 2.0)["y"], [[2.0, 6.0], [2.0, -1.0]])


def test_over_seed_axis_traces_under_the_choices_of_its_seed_block():
    """The trace-time choices (``seed_block``) follow the seed block that ``over_seed_axis`` is
    traced for, on the plain (one seed) and on the vmapped path; seed axes of different sizes
    are refused in one line."""
    from gmr_jax.policies import base

    seen = []

    def fn(x):
        seen.append(base.reduced_products())
        return x * 2.0

    mapped = sharding.over_seed_axis(fn, (True,))
    most = sharding.REDUCED_PRODUCTS_MAX_SEEDS
    with jax.default_device("gpu"):  # only read while tracing: no GPU needed
        for seeds in (1, 2, most, most + 1):
            jax.eval_shape(mapped, jax.ShapeDtypeStruct((seeds, 3), jnp.float32))
    with jax.default_device("cpu"):
        jax.eval_shape(mapped, jax.ShapeDtypeStruct((2, 3), jnp.float32))
    assert seen == [True, True, True, False, False]
    two = sharding.over_seed_axis(lambda x, y: x + y, (True, True))
    with pytest.raises(ValueError, match=r"one leading seed axis of one size, got sizes \[2, 3\]"):
        two(jnp.zeros((2, 1)), jnp.zeros((3, 1)))


def _loops(k, z, c, xs):
    """Loops whose carries start unbatched under a vmap over ``k``: a scan with a pass-through
    carry, a carry reached only through another carry, and a jitted call; a while loop on an
    unbatched predicate; a cond on an unbatched index."""
    def body(carry, x):
        a, b, n = carry
        return (a + x * k, b + a, n + 1), a * 2

    (a, b, n), ys = jax.lax.scan(body, (z, z, 0), xs)
    w, acc = jax.lax.while_loop(lambda s: s[0] < 3, lambda s: (s[0] + 1, s[1] + jax.jit(jnp.sin)(a)), (0, z))
    picked = jax.lax.cond(c > 0, lambda v: v * k, lambda v: v, z)
    kept, barred = jax.lax.optimization_barrier((z, a))
    return a, b, n, ys, w, acc, picked, z * 2, kept, barred


def test_depends_agrees_with_the_batching_of_vmap():
    """sharding._depends' flags for every output equal whether ``jax.vmap`` batches it, with
    each input in turn the batched one (out_axes=None raises exactly for a batched output)."""
    args = (jnp.ones(3), jnp.zeros(3), jnp.int32(1), jnp.ones((4, 3)))
    closed = jax.make_jaxpr(_loops)(*args)
    n_out = len(closed.jaxpr.outvars)
    for i in range(len(args)):
        flags = [j == i for j in range(len(args))]
        got = sharding._depends(closed, flags)
        in_axes = tuple(0 if f else None for f in flags)
        batched_args = tuple(jnp.stack([a, a]) if f else a for a, f in zip(args, flags))
        for o in range(n_out):
            def one(*a, o=o):
                return jax.tree_util.tree_leaves(_loops(*a))[o]
            try:
                jax.eval_shape(jax.vmap(one, in_axes=in_axes, out_axes=None), *batched_args)
                want = False
            except ValueError:
                want = True
            assert got[o] == want, (i, o)


def test_scan_varying_equals_the_scan_and_batches_its_body_once(monkeypatch):
    """Under vmap, scan_varying gives the scan's results bit for bit, and the vmap batches the
    scan's body once (jax.lax.scan alone batches it three times: its carries start unbatched,
    and one of them depends on the other)."""
    from jax._src.interpreters import batching

    def body(carry, x):
        a, b, n = carry
        return (jnp.tanh(a) + x, b + a, n + 1), a

    def plain(xs):
        return jax.lax.scan(body, (jnp.zeros(3), jnp.zeros(3), 0), xs)

    def varying(xs):
        init = (jnp.zeros(3), jnp.zeros(3), 0)
        return sharding.scan_varying(body, init, xs, ((False, False, False), True), xs)

    passes = []
    original = batching.batch_jaxpr

    def counting(closed_jaxpr, axis_data, in_batched, instantiate):
        if len(closed_jaxpr.jaxpr.eqns) == 4:  # the body: tanh, two adds, one integer add
            passes.append(tuple(in_batched))
        return original(closed_jaxpr, axis_data, in_batched, instantiate)

    monkeypatch.setattr(batching, "batch_jaxpr", counting)
    xs = jax.random.normal(jax.random.PRNGKey(0), (5, 4, 3))
    want = jax.vmap(plain)(xs)
    assert len(passes) == 3  # b is reached through a: two passes more
    passes.clear()
    got = jax.vmap(varying)(xs)
    assert len(passes) == 1
    for g, w in zip(jax.tree_util.tree_leaves(got), jax.tree_util.tree_leaves(want)):
        np.testing.assert_array_equal(np.asarray(g), np.asarray(w))
    # the integer counter stays unbatched, as the vmap of the scan keeps it
    assert np.shape(got[0][2]) == np.shape(want[0][2])

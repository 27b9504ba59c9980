"""The numba backend: generated point kernels and the fused UKF likelihood
kernel (bondgraph.numerics.compiled, bondgraph.inference.ukf_numba).

Reference: the numpy path (the batched numpy filter and the generated numpy
module), which is itself checked against filterpy in test_ukf.py. The NLL of
every registered model must agree within 1e-9 relative on random parameter
sets drawn from the model's box, with identical failures (same sets, same
sample, same reason). The test uses NSETS sets per model to keep CI time
small; bench/numba_equality.py runs the same comparison with 100 sets.
Known limits (measured with 100 sets, reported by that script): where a
filter sits on the positive-definite boundary of its covariance (many
diagonally loaded factorisations: dc_motor_gear, ced_linear) or its
discretisation is unstable or under-resolved (vehicle_full at 40 Hz with
ROS2(1)), rounding differences between the two implementations are
amplified: a few sets then fail at other samples or differ by more than
1e-9 (the NLL guard of the estimate flags the second case).
"""

import os
import warnings

import numpy as np
import pytest

from bondgraph.core.codegen_numba import padded_points
from bondgraph.errors import BackendWarning
from bondgraph.inference import ukf as ukf_module
from bondgraph.inference.options import UKFOptions
from bondgraph.inference.ukf import ukf_nll
from bondgraph.numerics import compiled, compiled_c, registry
from bondgraph.numerics.model import Model

pytest.importorskip("numba")

NSETS = 12
MODELS = sorted(registry.registered())


def _record(m: Model, N=120, dt=0.01, seed=0, substeps=8):
    """A record of ``m`` at its defaults: inputs around INPUT_DEFAULTS (a
    slow sine modulation), RK4(``substeps``) truth, measurement noise, one
    missing sample and one partially missing sample. (For vehicle_full at
    25 ms, RK4(8) is outside its stability region: that record depends on
    rounding; tests that need its figures use 40.)"""
    t = np.arange(N) * dt
    mod = 1.0 + 0.3 * np.sin(np.arange(N) / 7.0)
    u = m.u0[None, :] * mod[:, None] + 0.1 * np.sin(np.arange(N) / 5.0)[:, None]
    x = m.x0[None].copy()
    ys = []
    for k in range(N):
        ys.append(m.h(x, u[k], m.theta0)[0])
        x = m.module.fx(x, dt, u[k], m.theta0, substeps)
    rng = np.random.default_rng(seed)
    y = np.array(ys) + rng.normal(size=(N, m.n_y)) * m.meas_std(m.theta0[None])[0]
    y[3] = np.nan
    y[10, 0] = np.nan
    return t, u, y


def box_sets(m: Model, n: int, seed: int) -> np.ndarray:
    """``n`` parameter sets uniform in the model's finite box (defaults
    where a bound is infinite)."""
    rng = np.random.default_rng(seed)
    th = np.tile(m.theta0, (n, 1))
    fin = np.isfinite(m.lower) & np.isfinite(m.upper)
    th[:, fin] = m.lower[fin] + rng.random((n, int(fin.sum()))) * (m.upper[fin] - m.lower[fin])
    return th


def _round_off_breakdown(reason) -> bool:
    return reason is not None and any(w in reason for w in (
        "not positive definite", "sigma point diverged", "non-finite predicted output"))


def assert_same(a, b, rel=1e-9):
    """Same failures (sets, samples, reasons) and NLL within ``rel``.

    One exception, by construction of floating point: a set whose covariance
    has collapsed to round-off (no process noise, P ~ 1e-39 after the
    regularised factorisations) breaks down as "not positive definite", and
    a diverging set overflows (a non-finite state or output), in both
    backends at a sample that round-off decides; such a set must fail in
    both, for one of these reasons, but the sample and which of them may
    differ."""
    np.testing.assert_array_equal(a.failed, b.failed)
    both_pd = np.array([_round_off_breakdown(ra) and _round_off_breakdown(rb)
                        for ra, rb in zip(a.reasons, b.reasons)], dtype=bool)
    np.testing.assert_array_equal(a.fail_step[~both_pd], b.fail_step[~both_pd])
    assert [r for r, x in zip(a.reasons, both_pd) if not x] == \
        [r for r, x in zip(b.reasons, both_pd) if not x]
    ok = ~a.failed
    np.testing.assert_allclose(b.nll[ok], a.nll[ok], rtol=rel, atol=0)
    assert np.isposinf(b.nll[a.failed]).all()


@pytest.mark.parametrize("name", MODELS)
def test_point_kernels_equal_numpy_module(name):
    """f, h and f_dfdx of the generated numba kernels equal the numpy module's
    f, h, f and dfdx at random points (the same expressions)."""
    m = Model.load(name)
    pk = compiled.point_kernels(m)
    rng = np.random.default_rng(3)
    th = box_sets(m, 3, seed=1)
    for p in range(3):
        x = m.x0 + rng.normal(size=m.n_x) * (np.abs(m.x0) + 0.1)
        u = m.u0 + rng.normal(size=m.n_u) * 0.1
        dx, yv, J = np.empty(m.n_x), np.empty(m.n_y), np.empty((m.n_x, m.n_x))
        pk.f(x, u, th[p], dx)
        pk.h(x, u, th[p], yv)
        dx2 = np.empty(m.n_x)
        pk.f_dfdx(x, u, th[p], dx2, J)
        with np.errstate(all="ignore"):
            np.testing.assert_allclose(dx, m.f(x, u, th[p]), rtol=1e-12, atol=1e-300)
            np.testing.assert_allclose(dx2, dx, rtol=1e-12)
            np.testing.assert_allclose(yv, m.h(x, u, th[p]), rtol=1e-12, atol=1e-300)
            np.testing.assert_allclose(J, m.dfdx(x, u, th[p]), rtol=1e-12, atol=1e-300)


def _cols(pk, m, X, u, th):
    """f_cols and h_cols at the rows of X (2 n_x + 1 points, padded with
    copies of point 0 as the filter does), as (points, n)."""
    npt, pc = X.shape[0], padded_points(m.n_x)
    F, Y = np.empty(m.n_x * pc), np.empty(m.n_y * pc)
    XT = np.ascontiguousarray(np.vstack([X, np.tile(X[0], (pc - npt, 1))]).T).ravel()
    pk.f_cols(XT, u, th, F)
    pk.h_cols(XT, u, th, Y)
    return F.reshape(m.n_x, pc).T[:npt], Y.reshape(m.n_y, pc).T[:npt]


def _points_reference(pk, m, X, u, th):
    F, Y = np.empty((X.shape[0], m.n_x)), np.empty((X.shape[0], m.n_y))
    for j in range(X.shape[0]):
        pk.f(np.ascontiguousarray(X[j]), u, th, F[j])
        pk.h(np.ascontiguousarray(X[j]), u, th, Y[j])
    return F, Y


def _close_per_entry(got, ref):
    """Within 1e-12 of each entry's largest magnitude over the points, and
    1e-14 of the largest of all (the branch-free library functions are
    within 2 ulp, then summed: an entry that cancels to 0 keeps a rounding)."""
    ok = np.isfinite(ref)
    np.testing.assert_array_equal(np.isfinite(got), ok)
    scale = np.max(np.where(ok, np.abs(ref), 0.0), axis=0, keepdims=True)
    tol = 1e-12 * (np.abs(ref) + scale) + 1e-14 * scale.max()
    assert np.all(np.abs(got - ref)[ok] <= tol[ok])


@pytest.mark.parametrize("name", MODELS)
def test_column_kernels_equal_the_point_kernels(name):
    """f_cols and h_cols (every sigma point at once, state-major, branch-free
    sin/cos/atan/exp/tanh) at sigma points x ± c L_i and at unstructured
    points give f and h of the point kernels (numpy's library functions) to
    rounding."""
    m = Model.load(name)
    pk = compiled.point_kernels(m)
    rng = np.random.default_rng(5)
    th = box_sets(m, 2, seed=2)
    n = m.n_x
    x = m.x0 + rng.normal(size=n) * (np.abs(m.x0) + 0.1)
    L = np.tril(rng.normal(size=(n, n))) * 0.1 * (np.abs(m.x0) + 0.1)[:, None]
    sigma = np.vstack([x, x + L.T, x - L.T])
    dense = x + rng.normal(size=(2 * n + 1, n)) * (np.abs(m.x0) + 0.1)
    u = m.u0 + rng.normal(size=m.n_u) * 0.1
    for p in range(2):
        for X in (sigma, dense):
            F, Y = _cols(pk, m, X, u, th[p])
            Fr, Yr = _points_reference(pk, m, X, u, th[p])
            with np.errstate(all="ignore"):
                _close_per_entry(F, Fr)
                _close_per_entry(Y, Yr)


def test_column_kernels_take_numpy_sin_for_far_arguments():
    """A sin or cos argument of 1e8 or more (the branch-free reduction's
    limit) at any point: the column kernel recomputes every point with
    numpy's functions (vehicle_full: sin and cos of the road grade state)."""
    m = Model.load("vehicle_full")
    pk = compiled.point_kernels(m)
    n = m.n_x
    grade = m.states.index("theta_g")
    X = np.tile(m.x0, (2 * n + 1, 1)) * (1 + 0.01 * np.arange(2 * n + 1))[:, None]
    X[7, grade] = 1.0e17
    th, u = m.theta0, m.u0
    F, Y = _cols(pk, m, X, u, th)
    Fr, Yr = _points_reference(pk, m, X, u, th)
    _close_per_entry(F, Fr)
    _close_per_entry(Y, Yr)
    assert abs(Fr[7, 0] - F[7, 0]) <= 1e-9 * abs(Fr[7, 0])


@pytest.mark.parametrize("name", MODELS)
def test_numba_nll_equals_numpy_on_the_box(name):
    """Default options (ROS2, Jacobian at the central point, zero-order hold):
    NLL within 1e-9 relative, identical failures, on NSETS box sets."""
    m = Model.load(name)
    t, u, y = _record(m)
    th = box_sets(m, NSETS, seed=7)
    a = ukf_nll(m, t, u, y, th, options=UKFOptions(backend="numpy"))
    b = ukf_nll(m, t, u, y, th, options=UKFOptions(backend="numba"))
    assert a.settings["backend_used"] == "numpy" and b.settings["backend_used"] == "numba"
    assert_same(a, b)


@pytest.mark.parametrize("opts", [dict(method="rk4", substeps=20, hold="mean"),
                                  dict(method="ros2", substeps=3, jacobian="sigma"),
                                  dict(method="ros2", substeps=2, alpha=0.5, kappa=1.0),
                                  dict(method="rk4", substeps=20, hold="linear"),
                                  dict(method="ros2", substeps=3, hold="linear")])
def test_numba_equals_numpy_for_other_options(opts):
    """RK4 (stable step), ROS2 with per-point Jacobians, other sigma scaling,
    the mean and the first-order (linear) input holds, on the stiff vehicle
    model; stored arrays too."""
    m = Model.load("vehicle_coastdown")
    t, u, y = _record(m, N=60)
    th = box_sets(m, 6, seed=11)
    a = ukf_nll(m, t, u, y, th, store="full", options=UKFOptions(backend="numpy", **opts))
    b = ukf_nll(m, t, u, y, th, store="full", options=UKFOptions(backend="numba", **opts))
    assert b.settings["backend_used"] == "numba"
    assert_same(a, b)
    for key in ("innovations", "S", "y_pred", "y_filt", "x_filt", "P_filt", "nll_terms", "nis"):
        A, B = getattr(a, key), getattr(b, key)
        np.testing.assert_array_equal(np.isnan(A), np.isnan(B), err_msg=key)
        scale = np.nanmax(np.abs(A)) if np.isfinite(A).any() else 1.0
        np.testing.assert_allclose(B, A, rtol=1e-8, atol=1e-9 * scale, err_msg=key)


def test_failures_are_handled_as_numpy():
    """Sets failing at the start (non-finite parameter, non-positive noise) and
    during the record (a state diverging: explicit RK4 on a time constant
    of 3e-7 s at 10 ms steps): same sets, samples and reasons."""
    m = Model.load("rr_loop")
    t, u, y = _record(m)
    th = box_sets(m, 8, seed=2)
    th[1, 0] = np.nan
    th[2] = m.theta0
    th[2, m.param_index("L")] = 3e-6
    a = ukf_nll(m, t, u, y, th, options=UKFOptions(backend="numpy", method="rk4"))
    b = ukf_nll(m, t, u, y, th, options=UKFOptions(backend="numba", method="rk4"))
    assert a.failed[2] and a.fail_step[2] > 0
    assert a.failed[1] and a.fail_step[1] == 0
    assert a.failed.sum() >= 2
    assert_same(a, b)


def test_w_inverse_skips_only_unchanged_columns():
    """ROS2's W⁻¹ in the kernel (Gauss-Jordan restricted to the columns it
    changes) equals the dense Gauss-Jordan reference entry for entry (zeros'
    signs aside), including NaN/inf patterns, and numpy's inverse to round-off."""
    from bondgraph.inference import ukf_numba

    rng = np.random.default_rng(1)
    for trial in range(300):
        n = int(rng.integers(1, 11))
        J = rng.normal(size=(n, n)) * 10.0 ** rng.integers(-3, 4)
        kind = trial % 5
        if kind == 1:
            J[rng.random((n, n)) < 0.5] = 0.0
        elif kind == 2:
            J[rng.integers(n), rng.integers(n)] = (np.nan, np.inf)[trial % 2]
        elif kind == 3:
            J = np.diag(rng.normal(size=n))
        h = 0.025
        A1, A2, W1, W2 = np.zeros((n, 2 * n)), np.zeros((n, 2 * n)), np.zeros((n, n)), \
            np.zeros((n, n))
        ukf_numba._inverse_w_dense(J, h, A1, W1)
        ukf_numba._inverse_w(J, h, A2, W2, np.zeros(2 * n, dtype=np.int64))
        np.testing.assert_array_equal(W2, W1)   # NaN == NaN, -0.0 == 0.0 here
        if np.isfinite(J).all():
            W = np.eye(n) - ukf_numba.GAMMA * h * J
            np.testing.assert_allclose(W2, np.linalg.inv(W), rtol=1e-9,
                                       atol=1e-12 * np.abs(np.linalg.inv(W)).max())


def test_one_thread_and_two_give_the_same_numbers(monkeypatch):
    """The sets spread over one thread or over two (each set one call of the
    kernel, taken in turn by the pool's threads) give the NLLs, reasons and
    stored arrays of each other, bit for bit, with R and Q given per set."""
    from bondgraph.inference import ukf_numba

    m = Model.load("rr_loop")
    t, u, y = _record(m)
    th = box_sets(m, 7, seed=4)
    R = np.tile(np.diag(m.meas_std(m.theta0[None])[0] ** 2), (7, 1, 1))
    Q = np.tile(np.eye(m.n_x) * 1e-6, (7, 1, 1))
    opts = UKFOptions(backend="numba")
    monkeypatch.setattr(ukf_numba, "threads", lambda: 1)
    a = ukf_nll(m, t, u, y, th, options=opts, R=R, Q=Q, store="full")
    monkeypatch.setattr(ukf_numba, "threads", lambda: 2)
    b = ukf_nll(m, t, u, y, th, options=opts, R=R, Q=Q, store="full")
    assert np.isfinite(a.nll).sum() >= 5
    np.testing.assert_array_equal(b.nll, a.nll)
    assert b.reasons == a.reasons
    np.testing.assert_array_equal(b.P_filt, a.P_filt)
    np.testing.assert_array_equal(b.innovations, a.innovations)


def test_fallback_to_numpy_when_kernels_do_not_load(monkeypatch):
    """numba missing (point_kernels raising ImportError): a BackendWarning
    naming the model, and the numpy result."""
    m = Model.load("mass_spring_damper")
    t, u, y = _record(m, N=40)
    ref = ukf_nll(m, t, u, y, m.theta0, options=UKFOptions(backend="numpy"))

    def broken(model):
        raise ImportError("numba is not installed")
    monkeypatch.setattr(ukf_module, "point_kernels", broken)
    monkeypatch.setattr(ukf_module, "_WARNED", set())
    with pytest.warns(BackendWarning, match="mass_spring_damper"):
        r = ukf_nll(m, t, u, y, m.theta0, options=UKFOptions(backend="numba"))
    assert r.settings["backend_used"] == "numpy"
    assert r.nll[0] == ref.nll[0]


def test_in_memory_model_compiles_into_the_cache(tmp_path, monkeypatch):
    """A model built in memory gets its kernels written to the cache
    directory (keyed by its source) at its first numba run, and equal NLLs."""
    monkeypatch.setenv(compiled.CACHE_ENV, str(tmp_path))
    m = Model.from_spec("bondgraph.catalog.reference:mass_spring_damper")
    t, u, y = _record(m, N=40)
    th = box_sets(m, 4, seed=5)
    a = ukf_nll(m, t, u, y, th, options=UKFOptions(backend="numpy"))
    with warnings.catch_warnings():
        warnings.simplefilter("error", BackendWarning)
        b = ukf_nll(m, t, u, y, th, options=UKFOptions(backend="numba"))
    assert b.settings["backend_used"] == "numba"
    assert list(tmp_path.glob("mass_spring_damper_*.py"))
    assert_same(a, b)


def test_kernels_compiled_ahead_meet_in_the_middle(tmp_path, monkeypatch):
    """compile_ahead hands the models to a background process (a plain child
    fed kernel paths) from the last; this process takes them from the first:
    the first model, still queued when asked for, is compiled here (taken
    off the queue: nobody compiles it twice), the last is loaded from the
    disk cache the background wrote (waiting for it). The NLLs equal
    numpy's either way. A model already loaded is not queued again; 0
    processes switch it off; a bad setting is named. (numba's kernels: the
    C compiler's thread builds a model in 0.3 s and may reach the first
    before this process asks for it; see the test below.)"""
    monkeypatch.setenv(compiled.CACHE_ENV, str(tmp_path))
    monkeypatch.setenv(compiled.AHEAD_ENV, "1")
    monkeypatch.setenv(compiled.KERNELS_ENV, "numba")
    monkeypatch.setattr(compiled, "_AHEAD", [])   # a worker of its own (not one still busy)
    models = [Model.from_spec(f"bondgraph.catalog.reference:{n}")
              for n in ("mass_spring_damper", "rlc_circuit")]
    assert compiled.compile_ahead(models) == 2
    ahead, last_path = compiled._AHEAD[0], str(compiled.kernel_source_path(models[1]))
    with ahead.cond:                              # the worker has started (a cold venv: seconds)
        assert ahead.cond.wait_for(lambda: last_path not in ahead.queue, 300)
    first, last = (compiled.point_kernels(m) for m in models)
    assert not first.from_cache                   # compiled here
    assert last.from_cache                        # by the background process
    assert compiled._AHEAD[0].wait_idle(timeout=60)
    compiled._AHEAD[0].close()
    for m in models:
        t, u, y = _record(m, N=40)
        th = box_sets(m, 3, seed=2)
        assert_same(ukf_nll(m, t, u, y, th, options=UKFOptions(backend="numpy")),
                    ukf_nll(m, t, u, y, th, options=UKFOptions(backend="numba")))
    assert compiled.compile_ahead(models) == 0    # loaded: nothing to do
    monkeypatch.setenv(compiled.AHEAD_ENV, "0")
    assert compiled.ahead_workers() == 0
    monkeypatch.setenv(compiled.AHEAD_ENV, "two")
    with pytest.raises(ValueError, match="BONDGRAPH_COMPILE_AHEAD='two'"):
        compiled.ahead_workers()


def test_kernels_compiled_ahead_by_the_c_compiler_are_loaded(tmp_path, monkeypatch):
    """With the C compiler compile_ahead's workers are threads that run it:
    once they are idle, every queued model's library is in the cache, this
    process loads it (nothing compiled here) and the NLLs equal numpy's."""
    if compiled_c.compiler() is None:
        pytest.skip("no C compiler on this machine")
    monkeypatch.setenv(compiled.CACHE_ENV, str(tmp_path))
    monkeypatch.setenv(compiled.AHEAD_ENV, "1")
    monkeypatch.setenv(compiled.KERNELS_ENV, "c")
    monkeypatch.setattr(compiled, "_AHEAD", [])
    models = [Model.from_spec(f"bondgraph.catalog.reference:{n}")
              for n in ("mass_spring_damper", "rlc_circuit")]
    assert compiled.compile_ahead(models) == 2
    assert compiled._AHEAD[0].kind == "c"
    assert compiled._AHEAD[0].wait_idle(timeout=120)
    compiled._AHEAD[0].close()
    for m in models:
        k = compiled.point_kernels(m)
        assert k.kind == "c" and k.from_cache
        t, u, y = _record(m, N=40)
        th = box_sets(m, 3, seed=2)
        assert_same(ukf_nll(m, t, u, y, th, options=UKFOptions(backend="numpy")),
                    ukf_nll(m, t, u, y, th, options=UKFOptions(backend="numba")))
    assert compiled.compile_ahead(models) == 0    # loaded: nothing to do


def test_backend_is_taken_literally_whatever_the_history_or_the_cache(tmp_path):
    """The same call gives the same bits whatever ran before it in the
    process and whatever earlier runs left in the kernel cache: a one-sample
    batch of a new in-memory model is its first call (the old break-even
    rule ran it on numpy; after a large batch, or once its kernels were in
    the cache, on numba: the last digits of a result depended on the call
    history), then the same call after a large batch, then in a fresh
    process that finds the kernels in the cache. Backend numpy is honoured
    the same way."""
    import os
    import subprocess
    import sys

    script = (
        "import sys, numpy as np\n"
        "from bondgraph.inference.options import UKFOptions\n"
        "from bondgraph.inference.ukf import ukf_nll\n"
        "from bondgraph.numerics.model import Model\n"
        "m = Model.from_spec('bondgraph.catalog.reference:rlc_circuit')\n"
        "N = 60\n"
        "t = np.arange(N) * 1e-3\n"
        "u = (2 + np.sin(np.arange(N) / 4.0))[:, None]\n"
        "y = np.cos(np.arange(N)[:, None] / 9.0 + np.arange(m.n_y)) * 0.1\n"
        "out = []\n"
        "for backend in ('numba', 'numpy'):\n"
        "    o = UKFOptions(backend=backend)\n"
        "    first = ukf_nll(m, t, u, y, m.theta0, options=o)\n"
        "    ukf_nll(m, t, u, y, np.tile(m.theta0, (200, 1)), options=o)\n"
        "    again = ukf_nll(m, t, u, y, m.theta0, options=o)\n"
        "    out += [first.settings['backend_used'], again.settings['backend_used'],\n"
        "            first.nll[0].hex(), again.nll[0].hex()]\n"
        "print(' '.join(out))\n")
    env = dict(os.environ, BONDGRAPH_CACHE_DIR=str(tmp_path))

    def run():
        r = subprocess.run([sys.executable, "-c", script], env=env, text=True,
                           capture_output=True, check=True)
        return r.stdout.split()

    cold, warm = run(), run()              # an empty kernel cache, then a filled one
    assert cold[:2] == ["numba", "numba"] and cold[4:6] == ["numpy", "numpy"], cold
    assert cold[2] == cold[3] and cold[6] == cold[7], cold   # history: same bits
    assert warm == cold                                      # cache: same bits
    assert list(tmp_path.glob("rlc_circuit_*.py"))


def test_compiled_kernels_are_found_where_numba_caches_them(tmp_path):
    """An in-memory model compiled in one process counts as compiled in the
    next (information for announcing compiles; it decides no backend),
    wherever numba keeps its cache: beside the kernel file, or under
    NUMBA_CACHE_DIR when set (the check looked only beside the file)."""
    import os
    import subprocess
    import sys

    script = (
        "import sys\n"
        "from bondgraph.numerics import compiled\n"
        "from bondgraph.numerics.model import Model\n"
        "m = Model.from_spec('bondgraph.catalog.reference:mass_spring_damper')\n"
        "before = compiled.is_compiled(m)\n"
        "if sys.argv[1] == 'compile':\n"
        "    compiled.point_kernels(m)\n"
        "print(before, compiled.numba_cache_dir(compiled.kernel_source_path(m)))\n")
    for numba_dir in (None, tmp_path / "numba"):
        env = dict(os.environ, BONDGRAPH_CACHE_DIR=str(tmp_path / f"bc_{numba_dir is None}"))
        env.pop("NUMBA_CACHE_DIR", None)
        if numba_dir is not None:
            env["NUMBA_CACHE_DIR"] = str(numba_dir)

        def run(arg):
            r = subprocess.run([sys.executable, "-c", script, arg], env=env, text=True,
                               capture_output=True, check=True)
            return r.stdout.split()

        first, where = run("compile")
        second, where2 = run("check")
        assert (first, second) == ("False", "True"), (numba_dir, first, second)
        assert where == where2
        if numba_dir is None:
            assert where == str(tmp_path / "bc_True" / "__pycache__")
        else:
            assert where.startswith(str(numba_dir))


def test_generate_check_covers_the_numba_kernels(tmp_path):
    """`bondgraph generate --check` names a model whose numba file changed."""
    registry.generate(["mass_spring_damper"], directory=tmp_path, verbose=False)
    assert registry.generate(["mass_spring_damper"], check=True, directory=tmp_path,
                             verbose=False) == []
    p = registry.numba_path("mass_spring_damper", tmp_path)
    p.write_text(p.read_text().replace("k*q_spring", "k*q_spring*1.0001", 1))
    assert registry.generate(["mass_spring_damper"], check=True, directory=tmp_path,
                             verbose=False) == ["mass_spring_damper"]


def test_collapsed_state_variance_is_known_not_a_failure(tmp_path, monkeypatch):
    """A stable lag driven by the input alone, without process noise (the
    loop's source_lag on an RLC circuit), is known to the filter after a
    while: every sigma point of it rounds to the same value, its row and
    column of P are exactly zero. Both backends then factorise P without it
    (a semidefinite factor) instead of failing "prior covariance P not
    positive definite" (before: inf at sample 104 of 1000 for τ = 3 ms), and
    agree to 1e-9."""
    from bondgraph import apply_effect
    from bondgraph.catalog.reference import rlc_circuit

    monkeypatch.setenv(compiled.CACHE_ENV, str(tmp_path))
    g = rlc_circuit()
    apply_effect(g, "source_lag", ("source", "source"), {"tau": 0.003})
    m = Model.from_graph(g)
    N, dt = 1000, 0.001
    t = np.arange(N) * dt
    u = (6 * np.sin(2 * np.pi * 3 * t) + 4 * np.sin(2 * np.pi * 11 * t))[:, None]
    x = m.x0[None].copy()
    ys = []
    for k in range(N):
        ys.append(m.h(x, u[k], m.theta0)[0])
        x = m.module.fx(x, dt, u[k], m.theta0, 8)
    y = np.array(ys) + np.random.default_rng(3).normal(size=(N, m.n_y)) \
        * m.meas_std(m.theta0[None])[0]
    P0 = np.diag([20.0 if s.startswith("source_lag") else 1e-7 for s in m.states])
    th = np.tile(m.theta0, (3, 1))
    th[:, m.param_index("source_lag.source.tau")] = [0.003, 0.006, 0.012]
    a = ukf_nll(m, t, u, y, th, None, P0, options=UKFOptions(backend="numpy", method="ros2"))
    b = ukf_nll(m, t, u, y, th, None, P0, options=UKFOptions(backend="numba", method="ros2"))
    assert b.settings["backend_used"] == "numba"
    assert not a.failed.any(), a.reasons
    assert np.argmin(a.nll) == 0                   # the true lag fits best
    assert_same(a, b)


def test_a_few_refused_matrices_in_a_stack_get_the_single_calls_factors():
    """cholesky_batch on 1 000 covariances of which a few numpy refuses
    (indefinite by 1e-10, needing the diagonal loading; one negative
    variance; one NaN): the factors, flags and loading count equal those of
    factoring every matrix alone (numpy's single calls, the loading
    retries by hand), bit for bit."""
    from bondgraph.inference.sigma import _loaded_cholesky, cholesky_batch

    rng = np.random.default_rng(11)
    B = rng.normal(size=(1000, 3, 3))
    A = B @ np.swapaxes(B, 1, 2) + 0.1 * np.eye(3)
    V = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    for j in (7, 500, 501, 998):
        A[j] = V @ np.diag([2.0, 1.0, -1e-10]) @ V.T
    A[300, 1, 1] = -1.0
    A[640, 0, 2] = np.nan
    L, ok, nreg = cholesky_batch(A)
    for b in range(len(A)):
        if not np.isfinite(A[b]).all():
            ref, good = None, False
        else:
            try:
                ref, good = np.linalg.cholesky(A[b]), True
            except np.linalg.LinAlgError:
                ref = _loaded_cholesky(A[b])
                good = ref is not None
        assert ok[b] == good, b
        np.testing.assert_array_equal(L[b], ref if good else np.eye(3))
    assert not ok[300] and not ok[640] and ok[[7, 500, 501, 998]].all()
    assert nreg == 4


def test_semidefinite_factor_of_known_states():
    """cholesky_batch(known=True): exactly zero rows/columns are zero in L
    and L Lᵀ reproduces A (to the 1e-12 loading); an innovation covariance
    (known=False) with a zero variance still fails; a negative variance
    fails either way. The kernel's factorisation equals it."""
    from bondgraph.inference import ukf_numba
    from bondgraph.inference.sigma import cholesky_batch

    A = np.array([[4.0, 0.0, 1.0], [0.0, 0.0, 0.0], [1.0, 0.0, 2.0]])
    L, ok, nr = cholesky_batch(A[None], known=True)
    assert ok[0] and nr == 1
    assert np.all(L[0][1] == 0) and np.all(L[0][:, 1] == 0)
    np.testing.assert_allclose(L[0] @ L[0].T, A, rtol=1e-11, atol=0)
    assert not cholesky_batch(A[None])[1][0]
    B = A.copy()
    B[1, 1] = -1e-30
    assert not cholesky_batch(B[None], known=True)[1][0]
    Lk = np.zeros((3, 3))
    skip = np.zeros(3, np.int64)
    assert ukf_numba._chol(A, 3, Lk, True, skip) == 2
    np.testing.assert_allclose(Lk, L[0], rtol=1e-14, atol=0)
    assert ukf_numba._chol(A, 3, Lk, False, skip) == 0
    assert ukf_numba._chol(B, 3, Lk, True, skip) == 0


@pytest.mark.parametrize("name", ["mass_spring_damper", "emps", "vehicle_coastdown", "toy_cvt"])
def test_compiled_free_run_of_the_prior_equals_numpy(name):
    """The prior's free-run scales (bondgraph.inference.prior.simulated_rms):
    the compiled run equals the numpy steps to rounding, for ROS2 and RK4
    and each hold."""
    from bondgraph.inference.options import Discretisation
    from bondgraph.inference.prior import simulated_rms

    m = Model.load(name)
    t, u, _ = _record(m, N=200)
    for method, sub, hold in (("ros2", 2, "zoh"), ("rk4", 4, "mean"), ("ros2", 3, "linear")):
        a = simulated_rms(m, t, u, m.theta0, m.x0, Discretisation(method, sub, hold, "numpy"))
        b = simulated_rms(m, t, u, m.theta0, m.x0, Discretisation(method, sub, hold, "numba"))
        np.testing.assert_allclose(b, a, rtol=1e-12, atol=0)


def test_generated_tanh_equals_numpy_to_rounding():
    """The numba modules' tanh (bondgraph.core.codegen_numba.NUMBA_TANH: exp for
    |x| >= 0.55) is np.tanh to a few 1e-16 relative, ±1 at ±inf, NaN at NaN."""
    pk = compiled.point_kernels(Model.load("emps"), kind="numba")
    tanh = pk.f.py_func.__globals__["_tanh"]
    x = np.concatenate([np.linspace(-40.0, 40.0, 100001), [0.55, -0.55, 0.0, -0.0, 1e-300]])
    got = np.array([tanh(v) for v in x])
    np.testing.assert_allclose(got, np.tanh(x), rtol=5e-16, atol=0)
    assert tanh(np.inf) == 1.0 and tanh(-np.inf) == -1.0 and tanh(1e308) == 1.0
    assert np.isnan(tanh(np.nan))


def test_no_experimental_feature_warning_reaches_the_user():
    """The kernel's tuple of first-class point functions makes numba warn
    "First-class function type feature is experimental" when it types it;
    a user saw that warning five times in the output of `bondgraph loop`.
    A run with every such warning turned into an error succeeds."""
    import subprocess
    import sys

    script = (
        "import warnings, numba, numpy as np\n"
        "warnings.simplefilter('error', numba.NumbaExperimentalFeatureWarning)\n"
        "from bondgraph.inference.ukf import ukf_nll\n"
        "from bondgraph.numerics.model import Model\n"
        "m = Model.load('mass_spring_damper')\n"
        "t = np.arange(50) * 0.01\n"
        "r = ukf_nll(m, t, np.ones((50, m.n_u)), np.zeros((50, m.n_y)), m.theta0)\n"
        "print(r.settings['backend_used'])\n")
    r = subprocess.run([sys.executable, "-c", script], text=True, capture_output=True)
    assert r.returncode == 0, r.stderr[-2000:]
    assert r.stdout.split() == ["numba"]


def test_the_same_graph_from_another_source_shares_its_kernels():
    """The kernel cache is keyed on the code, not on where the graph came
    from (a user's file named relatively or absolutely: the candidates of a
    user's Silverbox graph were compiled again when the command named its
    file another way): one graph built in memory with two ``source``
    strings has one kernel source path; a changed law has another."""
    from bondgraph.catalog.reference import mass_spring_damper
    from bondgraph.diagnose.effects.laws import add_to_r_law
    paths = []
    for src in ("msd.py:msd", "/home/user/models/msd.py:msd"):
        g = mass_spring_damper()
        g.source = src
        m = Model.from_graph(g)
        assert m.module.SOURCE == src
        paths.append(compiled.kernel_source_path(m))
    assert paths[0] is not None and paths[0] == paths[1]
    g = mass_spring_damper()
    g.source = "msd.py:msd"
    d = g.param("d3", 0.1, "N*s^3/m^3", (0.0, 1.0), "cubic damping")
    add_to_r_law(g, g.elements["damper"], lambda v: d * v**3)
    assert compiled.kernel_source_path(Model.from_graph(g)) != paths[0]


_FORKED: list = []


def _forked_nll(_):
    m, t, u, y, th = _FORKED[0]
    return ukf_nll(m, t, u, y, th, options=UKFOptions(backend="numba")).nll


@pytest.mark.skipif(not hasattr(os, "fork"), reason="no fork on this platform")
def test_a_forked_child_runs_the_kernel_after_its_parent_did(monkeypatch):
    """The kernel's thread pool does not cross a fork: a child forked after
    the parent ran the kernel on two threads gets the parent's NLLs (with
    the parent's pool copied, the sets were queued to threads that do not
    run in the child, and it waited for ever)."""
    import multiprocessing

    from bondgraph.inference import ukf_numba

    monkeypatch.setattr(ukf_numba, "threads", lambda: 2)
    m = Model.load("mass_spring_damper")
    t, u, y = _record(m, N=60)
    th = np.repeat(m.theta0[None], 4, axis=0)
    ref = ukf_nll(m, t, u, y, th, options=UKFOptions(backend="numba")).nll
    assert 2 in ukf_numba._POOLS and np.isfinite(ref).all()
    _FORKED[:] = [(m, t, u, y, th)]
    with multiprocessing.get_context("fork").Pool(1) as pool:
        got = pool.map_async(_forked_nll, [0]).get(timeout=120)[0]
    np.testing.assert_array_equal(got, ref)

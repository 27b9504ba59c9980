"""The point kernels compiled by the C compiler (bondgraph.core.codegen_ckernel,
bondgraph.numerics.compiled_c): the numba modules' statements translated to
C give the numba kernels' values (every registered model, point and column
kernels, to rounding), the same likelihood in the fused UKF kernel, the
vmath functions within 2 ulp of numpy as the numba ones are, and a model
the C compiler cannot build is compiled by numba (with a warning) unless C
was asked for."""

import ctypes
import math
import os
import subprocess
import sys

import numpy as np
import pytest

from bondgraph.core import codegen_ckernel, vmath
from bondgraph.core.codegen_numba import padded_points
from bondgraph.errors import CodegenError
from bondgraph.inference.options import UKFOptions
from bondgraph.inference.ukf import ukf_nll
from bondgraph.numerics import compiled, compiled_c, registry
from bondgraph.numerics.model import Model
from test_vmath import _points

pytest.importorskip("numba")
if compiled_c.compiler() is None:
    pytest.skip("no C compiler on this machine: numba compiles the kernels", allow_module_level=True)

MODELS = sorted(registry.registered())
NAMES = ("_vsin", "_vcos", "_vatan", "_vexp", "_vtanh")
#: the point kernels' tanh calls libm's tanh below 0.55 as numba's does:
#: compared with libm's (math.tanh; numpy's own vector tanh differs by an ulp)
REFERENCE = {"_vsin": np.sin, "_vcos": np.cos, "_vatan": np.arctan, "_vexp": np.exp,
             "_vtanh": np.tanh, "bg_tanh": np.frompyfunc(math.tanh, 1, 1)}


@pytest.fixture(scope="module")
def vlib(tmp_path_factory):
    """The translated vmath functions (and the point kernels' tanh, and
    _pow2) in a library with a loop ``loop_<name>(x, out, n)`` each."""
    text = codegen_ckernel.functions_c()
    for name in NAMES + ("bg_tanh",):
        text += (f"\nvoid loop_{name}(const double *x, double *o, int64_t n)\n"
                 f"{{ for (int64_t j = 0; j < n; ++j) o[j] = {name}(x[j]); }}\n")
    text += "\nvoid pow2s(const int64_t *n, double *o, int64_t m)\n" \
            "{ for (int64_t j = 0; j < m; ++j) o[j] = _pow2(n[j]); }\n"
    lib = tmp_path_factory.mktemp("vmath_c") / "vmath.so"
    compiled_c.build(text, lib)
    return ctypes.CDLL(str(lib))


def _run(vlib, name, x):
    x = np.ascontiguousarray(x, dtype=float)
    o = np.empty_like(x)
    fn = getattr(vlib, f"loop_{name}")
    fn.argtypes = [ctypes.c_void_p, ctypes.c_void_p, ctypes.c_int64]
    fn(x.ctypes.data, o.ctypes.data, x.size)
    return o


@pytest.mark.parametrize("name", NAMES + ("bg_tanh",))
def test_translated_functions_within_two_ulp_of_numpy(vlib, name):
    """The vmath functions translated to C (and the point kernels' tanh) are
    within 2 ulp of numpy's, as the numba-compiled ones are
    (tests/test_vmath.py), with the same non-finite values."""
    x = _points(name if name != "bg_tanh" else "_vtanh", 2 * 10**5)
    if name in ("_vsin", "_vcos"):
        x = x[np.abs(x) < 1e8]
    edges = np.array([0.0, -0.0, np.nan, 0.55, -0.55, 0.625, -0.625, 0.66, 2.414213562373095,
                      709.78, -708.3, 1e-300, -1e-300])
    if name not in ("_vsin", "_vcos"):
        edges = np.concatenate([edges, [np.inf, -np.inf]])
    x = np.concatenate([x, edges])
    got = _run(vlib, name, x)
    with np.errstate(all="ignore"):
        ref = REFERENCE[name](x).astype(float)
    ok = np.isfinite(ref) & (np.abs(ref) > 1e-300)
    ulp = np.abs(got[ok] - ref[ok]) / np.spacing(np.abs(ref[ok]))
    assert ulp.max() <= 2.0, (name, float(ulp.max()), float(x[ok][ulp.argmax()]))
    np.testing.assert_array_equal(np.isinf(got[~ok]), np.isinf(ref[~ok]))
    np.testing.assert_array_equal(np.isnan(got[~ok]), np.isnan(ref[~ok]))


def test_pow2_is_vmaths_to_the_bit(vlib):
    """The C prelude's 2**n by exponent bits equals vmath._pow2 (selects over
    the bits of n) for every n the exponential functions give it."""
    n = np.arange(-1022, 1024, dtype=np.int64)
    o = np.empty(n.size)
    vlib.pow2s.argtypes = [ctypes.c_void_p, ctypes.c_void_p, ctypes.c_int64]
    vlib.pow2s(n.ctypes.data, o.ctypes.data, n.size)
    want = np.array([vmath._pow2(int(k)) for k in n])
    np.testing.assert_array_equal(o, want)
    np.testing.assert_array_equal(o, np.ldexp(1.0, n))


#: exponents ±m/4 the column kernels take by square roots (bg_powq)
QUARTERS = (0.25, 0.5, 0.75, 1.25, 1.5, 2.25, 7.75, -0.25, -0.5, -0.75, -1.25, -1.5, -7.75)


def test_quarter_powers_of_the_column_kernels_within_ulps_of_pow(tmp_path):
    """A column kernel's x**(±m/4) (bg_powq: square roots, which gcc
    vectorises, where pow is a library call that keeps the loop over the
    sigma points scalar) is within 4 + |e| ulp of libm's pow (numba's), with its
    values at ±0, ±inf, NaN and x < 0; point kernels keep pow (numba's, to the
    bit), and an exponent that is not a quarter stays pow."""
    body = "".join(f"    _y[{i}] = np.power(_X[0], {e})\n" for i, e in enumerate(QUARTERS))
    src = ("N_X = 1\n"
           "def f(x, u, theta, _dxdt):\n    _dxdt[0] = np.power(x[0], 0.25)\n"
           "def h(x, u, theta, _y):\n    _y[0] = x[0]**0.3\n"
           "def f_dfdx(x, u, theta, _dxdt, _J):\n    return\n"
           "def f_cols(_X, u, theta, _dxdt):\n    _dxdt[0] = _X[0]**-1.25\n"
           f"def h_cols(_X, u, theta, _y):\n{body}")
    text = codegen_ckernel.translate(src)
    assert "pow(x[0], 0.25)" in text and "pow(x[0], 0.3)" in text
    assert "bg_powq(_X[0], 5, 1)" in text and text.count("bg_powq(_X[0], ") == 1 + len(QUARTERS)
    text += ("\nvoid powq_all(const double *x, double *o, double *r, int64_t n)\n{\n"
             "    for (int64_t j = 0; j < n; ++j) {\n"
             + "".join(f"        o[{i} * n + j] = bg_powq(x[j], {int(abs(e) * 4)}, {int(e < 0)});\n"
                       f"        r[{i} * n + j] = pow(x[j], {e});\n"
                       for i, e in enumerate(QUARTERS)) + "    }\n}\n")
    lib = tmp_path / "powq.so"
    compiled_c.build(text, lib)
    fn = ctypes.CDLL(str(lib)).powq_all
    fn.argtypes = [ctypes.c_void_p, ctypes.c_void_p, ctypes.c_void_p, ctypes.c_int64]
    rng = np.random.default_rng(3)
    x = np.concatenate([np.exp(rng.uniform(-700, 700, 50_000)), rng.uniform(0, 10, 50_000),
                        [0.0, -0.0, np.inf, -np.inf, np.nan, -1.0, -1e-300, 5e-324, 1e300]])
    o, pw = np.empty((len(QUARTERS), x.size)), np.empty((len(QUARTERS), x.size))
    fn(x.ctypes.data, o.ctypes.data, pw.ctypes.data, x.size)
    for i, e in enumerate(QUARTERS):
        ref = pw[i]         # libm's pow, which numba's kernels call
        np.testing.assert_array_equal(np.isnan(o[i]), np.isnan(ref), err_msg=f"x**{e}")
        fin = np.isfinite(ref) & (ref > 1e-300)
        ulp = np.abs(o[i][fin] - ref[fin]) / np.spacing(ref[fin])
        assert ulp.max() <= 4 + abs(e), (e, ulp.max())     # a rounding per product
        tiny = (ref > 0) & (ref <= 1e-300)     # near and below the subnormals: relative error
        assert np.all(np.abs(o[i][tiny] - ref[tiny]) <= 1e-12 * ref[tiny] + 1e-320), e
        other = ~fin & ~tiny & ~np.isnan(ref)       # 0, inf
        np.testing.assert_array_equal(o[i][other], ref[other], err_msg=f"x**{e}")


def _close(got, ref, tol=1e-12):
    """Within ``tol`` of each entry's magnitude plus the largest magnitude
    (an entry that cancels keeps a rounding of the terms it sums)."""
    ok = np.isfinite(ref)
    np.testing.assert_array_equal(np.isfinite(got), ok)
    scale = np.max(np.abs(ref[ok]), initial=0.0)
    assert np.all(np.abs(got - ref)[ok] <= tol * (np.abs(ref[ok]) + scale) + 1e-300)


@pytest.mark.parametrize("name", MODELS)
def test_c_kernels_equal_the_numba_kernels(name):
    """Every kernel of every registered model: the C translation gives the
    numba kernel's values at random points and parameter sets: f, h and
    df/dx to the bit (the same statements, neither compiler contracts a
    multiply-add: -ffp-contract=off), the column kernels to 1e-12 of the
    entry's scale (numba compiles them with LLVM's arcp and contract, gcc
    makes other choices)."""
    m = Model.load(name)
    c, nb = compiled.point_kernels(m, kind="c"), compiled.point_kernels(m, kind="numba")
    assert c.kind == "c" and nb.kind == "numba"
    rng = np.random.default_rng(11)
    npt = padded_points(m.n_x)
    for _ in range(20):
        th = m.theta0 * np.exp(rng.normal(size=m.n_theta) * 0.2)
        x = m.x0 + rng.normal(size=m.n_x) * (np.abs(m.x0) + 0.1)
        u = m.u0 + rng.normal(size=m.n_u) * 0.1
        X = (np.tile(x, (npt, 1)) + rng.normal(size=(npt, m.n_x)) * 0.1).T.copy().ravel()
        for k, n in (("f", m.n_x), ("h", m.n_y)):
            a, b = np.empty(n), np.empty(n)
            getattr(c, k)(x, u, th, a)
            getattr(nb, k)(x, u, th, b)
            np.testing.assert_array_equal(a, b)
        a, b, Ja, Jb = np.empty(m.n_x), np.empty(m.n_x), np.empty((m.n_x,) * 2), np.empty(
            (m.n_x,) * 2)
        c.f_dfdx(x, u, th, a, Ja)
        nb.f_dfdx(x, u, th, b, Jb)
        np.testing.assert_array_equal(a, b)
        np.testing.assert_array_equal(Ja, Jb)
        for k, n in (("f_cols", m.n_x), ("h_cols", m.n_y)):
            a, b = np.empty(n * npt), np.empty(n * npt)
            getattr(c, k)(X, u, th, a)
            getattr(nb, k)(X, u, th, b)
            with np.errstate(all="ignore"):
                _close(a, b)


@pytest.mark.parametrize("name", ["mass_spring_damper", "emps", "vehicle_coastdown"])
def test_fused_kernel_with_c_kernels_equals_numpy(name, monkeypatch):
    """The fused UKF kernel calling the C kernels (through numba's wrapper
    address protocol) gives the numpy filter's NLL within 1e-9 relative, as
    with the numba kernels (tests/test_ukf_numba.py)."""
    from tests.test_ukf_numba import _record, assert_same, box_sets
    monkeypatch.setenv(compiled.KERNELS_ENV, "c")
    m = Model.load(name)
    t, u, y = _record(m, N=80, substeps=40)
    th = box_sets(m, 6, seed=3)
    b = ukf_nll(m, t, u, y, th, options=UKFOptions(backend="numba"))
    assert compiled.point_kernels(m).kind == "c"
    assert_same(ukf_nll(m, t, u, y, th, options=UKFOptions(backend="numpy")), b)


def test_a_kernel_takes_only_contiguous_float_arrays():
    """Called from Python a C kernel checks what numba's dispatcher would: a
    strided or integer array is refused with the kernel named, not read
    past its end."""
    m = Model.load("mass_spring_damper")
    c = compiled.point_kernels(m, kind="c")
    out = np.empty(m.n_x)
    with pytest.raises(TypeError, match="C-contiguous float64"):
        c.f(np.zeros(2 * m.n_x)[::2], m.u0, m.theta0, out)
    with pytest.raises(TypeError, match="takes 4 arrays"):
        c.f(m.x0, m.u0, m.theta0)


def test_the_translator_names_what_it_cannot_translate():
    src = ("N_X = 1\n"
           "def f(x, u, theta, _dxdt):\n    _dxdt[0] = np.frobnicate(x[0])\n"
           "def h(x, u, theta, _y):\n    return\n"
           "def f_dfdx(x, u, theta, _dxdt, _J):\n    return\n"
           "def f_cols(_X, u, theta, _dxdt):\n    return\n"
           "def h_cols(_X, u, theta, _y):\n    return\n")
    with pytest.raises(CodegenError, match="np.frobnicate"):
        codegen_ckernel.translate(src)
    # true division of integers stays a float division; a power by products
    src2 = src.replace("np.frobnicate(x[0])", "x[0]**3 + 1/2")
    text = codegen_ckernel.translate(src2)
    assert "((double)1 / (double)2)" in text and "((x[0] * x[0]) * x[0])" in text


def _in_child(code: str, env: dict) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", code], env=dict(os.environ, **env),
                          capture_output=True, text=True, timeout=600)


def test_without_a_compiler_numba_compiles_and_says_so(tmp_path):
    """No C compiler ($CC names none, PATH has none): the default falls back
    to numba with a BackendWarning naming the reason; ``BONDGRAPH_KERNELS=c``
    raises instead; ``numba`` never tries the C compiler."""
    code = ("import warnings, numpy as np\n"
            "from bondgraph.numerics import compiled\n"
            "from bondgraph.numerics.model import Model\n"
            "m = Model.from_spec('bondgraph.catalog.reference:mass_spring_damper')\n"
            "with warnings.catch_warnings(record=True) as w:\n"
            "    warnings.simplefilter('always')\n"
            "    try:\n"
            "        pk = compiled.point_kernels(m, kind='c')\n"
            "        print('kind', pk.kind)\n"
            "    except Exception as exc:\n"
            "        print('raised', type(exc).__name__)\n"
            "    print('default', compiled.kernel_kind(), compiled.point_kernels(m).kind)\n"
            "print('warned', any('C kernels' in str(x.message) for x in w))\n")
    env = {"CC": str(tmp_path / "no-such-cc"), "PATH": str(tmp_path),
           compiled.CACHE_ENV: str(tmp_path / "cache")}
    r = _in_child(code, env)
    assert r.returncode == 0, r.stderr
    assert "raised CCompileError" in r.stdout and "default numba numba" in r.stdout, r.stdout
    r = _in_child(code.replace("kind='c'", "kind=None"),
                  dict(env, **{compiled.KERNELS_ENV: "c"}))
    assert "raised CCompileError" in r.stdout, r.stdout + r.stderr
    bad = _in_child("from bondgraph.numerics import compiled; compiled.kernel_kind()",
                    {compiled.KERNELS_ENV: "fortran"})
    assert "BONDGRAPH_KERNELS='fortran'" in bad.stderr


def test_a_model_the_compiler_refuses_falls_back_to_numba(tmp_path, monkeypatch):
    """A C compiler that fails (here: one that always exits 1) leaves the
    numba kernels to run, with a BackendWarning that names the compiler's
    complaint; the numbers are numba's."""
    cc = tmp_path / "failing-cc"
    cc.write_text("#!/bin/sh\nif [ \"$1\" = --version ]; then echo failing-cc 1.0; exit 0; fi\n"
                  "echo 'error: refused' >&2; exit 1\n")
    cc.chmod(0o755)
    code = ("import warnings\n"
            "from bondgraph.numerics import compiled\n"
            "from bondgraph.numerics.model import Model\n"
            "m = Model.from_spec('bondgraph.catalog.reference:mass_spring_damper')\n"
            "with warnings.catch_warnings(record=True) as w:\n"
            "    warnings.simplefilter('always')\n"
            "    print(compiled.point_kernels(m).kind)\n"
            "print([str(x.message) for x in w if 'C kernels' in str(x.message)])\n")
    r = _in_child(code, {"CC": str(cc), compiled.CACHE_ENV: str(tmp_path / "cache")})
    assert r.returncode == 0, r.stderr
    assert r.stdout.splitlines()[0] == "numba"
    assert "refused" in r.stdout and "numba compiles them" in r.stdout


def test_the_translation_index_names_the_library_the_translation_does(tmp_path, monkeypatch):
    """A numba source's library found through the on-disk index (no
    translation) is the one its C translation names; another source gets
    another entry; an index that does not name a library is not trusted."""
    monkeypatch.setenv(compiled.CACHE_ENV, str(tmp_path / "cache"))
    monkeypatch.setattr(compiled, "_C_LIBRARIES", {})
    model = Model.load(MODELS[0])
    src = compiled.kernel_source_path(model)
    a, b = tmp_path / "a.py", tmp_path / "b.py"
    a.write_text(src.read_text())
    b.write_text(src.read_text() + "\n# another source\n")
    truth = compiled_c.library_path(compiled._c_text(a), tmp_path / "cache", "a")
    assert compiled._c_library(a) == truth
    (entry,) = (tmp_path / "cache" / "c" / "index").iterdir()
    assert entry.read_text() == truth.name
    calls = []
    monkeypatch.setattr(compiled, "_c_text", lambda p: calls.append(p) or "x")
    monkeypatch.setattr(compiled, "_C_LIBRARIES", {})
    assert compiled._c_library(a) == truth and calls == []       # from the index
    assert compiled._c_library(b) != truth and calls == [b]      # its own entry
    entry.write_text("../elsewhere")
    monkeypatch.setattr(compiled, "_C_LIBRARIES", {})
    assert compiled._c_library(a) == compiled_c.library_path("x", tmp_path / "cache", "a")

"""The branch-free sin, cos, atan, exp and tanh of the numba column kernels
(the functions of bondgraph.core.vmath, compiled once by
bondgraph.numerics.vmath_jit; Moshier 1989, the Cephes library), equal to
the bit to their statements written out (codegen_numba.vmath_inline), against
numpy's (glibc's) functions: within 2 ulp on 1e6 points per range, the same
non-finite values, and vectorised by LLVM in a loop; and the same functions
called as plain Python."""

import re

import numpy as np
import pytest

from bondgraph.core import codegen_numba
from bondgraph.core import vmath

numba = pytest.importorskip("numba")

NAMES = ("_vsin", "_vcos", "_vatan", "_vexp", "_vtanh")
REFERENCE = {"_vsin": np.sin, "_vcos": np.cos, "_vatan": np.arctan, "_vexp": np.exp,
             "_vtanh": np.tanh}


def _expanded() -> dict:
    """Each function as straight code: what :func:`codegen_numba.vmath_inline`
    writes out at a call site (the column kernels up to
    ``NUMBA_CODEGEN_VERSION`` 7), compiled with the column kernels' flags
    (inlined into the loops below)."""
    ns = {"np": np, "intrinsic": numba.extending.intrinsic, "types": numba.types}
    exec(codegen_numba.NUMBA_SELECT, ns)
    for name in NAMES:
        exec(codegen_numba.vmath_function(name), ns)
        ns[name] = numba.njit(error_model="numpy", inline="always",
                              fastmath=set(codegen_numba.COLS_FASTMATH))(ns[name])
    return ns


def _functions() -> dict:
    """Each function as the column kernels run it: compiled once by
    :mod:`bondgraph.numerics.vmath_jit` and called (LLVM inlines it)."""
    from bondgraph.numerics import vmath_jit
    return {name: getattr(vmath_jit, name) for name in NAMES}


def _loops(ns) -> dict:
    """For each function of ``ns`` a compiled loop ``out[j] = fn(x[j])``
    with the column kernels' flags (:data:`codegen_numba.COLS_FASTMATH`),
    over a trip count known at run time only, as in the column kernels."""
    out = {}
    for name in NAMES:
        fn = ns[name]

        def loop(x, o, fn=fn):
            for j in range(x.shape[0]):
                o[j] = fn(x[j])

        out[name] = numba.njit(error_model="numpy",
                               fastmath=set(codegen_numba.COLS_FASTMATH))(loop)
    return out


@pytest.fixture(scope="module")
def loops():
    """The loops of the functions the column kernels call."""
    return _loops(_functions())


@pytest.mark.parametrize("name", NAMES)
def test_compiled_equals_expanded(loops, name):
    """The compiled functions the column kernels call give, to the bit, what
    the statements written out at a call site gave (the same code, the same
    flags), NaN and inf included."""
    x = np.concatenate([_points(name)[::7],
                        [0.0, -0.0, np.inf, -np.inf, np.nan, 709.79, -745.0, 1e-300]])
    got, want = np.empty_like(x), np.empty_like(x)
    loops[name](x, got)
    _loops(_expanded())[name](x, want)
    np.testing.assert_array_equal(got, want)


def _points(name, n=10**6):
    """Arguments of vmath function ``name``: ``n`` normal, uniform and
    log-uniform of both signs, and the function's own hard ranges."""
    rng = np.random.default_rng(3)
    sets = [rng.normal(size=n) * 3, rng.uniform(-50.0, 50.0, n),
            np.exp(rng.uniform(-40.0, 18.0, n)) * rng.choice([-1.0, 1.0], n)]
    if name in ("_vsin", "_vcos"):
        sets.append(rng.uniform(-1e8, 1e8, 10**5))
    if name == "_vexp":
        sets.append(rng.uniform(-708.39, 709.78, n))
    if name == "_vatan":
        sets.append(np.exp(rng.uniform(-300.0, 300.0, n)) * rng.choice([-1.0, 1.0], n))
    return np.concatenate(sets)


@pytest.mark.parametrize("name", NAMES)
def test_within_two_ulp_of_numpy(loops, name):
    x = _points(name)
    if name in ("_vsin", "_vcos"):
        x = x[np.abs(x) < 1e8]
    got = np.empty_like(x)
    loops[name](x, got)
    with np.errstate(all="ignore"):
        ref = REFERENCE[name](x)
    ok = np.isfinite(ref) & (np.abs(ref) > 1e-300)
    ulp = np.abs(got[ok] - ref[ok]) / np.spacing(np.abs(ref[ok]))
    assert ulp.max() <= 2.0, (name, float(ulp.max()), float(x[ok][ulp.argmax()]))
    # where the reference is 0, inf or NaN, the same (exp: 0 below -708.40,
    # where numpy's exp is subnormal)
    np.testing.assert_array_equal(np.isinf(got[~ok]), np.isinf(ref[~ok]))
    np.testing.assert_array_equal(np.isnan(got[~ok]), np.isnan(ref[~ok]))


@pytest.mark.parametrize("name", NAMES)
def test_non_finite_and_edges(loops, name):
    x = np.array([0.0, -0.0, np.inf, -np.inf, np.nan, 0.625, -0.625, 0.66, 2.414213562373095,
                  708.5, -708.3, 709.78, 709.79, -745.0, 1e-300, -1e-300])
    if name in ("_vsin", "_vcos"):
        x = x[~np.isinf(x)]  # the column kernels recompute those with numpy's sin and cos
    got = np.empty_like(x)
    loops[name](x, got)
    with np.errstate(all="ignore"):
        ref = REFERENCE[name](x)
    if name == "_vexp":
        ref = np.where(x < -708.3964185322641, 0.0, ref)
    np.testing.assert_allclose(got, ref, rtol=3e-16, atol=0)
    np.testing.assert_array_equal(np.isnan(got), np.isnan(ref))


def test_loops_vectorise():
    """A loop over a column kernel's points that calls these functions
    compiles to vector instructions: LLVM inlines them (a libm call would
    keep it scalar), also in a loop as short as that of a one-state model
    (its trip count, as in the column kernels, known at run time only)."""
    ns = _functions()
    vsin, vatan, vtanh = ns["_vsin"], ns["_vatan"], ns["_vtanh"]

    @numba.njit(error_model="numpy", fastmath=set(codegen_numba.COLS_FASTMATH))
    def body(x, o):
        for j in range(min(21, o.shape[0])):
            o[j] = vsin(1.3 * vatan(x[j] - vatan(x[j]))) + vtanh(0.25 * x[21 + j])

    x, o = np.linspace(-3.0, 3.0, 42), np.empty(21)
    body(x, o)
    ir = "".join(body.inspect_llvm().values())
    assert re.search(r"<\d+ x double>", ir)


@pytest.mark.parametrize("name", NAMES + ("_tanh",))
def test_plain_python_equals_numpy(name):
    """The functions of bondgraph.core.vmath are real Python functions:
    called on floats and numpy scalars (``_sel`` is ``a if c else b`` there)
    they agree with numpy's to a few ulp (finite arguments; sin and cos
    below 1e8)."""
    fn = getattr(vmath, name)
    ref = {**REFERENCE, "_tanh": np.tanh}[name]
    rng = np.random.default_rng(5)
    x = np.concatenate([rng.normal(size=300) * 3, rng.uniform(-50.0, 50.0, 300),
                        [0.0, 0.55, -0.55, 0.625, -0.625, 0.66, 2.414213562373095, 1e-300]])
    if name == "_vexp":
        x = np.concatenate([x, rng.uniform(-700.0, 700.0, 300)])
    got = np.array([fn(v) for v in x.tolist()] + [fn(v) for v in x[:50]])
    want = ref(np.concatenate([x, x[:50]]))
    np.testing.assert_allclose(got, want, rtol=5e-16, atol=1e-300)

"""The generated code of a long chain (20 masses, 39 states) against values
computed independently: the chain's equations written by hand in numpy, and
central finite differences of them for the Jacobians.

A long chain exercises what a small model does not: the sparse (banded)
Jacobian, the common subexpressions shared by f and df/dx, the tree CSE of
the energy sums, and the numba kernels' text from the same expressions.
"""

import json
import os
import subprocess
import sys

import numpy as np
import pytest

from bondgraph.catalog.reference import mass_chain
from bondgraph.core.codegen import generate_source, module_from_source
from bondgraph.core.codegen_numba import generate_numba_source, padded_points
from bondgraph.core.equations import derive

N = 20                      # masses: 2N - 1 = 39 states
NX = 2 * N - 1


@pytest.fixture(scope="module")
def chain():
    ss = derive(mass_chain(N))
    mod = module_from_source(generate_source(ss), "_test_chain20")
    return ss, mod


def _split(mod, theta):
    """Masses, stiffnesses and dampings from theta (..., n_theta) by name."""
    names = list(mod.PARAMS)
    m = np.stack([theta[..., names.index(f"m{i}")] for i in range(1, N + 1)], -1)
    k = np.stack([theta[..., names.index(f"k{j}")] for j in range(1, N)], -1)
    c = np.stack([theta[..., names.index(f"c{j}")] for j in range(1, N)], -1)
    return m, k, c


def _hand(mod, x, u, theta):
    """The chain by hand (reference.mass_chain's docstring): v_i = p_i/m_i,
    spring-damper j between masses j and j+1 pulls with k_j q_j + c_j (v_j -
    v_j+1); dq_j/dt = v_j - v_j+1. Returns f, energy, source and dissipated
    power."""
    st = list(mod.STATES)
    p = np.stack([x[..., st.index(f"p_M{i}")] for i in range(1, N + 1)], -1)
    q = np.stack([x[..., st.index(f"q_K{j}")] for j in range(1, N)], -1)
    m, k, c = _split(mod, theta)
    v = p / m
    dv = v[..., :-1] - v[..., 1:]
    force = k * q + c * dv
    dp = np.zeros_like(p)
    dp[..., 0] += u[..., 0]
    dp[..., :-1] -= force
    dp[..., 1:] += force
    f = np.empty(x.shape)
    for i in range(1, N + 1):
        f[..., st.index(f"p_M{i}")] = dp[..., i - 1]
    for j in range(1, N):
        f[..., st.index(f"q_K{j}")] = dv[..., j - 1]
    energy = (p ** 2 / (2 * m)).sum(-1) + (k * q ** 2 / 2).sum(-1)
    return f, energy, u[..., 0] * v[..., 0], (c * dv ** 2).sum(-1)


def _points(mod, n, seed):
    rng = np.random.default_rng(seed)
    x = rng.normal(size=(n, NX))
    u = rng.normal(size=(n, 1))
    theta = mod.PARAM_DEFAULTS * rng.uniform(0.5, 1.5, size=(n, len(mod.PARAMS)))
    return x, u, theta


def _central(fun, z, h):
    """Central differences of fun (..., m) in the last axis of z (..., n):
    (..., m, n)."""
    cols = []
    for j in range(z.shape[-1]):
        e = np.zeros(z.shape[-1])
        e[j] = h
        cols.append((fun(z + e) - fun(z - e)) / (2 * h))
    return np.stack(cols, -1)


def test_chain_f_and_energy_match_hand_equations(chain):
    ss, mod = chain
    assert len(ss.states) == NX
    x, u, theta = _points(mod, 7, seed=1)
    f, energy, p_src, p_diss = _hand(mod, x, u, theta)
    np.testing.assert_allclose(mod.f(x, u, theta), f, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(mod.energy(x, u, theta), energy, rtol=1e-12)
    np.testing.assert_allclose(mod.power_sources(x, u, theta), p_src, rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(mod.power_dissipated(x, u, theta), p_diss, rtol=1e-12)
    np.testing.assert_allclose(mod.energy_rate(x, u, theta), p_src - p_diss,
                               rtol=1e-10, atol=1e-10 * np.abs(p_diss).max())


def test_chain_jacobians_match_central_differences(chain):
    """df/dx and df/dθ of the generated module (and f_dfdx) against central
    differences of the hand-written f; df/dx is banded (f is linear in x, so
    the differences are exact but for rounding)."""
    _, mod = chain
    x, u, theta = _points(mod, 3, seed=2)
    J = mod.dfdx(x, u, theta)
    fd = _central(lambda z: _hand(mod, z, u, theta)[0], x, 1e-3)
    np.testing.assert_allclose(J, fd, rtol=1e-9, atol=1e-9)
    # a chain couples each state to its neighbours only
    assert np.count_nonzero(J[0]) <= 5 * NX
    f2, J2 = mod.f_dfdx(x, u, theta)
    np.testing.assert_allclose(f2, _hand(mod, x, u, theta)[0], rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(J2, J, rtol=1e-14, atol=0)
    Jt = mod.dfdtheta(x, u, theta)
    h = 1e-6 * mod.PARAM_DEFAULTS
    cols = [(_hand(mod, x, u, theta + h[j] * np.eye(len(h))[j])[0]
             - _hand(mod, x, u, theta - h[j] * np.eye(len(h))[j])[0]) / (2 * h[j])
            for j in range(len(h))]
    np.testing.assert_allclose(Jt, np.stack(cols, -1), rtol=1e-6, atol=1e-6)


_NUMBA_SCRIPT = r"""
import json, sys
import numpy as np
from bondgraph.catalog.reference import mass_chain
from bondgraph.core.codegen_numba import generate_numba_source
from bondgraph.core.equations import derive
ns = {}
exec(compile(generate_numba_source(derive(mass_chain(int(sys.argv[1])))), "<chain>", "exec"), ns)
pts = json.loads(sys.stdin.read())
out = []
for x, u, th in zip(pts["x"], pts["u"], pts["theta"]):
    x, u, th = (np.array(a) for a in (x, u, th))
    dx, dx2, J = np.empty(x.size), np.empty(x.size), np.empty((x.size, x.size))
    ns["f"](x, u, th, dx)
    ns["f_dfdx"](x, u, th, dx2, J)
    npt = ns["N_PTS"]
    X = np.repeat(x[:, None], npt, 1).ravel()
    cols = np.empty(x.size * npt)
    ns["f_cols"](X, u, th, cols)
    out.append({"f": dx.tolist(), "f2": dx2.tolist(), "J": J.tolist(),
                "cols": cols.reshape(x.size, npt).T.tolist()})
print(json.dumps(out))
"""


def test_chain_numba_kernel_text_matches_hand_equations(chain):
    """The numba kernels' text (f, f_dfdx, f_cols), run as plain Python
    (NUMBA_DISABLE_JIT in a fresh interpreter: the values of the generated
    text, without compiling), against the hand-written chain."""
    _, mod = chain
    x, u, theta = _points(mod, 2, seed=3)
    env = dict(os.environ, NUMBA_DISABLE_JIT="1")
    r = subprocess.run([sys.executable, "-c", _NUMBA_SCRIPT, str(N)], env=env, text=True,
                       capture_output=True, check=True, timeout=300,
                       input=json.dumps({"x": x.tolist(), "u": u.tolist(),
                                         "theta": theta.tolist()}))
    got = json.loads(r.stdout.strip().splitlines()[-1])
    f = _hand(mod, x, u, theta)[0]
    J = _central(lambda z: _hand(mod, z, u, theta)[0], x, 1e-3)
    for p, g in enumerate(got):
        np.testing.assert_allclose(g["f"], f[p], rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(g["f2"], f[p], rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(g["J"], J[p], rtol=1e-9, atol=1e-9)
        cols = np.array(g["cols"])
        assert cols.shape == (padded_points(NX), NX)
        np.testing.assert_allclose(cols, np.broadcast_to(f[p], cols.shape), rtol=1e-12,
                                   atol=1e-12)
    assert "def f_cols(" in generate_numba_source(chain[0])


def test_tree_cse_prints_the_same_values():
    """codegen.Shared (the tree method, used for the energy sums): shared
    nodes printed as variables, children first, the unneeded ones left out;
    the printed code equals numpy's values of the expressions themselves
    (sympy.lambdify without CSE)."""
    import sympy as sp

    from bondgraph.core.codegen import Shared, _Printer, live_definitions

    x, y, z = sp.symbols("x y z", real=True)
    a = x * y + sp.sin(z)
    b = 1 / (a + 2)
    exprs = [a * b - x / y, sp.exp(a) * b ** 2 + sp.tanh(x - y), -x / y + a,
             sp.Piecewise((a, x > 0), (b, True)), b, sp.sqrt(a ** 2 + 1) * (x - y)]
    sh = Shared(exprs)
    assert {n for n, _ in sh.repl} >= {"_t0", "_t1"}          # a and b are shared
    assert sh.free == {x, y, z}
    assert sh.depends({z}) == [z in e.free_symbols for _, e in sh.repl]
    pr = _Printer({})
    defs = [(n, pr.code(e, sh, k)) for k, (n, e) in enumerate(sh.repl)]
    outs = [pr.code(e, sh) for e in sh.reduced]
    code = "\n".join(f"{n} = {t}" for n, t in live_definitions(defs, "\n".join(outs)))
    rng = np.random.default_rng(4)
    X, Y, Z = rng.normal(size=(3, 11))
    ns = {"np": np, "x": X, "y": Y, "z": Z}
    exec(f"{code}\n_out = [{', '.join(outs)}]", ns)
    ref = sp.lambdify((x, y, z), exprs, "numpy", cse=False)(X, Y, Z)
    for got, want in zip(ns["_out"], ref):
        np.testing.assert_allclose(np.broadcast_to(got, X.shape), want, rtol=1e-13)

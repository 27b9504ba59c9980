"""Linearisation (issue 31): A, B, C, D against central finite differences
of the generated f and h, the equilibrium against hand-derived values, the
frequency response of (A, B, C, D) (scipy.signal) against the nonlinear
model's small-signal response (solve_ivp), and the command."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy import signal
from scipy.integrate import solve_ivp
from scipy.optimize import brentq

from bondgraph.core.graph import BondGraph
from bondgraph.errors import ExportError
from bondgraph.export.linearize import linear_model, linearize
from bondgraph.numerics.model import Model

#: the transfer function of an output with a zero leading numerator coefficient
pytestmark = pytest.mark.filterwarnings("ignore::scipy.signal.BadCoefficients")


def nonlinear_tanks() -> BondGraph:
    """Pump Q into tank 1 (C1), a pipe (inertance L, resistance
    e = r1 f + r3 f^3) to tank 2 (C2), an outlet f = g1 e + g3 e^3.

    Equilibrium for a constant Q0 (hand-derived): pipe flow Q0, p2 the root
    of g1 p2 + g3 p2^3 = Q0, p1 = p2 + r1 Q0 + r3 Q0^3."""
    g = BondGraph("nonlinear_tanks", "Two tanks, a pipe with inertia, cubic laws.")
    Q = g.input("Q", "m^3/s", 1.0, "pump flow")
    C1 = g.param("C1", 1.0, "m^3/Pa")
    C2 = g.param("C2", 2.0, "m^3/Pa")
    L = g.param("L", 0.5, "Pa*s^2/m^3")
    r1, r3 = g.param("r1", 1.0, "Pa*s/m^3"), g.param("r3", 0.5, "Pa*s^3/m^9")
    g1, g3 = g.param("g1", 1.0, "m^3/(Pa*s)"), g.param("g3", 0.5, "m^3/(Pa^3*s)")
    t1 = g.zero("tank1", domain="hydraulic")
    g.connect(g.Sf("pump", Q), t1)
    g.connect(t1, g.C("C_1", C1))
    pipe = g.one("pipe", domain="hydraulic")
    g.connect(t1, pipe)
    g.connect(pipe, g.I("I_pipe", L))
    g.connect(pipe, g.R("R_pipe", effort=lambda f: r1 * f + r3 * f**3))
    t2 = g.zero("tank2", domain="hydraulic")
    g.connect(pipe, t2)
    g.connect(t2, g.C("C_2", C2))
    g.connect(t2, g.R("outlet", flow=lambda e: g1 * e + g3 * e**3))
    g.sensor("p1", t1.e, unit="Pa")
    g.sensor("Q_pipe", pipe.f, unit="m^3/s")
    return g


def _fd(fun, z, h):
    """Central differences of fun at z, step h per component."""
    cols = []
    for j in range(z.size):
        e = np.zeros_like(z)
        e[j] = h[j]
        cols.append((fun(z + e) - fun(z - e)) / (2 * h[j]))
    return np.column_stack(cols) if cols else np.zeros((fun(z).size, 0))


def _assert_close(M, ref, what, rel=1e-7):
    scale = max(np.max(np.abs(ref), initial=0.0), 1e-300)
    err = np.max(np.abs(M - ref), initial=0.0)
    assert err <= rel * scale, f"{what}: max error {err:.3g} of scale {scale:.3g}"


@pytest.mark.parametrize("case", ["nonlinear_tanks", "hydraulic_tanks", "vehicle_coastdown",
                                  "toy_cvt"])
def test_jacobians_match_central_differences(case):
    """A, B, C, D equal central differences of the generated numpy f and h
    (the committed module for registered models) to 1e-7 of each matrix's
    largest entry, at a point off equilibrium."""
    model = nonlinear_tanks() if case == "nonlinear_tanks" else case
    m = linear_model(model)
    ref = Model.from_graph(nonlinear_tanks()) if case == "nonlinear_tanks" else Model.load(case)
    rng = np.random.default_rng(1)
    x = ref.x0 + (0.2 + np.abs(ref.x0)) * rng.uniform(0.5, 1.0, ref.n_x)
    u = ref.u0 + rng.uniform(0.5, 1.0, ref.n_u)
    lin = linearize(m, {**dict(zip(ref.states, x)), **dict(zip(ref.inputs, u))})
    assert not lin.equilibrium
    th = ref.theta0

    def f(xx, uu):
        return ref.f(xx, uu, th)

    def h(xx, uu):
        return ref.h(xx, uu, th)

    hx, hu = 1e-5 * (1 + np.abs(x)), 1e-5 * (1 + np.abs(u))
    _assert_close(lin.A, _fd(lambda z: f(z, u), x, hx), f"{case} A")
    _assert_close(lin.B, _fd(lambda z: f(x, z), u, hu), f"{case} B")
    _assert_close(lin.C, _fd(lambda z: h(z, u), x, hx), f"{case} C")
    if np.any(lin.D):
        _assert_close(lin.D, _fd(lambda z: h(x, z), u, hu), f"{case} D")
    else:
        assert np.max(np.abs(_fd(lambda z: h(x, z), u, hu))) < 1e-12


def test_equilibrium_is_the_hand_derived_one():
    lin = linearize(nonlinear_tanks(), {"Q": 1.0})
    p2 = brentq(lambda p: p + 0.5 * p**3 - 1.0, 0.0, 2.0)
    p1 = p2 + 1.0 + 0.5
    x = dict(zip(lin.states, lin.x))
    assert lin.equilibrium and lin.residual < 1e-12
    assert x["q_C_1"] == pytest.approx(1.0 * p1, rel=1e-10)
    assert x["q_C_2"] == pytest.approx(2.0 * p2, rel=1e-10)
    assert x["p_I_pipe"] == pytest.approx(0.5 * 1.0, rel=1e-10)
    # the pipe's linearised resistance r1 + 3 r3 Q0^2 = 2.5 in A
    i = lin.states.index("p_I_pipe")
    assert lin.A[i, i] == pytest.approx(-2.5 / 0.5, rel=1e-12)


@pytest.mark.parametrize("w", [0.3, 1.0, 3.0])
def test_frequency_response_matches_small_signal_simulation(w):
    """scipy.signal.freqresp of (A, B, C, D) against the amplitude and phase
    fitted to the nonlinear model's response to Q0 + a sin(w t) (solve_ivp),
    once the transient has died out."""
    lin = linearize(nonlinear_tanks(), {"Q": 1.0})
    m = Model.from_graph(nonlinear_tanks())
    a, th = 1e-4, m.theta0
    slow = min(abs(lin.poles().real))
    t_end = 30 / slow + 20 * 2 * np.pi / w
    t_fit = np.linspace(t_end - 10 * 2 * np.pi / w, t_end, 4001)

    def rhs(t, x):
        return m.f(x, np.array([1.0 + a * np.sin(w * t)]), th)

    sol = solve_ivp(rhs, (0, t_end), lin.x, method="LSODA", rtol=1e-11, atol=1e-13,
                    t_eval=t_fit, max_step=0.05 * 2 * np.pi / w)
    assert sol.success
    U = 1.0 + a * np.sin(w * t_fit)
    Y = m.h(sol.y.T, U[:, None], th) - lin.y
    basis = np.column_stack([np.sin(w * t_fit), np.cos(w * t_fit), np.ones_like(t_fit)])
    coef, *_ = np.linalg.lstsq(basis, Y, rcond=None)
    measured = (coef[0] + 1j * coef[1]) / a          # y = Im(G e^{jwt}) a
    G = np.array([signal.freqresp(signal.StateSpace(lin.A, lin.B[:, [0]], lin.C[[i]],
                                                    lin.D[[i]][:, [0]]), w=[w])[1][0]
                  for i in range(len(lin.outputs))])
    np.testing.assert_allclose(measured, G, rtol=5e-5)
    np.testing.assert_allclose(lin.freqresp([w])[0, :, 0], G, rtol=1e-12)


def torricelli_tank() -> BondGraph:
    """One tank of area a fed by Q, drained by a square-root orifice:
    dq/dt = Q - k sqrt(q/a). Equilibrium (hand-derived) q* = a (Q/k)^2,
    where A = -k / (2 a sqrt(q*/a)) = -k^2 / (2 a Q)."""
    g = BondGraph("torricelli_tank", "A tank with a square-root orifice.")
    Q = g.input("Q", "m^3/s", 0.0, "inflow")
    a = g.param("a", 0.5, "m^2")
    k = g.param("k", 0.02, "m^2.5/s")
    t = g.zero("tank")                      # the level as effort: q / a [m]
    g.connect(g.Sf("inflow", Q), t)
    g.connect(t, g.C("C_tank", a))
    g.connect(t, g.R("orifice", flow=lambda h: k * h ** 0.5))
    g.sensor("h", t.e, unit="m")
    return g


def test_a_law_on_its_domains_boundary_is_said(tmp_path, capsys):
    """At an empty tank (the default inflow 0) the orifice's sqrt sits on
    its boundary: its slope is infinite there, the continued law's 0, and a
    pole at 0 would be reported as the tank's; the linearisation says so. At
    an inflow the equilibrium is inside the domain: A is the hand-derived
    -k^2 / (2 a Q), no warning."""
    from bondgraph.cli.main import main

    empty = linearize(torricelli_tank())
    assert np.allclose(empty.x, 0.0) and empty.A[0, 0] == 0.0
    w, = empty.warnings
    assert "(q_C_tank/a)**0.5 sits on the boundary of its domain" in w and "q_C_tank/a > 0" in w
    Q, a, k = 1e-3, 0.5, 0.02
    lin = linearize(torricelli_tank(), {"Q": Q})
    assert lin.warnings == ()
    assert lin.x[0] == pytest.approx(a * (Q / k) ** 2, rel=1e-9)
    assert lin.A[0, 0] == pytest.approx(-k ** 2 / (2 * a * Q), rel=1e-7)
    monkey = tmp_path / "tank_mod.py"
    monkey.write_text("import sys\nsys.path.insert(0, %r)\n"
                      "from test_linearize import torricelli_tank\n" % str(Path(__file__).parent))
    assert main(["linearize", f"{monkey}:torricelli_tank", "-o",
                 str(tmp_path / "t.npz"), "--no-plot"]) == 0
    err = capsys.readouterr().err
    assert "warning: (q_C_tank/a)**0.5 sits on the boundary" in err


def test_to_control_and_no_equilibrium():
    control = pytest.importorskip("control")
    lin = linearize("rlc_circuit", {"V": 2.0})
    sys = lin.to_control()
    np.testing.assert_allclose(np.sort_complex(control.poles(sys)), np.sort_complex(lin.poles()),
                               rtol=1e-12)
    # R = 10, L = 0.1, C = 1e-3: s^2 + (R/L) s + 1/(LC)
    np.testing.assert_allclose(np.sort_complex(lin.poles()),
                               np.sort_complex(np.roots([1, 100, 1e4])), rtol=1e-12)
    g = BondGraph("free_mass", "A mass pushed by a constant force.")
    F = g.input("F", "N", 1.0)
    j = g.one("v", domain="translation")
    g.connect(g.Se("force", F), j)
    g.connect(j, g.I("mass", g.param("m", 2.0, "kg")))
    with pytest.raises(ExportError, match="no equilibrium.*p_mass"):
        linearize(g, {"F": 1.0})
    with pytest.raises(ExportError, match="neither a state nor an input"):
        linearize("rlc_circuit", {"Vx": 1.0})


def test_cli_linearize_writes_npz_poles_and_bode(tmp_path, capsys):
    """`bondgraph linearize hydraulic_tanks --at Q=1e-4`: the equilibrium and
    A of the hand-derived equations (hydraulic_tanks' docstring)."""
    from bondgraph.cli.main import main

    out = tmp_path / "ht.npz"
    assert main(["linearize", "hydraulic_tanks", "--at", "Q=1e-4", "-o", str(out)]) == 0
    text = capsys.readouterr().out
    assert "poles [1/s]" in text and "equilibrium" in text
    d = np.load(out)
    C1, C2, R12, R2 = 1e-4, 2e-4, 1e5, 1e5
    A = [[-1 / (R12 * C1), 1 / (R12 * C2)], [1 / (R12 * C1), -(1 / R12 + 1 / R2) / C2]]
    np.testing.assert_allclose(d["A"], A, rtol=1e-12)
    np.testing.assert_allclose(d["B"], [[1.0], [0.0]])
    np.testing.assert_allclose(d["x"], [1e-4 * C1 * (R12 + R2), 1e-4 * R2 * C2], rtol=1e-10)
    assert list(d["states"]) == ["q_tank1_C", "q_tank2_C"] and bool(d["equilibrium"])
    assert (tmp_path / "ht.png").stat().st_size > 5000
    for p in np.linalg.eigvals(A):
        assert f"{p.real:.6g}" in text
    # a name without the suffix gets it: np.load and the plot beside it expect it
    assert main(["linearize", "hydraulic_tanks", "--at", "Q=1e-4", "-o",
                 str(tmp_path / "lin1")]) == 0
    assert f"wrote {tmp_path / 'lin1.npz'}" in capsys.readouterr().out
    np.testing.assert_allclose(np.load(tmp_path / "lin1.npz")["A"], A, rtol=1e-12)
    assert not (tmp_path / "lin1").exists() and (tmp_path / "lin1.png").exists()


def test_cli_linearize_at_an_estimates_values(tmp_path, capsys):
    """``--params result.json`` of ``bondgraph estimate``: its estimated noise
    levels and initial states (noise.<output>, x0.<state>) are not the
    graph's parameters and are left out (they were refused: "no
    parameter(s) noise.p1"); A is the hand-derived one at the estimate."""
    import json

    from bondgraph.cli.main import main

    res = tmp_path / "result.json"
    res.write_text(json.dumps({"params": ["Rh12", "noise.p1", "x0.q_tank1_C"],
                               "estimates": [2e5, 0.01, 1e-3], "fixed": {"Rh2": 1e5}}))
    out = tmp_path / "ht.npz"
    assert main(["linearize", "hydraulic_tanks", "--at", "Q=1e-4", "--params", str(res),
                 "-o", str(out), "--no-plot"]) == 0
    C1, C2, R12, R2 = 1e-4, 2e-4, 2e5, 1e5
    A = [[-1 / (R12 * C1), 1 / (R12 * C2)], [1 / (R12 * C1), -(1 / R12 + 1 / R2) / C2]]
    np.testing.assert_allclose(np.load(out)["A"], A, rtol=1e-12)


def damped_mass() -> BondGraph:
    """A mass m on a damper c pushed by F, its position q measured: at a
    constant F = 0 every position at rest is an equilibrium. Hand-derived
    (p = m v): dp/dt = F − c p/m, dq/dt = p/m, so A = [[−c/m, 0], [1/m, 0]],
    singular, its null direction q."""
    g = BondGraph("damped_mass", "A mass on a damper, pushed; its position measured.")
    F = g.input("F", "N", 0.0)
    m, c = g.param("m", 2.0, "kg"), g.param("c", 3.0, "N*s/m")
    v = g.one("v", domain="translation")
    g.connect(g.Se("push", F), v)
    g.connect(v, g.I("mass", m))
    g.connect(v, g.R("damper", c))
    q = g.displacement(v, name="q", unit="m")
    g.sensor("x", q, unit="m")
    return g


def test_an_equilibrium_that_is_not_isolated_is_said():
    """The solved equilibrium of a damped mass lies on a continuum (any
    position at rest): A is the hand-derived singular one and the warning
    names the position; where the user gave the position the search ended
    there and nothing is said; an isolated equilibrium (the RLC circuit)
    says nothing either."""
    lin = linearize(damped_mass())
    np.testing.assert_allclose(lin.A, [[-1.5, 0.0], [0.5, 0.0]], rtol=1e-12)
    w, = lin.warnings
    assert "the equilibrium is not isolated" in w and "along q are equilibria" in w
    at = linearize(damped_mass(), {"q": 0.25})
    assert at.x.tolist() == [0.0, 0.25] and at.warnings == ()
    assert linearize("rlc_circuit", {"V": 2.0}).warnings == ()

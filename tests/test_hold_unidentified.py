"""A parameter declared without a box is a known value: where the record
cannot tell it from the parameters it scales, `bondgraph loop` without
--params holds it at its declared value (LoopSettings.hold_unidentified).

The graph: a force source F = k_u·u (an actuator constant k_u, declared
without a box) on a mass m and a viscous damper c (declared with boxes),
the velocity measured. m v̇ = k_u u − c v is invariant under
(k_u, m, c) -> s·(k_u, m, c): the record identifies m/k_u and c/k_u only.
The reference is the truth the record was simulated from (scipy's
solve_ivp, a continuous multisine force).
"""

import json

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from bondgraph import BondGraph
from bondgraph.cli.main import main
from bondgraph.diagnose.settings import LoopSettings
from bondgraph.errors import OptionError

TRUTH = {"k_u": 2.0, "m": 3.0, "c": 1.5}

GRAPH = '''
from bondgraph import BondGraph


def drive():
    g = BondGraph("drive", "mass and damper behind an actuator constant")
    u = g.input("u", "V", 0.0, "command")
    k_u = g.param("k_u", 2.0, "N/V", None, "actuator constant (datasheet)")
    m = g.param("m", 2.0, "kg", (0.1, 100.0), "mass")
    c = g.param("c", 1.0, "N*s/m", (0.01, 100.0), "damping")
    v = g.one("v")
    g.connect(g.Se("act", k_u * u), v)
    g.connect(v, g.I("mass", m))
    g.connect(v, g.R("damper", c))
    g.sensor("vel", v.f, unit="m/s")
    return g
'''


def _record(path, n=1500, dt=0.02, seed=0, unit="V"):
    t = np.arange(n) * dt
    freqs = np.array([0.05, 0.13, 0.31, 0.7, 1.3])

    def u(tt):
        return np.sum(np.sin(2 * np.pi * freqs * tt + np.arange(5)), axis=-1)

    def f(tt, x):
        return [(TRUTH["k_u"] * u(tt) - TRUTH["c"] * x[0]) / TRUTH["m"]]

    sol = solve_ivp(f, (0.0, t[-1]), [0.0], t_eval=t, rtol=1e-10, atol=1e-12, max_step=dt)
    y = sol.y[0] + 0.01 * np.random.default_rng(seed).standard_normal(n)
    uu = u(t[:, None])
    with open(path, "w") as fh:
        fh.write(f"t [s],u [{unit}],vel [m/s]\n")
        for row in zip(t.tolist(), uu.tolist(), y.tolist()):
            fh.write("%r,%r,%r\n" % row)


def test_a_parameter_without_a_box_is_held_where_the_record_cannot_tell_it(tmp_path,
                                                                             monkeypatch):
    _record(tmp_path / "rec.csv")
    (tmp_path / "drive_user.py").write_text(GRAPH)
    monkeypatch.chdir(tmp_path)
    argv = ["loop", "--model", "drive_user.py:drive", "--data", "rec.csv", "--max-steps", "0",
            "--quiet", "--hold", "linear", "--no-plots"]
    assert main(argv + ["--out", "held"]) == 0
    log = (tmp_path / "held" / "loop.log").read_text()
    assert "k_u was declared without a box (a known value): held at 2" in log
    # --no-plots: the report's text and tables, no PNG and no reference to one
    assert not list((tmp_path / "held").glob("*.png"))
    assert ".png" not in (tmp_path / "held" / "report.md").read_text()
    assert ".png" not in (tmp_path / "held" / "report.html").read_text()
    rep = json.loads((tmp_path / "held" / "report.json").read_text())
    est, std = rep["initial_fit"]["estimates"], rep["initial_fit"]["std"]
    assert "k_u" not in est and rep["settings"]["fixed"] == {"k_u": 2.0}
    assert rep["settings"]["params"][:2] == ["m", "c"]
    # with k_u held at its true value, m and c are the truth within 3
    # Cramér-Rao std (and the ridge is gone)
    for p in ("m", "c"):
        assert abs(est[p] - TRUTH[p]) < 3 * std[p], (p, est[p], std[p])
    assert not {"m", "c"} & set(rep["initial_fit"]["flat"])
    assert any("held at 2" in w for w in rep["warnings"])
    # named in --params, k_u is estimated: the fit stops somewhere on the
    # ridge and says the record does not identify the three apart
    assert main(argv + ["--out", "all", "--params", "k_u,m,c"]) == 0
    rep = json.loads((tmp_path / "all" / "report.json").read_text())
    assert {"k_u", "m", "c"} <= set(rep["initial_fit"]["flat"])
    assert "k_u" in rep["initial_fit"]["estimates"]
    # the identified ratios agree with the held fit's
    e = rep["initial_fit"]["estimates"]
    assert e["m"] / e["k_u"] == pytest.approx(TRUTH["m"] / TRUTH["k_u"], rel=0.01)
    assert e["c"] / e["k_u"] == pytest.approx(TRUTH["c"] / TRUTH["k_u"], rel=0.01)


OVEN = '''
from bondgraph import BondGraph


def oven():
    g = BondGraph("oven", "heating element and wall, losses to the room")
    P = g.input("P", "W", 0.0, "heater power")
    T0 = g.param("T0", 300.0, "K", description="reference temperature")
    ce = g.param("C_e", 800.0, "J/K", (100.0, 5000.0), "element heat capacity")
    cw = g.param("C_w", 2000.0, "J/K", (300.0, 30000.0), "wall heat capacity")
    rew = g.param("R_ew", 0.05, "K/W", (0.005, 0.5), "element to wall")
    rwa = g.param("R_wa", 0.1, "K/W", (0.01, 1.0), "wall to room")
    n1 = g.zero("element", domain="thermal")
    g.connect(g.Sf("heater", P / T0), n1)
    g.connect(n1, g.C("C_element", ce / T0))
    gap = g.one("gap", domain="thermal")
    g.connect(n1, gap)
    g.connect(gap, g.R("R_gap", T0 * rew))
    n2 = g.zero("wall", domain="thermal")
    g.connect(gap, n2)
    g.connect(n2, g.C("C_wall", cw / T0))
    g.connect(n2, g.R("R_loss", T0 * rwa))
    g.sensor("T_e", n1.e, unit="K", noise_std=0.05)
    g.sensor("T_w", n2.e, unit="K", noise_std=0.05)
    return g
'''

OVEN_TRUTH = {"C_e": 800.0, "C_w": 3000.0, "R_ew": 0.04, "R_wa": 0.12}


def _oven_record(path, n=1200, dt=4.0):
    """The oven's own equations (temperature rises, hand-written),
    C_e dT_e/dt = P - (T_e - T_w)/R_ew, C_w dT_w/dt = (T_e - T_w)/R_ew -
    T_w/R_wa, heater steps every 300 s, by solve_ivp."""
    c = OVEN_TRUTH
    t = np.arange(n) * dt
    levels = np.random.default_rng(11).uniform(0.0, 600.0, size=int(t[-1] // 300) + 2)

    def P(s):
        return levels[(np.asarray(s) // 300).astype(int)]

    def f(s, z):
        q = (z[0] - z[1]) / c["R_ew"]
        return [(P(s) - q) / c["C_e"], (q - z[1] / c["R_wa"]) / c["C_w"]]

    sol = solve_ivp(f, (0.0, t[-1]), [0.0, 0.0], t_eval=t, method="LSODA", rtol=1e-9,
                    atol=1e-10, max_step=dt)
    y = sol.y + 0.05 * np.random.default_rng(3).standard_normal(sol.y.shape)
    with open(path, "w") as fh:
        fh.write("t [s],P [W],T_e [K],T_w [K]\n")
        for row in zip(t.tolist(), P(t).tolist(), y[0].tolist(), y[1].tolist()):
            fh.write("%r,%r,%r,%r\n" % row)


def test_a_known_value_the_declared_fit_moves_onto_its_box_is_held(tmp_path, monkeypatch):
    """The oven's reference temperature T0 (declared without a box: a known
    value) scales its entropy states and cancels from the temperatures:
    the record cannot tell it, and only the filter's initial covariance (in
    state units) depends on it, so the declared fit ran it onto the box
    the toolkit set around it (30 K of [30, 3000]), with no Cramér-Rao std.
    It is held at 300 K, and the heat capacities and resistances are the
    truth within 3 Cramér-Rao std."""
    _oven_record(tmp_path / "oven.csv")
    (tmp_path / "oven_user.py").write_text(OVEN)
    monkeypatch.chdir(tmp_path)
    assert main(["loop", "--model", "oven_user.py:oven", "--data", "oven.csv", "--max-steps",
                 "0", "--quiet", "--hold", "zoh", "--out", "held", "--no-plots"]) == 0
    log = (tmp_path / "held" / "loop.log").read_text()
    assert "the declared fit moves T0 to 30, onto the box [30, 3000]" in log
    assert "T0 was declared without a box (a known value): held at 300" in log
    rep = json.loads((tmp_path / "held" / "report.json").read_text())
    est, std = rep["initial_fit"]["estimates"], rep["initial_fit"]["std"]
    assert "T0" not in est and rep["settings"]["fixed"] == {"T0": 300.0}
    for p, v in OVEN_TRUTH.items():
        assert abs(est[p] - v) < 3 * std[p], (p, est[p], std[p])
    # holding it costs a few nats (the initial covariance's), no disagreement
    held = next(w for w in rep["warnings"] if "held at 300" in w)
    assert "(the declared fit's NLL" in held and "disagrees" not in held


MASS = '''
from bondgraph import BondGraph


def mass():
    g = BondGraph("mass", "a mass on a damper, pushed")
    u = g.input("u", "N", 0.0, "force")
    m = g.param("m", 0.1, "kg", None, "mass (a wrong datasheet value)")
    c = g.param("c", 1.0, "N*s/m", (0.01, 100.0), "damping")
    v = g.one("v")
    g.connect(g.Se("push", u), v)
    g.connect(v, g.I("body", m))
    g.connect(v, g.R("damper", c))
    g.sensor("vel", v.f, unit="m/s")
    return g
'''


def test_a_known_value_the_record_contradicts_stays_estimated_and_said_so(tmp_path,
                                                                          monkeypatch):
    """A mass declared without a box at 0.1 kg where the record's is 1.5 kg
    (the drive's record, 3 v̇ = 2u − 1.5 v, read as a force u [N]: m 1.5,
    c 0.75): the declared fit runs m onto its box's top (1 kg). Held at
    0.1 kg the declared fit would lose far more than χ²₁(1e-6)/2 nats (its
    NLL −112 -> 1333, its held-out error 1.63): the record disagrees with the
    declared value, so m stays estimated (on its box) and the log and the
    report's warnings say so."""
    _record(tmp_path / "rec.csv", unit="N")
    (tmp_path / "mass_user.py").write_text(MASS)
    monkeypatch.chdir(tmp_path)
    assert main(["loop", "--model", "mass_user.py:mass", "--data", "rec.csv", "--max-steps", "0",
                 "--quiet", "--hold", "linear", "--out", "held", "--no-plots"]) == 0
    log = (tmp_path / "held" / "loop.log").read_text()
    line = next(ln for ln in log.splitlines() if "held at 0.1" in ln)
    assert "but the declared fit moves it to 1, the end of the box" in line
    before, after = (float(x) for x in
                     line.split("the fit's NLL goes ")[1].split(" (")[0].split(" -> "))
    assert after - before > 11.96
    assert "the record disagrees with that value" in line and "m stays estimated" in line
    rep = json.loads((tmp_path / "held" / "report.json").read_text())
    assert rep["initial_fit"]["estimates"]["m"] == pytest.approx(1.0)
    assert "m" not in rep["settings"]["fixed"]
    assert any("m stays estimated" in w for w in rep["warnings"])


def test_box_declared_and_the_option_is_checked():
    g = BondGraph("g")
    assert g.param("a", 1.0).box_declared is False
    assert g.param("b", 1.0, bounds=(0.5, 2.0)).box_declared is True
    h = g.copy("h")
    assert h.params["a"].box_declared is False and h.params["b"].box_declared is True
    assert g.params["a"].with_name("x.a").box_declared is False
    with pytest.raises(OptionError, match="hold_unidentified"):
        LoopSettings(params=["a"], hold_unidentified=("b",))
    with pytest.raises(OptionError, match="hold_unidentified"):
        LoopSettings(params=["a"], hold_unidentified="a")


def test_the_loop_log_does_not_repeat_a_detail_line_within_a_step():
    from bondgraph.diagnose.runner import _stamped

    out = []
    emit = _stamped(out.append, 0.0)
    flat = "  the record does not identify a, b"
    for m in ("step 1: scored", flat, "  smoothed x0", flat, "ACCEPT e", flat):
        emit(m)
    assert [o.split("] ", 1)[1] for o in out] == [
        "step 1: scored", "  the record does not identify a, b", "  smoothed x0", "ACCEPT e",
        "  the record does not identify a, b"]

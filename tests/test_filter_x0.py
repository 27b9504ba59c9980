"""`bondgraph estimate` on a record that does not start from rest, with a
model that declares no process noise
(:func:`bondgraph.cli.estimate.filter_initial_states`).

A user's hydraulic circuit: a pump's multisine flow into a hose whose
compliance hardens (p1 = q1/C1 + k3·q1³, the cubic half the pressure at the
peaks), a linear orifice into a chamber (p2 = q2/C2), a leak to tank; both
pressures measured at 100 Hz with 0.5 bar of noise; the truth integrated by
scipy's LSODA, the record cut 10 s in, under pressure, with no initial
state. Started from the model's X0 (zero) with the state's whole scale as
prior std, the filter read the sensor noise as 77 kPa (NLL 124713, the
robust std 7 to 28 times the Cramér-Rao std); with the two initial states
estimated by default, 50.3 kPa (NLL 122407) and the declared parameters
within 3 std.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from scipy.integrate import solve_ivp

from bondgraph import BondGraph
from bondgraph.cli.main import main

C1, C2, R12, R2, K3, NOISE = 6.67e-13, 1.33e-12, 1.5e11, 3e11, 7e21, 5e4


def hydraulic() -> BondGraph:
    """The user's graph with the hose's cubic law declared."""
    g = BondGraph("hyd_cubic", "pump into a hardening hose, an orifice, a chamber, a leak")
    Q = g.input("Q", "m**3/s", 0.0, "pump flow")
    c1 = g.param("C1", 6e-13, "m**3/Pa", (1e-14, 1e-11), "hose compliance")
    c2 = g.param("C2", 1.2e-12, "m**3/Pa", (1e-14, 1e-11), "chamber compliance")
    r12 = g.param("R12", 1e11, "Pa*s/m**3", (1e9, 1e13), "orifice resistance")
    r2 = g.param("R2", 2e11, "Pa*s/m**3", (1e9, 1e13), "leak resistance")
    k3 = g.param("k3", 5e21, "Pa/m**9", (1e20, 1e23), "hose hardening")
    hose, ch = g.zero("hose", domain="hydraulic"), g.zero("chamber", domain="hydraulic")
    g.connect(g.Sf("pump", Q), hose)
    g.connect(hose, g.C("hose_volume", effort=lambda q: q / c1 + k3 * q**3))
    o = g.one("orifice_j", domain="hydraulic")
    g.connect(hose, o)
    g.connect(o, g.R("orifice", r12))
    g.connect(o, ch)
    g.connect(ch, g.C("chamber_volume", capacitance=c2))
    g.connect(ch, g.R("leak", r2))
    g.sensor("p1", hose.e, unit="Pa", noise_std=NOISE)
    g.sensor("p2", ch.e, unit="Pa", noise_std=NOISE)
    return g


def write_record(path) -> None:
    rng = np.random.default_rng(1)
    f = np.geomspace(0.05, 5, 12)
    ph = rng.uniform(0, 2 * np.pi, f.size)

    def q(t):
        return 4e-5 + 2.5e-5 * float(np.sum(np.sin(2 * np.pi * f * t + ph))) / np.sqrt(6)

    def rhs(t, x):
        a, b = x[0] / C1 + K3 * x[0] ** 3, x[1] / C2
        return [q(t) - (a - b) / R12, (a - b) / R12 - b / R2]

    t = np.arange(0.0, 40.0, 0.01)
    s = solve_ivp(rhs, (0, t[-1]), [0.0, 0.0], t_eval=t, method="LSODA", rtol=1e-10,
                  atol=1e-18, max_step=0.005)
    assert s.status == 0
    keep = t >= 10.0
    p1 = s.y[0] / C1 + K3 * s.y[0] ** 3 + rng.normal(0, NOISE, t.size)
    p2 = s.y[1] / C2 + rng.normal(0, NOISE, t.size)
    rows = ["t [s],Q [m**3/s],p1 [Pa],p2 [Pa]"] + [
        f"{a:.17g},{q(a):.17g},{b:.17g},{c:.17g}"
        for a, b, c in zip(t[keep], p1[keep], p2[keep])]
    path.write_text("\n".join(rows) + "\n")


def test_a_record_under_way_gets_its_initial_states_estimated(tmp_path, monkeypatch, capsys):
    """The initial states are estimated without being asked (the line says
    so), the noise levels land on the truth's 50 kPa and C1, C2, R12, R2
    within 3 Cramér-Rao std."""
    monkeypatch.chdir(tmp_path)
    (tmp_path / "hyd.py").write_text(
        "from test_filter_x0 import hydraulic as hyd  # noqa: F401\n")
    monkeypatch.syspath_prepend(str(Path(__file__).parent))
    write_record(tmp_path / "rec.csv")
    code = main(["estimate", "--model", "hyd.py:hyd", "--data", "rec.csv", "--no-plots",
                 "--out", "est", "--quiet"])
    assert code == 0
    err = capsys.readouterr().err
    assert "the record gives no initial value of q_hose_volume, q_chamber_volume" in err
    res = json.loads((tmp_path / "est" / "result.json").read_text())
    est, std = (dict(zip(res["params"], res[k])) for k in ("estimates", "std"))
    assert {"x0.q_hose_volume", "x0.q_chamber_volume"} <= set(est)
    for o in ("p1", "p2"):
        assert abs(est[f"noise.{o}"] - NOISE) < 3 * std[f"noise.{o}"], (o, est[f"noise.{o}"])
    for n, true in {"C1": C1, "C2": C2, "R12": R12, "R2": R2}.items():
        assert abs(est[n] - true) < 3 * std[n], (n, est[n], std[n])

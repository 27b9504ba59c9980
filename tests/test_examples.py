"""The short examples in examples/ run as a user runs them (a fresh process in
an empty folder), and print what their docstrings promise. The long ones
(estimate_emps.py: the EMPS record and a PSO; silverbox_user.py: a whole loop
on Silverbox) are not run here: tests/test_loop.py runs their cases;
emps_user.py's graph and record writer are checked, its loop is not run."""

import re
import subprocess
import sys
from pathlib import Path

import pytest

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"


def _run(name, cwd):
    r = subprocess.run([sys.executable, str(EXAMPLES / name)], cwd=cwd, capture_output=True,
                       text=True, timeout=600)
    assert r.returncode == 0, r.stderr
    return r.stdout


def test_quickstart_reaches_the_hand_derived_steady_state(tmp_path):
    out = _run("quickstart.py", tmp_path)
    got, steady = map(float, re.search(r"speed at 3 s: ([\d.]+) rad/s \(steady state ([\d.]+)",
                                       out).groups())
    assert got == pytest.approx(steady, rel=1e-3)
    assert (tmp_path / "quickstart_out" / "quickstart_motor.py").exists()


def test_track_user_graph_finds_the_damping_step(tmp_path):
    """The example doubles the damping (1.5 -> 3.0) at 30 s."""
    out = _run("track_user_graph.py", tmp_path)
    m = re.search(r"change of c at t = ([\d.]+) s \(alarm ([\d.]+) s\): ([\d.]+) ± ([\d.]+) -> "
                  r"([\d.]+) ± ([\d.]+)", out)
    t, alarm, before, sb, after, sa = map(float, m.groups())
    assert 30.0 <= t <= 31.0 and t <= alarm <= 35.0
    assert abs(before - 1.5) <= 3 * sb + 1e-3 and abs(after - 3.0) <= 3 * sa + 1e-3
    # the streaming tracker raises its alarm on-line at the batch tracker's alarm sample,
    # for the same change time, once, and ends at the batch's re-estimate
    online = re.findall(r"on-line at t = ([\d.]+) s: c changed at ([\d.]+) s", out)
    assert [tuple(map(float, o)) for o in online] == [(alarm, t)]
    end, = map(float, re.search(r"streaming at the end: c = ([\d.]+)", out).groups())
    assert end == pytest.approx(after, abs=2e-4)


def test_emps_user_graph_is_the_hand_derived_mass_on_viscous_friction(tmp_path):
    """examples/emps_user.py (its loop is a 13-minute run, not run here):
    the graph gives dp/dt = gtau·vir − Fv p/M, dq/dt = p/M, qm = q at
    random points, and its CSV writer gives the estimation run's 24 841
    samples (skipped without the data folder)."""
    import importlib.util

    import numpy as np

    from bondgraph.numerics.model import Model

    spec = importlib.util.spec_from_file_location("emps_user", EXAMPLES / "emps_user.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    m = Model.from_graph(mod.emps_user())
    assert m.states == ["p_mass", "q"] and m.inputs == ["vir"] and m.outputs == ["qm"]
    rng = np.random.default_rng(1)
    x, u = rng.normal(size=(5, 2)), rng.normal(size=(5, 1))
    th = np.tile(m.theta0, (5, 1))
    th[:, m.param_index("M")] = rng.uniform(50, 150, 5)
    th[:, m.param_index("Fv")] = rng.uniform(100, 300, 5)
    gt, M, Fv = (th[:, m.param_index(n)] for n in ("gtau", "M", "Fv"))
    np.testing.assert_allclose(m.f(x, u, th)[:, 0], gt * u[:, 0] - Fv * x[:, 0] / M, rtol=1e-12)
    np.testing.assert_allclose(m.f(x, u, th)[:, 1], x[:, 0] / M, rtol=1e-12)
    np.testing.assert_allclose(m.h(x, u, th)[:, 0], x[:, 1], rtol=1e-12)
    # --graph screw: rotor, screw (lead r per radian) and load, rigidly: the
    # rotor's inertia reflected into the load, dp/dt = (gtau·vir − Fv p/M) /
    # (1 + Jm/(M r²)), one momentum state
    s = Model.from_graph(mod.emps_screw())
    assert s.states == ["p_load", "q"] and s.inputs == ["vir"] and s.outputs == ["qm"]
    th = np.tile(s.theta0, (5, 1))
    th[:, s.param_index("Jm")] = rng.uniform(1e-5, 1e-3, 5)
    th[:, s.param_index("M")] = rng.uniform(50, 150, 5)
    gt, Jm, r, M, Fv = (th[:, s.param_index(n)] for n in ("gtau", "Jm", "r", "M", "Fv"))
    np.testing.assert_allclose(s.f(x, u, th)[:, 0],
                               (gt * u[:, 0] - Fv * x[:, 0] / M) / (1 + Jm / (M * r**2)),
                               rtol=1e-12)
    np.testing.assert_allclose(s.f(x, u, th)[:, 1], x[:, 0] / M, rtol=1e-12)
    # --graph closed: the reference qg is the input, the PD controller
    # ν = kp·kv·(qg − q) − kv·p/M a modulated source gtau·ν that reads the
    # states, ν measured beside q
    c = Model.from_graph(mod.emps_closed())
    assert c.states == ["p_mass", "q"] and c.inputs == ["qg"] and c.outputs == ["qm", "vir"]
    th = np.tile(c.theta0, (5, 1))
    th[:, c.param_index("M")] = rng.uniform(50, 150, 5)
    th[:, c.param_index("Fv")] = rng.uniform(100, 300, 5)
    th[:, c.param_index("kv")] = rng.uniform(200, 300, 5)
    gt, kp, kv, M, Fv = (th[:, c.param_index(n)] for n in ("gtau", "kp", "kv", "M", "Fv"))
    nu = kp * kv * (u[:, 0] - x[:, 1]) - kv * x[:, 0] / M
    np.testing.assert_allclose(c.f(x, u, th)[:, 0], gt * nu - Fv * x[:, 0] / M, rtol=1e-12)
    np.testing.assert_allclose(c.f(x, u, th)[:, 1], x[:, 0] / M, rtol=1e-12)
    np.testing.assert_allclose(c.h(x, u, th), np.column_stack([x[:, 1], nu]), rtol=1e-12)
    from bondgraph.data.datasets import default_data_dir, find_local
    root = default_data_dir()
    if root is None or find_local("emps", "emps_estimation.csv", root) is None:
        pytest.skip("the EMPS files are not in the data folder (../shared/data or BONDGRAPH_DATA)")
    csv = mod.write_csv(tmp_path / "emps.csv")
    data = np.loadtxt(csv, delimiter=",", skiprows=1)
    assert data.shape == (24841, 3)
    assert open(csv).readline() == "t [s],qm [m],vir [V]\n"
    # --protocol's force-pulse run: the same columns, its own drive command
    pulses = np.loadtxt(mod.write_csv(tmp_path / "pulses.csv", which="validation"),
                        delimiter=",", skiprows=1)
    assert pulses.shape == (24841, 3) and not np.allclose(pulses[:, 2], data[:, 2])
    # the closed-loop graph's record: the reference first, the same qm and vir
    ref = mod.write_csv(tmp_path / "closed.csv", reference=True)
    assert open(ref).readline() == "t [s],qg [m],qm [m],vir [V]\n"
    closed = np.loadtxt(ref, delimiter=",", skiprows=1)
    np.testing.assert_array_equal(closed[:, [0, 2, 3]], data)


def test_ced_user_graph_is_the_hand_derived_motor_belt_pulley(tmp_path):
    """examples/ced_user.py (its loop and comparison run about a minute, not
    run here): the graph gives, with ω_m = p_Jm/J_m, ω_p = p_Jp/J_p and the
    armature current (u − k_m ω_m)/R_a, dp_Jm/dt = k_m (u − k_m ω_m)/R_a −
    b_m ω_m − k_b q, dq/dt = ω_m − ω_p, dp_Jp/dt = k_b q − b_p ω_p and
    z = ω_p at random points; its CSV writer and its eq. (9) reference
    reproduce the data README's table (0.166, 1.14, 0.246 on the three PRBS
    runs; skipped without the data folder)."""
    import importlib.util

    import numpy as np

    from bondgraph.numerics.model import Model

    spec = importlib.util.spec_from_file_location("ced_user", EXAMPLES / "ced_user.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    m = Model.from_graph(mod.ced_user())
    assert sorted(m.states) == ["p_Jm", "p_Jp", "q_kb"] and m.inputs == ["u"]
    assert m.outputs == ["z"]
    rng = np.random.default_rng(2)
    x, u = rng.normal(size=(6, 3)), rng.normal(size=(6, 1))
    th = np.tile(m.theta0, (6, 1))
    for name, lo, hi in (("Ra", 0.5, 2), ("km", 0.1, 2), ("Jm", 0.01, 1), ("bm", 0.01, 1),
                         ("kb", 1, 50), ("Jp", 0.01, 1), ("bp", 0.01, 1)):
        th[:, m.param_index(name)] = rng.uniform(lo, hi, 6)
    P = {n: th[:, m.param_index(n)] for n in ("Ra", "km", "Jm", "bm", "kb", "Jp", "bp")}
    s = {n: x[:, m.states.index(n)] for n in m.states}
    wm, wp = s["p_Jm"] / P["Jm"], s["p_Jp"] / P["Jp"]
    want = {"p_Jm": P["km"] * (u[:, 0] - P["km"] * wm) / P["Ra"] - P["bm"] * wm
            - P["kb"] * s["q_kb"],
            "q_kb": wm - wp, "p_Jp": P["kb"] * s["q_kb"] - P["bp"] * wp}
    f = m.f(x, u, th)
    for n, w in want.items():
        np.testing.assert_allclose(f[:, m.states.index(n)], w, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(m.h(x, u, th)[:, 0], wp, rtol=1e-12)
    # --graph abs: the same state equations, the sign-blind counter |ω_p|
    a = Model.from_graph(mod.ced_abs())
    assert a.states == m.states and a.params == m.params
    np.testing.assert_allclose(a.f(x, u, th), f, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(a.h(x, u, th)[:, 0], np.abs(wp), rtol=1e-12)
    from bondgraph.data.datasets import default_data_dir, find_local
    root = default_data_dir()
    if root is None or find_local("ced", "DATAPRBS.csv", root) is None:
        pytest.skip("the CED files are not in the data folder (../shared/data or BONDGRAPH_DATA)")
    csvs = mod.write_csvs(tmp_path)
    data = np.loadtxt(csvs["prbs1"], delimiter=",", skiprows=1)
    assert data.shape == (500, 3) and open(csvs["prbs1"]).readline() == "t [s],u [V],z\n"
    assert np.allclose(np.diff(data[:, 0]), 0.02) and set(np.unique(data[:, 1])) == {-1.0, 1.0}
    got = [mod.eq9_rms(csvs[k]) for k in ("prbs1", "prbs2", "prbs3")]
    np.testing.assert_allclose(got, [0.166, 1.14, 0.246], atol=0.006)

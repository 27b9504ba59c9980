"""A user's own graph of the CED belt drive on the real record u1 (issue 26:
the loop on a user's graph and a real record; Wigren & Schoukens 2017).

The user declares the drive from the data README alone (armature R-L, motor
gyrator, motor damping, a belt compliance, the pulley's inertia, damping and
spring, and a speed sensor of unknown gain) and runs ``bondgraph loop``
without numerics options. The record's sensor is a sign-blind pulse counter
(|speed|), which the graph does not declare. With one sensor whose gain is
estimated and the pulley spring on the bottom of its box, the mechanical
impedances and the sensor gain scale together: the rectifying sensor's
refit slides along that ridge. It used to crawl for 120 iterations and be
refused as "not converged"; Fisher scoring now stops on the ridge once it
has converged in every direction the record identifies, names the
quantities along it, and the loop accepts the rectification.

References: the published CED models (eq. 9 with |.| of the README:
RMS 0.166 over u1, about 0.11 NRMSE); this graph reaches less (it is not
eq. 9), the figures below are this graph's, before and after, on the
held-out last quarter of u1.
"""

import json
from pathlib import Path

import numpy as np
import pytest

from bondgraph.cli.main import main

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
pytestmark = pytest.mark.skipif(not (DATA / "ced").exists(),
                                reason=f"real data folder {DATA} is absent (third-party "
                                       f"files, not copied into the project)")

GRAPH = '''
from bondgraph import BondGraph


def ced_user():
    g = BondGraph("ced_user", "CED drive: motor, belt, spring-held pulley")
    u = g.input("u", "V", 0.0, "motor voltage")
    Ra = g.param("R_a", 1.0, "ohm", (0.01, 100.0), "armature resistance")
    La = g.param("L_a", 0.05, "H", (1e-3, 1.0), "armature inductance")
    km = g.param("k_m", 0.1, "N*m/A", (0.001, 1.0), "torque constant")
    bm = g.param("b_m", 0.05, "N*m*s/rad", (1e-4, 1.0), "motor damping")
    kb = g.param("k_b", 1.0, "N*m/rad", (0.01, 100.0), "belt stiffness")
    Jp = g.param("J_p", 1e-3, "kg*m^2", (1e-5, 1e-1), "pulley inertia")
    bp = g.param("b_p", 1e-3, "N*m*s/rad", (1e-6, 1.0), "pulley damping")
    ks = g.param("k_s", 0.5, "N*m/rad", (0.001, 100.0), "pulley spring")
    ky = g.param("k_y", 1.0, "", (0.01, 100.0), "sensor scale")
    ji = g.one("i", domain="electrical")
    g.connect(g.Se("drive", u), ji)
    g.connect(ji, g.R("R_a", Ra))
    g.connect(ji, g.I("L_a", La))
    gy = g.GY("motor", km)
    g.connect(ji, gy.p1)
    jm = g.one("w_m", domain="rotation")
    g.connect(gy.p2, jm)
    g.connect(jm, g.R("b_m", bm))
    belt = g.zero("belt", domain="rotation")
    g.connect(jm, belt)
    g.connect(belt, g.C("belt_C", stiffness=kb))
    jp = g.one("w_p", domain="rotation")
    g.connect(belt, jp)
    g.connect(jp, g.I("J_p", Jp))
    g.connect(jp, g.R("b_p", bp))
    g.connect(jp, g.C("spring", stiffness=ks))
    g.sensor("z", ky * jp.f, unit="", description="pulley speed (pulse counter)")
    return g
'''


def test_the_rectifying_sensor_is_accepted_on_a_flat_ridge(tmp_path):
    from bondgraph.data.datasets import ced

    rec = ced("prbs_1", data_dir=DATA)
    np.savetxt(tmp_path / "u1.csv", np.column_stack([rec.t, rec["u"], rec["z"]]),
               delimiter=",", header="t,u,z", comments="", fmt="%.10g")
    (tmp_path / "ced_user.py").write_text(GRAPH)
    out = tmp_path / "out"
    code = main(["loop", "--model", f"{tmp_path / 'ced_user.py'}:ced_user",
                 "--data", str(tmp_path / "u1.csv"), "--max-steps", "1", "--no-structural",
                 "--out", str(out), "--quiet", "--no-plots"])
    assert code == 0
    rep = json.loads((out / "report.json").read_text())
    (s,) = rep["steps"]
    assert (s["effect"], s["attached_to"]) == ("sensor_rectification", "z")
    # the held-out last quarter: before, the user's linear graph (1.18);
    # after, |k_y·ω_p| (0.65; the estimation part 0.97 -> 0.29)
    assert s["validated"] and s["error_before"] == pytest.approx(1.182, abs=0.03)
    assert s["error_after"] < 0.6 * s["error_before"]
    assert s["estimation_error_after"] < 0.4 * s["estimation_error_before"]
    assert s["lr"] > 800
    # the ridge: the pulley side's impedances move together, and say so
    flat = set(rep["final_fit"]["flat"])
    assert {"b_m", "k_b", "J_p"} <= flat
    assert "does not identify" in (out / "report.md").read_text()


def _user_csv(path: Path) -> None:
    """The user's CSV: the run u1 of the data set's CSV, its text as it is
    (six digits), a time column at Ts = 20 ms."""
    import csv

    with open(DATA / "ced" / "DATAPRBS.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    lines = ["t [s],u [V],z"] + [f"{k * 0.02:.2f},{r['u1']},{r['z1']}" for k, r in enumerate(rows)]
    path.write_text("\n".join(lines) + "\n")


GRAPH_NO_SPRING = '''
from bondgraph import BondGraph


def ced_belt():
    g = BondGraph("ced_belt", "two DC motors drive a pulley through a belt")
    u = g.input("u", "V", 0.0, "sum of the motor voltages")
    R = g.param("R", 1.0, "ohm", (0.01, 100.0), "armature resistance")
    L = g.param("L", 0.05, "H", (1e-3, 1.0), "armature inductance")
    km = g.param("km", 0.1, "N*m/A", (1e-3, 10.0), "torque constant")
    kb = g.param("kb", 0.6, "N*m/rad", (1e-3, 100.0), "belt + spring stiffness")
    J = g.param("J", 1e-3, "kg*m^2", (1e-5, 1.0), "pulley inertia")
    b = g.param("b", 1e-3, "N*m*s/rad", (1e-6, 1.0), "pulley damping")
    ks = g.param("ks", 1.0, "", (0.01, 100.0), "counter scale")
    bm = g.param("bm", 0.05, "N*m*s/rad", (1e-4, 10.0), "motor damping")
    i = g.one("i", domain="electrical")
    g.connect(g.Se("drive", u), i)
    g.connect(i, g.R("Ra", R))
    g.connect(i, g.I("La", L))
    gy = g.GY("motor", km)
    g.connect(i, gy.p1)
    wm = g.one("wm", domain="rotation")
    g.connect(gy.p2, wm)
    g.connect(wm, g.R("motor_friction", bm))
    belt = g.zero("belt", domain="rotation")
    g.connect(wm, belt)
    g.connect(belt, g.C("belt_c", stiffness=kb))
    wp = g.one("wp", domain="rotation")
    g.connect(belt, wp)
    g.connect(wp, g.I("pulley", J))
    g.connect(wp, g.R("friction", b))
    g.sensor("z", ks * wp.f, unit="", description="pulley speed (counter)")
    return g
'''


@pytest.mark.long      # about 20 s (40-70 s while its refit crawled to L-BFGS-B); CI budget
def test_a_second_users_graph_finds_the_rectification(tmp_path):
    """Another user's graph of the same drive (the belt's compliance and the
    spring as one, no pulley spring to ground, other starts, boxes and
    parameter order: the swarm's draws follow the order), run with no
    options but the step limit. Its linear fit is worse than the record's
    mean (free-run NRMSE 1.01), so the rectifying sensor's score at that
    fit is nothing: the output-error screen must find the basin. One
    60-particle swarm in six misses it (here the default seed: free-run RMS
    0.740, against 0.208 with the basin), so independent swarms run until
    two agree; without that the step's best was a sensor offset (LR 51).

    The rectification's refit then crawls along the five unidentified
    combinations (3 % of its scoring step for 120 iterations, LR 946): it
    was refused as not comparable and the step accepted a weaker effect
    (38th session). L-BFGS-B from where the scoring stopped
    (:func:`bondgraph.diagnose.confirm.quasi_newton`) let the scoring
    converge, and the rectification was accepted: held-out NRMSE 1.38 ->
    0.545. Since the scoring's later changes (the staged line search,
    63rd session; the trust-region damping, 65th) the refit converges by
    itself, without the handoff (65th session: 35 iterations, LR 946.4,
    the flat combinations named; held out 1.376 -> 0.365, estimation
    record 1.01 -> 0.291). Reference: eq. (9) of the report with |.| gives RMS
    0.166 over u1 (NRMSE 0.11)."""
    _user_csv(tmp_path / "u1.csv")
    (tmp_path / "ced_belt.py").write_text(GRAPH_NO_SPRING)
    out = tmp_path / "out"
    code = main(["loop", "--model", f"{tmp_path / 'ced_belt.py'}:ced_belt",
                 "--data", str(tmp_path / "u1.csv"), "--max-steps", "1",
                 "--out", str(out), "--quiet", "--no-plots"])
    assert code == 0
    rep = json.loads((out / "report.json").read_text())
    first = rep["rankings"][0][0]
    assert first["label"] == "sensor_rectification @ z" and first["statistic"] > 900
    assert first["values"]["lam"] == 1.0
    log = (out / "loop.log").read_text()
    confirmed = [ln for ln in log.splitlines() if "confirmed sensor_rectification @ z: LR" in ln]
    assert confirmed and "(converged," in confirmed[0], confirmed
    (step,) = rep["steps"]
    assert step["effect"] == "sensor_rectification" and step["lr"] > 900
    assert step["error_before"] > 1.3 and step["error_after"] < 0.6
    assert step["estimation_error_before"] > 1.0 and step["estimation_error_after"] < 0.35


GRAPH_KNOWN_INERTIA = '''
from bondgraph import BondGraph


def ced_norm():
    g = BondGraph("ced_norm", "motor inertia, belt, pulley; the motor inertia normalises")
    u = g.input("u", "V", 0.0, "sum of the motor voltages")
    km = g.param("km", 10.0, "N*m/V", (0.1, 1000.0), "motor torque constant")
    Jm = g.param("Jm", 1.0, "kg*m^2", None, "motor inertia (normalises)")
    bm = g.param("bm", 5.0, "N*m*s", (0.01, 100.0), "motor damping")
    kb = g.param("kb", 200.0, "N*m", (1.0, 1e4), "belt stiffness")
    Jp = g.param("Jp", 1.0, "kg*m^2", (0.01, 100.0), "pulley inertia")
    bp = g.param("bp", 0.5, "N*m*s", (0.001, 100.0), "pulley damping")
    m = g.one("motor")
    g.connect(g.Se("drive", km * u), m)
    g.connect(m, g.I("Jmot", Jm))
    g.connect(m, g.R("Rmot", bm))
    belt = g.zero("belt")
    g.connect(m, belt)
    g.connect(belt, g.C("Cbelt", stiffness=kb))
    p = g.one("pulley")
    g.connect(belt, p)
    J = g.I("Jpul", Jp)
    g.connect(p, J)
    g.connect(p, g.R("Rpul", bp))
    g.sensor("z", J.f, unit="", description="pulley speed (pulse counter)")
    return g
'''


def test_a_known_value_is_held_where_the_fit_shows_the_ridge(tmp_path):
    """The drive's impedances and torque constant scale together (the
    pulley speed stays), so the user declares the motor inertia without a
    box: a known value that fixes the scale. Before the trust-region
    damping of the scoring (sixty-fifth session) the first declared fit
    on the rectified record stopped with bm on its box and no ridge in
    sight, the output-error and global restarts then found the ridge along
    kb and Jm, and Jm ran to the bottom of the box set around it (0.1) and
    stayed there for the whole loop (the restarted fit is checked again
    since). Now the first fit shows the ridge: Jm is held at 1, and the
    restarts run without it."""
    _user_csv(tmp_path / "u1.csv")
    (tmp_path / "ced_norm.py").write_text(GRAPH_KNOWN_INERTIA)
    out = tmp_path / "out"
    code = main(["loop", "--model", f"{tmp_path / 'ced_norm.py'}:ced_norm",
                 "--data", str(tmp_path / "u1.csv"), "--max-steps", "0",
                 "--out", str(out), "--quiet", "--no-plots"])
    assert code == 0
    log = (out / "loop.log").read_text()
    held = log.index("Jm was declared without a box (a known value): held at 1")
    # the restarts ran without Jm
    assert "km, bm, kb, Jp, bp searched globally by output error" in log[held:]
    rep = json.loads((out / "report.json").read_text())
    assert rep["settings"]["fixed"] == {"Jm": 1.0}
    assert "Jm" not in rep["initial_fit"]["estimates"]
    assert any("held at 1" in w for w in rep["warnings"])


def test_estimate_searches_again_where_its_nll_lived_on_the_step(tmp_path, capsys):
    """`bondgraph estimate` on the user's graph and u1 with the initial
    states at the prior (``--estimate-x0 none``: without process noise the
    command estimates them by default, and its fit then does not reach the
    place this test is about): the start's RK4(1) passes its check against
    the profiled noise level, but
    the estimate it reaches sits where a stiff armature mode makes the
    filter's NLL depend on the step (535.65 with RK4(1), 1444.67 with
    RK4(40)): the NLL guard names 2 substeps and the search runs again.
    Its refit lands where the armature mode (R_a/L_a up to 1e5 1/s at 50 Hz)
    puts RK4(2) outside its stability region (and RK4(40) too): the check
    takes ROS2 there (it took RK4(4) before it judged stability; NLL
    551.82). The result passes its own guard (its NLL within 1e-3 of its
    reference's, RK4(40), else ROS2(40) where RK4's is not finite, run
    here independently) and is no worse than the fit the old start choice
    (RK4(2) from the first) reached, 551.96."""
    from bondgraph.cli.common import load_record
    from bondgraph.inference.options import UKFOptions
    from bondgraph.inference.prior import PriorSpec
    from bondgraph.inference.problem import make_problem
    from bondgraph.inference.ukf import ukf_nll
    from bondgraph.cli.common import load_model

    _user_csv(tmp_path / "u1.csv")
    (tmp_path / "ced_user.py").write_text(GRAPH)
    out = tmp_path / "est"
    code = main(["estimate", "--model", f"{tmp_path / 'ced_user.py'}:ced_user",
                 "--data", str(tmp_path / "u1.csv"), "--out", str(out), "--no-plots",
                 "--estimate-x0", "none"])
    assert code == 0
    err = capsys.readouterr().err
    assert "an estimate that lives on the step's error: searching again): rk4(2)" in err, err
    res = json.loads((out / "result.json").read_text())
    assert (res["settings"]["ukf"]["method"], res["settings"]["ukf"]["substeps"]) != ("rk4", 1)
    guard = res["settings"]["discretisation"]["nll_guard"]
    assert guard["ok"], guard
    assert res["nll"] < 551.97
    ukf = res["settings"]["ukf"]
    model = load_model(f"{tmp_path / 'ced_user.py'}:ced_user")
    pb = make_problem(model, load_record(tmp_path / "u1.csv", model),
                      prior=PriorSpec(x0=np.array(res["settings"]["x0"]),
                                      P0=np.array(res["settings"]["P0"])))
    est = dict(zip(res["params"], res["estimates"]))
    th = pb.theta.copy()
    for n, v in est.items():
        if n in model.params:
            th[model.param_index(n)] = v
    R = np.diag([est["noise.z"] ** 2])

    def nll(method):
        return ukf_nll(model, pb.t, pb.u, pb.y, th[None], pb.x0, pb.P0, R=R,
                       options=UKFOptions(method=method, substeps=40, hold=ukf["hold"])).nll[0]

    ref = nll("rk4")
    if guard["reference"] == "ros2(40)":        # RK4 fails even with 40 substeps there
        assert not np.isfinite(ref)
        ref = nll("ros2")
    assert abs(res["nll"] - ref) <= 1e-3 * abs(ref), (res["nll"], ref)

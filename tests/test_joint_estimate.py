"""One parameter set fitted to several records (``estimate`` with a list of
problems, ``bondgraph estimate --data a.csv --data b.csv``).

References: each record's own estimate (its Cramér-Rao bound from its own
Hessian): the joint Fisher information of independent records is the sum of
theirs, so the joint standard deviation is 1/sqrt(Σ 1/σ_i²); the joint NLL at
the estimate is the sum of each record's UKF NLL there (``ukf_nll`` called
directly); records simulated with scipy's solve_ivp."""

import json

import numpy as np
import pytest

from bondgraph.cli.main import main
from bondgraph.data.records import Experiment
from bondgraph.errors import OptionError
from bondgraph.inference.estimate import estimate
from bondgraph.inference.options import FitOptions
from bondgraph.inference.ukf import ukf_nll
from bondgraph.numerics.model import Model
from test_estimate import P0, problem, simulate_zoh

TRUTH = {"m": 2.5, "k": 80.0, "c": 2.0}
FIT = FitOptions(particles=30, iterations=40, seed=2, progress=False)


@pytest.fixture(scope="module")
def records():
    """Two records of the mass-spring-damper (different force sequences and
    noise), 300 samples at 50 Hz each, the graph's sensor noise added."""
    m = Model.load("mass_spring_damper")
    th = m.theta(TRUTH)
    out = []
    for seed in (0, 1):
        t = np.arange(300) * 0.02
        rng = np.random.default_rng(seed)
        u = np.repeat(rng.normal(0.0, 20.0, 15), 20)[:, None]
        y0 = simulate_zoh(m, t, u, th, np.zeros(m.n_x))
        out.append((t, u, y0 + rng.normal(size=y0.shape) * m.meas_std(th)))
    return m, out


@pytest.fixture(scope="module")
def fits(records):
    m, recs = records
    ps = [problem(m, r, P0=P0) for r in recs]
    singles = [estimate(p, ["m", "k", "c"], fit=FIT) for p in ps]
    return ps, singles, estimate(ps, ["m", "k", "c"], fit=FIT)


def test_joint_information_is_the_sum_of_the_records(fits):
    _, singles, joint = fits
    expected = 1.0 / np.sqrt(sum(1.0 / r.std ** 2 for r in singles))
    np.testing.assert_allclose(joint.std, expected, rtol=0.15)
    for r in singles:
        assert (joint.std < r.std).all()
    for i, p in enumerate(joint.params):
        assert abs(joint.estimates[i] - TRUTH[p]) < 3 * joint.std[i], (p, joint.estimates[i])


def test_joint_nll_is_the_sum_of_each_records(records, fits):
    m, recs = records
    ps, _, joint = fits
    each = [float(ukf_nll(m, t, u, y, joint.theta[None, :], p.x0, p.P0,
                          options=p.ukf).nll[0]) for (t, u, y), p in zip(recs, ps)]
    assert joint.nll == pytest.approx(sum(each), abs=1e-6 * abs(sum(each)))
    rec = joint.settings["records"]
    assert [r["samples"] for r in rec] == [300, 300]
    assert joint.settings["samples"] == 600
    assert joint.experiment == "arrays #1 + arrays #2"
    assert set(joint.settings["discretisation"]["records"]) == {"arrays #1", "arrays #2"}


def test_joint_refuses_what_it_cannot_share(records):
    m, recs = records
    a = problem(m, recs[0], P0=P0)
    b = problem(m, recs[1], P0=P0, fixed={"m": 2.5})
    with pytest.raises(OptionError, match="different fixed values"):
        estimate([a, b], ["k", "c"], fit=FIT)
    with pytest.raises(OptionError, match="initial states are estimated on one record"):
        estimate([a, problem(m, recs[1], P0=P0)], ["k", "c"], fit=FIT, x0_states=["all"])


def test_cli_fits_two_records_together(records, tmp_path, capsys):
    m, recs = records
    paths = []
    for i, (t, u, y) in enumerate(recs):
        pth = tmp_path / f"run{i + 1}.csv"
        Experiment.from_arrays(t, model=m, u=u, y=y, name=f"run{i + 1}").save(pth)
        paths.append(str(pth))
    out = tmp_path / "est"
    code = main(["estimate", "--model", "mass_spring_damper", "--data", paths[0], "--data",
                 paths[1], "--params", "m,k,c", "--particles", "20", "--iterations", "15",
                 "--out", str(out), "--quiet"])
    assert code == 0
    doc = json.loads((out / "result.json").read_text())
    assert doc["settings"]["data"] == paths
    assert [r["name"] for r in doc["settings"]["records"]] == ["run1", "run2"]
    assert {p.name for p in out.glob("*.png")} >= {"run1_fit_outputs.png",
                                                    "run2_fit_outputs.png"}
    est = dict(zip(doc["params"], doc["estimates"]))
    std = dict(zip(doc["params"], doc["std"]))
    for p in ("m", "k", "c"):
        assert abs(est[p] - TRUTH[p]) < 4 * std[p], (p, est[p], std[p])
    assert main(["estimate", "--model", "mass_spring_damper", "--data", paths[0], "--data",
                 paths[1], "--params", "m,k,c", "--fit", "sim", "--out",
                 str(tmp_path / "sim")]) == 2
    assert "--fit sim fits one record" in capsys.readouterr().err

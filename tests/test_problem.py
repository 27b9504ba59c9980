"""The estimation problem as one immutable object (bondgraph.inference.problem):
built once from a model and a record, read by the likelihood, the smoother
and the checks, replaced (never changed) by what a fit learns."""
import dataclasses
import pickle

import numpy as np
import pytest

import bondgraph
from bondgraph.data.records import Experiment
from bondgraph.errors import DataError, ModelError, OptionError
from bondgraph.inference.options import P0_REL, Discretisation, UKFOptions
from bondgraph.inference.prior import (
    UNKNOWN_REL,
    X0_TOKEN,
    PriorSpec,
    default_P0,
    record_prior,
)
from bondgraph.inference.problem import NoiseSpec, Problem, make_problem
from bondgraph.inference.ukf import ukf_nll
from bondgraph.numerics.model import Model
from bondgraph.numerics.simulate import simulate

UKF = UKFOptions(method="rk4", substeps=2)


@pytest.fixture(scope="module")
def msd():
    """A mass-spring-damper record (only the position measured) whose
    sidecar gives the spring's initial state but not the momentum's."""
    m = Model.load("mass_spring_damper")
    t = np.arange(300) * 0.01
    u = np.repeat(np.random.default_rng(0).normal(0.0, 10.0, 15), 20)[:, None]
    th = m.theta(m=2.0, k=50.0, c=1.5)
    y = simulate(m, t, u, np.array([0.2, 0.01]), th, hold="zoh").y
    y = y + np.random.default_rng(1).normal(size=y.shape) * m.meas_std(th)
    y[:, 1] = np.nan
    exp = Experiment.from_arrays(t, model=m, u=u, y=y, name="msd",
                                 meta={"x0": {"q_spring": 0.01}})
    return m, exp


def test_the_prior_follows_the_one_rule(msd):
    """x0: the record's sidecar for q_spring, the model's X0 for the momentum
    (a guess: its prior spans its whole scale); P0 equals record_prior's with
    the free run of the filter's discretisation at no fewer than 2 substeps."""
    m, exp = msd
    pb = make_problem(m, exp, ukf=UKF)
    assert pb.x0_rule == "record state columns / sidecar x0"
    np.testing.assert_array_equal(pb.x0, [m.x0[0], 0.01])
    t, u, y = pb.arrays
    ref, info = record_prior(m, t, u, y, m.theta0, pb.x0, Discretisation("rk4", 2), rel=P0_REL,
                             unknown=["p_mass"])
    np.testing.assert_array_equal(pb.P0, ref)
    assert pb.P0[0, 0] == pytest.approx((UNKNOWN_REL * info["scales"]["p_mass"]) ** 2)
    assert pb.P0[1, 1] == pytest.approx((P0_REL * info["scales"]["q_spring"]) ** 2)
    # named states are imposed and count as given; magnitude: 5 % of max(|x0|, 1)
    named = make_problem(m, exp, prior=PriorSpec(scale="magnitude", x0_set={"p_mass": 0.4}))
    np.testing.assert_array_equal(named.x0, [0.4, 0.01])
    np.testing.assert_array_equal(named.P0, default_P0(m, [0.4, 0.01], P0_REL))
    assert PriorSpec(x0_set={"p_mass": 0.4}).unknown(m, exp) == []
    # a whole mean given wins over the record; a given P0 is used as it is
    given = make_problem(m, exp, prior=PriorSpec(x0=[0.1, 0.0], P0=np.diag([1e-4, 1e-6])))
    assert given.x0_rule == "given" and given.x0.tolist() == [0.1, 0.0]
    np.testing.assert_array_equal(given.P0, np.diag([1e-4, 1e-6]))


def test_nll_is_the_ukf_of_its_parts(msd):
    """Problem.nll equals ukf_nll called with the problem's arrays, prior and
    options, bit for bit; held noise levels enter as R = diag(σ²) (σ from
    meas_std(θ) for the outputs not held)."""
    m, exp = msd
    pb = make_problem(m, exp, ukf=UKF)
    th = np.array([m.theta0, m.theta(k=60.0)])
    want = ukf_nll(m, pb.t, pb.u, pb.y, th, pb.x0, pb.P0, options=UKF).nll
    np.testing.assert_array_equal(pb.nll(th).nll, want)
    held = pb.conditioned_on(noise_levels={"x": 0.003})
    assert held.P0 is pb.P0 and held.x0 is pb.x0          # the prior did not change
    R = np.zeros((2, 2, 2))
    R[:, 0, 0] = 0.003 ** 2
    R[:, 1, 1] = m.meas_std(th)[:, 1] ** 2
    want = ukf_nll(m, pb.t, pb.u, pb.y, th, pb.x0, pb.P0, options=UKF, R=R).nll
    np.testing.assert_array_equal(held.nll(th).nll, want)
    assert pb.noise.held == {} and held.noise.held == {"x": 0.003}     # pb is unchanged


def test_conditioning_on_estimated_initial_states(msd):
    """An initial state estimated with θ: the prior mean takes the estimate and
    the filter holds it at X0_TOKEN of its prior std (the prior recomputed at
    the new mean); full_prior gives the whole spread back."""
    m, exp = msd
    pb = make_problem(m, exp, ukf=UKF)
    c = pb.conditioned_on(x0={"p_mass": 0.2})
    assert c.x0[0] == 0.2 and pb.x0[0] == m.x0[0]
    full = c.full_prior()
    ref = make_problem(m, exp, prior=PriorSpec(x0_set={"p_mass": 0.2}), ukf=UKF)
    # the same mean; as the named state it would count as given (5 %), estimated
    # it keeps its whole scale until the token spread shrinks it
    assert full[0, 0] == pytest.approx(ref.P0[0, 0] / P0_REL ** 2 * UNKNOWN_REL ** 2)
    assert c.P0[0, 0] == pytest.approx(X0_TOKEN ** 2 * full[0, 0])
    assert c.P0[0, 1] == 0.0 and c.P0[1, 1] == full[1, 1]
    # conditioning on the same estimates again keeps the prior (no new free run)
    assert c.conditioned_on(x0={"p_mass": 0.2}).prior is c.prior


def test_a_problem_never_changes_and_travels(msd):
    """Frozen (a field cannot be set); pickled to a worker it gives the same NLL."""
    m, exp = msd
    pb = make_problem(m, exp, ukf=UKF)
    with pytest.raises(dataclasses.FrozenInstanceError):
        pb.x0 = np.zeros(2)
    back = pickle.loads(pickle.dumps(pb.conditioned_on(noise_levels={"x": 0.003})))
    np.testing.assert_array_equal(back.nll(m.theta0).nll,
                                  pb.conditioned_on(noise_levels={"x": 0.003}).nll(m.theta0).nll)


def test_other_records_models_and_stages(msd):
    """on_record: the validation record's own initial state (the named states
    and estimates belong to the estimation record); with_model keeps the
    policies; with_fixed sets values over the defaults."""
    m, exp = msd
    pb = make_problem(m, exp, prior=PriorSpec(x0_set={"p_mass": 0.4}), ukf=UKF)
    later = exp.segment(100)
    val = pb.on_record(later)
    assert val.x0[0] == m.x0[0] and val.t.size == 200 and val.prior.x0_set == {}
    assert val.prior.unknown(m, later) == ["p_mass", "q_spring"]
    other = pb.with_model(Model.load("mass_spring_damper"))
    np.testing.assert_array_equal(other.x0, pb.x0)
    assert other.prior.scales == pb.scales and other.prior.x0_set == pb.prior.x0_set
    assert other.ukf == pb.ukf
    np.testing.assert_array_equal(other.P0, pb.P0)
    fx = pb.with_fixed({"k": 60.0})
    assert fx.theta[m.param_index("k")] == 60.0 and fx.fixed == {"k": 60.0}


def test_bad_input_is_named(msd):
    m, exp = msd
    with pytest.raises(ModelError, match="kk"):
        make_problem(m, exp, fixed={"kk": 1.0})
    with pytest.raises(OptionError, match="rel"):
        PriorSpec(rel=0.0)
    with pytest.raises(OptionError, match="scale"):
        PriorSpec(scale="big")
    with pytest.raises(ModelError, match="nope"):
        PriorSpec(x0_set={"nope": 1.0}).check(m)
    with pytest.raises(OptionError, match="mode"):
        NoiseSpec("guess")
    with pytest.raises(OptionError, match="substeps"):
        Discretisation(substeps=0)
    with pytest.raises(OptionError, match="PriorSpec"):
        make_problem(m, exp, prior={"rel": 0.1})
    # an input the record lacks is an error unless the defaults are wanted
    bare = Experiment.from_arrays(exp.t, columns={"x": exp.columns["x"]}, units={"x": "m"},
                                  roles={"x": "output"}, name="no input")
    with pytest.raises(DataError, match="F"):
        make_problem(m, bare)
    assert make_problem(m, bare, defaults_ok=True).u.shape == (exp.t.size, 1)


def test_defaults_and_the_public_name():
    """One default each: the prior's 5 %, the free run's 2 substeps, the noise
    policy "auto" (bare arrays, which declare nothing: "model")."""
    assert PriorSpec().rel == P0_REL == 0.05
    assert Discretisation(substeps=1).for_free_run().substeps == 2
    assert Discretisation(substeps=4).for_free_run().substeps == 4
    assert NoiseSpec().mode == "auto"
    m = Model.load("mass_spring_damper")
    t = np.arange(10) * 0.1
    pb = make_problem(m, (t, np.zeros((10, 1)), np.zeros((10, 2))))
    assert pb.noise.mode == "model" and pb.record is None and pb.name == "arrays"
    assert pb.x0_rule == "model X0"
    assert bondgraph.Problem is Problem and bondgraph.make_problem is make_problem
    doc = Problem.__doc__
    assert "Attributes" in doc and "References" in doc and "(N, n_u)" in doc
    assert "Raises" in make_problem.__doc__

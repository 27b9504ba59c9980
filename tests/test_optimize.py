"""Particle swarm and differential evolution behind one batched interface
(bondgraph.inference.optimize): standard test functions, exact evaluation counts,
checkpoint/resume bit for bit, +inf handling, DE path, local polish."""

import numpy as np
import pytest

from bondgraph.inference.optimize import de, minimize_batched, pso
from bondgraph.inference.options import Checkpointing, EvolutionOptions, SwarmOptions
from bondgraph.errors import CheckpointError, OptionError


def sphere(X):
    return np.sum((X - 0.3) ** 2, axis=1)


def rosenbrock(X):
    return np.sum(100.0 * (X[:, 1:] - X[:, :-1] ** 2) ** 2 + (1.0 - X[:, :-1]) ** 2, axis=1)


class Counting:
    def __init__(self, f):
        self.f, self.sets, self.calls = f, 0, 0

    def __call__(self, X):
        self.sets += X.shape[0]
        self.calls += 1
        return self.f(X)


def test_pso_sphere_and_exact_counts():
    f = Counting(sphere)
    r = pso(f, [-5.0] * 8, [5.0] * 8, swarm=SwarmOptions(particles=80, iterations=100, seed=3),
            progress=False)
    assert r.nfev == 8080 == f.sets and r.ncalls == 101 == f.calls and r.nit == 100
    assert len(r.history) == 101 and np.all(np.diff(r.history) <= 0)
    np.testing.assert_allclose(r.x, 0.3, atol=2e-3)
    assert r.fun < 1e-5


def test_pso_rosenbrock():
    r = pso(rosenbrock, [-2.0] * 3, [2.0] * 3,
            swarm=SwarmOptions(particles=60, iterations=400, seed=1), progress=False)
    np.testing.assert_allclose(r.x, 1.0, atol=0.05)
    # polish from the swarm's best point reaches the minimum
    x, fx, nfev, _ = minimize_batched(rosenbrock, r.x, [-2.0] * 3, [2.0] * 3)
    np.testing.assert_allclose(x, 1.0, atol=1e-4)
    assert fx < 1e-8 and nfev % 7 == 0          # 2k+1 = 7 sets per gradient call


def test_pso_stall_rule():
    r = pso(sphere, [-1.0] * 2, [1.0] * 2,
            swarm=SwarmOptions(particles=20, iterations=1000, seed=0, stall_iterations=15,
                               ftol=1e-12), progress=False)
    assert r.nit < 1000 and r.stop_reason.startswith("stalled")
    assert r.nfev == 20 * (r.nit + 1)


def test_pso_checkpoint_resume_bit_for_bit(tmp_path):
    kw = dict(swarm=SwarmOptions(particles=25, iterations=30, seed=11), progress=False)
    full = pso(rosenbrock, [-2.0] * 4, [2.0] * 4, **kw)
    ck = tmp_path / "pso.npz"

    class Crash(Exception):
        pass

    def crash_at_12(it, x, f):
        if it == 12:
            raise Crash

    with pytest.raises(Crash):
        pso(rosenbrock, [-2.0] * 4, [2.0] * 4, checkpointing=Checkpointing(ck),
            callback=crash_at_12, **kw)
    assert ck.exists()
    res = pso(rosenbrock, [-2.0] * 4, [2.0] * 4, checkpointing=Checkpointing(ck, resume=True),
              **kw)
    assert res.resumed_from == 12
    assert np.array_equal(res.x, full.x) and res.fun == full.fun
    assert np.array_equal(res.history, full.history)
    assert res.nfev == full.nfev == 25 * 31
    # a checkpoint written with other settings is refused
    with pytest.raises(CheckpointError, match=r"seed \(checkpoint: 11, now: 12\) differs"):
        pso(rosenbrock, [-2.0] * 4, [2.0] * 4, checkpointing=Checkpointing(ck, resume=True),
            swarm=SwarmOptions(particles=25, iterations=30, seed=12), progress=False)


def test_inf_and_nan_do_not_crash():
    def f(X):
        out = rosenbrock(X)
        out[X[:, 0] > 1.5] = np.inf
        out[X[:, 1] < -1.5] = np.nan
        return out

    r = pso(f, [-2.0] * 2, [2.0] * 2, swarm=SwarmOptions(particles=30, iterations=150, seed=2),
            progress=False)
    assert np.isfinite(r.fun) and r.n_inf > 0
    np.testing.assert_allclose(r.x, 1.0, atol=0.05)
    d = de(f, [-2.0] * 2, [2.0] * 2, evolution=EvolutionOptions(popsize=15, iterations=150,
                                                                 seed=2), progress=False)
    assert np.isfinite(d.fun) and d.n_inf > 0
    np.testing.assert_allclose(d.x, 1.0, atol=0.05)
    # a criterion that fails everywhere: +inf result, no exception
    r = pso(lambda X: np.full(X.shape[0], np.inf), [0.0], [1.0],
            swarm=SwarmOptions(particles=5, iterations=3), progress=False)
    assert np.isinf(r.fun) and r.n_inf == 20


def test_de_counts_and_minimum():
    f = Counting(rosenbrock)
    r = de(f, [-2.0] * 8, [2.0] * 8, evolution=EvolutionOptions(popsize=10, iterations=100,
                                                                 seed=4), progress=False)
    # 80 members: initial population + one batched call per generation
    assert r.nfev == f.sets == 80 * (r.nit + 1) and r.ncalls == f.calls == r.nit + 1
    assert r.nit == 100 and r.nfev == 8080
    assert r.fun < rosenbrock(np.zeros((1, 8)))[0]
    r2 = de(rosenbrock, [-2.0] * 2, [2.0] * 2,
            evolution=EvolutionOptions(popsize=20, iterations=300, seed=4, tol=1e-12),
            progress=False)
    np.testing.assert_allclose(r2.x, 1.0, atol=1e-3)


def test_de_checkpoint_resume(tmp_path):
    ck = tmp_path / "de.npz"
    r1 = de(rosenbrock, [-2.0] * 3, [2.0] * 3,
            evolution=EvolutionOptions(popsize=10, iterations=20, seed=5), progress=False,
            checkpointing=Checkpointing(ck))
    assert ck.exists() and int(np.load(ck)["it"]) == 20
    r2 = de(rosenbrock, [-2.0] * 3, [2.0] * 3,
            evolution=EvolutionOptions(popsize=10, iterations=60, seed=5), progress=False,
            checkpointing=Checkpointing(ck, resume=True))
    assert r2.resumed_from == 20 and r2.nit == 60 and r2.fun <= r1.fun


def test_bad_bounds():
    with pytest.raises(OptionError, match="bound 1"):
        pso(sphere, [0.0, 1.0], [1.0, 1.0], progress=False)
    with pytest.raises(OptionError, match="resume"):
        pso(sphere, [0.0], [1.0], checkpointing=Checkpointing(None, resume=True),
            progress=False)


def test_options_validated_on_construction():
    with pytest.raises(OptionError, match=r"SwarmOptions\.particles .* got 1"):
        SwarmOptions(particles=1)
    with pytest.raises(OptionError, match=r"SwarmOptions\.vmax must be > 0, got -0\.1"):
        SwarmOptions(vmax=-0.1)
    with pytest.raises(OptionError, match=r"SwarmOptions\.iterations .* got -1"):
        SwarmOptions(iterations=-1)
    with pytest.raises(OptionError, match=r"EvolutionOptions\.strategy = 'best3bin'"):
        EvolutionOptions(strategy="best3bin")
    with pytest.raises(OptionError, match=r"EvolutionOptions\.recombination .* got 1\.5"):
        EvolutionOptions(recombination=1.5)
    with pytest.raises(OptionError, match=r"EvolutionOptions\.mutation"):
        EvolutionOptions(mutation=(0.5, 1.0, 2.0))
    with pytest.raises(OptionError, match=r"Checkpointing\.resume = True needs a checkpoint"):
        Checkpointing(resume=True)
    with pytest.raises(OptionError, match=r"swarm must be a SwarmOptions, got dict"):
        pso(sphere, [0.0], [1.0], swarm={"particles": 5}, progress=False)
    with pytest.raises(OptionError, match=r"DE needs a population of at least 5 members"):
        de(sphere, [0.0], [1.0], evolution=EvolutionOptions(popsize=2), progress=False)
    assert Checkpointing("ck.npz").path.name == "ck.npz"
    assert EvolutionOptions(mutation=[0.4, 0.9]).mutation == (0.4, 0.9)


def test_polish_beside_a_region_without_finite_values_reaches_the_minimum():
    """A minimum 0.005 of the box from where the criterion has no value (an
    explicit step that goes unstable below a time constant): L-BFGS-B's first
    step from the far side lands there and its line search stopped where it
    began (x stayed at the start). The rerun with a shorter first step
    reaches the analytic minimum (0.1, 1)."""
    def cliff(X):
        x, y = X[:, 0], X[:, 1]
        return np.where(x < 0.095, np.inf, ((x - 0.1) / 0.01) ** 2 + (y - 1.0) ** 2)

    x, fx, nfev, _ = minimize_batched(cliff, [0.189, 1.2], [0.02, -10.0], [20.0, 10.0])
    np.testing.assert_allclose(x, [0.1, 1.0], atol=1e-6)
    assert fx < 1e-10 and nfev % 5 == 0         # 2k+1 = 5 sets per gradient call

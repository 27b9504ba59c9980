"""An additive candidate's refit also starts where the effect vanishes
(bondgraph.diagnose.confirm.nested_starts), when the grid's start is worse
than the model the candidate nests: a refit from there can only gain, so a
confirmed nested candidate never ends below its own null (a square-root
orifice term on a user's two-tank record: grid start NLL 1.0e8, refit 3751
nats above the declared fit, reported as LR 0.0)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from bondgraph.diagnose import confirm


class _Model:
    params = ["k", "r.beta"]
    theta0 = np.array([1.0, 0.0])

    def param_index(self, n):
        return self.params.index(n)

    def bounds(self, names):
        box = {"k": (0.1, 10.0), "r.beta": (-100.0, 100.0)}
        return np.array([box[n][0] for n in names]), np.array([box[n][1] for n in names])


def _nll(names, base):
    """A likelihood whose optimum is beta = 0.01, k = 2: (k - 2)² + 1e6 (beta - 0.01)²."""
    def f(X):
        th = np.repeat(base[None, :], len(X), axis=0)
        for j, n in enumerate(names):
            th[:, _Model.params.index(n)] = X[:, j]
        return (th[:, 0] - 2.0) ** 2 + 1e6 * (th[:, 1] - 0.01) ** 2
    return f


def _case(monkeypatch, beta_start, additive=True):
    logged = []
    ctx = SimpleNamespace(log=logged.append)
    monkeypatch.setattr(confirm, "criterion_for", lambda ctx, model, names, base: _nll(names, base))
    fit = SimpleNamespace(params=["k"], estimates=lambda: {"k": 2.0})
    cand = SimpleNamespace(joint_step={"effect": {"beta": 0.5}, "estimated": {"k": 0.1}},
                           label="r @ orifice")
    eff = SimpleNamespace(additive=additive, params=[SimpleNamespace(name="beta", estimated=True)])
    P = {"beta": SimpleNamespace(name="r.beta")}
    start = {"k": 2.0, "r.beta": beta_start}
    return confirm.nested_starts(ctx, _Model(), fit, cand, eff, P, start), logged


def test_a_grid_start_beyond_the_optimum_adds_the_null_start(monkeypatch):
    starts, logged = _case(monkeypatch, beta_start=5.0)      # NLL 2.5e7 there, 100 at the null
    assert starts == [{"k": 2.0, "r.beta": 0.0}]
    assert "vanishes" in logged[0] and "NLL 100.0" in logged[0]


def test_a_grid_start_better_than_the_null_adds_nothing(monkeypatch):
    starts, logged = _case(monkeypatch, beta_start=0.012)    # NLL 4 < 100
    assert starts == [] and logged == []


def test_a_structural_candidate_has_no_null_start(monkeypatch):
    starts, _ = _case(monkeypatch, beta_start=5.0, additive=False)
    assert starts == []

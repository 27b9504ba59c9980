"""A pair's refit nests each member's own refit (diagnose.runner.sequential_pair):
started from a member's refit with the other (additive) member's coefficients
at 0, it ends no worse than that member alone. The joint start mixes the
current fit's estimates with both members' values; on a user's four-mass
chain a sensor gain refitted to LR 3383 alone and to LR -4101 with a Stribeck
term beside it. Record: the mass-spring-damper with Coulomb friction, from
the equations by hand, integrated by scipy."""

from __future__ import annotations

import numpy as np
from scipy.integrate import solve_ivp

from bondgraph.catalog.reference import mass_spring_damper
from bondgraph.data.records import Experiment
from bondgraph.diagnose.confirm import Confirmation, confirm, confirm_pair
from bondgraph.diagnose.effects import Target
from bondgraph.diagnose.fit import Context, fit_model, model_of
from bondgraph.diagnose.result import Candidate
from bondgraph.diagnose.runner import below_member, sequential_pair
from bondgraph.diagnose.scales import operating_scales
from bondgraph.diagnose.settings import LoopSettings

M, K, C, FC, EPS = 2.0, 50.0, 1.5, 3.0, 0.01
NOISE = (0.002, 0.01)


def record(n: int = 1500, dt: float = 0.01) -> Experiment:
    """A force held for 0.2 s at random levels (N(0, 20) N); dp/dt = F − k q −
    c v − Fc tanh(v/ε), dq/dt = v (LSODA, rtol 1e-9); the sensors' noise,
    declared."""
    rng = np.random.default_rng(4)
    t = np.arange(n) * dt
    levels = rng.normal(0.0, 20.0, n // 20 + 1)

    def f(tt, x):
        v = x[0] / M
        return [levels[int(tt / (20 * dt))] - K * x[1] - C * v - FC * np.tanh(v / EPS), v]

    X = solve_ivp(f, (0, t[-1]), [0.0, 0.0], t_eval=t, method="LSODA", rtol=1e-9, atol=1e-12,
                  max_step=dt).y.T
    y = np.column_stack([X[:, 1], X[:, 0] / M]) + np.array(NOISE) * rng.standard_normal((n, 2))
    u = levels[(t / (20 * dt)).astype(int)][:, None]
    g = mass_spring_damper()
    return Experiment.from_arrays(t, model=model_of(g), u=u, y=y, name="msd_coulomb",
                                  noise_std=dict(zip(["x", "v"], NOISE)))


def test_a_pair_started_from_a_members_refit_ends_no_worse_than_it():
    g = mass_spring_damper()
    ctx = Context.on(record(), LoopSettings(params=["m", "k", "c"]), model_of(g),
                     lambda s: None, False)
    current = fit_model(ctx, g, ["m", "k", "c"], None, "declared")
    scales = operating_scales(ctx, current)
    coulomb = Candidate("coulomb", "", Target("junction", "v"), "score", 500.0, 1, 0.0, 498.0,
                        values={"Fc": 1.0})
    offset = Candidate("sensor_offset", "", Target("sensor", "v"), "score", 20.0, 1, 1e-5, 18.0,
                       values={"b": 0.3})
    own = confirm(ctx, current, coulomb, scales, "alone")
    assert own.fit.nll < current.nll - 100          # the friction is there
    fc = own.values["Fc"]
    assert abs(fc - FC) < 0.1 * FC
    # the member's confirmed values (its kept tanh width among them) go with it,
    # as the runner records them (confirmed_record)
    coulomb.confirmed = {"values": dict(own.values)}
    # from the member's refit, the offset at 0: the start is that refit's point
    nested = confirm_pair(ctx, current, (coulomb, offset), scales, "nested", base=own.fit,
                          off=offset)
    assert nested.fit.nll <= own.fit.nll + 1e-6
    assert abs(nested.values["coulomb @ v.Fc"] - fc) < 0.05 * fc
    # a joint refit that ended above the member it nests is refitted from it
    worse = Confirmation(nested.fit, dict(nested.values), list(nested.new_params))
    worse.fit = fit_model(ctx, nested.fit.graph, nested.fit.params,
                          {**nested.fit.estimates(), "coulomb.v.Fc": 0.2}, "stuck",
                          iterations=0)
    assert below_member(worse, [own]) and not below_member(nested, [own])
    ctx.cache[("confirmation", id(current), current.nll, coulomb.label)] = own
    best = sequential_pair(ctx, current, (coulomb, offset), worse, "t", scales)
    assert best is not worse and best.fit.nll <= own.fit.nll + 1e-6

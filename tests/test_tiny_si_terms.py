"""Additive candidates whose term is below the rounding of f and h at a
unit coefficient (:func:`bondgraph.diagnose.scoring.nudge_sizes`).

A user's gas accumulator in SI units: capacitance 7e-11 m³/Pa, its volume
~7e-4 m³ at ~1e7 Pa, so a cubic stiffness k3·q³ at k3 = 1 adds 3e-10 Pa to
1e7 Pa, exactly nothing in double precision. The score test's nudge was
1e-3 divided by that zero change (floored at 1e-300): k3 = 1e297, and both
cubic candidates were reported as "could not be scored (filter failed)".

The truth hardens: p = q/Ca + k3 q³, k3 8.7e15 Pa/m⁹ (30 % of the pressure
at 7e-4 m³); a pump's multisine flow into the accumulator, a linear orifice
(1e11 Pa s/m³) out of it, written here by hand and integrated with scipy's
LSODA, the pressure measured at 10 Hz with N(0, 0.2 bar) noise.

The same accumulator a hundred times smaller (a hydraulic hose's volume,
~7e-6 m³: the capacitance and the flows times 1e-2, the orifice's
resistance times 1e2, the cubic coefficient times 1e6, the pressures the
same): k3 8.7e21 Pa/m⁹ lies beyond the library's numeric guard of ±1e15 on
the coefficient, which clipped the score test's start, and the refit's box
(±20 times the start) ended at 2e16, where a user's hose stopped
(:func:`bondgraph.diagnose.effects.base.reach_guards`).
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from bondgraph import BondGraph
from bondgraph.data.records import Experiment
from bondgraph.diagnose.effects.storage import CubicStiffness
from bondgraph.diagnose.loop import LoopSettings, run_loop
from bondgraph.diagnose.runner import chosen_numerics
from bondgraph.diagnose.settings import SearchOptions

CA, RO, K3 = 7e-11, 1e11, 8.7e15
NOISE, FS = 2e4, 10.0


def accumulator(s: float = 1.0) -> BondGraph:
    """The declared graph of the accumulator scaled in volume by ``s``."""
    g = BondGraph("accumulator", "a pump filling a gas accumulator, an orifice draining it")
    Q = g.input("Q", "m**3/s", 0.0, "pump flow")
    ca = g.param("Ca", 6e-11 * s, "m**3/Pa", (1e-12 * s, 1e-9 * s), "accumulator capacitance")
    ro = g.param("Ro", 1.2e11 / s, "Pa*s/m**3", (1e9 / s, 1e13 / s), "orifice resistance")
    j = g.zero("acc", domain="hydraulic")
    g.connect(g.Sf("pump", Q), j)
    g.connect(j, g.C("gas", compliance=ca))
    g.connect(j, g.R("orifice", ro))
    g.sensor("p", j.e, unit="Pa", noise_std=NOISE)
    return g


def record(seed: int, secs: float, name: str, s: float = 1.0) -> Experiment:
    rng = np.random.default_rng(seed)
    f = np.geomspace(0.01, 0.5, 10)
    ph = rng.uniform(0, 2 * np.pi, f.size)

    def q(t):
        return s * (1e-4 + 3e-5 * float(np.sum(np.sin(2 * np.pi * f * t + ph))) / np.sqrt(5))

    def rhs(t, x):
        p = x[0] / (CA * s) + K3 / s**3 * x[0] ** 3
        return [q(t) - p * s / RO]

    t = np.arange(0.0, secs, 1 / FS)
    sol = solve_ivp(rhs, (0, t[-1]), [5e-4 * s], t_eval=t, method="LSODA", max_step=0.05,
                    rtol=1e-10, atol=1e-16 * s)
    assert sol.status == 0
    p = sol.y[0] / (CA * s) + K3 / s**3 * sol.y[0] ** 3
    return Experiment.from_arrays(t, {"Q": np.array([q(s) for s in t]),
                                      "p": p + rng.normal(0, NOISE, t.size)},
                                  units={"Q": "m**3/s", "p": "Pa"},
                                  roles={"Q": "input", "p": "output"}, name=name)


@pytest.mark.parametrize("s", [1.0, 1e-2])
def test_a_cubic_stiffness_of_tiny_si_magnitude_is_scored_and_found(s):
    """The cubic candidate is scored (it could not be before; χ² 2569),
    accepted, and its coefficient and the declared parameters land within
    3 Cramér-Rao std of the truth (k3 8.617e15 ± 0.031e15, Ca 6.922e-11 ±
    0.037e-11); the held-out NRMSE 0.0403 -> 0.0133. A hundred times
    smaller (s = 1e-2): k3 8.7e21 found as well (the refit stopped at the
    guard's 2e16 before): 8.617e21 ± 0.031e21, the same digits scaled."""
    est, val = record(1, 300.0, "run1", s), record(2, 150.0, "run2", s)
    lines = []
    settings = chosen_numerics(accumulator(s), est, LoopSettings(
        ["Ca", "Ro"], validation=val, effects=(CubicStiffness(),),
        search=SearchOptions(max_steps=1)), log=lines.append)
    res = run_loop(accumulator(s), est, settings, log=lines.append, progress=False)
    assert not any("could not be scored" in x for x in lines)
    assert [(a.effect, a.target.name) for a in res.applied] == [("cubic_stiffness", "gas")]
    e, sd = res.final.estimates, res.final.std
    for name, true in {"Ca": CA * s, "Ro": RO / s, "cubic_stiffness.gas.k3": K3 / s**3}.items():
        assert abs(e[name] - true) < 3 * sd[name], (name, e[name], sd[name])

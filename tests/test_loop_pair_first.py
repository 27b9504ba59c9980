"""A pair tested before the best single is accepted (issue 26, "interacting
effects"): a mass-spring-damper whose spring has a cubic term and whose
damper a quadratic one (both in the library), records simulated by scipy's
solve_ivp from the hand-written equations

    m dv/dt = F − k x − k3 x³ − c v − c2 v|v|,   dx/dt = v.

Against the declared fit both effects are significant; the cubic spring
alone passes the accept rule, with the damping c absorbing the quadratic
drag (measured: c = 5.78 against 1.5). The pair's refit beats it, and the
one step adds both. With the drag absent, the pairs with the look-alikes
(Coulomb, viscous) are not refitted (neither is significant at the cubic
spring's refit): the single stands."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from bondgraph.catalog.reference import mass_spring_damper
from bondgraph.data.records import Experiment
from bondgraph.diagnose.effects import Coulomb, CubicStiffness, QuadraticDrag, Viscous
from bondgraph.diagnose.runner import run_loop
from bondgraph.diagnose.settings import LoopSettings, SearchOptions
from bondgraph.inference.options import UKFOptions

M, K, C, K3 = 2.0, 50.0, 1.5, 800.0
NOISE = {"x": 0.002, "v": 0.01}
T = np.arange(0.0, 30.0, 0.01)


def force(t, ph):
    return (15 * np.sin(2 * np.pi * 0.3 * t + ph) + 10 * np.sin(2 * np.pi * 1.1 * t + 1 + ph)
            + 5 * np.sin(2 * np.pi * 2.3 * t + 2 + ph))


def record(c2: float, seed: int, ph: float):
    """The truth's record (x [m], v [m/s] with N(0, NOISE) noise) and its
    noise-free outputs."""
    def rhs(t, s):
        x, v = s
        return [v, (force(t, ph) - K * x - K3 * x**3 - C * v - c2 * v * abs(v)) / M]

    sol = solve_ivp(rhs, (T[0], T[-1]), [0.0, 0.0], t_eval=T, method="LSODA", rtol=1e-9,
                    atol=1e-11, max_step=0.005)
    rng = np.random.default_rng(seed)
    y = {"x": sol.y[0] + NOISE["x"] * rng.standard_normal(T.size),
         "v": sol.y[1] + NOISE["v"] * rng.standard_normal(T.size)}
    rec = Experiment.from_arrays(T, {"F": force(T, ph), **y}, units={"F": "N", "x": "m", "v": "m/s"},
                                 roles={"F": "input", "x": "output", "v": "output"},
                                 noise_std=NOISE)
    return rec, {"x": sol.y[0], "v": sol.y[1]}, y


def loop(c2: float):
    val, clean, noisy = record(c2, 2, 0.7)
    lines = []
    settings = LoopSettings(params=["m", "k", "c"], validation=val,
                            ukf=UKFOptions(substeps=4, hold="linear"),
                            effects=(CubicStiffness(), Coulomb(), Viscous(), QuadraticDrag()),
                            search=SearchOptions(max_steps=1))
    res = run_loop(mass_spring_damper(), record(c2, 1, 0.0)[0], settings, log=lines.append,
                   progress=False)
    # the truth's own free-run error on the validation record (the noise
    # floor): RMS(measurement − noise-free truth) / std(measurement), mean
    floor = np.mean([np.sqrt(np.mean((noisy[n] - clean[n]) ** 2)) / np.std(noisy[n])
                     for n in ("x", "v")])
    return res, lines, floor


def test_the_pair_beats_the_single_that_absorbed_its_partner():
    res, lines, floor = loop(3.0)
    (step,) = res.steps
    assert (step.effect, step.attached_to, step.together_with) == \
        ("cubic_stiffness", "spring", ["quadratic_drag @ v"])
    assert any("pair cubic_stiffness @ spring + quadratic_drag @ v" in ln and
               "beats the single" in ln for ln in lines), "\n".join(lines)
    P = step.parameters
    for name, truth in (("cubic_stiffness.spring.k3", K3), ("quadratic_drag.v.c", 3.0),
                        ("k", K), ("c", C)):
        assert abs(P[name]["estimate"] - truth) < 3 * P[name]["std"], (name, P[name])
    # (m measured 2.0016 ± 0.0005: the filter's discretisation, not the pair)
    assert P["m"]["estimate"] == pytest.approx(M, rel=0.002)
    # the held-out free-run error reaches the noise floor (measured 0.00985
    # against 0.00984), from 0.196 before
    assert step.error_before > 0.15
    assert step.error_after < 1.05 * floor


def test_look_alikes_are_not_added_as_a_pair():
    res, lines, floor = loop(0.0)
    (step,) = res.steps
    assert (step.effect, step.attached_to, step.together_with) == ("cubic_stiffness", "spring", [])
    # the viscous damper duplicates the declared c: its score asks for a
    # negative damping beside c, which the one-sided score test takes as no
    # evidence (χ² 0: scoring._one_sided), so it is neither confirmed nor
    # paired (with the two-sided test it was confirmed to LR 1.0 against the
    # declared fit run to convergence); the
    # Coulomb look-alike's pair with the cubic spring is not refitted:
    # scored at the cubic spring's refit, it is not significant (the next
    # step's own test)
    (scored,) = [ln for ln in lines if "step 1: " in ln and "candidates scored" in ln]
    assert "viscous @ v (χ²=0.0, k=1)" in scored
    assert not any("confirmed viscous @ v" in ln for ln in lines)
    (line,) = [ln for ln in lines if "pair(s) not refitted" in ln]
    assert set(line.split("(score test): ")[1].split("; ")) == {
        "cubic_stiffness @ spring + coulomb @ v"}
    assert not any("beats the single" in ln for ln in lines)
    # measured 797.67 ± 0.45: 5 std off, the loop's own discretisation check
    # warns (ros2(4) 0.11 measurement-noise std per sample); within 0.5 %
    assert step.parameters["cubic_stiffness.spring.k3"]["estimate"] == pytest.approx(K3, rel=5e-3)
    # measured 0.00819 against the noise floor 0.00741 (the same bias)
    assert step.error_after < 1.15 * floor

"""A candidate's refit that moves a known value (a parameter declared
without a box, ``LoopSettings.hold_unidentified``) along a direction the
record does not identify apart from the candidate's new parameters is
refused (:func:`bondgraph.diagnose.accept.moved_known_value`).

The case it comes from: a pump-fed piston (F = A p, Q = A v; the area A
declared without a box), pressure and position measured, seal friction
reversing more softly than the library's tanh. Its position-sensor gain
g = −0.29 rescales A, M, k and c exactly (x -> x/(1 + g), A -> A (1 + g),
M, k, c -> (1 + g)² M, k, c: the same pressure and measured position) but
for the fixed tanh width, which it thereby widens: a width in disguise that
moved the user's known A by −29 %. The numbers below are that refit's."""

from types import SimpleNamespace

import numpy as np

from bondgraph.diagnose.accept import KNOWN_MOVE_REL, moved_known_value

NAMES = ["C_h", "R_l", "A", "M", "k", "c", "coulomb.rod.Fc"]
BEFORE = [6.98e-13, 1.0e11, 2.0e-3, 49.74, 1.998e5, 1841.0, 309.4]
AFTER = [6.99e-13, 1.0e11, 1.4148e-3, 24.90, 1.0006e5, 996.7, 211.1, -0.2927]


def fit(names, values, flat=()):
    model = SimpleNamespace(param_index=names.index)
    return SimpleNamespace(params=list(names), theta=np.array(values, dtype=float),
                           model=model, flat=tuple(flat))


def test_a_gain_that_rescales_a_known_area_is_refused_with_the_move():
    current = fit(NAMES, BEFORE)
    after = fit(NAMES + ["sensor_gain.x.g"], AFTER, flat=("sensor_gain.x.g", "k", "A"))
    why = moved_known_value(current, after, known=["A"])
    assert "A 0.002 -> 0.001415 (-29%)" in why and "sensor_gain.x.g" in why
    assert "declared without a box" in why and "--params" in why
    # the same refit where A was declared with a box (estimated freely): no objection
    assert moved_known_value(current, after, known=[]) == ""
    # nor where the record tells the gain apart from A (no flat direction)
    assert moved_known_value(current, fit(NAMES + ["sensor_gain.x.g"], AFTER), ["A"]) == ""
    # nor where the known value is not on the ridge (k moved, A did not)
    ridge_k = fit(NAMES + ["sensor_gain.x.g"], BEFORE[:4] + [1.0e5] + BEFORE[5:] + [-0.29],
                  flat=("sensor_gain.x.g", "k"))
    assert moved_known_value(current, ridge_k, ["A"]) == ""


def test_a_known_value_that_hardly_moves_is_no_objection():
    """On the ridge but moved by less than KNOWN_MOVE_REL: the effect is
    determined with the value where the user put it."""
    current = fit(NAMES, BEFORE)
    small = list(BEFORE) + [-0.01]
    small[2] = BEFORE[2] * (1 - 0.5 * KNOWN_MOVE_REL)
    after = fit(NAMES + ["sensor_gain.x.g"], small, flat=("sensor_gain.x.g", "A"))
    assert moved_known_value(current, after, ["A"]) == ""
    small[2] = BEFORE[2] * (1 - 2 * KNOWN_MOVE_REL)
    assert "A 0.002 -> 0.0018 (-10%)" in moved_known_value(
        current, fit(NAMES + ["sensor_gain.x.g"], small, flat=("sensor_gain.x.g", "A")), ["A"])

"""The discretisation guard of the likelihood (bondgraph.inference.ukf.nll_guard)
and its warning at the estimate.

Reference: independent ukf_nll runs with RK4(40) and with the filter's
method at the reported number of sub-steps.
"""

import sys
from pathlib import Path

import numpy as np
import pytest

from bondgraph.errors import IdentifiabilityWarning
from bondgraph.inference.estimate import _guard_message
from bondgraph.inference.options import UKFOptions
from bondgraph.inference.ukf import GUARD_REL, nll_guard, ukf_nll
from bondgraph.numerics.model import Model

sys.path.insert(0, str(Path(__file__).parent))
from test_ukf_numba import _record  # noqa: E402


def _nll(m, t, u, y, th, **kw):
    return float(ukf_nll(m, t, u, y, th, options=UKFOptions(**kw)).nll[0])


def test_guard_flags_a_coarse_step_and_finds_the_substeps():
    """vehicle_full at 40 Hz with ROS2(1): far from RK4(40); the reported
    sub-steps agree within 1e-3 and half of them do not."""
    m = Model.load("vehicle_full")
    t, u, y = _record(m, N=400, dt=0.025, substeps=40)
    g = nll_guard(m, t, u, y, m.theta0, options=UKFOptions())
    ref = _nll(m, t, u, y, m.theta0, method="rk4", substeps=40)
    coarse = _nll(m, t, u, y, m.theta0)
    assert g["nll_reference"] == pytest.approx(ref, rel=1e-12)
    assert g["nll"] == pytest.approx(coarse, rel=1e-12)
    assert g["rel_diff"] == pytest.approx(abs(coarse - ref) / abs(ref), rel=1e-9)
    assert not g["ok"] and g["rel_diff"] > GUARD_REL
    s = g["substeps_needed"]
    assert s is not None and s > 1
    assert abs(_nll(m, t, u, y, m.theta0, substeps=s) - ref) <= GUARD_REL * abs(ref)
    assert abs(_nll(m, t, u, y, m.theta0, substeps=s // 2) - ref) > GUARD_REL * abs(ref)
    msg = _guard_message(g, UKFOptions())
    assert f"needs {s} substeps" in msg and "ros2(1)" in msg


def test_guard_passes_a_fine_step():
    """A slow, non-stiff model at 100 Hz with ROS2(1): within 1e-3, nothing tried."""
    m = Model.load("mass_spring_damper")
    t, u, y = _record(m, N=300, dt=0.01)
    g = nll_guard(m, t, u, y, m.theta0, options=UKFOptions())
    assert g["ok"] and g["substeps_needed"] is None and g["tried"] == {}
    ref = _nll(m, t, u, y, m.theta0, method="rk4", substeps=40)
    assert g["rel_diff"] == pytest.approx(abs(g["nll"] - ref) / abs(ref), rel=1e-9)
    assert g["rel_diff"] <= GUARD_REL


def test_estimate_warns_with_the_substeps_needed():
    """estimate() on a coarse ROS2(1) filter of vehicle_full: the result's
    settings carry the guard and an IdentifiabilityWarning names the substeps."""
    from bondgraph.inference.estimate import estimate
    from bondgraph.inference.options import FitOptions
    from bondgraph.inference.prior import PriorSpec
    from bondgraph.inference.problem import make_problem

    m = Model.load("vehicle_full")
    t, u, y = _record(m, N=400, dt=0.025, substeps=40)
    params = [m.params[0]]
    with pytest.warns(IdentifiabilityWarning, match="substeps to agree"):
        res = estimate(make_problem(m, (t, u, y), prior=PriorSpec(scale="magnitude")), params,
                       fit=FitOptions(particles=6, iterations=2, seed=1, polish=False,
                                      progress=False))
    g = res.settings["discretisation"]["nll_guard"]
    assert not g["ok"] and g["substeps_needed"] >= 2
    assert np.isfinite(g["nll_reference"])

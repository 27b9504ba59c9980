"""Signs of life on long passes (issue 13, item 7): bondgraph.core.progress."""

from __future__ import annotations

import itertools
from types import SimpleNamespace

import numpy as np

from bondgraph.core import progress
from bondgraph.data.experiments import run_experiment
from bondgraph.inference.options import UKFOptions
from bondgraph.inference.record import record_arrays
from bondgraph.inference.ukf import default_P0, ukf_nll
from bondgraph.numerics.model import Model


def test_bar_appears_only_when_enabled_and_says_what_and_how_far(capsys):
    assert list(progress.long_range(500, "work: 500 items", delay=0.0, every=1)) == list(range(500))
    assert capsys.readouterr().err == ""                     # off by default in the library
    with progress.enabled():
        assert sum(progress.long_range(500, "work: 500 items", delay=0.0, every=1)) == 124750
    err = capsys.readouterr().err
    assert "work: 500 items" in err and "/500" in err


def test_short_passes_print_nothing(capsys):
    with progress.enabled():
        list(progress.long_range(500, "quick", delay=60.0, every=1))
    assert capsys.readouterr().err == ""


def test_a_long_ukf_pass_shows_a_bar_naming_the_pass(monkeypatch, capsys):
    """The filter's sample loop reports as a long pass once it has run for the
    delay (the clock is made to run fast here); the NLL is unchanged. The
    numpy filter's sample loop is the one that reports (the fused numba kernel
    runs a whole pass in one call)."""
    model = Model.load("mass_spring_damper")
    t, u, y, _, _ = record_arrays(model, run_experiment("msd_force_step").segment(0, 400))
    x0 = np.zeros(model.n_x)
    args = (model, t, u, y, model.theta0[None, :], x0, default_P0(model, x0))
    quiet = ukf_nll(*args, options=UKFOptions(method="rk4", backend="numpy"))
    capsys.readouterr()
    clock = itertools.count(0.0, 10.0)                       # 10 s per look at the clock
    monkeypatch.setattr(progress, "time", SimpleNamespace(monotonic=lambda: next(clock)))
    with progress.enabled():
        loud = ukf_nll(*args, options=UKFOptions(method="rk4", backend="numpy"))
    err = capsys.readouterr().err
    assert "UKF pass: 1 parameter sets x 400 samples" in err
    assert np.isfinite(quiet.nll).all()
    np.testing.assert_array_equal(quiet.nll, loud.nll)


def test_a_long_compile_is_announced_and_a_short_one_is_silent(capsys):
    """`announced` prints what runs once it has run ``delay`` s, and how long
    it took; nothing for a short block or with bars switched off."""
    import time

    from bondgraph.core import progress

    with progress.enabled():
        with progress.announced("compiling X", delay=0.1, note="once"):
            time.sleep(0.4)
        err = capsys.readouterr().err.splitlines()
        assert err[0] == "  ... compiling X (once)"
        assert err[1].startswith("  ... compiling X: done in ")
        with progress.announced("compiling Y", delay=0.5):
            time.sleep(0.05)
        assert capsys.readouterr().err == ""
    with progress.announced("compiling Z", delay=0.05):
        time.sleep(0.2)
    assert capsys.readouterr().err == ""

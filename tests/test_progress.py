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


def test_bar_appears_only_when_enabled_and_says_what_and_how_far(monkeypatch, capsys):
    monkeypatch.setattr(progress, "_is_terminal", lambda stream: True)   # as on a terminal
    assert list(progress.long_range(500, "work: 500 items", delay=0.0, every=1)) == list(range(500))
    assert capsys.readouterr().err == ""                     # off by default in the library
    with progress.enabled():
        assert sum(progress.long_range(500, "work: 500 items", delay=0.0, every=1)) == 124750
    err = capsys.readouterr().err
    assert "work: 500 items" in err and "/500" in err


def test_off_a_terminal_a_bar_leaves_no_text(capsys):
    """In a pipe or log file (pytest's capture is neither a terminal) a bar
    would leave each redraw behind as text; it is not drawn there, the
    iteration is unchanged, and the watchdog speaks for a silent phase."""
    with progress.enabled():
        assert sum(progress.long_range(500, "work: 500 items", delay=0.0, every=1)) == 124750
    assert list(progress.bar(range(3), desc="structural candidates")) == [0, 1, 2]
    assert capsys.readouterr().err == ""


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
    monkeypatch.setattr(progress, "_is_terminal", lambda stream: True)   # as on a terminal
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


class _Terminal:
    """A stream that says it is a terminal and keeps what is written."""

    def __init__(self):
        import threading
        self.text, self.lock = "", threading.Lock()

    def isatty(self):
        return True

    def write(self, s):
        with self.lock:
            self.text += s

    def flush(self):
        pass


def test_a_slow_compile_shows_a_live_elapsed_bar_on_a_terminal(capsys):
    """Issue 30: on a terminal the announcement of a compile is a bar whose
    elapsed time is refreshed while the compile blocks (the fake compile
    waits until the bar has been redrawn several times), then removed, and
    the duration printed; the line names what is compiled."""
    import threading

    from bondgraph.core import progress

    term, released = _Terminal(), threading.Event()

    def slow_compile():
        guard = 600                                   # a hung thread, not a timing test
        while term.text.count("\r") < 4 and guard:
            guard -= 1
            released.wait(0.05)
        return term.text.count("\r")

    with progress.enabled():
        with progress.announced("compiling the fused UKF kernel", delay=0.0, note="once",
                                stream=term, tick=0.01):
            redraws = slow_compile()
    assert redraws >= 4, term.text
    lines = [ln for ln in term.text.replace("\r", "\n").splitlines() if ln.strip()]
    live = [ln for ln in lines if "elapsed" in ln]
    assert live and all(ln.startswith("  ... compiling the fused UKF kernel (once): ")
                        for ln in live)
    assert {ln.rsplit(": ", 1)[1] for ln in live} <= {f"00:{s:02d} elapsed" for s in range(60)}
    assert lines[-1].startswith("  ... compiling the fused UKF kernel: done in ")
    assert capsys.readouterr().err == ""              # all of it on the given stream


def test_a_compile_announced_to_a_file_is_one_line_without_redraws(tmp_path):
    import time

    from bondgraph.core import progress

    log = tmp_path / "log.txt"
    with open(log, "w") as fh, progress.enabled():
        with progress.announced("compiling K", delay=0.0, stream=fh, tick=0.01):
            guard = 600                               # until announced (no timing test)
            while not log.read_text() and guard:
                guard -= 1
                time.sleep(0.05)
    text = log.read_text()
    assert "\r" not in text
    assert text.splitlines() == ["  ... compiling K", text.splitlines()[1]]
    assert text.splitlines()[1].startswith("  ... compiling K: done in ")


def test_a_long_compile_off_a_terminal_shows_a_dot_per_heartbeat(tmp_path):
    """Off a terminal the announcement stays one line (no carriage
    returns), and a dot is appended every ``heartbeat`` seconds while the
    block runs, so a pipe is never silent for longer; the line ends when the
    block does, then the "done" line follows."""
    import re
    import time

    from bondgraph.core import progress

    log = tmp_path / "log.txt"
    with open(log, "w") as fh, progress.enabled():
        with progress.announced("compiling H", delay=0.0, stream=fh, heartbeat=0.01):
            guard = 600                               # until three dots (no timing test)
            while log.read_text().count(".") < 3 + 3 and guard:
                guard -= 1
                time.sleep(0.05)
    lines = log.read_text().splitlines()
    assert "\r" not in log.read_text() and len(lines) == 2
    assert re.fullmatch(r"  \.\.\. compiling H( \.){3,}", lines[0]), lines[0]
    assert lines[1].startswith("  ... compiling H: done in ")


def test_the_watchdog_names_the_phase_of_a_silent_stretch_and_stays_quiet_otherwise(capsys):
    """Bars on: after quiet_after seconds without output, one stderr line
    names the innermost phase and its age; output in between (a log line)
    resets the clock; an announced compile, once its line shows, keeps it
    quiet (its own dots); bars off, nothing; stdout and stderr are the
    originals afterwards."""
    import re
    import sys
    import time

    out0, err0 = sys.stdout, sys.stderr
    with progress.enabled(), progress.watchdog(quiet_after=0.5, poll=0.02):
        with progress.phase("step 1: scoring the candidates"):
            time.sleep(0.75)                        # one line at 0.5 s
            print("a log line")
            time.sleep(0.3)                         # < 0.5 s since the log line: none
        with progress.announced("compiling X", delay=0.05, heartbeat=0.2):
            time.sleep(1.2)                         # announced, its dots: none
    assert (sys.stdout, sys.stderr) == (out0, err0)
    got = capsys.readouterr()
    assert got.out == "a log line\n"
    lines = got.err.splitlines()
    assert re.fullmatch(r"  \.\.\. step 1: scoring the candidates \([01] s\)", lines[0]), got.err
    assert lines[1].startswith("  ... compiling X . .")           # its dots, no watchdog line
    assert lines[2] == "  ... compiling X: done in 1 s" and len(lines) == 3, got.err
    with progress.enabled(False), progress.watchdog(quiet_after=0.1, poll=0.02):
        time.sleep(0.3)
    assert capsys.readouterr().err == ""


def test_loading_a_slow_command_module_is_not_silent(monkeypatch, capsys):
    """The command's module loads numpy, scipy, sympy and numba before any
    line of its own (2.6 s on the bundled loop of a slow day): the watchdog
    covers that stretch and names it; ``--quiet`` keeps it silent."""
    import importlib
    import re
    import time

    from bondgraph.cli import main as cli

    real = importlib.import_module

    def slow(name, *a):
        if name == "bondgraph.cli.models":
            time.sleep(2.6)
        return real(name, *a)

    monkeypatch.setattr(cli.importlib, "import_module", slow)
    assert cli.main(["models"]) == 0
    err = capsys.readouterr().err
    # the phase's age as the watchdog sees it (2 s; 1 s when a loaded machine
    # let the watchdog's clock start late)
    assert re.search(r"\.\.\. loading the models command \(numpy, scipy, sympy, numba\) "
                     r"\([12] s\)", err), err
    monkeypatch.setattr(cli, "command_parser", lambda cmd: (_ for _ in ()).throw(SystemExit(0)))
    try:
        cli.main(["models", "--quiet"])
    except SystemExit:
        pass
    assert "loading" not in capsys.readouterr().err


def test_a_long_silent_phase_keeps_one_line_and_adds_dots(capsys):
    """Off a terminal the watchdog's line for one long phase grows by a dot
    per silent stretch instead of a new line per stretch (a user's EMPS loop
    wrote 400 such lines); another phase starts a new line, other output
    ends the open line first, and the block's end ends it too."""
    import re
    import time

    with progress.enabled(), progress.watchdog(quiet_after=0.2, poll=0.02):
        with progress.phase("step 2: confirming"):
            time.sleep(1.0)                         # a line, then about 3 dots
            with progress.phase("a refit"):
                time.sleep(0.5)                     # a new line
            print("a log line")                     # ends it
            time.sleep(0.5)                         # the outer phase again: a new line
    got = capsys.readouterr()
    assert got.out == "a log line\n"
    lines = got.err.splitlines()
    assert len(lines) == 3, got.err
    assert re.fullmatch(r"  \.\.\. step 2: confirming \([01] s\)( \.){1,6}", lines[0]), lines[0]
    assert re.fullmatch(r"  \.\.\. a refit \([01] s\)( \.){0,3}", lines[1]), lines[1]
    assert re.fullmatch(r"  \.\.\. step 2: confirming \([12] s\)( \.)*", lines[2]), lines[2]
    assert got.err.endswith("\n")


def test_the_estimation_names_each_of_its_stages_for_the_watchdog(monkeypatch):
    """``estimate`` runs its stages inside named phases, so a log or a pipe
    reads what a long stretch is doing instead of "working" (a user's EMPS
    estimate: 110 s of "... working" while the swarm ran): the start's
    noise levels, the global search with its population and iterations
    (10 k particles by default), the polish, the Hessian, the check at the
    estimate, in that order."""
    import warnings

    import numpy as np

    from bondgraph.errors import IdentifiabilityWarning
    from bondgraph.inference.estimate import estimate, search_text
    from bondgraph.inference.options import FitOptions, UKFOptions
    from bondgraph.inference.prior import PriorSpec
    from bondgraph.inference.problem import NoiseSpec, make_problem
    from bondgraph.numerics.model import Model

    entered = []
    real = progress.phase

    def recording(what):
        entered.append(what)
        return real(what)
    monkeypatch.setattr(progress, "phase", recording)
    m = Model.load("mass_spring_damper")
    t = np.arange(120) * 0.02
    u = np.repeat(np.random.default_rng(1).normal(0.0, 20.0, 6), 20)[:, None]
    y = np.zeros((t.size, m.n_y))           # the stages, not the numbers, are tested
    pb = make_problem(m, (t, u, y), prior=PriorSpec(P0=np.diag([1e-8, 1e-10])),
                      noise=NoiseSpec("auto"), ukf=UKFOptions(method="rk4", substeps=1))
    fit = FitOptions(iterations=2, seed=0, progress=False)
    with warnings.catch_warnings():         # a record of zeros: its fit's warnings are not tested
        warnings.simplefilter("ignore", IdentifiabilityWarning)
        estimate(pb, ["k", "c"], fit=fit)
    k = 2 + m.n_y                           # k, c and each output's noise level
    assert search_text(fit, k) == (f"global search over {k} quantities (particle swarm, "
                                   f"{10 * k} particles, up to 2 iterations)")
    assert search_text(FitOptions(optimizer="de", iterations=0), 3) == (
        "global search over 3 quantities (differential evolution, 30 members, its first "
        "population only)")
    assert entered == ["profiling the start's noise levels", search_text(fit, k),
                       "polishing the search's best point (Fisher scoring, then L-BFGS-B)",
                       "the Hessian and the standard errors at the estimate",
                       "checking the filter's discretisation at the estimate"], entered

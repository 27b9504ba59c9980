"""The short examples in examples/ run as a user runs them (a fresh process in
an empty folder), and print what their docstrings promise. The long ones
(estimate_emps.py: the EMPS record and a PSO; silverbox_user.py: a whole loop
on Silverbox) are not run here: tests/test_loop.py runs their cases."""

import re
import subprocess
import sys
from pathlib import Path

import pytest

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"


def _run(name, cwd):
    r = subprocess.run([sys.executable, str(EXAMPLES / name)], cwd=cwd, capture_output=True,
                       text=True, timeout=600)
    assert r.returncode == 0, r.stderr
    return r.stdout


def test_quickstart_reaches_the_hand_derived_steady_state(tmp_path):
    out = _run("quickstart.py", tmp_path)
    got, steady = map(float, re.search(r"speed at 3 s: ([\d.]+) rad/s \(steady state ([\d.]+)",
                                       out).groups())
    assert got == pytest.approx(steady, rel=1e-3)
    assert (tmp_path / "quickstart_out" / "quickstart_motor.py").exists()


def test_track_user_graph_finds_the_damping_step(tmp_path):
    """The example doubles the damping (1.5 -> 3.0) at 30 s."""
    out = _run("track_user_graph.py", tmp_path)
    m = re.search(r"change of c at t = ([\d.]+) s \(alarm ([\d.]+) s\): ([\d.]+) ± ([\d.]+) -> "
                  r"([\d.]+) ± ([\d.]+)", out)
    t, alarm, before, sb, after, sa = map(float, m.groups())
    assert 30.0 <= t <= 31.0 and t <= alarm <= 35.0
    assert abs(before - 1.5) <= 3 * sb + 1e-3 and abs(after - 3.0) <= 3 * sa + 1e-3

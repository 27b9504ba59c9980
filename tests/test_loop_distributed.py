"""The loop's candidates on Dask workers (bondgraph.diagnose.parallel): the
structural candidates' scoring and the confirmation refits run one task per
candidate on a 2-worker LocalCluster, and the loop's ranking, confirmations,
decision and final fit are identical to the serial run's, bit for bit
(every task depends only on the current fit, the record and its candidate;
results come back in the order of the tasks). The runs use the numpy
backend to spare the workers the candidates' compilation; the numba backend
is as deterministic (taken literally, whatever the kernel cache holds:
tests/test_ukf_numba.py::test_backend_is_taken_literally_whatever_the_history_or_the_cache)."""

import numpy as np
import pytest
from dask.distributed import LocalCluster

from bondgraph.catalog.reference import mass_spring_damper
from bondgraph.diagnose.cases import SimulationOptions, synthesize
from bondgraph.diagnose.effects import apply_effect, get_effect
from bondgraph.diagnose.loop import LoopSettings, run_loop
from bondgraph.inference.options import Evaluation
from bondgraph.diagnose.settings import SearchOptions
from bondgraph.errors import OptionError
from bondgraph.inference.options import UKFOptions

EFFECTS = ["cubic_stiffness", "end_stop", "coulomb", "sensor_gain"]


def _record():
    truth = mass_spring_damper()
    eff = get_effect("cubic_stiffness")
    apply_effect(truth, eff, eff.targets(truth)[0], {"k3": 400.0})
    levels = np.random.default_rng(2).normal(0, 20, 20)
    t = np.arange(400) * 0.01
    return synthesize(truth, mass_spring_damper(), t,
                      {"F": lambda tt: levels[np.minimum((np.asarray(tt) / 0.2).astype(int),
                                                         19)]},
                      {}, {"m": 2.0, "k": 50.0, "c": 1.5}, 11, "cubic", "",
                      simulation=SimulationOptions(hold="zoh", method="rk4", substeps=10))


def _run(scheduler=None):
    logs = []
    res = run_loop(mass_spring_damper(), _record(), LoopSettings(params=["m", "k", "c"], effects=[get_effect(e) for e in EFFECTS], ukf=UKFOptions(method="ros2", substeps=2, backend="numpy"), search=SearchOptions(max_steps=1), evaluation=Evaluation(scheduler=scheduler)), log=logs.append, progress=False)
    return res, logs


def _summary(res):
    ranks = [[(c.label, c.statistic, c.confirmed_statistic, tuple(c.tied))
              for c in r] for r in res.rankings]
    return ranks, [(s.effect, s.attached_to, s.nll_after) for s in res.steps], \
        res.final.nll, res.final.estimates


# 70 s cold: in pytest -m long; the executor's own two-worker equality
# (tests/test_executor.py) stays in the default run
@pytest.mark.long
def test_loop_on_two_workers_equals_serial():
    serial, logs = _run()
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                      dashboard_address=None, env={"NUMBA_NUM_THREADS": "1"}) as cluster:
        dist, dlogs = _run(scheduler=cluster.scheduler_address)
    assert any("on the Dask workers" in line for line in dlogs)
    assert not any("on the Dask workers" in line for line in logs)
    # the truth is found, and everything the loop decided is the same
    assert [(s.effect, s.attached_to) for s in serial.steps] == [("cubic_stiffness", "spring")]
    assert _summary(dist) == _summary(serial)
    # the workers' log lines come back (the confirmations' lines, in order)
    conf = [line.split("] ", 1)[-1] for line in logs if "confirmed " in line]
    dconf = [line.split("] ", 1)[-1] for line in dlogs if "confirmed " in line]
    assert conf and conf == dconf


def test_bad_scheduler_and_workers_fail_before_any_fit():
    with pytest.raises(OptionError, match="scheduler"):
        run_loop(mass_spring_damper(), _record(), LoopSettings(params=["k"], evaluation=Evaluation(scheduler="localhost:8786")), log=lambda s: None, progress=False)
    with pytest.raises(OptionError, match="workers"):
        run_loop(mass_spring_damper(), _record(), LoopSettings(params=["k"], evaluation=Evaluation(workers=0)), log=lambda s: None, progress=False)

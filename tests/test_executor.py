"""The Dask executor of batched likelihood evaluations
(bondgraph.inference.executor, bondgraph.inference.estimate.Criterion).

Reference: the serial in-process evaluation; results must be identical
(bit for bit) on a 2-worker LocalCluster, on the embedded cluster, and for
any chunking.
"""

import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from dask.distributed import LocalCluster

from bondgraph.errors import OptionError
from bondgraph.inference.estimate import Criterion, _chunks
from bondgraph.inference.executor import SCHEDULER_ENV, Executor
from bondgraph.inference.options import Evaluation, UKFOptions
from bondgraph.inference.prior import PriorSpec
from bondgraph.inference.problem import make_problem
from bondgraph.numerics.model import Model

sys.path.insert(0, str(Path(__file__).parent))
from test_ukf_numba import _record, box_sets  # noqa: E402


@pytest.fixture(scope="module")
def cluster():
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                      dashboard_address=None, env={"NUMBA_NUM_THREADS": "1"}) as c:
        yield c


def _criterion(m, backend, **kw):
    """The criterion of 3 parameters on a short record; ``kw``: the
    :class:`Evaluation` fields (chunk, workers, scheduler)."""
    t, u, y = _record(m, N=80)
    params = list(m.params[:3])
    pb = make_problem(m, (t, u, y), prior=PriorSpec(scale="magnitude"),
                      ukf=UKFOptions(backend=backend))
    return Criterion(pb, params, m.theta0, where=Evaluation(**kw))


def _X(m, n=21):
    th = box_sets(m, n, seed=4)
    th[5, 0] = -th[5, 0]                      # some sets fail: same failures expected
    return th[:, :3]


@pytest.mark.parametrize("backend", ["numba", "numpy"])
def test_two_worker_cluster_equals_serial(cluster, backend):
    m = Model.load("vehicle_coastdown")
    X = _X(m)
    serial = _criterion(m, backend)
    ref = serial(X)
    dist = _criterion(m, backend, scheduler=cluster.scheduler_address)
    assert dist._executor.distributed
    got = dist(X)
    got2 = dist(X[:7])                          # the criterion is sent once, reused
    dist.close()
    np.testing.assert_array_equal(got, ref)
    np.testing.assert_array_equal(got2, ref[:7])
    assert dist.failures == serial.failures + _criterion(m, backend)._evaluate(X[:7])[1]
    assert dist.evaluations == 28 and dist.calls == 2


def test_in_memory_model_on_the_cluster(cluster):
    """A module:function model (generated in memory) travels to the workers."""
    m = Model.from_spec("bondgraph.catalog.reference:mass_spring_damper")
    X = _X(m, n=9)
    ref = _criterion(m, "numpy")(X)
    dist = _criterion(m, "numpy", scheduler=cluster.scheduler_address, chunk=2)
    got = dist(X)
    dist.close()
    np.testing.assert_array_equal(got, ref)


def test_scheduler_from_the_environment(cluster, monkeypatch):
    monkeypatch.setenv(SCHEDULER_ENV, cluster.scheduler_address)
    m = Model.load("mass_spring_damper")
    X = _X(m, n=6)
    dist = _criterion(m, "numba")
    assert dist._executor.scheduler == cluster.scheduler_address
    got = dist(X)
    dist.close()
    monkeypatch.delenv(SCHEDULER_ENV)
    np.testing.assert_array_equal(got, _criterion(m, "numba")(X))


def test_embedded_cluster_equals_serial():
    """workers=2 without a scheduler starts a local cluster of its own."""
    m = Model.load("dc_motor_gear")
    X = _X(m, n=10)
    emb = _criterion(m, "numba", workers=2)
    got = emb(X)
    assert emb._executor._cluster is not None
    emb.close()
    assert emb._executor._cluster is None
    np.testing.assert_array_equal(got, _criterion(m, "numba")(X))


def test_chunks_do_not_depend_on_what_is_evaluated():
    X = np.arange(40.0).reshape(20, 2)
    for workers in (1, 2, 5):
        parts = _chunks(X, None, workers)
        np.testing.assert_array_equal(np.concatenate(parts), X)
    assert [len(p) for p in _chunks(X, 6, 2)] == [6, 6, 6, 2]


def test_bad_scheduler_addresses(monkeypatch):
    with pytest.raises(OptionError, match="not a Dask scheduler address"):
        Executor(scheduler="localhost:8786")
    monkeypatch.setenv(SCHEDULER_ENV, "nonsense")
    with pytest.raises(OptionError, match=SCHEDULER_ENV):
        Executor()
    with pytest.raises(OptionError):
        Executor(workers=0)
    monkeypatch.delenv(SCHEDULER_ENV)
    assert not Executor().distributed and Executor(workers=2).distributed


@pytest.mark.parametrize("cmd", ["estimate", "sensitivity", "loop"])
def test_cli_backend_option(cmd):
    """`--backend` is declared once (cli/common.add_backend) on every command
    that evaluates a likelihood; `--workers` and `--scheduler` on estimate,
    sensitivity and loop."""
    import argparse
    import importlib

    mod = importlib.import_module(f"bondgraph.cli.{cmd}")
    p = argparse.ArgumentParser()
    mod.configure(p)
    base = {"estimate": ["--model", "m", "--data", "d.csv", "--params", "a"],
            "sensitivity": ["--model", "m", "--data", "d.csv"], "loop": []}[cmd]
    try:
        args = p.parse_args(base + ["--backend", "numpy"])
    except SystemExit:  # a command with other required options
        pytest.skip(f"{cmd}: other required options")
    assert args.backend == "numpy"
    assert p.parse_args(base).backend == UKFOptions().backend
    # --workers and --scheduler on every command that runs work on Dask workers
    args = p.parse_args(base + ["--scheduler", "tcp://h:1", "--workers", "3"])
    assert args.scheduler == "tcp://h:1" and args.workers == 3


def _msd_csv(tmp_path):
    """A short mass-spring-damper record as a CSV file (t, F, x, v)."""
    csv = tmp_path / "r.csv"
    m = Model.load("mass_spring_damper")
    t, u, y = _record(m, N=20)
    rows = ["t,F,x,v"] + [f"{t[k]},{u[k, 0]},{y[k, 0]},{y[k, 1]}" for k in range(t.size)]
    csv.write_text("\n".join(rows).replace("nan", ""))
    return csv


def test_cli_sensitivity_passes_and_checks_the_executor_options(tmp_path, monkeypatch):
    """sensitivity hands --workers/--scheduler to the analysis's Sobol'
    options, and a bad value stops it before any work."""
    from bondgraph.cli import sensitivity as cli_sens
    from bondgraph.cli.main import main

    seen = {}

    def fake(problem, params, *, sobol, **kw):
        seen.update(workers=sobol.workers, scheduler=sobol.scheduler)
        raise OptionError("stop here")
    monkeypatch.setattr(cli_sens, "analyse", fake)
    csv = _msd_csv(tmp_path)
    base = ["sensitivity", "--model", "mass_spring_damper", "--data", str(csv), "--quiet",
            "--global", "8"]
    assert main(base + ["--workers", "2", "--scheduler", "tcp://127.0.0.1:9",
                        "--out", str(tmp_path / "a")]) != 0
    assert seen == dict(workers=2, scheduler="tcp://127.0.0.1:9")
    seen.clear()
    assert main(base + ["--workers", "0", "--out", str(tmp_path / "b")]) != 0
    assert main(base + ["--scheduler", "h:1", "--out", str(tmp_path / "c")]) != 0
    assert seen == {}


def test_cli_estimate_runs_on_the_numpy_backend(tmp_path, monkeypatch):
    """The estimate command hands --backend and --scheduler to the options."""
    from bondgraph.cli import estimate as cli_estimate

    seen = {}

    def fake(problem, params, *, fit, **kw):
        seen.update(backend=problem.ukf.backend, scheduler=fit.scheduler, workers=fit.workers)
        raise OptionError("stop here")
    monkeypatch.setattr(cli_estimate, "estimate", fake)
    from bondgraph.cli.main import main
    csv = _msd_csv(tmp_path)
    rc = main(["estimate", "--model", "mass_spring_damper", "--data", str(csv), "--params", "m",
               "--backend", "numpy", "--scheduler", "tcp://127.0.0.1:9", "--workers", "2",
               "--out", str(tmp_path / "o"), "--quiet"])
    assert rc != 0 and seen == dict(backend="numpy", scheduler="tcp://127.0.0.1:9", workers=2)


def test_sobol_sample_on_the_cluster_equals_serial(cluster):
    """The Sobol' sample's chunks on a 2-worker cluster: the NLL values and
    the indices are the serial run's, bit for bit."""
    from bondgraph.sensitivity.sobol import global_sensitivity

    m = Model.load("mass_spring_damper")
    t, u, y = _record(m, N=60)
    from bondgraph.sensitivity.sobol import SobolOptions

    pb = make_problem(m, (t, u, y), prior=PriorSpec(scale="magnitude", x0=np.zeros(m.n_x)),
                      ukf=UKFOptions(backend="numba"))
    o = SobolOptions(N=8, chunk=8, box_rel=0.3, seed=3)
    ref = global_sensitivity(pb, ["m", "k", "c"], o)
    got = global_sensitivity(pb, ["m", "k", "c"], replace(o, scheduler=cluster.scheduler_address))
    assert got["evaluations"] == ref["evaluations"] == 8 * (2 * 3 + 2)
    for key in ("S1", "ST", "S2"):
        np.testing.assert_array_equal(got["indices"]["NLL"][key], ref["indices"]["NLL"][key])
    assert got["nll_min"] == ref["nll_min"] and got["nll_max"] == ref["nll_max"]

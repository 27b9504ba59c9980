"""The loop's tasks on threads of the process (bondgraph.diagnose.parallel.local_map):
results and log lines in the order of the tasks whatever order they finish
in, a task's exception raised at its result, the warning filters as they
were after the map, one thread run in the caller's thread."""

import threading
import time
import warnings

import pytest

from bondgraph.diagnose import parallel
from bondgraph.diagnose.fit import Context
from bondgraph.diagnose.settings import LoopSettings


def _ctx(lines):
    return Context(None, LoopSettings(params=["k"]), log=lines.append, progress=False)


def _task(ctx, item):
    delay, name = item
    time.sleep(delay)
    ctx.log(f"{name} done in {threading.current_thread().name}")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        time.sleep(delay / 2)
    return name


def test_results_and_log_lines_in_task_order_on_threads(monkeypatch):
    monkeypatch.setattr(parallel, "LOCAL_THREADS", 2)
    lines = []
    items = [(0.3, "a"), (0.0, "b"), (0.15, "c"), (0.0, "d")]
    before = list(warnings.filters)
    t0 = time.perf_counter()
    got = list(parallel.local_map(_ctx(lines), _task, items))
    wall = time.perf_counter() - t0
    assert got == ["a", "b", "c", "d"]
    assert [ln.split()[0] for ln in lines] == ["a", "b", "c", "d"]
    # two at a time: b, c, d ran while a slept (0.45 s alone; 0.675 s one by one)
    assert wall < 0.6
    assert any("bondgraph-task" in ln for ln in lines)
    assert warnings.filters == before


def test_a_task_error_is_raised_at_its_result(monkeypatch):
    monkeypatch.setattr(parallel, "LOCAL_THREADS", 2)
    lines = []

    def task(ctx, item):
        if item == 2:
            raise ValueError("task 2 failed")
        ctx.log(f"task {item}")
        return item

    it = parallel.local_map(_ctx(lines), task, [0, 1, 2, 3])
    assert next(it) == 0 and next(it) == 1
    with pytest.raises(ValueError, match="task 2 failed"):
        next(it)
    assert lines == ["task 0", "task 1"]


def test_one_thread_runs_in_the_callers_thread(monkeypatch):
    monkeypatch.setattr(parallel, "LOCAL_THREADS", 1)
    lines = []
    got = list(parallel.local_map(_ctx(lines), _task, [(0.0, "a"), (0.0, "b")]))
    assert got == ["a", "b"]
    me = threading.current_thread().name
    assert lines == [f"a done in {me}", f"b done in {me}"]

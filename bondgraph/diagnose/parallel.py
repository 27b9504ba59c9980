"""The loop's candidates on an executor: structural candidates' scoring and
confirmation refits, each one task, in process or on Dask workers
(:class:`bondgraph.inference.executor.Executor`: the embedded
``LocalCluster`` with ``workers > 1``, or an existing cluster given by
``scheduler`` / ``$BONDGRAPH_SCHEDULER``).

In process the tasks run on threads (:func:`local_map`, as many as the
filter kernel's threads): the compiled kernels release the GIL, so one
task's Python (Fisher-scoring bookkeeping, free runs, model building) runs
while another's filter runs.

Every task depends only on the current fit, the record and its own
candidate, and the results come back in the order of the tasks, so the
loop's ranking, confirmations and decisions do not depend on the number of
workers or threads or on where they ran. The tasks' log lines are replayed
in the task order.
"""

from __future__ import annotations

import warnings
from concurrent.futures import ThreadPoolExecutor
from dataclasses import replace
from typing import Any, Callable, Iterable, Sequence

from bondgraph.diagnose.fit import Context
from bondgraph.diagnose.inference_calls import kernel_threads

#: threads of :func:`local_map` (None: the filter kernel's,
#: :func:`bondgraph.inference.ukf_numba.threads`); 1 runs the tasks one
#: after the other in the caller's thread
LOCAL_THREADS: int | None = None


def _discard(_msg: str) -> None:
    """A worker's logger before its task sets one."""


def distributed(ctx: Context) -> bool:
    """Whether ``ctx``'s executor sends tasks to Dask workers."""
    ex = getattr(ctx, "executor", None)
    return ex is not None and ex.distributed


def run_tasks(ctx: Context, fn: Callable[[Context, Any, Any], Any], shared: Any,
              items: Sequence) -> list:
    """``[fn(ctx, shared, item) for item in items]`` in order, on ``ctx``'s
    executor when it is distributed (one task per item; ``shared`` and a
    portable copy of ``ctx`` sent once), else in process.

    Parameters
    ----------
    ctx : Context
    fn : callable
        A module-level function (workers import it by name).
    shared : object
        Picklable data every task reads (the current fit, the scales).
    items : sequence
        One picklable item per task.

    Returns
    -------
    list
        The results, in the order of ``items``.
    """
    if not distributed(ctx) or len(items) < 2:
        return list(local_map(ctx, lambda c, it: fn(c, shared, it), items))
    portable = replace(ctx, log=_discard, progress=False, cache={}, executor=None)
    results = ctx.executor.map(_task, (fn, portable, shared), list(items))
    out = []
    for value, lines in results:
        for line in lines:
            ctx.log(line)
        out.append(value)
    return out


def _task(packed, item):
    """One task on a worker: ``fn(ctx, shared, item)`` with the log lines
    collected."""
    fn, ctx, shared = packed
    lines: list[str] = []
    return fn(replace(ctx, log=lines.append), shared, item), lines


def local_threads() -> int:
    """Threads of :func:`local_map`: :data:`LOCAL_THREADS`, else the filter
    kernel's (numba's thread count: the machine's cores by default)."""
    return max(1, int(LOCAL_THREADS if LOCAL_THREADS is not None else kernel_threads()))


def local_map(ctx: Context, fn: Callable[[Context, Any], Any], items: Sequence) -> Iterable:
    """``fn(ctx, item)`` for every item on :func:`local_threads` threads of
    this process, the results yielded in the order of ``items`` as they are
    ready, each task's log lines (``ctx.log``) replayed before its result
    is yielded. One item, or one thread: in the caller's thread, logging
    directly.

    The warning filters are restored when the map ends (tasks that silence
    warnings with ``warnings.catch_warnings`` save and restore the
    process-wide filters; from several threads a restore may undo another
    thread's, never beyond the map's end). An exception of a task is raised
    when its result is reached (the later tasks are cancelled)."""
    n = min(local_threads(), len(items))
    if n <= 1:
        for it in items:
            yield fn(ctx, it)
        return

    def task(it):
        lines: list[str] = []
        return fn(replace(ctx, log=lines.append), it), lines

    with warnings.catch_warnings(), ThreadPoolExecutor(n, thread_name_prefix="bondgraph-task") as ex:
        futures = [ex.submit(task, it) for it in items]
        try:
            for fut in futures:
                value, lines = fut.result()
                for line in lines:
                    ctx.log(line)
                yield value
        finally:
            for fut in futures:
                fut.cancel()

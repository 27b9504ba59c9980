"""The loop's candidates on an executor: structural candidates' scoring and
confirmation refits, each one task, in process or on Dask workers
(:class:`bondgraph.inference.executor.Executor`: the embedded
``LocalCluster`` with ``workers > 1``, or an existing cluster given by
``scheduler`` / ``$BONDGRAPH_SCHEDULER``).

Every task depends only on the current fit, the record and its own
candidate, and the results come back in the order of the tasks, so the
loop's ranking, confirmations and decisions do not depend on the number of
workers or on where they ran. The workers' log lines are replayed in the
task order.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Any, Callable, Sequence

from bondgraph.diagnose.fit import Context


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
        return [fn(ctx, shared, it) for it in items]
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

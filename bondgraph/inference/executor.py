"""Where batched likelihood evaluations run: in process, on local Dask
workers, or on an existing Dask cluster.

:class:`Executor` maps a function over chunks of work and returns the
results in the order of the chunks. It runs

* in process when there is one worker and no scheduler (no Dask at all);
* on an embedded Dask ``LocalCluster`` (``workers`` processes on this
  machine, one thread each; no cluster to set up) when ``workers > 1``;
* on an existing Dask cluster when a scheduler address is given
  (``scheduler="tcp://HOST:PORT"``) or set in the environment variable
  :data:`SCHEDULER_ENV` (``BONDGRAPH_SCHEDULER``).

A cluster is started with the Dask command-line tools::

    dask scheduler                      # prints tcp://HOST:8786
    dask worker tcp://HOST:8786 --nworkers 2 --nthreads 1   # on each machine

The workers need the same installation of the toolkit (and of any
``module:function`` model code) as the client. Work is split into chunks of
a size that does not depend on the number of workers, and every parameter
set's likelihood depends only on its own data, so results never depend on
the number of workers or on where they ran.

References
----------
Rocklin, M. (2015). Dask: parallel computation with blocked algorithms and
task scheduling. Proc. 14th Python in Science Conf., 130-136.
"""

from __future__ import annotations

import os
import threading
from typing import Any, Callable, Sequence

from bondgraph.errors import OptionError

#: environment variable naming the Dask scheduler (tcp://HOST:PORT)
SCHEDULER_ENV = "BONDGRAPH_SCHEDULER"
#: environment of the embedded cluster's worker processes: one numba thread
#: each (the workers are the parallelism; no oversubscription of the cores)
LOCAL_WORKER_ENV = {"NUMBA_NUM_THREADS": "1", "OMP_NUM_THREADS": "1",
                    "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}


def scheduler_address(scheduler: str | None = None) -> str | None:
    """The scheduler to use: ``scheduler``, else ``$BONDGRAPH_SCHEDULER``,
    else None (embedded).

    Raises
    ------
    OptionError
        An address that is not ``tcp://``, ``tls://``, ``inproc://`` or
        ``ucx://`` followed by a host.
    """
    addr = scheduler if scheduler else os.environ.get(SCHEDULER_ENV) or None
    if addr is None:
        return None
    proto, sep, rest = str(addr).partition("://")
    if not sep or proto not in ("tcp", "tls", "inproc", "ucx") or not rest:
        src = "scheduler" if scheduler else f"${SCHEDULER_ENV}"
        raise OptionError(f"{src} = {addr!r} is not a Dask scheduler address "
                          f"(expected tcp://HOST:PORT)")
    return addr


class Executor:
    """Ordered map over chunks, in process or on Dask workers.

    Parameters
    ----------
    workers : int
        Worker processes of the embedded cluster (1: in process). Ignored
        when a scheduler is given (the cluster has its own workers).
    scheduler : str, optional
        Address of an existing Dask scheduler (default
        ``$BONDGRAPH_SCHEDULER``).

    Raises
    ------
    OptionError
        ``workers`` < 1 or a malformed scheduler address.
    """

    def __init__(self, workers: int = 1, scheduler: str | None = None):
        if int(workers) < 1:
            raise OptionError(f"workers = {workers} must be >= 1")
        self.workers = int(workers)
        self.scheduler = scheduler_address(scheduler)
        self._client = None
        self._cluster = None
        self._shared: dict[int, tuple[Any, Any]] = {}
        self._lock = threading.Lock()

    @property
    def distributed(self) -> bool:
        """Whether work goes to Dask workers."""
        return self.scheduler is not None or self.workers > 1

    def client(self):
        """The Dask client (started on first use; dask is imported then, not
        by every in-process run)."""
        with self._lock:
            if self._client is None:
                from dask.distributed import Client, LocalCluster

                if self.scheduler is not None:
                    self._client = Client(self.scheduler)
                else:
                    self._cluster = LocalCluster(n_workers=self.workers, threads_per_worker=1,
                                                 processes=True, dashboard_address=":0",
                                                 env=dict(LOCAL_WORKER_ENV))
                    self._client = Client(self._cluster)
            return self._client

    def map(self, fn: Callable, shared: Any, chunks: Sequence) -> list:
        """``[fn(shared, c) for c in chunks]``, in order.

        ``shared`` (e.g. a likelihood criterion) is sent to the workers once
        per executor and reused by every later call with the same object.
        """
        if not self.distributed:
            return [fn(shared, c) for c in chunks]
        client = self.client()
        key = id(shared)
        if key not in self._shared or self._shared[key][0] is not shared:
            fut = client.scatter(shared, broadcast=True, hash=False)
            self._shared[key] = (shared, fut)
        fut = self._shared[key][1]
        futures = client.map(fn, [fut] * len(chunks), list(chunks), pure=False)
        return client.gather(futures)

    def close(self) -> None:
        """Close the client and the embedded cluster (if started)."""
        with self._lock:
            self._shared.clear()
            if self._client is not None:
                self._client.close()
                self._client = None
            if self._cluster is not None:
                self._cluster.close()
                self._cluster = None

    def __getstate__(self):
        d = dict(self.__dict__)
        d.update(_client=None, _cluster=None, _shared={}, _lock=None)
        return d

    def __setstate__(self, d):
        self.__dict__.update(d)
        self._lock = threading.Lock()

"""Typed options of the filter and of the estimation search.

Frozen dataclasses, validated when they are built, so that a bad value
fails where it is written (with an :class:`~bondgraph.errors.OptionError`
naming the option and the value), not deep inside a filter run:

* :class:`UKFOptions` — the knobs of the batched UKF
  (:func:`bondgraph.inference.ukf.ukf_nll`): sigma-point scaling, the
  discretisation of the state equations between samples and the input hold.
* :class:`FitOptions` — how :func:`bondgraph.inference.estimate.estimate`
  searches (optimizer, swarm size, iterations, seed, checkpoint, polish,
  Hessian, evaluation chunks and worker processes), not what it estimates.
* :class:`Discretisation` — method, substeps, input hold and backend: the
  one value the UKF, the prior's free run and the discretisation check read.
* :class:`Evaluation` — chunk size and where a criterion's batches run.

What belongs to the *problem* (the record, the prior, the noise levels, the
fixed values) is a :class:`bondgraph.inference.problem.Problem`.
* :class:`SwarmOptions`, :class:`EvolutionOptions` and :class:`Checkpointing`
  — the settings of the global optimizers :func:`bondgraph.inference.optimize.pso`
  and :func:`bondgraph.inference.optimize.de` and of their checkpoint.
* :class:`ScoringOptions` — the iteration controls of Fisher scoring
  (:func:`bondgraph.inference.fisher.estimand_scoring`).

Results keep them as plain dicts (``dataclasses.asdict``, see
:meth:`UKFOptions.to_dict`), so JSON result files stay readable; a dict read
back is turned into options with ``UKFOptions(**d)``.
"""

from __future__ import annotations

import importlib.util
import math
import numbers
import os
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Callable, Mapping

import numpy as np

from bondgraph.errors import OptionError
from bondgraph.numerics.integrators import join_hold, split_hold

#: discretisations of the UKF's prediction (bondgraph.numerics.integrators)
UKF_METHODS = ("ros2", "rk4")
#: where ROS2 evaluates df/dx: at the central sigma point, or at every one
UKF_JACOBIANS = ("mean", "sigma")
#: input over a prediction interval: u_k, (u_k + u_k+1)/2, or the first-order
#: hold (bondgraph.numerics.integrators.hold_inputs)
UKF_HOLDS = ("zoh", "mean", "linear")
#: implementations of the UKF likelihood: the numpy reference, the fused numba kernel
UKF_BACKENDS = ("numba", "numpy")
#: the default backend: numba when it is installed
DEFAULT_BACKEND = "numba" if importlib.util.find_spec("numba") is not None else "numpy"
#: global optimizers of :func:`bondgraph.inference.estimate.estimate`
OPTIMIZERS = ("pso", "de")
#: measurement-noise policies (FitOptions.noise, NoiseSpec.mode, ``--noise``)
NOISE_MODES = ("auto", "model")
#: the prior std of each initial state relative to its scale, when nothing
#: else is said (``--p0-rel``; :class:`bondgraph.inference.prior.PriorSpec`):
#: the toolkit's one definition of that default
P0_REL = 0.05
#: the scale a prior's relative spread refers to: each state's own scale
#: along the record, or max(abs(x0), 1) (:class:`bondgraph.inference.prior.PriorSpec`)
P0_SCALES = ("state", "magnitude")
#: fewest steps per sample of the free run that gives the prior's state
#: scales (:meth:`Discretisation.for_free_run`)
FREE_RUN_MIN_SUBSTEPS = 2
#: Clerc-Kennedy constriction coefficients of the particle swarm (Clerc &
#: Kennedy 2002): the inertia w and the accelerations c1 = c2
CONSTRICTION_W = 0.7298
CONSTRICTION_C = 1.49618
#: mutation strategies of scipy's differential evolution
DE_STRATEGIES = ("best1bin", "best1exp", "rand1bin", "rand1exp", "rand2bin", "rand2exp",
                 "randtobest1bin", "randtobest1exp", "currenttobest1bin", "currenttobest1exp",
                 "best2exp", "best2bin")


def _set(obj, name: str, value) -> None:
    object.__setattr__(obj, name, value)


def _real(obj, name: str, *, positive: bool = False) -> None:
    v = getattr(obj, name)
    cls = type(obj).__name__
    if isinstance(v, bool) or not isinstance(v, numbers.Real) or not math.isfinite(v):
        raise OptionError(f"{cls}.{name} must be a finite number, got {v!r}")
    if positive and v <= 0:
        raise OptionError(f"{cls}.{name} must be > 0, got {v!r}")
    _set(obj, name, float(v))


def _integer(obj, name: str, minimum: int, *, optional: bool = False) -> None:
    v = getattr(obj, name)
    if v is None and optional:
        return
    cls = type(obj).__name__
    if isinstance(v, bool) or not isinstance(v, numbers.Integral) or v < minimum:
        raise OptionError(f"{cls}.{name} must be an integer >= {minimum}"
                          f"{' or None' if optional else ''}, got {v!r}")
    _set(obj, name, int(v))


def _choice(obj, name: str, choices: tuple[str, ...]) -> None:
    v = getattr(obj, name)
    if v not in choices:
        raise OptionError(f"{type(obj).__name__}.{name} = {v!r} is not one of "
                          f"{', '.join(repr(c) for c in choices)}")


def _flag(obj, name: str) -> None:
    v = getattr(obj, name)
    if not isinstance(v, bool):
        raise OptionError(f"{type(obj).__name__}.{name} must be True or False, got {v!r}")

def _discretisation_fields(obj) -> None:
    """Check method, substeps, hold and backend of ``obj`` (one rule for
    :class:`Discretisation` and :class:`UKFOptions`)."""
    _choice(obj, "method", UKF_METHODS)
    _integer(obj, "substeps", 1)
    try:
        _set(obj, "hold", join_hold(split_hold(obj.hold)))      # canonical: "zoh, zoh" -> "zoh"
    except OptionError as e:
        raise OptionError(f"{type(obj).__name__}.hold: {e}") from None
    _choice(obj, "backend", UKF_BACKENDS)
    if obj.backend == "numba" and importlib.util.find_spec("numba") is None:
        raise OptionError(f"{type(obj).__name__}.backend = 'numba' but numba is not installed "
                          f"(pip install numba, or backend='numpy')")
    _set(obj, "refine", _refine_runs(type(obj).__name__, obj.refine))


def _refine_runs(owner: str, runs) -> tuple:
    """``runs`` as a canonical tuple of ``(start, stop, substeps)`` int
    triples, sorted, each ``0 <= start < stop`` and ``substeps >= 1``, not
    overlapping.

    Raises
    ------
    OptionError
        Any other value (named).
    """
    out = []
    try:
        for r in runs or ():
            a, b, n = (int(v) for v in r)
            if not (len(r) == 3 and 0 <= a < b and n >= 1
                    and all(float(v) == int(v) for v in r)):
                raise ValueError
            out.append((a, b, n))
    except (TypeError, ValueError):
        raise OptionError(f"{owner}.refine = {runs!r} must be (start, stop, substeps) triples "
                          f"of integers, 0 <= start < stop, substeps >= 1") from None
    out.sort()
    if any(p[1] > q[0] for p, q in zip(out, out[1:])):
        raise OptionError(f"{owner}.refine: the runs {out!r} overlap")
    return tuple(out)


def interval_substeps(obj, intervals: int) -> np.ndarray:
    """The substeps of each of ``intervals`` sample intervals (intervals,)
    int64 of a :class:`Discretisation` or :class:`UKFOptions` ``obj``:
    ``substeps``, and in a run of ``refine`` the larger of it and the run's.

    Raises
    ------
    OptionError
        A run beyond the record's last interval (a refinement made for
        another record).
    """
    out = np.full(max(int(intervals), 0), obj.substeps, dtype=np.int64)
    for a, b, n in obj.refine:
        if b > out.size:
            raise OptionError(f"the refined substeps {n} on intervals {a}..{b - 1} reach beyond "
                              f"the record's {out.size} intervals: they were chosen for another "
                              f"record")
        np.maximum(out[a:b], n, out=out[a:b])
    return out


def most_substeps(obj) -> int:
    """The largest substeps of any interval of ``obj`` (``substeps`` and
    its refined runs)."""
    return max([obj.substeps] + [n for _, _, n in obj.refine])


def refine_text(obj) -> str:
    """``", 4 on 12 of the intervals (3 runs)"``: the refinement of
    ``obj`` for log lines ("" without one)."""
    runs = [r for r in obj.refine if r[2] > obj.substeps]
    if not runs:
        return ""
    counts = sorted({n for _, _, n in runs})
    k = sum(b - a for a, b, _ in runs)
    return (f"; {'/'.join(map(str, counts))} on {k} intervals "
            f"({len(runs)} run{'s' if len(runs) > 1 else ''})")


@dataclass(frozen=True)
class Discretisation:
    """How the state equations are stepped between two samples: the one
    value that the UKF (:class:`UKFOptions`), the prior's free run
    (:func:`bondgraph.inference.prior.simulated_rms`), the discretisation
    check (:func:`bondgraph.inference.ukf.discretisation_check`) and the batch
    simulations read.

    Parameters
    ----------
    method : {"ros2", "rk4"}
        The step (:func:`bondgraph.numerics.integrators.make_step`): the
        L-stable linearly implicit Rosenbrock method or classical RK4.
    substeps : int
        Steps per sample interval (>= 1).
    hold : {"zoh", "mean", "linear"} or str
        The input over an interval (:func:`bondgraph.numerics.integrators.hold_inputs`); one
        per input joined by commas (``"zoh,linear"``) holds each input its own way.
    backend : {"numba", "numpy"}
        Compiled kernels or the numpy reference (equal to rounding).
    refine : tuple of (start, stop, substeps)
        Runs of sample intervals ``start <= k < stop`` (interval k goes from
        sample k to k + 1 of the record it was chosen for) stepped with
        more substeps than ``substeps``: a record whose stiff or
        non-smooth stretches (a friction law's zero crossings, an end
        stop's contact) are short takes the fine step there only
        (:func:`bondgraph.inference.discretise.refined_runs`). The UKF and
        its smoother read it; whatever does not (a free run, another
        record: :meth:`uniform`) takes the largest substeps throughout.

    Raises
    ------
    OptionError
        A value out of its domain (named).

    Examples
    --------
    >>> Discretisation(method="rk4", substeps=4).for_free_run().substeps
    4
    >>> Discretisation().for_free_run().substeps
    2
    """

    method: str = "ros2"
    substeps: int = 1
    hold: str = "zoh"
    backend: str = DEFAULT_BACKEND
    refine: tuple = ()

    def __post_init__(self):
        _discretisation_fields(self)

    def for_free_run(self) -> "Discretisation":
        """The discretisation of the prior's free run: at least
        :data:`FREE_RUN_MIN_SUBSTEPS` steps per sample (a free run has no
        measurement update to pull a coarse step back; the toolkit's one
        place for that rule), and the largest substeps of a refinement
        throughout."""
        u = self.uniform()
        return replace(u, substeps=max(u.substeps, FREE_RUN_MIN_SUBSTEPS))

    def uniform(self) -> "Discretisation":
        """This discretisation without its refined runs, at their largest
        substeps throughout (what another record, or a step that does not
        read the runs, takes)."""
        if not self.refine:
            return self
        return replace(self, substeps=most_substeps(self), refine=())

    def interval_substeps(self, intervals: int) -> np.ndarray:
        """Substeps per interval (intervals,): :func:`interval_substeps`."""
        return interval_substeps(self, intervals)

    def describe(self) -> str:
        """``"ros2(2), zoh hold"``: for log lines."""
        return f"{self.method}({self.substeps}{refine_text(self)}), {self.hold} hold"

    def to_dict(self) -> dict:
        """The value as a plain dict (JSON-able)."""
        return asdict(self)


@dataclass(frozen=True)
class UKFOptions:
    """Options of the batched UKF (:func:`bondgraph.inference.ukf.ukf_nll`).

    Parameters
    ----------
    alpha : float
        Sigma-point spread α > 0 (Wan & van der Merwe 2000; 1e-3 ... 1
        supported, see :mod:`bondgraph.inference.ukf`).
    beta : float
        Prior-distribution term β (2 is optimal for a Gaussian).
    kappa : float
        Secondary scaling κ; the filter checks n + κ > 0 for the state
        dimension n.
    method : {"ros2", "rk4"}
        Discretisation of the prediction between samples
        (:mod:`bondgraph.numerics.integrators`).
    substeps : int
        Integration steps per sample interval (>= 1).
    refine : tuple of (start, stop, substeps)
        Runs of intervals stepped with more substeps
        (:attr:`Discretisation.refine`); the record must have them.
    jacobian : {"mean", "sigma"}
        ROS2 only: df/dx once per parameter set at the central sigma point,
        shared by its sigma points (a W-method, second order for any J), or
        at every sigma point.
    hold : {"zoh", "mean", "linear"} or str
        Input over a prediction interval [t_k, t_k+1]: ``u_k`` (zero-order
        hold, the sampled-data convention), ``(u_k + u_k+1)/2`` (the
        interval mean of a linearly interpolated input) or the first-order
        hold ``u_k + s (u_k+1 − u_k)`` seen by every integrator stage at its
        own time (:func:`bondgraph.numerics.integrators.hold_inputs`). For records of
        continuous inputs (ramps) the zero-order hold lags them by half a
        sample on average: a model error that biases inertias (the vehicle's
        engine inertia came out 3 % = 4 standard deviations low on the
        synthetic throttle-steps record with "zoh", within 1 with "mean").
        One hold per input, comma-joined in the model's input order
        (``"zoh,linear"``), holds each input its own way.
    backend : {"numba", "numpy"}
        The fused, compiled UKF kernel (:mod:`bondgraph.inference.ukf_numba`,
        parallel over parameter sets) or the batched numpy filter, the
        reference (equal NLL within 1e-9 relative). Default: numba when it
        is installed. Taken literally: with numba, a model's kernels are
        compiled the first time they are needed (once per installation, or
        per code key for a model built in memory), whatever the run's size,
        so a result never depends on the calls before it or on what is in
        the kernel cache; choose ``"numpy"`` for a one-shot run of a new
        model on a short record. Only a model or an option the kernel
        cannot serve runs on numpy instead (with a
        :class:`~bondgraph.errors.BackendWarning` for the model); the
        result's settings say which backend ran.

    Raises
    ------
    OptionError
        A value out of its domain (the message names the option and value).
    """

    alpha: float = 1.0
    beta: float = 2.0
    kappa: float = 0.0
    method: str = "ros2"
    substeps: int = 1
    jacobian: str = "mean"
    hold: str = "zoh"
    backend: str = DEFAULT_BACKEND
    refine: tuple = ()

    def __post_init__(self):
        _real(self, "alpha", positive=True)
        _real(self, "beta")
        _real(self, "kappa")
        _discretisation_fields(self)
        _choice(self, "jacobian", UKF_JACOBIANS)

    @property
    def discretisation(self) -> Discretisation:
        """The :class:`Discretisation` of these options (method, substeps,
        hold, backend)."""
        return Discretisation(self.method, self.substeps, self.hold, self.backend, self.refine)

    def with_discretisation(self, disc: Discretisation) -> "UKFOptions":
        """These options with the discretisation ``disc``."""
        return replace(self, method=disc.method, substeps=disc.substeps, hold=disc.hold,
                       backend=disc.backend, refine=disc.refine)

    def uniform(self) -> "UKFOptions":
        """These options at the largest substeps throughout
        (:meth:`Discretisation.uniform`)."""
        return self.with_discretisation(self.discretisation.uniform()) if self.refine else self

    def to_dict(self) -> dict:
        """The options as a plain dict (JSON-able)."""
        return asdict(self)


@dataclass(frozen=True)
class FitOptions:
    """How :func:`bondgraph.inference.estimate.estimate` searches.

    Parameters
    ----------
    optimizer : {"pso", "de"}
        Particle swarm (Kennedy & Eberhart 1995) or differential evolution
        (Storn & Price 1997), :mod:`bondgraph.inference.optimize`.
    particles : int, optional
        PSO swarm size, or DE population (popsize = particles // k);
        default 10 k for k estimated parameters.
    iterations : int
        PSO iterations / DE generations after the initial population.
    seed : int or None
        Seed of the optimizer's random generator.
    checkpoint : path, optional
        Optimizer checkpoint written after every iteration.
    resume : bool
        Continue from ``checkpoint`` (PSO: bit for bit the uninterrupted run).
    stall_iterations : int, optional
        PSO stopping rule (:func:`bondgraph.inference.optimize.pso`).
    polish : bool
        Refine the optimizer's best point with bounded L-BFGS-B.
    polish_maxiter : int
        Iterations of the polish.
    hessian : bool
        Hessian of the NLL at the estimate: Cramér-Rao standard deviations
        and correlations.
    check_discretisation : bool
        Compare the filter's one-step discretisation error at the estimate
        with a fine reference (:func:`bondgraph.inference.ukf.discretisation_check`).
    progress : bool
        tqdm progress bar.
    chunk : int, optional
        Largest number of parameter sets per UKF run (memory bound).
    workers : int
        Worker processes of the embedded Dask cluster sharing each batched
        evaluation (:class:`bondgraph.inference.estimate.Criterion`,
        :class:`bondgraph.inference.executor.Executor`); 1: in process.
    scheduler : str, optional
        Address of an existing Dask scheduler, ``tcp://HOST:PORT`` (default:
        ``$BONDGRAPH_SCHEDULER``, else none). Results do not depend on it.

    Raises
    ------
    OptionError
        A value out of its domain, or ``resume`` without a ``checkpoint``.
    """

    optimizer: str = "pso"
    particles: int | None = None
    iterations: int = 100
    seed: int | None = 0
    checkpoint: str | Path | None = None
    resume: bool = False
    stall_iterations: int | None = None
    polish: bool = True
    polish_maxiter: int = 50
    hessian: bool = True
    check_discretisation: bool = True
    progress: bool = True
    chunk: int | None = None
    workers: int = 1
    scheduler: str | None = None

    def __post_init__(self):
        _choice(self, "optimizer", OPTIMIZERS)
        _integer(self, "particles", 2, optional=True)
        _integer(self, "iterations", 0)
        _integer(self, "seed", 0, optional=True)
        _integer(self, "stall_iterations", 1, optional=True)
        _integer(self, "polish_maxiter", 1)
        _integer(self, "chunk", 1, optional=True)
        _integer(self, "workers", 1)
        if self.scheduler is not None and not isinstance(self.scheduler, str):
            raise OptionError(f"FitOptions.scheduler = {self.scheduler!r} must be an address "
                              f"string (tcp://HOST:PORT) or None")
        for name in ("resume", "polish", "hessian", "check_discretisation", "progress"):
            _flag(self, name)
        if self.resume and self.checkpoint is None:
            raise OptionError("FitOptions.resume = True needs a checkpoint (checkpoint = None)")

    def to_dict(self) -> dict:
        """The options as a plain dict (JSON-able; a checkpoint path as str)."""
        d = asdict(self)
        if d["checkpoint"] is not None:
            d["checkpoint"] = str(d["checkpoint"])
        return d

    def swarm(self, particles: int) -> "SwarmOptions":
        """The particle swarm of this search (``iterations``, ``seed``,
        ``stall_iterations``) with ``particles`` particles."""
        return SwarmOptions(particles=particles, iterations=self.iterations, seed=self.seed,
                            stall_iterations=self.stall_iterations)

    def evolution(self, popsize: int) -> "EvolutionOptions":
        """The differential evolution of this search (``iterations``,
        ``seed``) with the population multiplier ``popsize``."""
        return EvolutionOptions(popsize=popsize, iterations=self.iterations, seed=self.seed)

    def checkpointing(self, fingerprint: Mapping[str, str] | None = None) -> "Checkpointing":
        """The optimizer's :class:`Checkpointing`: ``checkpoint``, ``resume``
        and the problem's ``fingerprint``."""
        return Checkpointing(path=self.checkpoint, resume=self.resume, fingerprint=fingerprint)


@dataclass(frozen=True)
class SwarmOptions:
    """Settings of the particle swarm :func:`bondgraph.inference.optimize.pso`
    (Kennedy & Eberhart 1995; constriction of Clerc & Kennedy 2002).

    Parameters
    ----------
    particles : int, optional
        Swarm size S (>= 2; default 10 k for k parameters).
    iterations : int
        Maximum iterations after the initial swarm (>= 0).
    seed : int or None
        Seed of the ``numpy.random.Generator`` (PCG64).
    w, c1, c2 : float
        Inertia (constriction) and acceleration coefficients (default
        :data:`CONSTRICTION_W`, :data:`CONSTRICTION_C`).
    vmax : float
        Velocity clamp as a fraction of the box width (normalised units, > 0).
    stall_iterations : int, optional
        Stop when the best value improved by less than ``ftol * (1 + |best|)``
        over this many iterations (>= 1; None: never).
    ftol : float
        Tolerance of that stall rule (>= 0).

    Raises
    ------
    OptionError
        A value out of its domain (the message names the option and value).

    Examples
    --------
    >>> SwarmOptions(particles=20, iterations=50, seed=3).w
    0.7298
    """

    particles: int | None = None
    iterations: int = 100
    seed: int | None = 0
    w: float = CONSTRICTION_W
    c1: float = CONSTRICTION_C
    c2: float = CONSTRICTION_C
    vmax: float = 0.5
    stall_iterations: int | None = None
    ftol: float = 1e-8

    def __post_init__(self):
        _integer(self, "particles", 2, optional=True)
        _integer(self, "iterations", 0)
        _integer(self, "seed", 0, optional=True)
        for name in ("w", "c1", "c2"):
            _real(self, name)
        _real(self, "vmax", positive=True)
        _integer(self, "stall_iterations", 1, optional=True)
        _nonnegative(self, "ftol")

    def size(self, k: int) -> int:
        """The swarm size S for ``k`` parameters: ``particles``, default 10 k."""
        return self.particles if self.particles is not None else 10 * k


@dataclass(frozen=True)
class EvolutionOptions:
    """Settings of the differential evolution :func:`bondgraph.inference.optimize.de`
    (Storn & Price 1997; :func:`scipy.optimize.differential_evolution`).

    Parameters
    ----------
    popsize : int
        Population multiplier (>= 1): the population has ``popsize * k``
        members (scipy's convention), so 10 x 8 parameters = 80 members.
    iterations : int
        ``maxiter``: generations after the initial population (>= 0).
    seed : int or None
        Seed of scipy's random generator.
    tol, atol : float
        scipy's convergence tolerances (>= 0; 0: run all generations).
    mutation : float or (float, float)
        Differential weight F, or the range of its dithering (scipy).
    recombination : float
        Crossover probability in [0, 1].
    strategy : str
        One of :data:`DE_STRATEGIES`.

    Raises
    ------
    OptionError
        A value out of its domain (the message names the option and value).

    Examples
    --------
    >>> EvolutionOptions(popsize=15).mutation
    (0.5, 1.0)
    """

    popsize: int = 10
    iterations: int = 100
    seed: int | None = 0
    tol: float = 0.0
    atol: float = 0.0
    mutation: float | tuple[float, float] = (0.5, 1.0)
    recombination: float = 0.7
    strategy: str = "best1bin"

    def __post_init__(self):
        _integer(self, "popsize", 1)
        _integer(self, "iterations", 0)
        _integer(self, "seed", 0, optional=True)
        _nonnegative(self, "tol")
        _nonnegative(self, "atol")
        _mutation(self)
        _real(self, "recombination")
        if not 0.0 <= self.recombination <= 1.0:
            raise OptionError(f"EvolutionOptions.recombination must be in [0, 1], "
                              f"got {self.recombination!r}")
        _choice(self, "strategy", DE_STRATEGIES)


def _nonnegative(obj, name: str) -> None:
    """A finite number >= 0 (converted to float)."""
    _real(obj, name)
    if getattr(obj, name) < 0:
        raise OptionError(f"{type(obj).__name__}.{name} must be >= 0, got {getattr(obj, name)!r}")


def _mutation(obj) -> None:
    """A finite number, or a pair of them (kept a tuple of floats)."""
    v = obj.mutation
    if isinstance(v, (tuple, list)):
        ok = len(v) == 2 and all(isinstance(x, numbers.Real) and not isinstance(x, bool)
                                 and math.isfinite(x) for x in v)
        if not ok:
            raise OptionError(f"{type(obj).__name__}.mutation must be a number or a pair of "
                              f"numbers, got {v!r}")
        _set(obj, "mutation", tuple(float(x) for x in v))
    else:
        _real(obj, "mutation")


@dataclass(frozen=True)
class Checkpointing:
    """Where an optimizer (:func:`bondgraph.inference.optimize.pso`,
    :func:`bondgraph.inference.optimize.de`) keeps its checkpoint, whether it
    resumes from it, and what the resumed run must share with the
    interrupted one.

    Parameters
    ----------
    path : path, optional
        ``.npz`` file written (atomically) after every iteration; None: no
        checkpoint (kept as a :class:`pathlib.Path`).
    resume : bool
        Continue from ``path`` (which must exist and match the fingerprint).
    fingerprint : dict, optional
        Components of the problem a resumed run must share, besides the
        optimizer's settings
        (:func:`bondgraph.inference.checkpoint.problem_fingerprint`).

    Raises
    ------
    OptionError
        ``resume`` without a ``path``, a path that is not one, or a
        fingerprint that is not a mapping.
    """

    path: str | Path | None = None
    resume: bool = False
    fingerprint: Mapping[str, str] | None = None

    def __post_init__(self):
        if self.path is not None:
            if not isinstance(self.path, (str, os.PathLike)):
                raise OptionError(f"Checkpointing.path must be a path or None, got {self.path!r}")
            _set(self, "path", Path(self.path))
        _flag(self, "resume")
        if self.resume and self.path is None:
            raise OptionError("Checkpointing.resume = True needs a checkpoint (path = None)")
        if self.fingerprint is not None:
            if not isinstance(self.fingerprint, Mapping):
                raise OptionError(f"Checkpointing.fingerprint must be a mapping or None, got "
                                  f"{self.fingerprint!r}")
            _set(self, "fingerprint", dict(self.fingerprint))


@dataclass(frozen=True)
class ScoringOptions:
    """Iteration controls of Levenberg-damped Fisher scoring
    (:func:`bondgraph.inference.fisher.estimand_scoring`,
    :func:`bondgraph.inference.fisher.fisher_scoring`).

    Parameters
    ----------
    max_iter : int
        Most scoring iterations (>= 0).
    rtol : float
        Stop when a step improves the NLL by less than ``rtol * (1 + |NLL|)``.
    atol : float
        Stop (converged) when the predicted decrease of a full step,
        ½ gᵀ F⁻¹ g, is below ``atol`` nats (0: only ``rtol`` stops).
    log_scale : sequence of bool (k,), optional
        Quantities moved in log θ (scale parameters such as noise
        intensities, whose likelihood is far from quadratic in θ near zero);
        kept a tuple. Default: positive boxes spanning more than two decades.
    information : bool
        Compute the Fisher information at a result the last iteration moved
        to (False: one batched UKF run fewer; ``F`` is then None).
    log : callable, optional
        ``log(line)`` for progress lines.
    stop : callable, optional
        ``stop(estimand, nll) -> bool``, asked after every accepted step:
        True ends the scoring there, not converged (a caller that knows
        where the iterations are heading: another start's converged
        optimum).

    Raises
    ------
    OptionError
        A value out of its domain (the message names the option and value).

    Examples
    --------
    >>> ScoringOptions(max_iter=30, log_scale=[True, False]).log_scale
    (True, False)
    """

    max_iter: int = 12
    rtol: float = 1e-6
    atol: float = 1e-3
    log_scale: tuple[bool, ...] | None = None
    information: bool = True
    log: Callable[[str], None] | None = None
    stop: Callable[..., bool] | None = None

    def __post_init__(self):
        _integer(self, "max_iter", 0)
        _nonnegative(self, "rtol")
        _nonnegative(self, "atol")
        _flag(self, "information")
        if self.log is not None and not callable(self.log):
            raise OptionError(f"ScoringOptions.log must be callable or None, got {self.log!r}")
        if self.stop is not None and not callable(self.stop):
            raise OptionError(f"ScoringOptions.stop must be callable or None, got {self.stop!r}")
        if self.log_scale is not None:
            L = np.asarray(self.log_scale)
            if L.ndim != 1:
                raise OptionError(f"ScoringOptions.log_scale must be a sequence of flags, "
                                  f"got {self.log_scale!r}")
            _set(self, "log_scale", tuple(bool(v) for v in L))


@dataclass(frozen=True)
class Evaluation:
    """Where and in what batches a criterion's parameter sets are evaluated
    (:class:`bondgraph.inference.estimate.Criterion`). Results never depend
    on it.

    Parameters
    ----------
    chunk : int, optional
        Largest number of parameter sets per UKF run (memory bound).
    workers : int
        Worker processes of the embedded Dask cluster sharing each batch
        (:class:`bondgraph.inference.executor.Executor`); 1: in process.
    scheduler : str, optional
        Address of an existing Dask scheduler (``tcp://HOST:PORT``; default
        ``$BONDGRAPH_SCHEDULER``).

    Raises
    ------
    OptionError
        A chunk or worker count below 1, a scheduler that is not a string.
    """

    chunk: int | None = None
    workers: int = 1
    scheduler: str | None = None

    def __post_init__(self):
        _integer(self, "chunk", 1, optional=True)
        _integer(self, "workers", 1)
        if self.scheduler is not None and not isinstance(self.scheduler, str):
            raise OptionError(f"Evaluation.scheduler = {self.scheduler!r} must be an address "
                              f"string (tcp://HOST:PORT) or None")


#: the default GLR and observability windows of :class:`TrackOptions` [s] and
#: the fewest samples each spans (:meth:`TrackOptions.seconds`)
DEFAULT_WINDOW_S, DEFAULT_OBSERVABLE_S = 10.0, 2.0
GLR_LEAST_SAMPLES, OBSERVABLE_LEAST_SAMPLES = 20, 10


@dataclass(frozen=True)
class TrackOptions:
    """How :func:`bondgraph.inference.track.track` and
    :class:`bondgraph.inference.track.Tracker` follow parameters and detect
    their changes.

    Parameters
    ----------
    prior_rel : float
        Prior std of a tracked parameter, relative to its start value, when
        no std is given (> 0; at a start of 0: relative to its box width).
    false_alarm_hours : float or None
        Mean time between false alarms of the change detector [h]
        (:func:`bondgraph.inference.changes.glr_threshold`); None: no
        detection.
    window_s : float or None
        The GLR window [s]: how far back a change may start (> 0). None
        (default): 10 s, but at least :data:`GLR_LEAST_SAMPLES` samples
        (:meth:`seconds`).
    smooth : bool
        Also the RTS-smoothed estimates (batch tracker).
    match_spread : bool
        Keep the sigma-point spread of the filter without the tracked
        states (κ' = κ − k for k tracked parameters): a tracked parameter
        with zero variance and zero drift then gives exactly the
        constant-parameter UKF (the difference form of the unscented
        moments keeps the covariance positive for any κ).
    max_changes : int
        Most changes reported (and re-estimated) in one record (>= 0).
    reset_rel : float
        Prior std of a parameter after a detected change, relative to its
        value before it (> 0; never below the ``prior_rel`` rule): the filter
        restarts at the change time with this spread.
    holdoff_s : float or None
        After a change, how long the detector ignores the re-estimation's
        transient [s] (>= 0; None: ``window_s``): a second change within it
        is not detected.
    observable_s : float or None
        Window [s] (> 0) over which the information the record carries about
        a tracked parameter is summed to decide whether it is observable
        there (:func:`bondgraph.inference.changes.observable_mask`; trailing
        window, ending at the sample). None (default): 2 s, but at least
        :data:`OBSERVABLE_LEAST_SAMPLES` samples.
    observable_ratio : float
        A parameter is observable at a sample when the window's data alone
        would bring its prior variance down to at most this fraction of it
        (0 < ratio < 1; default ½: the window carries at least as much
        information as the prior, Ham & Brown 1983's normalised covariance
        as the degree of observability). Where it is not observable, the
        change detector raises no alarm for it.
    glr_clip : float or None
        The detector's standardised increments are clipped to ±glr_clip
        (> 0; default 3) before the GLR sums
        (:func:`bondgraph.inference.changes.glr_mean_jump`): one sample
        adds at most glr_clip²/2 nats, so a single outlier (a sensor's
        spike) raises no alarm; a change shows as a run of samples. None:
        the plain Gaussian GLR (a single sample past √(2h) alarms).
    calibrate : bool
        Divide each parameter's standardised updates by √λ, λ the factor by
        which their sums vary more than a white sequence's on this record
        (:func:`bondgraph.inference.changes.serial_inflation`; from 2 on,
        else 1), so that the false-alarm rate holds where the model's error
        makes them serially correlated. One more filter pass over the
        record. False: the test as the threshold assumes.

    Raises
    ------
    OptionError
        A value out of its domain (named).

    References
    ----------
    Ham, F. M., Brown, R. G. (1983). Observability, eigenvalues, and Kalman
    filtering. IEEE TAES 19(2), 269-273.
    """

    prior_rel: float = 0.1
    false_alarm_hours: float | None = 10.0
    window_s: float | None = None
    smooth: bool = True
    match_spread: bool = True
    max_changes: int = 20
    reset_rel: float = 1.0
    holdoff_s: float | None = None
    observable_s: float | None = None
    observable_ratio: float = 0.5
    glr_clip: float | None = 3.0
    calibrate: bool = True

    def __post_init__(self):
        _real(self, "prior_rel", positive=True)
        if self.false_alarm_hours is not None:
            _real(self, "false_alarm_hours", positive=True)
        if self.window_s is not None:
            _real(self, "window_s", positive=True)
        _flag(self, "smooth")
        _flag(self, "match_spread")
        _integer(self, "max_changes", 0)
        _real(self, "reset_rel", positive=True)
        if self.holdoff_s is not None:
            _real(self, "holdoff_s")
            if self.holdoff_s < 0:
                raise OptionError(f"TrackOptions.holdoff_s must be >= 0, got {self.holdoff_s}")
        if self.observable_s is not None:
            _real(self, "observable_s", positive=True)
        _real(self, "observable_ratio", positive=True)
        if self.glr_clip is not None:
            _real(self, "glr_clip", positive=True)
        _flag(self, "calibrate")
        if not self.observable_ratio < 1.0:
            raise OptionError("TrackOptions.observable_ratio must be < 1 (a posterior to prior "
                              f"variance ratio), got {self.observable_ratio}")

    def seconds(self, dt: float) -> tuple[float, float]:
        """The GLR and observability windows [s] on a record sampled every
        ``dt`` seconds: the ones given, or the defaults (10 s and 2 s, at
        a vehicle's 40 Hz 400 and 80 samples) stretched to at least
        :data:`GLR_LEAST_SAMPLES` and :data:`OBSERVABLE_LEAST_SAMPLES`
        samples: on a thermal record sampled every 10 s, 10 s is one sample,
        a "window" that judges a change, or the information about a
        parameter, by a single innovation (a constant-parameter record then
        raised changes; 200 s and 100 s there)."""
        glr = (self.window_s if self.window_s is not None
               else max(DEFAULT_WINDOW_S, GLR_LEAST_SAMPLES * dt))
        obs = (self.observable_s if self.observable_s is not None
               else max(DEFAULT_OBSERVABLE_S, OBSERVABLE_LEAST_SAMPLES * dt))
        return float(glr), float(obs)

    def samples(self, dt: float) -> tuple[int, int]:
        """:meth:`seconds` in samples of ``dt`` (each at least 1)."""
        return tuple(max(1, int(round(w / dt))) for w in self.seconds(dt))

    def to_dict(self) -> dict:
        """The options as a plain dict (JSON-able)."""
        return asdict(self)


def _checked(options, cls, what: str):
    """``options`` checked to be a ``cls`` (None: its defaults); the one
    check behind :func:`ukf_options`, :func:`fit_options`, :func:`scoring_options`.

    Raises
    ------
    OptionError
        For anything else (e.g. a dict: use ``cls(**d)``).
    """
    if options is None:
        return cls()
    if not isinstance(options, cls):
        raise OptionError(f"{what} must be a {cls.__name__}, got {type(options).__name__} "
                          f"{options!r} (use {cls.__name__}(**d) for a dict)")
    return options


def ukf_options(options) -> UKFOptions:
    """``options`` checked to be :class:`UKFOptions` (None: the defaults).

    Raises
    ------
    OptionError
        For anything else (e.g. a dict of options: use ``UKFOptions(**d)``).
    """
    return _checked(options, UKFOptions, "UKF options")


def fit_options(options) -> FitOptions:
    """``options`` checked to be :class:`FitOptions` (None: the defaults).

    Raises
    ------
    OptionError
        For anything else (e.g. a dict: use ``FitOptions(**d)``).
    """
    return _checked(options, FitOptions, "fit options")


def scoring_options(options) -> ScoringOptions:
    """``options`` checked to be :class:`ScoringOptions` (None: the defaults).

    Raises
    ------
    OptionError
        For anything else (e.g. a dict: use ``ScoringOptions(**d)``).
    """
    return _checked(options, ScoringOptions, "scoring options")

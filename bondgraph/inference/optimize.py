"""Global optimisers for batched criteria: particle swarm and differential evolution.

Both minimise ``fun(X (S, k)) -> (S,)`` over a box, where one call
evaluates a whole population (the batched UKF likelihood of
:mod:`bondgraph.inference.ukf` evaluates every particle in one call). ``+inf`` (or
NaN) values mark failed evaluations; they never stop the search.

* :func:`pso` — particle swarm optimisation (Kennedy & Eberhart 1995) with
  Clerc-Kennedy constriction (w = 0.7298, c1 = c2 = 1.49618; Clerc & Kennedy
  2002), global-best topology, uniform initialisation in the box, velocity
  clamp, absorbing bounds, all in normalised [0, 1] coordinates
  (:class:`~bondgraph.inference.options.SwarmOptions`). A checkpoint
  (positions, velocities, bests, history and the RNG state) is written after
  every iteration; resuming (:class:`~bondgraph.inference.options.Checkpointing`)
  continues from it and reproduces the uninterrupted run bit for bit.
* :func:`de` — :func:`scipy.optimize.differential_evolution` with
  ``vectorized=True`` behind the same interface
  (:class:`~bondgraph.inference.options.EvolutionOptions`).

Evaluation counts are exact: ``nfev`` counts parameter sets (members)
evaluated, ``ncalls`` batched calls of ``fun``. A PSO with 80 particles and
100 iterations makes 101 calls and 8080 evaluations.

References
----------
Kennedy, J., Eberhart, R. (1995). Particle swarm optimization. Proc. IEEE
Int. Conf. Neural Networks, 1942-1948.
Clerc, M., Kennedy, J. (2002). The particle swarm: explosion, stability,
and convergence in a multidimensional complex space. IEEE Trans. Evol.
Comput. 6(1), 58-73.
Storn, R., Price, K. (1997). Differential evolution. J. Global Optim. 11,
341-359.
"""

from __future__ import annotations

import json
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Callable, ClassVar, Mapping

import numpy as np
from scipy.optimize import differential_evolution, minimize

from bondgraph.core import atomic
from bondgraph.core import progress as _progress
from bondgraph.errors import CheckpointError, OptionError
from bondgraph.inference import checkpoint as fingerprints
from bondgraph.inference.options import Checkpointing, EvolutionOptions, SwarmOptions


@dataclass
class OptimizeResult:
    """Outcome of :func:`pso` or :func:`de`.

    Attributes
    ----------
    x : ndarray (k,)
        Best point found (physical units).
    fun : float
        Criterion at ``x``.
    nfev : int
        Parameter sets evaluated (e.g. 80 x 101 = 8080).
    ncalls : int
        Batched calls of the criterion.
    nit : int
        Iterations (generations) completed.
    n_inf : int
        Evaluations that returned +inf or NaN.
    stop_reason : str
    history : ndarray (nit + 1,)
        Best criterion after the initial swarm and after each iteration.
    method : str
    wall_s : float
        Wall time of this run [s] (of the last session when resumed).
    resumed_from : int
        Iteration the run was resumed from (0 if it started fresh).
    settings : dict
    """

    x: np.ndarray
    fun: float
    nfev: int
    ncalls: int
    nit: int
    n_inf: int
    stop_reason: str
    history: np.ndarray
    method: str
    wall_s: float = 0.0
    resumed_from: int = 0
    settings: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        d = asdict(self)
        d["x"] = [float(v) for v in self.x]
        d["history"] = [float(v) for v in self.history]
        d["fun"] = float(self.fun)
        return d


def _check_box(lower, upper):
    lo = np.asarray(lower, dtype=float).ravel()
    hi = np.asarray(upper, dtype=float).ravel()
    if lo.shape != hi.shape or lo.size == 0:
        raise OptionError(f"lower and upper bounds must be non-empty and of equal length "
                          f"(got {lo.size} and {hi.size})")
    bad = ~(np.isfinite(lo) & np.isfinite(hi) & (hi > lo))
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise OptionError(f"bound {i}: need finite lower < upper, got [{lo[i]}, {hi[i]}]")
    return lo, hi


def _evaluate(fun, X):
    f = np.asarray(fun(X), dtype=float).reshape(-1)
    if f.shape[0] != X.shape[0]:
        raise OptionError(f"criterion returned {f.shape[0]} values for {X.shape[0]} parameter sets")
    f = np.where(np.isnan(f), np.inf, f)
    return f


def _save_checkpoint(path: Path, state: dict) -> None:
    """``np.savez`` of ``state`` to ``path``, atomically."""
    atomic.replace_file(path, lambda tmp: np.savez(tmp, **state))


def _load_checkpoint(path: Path | None, fingerprint: Mapping[str, str]):
    """The arrays of a checkpoint written for the problem ``fingerprint``.

    Raises
    ------
    CheckpointError
        Missing or unreadable file, or a fingerprint that differs (the
        differing components named, :func:`bondgraph.inference.checkpoint.check`).
    """
    if path is None or not path.exists():
        raise CheckpointError(f"cannot resume: checkpoint {path} does not exist",
                              hint="run without --resume first")
    try:
        d = dict(np.load(path, allow_pickle=False))
    except Exception as exc:            # zip, npy and OS errors of a damaged file
        raise CheckpointError(f"cannot resume: checkpoint {path} is not readable "
                              f"({type(exc).__name__}: {exc})") from None
    fingerprints.check(path, d.get("fingerprint"), fingerprint)
    return d


def _progress_bar(progress: bool, total: int, initial: int, desc: str, unit: str):
    """A tqdm bar, or None without ``progress``."""
    if not progress:
        return None
    return _progress.bar(total=total, initial=initial, desc=desc, unit=unit, dynamic_ncols=True)


@dataclass(eq=False)
class _Swarm:
    """State of a PSO run in normalised coordinates z ∈ [0, 1]^k: positions
    ``Z`` and velocities ``V`` (S, k), personal bests, the global best ``g``,
    counters, history and the random generator. A checkpoint stores all of
    it, so a resumed run continues bit for bit."""

    #: arrays of the checkpoint besides the settings key and the RNG state
    FIELDS: ClassVar[tuple[str, ...]] = ("Z", "V", "pbest", "pbest_f", "g", "gf", "it",
                                         "nfev", "ncalls", "n_inf", "history", "stall")

    rng: np.random.Generator
    Z: np.ndarray
    V: np.ndarray
    pbest: np.ndarray
    pbest_f: np.ndarray
    g: np.ndarray
    gf: float
    it: int
    nfev: int
    ncalls: int
    n_inf: int
    history: list
    stall: int

    @classmethod
    def start(cls, fun, lo, hi, S: int, seed, vmax: float, x0) -> "_Swarm":
        """Uniform positions in the box, velocities within ±vmax/2, ``x0``
        (if given) as particle 0; one evaluation of the swarm."""
        k = lo.size
        rng = np.random.default_rng(seed)
        Z = rng.random((S, k))
        V = (rng.random((S, k)) * 2.0 - 1.0) * vmax * 0.5
        if x0 is not None:
            Z[0] = np.clip((np.asarray(x0, float) - lo) / (hi - lo), 0.0, 1.0)
        f = _evaluate(fun, lo + Z * (hi - lo))
        i = int(np.argmin(f))
        return cls(rng, Z=Z, V=V, pbest=Z.copy(), pbest_f=f.copy(), g=Z[i].copy(),
                   gf=float(f[i]), it=0, nfev=S, ncalls=1,
                   n_inf=int(np.count_nonzero(~np.isfinite(f))), history=[float(f[i])], stall=0)

    @classmethod
    def load(cls, path: Path | None, fingerprint: Mapping[str, str]) -> "_Swarm":
        """The swarm of a checkpoint written for the same ``fingerprint``.

        Raises
        ------
        CheckpointError
            Missing checkpoint, or one written for another problem or with
            other settings (what differs is named).
        """
        d = _load_checkpoint(path, fingerprint)
        rng = np.random.Generator(np.random.PCG64())
        rng.bit_generator.state = json.loads(str(d["rng"]))
        return cls(rng, Z=d["Z"].copy(), V=d["V"].copy(), pbest=d["pbest"].copy(),
                   pbest_f=d["pbest_f"].copy(), g=d["g"].copy(), gf=float(d["gf"]),
                   it=int(d["it"]), nfev=int(d["nfev"]), ncalls=int(d["ncalls"]),
                   n_inf=int(d["n_inf"]), history=list(d["history"]), stall=int(d["stall"]))

    def save(self, path: Path | None, fingerprint: Mapping[str, str]) -> None:
        """Write the checkpoint (atomically); nothing without a path."""
        if path is None:
            return
        state = {name: np.asarray(getattr(self, name)) for name in self.FIELDS}
        _save_checkpoint(path, dict(fingerprint=fingerprints.encode(fingerprint),
                                    rng=np.array(json.dumps(self.rng.bit_generator.state)),
                                    **state))

    def iterate(self, fun, lo, hi, opts: SwarmOptions) -> None:
        """One PSO iteration (velocity and position update, evaluation, bests)."""
        w, c1, c2, vmax, ftol = opts.w, opts.c1, opts.c2, opts.vmax, opts.ftol
        S, k = self.Z.shape
        r1 = self.rng.random((S, k))
        r2 = self.rng.random((S, k))
        V = w * self.V + c1 * r1 * (self.pbest - self.Z) + c2 * r2 * (self.g - self.Z)
        np.clip(V, -vmax, vmax, out=V)
        Z = self.Z + V
        out = (Z < 0.0) | (Z > 1.0)
        if out.any():
            Z = np.clip(Z, 0.0, 1.0)
            V[out] = 0.0
        self.Z, self.V = Z, V
        f = _evaluate(fun, lo + Z * (hi - lo))
        self.nfev += S
        self.ncalls += 1
        self.n_inf += int(np.count_nonzero(~np.isfinite(f)))
        better = f < self.pbest_f
        self.pbest[better] = Z[better]
        self.pbest_f[better] = f[better]
        i = int(np.argmin(self.pbest_f))
        old = self.gf
        if self.pbest_f[i] < self.gf:
            self.g, self.gf = self.pbest[i].copy(), float(self.pbest_f[i])
        self.it += 1
        self.history.append(self.gf)
        if np.isfinite(old) and old - self.gf <= ftol * (1.0 + abs(self.gf)):
            self.stall += 1
        else:
            self.stall = 0


def pso(fun: Callable[[np.ndarray], np.ndarray], lower, upper, *,
        swarm: SwarmOptions | None = None, checkpointing: Checkpointing | None = None,
        progress: bool = True, x0=None, callback: Callable | None = None) -> OptimizeResult:
    """Minimise a batched criterion by particle swarm optimisation
    (Kennedy & Eberhart 1995; constriction of Clerc & Kennedy 2002).

    Parameters
    ----------
    fun : callable
        ``fun(X) -> f``: X (S, k) in physical units, f (S,); +inf/NaN for a
        failed evaluation.
    lower, upper : array (k,)
        Box bounds (finite, lower < upper).
    swarm : SwarmOptions, optional
        Swarm size (default 10 k), iterations, seed, coefficients w, c1,
        c2, velocity clamp and the stall rule
        (:class:`~bondgraph.inference.options.SwarmOptions`; default: its
        defaults).
    checkpointing : Checkpointing, optional
        ``.npz`` checkpoint written (atomically) after every iteration, and
        whether to resume from it (it must exist and match the fingerprint:
        the problem's components and the swarm's settings)
        (:class:`~bondgraph.inference.options.Checkpointing`; default: none).
    progress : bool
        Show a tqdm bar with the best criterion.
    x0 : array (k,), optional
        A point placed into the initial swarm (replaces particle 0).
    callback : callable, optional
        ``callback(it, best_x, best_f)`` after every iteration; True stops.

    Returns
    -------
    OptimizeResult

    Raises
    ------
    OptionError
        Bad bounds or options; a missing checkpoint or one of another problem
        (:class:`~bondgraph.errors.CheckpointError`, what differs named).

    Notes
    -----
    Per iteration, in normalised coordinates z ∈ [0, 1]^k::

        v <- w v + c1 r1 (pbest − z) + c2 r2 (gbest − z),   |v_i| <= vmax
        z <- z + v;  a coordinate leaving [0, 1] is clipped and its velocity zeroed

    The random numbers r1, r2 (uniform, per particle and coordinate) come
    from one generator whose state is checkpointed.
    """
    opts = _given(swarm, SwarmOptions, "swarm")
    ckp = _given(checkpointing, Checkpointing, "checkpointing")
    lo, hi = _check_box(lower, upper)
    S = opts.size(lo.size)
    settings, key = _pso_settings(lo, hi, S, opts, x0, ckp.fingerprint)
    ck = ckp.path
    t0 = time.perf_counter()
    sw = (_Swarm.load(ck, key) if ckp.resume
          else _Swarm.start(fun, lo, hi, S, opts.seed, opts.vmax, x0))
    if not ckp.resume:
        sw.save(ck, key)
    it0 = sw.it
    stop_reason = _pso_iterations(sw, fun, lo, hi, opts, (ck, key), progress, callback)
    return OptimizeResult(x=lo + sw.g * (hi - lo), fun=sw.gf, nfev=sw.nfev, ncalls=sw.ncalls,
                          nit=sw.it, n_inf=sw.n_inf, stop_reason=stop_reason,
                          history=np.array(sw.history), method="pso",
                          wall_s=time.perf_counter() - t0, resumed_from=it0, settings=settings)


def _given(value, cls, name: str):
    """``value`` checked to be a ``cls`` (None: its defaults).

    Raises
    ------
    OptionError
        For anything else (a dict: use ``cls(**d)``).
    """
    if value is None:
        return cls()
    if not isinstance(value, cls):
        raise OptionError(f"{name} must be a {cls.__name__}, got {type(value).__name__} "
                          f"{value!r} (use {cls.__name__}(**d) for a dict)")
    return value


def _pso_settings(lo, hi, S: int, opts: SwarmOptions, x0, problem: Mapping[str, str] | None):
    """``(settings, checkpoint fingerprint)``; the fingerprint covers what a
    resumed run must share with the interrupted one: the ``problem``
    components and the swarm's settings (not the iteration budget)."""
    seed, w, c1, c2, vmax = opts.seed, opts.w, opts.c1, opts.c2, opts.vmax
    settings = dict(method="pso", particles=S, seed=seed, w=w, c1=c1, c2=c2, vmax=vmax,
                    lower=lo.tolist(), upper=hi.tolist(),
                    x0=None if x0 is None else np.asarray(x0, float).tolist())
    key = _search_fingerprint(problem, "pso",
                              {"particles": str(S), "seed": str(seed),
                               "coefficients": f"w={w!r} c1={c1!r} c2={c2!r} vmax={vmax!r}"},
                              box=(lo, hi), start=x0)
    settings["iterations"] = opts.iterations
    settings["stall_iterations"] = opts.stall_iterations
    return settings, key


def _search_fingerprint(problem: Mapping[str, str] | None, method: str,
                        settings: Mapping[str, str], *, box, start) -> dict[str, str]:
    """The checkpoint fingerprint: the problem's components, the optimizer,
    its ``settings`` (name -> text, in order), the search box and the start
    point (hashed)."""
    fp = dict(problem or {})
    fp["optimizer"] = method
    fp.update(settings)
    fp["search box (bounds)"] = fingerprints.digest(*box)
    fp["start point"] = fingerprints.digest(start)
    return fp


def _pso_iterations(sw: _Swarm, fun, lo, hi, opts: SwarmOptions, ck_key, progress: bool,
                    callback) -> str:
    """Iterate until ``opts.iterations``, the stall rule or the callback;
    returns the stop reason. Checkpoints after every iteration; a bar
    (iterations done, time left, best criterion) with ``progress``."""
    bar = _progress_bar(progress, opts.iterations, min(sw.it, opts.iterations),
                        f"PSO: {sw.Z.shape[0]} particles x {lo.size} parameters", "it")
    try:
        if bar is not None:
            bar.set_postfix(best=f"{sw.gf:.6g}")
        return _pso_loop(sw, fun, lo, hi, opts, ck_key, bar, callback)
    finally:
        if bar is not None:
            bar.close()


def _pso_loop(sw: _Swarm, fun, lo, hi, opts: SwarmOptions, ck_key, bar, callback) -> str:
    """The iterations of :func:`_pso_iterations`."""
    stall_iterations = opts.stall_iterations
    stalled = f"stalled {stall_iterations} iterations"
    if stall_iterations is not None and sw.stall >= stall_iterations:
        return stalled
    while sw.it < opts.iterations:
        sw.iterate(fun, lo, hi, opts)
        sw.save(*ck_key)
        if bar is not None:
            bar.update(1)
            bar.set_postfix(best=f"{sw.gf:.6g}")
        if callback is not None and callback(sw.it, lo + sw.g * (hi - lo), sw.gf):
            return "callback"
        if stall_iterations is not None and sw.stall >= stall_iterations:
            return stalled
    return "max iterations"


class _DEMonitor:
    """The criterion as scipy's vectorised DE sees it, with exact counts,
    the best value, its history and the checkpoint after every generation.

    Infinite values are replaced by a finite penalty for scipy's bookkeeping
    (its convergence test takes a standard deviation of the energies).
    """

    PENALTY = 1e100

    def __init__(self, fun, ck: Path | None, it0: int, history: list, best: float,
                 resumed: bool, bar, fingerprint: Mapping[str, str]):
        self.fun, self.ck, self.gen, self.history, self.best = fun, ck, it0, history, best
        self.resumed, self.bar, self.fingerprint = resumed, bar, fingerprint
        self.nfev = self.ncalls = self.n_inf = 0

    def __call__(self, Xt):
        X = np.atleast_2d(np.asarray(Xt, dtype=float).T)
        f = _evaluate(self.fun, X)
        self.nfev += X.shape[0]
        self.ncalls += 1
        bad = ~np.isfinite(f)
        self.n_inf += int(np.count_nonzero(bad))
        if (~bad).any():
            self.best = min(self.best, float(np.min(f[~bad])))
        if self.ncalls == 1 and not self.resumed:
            self.history.append(self.best)          # best of the initial population
        return np.where(bad, self.PENALTY, f)

    def callback(self, intermediate_result) -> bool:
        self.gen += 1
        self.history.append(self.best)
        if self.bar is not None:
            self.bar.update(1)
            self.bar.set_postfix(best=f"{self.best:.6g}")
        if self.ck is not None:
            _save_checkpoint(self.ck, dict(
                population=np.asarray(intermediate_result.population), it=np.array(self.gen),
                history=np.array(self.history), best=np.array(self.best),
                fingerprint=fingerprints.encode(self.fingerprint)))
        return False


def de(fun: Callable[[np.ndarray], np.ndarray], lower, upper, *,
       evolution: EvolutionOptions | None = None, checkpointing: Checkpointing | None = None,
       progress: bool = True, x0=None) -> OptimizeResult:
    """Minimise a batched criterion with scipy's differential evolution
    (Storn & Price 1997).

    Parameters
    ----------
    fun : callable
        ``fun(X (S, k)) -> (S,)`` as for :func:`pso`.
    lower, upper : array (k,)
    evolution : EvolutionOptions, optional
        Population multiplier (``popsize * k`` members, scipy's convention),
        generations, seed, tolerances, mutation, recombination and strategy
        (:class:`~bondgraph.inference.options.EvolutionOptions`; default:
        its defaults).
    checkpointing : Checkpointing, optional
        ``.npz`` with the population after every generation; resuming
        restarts from the checkpointed population (``init=``) for the
        remaining generations. Unlike :func:`pso`, this is not bit-for-bit
        the uninterrupted run: scipy's generator state is not restored
        (:class:`~bondgraph.inference.options.Checkpointing`; default: none).
    progress : bool
        tqdm bar with the best criterion.
    x0 : array (k,), optional

    Returns
    -------
    OptimizeResult
        ``nfev`` counts members (counted in the wrapper), ``ncalls`` the
        batched calls: 80 + 100 x 80 = 8080 for 10 x 8 parameters and 100
        generations.

    Raises
    ------
    OptionError
        Bad bounds or options, a population of fewer than 5 members; a
        missing checkpoint or one of another problem
        (:class:`~bondgraph.errors.CheckpointError`).

    Notes
    -----
    With ``vectorized=True`` scipy passes ``X`` with shape (k, S) and
    ``updating='deferred'``; the wrapper transposes it. Infinite values
    are replaced by a finite penalty (1e100) and counted in ``n_inf``.
    """
    opts = _given(evolution, EvolutionOptions, "evolution")
    ckp = _given(checkpointing, Checkpointing, "checkpointing")
    lo, hi = _check_box(lower, upper)
    k, popsize, iterations, resume = lo.size, opts.popsize, opts.iterations, ckp.resume
    if popsize * k < 5:
        raise OptionError(f"DE needs a population of at least 5 members (popsize * k), "
                          f"got {popsize} x {k}")
    fp = _search_fingerprint(ckp.fingerprint, "de",
                             {"popsize": str(popsize), "seed": str(opts.seed),
                              "strategy": f"{opts.strategy} mutation={opts.mutation!r} "
                                          f"recombination={opts.recombination!r}"},
                             box=(lo, hi), start=x0)
    init, it0, history, best = (_de_start(ckp.path, fp) if resume
                                else ("latinhypercube", 0, [], np.inf))
    mon = _DEMonitor(fun, ckp.path, it0, history, best, resume,
                     _progress_bar(progress, iterations, it0,
                                   f"DE: {popsize * k} members x {k} parameters", "gen"), fp)
    t0 = time.perf_counter()
    kw = dict(strategy=opts.strategy, maxiter=max(iterations - it0, 0), popsize=popsize,
              tol=opts.tol, atol=opts.atol, mutation=opts.mutation,
              recombination=opts.recombination, polish=False, init=init, vectorized=True,
              updating="deferred", callback=mon.callback)
    if x0 is not None and not resume:
        kw["x0"] = np.clip(np.asarray(x0, float), lo, hi)
    res = differential_evolution(mon, list(zip(lo, hi)), rng=opts.seed, **kw)
    if mon.bar is not None:
        mon.bar.close()
    return OptimizeResult(x=np.asarray(res.x, dtype=float),
                          fun=float(res.fun) if res.fun < mon.PENALTY else np.inf,
                          nfev=mon.nfev, ncalls=mon.ncalls, nit=mon.gen, n_inf=mon.n_inf,
                          stop_reason=str(res.message), history=np.array(mon.history),
                          method="de", wall_s=time.perf_counter() - t0, resumed_from=it0,
                          settings=_de_settings(opts, lo, hi))


def _de_settings(opts: EvolutionOptions, lo, hi) -> dict:
    """The settings a DE result reports."""
    return dict(method="de", popsize=opts.popsize, members=opts.popsize * lo.size,
                seed=opts.seed, iterations=opts.iterations, strategy=opts.strategy,
                mutation=[float(v) for v in np.atleast_1d(opts.mutation)],
                recombination=opts.recombination, lower=lo.tolist(), upper=hi.tolist())


def _de_start(ck: Path | None, fingerprint: Mapping[str, str]):
    """``(init population, generation, history, best)`` of a DE checkpoint.

    Raises
    ------
    CheckpointError
        Missing checkpoint, or one of another problem (:func:`_load_checkpoint`).
    """
    d = _load_checkpoint(ck, fingerprint)
    return (np.asarray(d["population"], dtype=float), int(d["it"]),
            [float(v) for v in d["history"]], float(d["best"]))


class _DifferencedCriterion:
    """``fg(z) -> (f, gradient)`` of a batched criterion in normalised
    coordinates z ∈ [0, 1]^k (x = lo + z·width), the gradient by central
    differences of ``step`` (one-sided at a bound or beside a non-finite
    value), the 2k + 1 points in one batched call; a non-finite f is 1e300
    with a zero gradient and sets ``failed``. The last point is cached
    (scipy asks for it twice). ``nfev`` counts the parameter sets."""

    def __init__(self, fun, lo, width, step: float):
        self.fun, self.lo, self.width, self.step = fun, lo, width, step
        self.k = lo.size
        self.nfev = 0
        self.failed = False
        self.cache: dict = {}

    def __call__(self, z):
        k, step = self.k, self.step
        z = np.clip(np.asarray(z, float), 0.0, 1.0)
        key = z.tobytes()
        if key in self.cache:
            return self.cache[key]
        Zp = np.clip(z + step * np.eye(k), 0.0, 1.0)
        Zm = np.clip(z - step * np.eye(k), 0.0, 1.0)
        Zall = np.vstack([z[None], Zp, Zm])
        f = _evaluate(self.fun, self.lo + Zall * self.width)
        self.nfev += Zall.shape[0]
        f0 = f[0]
        if not np.isfinite(f0):
            self.failed = True
            out = (1e300, np.zeros(k))
        else:
            dz = (Zp - Zm)[np.arange(k), np.arange(k)]
            fp, fm = f[1:k + 1], f[k + 1:]
            g = np.zeros(k)
            for i in range(k):
                if np.isfinite(fp[i]) and np.isfinite(fm[i]) and dz[i] > 0:
                    g[i] = (fp[i] - fm[i]) / dz[i]
                elif np.isfinite(fp[i]) and Zp[i, i] > z[i]:
                    g[i] = (fp[i] - f0) / (Zp[i, i] - z[i])
                elif np.isfinite(fm[i]) and Zm[i, i] < z[i]:
                    g[i] = (f0 - fm[i]) / (z[i] - Zm[i, i])
            out = (float(f0), g)
        self.cache.clear()
        self.cache[key] = out
        return out


#: the lengths of the first step (fractions of the box width) of the runs of
#: :func:`minimize_batched`: the first as L-BFGS-B takes it, the shorter ones
#: after a run whose first step fell where the criterion has no finite value
REACHES = (1.0, 0.1, 0.01, 1e-3, 1e-4)


def minimize_batched(fun: Callable[[np.ndarray], np.ndarray], x0, lower, upper, *,
                     step: float = 1e-6, maxiter: int = 50, gtol: float = 1e-8,
                     ftol: float = 1e-10) -> tuple[np.ndarray, float, int, str]:
    """Local bounded polish: L-BFGS-B with central-difference gradients, the
    2k + 1 points of each gradient evaluated in one batched call.

    Parameters
    ----------
    fun : callable
        Batched criterion ``fun(X (S, k)) -> (S,)``.
    x0 : array (k,)
    lower, upper : array (k,)
    step : float
        Difference step as a fraction of the box width.
    maxiter : int
        L-BFGS-B iterations (each one batched gradient call of 2k + 1 sets,
        plus line-search calls).
    gtol, ftol : float
        scipy L-BFGS-B tolerances (on the normalised problem); ``ftol`` is
        relative to |f|: 1e-10 of an NLL of 1e4 is 1e-6 nats.

    Returns
    -------
    (x, f, nfev, message)
        Best point, its value, parameter sets evaluated, scipy's message.

    Notes
    -----
    Works in normalised coordinates z = (x − lower)/(upper − lower); at a
    bound the difference uses the points inside the box (one-sided).

    In a box, L-BFGS-B's first step is the whole gradient projected onto the
    box: from a point near a bound of a wide box it lands far away, where
    the criterion may have no finite value (an explicit step that is
    unstable there). Its line search then shrinks the step to nothing and
    reports convergence where it started. When a run saw a non-finite value
    and gained nothing, it is run again from the best point with the
    coordinates scaled so that its first step is 0.1, then 0.01, ... of the
    box long (:data:`REACHES`); a run that saw a non-finite value and gained
    is run again (its line search may have stopped it short).
    """
    lo, hi = _check_box(lower, upper)
    width = hi - lo
    k = lo.size
    fg = _DifferencedCriterion(fun, lo, width, step)
    z0 = np.clip((np.asarray(x0, float) - lo) / width, 0.0, 1.0)
    f0 = fg(z0)[0]
    z, fz, message = z0, f0, "not run"
    rung, left = 0, maxiter
    while left > 0:
        fg.failed = False
        # the first step of L-BFGS-B in a box is -gradient (to the box's
        # edge): in w = (z - zc)/s it is s^2 |g| long in z; the first run
        # in the plain coordinates (zc = 0, s = 1)
        gmax = 0.0 if rung == 0 else float(np.max(np.abs(fg(z)[1]), initial=0.0))
        s = np.sqrt(REACHES[rung] / gmax) if gmax > 0 else 1.0
        zc = z if s != 1.0 else np.zeros(k)

        def fg_scaled(w, zc=zc, s=s):
            f, g = fg(zc + s * np.asarray(w, float))
            return f, s * g
        r = minimize(fg_scaled, (z - zc) / s, jac=True, method="L-BFGS-B",
                     bounds=list(zip(-zc / s, (1.0 - zc) / s)),
                     options=dict(maxiter=left, gtol=gtol * s, ftol=ftol))
        left -= max(int(r.nit), 1)
        zn = np.clip(zc + s * r.x, 0.0, 1.0)
        fn = fg(zn)[0]
        gained = fn < fz - ftol * max(abs(fz), 1.0)
        message = str(r.message)
        if fn < fz:
            z, fz = zn, fn
        if not fg.failed or (not gained and rung + 1 == len(REACHES)):
            break
        if not gained:
            rung += 1           # its first step fell where nothing is finite: a shorter one
    return lo + z * width, float(fz), fg.nfev, message

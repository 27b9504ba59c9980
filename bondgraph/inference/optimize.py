"""Global optimisers for batched criteria: particle swarm and differential evolution.

Both minimise ``fun(X (S, k)) -> (S,)`` over a box, where one call
evaluates a whole population (the batched UKF likelihood of
:mod:`bondgraph.inference.ukf` evaluates every particle in one call). ``+inf`` (or
NaN) values mark failed evaluations; they never stop the search.

* :func:`pso` — particle swarm optimisation (Kennedy & Eberhart 1995) with
  Clerc-Kennedy constriction (w = 0.7298, c1 = c2 = 1.49618; Clerc & Kennedy
  2002), global-best topology, uniform initialisation in the box, velocity
  clamp, absorbing bounds, all in normalised [0, 1] coordinates. A checkpoint
  (positions, velocities, bests, history and the RNG state) is written after
  every iteration; ``resume=True`` continues from it and reproduces the
  uninterrupted run bit for bit.
* :func:`de` — :func:`scipy.optimize.differential_evolution` with
  ``vectorized=True`` behind the same interface.

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

import hashlib
import json
import os
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from bondgraph.errors import OptionError

#: Clerc-Kennedy constriction coefficients
CONSTRICTION_W = 0.7298
CONSTRICTION_C = 1.49618


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


def _settings_key(d: dict) -> str:
    return hashlib.sha1(json.dumps(d, sort_keys=True).encode()).hexdigest()[:16]


def _save_checkpoint(path: Path, state: dict) -> None:
    tmp = path.with_name(path.name + ".tmp.npz")
    np.savez(tmp, **state)
    os.replace(tmp, path)


def pso(fun: Callable[[np.ndarray], np.ndarray], lower, upper, *, particles: int | None = None,
        iterations: int = 100, seed: int | None = 0, w: float = CONSTRICTION_W,
        c1: float = CONSTRICTION_C, c2: float = CONSTRICTION_C, vmax: float = 0.5,
        stall_iterations: int | None = None, ftol: float = 1e-8,
        checkpoint: str | Path | None = None, resume: bool = False, progress: bool = True,
        x0=None, callback: Callable | None = None) -> OptimizeResult:
    """Minimise a batched criterion by particle swarm optimisation.

    Parameters
    ----------
    fun : callable
        ``fun(X) -> f``: X (S, k) in physical units, f (S,); +inf/NaN for a
        failed evaluation.
    lower, upper : array (k,)
        Box bounds (finite, lower < upper).
    particles : int, optional
        Swarm size (default 10 k).
    iterations : int
        Maximum iterations after the initial swarm.
    seed : int or None
        Seed of the ``numpy.random.Generator`` (PCG64).
    w, c1, c2 : float
        Inertia (constriction) and acceleration coefficients.
    vmax : float
        Velocity clamp as a fraction of the box width (normalised units).
    stall_iterations : int, optional
        Stop when the best value improved by less than
        ``ftol * (1 + |best|)`` over this many iterations.
    ftol : float
    checkpoint : path, optional
        ``.npz`` file written (atomically) after every iteration.
    resume : bool
        Continue from ``checkpoint`` (must exist and match the settings).
    progress : bool
        Show a tqdm bar with the best criterion.
    x0 : array (k,), optional
        A point placed into the initial swarm (replaces particle 0).
    callback : callable, optional
        ``callback(it, best_x, best_f)`` after every iteration; return True
        to stop.

    Returns
    -------
    OptimizeResult

    Raises
    ------
    OptionError
        Bad bounds, sizes, or a checkpoint that does not match the settings.

    Notes
    -----
    Per iteration, in normalised coordinates z ∈ [0, 1]^k::

        v <- w v + c1 r1 (pbest − z) + c2 r2 (gbest − z),   |v_i| <= vmax
        z <- z + v;  a coordinate leaving [0, 1] is clipped and its velocity zeroed

    The random numbers r1, r2 (uniform, per particle and coordinate) come
    from one generator whose state is checkpointed.
    """
    lo, hi = _check_box(lower, upper)
    k = lo.size
    S = int(particles) if particles is not None else 10 * k
    if S < 2:
        raise OptionError(f"PSO needs at least 2 particles, got {S}")
    if iterations < 0:
        raise OptionError(f"iterations must be >= 0, got {iterations}")
    width = hi - lo
    settings = dict(method="pso", particles=S, seed=seed, w=w, c1=c1, c2=c2, vmax=vmax,
                    lower=lo.tolist(), upper=hi.tolist(),
                    x0=None if x0 is None else np.asarray(x0, float).tolist())
    key = _settings_key(settings)
    settings["iterations"] = iterations
    settings["stall_iterations"] = stall_iterations
    ck = Path(checkpoint) if checkpoint is not None else None

    def to_phys(Z):
        return lo + Z * width

    t0 = time.perf_counter()
    if resume:
        if ck is None or not ck.exists():
            raise OptionError(f"cannot resume: checkpoint {ck} does not exist")
        d = np.load(ck, allow_pickle=False)
        if str(d["key"]) != key:
            raise OptionError(f"checkpoint {ck} was written with other PSO settings "
                              f"(particles, seed, coefficients or bounds differ); not resuming")
        rng = np.random.Generator(np.random.PCG64())
        rng.bit_generator.state = json.loads(str(d["rng"]))
        Z, V = d["Z"].copy(), d["V"].copy()
        pbest, pbest_f = d["pbest"].copy(), d["pbest_f"].copy()
        g, gf = d["g"].copy(), float(d["gf"])
        it0 = int(d["it"])
        nfev, ncalls, n_inf = int(d["nfev"]), int(d["ncalls"]), int(d["n_inf"])
        history = list(d["history"])
        stall = int(d["stall"])
    else:
        rng = np.random.default_rng(seed)
        Z = rng.random((S, k))
        V = (rng.random((S, k)) * 2.0 - 1.0) * vmax * 0.5
        if x0 is not None:
            Z[0] = np.clip((np.asarray(x0, float) - lo) / width, 0.0, 1.0)
        f = _evaluate(fun, to_phys(Z))
        nfev, ncalls, n_inf = S, 1, int(np.count_nonzero(~np.isfinite(f)))
        pbest, pbest_f = Z.copy(), f.copy()
        i = int(np.argmin(f))
        g, gf = Z[i].copy(), float(f[i])
        it0 = 0
        history = [gf]
        stall = 0

    def write(it):
        if ck is None:
            return
        _save_checkpoint(ck, dict(key=np.array(key), rng=np.array(json.dumps(rng.bit_generator.state)),
                                  Z=Z, V=V, pbest=pbest, pbest_f=pbest_f, g=g, gf=np.array(gf),
                                  it=np.array(it), nfev=np.array(nfev), ncalls=np.array(ncalls),
                                  n_inf=np.array(n_inf), history=np.array(history),
                                  stall=np.array(stall)))

    if not resume:
        write(0)
    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=iterations, initial=min(it0, iterations), desc="PSO", unit="it",
                   dynamic_ncols=True)
        bar.set_postfix(best=f"{gf:.6g}")
    stop_reason = "max iterations"
    it = it0
    if stall_iterations is not None and stall >= stall_iterations:
        stop_reason = f"stalled {stall_iterations} iterations"
    else:
        while it < iterations:
            r1 = rng.random((S, k))
            r2 = rng.random((S, k))
            V = w * V + c1 * r1 * (pbest - Z) + c2 * r2 * (g - Z)
            np.clip(V, -vmax, vmax, out=V)
            Z = Z + V
            out = (Z < 0.0) | (Z > 1.0)
            if out.any():
                Z = np.clip(Z, 0.0, 1.0)
                V[out] = 0.0
            f = _evaluate(fun, to_phys(Z))
            nfev += S
            ncalls += 1
            n_inf += int(np.count_nonzero(~np.isfinite(f)))
            better = f < pbest_f
            pbest[better] = Z[better]
            pbest_f[better] = f[better]
            i = int(np.argmin(pbest_f))
            old = gf
            if pbest_f[i] < gf:
                g, gf = pbest[i].copy(), float(pbest_f[i])
            it += 1
            history.append(gf)
            if np.isfinite(old) and old - gf <= ftol * (1.0 + abs(gf)):
                stall += 1
            else:
                stall = 0
            write(it)
            if bar is not None:
                bar.update(1)
                bar.set_postfix(best=f"{gf:.6g}")
            if callback is not None and callback(it, to_phys(g), gf):
                stop_reason = "callback"
                break
            if stall_iterations is not None and stall >= stall_iterations:
                stop_reason = f"stalled {stall_iterations} iterations"
                break
    if bar is not None:
        bar.close()
    return OptimizeResult(x=to_phys(g), fun=gf, nfev=nfev, ncalls=ncalls, nit=it, n_inf=n_inf,
                          stop_reason=stop_reason, history=np.array(history), method="pso",
                          wall_s=time.perf_counter() - t0, resumed_from=it0, settings=settings)


def de(fun: Callable[[np.ndarray], np.ndarray], lower, upper, *, popsize: int = 10,
       iterations: int = 100, seed: int | None = 0, tol: float = 0.0, atol: float = 0.0,
       mutation=(0.5, 1.0), recombination: float = 0.7, strategy: str = "best1bin",
       progress: bool = True, x0=None, checkpoint: str | Path | None = None,
       resume: bool = False) -> OptimizeResult:
    """Minimise a batched criterion with scipy's differential evolution.

    Parameters
    ----------
    fun : callable
        ``fun(X (S, k)) -> (S,)`` as for :func:`pso`.
    lower, upper : array (k,)
    popsize : int
        Population multiplier: the population has ``popsize * k`` members
        (scipy's convention), so 10 x 8 parameters = 80 members.
    iterations : int
        ``maxiter`` (generations after the initial population).
    seed : int or None
    tol, atol : float
        scipy's convergence tolerances (0: run all generations).
    mutation, recombination, strategy :
        Passed to scipy.
    progress : bool
        tqdm bar with the best criterion.
    x0 : array (k,), optional
    checkpoint : path, optional
        ``.npz`` with the population after every generation.
    resume : bool
        Restart from the checkpointed population (``init=``) for the
        remaining generations. Unlike :func:`pso`, this is not bit-for-bit
        the uninterrupted run: scipy's generator state is not restored.

    Returns
    -------
    OptimizeResult
        ``nfev`` counts members (scipy's own ``nfev`` counts members too in
        recent versions; ours is counted in the wrapper), ``ncalls`` the
        batched calls: 80 + 100 x 80 = 8080 for the settings above.

    Notes
    -----
    With ``vectorized=True`` scipy passes ``X`` with shape (k, S) and
    ``updating='deferred'``; the wrapper transposes it. Infinite values
    are replaced by a finite penalty (1e300) for scipy's bookkeeping
    (its convergence test takes a standard deviation of the energies) and
    counted in ``n_inf``.
    """
    from scipy.optimize import differential_evolution

    lo, hi = _check_box(lower, upper)
    k = lo.size
    if popsize < 1 or popsize * k < 5:
        raise OptionError(f"DE needs a population of at least 5 members (popsize * k), "
                          f"got {popsize} x {k}")
    counts = dict(nfev=0, ncalls=0, n_inf=0)
    history: list[float] = []
    best = [np.inf]
    ck = Path(checkpoint) if checkpoint is not None else None
    it0 = 0
    init: object = "latinhypercube"
    if resume:
        if ck is None or not ck.exists():
            raise OptionError(f"cannot resume: checkpoint {ck} does not exist")
        d = np.load(ck)
        init = np.asarray(d["population"], dtype=float)
        it0 = int(d["it"])
        history = [float(v) for v in d["history"]]
        best[0] = float(d["best"])
    PEN = 1e100

    def wrapped(Xt):
        X = np.atleast_2d(np.asarray(Xt, dtype=float).T)
        f = _evaluate(fun, X)
        counts["nfev"] += X.shape[0]
        counts["ncalls"] += 1
        bad = ~np.isfinite(f)
        counts["n_inf"] += int(np.count_nonzero(bad))
        if (~bad).any():
            best[0] = min(best[0], float(np.min(f[~bad])))
        if counts["ncalls"] == 1 and not resume:
            history.append(best[0])          # best of the initial population
        return np.where(bad, PEN, f)

    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=iterations, initial=it0, desc="DE", unit="gen", dynamic_ncols=True)
    gen = [it0]

    def cb(intermediate_result):
        gen[0] += 1
        history.append(best[0])
        if bar is not None:
            bar.update(1)
            bar.set_postfix(best=f"{best[0]:.6g}")
        if ck is not None:
            tmp = ck.with_name(ck.name + ".tmp.npz")
            np.savez(tmp, population=np.asarray(intermediate_result.population),
                     it=np.array(gen[0]), history=np.array(history), best=np.array(best[0]))
            os.replace(tmp, ck)
        return False

    t0 = time.perf_counter()
    kw = dict(strategy=strategy, maxiter=max(iterations - it0, 0), popsize=popsize, tol=tol,
              atol=atol, mutation=mutation, recombination=recombination, polish=False,
              init=init, vectorized=True, updating="deferred", callback=cb)
    if x0 is not None and not resume:
        kw["x0"] = np.clip(np.asarray(x0, float), lo, hi)
    res = differential_evolution(wrapped, list(zip(lo, hi)), rng=seed, **kw)
    if bar is not None:
        bar.close()
    fun_best = float(res.fun) if res.fun < PEN else np.inf
    settings = dict(method="de", popsize=popsize, members=popsize * k, seed=seed,
                    iterations=iterations, strategy=strategy,
                    mutation=[float(v) for v in np.atleast_1d(mutation)],
                    recombination=recombination, lower=lo.tolist(), upper=hi.tolist())
    return OptimizeResult(x=np.asarray(res.x, dtype=float), fun=fun_best, nfev=counts["nfev"],
                          ncalls=counts["ncalls"], nit=gen[0], n_inf=counts["n_inf"],
                          stop_reason=str(res.message), history=np.array(history), method="de",
                          wall_s=time.perf_counter() - t0, resumed_from=it0, settings=settings)


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
    """
    from scipy.optimize import minimize

    lo, hi = _check_box(lower, upper)
    width = hi - lo
    k = lo.size
    nfev = [0]
    cache: dict = {}

    def fg(z):
        z = np.clip(np.asarray(z, float), 0.0, 1.0)
        key = z.tobytes()
        if key in cache:
            return cache[key]
        Zp = np.clip(z + step * np.eye(k), 0.0, 1.0)
        Zm = np.clip(z - step * np.eye(k), 0.0, 1.0)
        Zall = np.vstack([z[None], Zp, Zm])
        f = _evaluate(fun, lo + Zall * width)
        nfev[0] += Zall.shape[0]
        f0 = f[0]
        if not np.isfinite(f0):
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
        cache.clear()
        cache[key] = out
        return out

    z0 = np.clip((np.asarray(x0, float) - lo) / width, 0.0, 1.0)
    r = minimize(fg, z0, jac=True, method="L-BFGS-B", bounds=[(0.0, 1.0)] * k,
                 options=dict(maxiter=maxiter, gtol=gtol, ftol=ftol))
    f0 = fg(z0)[0]
    z = np.clip(r.x, 0.0, 1.0)
    fz = fg(z)[0]
    if fz > f0:  # never return a worse point than the start
        z, fz = z0, f0
    return lo + z * width, float(fz), nfev[0], str(r.message)

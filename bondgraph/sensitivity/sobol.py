"""Global sensitivity: Sobol' indices over a parameter box.

:func:`sobol_indices` wraps SALib: Saltelli's extension of the Sobol'
sequence (``SALib.sample.sobol``) and the Sobol'/Saltelli estimators with
bootstrap confidence intervals (``SALib.analyze.sobol``): first-order S1,
total ST and second-order S2 indices (Sobol' 2001; Saltelli 2002; Saltelli
et al. 2010). The whole sample is evaluated in batches:
:func:`global_sensitivity` evaluates the NLL of the UKF for all parameter
sets of a chunk in one :func:`bondgraph.inference.ukf.ukf_nll` call, and
chosen outputs by one batched fixed-step simulation per chunk
(:func:`simulate_batch`).

References
----------
Saltelli, A. (2002). Making best use of model evaluations to compute
sensitivity indices. Comput. Phys. Commun. 145(2), 280-297.
Saltelli, A., Annoni, P., Azzini, I., Campolongo, F., Ratto, M., Tarantola,
S. (2010). Variance based sensitivity analysis of model output. Comput.
Phys. Commun. 181(2), 259-270.
Sobol', I. M. (2001). Global sensitivity indices for nonlinear mathematical
models and their Monte Carlo estimates. Math. Comput. Simul. 55, 271-280.
"""

from __future__ import annotations

import time
import warnings
from dataclasses import dataclass
from typing import Any, Callable, Mapping, Sequence

import numpy as np

from bondgraph.core.progress import bar as progress_bar
from bondgraph.errors import SensitivityError
from bondgraph.inference.executor import Executor
from bondgraph.inference.problem import Problem
from bondgraph.numerics.forward_sensitivity import check_params
from bondgraph.numerics.integrators import simulate_batch  # noqa: F401 (re-exported)

#: transforms of the NLL before its Sobol' analysis (:func:`global_sensitivity`)
NLL_TRANSFORMS = ("log", "none")


@dataclass(frozen=True)
class SobolOptions:
    """Options of a Sobol' analysis (:func:`sobol_indices`,
    :func:`global_sensitivity`; Saltelli et al. 2010).

    Parameters
    ----------
    N : int
        Base sample size, rounded up to a power of two (Sobol' sequence);
        ``N (2k + 2)`` evaluations with second-order indices, ``N (k + 2)``
        without.
    second_order : bool
        Also the second-order indices S2.
    seed : int, optional
        Scrambling of the sequence and bootstrap.
    chunk : int, optional
        Largest number of rows per call of the batched function (None: all
        at once).
    conf_level : float
        Level of the bootstrap confidence intervals, in (0, 1).
    num_resamples : int
        Bootstrap resamples.
    progress : bool
        tqdm progress bar over the chunks.
    outputs : tuple of str
        :func:`global_sensitivity`: model outputs whose noise-free time-mean
        over the record also gets indices.
    box : (lower (k,), upper (k,)), optional
        :func:`global_sensitivity`: the box (default the model's bounds, or
        θ (1 ± box_rel) with ``box_rel``).
    box_rel : float, optional
        Relative half-width of the box around θ.
    nll_transform : {"log", "none"}
        Indices of ln(1 + NLL − min NLL) (:func:`log_excess`) or of the NLL.
    workers : int
        Local Dask worker processes evaluating the chunks (1: in process).
    scheduler : str, optional
        An existing Dask scheduler's address (``tcp://HOST:PORT``). Results
        depend neither on it nor on ``workers``.

    Raises
    ------
    SensitivityError
        A value out of its domain (named).
    """

    N: int = 256
    second_order: bool = True
    seed: int | None = 0
    chunk: int | None = 256
    conf_level: float = 0.95
    num_resamples: int = 100
    progress: bool = False
    outputs: tuple = ()
    box: tuple | None = None
    box_rel: float | None = None
    nll_transform: str = "log"
    workers: int = 1
    scheduler: str | None = None

    def __post_init__(self):
        if isinstance(self.N, bool) or not isinstance(self.N, (int, np.integer)) or self.N < 2:
            raise SensitivityError(f"SobolOptions.N (--global) must be an integer >= 2, got "
                                   f"{self.N!r}")
        if self.chunk is not None and (not isinstance(self.chunk, (int, np.integer))
                                       or self.chunk < 1):
            raise SensitivityError(f"SobolOptions.chunk must be an integer >= 1 or None, got "
                                   f"{self.chunk!r}")
        if not 0 < self.conf_level < 1:
            raise SensitivityError(f"SobolOptions.conf_level must lie in (0, 1), got "
                                   f"{self.conf_level!r}")
        if self.nll_transform not in NLL_TRANSFORMS:
            raise SensitivityError(f"unknown NLL transform '{self.nll_transform}' (log, none)")
        if self.box_rel is not None and not self.box_rel > 0:
            raise SensitivityError(f"SobolOptions.box_rel must be > 0, got {self.box_rel!r}")
        object.__setattr__(self, "outputs", tuple(self.outputs))


def _pow2(n: int) -> int:
    n = max(int(n), 2)
    return 1 << (n - 1).bit_length()


def sobol_indices(fun: Callable[[np.ndarray], np.ndarray], names: Sequence[str], lower, upper,
                  options: SobolOptions | None = None, *,
                  output_names: Sequence[str] | None = None, desc: str = "sobol",
                  transforms: Mapping[str, Callable[[np.ndarray], np.ndarray]] | None = None,
                  executor: Executor | None = None) -> dict:
    """Sobol' indices of a batched function over a box (SALib; Saltelli 2002).

    Parameters
    ----------
    fun : callable
        ``fun(X (S, k)) -> (S,)`` or ``(S, m)``: evaluates a whole chunk of
        the sample in one call.
    names : sequence of str (k)
    lower, upper : arrays (k,)
        The box (uniform distributions).
    options : SobolOptions, optional
        Sample size ``N``, second order, seed, chunk, confidence level and
        resamples, progress bar (the box and outputs fields are
        :func:`global_sensitivity`'s).
    output_names : sequence of str (m), optional
    desc : str
        The progress bar's label.
    transforms : dict output name -> callable, optional
        Applied to an output's whole column (after non-finite values are
        replaced) before the analysis, e.g. :func:`log_excess`.
    executor : Executor, optional
        Where the chunks are evaluated (:class:`bondgraph.inference.executor.Executor`:
        Dask workers when it is distributed; ``fun`` is sent to them once).
        The chunks do not depend on it, nor do the results.

    Returns
    -------
    dict
        ``N, evaluations, names, lower, upper, conf_level``, ``failed``
        (non-finite evaluations per output, replaced by the largest finite
        value before the analysis), and ``indices``: per output name a dict
        ``S1, S1_conf, ST, ST_conf`` (k,) and ``S2, S2_conf`` (k, k, upper
        triangle; NaN elsewhere).

    Raises
    ------
    SensitivityError
        Bad box, fewer than two parameters, or all evaluations non-finite.
    """
    o = SobolOptions() if options is None else options
    names = list(names)
    k = len(names)
    lo, hi = np.asarray(lower, float), np.asarray(upper, float)
    if lo.shape != (k,) or hi.shape != (k,) or not np.all(hi > lo):
        raise SensitivityError(f"the box must have lower < upper for each of {names}")
    if k < 2:
        raise SensitivityError("Sobol' indices need at least two parameters")
    Np = _pow2(o.N)
    problem = dict(num_vars=k, names=names, bounds=[[float(a), float(b)] for a, b in zip(lo, hi)])
    from SALib.sample import sobol as sobol_sample   # deferred: SALib pulls in pandas, scipy.stats

    X = sobol_sample.sample(problem, Np, calc_second_order=o.second_order, seed=o.seed)
    t_wall = time.perf_counter()
    Y = _evaluate_chunks(fun, X, o.chunk, o.progress, desc, executor)
    m = Y.shape[1]
    onames = list(output_names) if output_names is not None else (
        ["y"] if m == 1 else [f"y{i}" for i in range(m)])
    if len(onames) != m:
        raise SensitivityError(f"{len(onames)} output names for {m} outputs")
    out: dict[str, Any] = dict(N=Np, evaluations=int(X.shape[0]), names=names, lower=lo,
                               upper=hi, conf_level=o.conf_level, second_order=o.second_order,
                               failed={}, wall_time_s=time.perf_counter() - t_wall, indices={})
    for c, on in enumerate(onames):
        yc, out["failed"][on] = _prepared_column(Y[:, c], on, (transforms or {}).get(on))
        out["indices"][on] = _analyse_output(problem, yc, o.second_order, o.conf_level,
                                             o.num_resamples, o.seed)
    return out


def _prepared_column(y: np.ndarray, name: str, transform) -> tuple[np.ndarray, int]:
    """An output column with its non-finite values replaced by the largest
    finite one, then transformed: ``(column, number replaced)``.

    Raises
    ------
    SensitivityError
        Every value non-finite.
    """
    yc = y.copy()
    bad = ~np.isfinite(yc)
    if bad.all():
        raise SensitivityError(f"every evaluation of '{name}' is non-finite")
    if bad.any():
        yc[bad] = np.max(yc[~bad])
    if transform is not None:
        yc = np.asarray(transform(yc), dtype=float)
    return yc, int(bad.sum())


def _evaluate_chunks(fun, X, chunk, progress: bool, desc: str,
                     executor: Executor | None = None) -> np.ndarray:
    """``fun`` over the sample X (S, k) in chunks: (S, m); on ``executor``'s
    Dask workers when it is distributed (same chunks, same order)."""
    S = X.shape[0]
    step = int(chunk) if chunk else S
    if executor is not None and executor.distributed:
        parts = executor.map(_chunk_values, fun, [X[a:a + step] for a in range(0, S, step)])
        return np.concatenate(parts, axis=0)
    parts = []
    it = range(0, S, step)
    if progress:
        it = progress_bar(it, desc=desc, unit="chunk", total=(S + step - 1) // step,
                          leave=False)
    for a in it:
        parts.append(np.asarray(fun(X[a:a + step]), dtype=float).reshape(min(step, S - a), -1))
    return np.concatenate(parts, axis=0)


def _chunk_values(fun, Xc: np.ndarray) -> np.ndarray:
    """One chunk's values (rows of Xc, m) on a worker."""
    return np.asarray(fun(Xc), dtype=float).reshape(Xc.shape[0], -1)


def _analyse_output(problem, yc, second_order, conf_level, num_resamples, seed) -> dict:
    """SALib's Sobol' analysis of one output column: S1, ST (and S2) with
    their confidence half-widths, and the column's variance."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        from SALib.analyze import sobol as sobol_analyze

        Si = sobol_analyze.analyze(problem, yc, calc_second_order=second_order,
                                   conf_level=conf_level, num_resamples=num_resamples,
                                   seed=seed)
    d = {key: np.asarray(Si[key], dtype=float) for key in ("S1", "S1_conf", "ST", "ST_conf")}
    if second_order:
        d["S2"] = np.asarray(Si["S2"], dtype=float)
        d["S2_conf"] = np.asarray(Si["S2_conf"], dtype=float)
    d["variance"] = float(np.var(yc))
    return d


def log_excess(y: np.ndarray) -> np.ndarray:
    """ln(1 + y − min y): a monotone transform of the NLL for Sobol' indices.

    Over a wide parameter box the NLL spans orders of magnitude (sets that
    drive the filter far from the data reach 10⁶-10⁹ nats); its variance,
    and so its Sobol' indices and their bootstrap intervals, is then
    decided by a handful of such sets. On the log scale every decade of
    misfit counts alike. (Sobol' indices are not invariant under nonlinear
    transforms: they answer "which parameters decide how many orders of
    magnitude the fit is off".)
    """
    y = np.asarray(y, dtype=float)
    return np.log1p(y - np.min(y))


def global_sensitivity(problem: Problem, params: Sequence[str],
                       options: SobolOptions | None = None) -> dict:
    """Sobol' indices of the UKF NLL (and of the time-means of chosen
    outputs) over a parameter box (Sobol' 2001; Saltelli et al. 2010).

    Parameters
    ----------
    problem : Problem
        The model on the record (:func:`bondgraph.inference.problem.make_problem`):
        its arrays (y is used by the NLL only), its θ (the values of the
        parameters outside ``params``, the centre of a ``box_rel`` box), its
        prior and filter options; the outputs' simulation uses its method,
        substeps and hold too.
    params : sequence of str (k)
    options : SobolOptions, optional
        Sample size, seed, chunk, box, outputs, NLL transform, and where the
        chunks run.

    Returns
    -------
    dict
        As :func:`sobol_indices`, outputs named ``"NLL"`` and
        ``"mean(<output>)"``; ``nll_transform``, ``nll_min``, ``nll_max``, ``box``.

    Raises
    ------
    SensitivityError
        Bad parameters or box.
    """
    o = SobolOptions() if options is None else options
    model = problem.model
    params = check_params(model, params)
    th = problem.theta
    fun = _nll_and_means(problem, params, o.outputs)
    lo, hi = _sobol_box(model, params, th, o.box, o.box_rel)
    seen: dict[str, float] = {}

    def tr(yv):
        seen.update(nll_min=float(np.min(yv)), nll_max=float(np.max(yv)))
        return log_excess(yv) if o.nll_transform == "log" else yv

    executor = Executor(o.workers, o.scheduler)
    try:
        res = sobol_indices(fun, params, lo, hi, o,
                            output_names=["NLL"] + [f"mean({n})" for n in o.outputs],
                            desc="Sobol NLL", transforms={"NLL": tr}, executor=executor)
    finally:
        executor.close()
    res.update(nll_transform="ln(1 + NLL - min NLL)" if o.nll_transform == "log" else "none",
               **seen)
    res["box"] = "custom" if o.box is not None else (f"theta*(1±{o.box_rel:g})" if o.box_rel
                                                     else "model bounds")
    return res


def _sobol_box(model, params, th, box, box_rel) -> tuple[np.ndarray, np.ndarray]:
    """The box of the Sobol' sample: given, θ (1 ± box_rel) (the box width
    for a zero θ), or the model's bounds."""
    idx = model.param_indices(params)
    if box is not None:
        lo, hi = (np.asarray(b, float) for b in box)
        return lo, hi
    if box_rel is not None:
        c = th[idx]
        w = np.abs(c) * box_rel
        w = np.where(w > 0, w, box_rel * (model.upper[idx] - model.lower[idx]))
        return c - w, c + w
    return model.lower[idx], model.upper[idx]


def _nll_and_means(problem: Problem, params, outputs):
    """The batched function of the Sobol' sample: X (S, k) -> columns
    [NLL, mean(output) ...] (S, 1 + len(outputs))."""
    model, th, ukf = problem.model, problem.theta, problem.ukf
    t, u, _ = problem.arrays
    oidx = [model.output_index(o) for o in outputs]

    def fun(X):
        sets = model.expand_theta(params, X, th)
        cols = [problem.nll(sets).nll]
        if oidx:
            Ys = simulate_batch(model, t, u, sets, problem.x0, method=ukf.method,
                                substeps=ukf.substeps, hold=ukf.hold)
            cols += [np.mean(Ys[:, :, j], axis=0) for j in oidx]
        return np.column_stack(cols)
    return fun

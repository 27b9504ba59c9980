"""Closing the loop with measured data: trace the residual to an effect the
model lacks, add it to the graph, re-estimate, report the error before and
after.

One step of the loop:

1. **Fit** the current model: maximum-likelihood estimate of the chosen
   parameters with the batched UKF (:mod:`bondgraph.inference.estimate`), warm-started.
2. **Residuals**: UKF innovations and free-run simulation errors per output;
   whiteness, NIS, bias, spectral peaks, operating regions
   (:mod:`bondgraph.diagnose.residuals`).
3. **Evidence** for every candidate of the effect library
   (:mod:`bondgraph.diagnose.effects`) at every place the graph offers:

   * additive effects (friction laws, drags, offsets, gains, sensor
     offset/gain/rectification) are all added at once to a *probe* model at
     their neutral value β = 0. One batched UKF run with each β nudged gives
     the innovation signatures J = ∂ε/∂β; with whitened innovations e and
     signatures G the score (Lagrange-multiplier) statistic of a candidate
     with columns c is LM = bᵀ A⁻¹ b, b = Σ G_cᵀ e, A = Σ G_cᵀ G_c: how much
     of the innovation energy the candidate's signature explains. Under "the
     effect is absent" LM ~ χ²(k) (Rao 1948; Engle 1984).
   * structural effects (slip, compliance, low-pass, saturation, dead zone,
     end stops, backlash, disturbance) have no neutral value; each is built
     and fitted over a grid of its parameter in one batched UKF run, giving
     the likelihood-ratio statistic LR = 2 (NLL₀ − NLL₁) ~ χ²(k).

   Both statistics are χ²(k): candidates are ranked by the predicted
   decrease of AIC, statistic − 2k, which is comparable between them.
4. **Confirm** the best few by building the real augmented graph and fitting
   its new parameters (likelihood ratio), then **accept** the best one only
   if, after re-estimating all parameters warm-started, the information
   criterion (AIC by default, or BIC) and the residual whiteness (sum of the
   Ljung-Box statistics) both improve.
5. Repeat until no candidate is significant (Bonferroni-corrected p-value
   above ``significance``) or nothing is accepted.

The user's graph is never modified: every step works on a copy, and the
final augmented graph is written out as a new declared model
(``augmented_model.py``, which rebuilds it from the user's builder plus the
named effects), with its generated code and the estimates. Every step is
logged to ``loop.log``, and the report (``report.json``, ``report.md``,
PNG plots) is rewritten after every step, so an interrupted run keeps its
work.

References
----------
Rao, C. R. (1948). Large sample tests of statistical hypotheses concerning
several parameters. Proc. Cambridge Phil. Soc. 44, 50-57. Engle, R. F. (1984).
Wald, likelihood ratio and Lagrange multiplier tests in econometrics.
Handbook of Econometrics II, ch. 13. Akaike, H. (1974). A new look at the
statistical model identification. IEEE TAC 19(6), 716-723. Ljung & Box
(1978), see :mod:`bondgraph.diagnose.residuals`.
"""

from __future__ import annotations

import math
import time
import warnings
from dataclasses import asdict, dataclass, field
from typing import Any, Callable, Mapping, Sequence

import numpy as np
import sympy as sp

from bondgraph.core.equations import derive
from bondgraph.core.graph import BondGraph
from bondgraph.diagnose.effects import (
    DEFAULT_EFFECTS,
    Effect,
    Scales,
    Target,
    get_effect,
    probe_graph,
)
from bondgraph.errors import BondGraphError, ModelError
from bondgraph.inference.options import UKFOptions
from bondgraph.numerics.model import Model

CANDIDATE_FUNCTIONS = ("f", "h", "dfdx", "f_dfdx")

#: factors applied to the estimated noise intensities when a candidate is
#: screened: a missing effect inflates them, so a candidate's likelihood is
#: profiled over them (their likelihood is far from quadratic near zero)
NOISE_FACTORS = (1.0, 0.3, 0.1, 0.01, 0.001)


# ----------------------------------------------------------------- records
@dataclass
class Candidate:
    """Evidence for one effect at one place."""

    effect: str
    title: str
    target: Target
    kind: str                      # "score" (additive) or "likelihood ratio" (structural)
    statistic: float               # χ² statistic
    dof: int
    p_value: float
    score: float                   # predicted AIC decrease: statistic - 2 dof
    explained: float | None = None  # fraction of whitened innovation energy (score test)
    values: dict = field(default_factory=dict)
    confirmed_statistic: float | None = None
    last_resort: bool = False
    #: candidates whose innovation signatures are indistinguishable from this
    #: one in this record (|correlation| > 0.999 after the estimated
    #: parameters are partialled out): the data cannot tell them apart
    equivalent: list = field(default_factory=list)

    @property
    def label(self) -> str:
        return f"{self.effect} @ {self.target.name}"

    def to_dict(self) -> dict:
        d = asdict(self)
        d["target"] = {"kind": self.target.kind, "name": self.target.name}
        d["label"] = self.label
        return _jsonable(d)


@dataclass
class Fit:
    """A fitted model: graph, generated model, estimated names, full θ, NLL,
    stored UKF run, residual report, metric value."""

    graph: BondGraph
    model: Model
    params: list[str]
    theta: np.ndarray
    nll: float
    ukf: Any
    residuals: Any
    metric: float
    sim_y: np.ndarray | None
    std: dict = field(default_factory=dict)
    n_obs: int = 0

    @property
    def k(self) -> int:
        return len(self.params)

    def aic(self) -> float:
        return 2 * self.nll + 2 * self.k

    def bic(self) -> float:
        return 2 * self.nll + self.k * math.log(max(self.n_obs, 1))

    def estimates(self) -> dict:
        return {n: float(self.theta[self.model.param_index(n)]) for n in self.params}


@dataclass
class LoopSettings:
    """Options of :func:`run_loop`.

    Attributes
    ----------
    params : list of str
        Parameters of the declared model estimated at every step.
    metric : str or callable
        Error measure reported before/after: ``"nrmse_sim"`` (mean over
        outputs of RMS(free-run simulation error)/std(measurement)),
        ``"rmse_sim"`` (RMS over outputs, output units), ``"rmse_pred"``
        (RMS of the one-step innovations), or a callable
        ``metric(fit, data) -> float`` with attribute ``name``.
    criterion : {"aic", "bic"}
    max_steps : int
    significance : float
        Family-wise level for "a significant effect is left" (Bonferroni over
        the candidates evaluated).
    confirm_top : int
        Candidates confirmed by a real fit per step.
    structural : bool
        Evaluate structural effects (slower: one model each).
    effects : sequence of Effect
    x0, P0 : arrays, optional
        UKF prior (default: the record's true x0 if it has one, else the
        model's X0; :func:`bondgraph.inference.ukf.default_P0`).
    P0_std : dict
        Prior standard deviations of named initial states (e.g. the grade on
        a level track), overriding ``P0``'s diagonal.
    fixed : dict
        Known parameter values (name -> value) set before every fit.
    initial_params : list of str, optional
        Parameters of the initial fit (default ``params``; later steps
        re-estimate all of ``params``). CED fits only its noise intensity
        first, so that "before" is the published linear model.
    ukf : UKFOptions
        Options of :func:`bondgraph.inference.ukf.ukf_nll` (alpha, method, substeps ...).
    sim_method : str
        Solver of the free-run simulations (:func:`bondgraph.numerics.simulate.simulate`).
    fit_iterations, confirm_iterations : int
        Fisher-scoring iterations of each warm-started re-estimation and of
        each candidate's confirmation fit (L-BFGS-B if scoring fails).
    metric_tolerance : float
        Reject an effect whose reported error grows by more than this factor
        (default: no limit; acceptance rests on the criterion and whiteness).
    structural_threshold : float
        Skip the (slow) structural candidates when an additive effect already
        explains more than this share of the innovation energy.
    chunk : int
        Parameter sets per batched UKF run.
    """

    params: list[str]
    metric: Any = "nrmse_sim"
    criterion: str = "aic"
    max_steps: int = 4
    significance: float = 0.01
    confirm_top: int = 3
    structural: bool = True
    effects: Sequence[Effect] = DEFAULT_EFFECTS
    x0: Any = None
    P0: Any = None
    P0_std: dict = field(default_factory=dict)
    fixed: dict = field(default_factory=dict)
    initial_params: list | None = None
    ukf: UKFOptions = field(default_factory=UKFOptions)     # ros2, 1 substep, alpha 1
    sim_method: str = "BDF"
    fit_iterations: int = 10
    confirm_iterations: int = 6
    metric_tolerance: float = float("inf")
    structural_threshold: float = 0.5
    chunk: int = 48
    metric_name: str | None = None


@dataclass
class Step:
    """One accepted effect (or the final "nothing significant left")."""

    effect: str
    attached_to: str
    metric: str
    error_before: float
    error_after: float
    nll_before: float
    nll_after: float
    criterion_before: float
    criterion_after: float
    whiteness_before: float
    whiteness_after: float
    parameters: dict
    statistic: float
    p_value: float


# ----------------------------------------------------------------- helpers
def _jsonable(obj):
    if isinstance(obj, dict):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, (np.floating, float)):
        v = float(obj)
        return v if math.isfinite(v) else (None if math.isnan(v) else ("inf" if v > 0 else "-inf"))
    if isinstance(obj, (np.integer,)):
        return int(obj)
    if isinstance(obj, np.ndarray):
        return _jsonable(obj.tolist())
    if isinstance(obj, Target):
        return {"kind": obj.kind, "name": obj.name}
    return obj


class _Data:
    """The record, resolved for one model at a time."""

    def __init__(self, experiment):
        self.exp = experiment

    def arrays(self, model: Model):
        t = np.asarray(self.exp.t, dtype=float)
        u = self.exp.inputs_for(model, defaults_ok=True) if model.n_u else np.zeros((t.size, 0))
        y = self.exp.outputs_for(model)
        return t, u, y


def _metric_name(settings: LoopSettings, model: Model) -> str:
    if settings.metric_name:
        return settings.metric_name
    m = settings.metric
    if callable(m):
        return getattr(m, "name", getattr(m, "__name__", "custom metric"))
    return {"nrmse_sim": "free-run simulation NRMSE (RMS error / std of the measurement, "
                         "mean over outputs)",
            "rmse_sim": "free-run simulation RMS error (over outputs, output units)",
            "rmse_pred": "RMS of the one-step-ahead innovations (output units)"}.get(m, str(m))


def _compute_metric(settings: LoopSettings, fit: Fit, data: _Data) -> float:
    m = settings.metric
    t, u, y = data.arrays(fit.model)
    if callable(m):
        return float(m(fit, data))
    if m == "rmse_pred":
        e = fit.ukf.innovations[:, 0, :]
        return float(np.sqrt(np.nanmean(e**2)))
    if fit.sim_y is None:
        return float("inf")
    err = y - fit.sim_y
    if m == "rmse_sim":
        return float(np.sqrt(np.nanmean(err**2)))
    vals = []
    for i in range(y.shape[1]):
        ok = np.isfinite(err[:, i])
        if ok.sum() < 2:
            continue
        sd = np.nanstd(y[ok, i])
        vals.append(np.sqrt(np.mean(err[ok, i] ** 2)) / (sd if sd > 0 else 1.0))
    return float(np.mean(vals)) if vals else float("inf")


# ------------------------------------------------------------------ fitting
class Loop:
    """The residual-tracing loop; see the module docstring. Use
    :func:`run_loop`."""

    def __init__(self, graph: BondGraph, experiment, settings: LoopSettings,
                 log: Callable[[str], None] | None = None, progress: bool = True,
                 on_update: Callable[["Loop", "Fit", bool], None] | None = None):
        self.user_graph = graph
        self.data = _Data(experiment)
        self.s = settings
        self.progress = progress
        self.on_update = on_update
        self._print = log if log is not None else print
        self.steps: list[Step] = []
        self.rejected: list[dict] = []
        self.rankings: list[list[Candidate]] = []
        self.applied: list[dict] = []  # effect, target, values (for the augmented model file)
        self.t0 = time.perf_counter()

    # ------------------------------------------------------------ logging
    def log(self, msg: str) -> None:
        self._print(f"[{time.perf_counter() - self.t0:7.1f} s] {msg}")

    # ------------------------------------------------------------ models
    def model_of(self, graph: BondGraph) -> Model:
        return Model.from_graph(graph, functions=CANDIDATE_FUNCTIONS, name=f"_loop_{graph.name}")

    def x0_for(self, model: Model) -> np.ndarray:
        if self.s.x0 is not None:
            x = np.asarray(self.s.x0, dtype=float)
            if x.shape == (model.n_x,):
                return x
        x = model.x0.copy()
        meta_x0 = (getattr(self.data.exp, "meta", {}) or {}).get("x0") or {}
        for k, v in meta_x0.items():
            if k in model.states:
                x[model.state_index(k)] = float(v)
        return x

    def P0_for(self, model: Model, x0) -> np.ndarray:
        """UKF prior covariance: ``P0`` if it fits the model, else the default
        (5 % of |x0|), with the standard deviations of ``P0_std`` (by state
        name) imposed, e.g. a level test track: {"theta_g": 0.002}."""
        from bondgraph.inference.ukf import default_P0

        if self.s.P0 is not None:
            P = np.asarray(self.s.P0, dtype=float)
            if P.shape in ((model.n_x,), (model.n_x, model.n_x)):
                return np.diag(P) if P.ndim == 1 else P
            # states added by effects: fall back to the default variance
        P = default_P0(model, x0)
        for name, sd in (self.s.P0_std or {}).items():
            if name in model.states:
                i = model.state_index(name)
                P[i, :] = 0.0
                P[:, i] = 0.0
                P[i, i] = float(sd) ** 2
        return P

    def criterion(self, model: Model, names: Sequence[str], base: np.ndarray):
        from bondgraph.inference.estimate import Criterion

        t, u, y = self.data.arrays(model)
        x0 = self.x0_for(model)
        return Criterion(model, t, u, y, names, base, x0, self.P0_for(model, x0),
                         options=self.s.ukf, chunk=self.s.chunk)

    def bounds_for(self, model: Model, names, theta) -> tuple[np.ndarray, np.ndarray]:
        lo, hi = model.bounds(names)
        x = np.array([theta[model.param_index(n)] for n in names])
        lo = np.minimum(lo, x)
        hi = np.maximum(hi, x)
        return lo, hi

    def fit(self, graph: BondGraph, params: list[str], theta_start: Mapping[str, float] | None,
            what: str, model: Model | None = None, iterations: int | None = None) -> Fit:
        """Warm-started ML fit of ``params``; everything else fixed."""
        from bondgraph.inference.optimize import minimize_batched
        from bondgraph.inference.ukf import ukf_nll

        model = model or self.model_of(graph)
        theta = model.theta0.copy()
        for k, v in {**self.s.fixed, **(theta_start or {})}.items():
            if k in model.params:
                theta[model.param_index(k)] = v
        params = [p for p in params if p in model.params]
        iters = self.s.fit_iterations if iterations is None else int(iterations)
        t, u, y = self.data.arrays(model)
        x0 = self.x0_for(model)
        std: dict = {}
        if params and iters > 0:
            from bondgraph.inference.fisher import fisher_scoring

            idx = [model.param_index(n) for n in params]
            lo, hi = self.bounds_for(model, params, theta)
            # log scale and decade moves for the noise intensities only: a
            # physical parameter with a wide box (R_a in [0.05, 10]) is no scale
            # parameter, and decade jumps strand it on a bound
            noise = self.noise_params(graph)
            scale = np.array([n in noise and lo[i] > 0 for i, n in enumerate(params)])
            try:
                theta, _, F, runs = fisher_scoring(model, t, u, y, theta, idx, lo, hi, x0,
                                                   self.P0_for(model, x0), options=self.s.ukf,
                                                   max_iter=iters, log_scale=scale)
                std = _cr_std(F, params)
            except (FloatingPointError, np.linalg.LinAlgError) as exc:
                self.log(f"  {what}: Fisher scoring failed ({exc}); falling back to L-BFGS-B")
                crit = self.criterion(model, params, theta)
                xs = np.array([theta[model.param_index(n)] for n in params])
                x, f, nfev, msg = minimize_batched(crit, xs, lo, hi, maxiter=iters)
                theta = crit.theta(x[None, :])[0]
        res = ukf_nll(model, t, u, y, theta[None, :], x0, self.P0_for(model, x0), store=True,
                      options=self.s.ukf)
        nll = float(res.nll[0])
        if not np.isfinite(nll):
            raise BondGraphError(f"{what}: the UKF failed at the fitted parameters "
                                 f"({res.reasons[0]})")
        sim_y = self.simulate(model, theta, res)
        from bondgraph.diagnose.residuals import analyze

        rep = analyze(res, model, t, u, y, sim_y=sim_y)
        fit = Fit(graph, model, list(params), theta, nll, res, rep, float("nan"), sim_y,
                  std=std, n_obs=int(res.n_obs.sum()))
        fit.metric = _compute_metric(self.s, fit, self.data)
        return fit

    def simulate(self, model: Model, theta, ukf_res) -> np.ndarray | None:
        """Free-run simulation from the first filtered state, measured inputs."""
        from bondgraph.numerics.simulate import simulate

        t, u, y = self.data.arrays(model)
        x0 = ukf_res.x_filt[0, 0, :]
        if not np.all(np.isfinite(x0)):
            x0 = self.x0_for(model)
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                sim = simulate(model, t, u, x0=x0, theta=theta, method=self.s.sim_method,
                               rtol=1e-6, atol=1e-9)
            return sim.y
        except Exception as exc:  # a model that cannot be simulated freely
            self.log(f"  free-run simulation failed ({str(exc).splitlines()[0]})")
            return None

    @staticmethod
    def noise_params(graph: BondGraph) -> set:
        """Names of parameters that appear only in process- or measurement-
        noise declarations (scale parameters of the filter, profiled by
        decades when candidates are screened)."""
        used_noise, used_model = set(), set()
        for v in list(graph.process_noise.values()) + [s.noise_std for s in graph.sensors.values()]:
            if isinstance(v, sp.Basic):
                used_noise |= {x.name for x in v.free_symbols}
        for el in graph.elements.values():
            for ex in el.expressions():
                used_model |= {x.name for x in ex.free_symbols}
        for s_ in graph.sensors.values():
            used_model |= {x.name for x in s_.expr.free_symbols}
        for ss in graph.signal_states.values():
            used_model |= {x.name for x in ss.rhs.free_symbols}
        return (used_noise - used_model) & set(graph.params)

    def _noise_variants(self, model: Model, fit: Fit, base: np.ndarray, factors) -> list:
        """Copies of ``base`` with the estimated noise intensities scaled by
        each factor (clipped to their box)."""
        names = [n for n in fit.params if n in self.noise_params(fit.graph) and n in model.params]
        if not names:
            return [base]
        out = []
        for f in factors:
            th = base.copy()
            for n in names:
                j = model.param_index(n)
                th[j] = float(np.clip(base[j] * f, model.lower[j], model.upper[j]))
            out.append(th)
        return out

    # ------------------------------------------------------------ scales
    def scales(self, fit: Fit) -> Scales:
        ss = derive(fit.graph)
        model = fit.model
        t, u, y = self.data.arrays(model)
        X = fit.ukf.x_filt[:, 0, :]
        sc = Scales(duration=float(t[-1] - t[0]) or 1.0, dt=float(np.median(np.diff(t))))
        args = (list(ss.states), list(ss.inputs), list(ss.params))

        def evaluate(expr):
            fn = sp.lambdify(args, expr, "numpy")
            vals = fn(X.T, u.T if u.size else np.zeros((0, t.size)), fit.theta)
            return np.broadcast_to(np.asarray(vals, dtype=float), t.shape)

        from bondgraph.core.elements import C, One, Source

        for name, el in fit.graph.elements.items():
            try:
                if isinstance(el, One):
                    v = evaluate(ss.variable(el.f))
                    sc.flow_rms[name] = float(np.sqrt(np.nanmean(v**2)))
                    sc.flow_max[name] = float(np.nanmax(np.abs(v)))
                elif isinstance(el, Source):
                    v = evaluate(ss.variable(el.value))
                    sc.source_max[name] = float(np.nanmax(np.abs(v)))
                elif isinstance(el, C) and el.q in ss.states:
                    v = X[:, ss.states.index(el.q)]
                    sc.storage_max[name] = float(np.nanmax(np.abs(v)))
            except Exception:
                continue
        for i, o in enumerate(model.outputs):
            sc.output_rms[o] = float(np.sqrt(np.nanmean(y[:, i] ** 2)))
        return sc

    # ------------------------------------------------------------ evidence
    def score_additive(self, fit: Fit, scales: Scales, effects) -> list[Candidate]:
        """Score test of every additive candidate with one probe model."""
        from scipy.stats import chi2

        from bondgraph.inference.ukf import ukf_nll

        exclude: set = set()
        while True:
            pg, cols = probe_graph(fit.graph, effects, scales, exclude)
            if not cols:
                return []
            try:
                pm = self.model_of(pg)
                break
            except BondGraphError as exc:
                # drop the targets on the failing causal path and retry
                bad = {e.replace("probe.", "", 1) for e in exc.elements} & \
                    {c.target.name for c in cols}
                if not bad:
                    raise
                self.log(f"  probe: no additive effects at {', '.join(sorted(bad))} "
                         f"({str(exc).splitlines()[0][:120]})")
                exclude |= bad
        base = pm.theta0.copy()
        for n in fit.model.params:
            base[pm.param_index(n)] = fit.theta[fit.model.param_index(n)]
        t, u, y = self.data.arrays(pm)
        x0 = self.x0_for(pm)
        P0 = self.P0_for(pm, x0)
        idx = [pm.param_index(c.param) for c in cols]
        # the currently estimated parameters: their signatures are partialled
        # out (efficient score test: the nuisance parameters re-adjust)
        nuis = [pm.param_index(n) for n in fit.params]
        nuis_delta = [1e-4 * max(abs(base[j]), 1e-3 * (pm.upper[j] - pm.lower[j]), 1e-12)
                      for j in nuis]
        # the size of a nudge: make each column's one-sample state (or output)
        # change small against the state (output) scale, then check linearity
        X = fit.ukf.x_filt[:, 0, :]
        ok = np.all(np.isfinite(X), axis=1)
        sel = np.flatnonzero(ok)[:: max(1, ok.sum() // 200)]
        xs, us = X[sel], u[sel]
        dt = scales.dt
        xscale = np.maximum(np.nanstd(X, axis=0), 1e-9)
        yscale = np.maximum(np.nanstd(y, axis=0), 1e-12)
        F0 = pm.f(xs, us, base)
        H0 = pm.h(xs, us, base)
        deltas = []
        for j in idx:
            th = base.copy()
            th[j] = 1.0
            dF = np.nanmax(np.abs((pm.f(xs, us, th) - F0) * dt / xscale))
            dH = np.nanmax(np.abs((pm.h(xs, us, th) - H0) / yscale))
            sens = max(dF, dH, 1e-300)
            deltas.append(1e-3 / sens)
        deltas = np.array(deltas)
        ladder = (1.0, 1e-2)
        sets = [base]
        for j, d in zip(idx, deltas):
            for s in ladder:
                th = base.copy()
                th[j] = d * s
                sets.append(th)
        for j, d in zip(nuis, nuis_delta):
            th = base.copy()
            th[j] = base[j] + d
            sets.append(th)
        sets = np.array(sets)
        n_lad = 1 + len(idx) * len(ladder)
        Dn = np.empty((len(nuis), t.size, pm.n_y))
        eps0 = S0 = None
        D = np.empty((len(ladder), len(cols)) + (t.size, pm.n_y))
        for a in range(0, len(sets), self.s.chunk):
            r = ukf_nll(pm, t, u, y, sets[a:a + self.s.chunk], x0, P0, store=True,
                        options=self.s.ukf)
            for q in range(r.nll.size):
                gi = a + q
                if gi == 0:
                    eps0 = r.innovations[:, 0, :].copy()
                    S0 = r.S[:, 0, :, :].copy()
                    continue
                if gi >= n_lad:
                    Dn[gi - n_lad] = r.innovations[:, q, :] if np.isfinite(r.nll[q]) else np.nan
                    continue
                c, l = divmod(gi - 1, len(ladder))
                D[l, c] = r.innovations[:, q, :] if np.isfinite(r.nll[q]) else np.nan
        # innovation signatures, with a linearity check between the two nudges
        nn = len(nuis)
        J = np.empty((t.size, pm.n_y, nn + len(cols)))
        for a_, d in enumerate(nuis_delta):
            J[:, :, a_] = (Dn[a_] - eps0) / d
        for c in range(len(cols)):
            j_big = (D[0, c] - eps0) / (deltas[c] * ladder[0])
            j_small = (D[1, c] - eps0) / (deltas[c] * ladder[1])
            use_small = ~np.all(np.isfinite(j_big)) or (
                np.nanmax(np.abs(j_big - j_small)) > 0.05 * np.nanmax(np.abs(j_small)) + 1e-300)
            J[:, :, nn + c] = j_small if use_small else j_big
        # whiten with the innovation covariance, skip missing entries
        e = np.nan_to_num(eps0)
        valid = np.isfinite(eps0)
        L = np.linalg.cholesky(np.where(np.isfinite(S0), S0, 0) + np.eye(pm.n_y) * 1e-300)
        Jv = np.where(valid[:, :, None] & np.isfinite(J), J, 0.0)
        # rows of missing outputs: remove from S too (use the diagonal then)
        if not valid.all():
            sd = np.sqrt(np.einsum("kii->ki", S0))
            ew = np.where(valid, e / sd, 0.0)
            Gw = Jv / sd[:, :, None]
        else:
            ew = np.linalg.solve(L, e[:, :, None])[:, :, 0]
            Gw = np.linalg.solve(L, Jv)
        Gw = np.where(np.isfinite(Gw), Gw, 0.0)
        total = float(np.sum(ew**2))
        A = np.einsum("kic,kid->cd", Gw, Gw)
        b = np.einsum("kic,ki->c", Gw, ew)
        # columns are scaled to unit norm before solving (conditioning)
        norm = np.sqrt(np.maximum(np.diag(A), 1e-300))
        An = A / np.outer(norm, norm)
        bn = b / norm
        base_cols = list(range(nn))

        def explained(cs):
            if not cs:
                return 0.0, np.zeros(0)
            sol = np.linalg.lstsq(An[np.ix_(cs, cs)], bn[cs], rcond=1e-9)[0]
            return float(bn[cs] @ sol), sol / norm[cs]

        e_base, _ = explained(base_cols)
        col_of: dict = {}
        out = []
        groups: dict[tuple, list[int]] = {}
        for c, col in enumerate(cols):
            groups.setdefault((col.effect, col.target), []).append(nn + c)
        for (ename, tgt), cs in groups.items():
            eff = get_effect(ename, self.s.effects)
            try:
                e_all, sol = explained(base_cols + cs)
            except np.linalg.LinAlgError:
                continue
            lm = max(0.0, e_all - e_base)
            if not np.isfinite(lm):
                continue
            k = len(cs)
            col_of[(ename, tgt)] = cs
            beta = -sol[nn:]
            est = [p.name for p in eff.params if p.estimated]
            values = {est[i]: float(beta[i]) for i in range(min(k, len(est)))}
            out.append(Candidate(ename, eff.title, tgt, "score", lm, k, float(chi2.sf(lm, k)),
                                 lm - 2 * k, lm / total if total > 0 else None, values))
        self._mark_equivalent(out, col_of, An, base_cols)
        self._fit_for_probe = fit
        self._line_probe(pm, base, cols, out, t, u, y, x0, P0, fit.nll)
        return out

    def _line_probe(self, pm, base, cols, cands, t, u, y, x0, P0, nll0) -> None:
        """Second batched run: every additive candidate at multiples of its
        one-step estimate and at its natural values, nuisance parameters held.
        The likelihood gain found (LR, a lower bound of the candidate's full
        LR) replaces the score statistic where it is larger: the score test is
        local and misses effects to which the filter reacts nonlinearly (at
        λ = 0 a filter bends its states towards a rectified measurement)."""
        from scipy.stats import chi2

        from bondgraph.inference.ukf import ukf_nll

        index = {(c.effect, c.target): [] for c in cands}
        for c, col in enumerate(cols):
            if (col.effect, col.target) in index:
                index[(col.effect, col.target)].append(pm.param_index(col.param))
        sets, owner = [], []
        for cand in cands:
            eff = get_effect(cand.effect, self.s.effects)
            est = [p.name for p in eff.params if p.estimated]
            js = index[(cand.effect, cand.target)]
            beta = np.array([cand.values.get(n, 0.0) for n in est[:len(js)]])
            trials = [beta * f for f in (0.5, 1.0, 2.0)] if np.any(beta) else []
            for pt in eff.natural_points(cand.target):
                trials.append(np.array([pt.get(n, b) for n, b in zip(est, beta)]))
            for tr in trials:
                th = base.copy()
                th[js] = tr
                for thv in self._noise_variants(pm, self._fit_for_probe, th, (1.0, 0.1, 0.01)):
                    sets.append(thv)
                    owner.append((cand, tr))
        if not sets:
            return
        sets = np.array(sets)
        nll = np.empty(len(sets))
        for a in range(0, len(sets), self.s.chunk):
            nll[a:a + self.s.chunk] = ukf_nll(pm, t, u, y, sets[a:a + self.s.chunk], x0, P0,
                                             options=self.s.ukf).nll
        best: dict = {}
        for (cand, tr), v in zip(owner, nll):
            if np.isfinite(v) and (id(cand) not in best or v < best[id(cand)][0]):
                best[id(cand)] = (v, tr)
        for cand in cands:
            if id(cand) not in best:
                continue
            v, tr = best[id(cand)]
            lr = 2.0 * (nll0 - v)
            if lr > cand.statistic:
                eff = get_effect(cand.effect, self.s.effects)
                est = [p.name for p in eff.params if p.estimated]
                cand.statistic = float(lr)
                cand.p_value = float(chi2.sf(lr, cand.dof))
                cand.score = float(lr - 2 * cand.dof)
                cand.values.update({n: float(x) for n, x in zip(est, tr)})

    @staticmethod
    def _mark_equivalent(cands, col_of, An, base_cols, tol: float = 0.999) -> None:
        """Fill ``Candidate.equivalent`` for single-column candidates whose
        signatures, with the estimated parameters partialled out, have
        |correlation| > ``tol``."""
        B = list(base_cols)
        ABB = An[np.ix_(B, B)] if B else None

        def resid(a, b):
            v = An[a, b]
            if B:
                v -= An[a, B] @ np.linalg.lstsq(ABB, An[B, b], rcond=1e-9)[0]
            return v

        singles = [c for c in cands if len(col_of[(c.effect, c.target)]) == 1]
        idx = {id(c): col_of[(c.effect, c.target)][0] for c in singles}
        var = {id(c): resid(idx[id(c)], idx[id(c)]) for c in singles}
        for i, a in enumerate(singles):
            for b in singles[i + 1:]:
                va, vb = var[id(a)], var[id(b)]
                if va <= 0 or vb <= 0:
                    continue
                r = resid(idx[id(a)], idx[id(b)]) / np.sqrt(va * vb)
                if abs(r) > tol:
                    a.equivalent.append(b.label)
                    b.equivalent.append(a.label)

    def score_structural(self, fit: Fit, scales: Scales, effects) -> list[Candidate]:
        from scipy.stats import chi2
        from tqdm.auto import tqdm

        from bondgraph.inference.ukf import ukf_nll

        todo = [(eff, tgt) for eff in effects if not eff.additive
                for tgt in eff.targets(fit.graph) if not eff.present(fit.graph, tgt)]
        out = []
        for eff, tgt in tqdm(todo, desc="structural candidates", unit="cand", leave=False,
                             disable=not self.progress):
            try:
                g = fit.graph.copy(f"{fit.graph.name}__{eff.name}")
                grid = eff.grid(g, tgt, scales)
                P = eff.apply(g, tgt, grid[0], scales)
                model = self.model_of(g)
            except BondGraphError as exc:
                self.log(f"  skip {eff.name} @ {tgt.name}: {str(exc).splitlines()[0]}")
                continue
            base = model.theta0.copy()
            for n in fit.model.params:
                if n in model.params:
                    base[model.param_index(n)] = fit.theta[fit.model.param_index(n)]
            sets = []
            grid_of = []
            for vals in grid:
                th = base.copy()
                for k, v in vals.items():
                    if k in P:
                        th[model.param_index(P[k].name)] = v
                for thv in self._noise_variants(model, fit, th, NOISE_FACTORS):
                    sets.append(thv)
                    grid_of.append(vals)
            t, u, y = self.data.arrays(model)
            x0 = self.x0_for(model)
            r = ukf_nll(model, t, u, y, np.array(sets), x0, self.P0_for(model, x0),
                        options=self.s.ukf)
            if not np.any(np.isfinite(r.nll)):
                continue
            net = np.where(np.isfinite(r.nll), r.nll, np.inf)
            i = int(np.argmin(net))
            lr = max(0.0, 2 * (fit.nll - float(net[i])))
            best_vals = grid_of[i]
            k = sum(1 for p in eff.params if p.estimated)
            out.append(Candidate(eff.name, eff.title, tgt, "likelihood ratio", lr, k,
                                 float(chi2.sf(lr, k)), lr - 2 * k, None, dict(best_vals),
                                 last_resort=getattr(eff, "last_resort", False)))
        return out

    def confirm(self, fit: Fit, cand: Candidate, scales: Scales) -> tuple[Fit, dict] | None:
        """Build the real augmented graph and fit the new parameters only."""
        eff = get_effect(cand.effect, self.s.effects)
        g = fit.graph.copy(f"{self.user_graph.name}_step{len(self.steps) + 1}")
        values = {k: v for k, v in cand.values.items()}
        if eff.additive:
            # physical sign: friction coefficients of R laws are >= 0
            for p in eff.params:
                if p.nonnegative and p.name in values:
                    values[p.name] = abs(values[p.name]) or 1e-9
        try:
            P = eff.apply(g, cand.target, values, scales)
        except BondGraphError as exc:
            self.log(f"  cannot apply {cand.label}: {str(exc).splitlines()[0]}")
            return None
        new = [P[p.name].name for p in eff.params if p.estimated and p.name in P]
        start = dict(fit.estimates())
        for n in fit.model.params:
            start.setdefault(n, float(fit.theta[fit.model.param_index(n)]))
        # widen the box of the new parameters around their start values
        for p in eff.params:
            if p.name in P and p.estimated:
                par = P[p.name]
                v = float(par.default)
                span = max(abs(v) * 20.0, 1e-6)
                if p.bounds is not None:
                    par.bounds = tuple(p.bounds)
                elif not eff.additive and v > 0:
                    par.bounds = (v / 100.0, v * 100.0)
                else:
                    par.bounds = (0.0 if p.nonnegative else -span, span)
        try:
            model = self.model_of(g)
            start = self.grid_refine(model, new, start)
            # the effect's natural values (full rectification, ...) are extra
            # starts: its likelihood may have two basins (a half-rectified
            # sensor is a compromise the nuisance parameters can settle in)
            starts = [start]
            for pt in eff.natural_points(cand.target):
                alt, moved = dict(start), False
                for k, v in pt.items():
                    if k in P and P[k].name in new:
                        old_v = float(start.get(P[k].name, np.nan))
                        moved |= not abs(old_v - v) <= 0.05 * max(abs(v), 1e-12)
                        alt[P[k].name] = float(v)
                if moved:
                    starts.append(alt)
            # all parameters re-adjust (the nuisance ones absorbed part of the
            # missing effect): the confirmed fit is the candidate's final fit
            fits = [self.fit(g, list(fit.params) + new, s0, f"confirming {cand.label}",
                             model=model, iterations=self.s.confirm_iterations)
                    for s0 in starts]
            f1 = min(fits, key=lambda f: f.nll if np.isfinite(f.nll) else np.inf)
        except BondGraphError as exc:
            self.log(f"  confirmation of {cand.label} failed: {str(exc).splitlines()[0]}")
            return None
        return f1, {"effect": cand.effect, "target": cand.target,
                    "values": {p.name: float(f1.theta[f1.model.param_index(P[p.name].name)])
                               for p in eff.params if p.name in P},
                    "new_params": new}

    def grid_refine(self, model: Model, names: list[str], start: dict) -> dict:
        """Improve the start values of ``names`` (the new parameters) by two
        batched grid searches (coarse, then fine) with everything else fixed:
        two UKF calls instead of an optimizer's dozens."""
        theta = model.theta0.copy()
        for k, v in start.items():
            if k in model.params:
                theta[model.param_index(k)] = v
        for n in names:
            if n not in start:
                start[n] = float(theta[model.param_index(n)])
        if not names:
            return start
        crit = self.criterion(model, names, theta)
        lo, hi = self.bounds_for(model, names, theta)
        x = np.array([start[n] for n in names], dtype=float)
        for factors in (np.geomspace(0.05, 20.0, 13), np.geomspace(0.6, 1.66, 9)):
            for i in range(len(names)):
                xs = np.repeat(x[None, :], factors.size + 1, axis=0)
                base = x[i] if x[i] != 0 else (hi[i] - lo[i]) * 1e-3
                xs[1:, i] = np.clip(base * factors, lo[i], hi[i])
                if lo[i] < 0 < hi[i]:
                    xs = np.concatenate([xs, -xs[1:]])
                    xs[:, i] = np.clip(xs[:, i], lo[i], hi[i])
                f = crit(xs)
                if np.any(np.isfinite(f)):
                    x = xs[int(np.nanargmin(np.where(np.isfinite(f), f, np.nan)))]
        out = dict(start)
        out.update({n: float(v) for n, v in zip(names, x)})
        return out

    # ------------------------------------------------------------ the loop
    def run(self) -> "LoopResult":
        s = self.s
        mname = None
        self.log(f"loop on model '{self.user_graph.name}', record "
                 f"'{getattr(self.data.exp, 'name', '?')}', estimating {', '.join(s.params)}")
        if not self.user_graph.process_noise and not any(
                ss.process_noise is not None for ss in self.user_graph.signal_states.values()):
            self.log("warning: the filter model declares no process noise; model errors then "
                     "do not show as local innovations and the likelihood is poorly "
                     "conditioned. Declare process noise (g.set_process_noise) on the states "
                     "where forces are unmodelled, ideally as an estimated parameter.")
        first = list(s.params) if s.initial_params is None else list(s.initial_params)
        current = self.fit(self.user_graph.copy(self.user_graph.name), first, None,
                           "initial fit")
        # later steps re-estimate every parameter of ``params``
        current.params = list(s.params)
        mname = _metric_name(s, current.model)
        self.initial = current
        self.log(f"initial fit: NLL {current.nll:.2f}, {s.criterion.upper()} "
                 f"{self._crit(current):.2f}, whiteness {current.residuals.whiteness:.1f}, "
                 f"{mname} = {current.metric:.4g}")
        self.write_report(current)
        for step in range(s.max_steps):
            scales = self.scales(current)
            t_ev = time.perf_counter()
            cands = self.score_additive(current, scales, s.effects)
            best_expl = max([c.explained or 0.0 for c in cands] + [0.0])
            physical_fx = [e for e in s.effects if not getattr(e, "last_resort", False)]
            resort_fx = [e for e in s.effects if getattr(e, "last_resort", False)]
            if s.structural == "always" or (s.structural and best_expl < s.structural_threshold):
                cands += self.score_structural(current, scales, physical_fx)
            elif s.structural:
                self.log(f"  structural candidates not scored: an additive effect explains "
                         f"{100 * best_expl:.0f} % of the innovation energy")
            n_c = max(len(cands), 1)
            significant = [c for c in cands if c.p_value * n_c < s.significance]
            if not significant and s.structural and resort_fx:
                self.log("  no physical effect is significant: scoring the last-resort "
                         "effects (unmeasured disturbances)")
                cands += self.score_structural(current, scales, resort_fx)
                n_c = max(len(cands), 1)
                significant = [c for c in cands if c.p_value * n_c < s.significance]
            ranking = sorted(cands, key=lambda c: -c.score)
            self.rankings.append(ranking)
            self.log(f"step {step + 1}: {len(cands)} candidates scored in "
                     f"{time.perf_counter() - t_ev:.1f} s; best: " + "; ".join(
                         f"{c.label} (χ²={c.statistic:.1f}, k={c.dof})" for c in ranking[:5]))
            if ranking and ranking[0].equivalent:
                self.log(f"  note: {ranking[0].label} is indistinguishable in this record from "
                         f"{', '.join(ranking[0].equivalent)} (signatures correlated > 0.999)")
            if not significant:
                self.log("nothing significant left: stop")
                break
            todo = sorted(significant, key=lambda c: -c.score)[: s.confirm_top]
            confirmed = []
            for c in todo:
                r = self.confirm(current, c, scales)
                if r is None:
                    continue
                f1, info = r
                c.confirmed_statistic = max(0.0, 2 * (current.nll - f1.nll))
                confirmed.append((c.confirmed_statistic - 2 * c.dof, c, f1, info))
                self.log(f"  confirmed {c.label}: LR {c.confirmed_statistic:.1f} "
                         f"(score test {c.statistic:.1f}), values {info['values']}")
            confirmed.sort(key=lambda z: -z[0])
            accepted = False
            for _, c, f1, info in confirmed:
                names = list(current.params) + info["new_params"]
                after = f1
                better_ic = self._crit(after) < self._crit(current)
                # "whiteness improves": the Ljung-Box total decreases, or the
                # innovations are white already (within noise of χ²(dof))
                whiter = (after.residuals.whiteness < current.residuals.whiteness
                          or after.residuals.is_white())
                # guard: a step may not wreck the reported error (e.g. a
                # friction law that makes the free-run simulation stick)
                metric_ok = not (np.isfinite(current.metric) and
                                 after.metric > s.metric_tolerance * current.metric)
                if better_ic and whiter and metric_ok:
                    eff = get_effect(c.effect, s.effects)
                    new_std = self.std(after)
                    P = {n: {"estimate": float(after.theta[after.model.param_index(n)]),
                             "std": new_std.get(n)} for n in names}
                    st = Step(c.effect, c.target.name, mname, current.metric, after.metric,
                              current.nll, after.nll, self._crit(current), self._crit(after),
                              current.residuals.whiteness, after.residuals.whiteness, P,
                              c.confirmed_statistic or c.statistic, c.p_value)
                    self.steps.append(st)
                    self.applied.append({"effect": c.effect, "target": c.target,
                                         "values": {p.name: float(after.theta[after.model.param_index(
                                             eff.pname(c.target, p.name))])
                                             for p in eff.params
                                             if eff.pname(c.target, p.name) in after.model.params}})
                    after.std = new_std
                    self.log(f"ACCEPT {c.label}: {mname} {current.metric:.4g} -> {after.metric:.4g}, "
                             f"NLL {current.nll:.2f} -> {after.nll:.2f}, {s.criterion.upper()} "
                             f"{self._crit(current):.2f} -> {self._crit(after):.2f}, whiteness "
                             f"{current.residuals.whiteness:.1f} -> {after.residuals.whiteness:.1f}")
                    current = after
                    accepted = True
                    break
                self.rejected.append({"step": step + 1, **c.to_dict(),
                                      "reason": ("information criterion did not improve"
                                                 if not better_ic else
                                                 "whiteness did not improve" if not whiter else
                                                 f"the error grew ({current.metric:.4g} -> "
                                                 f"{after.metric:.4g})"),
                                      "criterion_after": self._crit(after),
                                      "whiteness_after": after.residuals.whiteness})
                self.log(f"reject {c.label}: {s.criterion.upper()} {self._crit(current):.2f} -> "
                         f"{self._crit(after):.2f}, whiteness {current.residuals.whiteness:.1f} -> "
                         f"{after.residuals.whiteness:.1f}, error {current.metric:.4g} -> "
                         f"{after.metric:.4g}")
            for c in ranking:
                if not any(st.effect == c.effect and st.attached_to == c.target.name
                           for st in self.steps):
                    pass
            self.write_report(current)
            if not accepted:
                self.log("no candidate improved both the criterion and the whiteness: stop")
                break
        self.final = current
        if not current.std:
            current.std = self.std(current)
        self.write_report(current, final=True)
        self.log(f"done in {time.perf_counter() - self.t0:.1f} s")
        return LoopResult(self.steps, self.rejected, self.rankings, self.initial, self.final,
                          mname)

    def _crit(self, fit: Fit) -> float:
        return fit.bic() if self.s.criterion == "bic" else fit.aic()

    def std(self, fit: Fit) -> dict:
        """Cramér-Rao standard deviations of the estimated parameters (from the
        Fisher information of the last scoring step, else a batched Hessian)."""
        from bondgraph.inference.estimate import cramer_rao, hessian_batched

        if not fit.params:
            return {}
        if fit.std and all(n in fit.std for n in fit.params):
            return fit.std
        crit = self.criterion(fit.model, fit.params, fit.theta)
        x = np.array([fit.theta[fit.model.param_index(n)] for n in fit.params])
        h = 1e-4 * np.maximum(np.abs(x), 1e-6)
        try:
            H, _, _ = hessian_batched(crit, x, h)
            cr = cramer_rao(H, fit.params)
            return {n: (float(v) if v is not None and np.isfinite(v) else None)
                    for n, v in zip(fit.params, cr.get("std", [None] * len(fit.params)))}
        except Exception as exc:
            self.log(f"  Cramér-Rao bounds unavailable ({str(exc).splitlines()[0]})")
            return {}

    # ------------------------------------------------------------ report
    def write_report(self, current: Fit, final: bool = False) -> None:
        """Hand the state of the loop to ``on_update`` (the report writer), after
        the initial fit, after every step and at the end."""
        if self.on_update is not None:
            self.on_update(self, current, final)


@dataclass
class LoopResult:
    """What :func:`run_loop` returns."""

    steps: list[Step]
    rejected: list[dict]
    rankings: list[list[Candidate]]
    initial: Fit
    final: Fit
    metric: str

    def table(self) -> str:
        """Markdown table of the accepted steps (error = :attr:`metric`)."""
        rows = ["| step | effect | attached to | error before | error after | NLL before | NLL after |",
                "|---|---|---|---|---|---|---|"]
        for i, s in enumerate(self.steps, 1):
            rows.append(f"| {i} | {s.effect} | {s.attached_to} | {s.error_before:.4g} | "
                        f"{s.error_after:.4g} | {s.nll_before:.1f} | {s.nll_after:.1f} |")
        return "\n".join(rows)


def _cr_std(F: np.ndarray, names: Sequence[str]) -> dict:
    """Cramér-Rao standard deviations sqrt(diag(F⁻¹)); None where F is singular."""
    try:
        C = np.linalg.inv(F)
        d = np.diag(C)
        return {n: (float(np.sqrt(v)) if v > 0 and np.isfinite(v) else None)
                for n, v in zip(names, d)}
    except np.linalg.LinAlgError:
        return {n: None for n in names}


def run_loop(graph: BondGraph, experiment, params: Sequence[str], *,
             log: Callable[[str], None] | None = None, progress: bool = True,
             on_update: Callable[[Loop, Fit, bool], None] | None = None,
             **settings) -> LoopResult:
    """Trace residuals to missing effects, add them, re-estimate.

    Parameters
    ----------
    graph : BondGraph
        The declared model (never modified).
    experiment : Experiment
        The measured record (:class:`bondgraph.data.records.Experiment`).
    params : sequence of str
        Parameters of the declared model to estimate.
    log : callable, optional
        Line logger (default ``print``).
    progress : bool
        Progress bars on long steps.
    on_update : callable, optional
        ``on_update(loop, current_fit, finished)``, called after the initial
        fit, after every step and at the end; the report writer
        (:class:`bondgraph.report.loop_report.LoopReporter`) uses it, so that an
        interrupted run keeps its work.
    **settings
        Fields of :class:`LoopSettings` (metric, criterion, max_steps,
        significance, confirm_top, structural, effects, x0, P0, ukf, ...).

    Returns
    -------
    LoopResult
        Accepted steps (error before/after, NLL, parameters), rejected
        candidates, the evidence ranking of every step.

    Raises
    ------
    ModelError
        Unknown parameter names.
    BondGraphError
        If the declared model cannot be fitted at all (UKF failure).
    """
    model_params = set(graph.params)
    missing = [p for p in params if p not in model_params]
    if missing:
        raise ModelError(f"graph '{graph.name}' has no parameter(s) {missing} "
                         f"(known: {', '.join(graph.params)})")
    s = LoopSettings(params=list(params), **settings)
    return Loop(graph, experiment, s, log, progress, on_update).run()

"""Sensitivity and identifiability of a record: which parameters it can estimate.

:func:`analyse` runs, at one parameter vector θ along one record:

* the Fisher information of the UKF likelihood and the identifiability
  analysis built on it (Cramér-Rao bounds, correlations, collinearity,
  product / ratio flags; :mod:`bondgraph.sensitivity.identifiability`);
* the recommendation of the parameters to estimate (Yao et al. 2003
  orthogonalised ranking with subset selection, :func:`recommend`);
* optionally the output sensitivities dy/dθ from the forward sensitivity
  equations (:mod:`bondgraph.numerics.forward_sensitivity`) and the
  output-error information they give;
* optionally the Sobol' indices of the NLL over a box
  (:mod:`bondgraph.sensitivity.sobol`).

CLI: ``bondgraph sensitivity --model M --data FILE.csv [--params a,b] [--global N]``
writes ``sensitivity.json`` and PNG plots; ``bondgraph estimate --params
recommended:<dir>/sensitivity.json`` estimates the recommended set
(:func:`recommended_params`).

References
----------
Brun, R., Reichert, P., Künsch, H. R. (2001). Practical identifiability
analysis of large environmental simulation models. Water Resources Research
37(4), 1015-1030.
Yao, K. Z., Shaw, B. M., Kou, B., McAuley, K. B., Bacon, D. W. (2003).
Modeling ethylene/butene copolymerization with multi-site catalysts:
parameter estimability and experimental design. Polymer Reaction
Engineering 11(3), 563-588.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

import numpy as np

from bondgraph.core.jsonsafe import to_jsonable
from bondgraph.errors import EstimationError, NumericalError, SensitivityError
from bondgraph.inference.estimand import plan_estimand, x0_state_names
from bondgraph.inference.estimate import start_levels_profiled
from bondgraph.inference.fisher import estimand_derivatives, jacobi_pinv
from bondgraph.inference.problem import Problem
from bondgraph.numerics.forward_sensitivity import (
    Sensitivities,
    SolverOptions,
    check_params,
    output_sensitivities,
    parameter_scale,
)
from bondgraph.numerics.model import Model
from bondgraph.numerics.integrators import join_hold, split_hold
from bondgraph.sensitivity.identifiability import (
    CORR_MAX,
    REL_CRB_MAX,
    identifiability,
    orthogonal_ranking,
    recommend,
    ridge_line,
    ukf_fisher,
)
from bondgraph.sensitivity.sobol import SobolOptions, _pow2, global_sensitivity

#: the identifiability entries kept in the report
_IDENT_KEYS = ("std", "rel_std", "corr", "cosine", "eigenvalues", "condition",
               "collinearity_index", "full_rank", "null_directions", "flags", "unidentifiable")


@dataclass
class SensitivityReport:
    """Result of :func:`analyse` (JSON-able via :meth:`to_json`)."""

    model: str
    experiment: str
    params: list
    theta: dict
    scale: list
    local: dict
    recommendation: dict
    global_: dict | None = None
    settings: dict = field(default_factory=dict)
    sensitivities: Sensitivities | None = None

    def to_dict(self) -> dict:
        d = dict(format="bondgraph-sensitivity/1", model=self.model, experiment=self.experiment,
                 params=self.params, theta=self.theta, scale=self.scale, local=self.local,
                 recommendation=self.recommendation, settings=self.settings)
        d["global"] = self.global_
        return to_jsonable(d)

    def to_json(self, path: str | Path | None = None) -> str:
        text = json.dumps(self.to_dict(), indent=2, allow_nan=False)
        if path is not None:
            Path(path).write_text(text + "\n")
        return text

    def table(self) -> str:
        """Plain-text table of the recommendation."""
        rec = self.recommendation
        lines = [f"{self.model} on {self.experiment}: {len(self.params)} candidates, "
                 f"recommended {len(rec['estimate'])}: {', '.join(rec['estimate']) or '-'}"]
        # the name column as wide as the longest name (an effect's parameter,
        # cubic_stiffness.spring.k3, ran into the decision)
        w = max([14] + [len(d["param"]) + 2 for d in rec["decisions"]])
        lines += [f"{'rank':>4}  {'parameter':<{w}}{'decision':<10}{'rel CRB':>9}  reason",
                  "-" * (w + 64)]
        for d in rec["decisions"]:
            rc = d.get("rel_crb")
            rcs = f"{rc:>9.2%}" if rc is not None and np.isfinite(rc) else f"{'-':>9}"
            lines.append(f"{d['rank']:>4}  {d['param']:<{w}}{d['decision']:<10}{rcs}  "
                         f"{d['reason']}")
        ck = rec.get("check")
        if ck:
            lines.append(f"check: full rank {ck['full_rank']}, condition {ck['condition']:.3g}, "
                         f"collinearity index {ck['collinearity_index']:.3g}, max rel CRB "
                         f"{ck['max_rel_crb']:.2%}, max |corr| {ck['max_abs_corr']:.3f}")
        if rec.get("ridge"):
            lines.append(ridge_line(rec["ridge"]))
        nu = self.local.get("nuisance")
        if nu:
            lines.append("estimated with the parameters (Cramér-Rao std, nuisance of the "
                         "recommendation): " + ", ".join(
                             f"{n} = {v:.4g} ± {s_:.3g}"
                             for n, v, s_ in zip(nu["names"], nu["values"], nu["std"])))
        fl = self.local.get("identifiability", {}).get("flags", [])
        lines += flag_lines(fl, rec.get("ridge"))
        if self.global_:
            lines += _sobol_lines(self.global_)
        return "\n".join(lines)


def flag_lines(flags: list[dict], ridge: dict | None = None) -> list[str]:
    """``flag: ...`` lines of the identifiability flags (products, ratios,
    singular directions, correlations, parameters without sensitivity); the
    pairwise correlations among the members of ``ridge`` (the line above
    them) as one line: a k-way scale symmetry gives k(k-1)/2 pairs of
    |corr| near 1, ten lines for the five of a quarter-car, which say
    together what the ridge line says."""
    members = set(ridge["params"]) if ridge else set()
    on_ridge = [f for f in flags if f["type"] == "correlated" and members
                and set(f["params"]) <= members]
    out = [f"flag: {f['message']}" for f in flags
           if f["type"] in ("product", "ratio", "singular", "correlated", "no_sensitivity")
           and not any(f is g for g in on_ridge)]
    if on_ridge:
        c = [abs(float(f["value"])) for f in on_ridge]
        names = sorted({n for f in on_ridge for n in f["params"]}, key=ridge["params"].index)
        out.append(f"flag: {len(on_ridge)} pairwise correlations among {', '.join(names)} with "
                   f"|corr| {min(c):.3f} to {max(c):.3f} (the ridge above)")
    return out


def _sobol_lines(g: dict) -> list[str]:
    """Table lines of the Sobol' indices (NLL first, by total index)."""
    ind = g["indices"]["NLL"]
    order = np.argsort(-np.asarray(ind["ST"]))
    what = "ln(1 + NLL - min)" if g.get("nll_transform", "none") != "none" else "the NLL"
    lines = [f"Sobol' indices of {what} (N = {g['N']}, {g['evaluations']} "
             f"evaluations, {g['failed'].get('NLL', 0)} failed; "
             f"{int(100 * g['conf_level'])} % confidence):"]
    for i in order:
        lines.append(f"  {g['names'][i]:<14} S1 {ind['S1'][i]:+.3f} ± "
                     f"{ind['S1_conf'][i]:.3f}   ST {ind['ST'][i]:.3f} ± "
                     f"{ind['ST_conf'][i]:.3f}")
    for on, ind in g["indices"].items():
        if on == "NLL":
            continue
        lines.append(f"Sobol' indices of {on}: " + ", ".join(
            f"{nm} S1 {ind['S1'][i]:+.2f} ST {ind['ST'][i]:.2f}"
            for i, nm in enumerate(g["names"]) if ind["ST"][i] >= 0.01))
    return lines


@dataclass(frozen=True)
class LocalOptions:
    """Options of the local analysis of :func:`analyse`.

    Parameters
    ----------
    rel_crb_max, corr_max : float
        Selection thresholds of the recommendation (:func:`recommend`): the
        largest relative Cramér-Rao bound of a recommended parameter, the
        largest abs(correlation) within the recommended set.
    sensitivities : bool
        Also integrate the forward sensitivity equations (output-error
        information, sensitivity plots;
        :func:`bondgraph.numerics.forward_sensitivity.output_sensitivities`).
    sens_method : str
        Their solver (scipy ``solve_ivp`` method).
    sens_rtol, sens_atol : float
        Their tolerances.

    Raises
    ------
    SensitivityError
        A threshold or tolerance that is not > 0.
    """

    rel_crb_max: float = REL_CRB_MAX
    corr_max: float = CORR_MAX
    sensitivities: bool = True
    sens_method: str = "LSODA"
    sens_rtol: float = 1e-6
    sens_atol: float = 1e-8

    def __post_init__(self):
        for name in ("rel_crb_max", "corr_max", "sens_rtol", "sens_atol"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and np.isfinite(v) and v > 0):
                raise SensitivityError(f"LocalOptions.{name} must be a number > 0, got {v!r}")


@dataclass
class _Analysis:
    """What every part of :func:`analyse` works on: the problem, the
    candidates, the thresholds, the logger, the timings and the estimand."""

    problem: Problem
    params: list
    limits: dict
    say: Callable
    timing: dict
    estimand: Any = None
    #: output -> the factor by which its noise level, profiled at θ, rose
    #: over the level it started from, where that is at least
    #: :data:`MISFIT_RATIO` (:func:`_profiled_levels`)
    misfit: dict = field(default_factory=dict)

    @property
    def model(self):
        """The problem's model."""
        return self.problem.model


def analyse(problem: Problem, params: Sequence[str] | None = None, *,
            local: LocalOptions | None = None, sobol: SobolOptions | None = None,
            x0_states: Sequence[str] = (), fixed: Sequence[str] = (),
            log=None) -> SensitivityReport:
    """Local (and optionally global) sensitivity and identifiability analysis
    of one record, with a recommendation of the parameters to estimate.

    Parameters
    ----------
    problem : Problem
        The model on the record (:func:`bondgraph.inference.problem.make_problem`):
        its θ is the point of the analysis, its prior (x0, P0), noise policy
        ("auto": declared levels used, undeclared ones estimated; "model")
        and filter options are the likelihood's.
    params : sequence of str, optional
        Candidates (default: every parameter with a proper box).
    local : LocalOptions, optional
        Thresholds of the recommendation and the forward sensitivities.
    sobol : SobolOptions, optional
        The Sobol' analysis of the NLL (:func:`bondgraph.sensitivity.sobol.global_sensitivity`;
        None: local only).
    x0_states : sequence of str
        Initial states estimated with θ (``["all"]``): nuisance columns of
        the Fisher information (:func:`_information`).
    fixed : sequence of str
        The parameters the user holds fixed (not noise intensities to
        estimate under the "auto" noise policy).
    log : callable, optional
        Receives progress messages.

    Returns
    -------
    SensitivityReport

    Raises
    ------
    ModelError, SensitivityError, DataError, NumericalError
        Unknown names, bad options, bad records; the UKF fails at θ.

    References
    ----------
    Cramér (1946), Rao (1945) for the bound; Yao et al. (2003) for the
    orthogonal ranking; Saltelli et al. (2010) for the Sobol' indices.
    """
    lo = LocalOptions() if local is None else local
    model = problem.model
    params = check_params(model, params)
    an = _Analysis(problem, params, dict(corr_max=lo.corr_max, rel_crb_max=lo.rel_crb_max),
                   log or (lambda *_: None), {})
    an.estimand, notes = _estimand(an, x0_states, fixed)
    an.estimand, notes = _profiled_levels(an, x0_states, notes)
    for note in notes:
        an.say(note)
    scale = analysis_scale(model, params, problem.theta)
    loc, recommendation = _local(an, scale, problem.name)
    sens = _output_error(an, loc, lo) if lo.sensitivities else None
    glob = _global(an, sobol) if sobol is not None else None
    return _report(an, scale, loc, recommendation, glob, sens, dict(
        x0_rule=problem.x0_rule, noise=problem.noise.mode, noise_notes=notes,
        x0_states=list(an.estimand.states), misfit=dict(an.misfit)))


#: a box that reaches this far (either bound, model units) states no scale
#: of its parameter: the effect library's (-1e9, 1e9) for an offset or a
#: calibration term (:func:`analysis_scale`)
UNBOUNDED = 1e8


def analysis_scale(model, params: Sequence[str], theta) -> np.ndarray:
    """The scale (k,) of each parameter for the relative information,
    bounds and ranking: :func:`~bondgraph.numerics.forward_sensitivity.parameter_scale`
    (|θ|, or the box's width where θ is nearly 0 beside it), but |θ| for a
    nonzero θ whose box reaches :data:`UNBOUNDED`: beside the library's
    (-1e9, 1e9) every value below 2 counted as nearly 0, so a force offset
    of 0.76 N on the EMPS pulses run took a scale of 2e9 and its
    sensitivity, 1e9 times its own, ranked first while the mass, the
    friction coefficients "added no independent direction" (6e-10 of it).

    Returns
    -------
    ndarray (k,)
    """
    s = parameter_scale(model, params, theta)
    idx = model.param_indices(params)
    th = np.abs(np.asarray(theta, float)[idx])
    reach = np.maximum(np.abs(model.lower[idx]), np.abs(model.upper[idx]))
    return np.where((reach >= UNBOUNDED) & (th > 0), th, s)


def _report(an: _Analysis, scale, local, recommendation, glob, sens,
            settings: dict) -> SensitivityReport:
    """The :class:`SensitivityReport` of :func:`analyse`."""
    pb, params = an.problem, an.params
    model, t = pb.model, pb.t
    settings.update(samples=int(t.size), duration_s=float(t[-1] - t[0]), x0=pb.x0.tolist(),
                    P0_diag=np.diag(pb.P0).tolist(), ukf=pb.ukf.to_dict(),
                    theta_full=pb.theta.tolist(), timing=an.timing,
                    units=[model.param_units[i] for i in model.param_indices(params)])
    return SensitivityReport(
        model=model.name, experiment=pb.name, params=list(params),
        theta={p: float(pb.theta[model.param_index(p)]) for p in params},
        scale=scale.tolist(), local=local, recommendation=recommendation, global_=glob,
        settings=settings, sensitivities=sens)


def _global(an: _Analysis, options: SobolOptions) -> dict:
    """Sobol' indices of the NLL (:func:`bondgraph.sensitivity.sobol.global_sensitivity`),
    the estimated noise levels held at the analysis' levels."""
    t0 = time.perf_counter()
    an.say(f"Sobol' indices: N = {_pow2(options.N)} ...")
    pb, est = an.problem, an.estimand
    if est is not None and est.noises:
        # the estimated noise levels held where the local analysis has them
        # (profiled at θ): the problem's own are the sensors' declarations,
        # 0 for a user's sensor without one (every NLL was non-finite)
        pb = pb.conditioned_on(noise_levels={
            o: float(est.sigma[pb.model.output_index(o)]) for o in est.noises})
    glob = global_sensitivity(pb, an.params, options)
    an.timing["global_s"] = time.perf_counter() - t0
    return glob


def _estimand(an: _Analysis, x0_states, fixed) -> tuple[Any, list[str]]:
    """The :class:`~bondgraph.inference.estimand.Estimand` of the analysis
    (the candidates, the initial states, the noise policy) and its notes."""
    pb = an.problem
    states = x0_state_names(pb.model, x0_states)
    declared = None if pb.record is None else pb.record.noise_std_for(pb.model)
    scale = np.sqrt(np.maximum(np.diag(pb.P0), 1e-24))
    return plan_estimand(pb.model, pb.theta, an.params, list(fixed), declared,
                         noise=pb.noise.mode, states=states, x0=pb.x0, x0_scale=scale, y=pb.y)


#: a noise level profiled at the analysed θ this many times above the level
#: it started from (the record's second differences, or a declaration)
#: says that the model misses the record there by more than its noise
#: (:func:`_profiled_levels`)
MISFIT_RATIO = 3.0


def _profiled_levels(an: _Analysis, x0_states, notes: list[str]) -> tuple[Any, list[str]]:
    """The estimand with each estimated noise level at the level the NLL
    at the analysed θ is highest with
    (:func:`bondgraph.inference.estimate.start_levels_profiled`), and a
    note naming them, where that moves any. The information is the one of
    the misfit the model has at θ: at a level that nothing declares the
    estimand starts from the record's second differences (a quantised
    encoder's resolution, 8.3e-6 m on the EMPS pulses run where the model
    misses by 3.8e-3 m), and the information there was (3.8e-3 / 8.3e-6)²,
    about 2e5 times too large: Cramér-Rao bounds 460 times too small.
    A level that rose :data:`MISFIT_RATIO` times or more is recorded in
    ``an.misfit`` and the note says that the information is then the
    misfit's: a user's EMPS graph in its position loop at its declared
    values (M 80 kg, Fv 100 N s/m, against 99 and 409 fitted) had its
    drive command's level profiled 46 times up, and the analysis advised
    fixing Fv (relative bound 12.8 %), which the fit then determines to
    0.42 %."""
    est = an.estimand
    if est is None or not est.noises:
        return est, notes
    try:
        levels = start_levels_profiled(an.problem, an.params, x0_states=x0_states)
    except (FloatingPointError, np.linalg.LinAlgError, NumericalError, EstimationError):
        return est, notes
    sigma = est.sigma.copy()
    moved = [(o, sigma[j], levels[j]) for o, j in zip(est.noises, est.n_idx)
             if np.isfinite(levels[j]) and levels[j] != sigma[j]]
    if not moved:
        return est, notes
    for o, _, v in moved:
        sigma[an.problem.model.output_index(o)] = v
    note = ("noise levels at the analysed θ, profiled (the information of the misfit the model "
            "has there): " + ", ".join(f"{o} {a:.4g} -> {b:.4g}" for o, a, b in moved))
    an.misfit = {o: float(b / a) for o, a, b in moved if a > 0 and b >= MISFIT_RATIO * a}
    if an.misfit:
        note += ("; " + ", ".join(f"{o} {r:.3g} times" for o, r in an.misfit.items())
                 + " the level it started from: the model misses the record at this θ by more "
                   "than the noise (a θ far from a fit, or an effect the model lacks), and the "
                   "information below is that of its misfit")
    return replace(est, sigma=sigma), [*notes, note]


def _information(an: _Analysis):
    """The UKF Fisher information of the parameters (efficient: the nuisance
    columns profiled out, F_pp − F_pn F_nn⁻¹ F_np) and the report of the
    nuisance quantities (None without any).

    Raises
    ------
    FloatingPointError
        If the UKF fails at the analysis point.
    """
    est, pb = an.estimand, an.problem
    k = len(an.params)
    if est is None or (est.k == k and not est.uses_R):
        return ukf_fisher(pb.model, pb.t, pb.u, pb.y, pb.theta, an.params, pb.x0, pb.P0,
                          pb.ukf), None
    lo, hi = est.bounds()
    z = est.value()
    steps = 1e-6 * np.maximum(np.abs(z), 1e-3 * np.maximum(hi - lo, 1e-300))
    steps = np.where((z + steps > hi) & (z - steps >= lo), -steps, steps)
    D = estimand_derivatives(pb.model, pb.t, pb.u, pb.y, est, steps, pb.P0, pb.ukf)
    F = D.F
    names = est.names
    nuis = None
    if est.k > k:
        Fpp, Fpn, Fnn = F[:k, :k], F[:k, k:], F[k:, k:]
        Feff = Fpp - Fpn @ jacobi_pinv(Fnn) @ Fpn.T
        cov = jacobi_pinv(F)
        std = np.sqrt(np.clip(np.diag(cov), 0, None))
        corr = cov / np.outer(np.where(std > 0, std, 1), np.where(std > 0, std, 1))
        nuis = dict(names=names[k:], values=z[k:], std=std[k:], corr=corr,
                    corr_names=names, description="initial states and noise levels estimated "
                    "with the parameters: Cramér-Rao std sqrt(diag(F⁻¹)) over all names")
        D.F = Feff
    D.grad = D.grad[:k]
    return D, nuis


def _local(an: _Analysis, scale, experiment: str) -> tuple[dict, dict]:
    """The UKF Fisher information, the identifiability analysis and ranking
    built on it, and the recommendation: ``(local, recommendation)``."""
    t0 = time.perf_counter()
    k = 0 if an.estimand is None else an.estimand.k
    an.say(f"UKF Fisher information: {max(k, len(an.params)) + 1} sets in one batched run ...")
    try:
        D, nuis = _information(an)
    except FloatingPointError as exc:
        raise NumericalError(f"UKF fails at the analysis point: {exc}") from None
    an.timing["ukf_fisher_s"] = time.perf_counter() - t0
    ident = identifiability(D.F, an.params, scale, **an.limits)
    rec = recommend(D.F, an.params, scale, experiment=experiment, **an.limits)
    ranking = orthogonal_ranking(ident["F_rel"], an.params)
    local: dict[str, Any] = dict(
        nll=D.nll, grad=D.grad, fisher=D.F, fisher_rel=ident["F_rel"],
        identifiability={k_: ident[k_] for k_ in _IDENT_KEYS},
        ranking=[dict(param=p, orthogonal_norm=n_) for p, n_ in ranking],
        relative_information=np.sqrt(np.clip(np.diag(ident["F_rel"]), 0, None)))
    if nuis is not None:
        local["nuisance"] = nuis
    return local, rec


def output_noise_levels(an: _Analysis) -> np.ndarray:
    """The measurement-noise std (n_y,) [output units] that weighs each
    output in the output-error information: the level the analysis holds or
    estimates (the record's declaration, or the start of an estimated one,
    :attr:`Estimand.sigma <bondgraph.inference.estimand.Estimand>`), else
    the sensor's own (``meas_std``). A user's sensor declared without a
    noise level has ``meas_std`` 0: weighing by it divided by zero (a user's
    CED graph: "Eigenvalues did not converge").

    Raises
    ------
    SensitivityError
        An output measured in the record with no positive level anywhere
        (named).
    """
    pb, model = an.problem, an.model
    sigma = np.asarray(model.meas_std(pb.theta), float).reshape(-1)
    levels = [] if an.estimand is None else [np.asarray(an.estimand.sigma, float)]
    for lev in levels + [pb.noise.sigma(model)]:
        sigma = np.where(np.isfinite(lev) & (lev > 0), lev, sigma)
    seen = np.isfinite(np.asarray(pb.y, float)).any(axis=0)
    bad = [o for o, s_, m in zip(model.outputs, sigma, seen) if m and not (s_ > 0)]
    if bad:
        raise SensitivityError(f"no measurement-noise level for output(s) {', '.join(bad)}: "
                               f"the sensor declares none and the record neither declares nor "
                               f"shows one (columns.<output>.noise_std in its sidecar)")
    return sigma


def _output_error(an: _Analysis, local: dict, lo: LocalOptions) -> Sensitivities:
    """Forward sensitivities and the output-error information (no process
    noise, known x0), stored in ``local["output_error"]``."""
    pb, model = an.problem, an.model
    t0 = time.perf_counter()
    an.say(f"forward sensitivities ({lo.sens_method}, {model.n_x} + "
           f"{model.n_x}·{len(an.params)} states) ...")
    hold = join_hold("zoh" if h == "zoh" else "linear" for h in split_hold(pb.ukf.hold))
    sens = output_sensitivities(model, pb.t, pb.u, pb.theta, pb.x0, an.params,
                                solver=SolverOptions(method=lo.sens_method, rtol=lo.sens_rtol,
                                                     atol=lo.sens_atol, hold=hold))
    an.timing["sensitivities_s"] = time.perf_counter() - t0
    sigma = output_noise_levels(an)
    mask = np.isfinite(pb.y)
    Zm = np.where(mask[:, :, None], sens.scaled(sigma), 0.0)
    F_oe = sens.information(sigma, mask)
    ident_oe = identifiability(F_oe, an.params, None, **an.limits)
    local["output_error"] = dict(
        description="no process noise, known x0: F = Σ_k (∂y_k/∂θ)ᵀ R⁻¹ ∂y_k/∂θ from the "
                    "forward sensitivity equations, relative coordinates",
        fisher_rel=F_oe, rel_std=ident_oe["rel_std"], full_rank=ident_oe["full_rank"],
        flags=ident_oe["flags"], collinearity_index=ident_oe["collinearity_index"],
        rms_scaled=np.sqrt(np.sum(Zm ** 2, axis=0)
                           / np.maximum(mask.sum(axis=0), 1)[:, None]).T,
        outputs=list(model.outputs), sigma=np.asarray(sigma, float).tolist(),
        solver=sens.stats)
    return sens


def recommend_experiments(cases: Mapping[str, tuple],
                          local: LocalOptions | None = None) -> dict[str, SensitivityReport]:
    """:func:`analyse` for several experiments, e.g. the vehicle's coast-down,
    acceleration and braking records: which parameters to estimate from
    each.

    Parameters
    ----------
    cases : dict label -> (problem, candidates)
        A :class:`~bondgraph.inference.problem.Problem` per record;
        ``candidates`` may be None (every free parameter).
    local : LocalOptions, optional
        Shared by all cases.

    Returns
    -------
    dict label -> SensitivityReport
        ``report.recommendation["estimate"]`` is the list to pass to
        :func:`bondgraph.inference.estimate.estimate` (or :func:`recommended_params`).
    """
    return {label: analyse(problem, params, local=local)
            for label, (problem, params) in cases.items()}


def recommended_params(source, model=None) -> list[str]:
    """The recommended parameter list of a ``sensitivity.json``.

    Parameters
    ----------
    source : path, dict or SensitivityReport
        A file written by ``bondgraph sensitivity`` (or its directory).
    model : Model or str, optional
        Check that the model has these parameters.

    Returns
    -------
    list of str

    Raises
    ------
    SensitivityError
        Missing file or no recommendation in it.
    ModelError
        A recommended parameter the model does not have.
    """
    if isinstance(source, SensitivityReport):
        d = source.to_dict()
    elif isinstance(source, Mapping):
        d = dict(source)
    else:
        p = Path(source)
        if p.is_dir():
            p = p / "sensitivity.json"
        if not p.exists():
            raise SensitivityError(f"no sensitivity file {p} (run `bondgraph sensitivity`)")
        try:
            d = json.loads(p.read_text())
        except json.JSONDecodeError as exc:
            raise SensitivityError(f"{p} is not JSON: {exc}") from None
    try:
        names = list(d["recommendation"]["estimate"])
    except (KeyError, TypeError):
        raise SensitivityError("no recommendation['estimate'] in the sensitivity result") from None
    if not names:
        raise SensitivityError("the sensitivity result recommends no parameter to estimate")
    if model is not None:
        Model.from_spec(model).param_indices(names)
    return names

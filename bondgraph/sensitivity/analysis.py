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
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

import numpy as np

from bondgraph.core.jsonsafe import to_jsonable
from bondgraph.errors import NumericalError, SensitivityError
from bondgraph.inference.estimand import plan_estimand, x0_state_names
from bondgraph.inference.fisher import estimand_derivatives, jacobi_pinv
from bondgraph.inference.options import UKFOptions, ukf_options
from bondgraph.inference.record import as_record, initial_state, record_arrays
from bondgraph.inference.ukf import default_P0
from bondgraph.numerics.forward_sensitivity import (
    Sensitivities,
    SolverOptions,
    check_params,
    output_sensitivities,
    parameter_scale,
)
from bondgraph.numerics.model import Model
from bondgraph.numerics.simulate import _vector
from bondgraph.sensitivity.identifiability import (
    CORR_MAX,
    REL_CRB_MAX,
    identifiability,
    orthogonal_ranking,
    recommend,
    ukf_fisher,
)
from bondgraph.sensitivity.sobol import _pow2, global_sensitivity

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
                 f"recommended {len(rec['estimate'])}: {', '.join(rec['estimate']) or '-'}",
                 f"{'rank':>4}  {'parameter':<14}{'decision':<10}{'rel CRB':>9}  reason",
                 "-" * 78]
        for d in rec["decisions"]:
            rc = d.get("rel_crb")
            rcs = f"{rc:>9.2%}" if rc is not None and np.isfinite(rc) else f"{'-':>9}"
            lines.append(f"{d['rank']:>4}  {d['param']:<14}{d['decision']:<10}{rcs}  "
                         f"{d['reason']}")
        ck = rec.get("check")
        if ck:
            lines.append(f"check: full rank {ck['full_rank']}, condition {ck['condition']:.3g}, "
                         f"collinearity index {ck['collinearity_index']:.3g}, max rel CRB "
                         f"{ck['max_rel_crb']:.2%}, max |corr| {ck['max_abs_corr']:.3f}")
        nu = self.local.get("nuisance")
        if nu:
            lines.append("estimated with the parameters (Cramér-Rao std, nuisance of the "
                         "recommendation): " + ", ".join(
                             f"{n} = {v:.4g} ± {s_:.3g}"
                             for n, v, s_ in zip(nu["names"], nu["values"], nu["std"])))
        fl = self.local.get("identifiability", {}).get("flags", [])
        for f in fl:
            if f["type"] in ("product", "ratio", "singular", "correlated", "no_sensitivity"):
                lines.append(f"flag: {f['message']}")
        if self.global_:
            lines += _sobol_lines(self.global_)
        return "\n".join(lines)


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


@dataclass
class _Problem:
    """What every part of :func:`analyse` works on."""

    model: Any
    t: np.ndarray
    u: np.ndarray
    y: np.ndarray
    theta: np.ndarray
    params: list
    x0: np.ndarray
    P0: np.ndarray
    ukf: UKFOptions
    limits: dict
    say: Callable
    timing: dict
    estimand: Any = None


def analyse(model, experiment, params: Sequence[str] | None = None, *, theta=None, x0=None,
            P0=None, p0_rel: float = 0.05, ukf: UKFOptions | None = None,
            global_N: int | None = None, outputs: Sequence[str] = (),
            box_rel: float | None = None, chunk: int = 256, seed: int = 0,
            rel_crb_max: float = REL_CRB_MAX, corr_max: float = CORR_MAX,
            sensitivities: bool = True, sens_method: str = "LSODA", sens_rtol: float = 1e-6,
            sens_atol: float = 1e-8, progress: bool = False, log=None,
            nll_transform: str = "log", x0_states: Sequence[str] = (), noise: str = "model",
            fixed: Sequence[str] = (), workers: int = 1, scheduler: str | None = None
            ) -> SensitivityReport:
    """Local (and optionally global) sensitivity and identifiability analysis
    of one record, with a recommendation of the parameters to estimate.

    Parameters
    ----------
    model : Model or str
        Filter model (:meth:`~bondgraph.numerics.model.Model.from_spec`).
    experiment : Experiment, path of a CSV record, or (t, u, y)
    params : sequence of str, optional
        Candidates (default: every parameter with a proper box).
    theta : array or dict, optional
        Parameter values of the analysis (default: model defaults; a dict
        overrides named ones).
    x0 : array (n_x,) or dict, optional
        Initial state (default: the record's rule,
        :func:`bondgraph.inference.record.initial_state`).
    P0 : array, optional
        UKF prior covariance (default ``default_P0(model, x0, p0_rel)``).
    ukf : UKFOptions, optional
        Filter options (:func:`bondgraph.inference.ukf.ukf_nll`).
    global_N : int, optional
        Base sample size of the Sobol' analysis (None: local only).
    outputs, box_rel, chunk, seed, nll_transform, workers, scheduler :
        Of the Sobol' analysis (:func:`bondgraph.sensitivity.sobol.global_sensitivity`):
        outputs whose time-means also get indices, box θ (1 ± box_rel) instead of the
        model's bounds, parameter sets per batched UKF run, seed, the transform of the NLL
        ("log": ln(1 + NLL − min NLL)), where the chunks run (Dask processes or a scheduler's).
    rel_crb_max, corr_max : float
        Selection thresholds (:func:`recommend`).
    sensitivities : bool
        Also integrate the forward sensitivity equations (output-error
        information, sensitivity plots) with ``sens_method``, ``sens_rtol``,
        ``sens_atol`` (:func:`bondgraph.numerics.forward_sensitivity.output_sensitivities`).
    progress, log :
        Progress bar of the Sobol' sample; a callable for progress messages.
    x0_states, noise, fixed :
        Initial states estimated with θ (``["all"]``), the noise policy ("auto":
        declared levels used, undeclared ones estimated; "model") and the fixed
        parameters: nuisance columns of the Fisher information (:func:`_information`).

    Returns
    -------
    SensitivityReport

    Raises
    ------
    ModelError, SensitivityError, DataError, NumericalError
        Unknown names, bad options, bad records; the UKF fails at θ.
    """
    model = Model.from_spec(model)
    params = check_params(model, params)
    rec = as_record(experiment)
    t, u, y, ename, _ = record_arrays(model, rec)
    x0a, x0_how = initial_state(model, rec, x0)
    P0a = default_P0(model, x0a, p0_rel) if P0 is None else np.asarray(P0, float)
    pb = _Problem(model, t, u, y, _vector(model, theta, "theta"), params, x0a, P0a,
                  ukf_options(ukf), dict(corr_max=corr_max, rel_crb_max=rel_crb_max),
                  log or (lambda *_: None), {})
    pb.estimand, notes = _estimand(pb, rec, x0_states, noise, fixed)
    for note in notes:
        pb.say(note)
    scale = parameter_scale(model, params, pb.theta)
    local, recommendation = _local(pb, scale, ename)
    sens = _output_error(pb, local, sens_method, sens_rtol, sens_atol) if sensitivities else None
    sobol = dict(outputs=outputs, box_rel=box_rel, chunk=chunk, seed=seed, progress=progress,
                 nll_transform=nll_transform, workers=workers, scheduler=scheduler)
    glob = _global(pb, global_N, sobol) if global_N else None
    return _report(pb, ename, scale, local, recommendation, glob, sens, dict(
        x0_rule=x0_how, noise=noise, noise_notes=notes, x0_states=list(pb.estimand.states)))


def _report(pb: _Problem, ename: str, scale, local, recommendation, glob, sens,
            settings: dict) -> SensitivityReport:
    """The :class:`SensitivityReport` of :func:`analyse`."""
    model, params, t = pb.model, pb.params, pb.t
    settings.update(samples=int(t.size), duration_s=float(t[-1] - t[0]), x0=pb.x0.tolist(),
                    P0_diag=np.diag(pb.P0).tolist(), ukf=pb.ukf.to_dict(),
                    theta_full=pb.theta.tolist(), timing=pb.timing,
                    units=[model.param_units[i] for i in model.param_indices(params)])
    return SensitivityReport(
        model=model.name, experiment=ename, params=list(params),
        theta={p: float(pb.theta[model.param_index(p)]) for p in params},
        scale=scale.tolist(), local=local, recommendation=recommendation, global_=glob,
        settings=settings, sensitivities=sens)


def _global(pb: _Problem, N: int, options: dict) -> dict:
    """Sobol' indices of the NLL (:func:`bondgraph.sensitivity.sobol.global_sensitivity`)."""
    t0 = time.perf_counter()
    pb.say(f"Sobol' indices: N = {_pow2(N)} ...")
    glob = global_sensitivity(pb.model, pb.t, pb.u, pb.y, pb.params, N, theta=pb.theta,
                              x0=pb.x0, P0=pb.P0, ukf=pb.ukf, **options)
    pb.timing["global_s"] = time.perf_counter() - t0
    return glob


def _estimand(pb: _Problem, rec, x0_states, noise: str, fixed) -> tuple[Any, list[str]]:
    """The :class:`~bondgraph.inference.estimand.Estimand` of the analysis
    (the candidates, the initial states, the noise policy) and its notes."""
    states = x0_state_names(pb.model, x0_states)
    declared = None if isinstance(rec, tuple) else rec.noise_std_for(pb.model)
    scale = np.sqrt(np.maximum(np.diag(np.atleast_2d(pb.P0)) if np.ndim(pb.P0) == 2
                               else np.asarray(pb.P0, float), 1e-24))
    return plan_estimand(pb.model, pb.theta, pb.params, list(fixed), declared, noise=noise,
                         states=states, x0=pb.x0, x0_scale=scale)


def _information(pb: _Problem):
    """The UKF Fisher information of the parameters (efficient: the nuisance
    columns profiled out, F_pp − F_pn F_nn⁻¹ F_np) and the report of the
    nuisance quantities (None without any).

    Raises
    ------
    FloatingPointError
        If the UKF fails at the analysis point.
    """
    est = pb.estimand
    k = len(pb.params)
    if est is None or (est.k == k and not est.uses_R):
        return ukf_fisher(pb.model, pb.t, pb.u, pb.y, pb.theta, pb.params, pb.x0, pb.P0,
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


def _local(pb: _Problem, scale, experiment: str) -> tuple[dict, dict]:
    """The UKF Fisher information, the identifiability analysis and ranking
    built on it, and the recommendation: ``(local, recommendation)``."""
    t0 = time.perf_counter()
    k = 0 if pb.estimand is None else pb.estimand.k
    pb.say(f"UKF Fisher information: {max(k, len(pb.params)) + 1} sets in one batched run ...")
    try:
        D, nuis = _information(pb)
    except FloatingPointError as exc:
        raise NumericalError(f"UKF fails at the analysis point: {exc}") from None
    pb.timing["ukf_fisher_s"] = time.perf_counter() - t0
    ident = identifiability(D.F, pb.params, scale, **pb.limits)
    rec = recommend(D.F, pb.params, scale, experiment=experiment, **pb.limits)
    ranking = orthogonal_ranking(ident["F_rel"], pb.params)
    local: dict[str, Any] = dict(
        nll=D.nll, grad=D.grad, fisher=D.F, fisher_rel=ident["F_rel"],
        identifiability={k_: ident[k_] for k_ in _IDENT_KEYS},
        ranking=[dict(param=p, orthogonal_norm=n_) for p, n_ in ranking],
        relative_information=np.sqrt(np.clip(np.diag(ident["F_rel"]), 0, None)))
    if nuis is not None:
        local["nuisance"] = nuis
    return local, rec


def _output_error(pb: _Problem, local: dict, method: str, rtol: float,
                  atol: float) -> Sensitivities:
    """Forward sensitivities and the output-error information (no process
    noise, known x0), stored in ``local["output_error"]``."""
    model = pb.model
    t0 = time.perf_counter()
    pb.say(f"forward sensitivities ({method}, {model.n_x} + {model.n_x}·{len(pb.params)} "
           f"states) ...")
    hold = "zoh" if pb.ukf.hold == "zoh" else "linear"
    sens = output_sensitivities(model, pb.t, pb.u, pb.theta, pb.x0, pb.params,
                                solver=SolverOptions(method=method, rtol=rtol, atol=atol,
                                                     hold=hold))
    pb.timing["sensitivities_s"] = time.perf_counter() - t0
    sigma = np.asarray(model.meas_std(pb.theta), float)
    mask = np.isfinite(pb.y)
    Zm = np.where(mask[:, :, None], sens.scaled(sigma), 0.0)
    F_oe = sens.information(sigma, mask)
    ident_oe = identifiability(F_oe, pb.params, None, **pb.limits)
    local["output_error"] = dict(
        description="no process noise, known x0: F = Σ_k (∂y_k/∂θ)ᵀ R⁻¹ ∂y_k/∂θ from the "
                    "forward sensitivity equations, relative coordinates",
        fisher_rel=F_oe, rel_std=ident_oe["rel_std"], full_rank=ident_oe["full_rank"],
        flags=ident_oe["flags"], collinearity_index=ident_oe["collinearity_index"],
        rms_scaled=np.sqrt(np.sum(Zm ** 2, axis=0)
                           / np.maximum(mask.sum(axis=0), 1)[:, None]).T,
        outputs=list(model.outputs), solver=sens.stats)
    return sens


def recommend_experiments(cases: Mapping[str, tuple], **options) -> dict[str, SensitivityReport]:
    """:func:`analyse` for several experiments, e.g. the vehicle's coast-down,
    acceleration and braking records: which parameters to estimate from
    each.

    Parameters
    ----------
    cases : dict label -> (model, experiment, candidates)
        ``candidates`` may be None (every free parameter).
    **options
        Keyword arguments of :func:`analyse` shared by all cases.

    Returns
    -------
    dict label -> SensitivityReport
        ``report.recommendation["estimate"]`` is the list to pass to
        :func:`bondgraph.inference.estimate.estimate` (or :func:`recommended_params`).
    """
    return {label: analyse(model, exp, params, **options)
            for label, (model, exp, params) in cases.items()}


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

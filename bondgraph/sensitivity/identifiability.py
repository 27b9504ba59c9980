"""Local identifiability from a Fisher information, and parameter selection.

* **Fisher information of the UKF likelihood** F (the expected information
  of the prediction-error decomposition, :func:`bondgraph.inference.fisher.derivatives`,
  one batched UKF run with nudged copies, :func:`ukf_fisher`), in relative
  coordinates F̃ = diag(s) F diag(s); the Cramér-Rao bounds std =
  sqrt(diag F⁻¹), the correlation matrix, eigenvalues and condition number.
* **Collinearity** (Brun, Reichert & Künsch 2001): with the normalised
  information F̂_ij = F̃_ij / sqrt(F̃_ii F̃_jj) (the cosines between the
  scaled sensitivity directions), the collinearity index of a set is
  γ = 1 / sqrt(λ_min(F̂)); γ > 10-20 means near-linear dependence.
* **Flags** of practically unidentifiable parameters: near-singular
  information (relative eigenvalue below ``rcond``), |correlation| > 0.95,
  and parameters that enter only as a product or a ratio: their
  log-sensitivity directions θ_a ∂y/∂θ_a and θ_b ∂y/∂θ_b are parallel
  (cos = +1: only a·b, or a power product, matters) or anti-parallel
  (cos = −1: only a/b).

Parameter selection: :func:`recommend` is the orthogonalised sensitivity
ranking of Yao et al. (2003) with a subset-selection test at every step:
the candidate whose scaled sensitivity direction has the largest component
orthogonal to the parameters already selected (the Schur complement of F̃,
i.e. Yao's Gram-Schmidt step written with the information matrix) is tried
next; it is kept if the enlarged set still has a positive definite
information, every relative Cramér-Rao bound under ``rel_crb_max`` and every
|correlation| under ``corr_max``, otherwise it is fixed, with the reason.
The selected set is then full-rank by construction (checked and reported).

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

from typing import Any, Sequence

import numpy as np

from bondgraph.errors import SensitivityError
from bondgraph.inference.fisher import (
    Derivatives,
    derivatives,
    relative_changes,
    typical_magnitude,
)
from bondgraph.inference.options import UKFOptions
from bondgraph.inference.ukf import default_P0

#: defaults of the selection rules
REL_CRB_MAX = 0.10
CORR_MAX = 0.95
#: |cos| of two log-sensitivity directions above 1 - PARALLEL_TOL: product / ratio
PARALLEL_TOL = 1e-6
#: relative eigenvalue of the normalised information below which it is singular
RCOND = 1e-9
#: a candidate set whose collinearity index γ exceeds this is reported as a
#: ridge (:func:`ridge`): near-linear dependence (Brun et al. 2001: γ > 10-20)
RIDGE_GAMMA = 20.0
#: a parameter is named on a ridge when its relative change along it is at
#: least this fraction of the largest one's
RIDGE_LOADING = 0.2


# -------------------------------------------------- UKF Fisher information
def ukf_fisher(model, t, u, y, theta, params: Sequence[str], x0=None, P0=None,
               options: UKFOptions | None = None, rel_step: float = 1e-6) -> Derivatives:
    """Expected Fisher information of the UKF likelihood for ``params``.

    One batched UKF run over θ and its k nudged copies
    (:func:`bondgraph.inference.fisher.derivatives`, forward differences of the
    innovations and their covariances; steps ``rel_step · max(|θ_j|,
    1e-3·width_j)``, taken downwards at an upper bound).

    Parameters
    ----------
    model : Model
    t, u, y : arrays (N,), (N, n_u), (N, n_y)
    theta : array (n_theta,)
    params : sequence of str (k)
    x0, P0 : UKF prior (default ``model.x0``, :func:`bondgraph.inference.ukf.default_P0`)
    options : UKFOptions, optional
        Filter options (:func:`bondgraph.inference.ukf.ukf_nll`).
    rel_step : float

    Returns
    -------
    bondgraph.inference.fisher.Derivatives
        ``F`` (k, k) in model units (per parameter unit squared), ``nll``,
        ``grad``.

    Raises
    ------
    FloatingPointError
        If the UKF fails at θ.
    """
    idx = model.param_indices(params)
    th = np.asarray(theta, dtype=float)
    x0a = model.x0.copy() if x0 is None else np.asarray(x0, dtype=float)
    P0a = default_P0(model, x0a) if P0 is None else P0
    lo, hi = model.lower[idx], model.upper[idx]
    width = np.maximum(hi - lo, 1e-300)
    xv = th[idx]
    steps = rel_step * np.maximum(np.abs(xv), typical_magnitude(xv, width))
    steps = np.where((xv + steps > hi) & (xv - steps >= lo), -steps, steps)
    return derivatives(model, t, u, y, th, idx, steps, x0a, P0a, options)


# ------------------------------------------------------ identifiability
def _flag(kind: str, params: Sequence[str], value: float | None, message: str) -> dict:
    return dict(type=kind, params=list(params), value=None if value is None else float(value),
                message=message)


def identifiability(F, names: Sequence[str], scale=None, *, corr_max: float = CORR_MAX,
                    rel_crb_max: float = REL_CRB_MAX, parallel_tol: float = PARALLEL_TOL,
                    rcond: float = RCOND) -> dict:
    """Cramér-Rao bounds, correlations, collinearity and flags from a Fisher
    information (Brun, Reichert & Künsch 2001).

    Parameters
    ----------
    F : array (k, k)
        Fisher information in model units (or already relative with
        ``scale=None``).
    names : sequence of str (k)
    scale : array (k,), optional
        Parameter scales s (:func:`bondgraph.numerics.forward_sensitivity.parameter_scale`):
        the analysis is in relative coordinates θ_j / s_j, F̃ = diag(s) F diag(s).
    corr_max : float
        Flag pairs with |correlation| above it.
    rel_crb_max : float
        Flag parameters whose relative Cramér-Rao bound std/s exceeds it.
    parallel_tol : float
        Flag pairs whose log-sensitivity directions have |cos| > 1 − tol as
        entering only as a product (cos > 0) or a ratio (cos < 0).
    rcond : float
        The information is singular when the smallest eigenvalue of the
        normalised information F̂ is below ``rcond``.

    Returns
    -------
    dict
        ``F_rel (k, k)``, ``cosine (k, k)`` (F̂), ``eigenvalues`` (of F̃),
        ``condition`` (of F̃), ``collinearity_index`` γ, ``full_rank``
        (bool), ``std (k,)``, ``rel_std (k,)``, ``corr (k, k)`` (NaN when
        singular), ``null_directions`` (list of {param: weight} in relative
        coordinates d θ_j / s_j), ``flags`` (list of dicts with ``type`` in
        {"no_sensitivity", "singular", "product", "ratio", "correlated",
        "crb"}, ``params``, ``value``, ``message``) and ``unidentifiable``
        (sorted names appearing in a flag).

    Raises
    ------
    SensitivityError
        ``F`` not of shape (k, k).
    """
    names = list(names)
    k = len(names)
    F = np.asarray(F, dtype=float)
    if F.shape != (k, k):
        raise SensitivityError(f"information matrix has shape {F.shape}, expected ({k}, {k})")
    s = np.ones(k) if scale is None else np.asarray(scale, dtype=float)
    Fs = 0.5 * (F + F.T) * np.outer(s, s)
    C, d, dead = _normalised(Fs)
    flags = [_flag("no_sensitivity", [names[i]], 0.0,
                   f"{names[i]}: the record carries no information on it (zero sensitivity)")
             for i in np.flatnonzero(dead)]
    flags += _product_ratio_flags(C, names, np.flatnonzero(~dead), parallel_tol)
    lam_s = np.linalg.eigvalsh(Fs) if k else np.zeros(0)
    out: dict[str, Any] = dict(
        params=names, scale=s, F_rel=Fs, cosine=C, eigenvalues=lam_s,
        condition=float(lam_s[-1] / lam_s[0]) if k and lam_s[0] > 0 else float("inf"),
        collinearity_index=float("inf"), full_rank=False,
        std=np.full(k, np.nan), rel_std=np.full(k, np.nan), corr=np.full((k, k), np.nan),
        null_directions=[], flags=flags)
    limits = dict(corr_max=corr_max, rel_crb_max=rel_crb_max, rcond=rcond)
    if k and not dead.any():
        _all_sensitive(out, Fs, C, d, s, names, **limits)
    elif k and dead.any() and (~dead).any():
        _some_insensitive(out, Fs, dead, s, names, (corr_max, rel_crb_max, rcond, parallel_tol))
    out["unidentifiable"] = sorted({p for f in flags for p in f["params"]})
    return out


def _normalised(Fs: np.ndarray):
    """``(F̂, sqrt(diag F̃), dead)``: the normalised information (cosines),
    with the rows and columns of insensitive parameters (``dead``) zeroed."""
    d = np.sqrt(np.clip(np.diag(Fs), 0.0, None))
    dmax = float(d.max()) if d.size else 0.0
    dead = d <= 1e-12 * max(dmax, 1e-300)
    dd = np.where(dead, 1.0, d)
    C = Fs / np.outer(dd, dd)
    C[dead, :] = 0.0
    C[:, dead] = 0.0
    np.fill_diagonal(C, np.where(dead, 0.0, 1.0))
    return C, d, dead


def _product_ratio_flags(C, names, live, parallel_tol: float) -> list[dict]:
    """Pairs whose log-sensitivity directions are (anti-)parallel."""
    flags = []
    for a_ in range(len(live)):
        for b_ in range(a_ + 1, len(live)):
            i, j = live[a_], live[b_]
            c = C[i, j]
            if abs(c) > 1.0 - parallel_tol:
                kind = "product" if c > 0 else "ratio"
                what = (f"{names[i]}·{names[j]}" if c > 0 else f"{names[i]}/{names[j]}")
                flags.append(_flag(kind, [names[i], names[j]], c,
                                   f"{names[i]} and {names[j]} enter only as the {kind} {what} "
                                   f"(log-sensitivities {'parallel' if c > 0 else 'anti-parallel'}"
                                   f", cos = {c:+.7f}): not separately identifiable"))
    return flags


def _all_sensitive(out, Fs, C, d, s, names, *, corr_max, rel_crb_max, rcond) -> None:
    """Collinearity, null directions or bounds and correlations when every
    parameter has some sensitivity (fills ``out``)."""
    flags = out["flags"]
    lam, V = np.linalg.eigh(C)
    if lam[0] > 0:
        out["collinearity_index"] = float(1.0 / np.sqrt(lam[0]))
    if lam[0] <= rcond:
        for m_ in np.flatnonzero(lam <= rcond):
            w = V[:, m_] / d                                     # relative coordinates
            w = w / np.max(np.abs(w))
            terms = {names[i]: float(w[i]) for i in np.argsort(-np.abs(w)) if abs(w[i]) > 0.05}
            out["null_directions"].append(terms)
            txt = " ".join(f"{c:+.2f}·δ{p}" for p, c in terms.items())
            flags.append(_flag("singular", list(terms), float(lam[m_]),
                               f"information singular (normalised eigenvalue {lam[m_]:.2g})"
                               f": the direction {txt} (relative changes δθ = dθ/s) is not "
                               f"identified"))
        return
    cov = np.linalg.inv(Fs)
    rel = np.sqrt(np.diag(cov))
    corr = cov / np.outer(rel, rel)
    out.update(full_rank=True, rel_std=rel, std=rel * s, corr=corr)
    k = len(names)
    for i in range(k):
        for j in range(i + 1, k):
            if abs(corr[i, j]) > corr_max:
                flags.append(_flag("correlated", [names[i], names[j]], corr[i, j],
                                   f"corr({names[i]}, {names[j]}) = {corr[i, j]:+.3f} "
                                   f"(|corr| > {corr_max:g})"))
    for i in range(k):
        if rel[i] > rel_crb_max:
            flags.append(_flag("crb", [names[i]], rel[i],
                               f"{names[i]}: relative Cramér-Rao bound {rel[i]:.1%} "
                               f"(> {rel_crb_max:.0%})"))


def _some_insensitive(out, Fs, dead, s, names, limits: tuple) -> None:
    """The analysis of the sensitive parameters alone (the insensitive ones
    fixed; their bounds are infinite), merged into ``out``; ``limits``:
    ``(corr_max, rel_crb_max, rcond, parallel_tol)`` of :func:`identifiability`."""
    live = np.flatnonzero(~dead)
    corr_max, rel_crb_max, rcond, parallel_tol = limits
    sub = identifiability(Fs[np.ix_(live, live)], [names[i] for i in live], None,
                          corr_max=corr_max, rel_crb_max=rel_crb_max, rcond=rcond,
                          parallel_tol=parallel_tol)
    out["collinearity_index"] = sub["collinearity_index"]
    out["flags"].extend(f for f in sub["flags"] if f["type"] not in ("product", "ratio"))
    out["null_directions"] = [{names[i]: 1.0} for i in np.flatnonzero(dead)]
    out["null_directions"] += sub["null_directions"]
    if sub["full_rank"]:
        out["rel_std"][dead] = np.inf
        out["rel_std"][live] = sub["rel_std"]
        out["std"] = out["rel_std"] * s
        out["corr"][np.ix_(live, live)] = sub["corr"]


def orthogonal_ranking(G, names: Sequence[str]) -> list[tuple[str, float]]:
    """Orthogonalised sensitivity ranking (Yao et al. 2003) from a Gram matrix.

    With Z the (scaled) sensitivity matrix and G = ZᵀZ (e.g. the relative
    Fisher information), Yao's algorithm picks the column of largest norm,
    projects the remaining columns on the orthogonal complement of the
    selected ones and repeats. The squared norm of a projected column is a
    diagonal entry of the Schur complement of G on the selected set, so the
    ranking is a greedy pivoted Cholesky factorisation of G.

    Parameters
    ----------
    G : array (k, k), symmetric positive semi-definite
    names : sequence of str (k)

    Returns
    -------
    list of (name, norm)
        In rank order; ``norm`` is the norm of the parameter's sensitivity
        column orthogonal to all higher-ranked ones (0 for a parameter that
        adds no independent direction).
    """
    R = 0.5 * (np.asarray(G, float) + np.asarray(G, float).T)
    remaining = list(range(len(names)))
    out = []
    while remaining:
        dg = np.array([R[i, i] for i in remaining])
        j = remaining[int(np.argmax(dg))]
        piv = R[j, j]
        out.append((names[j], float(np.sqrt(max(piv, 0.0)))))
        remaining.remove(j)
        if piv > 0:
            R = R - np.outer(R[:, j], R[j, :]) / piv
    return out


# ----------------------------------------------------------- selection
def recommend(F, names: Sequence[str], scale=None, *, rel_crb_max: float = REL_CRB_MAX,
              corr_max: float = CORR_MAX, rcond: float = RCOND,
              parallel_tol: float = PARALLEL_TOL, experiment: str | None = None) -> dict:
    """Which parameters to estimate from this record and which to fix, with
    the reason for each.

    Orthogonalised forward selection (Yao et al. 2003 ranking with a subset
    test at each step): among the undecided candidates, take the one whose
    scaled sensitivity has the largest component orthogonal to the
    parameters selected so far; keep it if, together with them, the
    information is positive definite, every relative Cramér-Rao bound is at
    most ``rel_crb_max`` and every |correlation| at most ``corr_max``;
    otherwise fix it. Repeat until every candidate is decided.

    Parameters
    ----------
    F : array (k, k)
        Fisher information (model units), e.g. of the UKF likelihood.
    names : sequence of str (k)
        Candidates.
    scale : array (k,), optional
        Parameter scales (relative bounds are std / scale).
    rel_crb_max, corr_max, rcond, parallel_tol : float
        Selection thresholds (see :func:`identifiability`).
    experiment : str, optional
        Label stored in the result.

    Returns
    -------
    dict
        ``estimate`` (names in selection order), ``fix`` (names),
        ``decisions`` (one dict per candidate in the order considered:
        ``param, decision ("estimate" | "fix"), rank, orthogonal_norm``
        (relative to the first), ``rel_crb`` (in the final set for estimated
        ones; alone-with-the-set when it was tried for fixed ones), ``reason``),
        ``check`` (:func:`identifiability` of the selected set, summarised:
        ``full_rank, condition, collinearity_index, max_rel_crb,
        max_abs_corr``), ``ridge`` (:func:`ridge` of all candidates, or
        None), thresholds.
    """
    names = list(names)
    k = len(names)
    s = np.ones(k) if scale is None else np.asarray(scale, dtype=float)
    Fs = 0.5 * (np.asarray(F, float) + np.asarray(F, float).T) * np.outer(s, s)
    limits = dict(corr_max=corr_max, rel_crb_max=rel_crb_max, parallel_tol=parallel_tol,
                  rcond=rcond)
    full = identifiability(F, names, s, **limits)
    partners = _partners(full["flags"])
    selected, decisions = _forward_selection(Fs, names, partners, limits)
    est = [names[i] for i in selected]
    check = identifiability(Fs[np.ix_(selected, selected)], est, None, **limits) \
        if selected else None
    final_rel = dict(zip(est, check["rel_std"])) if check else {}
    for dec in decisions:
        if dec["decision"] == "estimate":
            r = float(final_rel[dec["param"]])
            dec["rel_crb"] = r
            dec["reason"] = (f"rank {dec['rank']} (orthogonalised sensitivity "
                             f"{dec['orthogonal_norm']:.2g} of the first), relative CRB "
                             f"{r:.2%} in the recommended set")
    return dict(experiment=experiment, estimate=est,
                fix=[d["param"] for d in decisions if d["decision"] == "fix"],
                decisions=decisions, check=_check_summary(check, len(est)),
                ridge=ridge(Fs, names, full, [names[i] for i in selected]),
                thresholds=dict(rel_crb_max=rel_crb_max, corr_max=corr_max, rcond=rcond,
                                parallel_tol=parallel_tol),
                method="orthogonalised sensitivity ranking (Yao et al. 2003) with subset "
                       "selection on the relative Fisher information of the UKF likelihood")


def ridge(Fs, names: Sequence[str], full: dict, estimated: Sequence[str]) -> dict | None:
    """The direction along which the candidates are least identifiable
    together, when their collinearity index γ exceeds :data:`RIDGE_GAMMA`:
    the eigenvector of the relative information F̃ = diag(s) F diag(s) (k, k)
    with the smallest eigenvalue, as relative changes dθ_j / s_j scaled to
    a largest of +1. Masses, stiffnesses and dampings that all move by +1
    are a scale symmetry: a record without a force or mass reference (a
    quarter-car driven by the road's velocity, its body acceleration
    measured) gives them only up to a common factor, and a parameter the
    recommendation fixes on the ridge sets the scale of the others.

    Parameters
    ----------
    Fs : array (k, k)
        Relative information F̃.
    names : sequence of str (k)
    full : dict
        :func:`identifiability` of all candidates (its ``collinearity_index``
        and ``rel_std``).
    estimated : sequence of str
        The recommended parameters.

    Returns
    -------
    dict or None
        ``params`` (named on the ridge, |change| >= :data:`RIDGE_LOADING`
        of the largest, largest first), ``direction`` ({name: change}),
        ``collinearity_index``, ``rel_crb`` ({name: relative Cramér-Rao
        bound with all candidates estimated}), ``fixed`` (those of
        ``params`` the recommendation fixes); None when γ <= RIDGE_GAMMA or
        fewer than two parameters are named.
    """
    gamma = float(full.get("collinearity_index", np.nan))
    if len(names) < 2 or not np.all(np.isfinite(Fs)) or not gamma > RIDGE_GAMMA:
        return None
    _, V = np.linalg.eigh(0.5 * (Fs + Fs.T))
    v, keep = relative_changes(V[:, 0], 0.0)
    named = [names[i] for i in keep if abs(v[i]) >= RIDGE_LOADING]
    if len(named) < 2:
        return None
    rel = dict(zip(names, np.asarray(full.get("rel_std", np.full(len(names), np.nan)), float)))
    return dict(params=named, direction={names[i]: float(v[i]) for i in keep},
                collinearity_index=gamma, rel_crb={n: float(rel[n]) for n in named},
                fixed=[n for n in named if n not in set(estimated)])


def ridge_line(r: dict) -> str:
    """One line for a user about :func:`ridge`'s result ``r``."""
    moves = ", ".join(f"{n} {r['direction'][n]:+.2f}" for n in r["params"])
    crb = [c for c in r["rel_crb"].values() if np.isfinite(c)]
    text = (f"ridge: the record does not identify {', '.join(r['params'])} together "
            f"(collinearity index {r['collinearity_index']:.3g}): the relative changes "
            f"{moves} barely change the likelihood")
    if crb:
        text += f" (relative Cramér-Rao bounds up to {max(crb):.0%} with all estimated)"
    if r["fixed"]:
        text += (f"; fixing {', '.join(r['fixed'])} sets the scale of the others: their "
                 f"estimates follow its value. Fix the one you know best instead "
                 f"(estimate --fixed NAME=VALUE)")
    return text


def _partners(flags) -> dict[str, list[str]]:
    """Parameter -> the products / ratios it enters only in ("the product with b")."""
    partners: dict[str, list[str]] = {}
    for fl in flags:
        if fl["type"] in ("product", "ratio"):
            a, b = fl["params"]
            partners.setdefault(a, []).append(f"the {fl['type']} with {b}")
            partners.setdefault(b, []).append(f"the {fl['type']} with {a}")
    return partners


def _orthogonal_norms(Fs, selected: list[int], undecided: list[int]) -> np.ndarray:
    """Squared norms of the candidates' sensitivity components orthogonal to
    the selected ones: the diagonal of the Schur complement of F̃."""
    if not selected:
        return np.clip(np.array([Fs[j, j] for j in undecided]), 0.0, None)
    A = Fs[np.ix_(selected, selected)]
    Bm = Fs[np.ix_(selected, undecided)]
    try:
        sol = np.linalg.solve(A, Bm)
    except np.linalg.LinAlgError:
        sol = np.linalg.lstsq(A, Bm, rcond=None)[0]
    res = np.array([Fs[j, j] for j in undecided]) - np.einsum("ij,ij->j", Bm, sol)
    return np.clip(res, 0.0, None)


def _forward_selection(Fs, names, partners, limits) -> tuple[list[int], list[dict]]:
    """Yao's orthogonalised ranking with a subset test at each step:
    ``(selected indices, decisions)`` (decision "estimate" or "fix" with reason)."""
    selected: list[int] = []
    undecided = list(range(len(names)))
    decisions = []
    top = None
    while undecided:
        res = _orthogonal_norms(Fs, selected, undecided)
        pick = int(np.argmax(res))
        j = undecided.pop(pick)
        norm = float(np.sqrt(res[pick]))
        if top is None:
            top = norm if norm > 0 else 1.0
        dec = dict(param=names[j], rank=len(decisions) + 1, orthogonal_norm=norm / top,
                   rel_crb=None)
        trial = selected + [j]
        ident = identifiability(Fs[np.ix_(trial, trial)], [names[i] for i in trial], None,
                                **limits)
        if norm <= np.sqrt(limits["rcond"]) * top or not ident["full_rank"]:
            why = (f"adds no independent direction (orthogonalised sensitivity "
                   f"{norm / top:.1e} of the first)")
            if names[j] in partners:
                why = f"enters only as {', '.join(partners[names[j]])}: " + why
            elif selected:
                why += f"; information singular with {', '.join(names[i] for i in selected)}"
            dec.update(decision="fix", reason=why)
        else:
            _subset_test(dec, ident, selected, names, limits)
            if dec["decision"] == "estimate":
                selected.append(j)
        decisions.append(dec)
    return selected, decisions


def _subset_test(dec: dict, ident: dict, selected: list[int], names, limits) -> None:
    """Keep the candidate (last in ``ident``) if the enlarged set has every
    |correlation| <= corr_max and every relative bound <= rel_crb_max."""
    corr_max, rel_crb_max = limits["corr_max"], limits["rel_crb_max"]
    rel = ident["rel_std"]
    corr = ident["corr"]
    dec["rel_crb"] = float(rel[-1])
    worst_c = int(np.argmax(np.abs(corr[-1, :-1]))) if selected else None
    if selected and abs(corr[-1, worst_c]) > corr_max:
        q = names[selected[worst_c]]
        dec.update(decision="fix", reason=f"correlated {corr[-1, worst_c]:+.3f} with {q} "
                                          f"(|corr| > {corr_max:g})")
    elif rel[-1] > rel_crb_max:
        dec.update(decision="fix", reason=f"relative Cramér-Rao bound {rel[-1]:.1%} "
                                          f"(> {rel_crb_max:.0%}) with the parameters "
                                          f"selected before it")
    elif np.any(rel[:-1] > rel_crb_max):
        i = int(np.argmax(rel[:-1]))
        dec.update(decision="fix", reason=f"would raise the relative Cramér-Rao bound of "
                                          f"{names[selected[i]]} to {rel[i]:.1%} "
                                          f"(> {rel_crb_max:.0%})")
    else:
        dec.update(decision="estimate")


def _check_summary(check: dict | None, kk: int) -> dict | None:
    """Summary of the identifiability of the recommended set."""
    if check is None:
        return None
    offd = np.abs(check["corr"][~np.eye(kk, dtype=bool)]) if kk > 1 else np.zeros(0)
    return dict(full_rank=bool(check["full_rank"]), condition=check["condition"],
                collinearity_index=check["collinearity_index"],
                max_rel_crb=float(np.max(check["rel_std"])),
                max_abs_corr=float(offd.max()) if offd.size else 0.0,
                corr=check["corr"], rel_crb=check["rel_std"])

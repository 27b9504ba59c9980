"""Sensitivity and identifiability: which parameters a record can estimate.

Local analysis (at one parameter vector θ, along one record)
------------------------------------------------------------
* **Output sensitivities** dy/dθ from the forward sensitivity equations
  (e.g. Dickinson & Gelinas 1976): with S = dx/dθ,

  ::

      dx/dt = f(x, u, θ),          x(t0) = x0
      dS/dt = ∂f/∂x · S + ∂f/∂θ,   S(t0) = 0
      dy/dθ = ∂h/∂x · S + ∂h/∂θ

  integrated together by scipy's ``solve_ivp`` (BDF by default) with the
  generated Jacobians ``dfdx``, ``dfdtheta``, ``dhdx``, ``dhdtheta`` — no
  finite differences. Columns are integrated scaled, S̃_j = s_j ∂x/∂θ_j
  (``s_j`` = :func:`parameter_scale`), so every column has the units of x
  and one absolute tolerance serves all of them.
* **Fisher information of the UKF likelihood** F (the expected information
  of the prediction-error decomposition, :func:`bondgraph.inference.fisher.derivatives`,
  one batched UKF run with nudged copies), in relative coordinates
  F̃ = diag(s) F diag(s); the Cramér-Rao bounds std = sqrt(diag F⁻¹), the
  correlation matrix, eigenvalues and condition number.
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

Parameter selection
-------------------
:func:`recommend` is the orthogonalised sensitivity ranking of Yao et al.
(2003) with a subset-selection test at every step: the candidate whose
scaled sensitivity direction has the largest component orthogonal to the
parameters already selected (the Schur complement of F̃, i.e. Yao's
Gram-Schmidt step written with the information matrix) is tried next; it is
kept if the enlarged set still has a positive definite information, every
relative Cramér-Rao bound under ``rel_crb_max`` and every |correlation|
under ``corr_max``, otherwise it is fixed, with the reason. The selected set
is then full-rank by construction (checked and reported).

Global analysis
---------------
:func:`sobol_indices` wraps SALib: Saltelli's extension of the Sobol'
sequence (``SALib.sample.sobol``) and the Sobol'/Saltelli estimators with
bootstrap confidence intervals (``SALib.analyze.sobol``): first-order S1,
total ST and second-order S2 indices (Sobol' 2001; Saltelli 2002; Saltelli
et al. 2010). The whole sample is evaluated in batches: the NLL of the
UKF for all parameter sets of a chunk in one :func:`bondgraph.inference.ukf.ukf_nll`
call, chosen outputs by one batched fixed-step simulation per chunk.

CLI: ``bondgraph sensitivity --model M --data FILE.csv [--params a,b] [--global N]``
writes ``sensitivity.json`` and PNG plots; ``bondgraph estimate --params
recommended:<dir>/sensitivity.json`` estimates the recommended set.

References
----------
Brun, R., Reichert, P., Künsch, H. R. (2001). Practical identifiability
analysis of large environmental simulation models. Water Resources Research
37(4), 1015-1030.
Dickinson, R. P., Gelinas, R. J. (1976). Sensitivity analysis of ordinary
differential equation systems — a direct method. J. Comput. Phys. 21(2),
123-143.
Saltelli, A. (2002). Making best use of model evaluations to compute
sensitivity indices. Comput. Phys. Commun. 145(2), 280-297.
Saltelli, A., Annoni, P., Azzini, I., Campolongo, F., Ratto, M., Tarantola,
S. (2010). Variance based sensitivity analysis of model output. Comput.
Phys. Commun. 181(2), 259-270.
Sobol', I. M. (2001). Global sensitivity indices for nonlinear mathematical
models and their Monte Carlo estimates. Math. Comput. Simul. 55, 271-280.
Yao, K. Z., Shaw, B. M., Kou, B., McAuley, K. B., Bacon, D. W. (2003).
Modeling ethylene/butene copolymerization with multi-site catalysts:
parameter estimability and experimental design. Polymer Reaction
Engineering 11(3), 563-588.
"""

from __future__ import annotations

import json
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

import numpy as np

from bondgraph.errors import DataError, NumericalError, SensitivityError
from bondgraph.inference.options import UKFOptions, ukf_options

#: defaults of the selection rules
REL_CRB_MAX = 0.10
CORR_MAX = 0.95
#: |cos| of two log-sensitivity directions above 1 - PARALLEL_TOL: product / ratio
PARALLEL_TOL = 1e-6
#: relative eigenvalue of the normalised information below which it is singular
RCOND = 1e-9


# --------------------------------------------------------------- helpers
def _resolve_model(model):
    from bondgraph.numerics.model import Model

    return Model.load(model) if isinstance(model, str) else model


def free_parameters(model) -> list[str]:
    """Parameters whose bounds are a proper interval (lower < upper).

    Returns
    -------
    list of str
    """
    return [p for i, p in enumerate(model.params) if model.upper[i] > model.lower[i]]


def check_params(model, params: Sequence[str] | None) -> list[str]:
    """Validated parameter names (default: :func:`free_parameters`).

    Raises
    ------
    SensitivityError
        Empty list or a name given twice.
    ModelError
        Unknown names (the message lists the model's parameters).
    """
    params = free_parameters(model) if params is None else list(params)
    if not params:
        raise SensitivityError(f"no parameters to analyse for model '{model.name}'")
    dup = sorted({p for p in params if params.count(p) > 1})
    if dup:
        raise SensitivityError(f"parameter(s) listed twice: {', '.join(dup)}")
    model.param_indices(params)
    return params


def parameter_scale(model, params: Sequence[str], theta) -> np.ndarray:
    """Scale s_j of each parameter for relative sensitivities and bounds.

    ``|θ_j|``, or the width of its box when θ_j is (nearly) zero (an offset
    such as a sensor bias has no natural relative scale).

    Returns
    -------
    ndarray (k,)
    """
    idx = model.param_indices(params)
    th = np.asarray(theta, dtype=float)[idx]
    width = model.upper[idx] - model.lower[idx]
    small = np.abs(th) <= 1e-9 * np.maximum(width, 1e-300)
    s = np.where(small, width, np.abs(th))
    return np.where(s > 0, s, 1.0)


def _theta_vector(model, theta) -> np.ndarray:
    from bondgraph.numerics.simulate import _vector

    return _vector(model, theta, "theta")


def _state_vector(model, x0) -> np.ndarray:
    from bondgraph.numerics.simulate import _vector

    return _vector(model, x0, "x0")


# ------------------------------------------------- forward sensitivities
@dataclass
class Sensitivities:
    """Output sensitivities along a record (:func:`output_sensitivities`).

    Attributes
    ----------
    t : ndarray (N,)
    x : ndarray (N, n_x)
        States of the nominal simulation.
    y : ndarray (N, n_y)
        Noise-free outputs.
    dxdtheta : ndarray (N, n_x, k)
        ∂x/∂θ_j [state unit / parameter unit].
    dydtheta : ndarray (N, n_y, k)
        ∂y/∂θ_j [output unit / parameter unit].
    params : list of str
    theta : ndarray (n_theta,)
        Parameter vector of the analysis.
    scale : ndarray (k,)
        Parameter scales s_j (:func:`parameter_scale`).
    outputs : list of str
    stats : dict
        Solver statistics (nfev, njev, nlu, wall time, ...).
    """

    t: np.ndarray
    x: np.ndarray
    y: np.ndarray
    dxdtheta: np.ndarray
    dydtheta: np.ndarray
    params: list
    theta: np.ndarray
    scale: np.ndarray
    outputs: list
    stats: dict = field(default_factory=dict)

    def scaled(self, sigma=None) -> np.ndarray:
        """Scaled (dimensionless) sensitivities s_j ∂y_i/∂θ_j / σ_i.

        Parameters
        ----------
        sigma : array (n_y,), optional
            Output scales, e.g. the measurement-noise standard deviations
            (default 1: relative sensitivities s_j ∂y/∂θ_j in output units).

        Returns
        -------
        ndarray (N, n_y, k)
        """
        sig = np.ones(len(self.outputs)) if sigma is None else np.asarray(sigma, float)
        return self.dydtheta * self.scale[None, None, :] / sig[None, :, None]

    def information(self, sigma, mask=None) -> np.ndarray:
        """Output-error Fisher information in relative coordinates,
        Σ_k Z_kᵀ Z_k with Z = :meth:`scaled` (σ = noise std).

        Parameters
        ----------
        sigma : array (n_y,)
            Measurement-noise standard deviations.
        mask : array of bool (N, n_y), optional
            Measured samples (default: all).

        Returns
        -------
        ndarray (k, k)
        """
        Z = self.scaled(sigma)
        if mask is not None:
            Z = np.where(np.asarray(mask, bool)[:, :, None], Z, 0.0)
        Zf = Z.reshape(-1, Z.shape[-1])
        return Zf.T @ Zf


def output_sensitivities(model, t, u=None, theta=None, x0=None,
                         params: Sequence[str] | None = None, *, method: str = "LSODA",
                         rtol: float = 1e-8, atol: float = 1e-10, hold: str = "linear",
                         max_step: float | None = None) -> Sensitivities:
    """Output sensitivities dy/dθ along a record by the forward sensitivity
    equations (not finite differences).

    Parameters
    ----------
    model : Model or str
    t : array (N,)
        Sample times [s], strictly increasing.
    u : array (N, n_u), dict or callable, optional
        Inputs (any form accepted by :func:`bondgraph.numerics.simulate.simulate`).
    theta : array (n_theta,) or dict, optional
        Parameters (default: model defaults; a dict overrides named ones).
    x0 : array (n_x,) or dict, optional
        Initial state, taken as independent of θ (S(t0) = 0).
    params : sequence of str, optional
        Parameters differentiated (default :func:`free_parameters`).
    method : {"BDF", "Radau", "LSODA"} or an explicit solve_ivp method
        Implicit methods get the Jacobian of the augmented system
        (block-diagonal: ∂f/∂x on every block; the second-derivative
        coupling of S to x is left out, which only slows Newton's
        convergence, not the accuracy).
    rtol, atol : float
        Tolerances for x and for the scaled sensitivities s_j ∂x/∂θ_j
        (same units as x).
    hold : {"linear", "zoh"}
        Sampled inputs between samples (``"zoh"``: integrated segment by
        segment, as the UKF's default sees them).
    max_step : float, optional

    Returns
    -------
    Sensitivities

    Raises
    ------
    ModelError
        Unknown parameter names, wrong shapes.
    NumericalError
        If the solver fails (time and message given).
    """
    from scipy.integrate import solve_ivp

    from bondgraph.numerics.simulate import InputSignals

    model = _resolve_model(model)
    params = check_params(model, params)
    idx = model.param_indices(params)
    th = _theta_vector(model, theta)
    x_init = _state_vector(model, x0)
    t = np.asarray(t, dtype=float)
    if t.ndim != 1 or t.size < 2 or np.any(np.diff(t) <= 0):
        raise DataError("t must be a strictly increasing 1-D array of at least 2 samples")
    sc = parameter_scale(model, params, th)
    sig = InputSignals(model, t, u, hold=hold)
    n, k, N = model.n_x, len(idx), t.size
    th1 = th[None, :]
    eye_k = np.eye(k)

    def make(u_at):
        def rhs(tq, z):
            x = z[:n][None, :]
            uq = u_at(tq)[None, :]
            fx = model.f(x, uq, th1)[0]
            A = model.dfdx(x, uq, th1)[0]
            B = model.dfdtheta(x, uq, th1)[0][:, idx] * sc
            S = z[n:].reshape(n, k)
            return np.concatenate([fx, (A @ S + B).ravel()])

        def jac(tq, z):
            A = model.dfdx(z[:n][None, :], u_at(tq)[None, :], th1)[0]
            J = np.zeros((n + n * k, n + n * k))
            J[:n, :n] = A
            J[n:, n:] = np.kron(A, eye_k)
            return J
        return rhs, jac

    if hold == "zoh":
        bounds = list(sig.change_points()) + [N - 1]
        segments = [(a, b) for a, b in zip(bounds[:-1], bounds[1:]) if b > a]
    else:
        segments = [(0, N - 1)]
    Z = np.empty((N, n + n * k))
    z = np.concatenate([x_init, np.zeros(n * k)])
    Z[0] = z
    kw: dict[str, Any] = dict(method=method, rtol=rtol, atol=atol)
    if max_step is not None:
        kw["max_step"] = float(max_step)
    totals = {"nfev": 0, "njev": 0, "nlu": 0}
    t_wall = time.perf_counter()
    for a, b in segments:
        u_at = sig.segment_input(a, hold)
        rhs, jac = make(u_at)
        if method in ("BDF", "Radau", "LSODA"):
            kw["jac"] = jac
        with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
            sol = solve_ivp(rhs, (t[a], t[b]), z, t_eval=t[a:b + 1], **kw)
        for key in totals:
            totals[key] += int(getattr(sol, key, 0) or 0)
        if sol.status != 0 or sol.y.shape[1] != b - a + 1 or not np.isfinite(sol.y).all():
            t_fail = float(sol.t[-1]) if sol.t.size else float(t[a])
            raise NumericalError(
                f"forward sensitivity integration ({method}) of model '{model.name}' failed "
                f"near t = {t_fail:.6g} s: {sol.message}",
                hint="try method='LSODA' or 'Radau', looser tolerances, or fewer parameters")
        Z[a:b + 1] = sol.y.T
        z = Z[b]
    X = Z[:, :n]
    St = Z[:, n:].reshape(N, n, k)                      # scaled: s_j ∂x/∂θ_j
    U = sig.samples
    with np.errstate(all="ignore"):
        Y = np.asarray(model.h(X, U, th1), dtype=float)
        Hx = model.dhdx(X, U, th1)                     # (N, n_y, n_x)
        Ht = model.dhdtheta(X, U, th1)[:, :, idx]      # (N, n_y, k)
    dY_scaled = Hx @ St + Ht * sc
    stats = dict(method=method, rtol=rtol, atol=atol, hold=hold, segments=len(segments),
                 augmented_states=n + n * k, wall_time_s=time.perf_counter() - t_wall, **totals)
    return Sensitivities(t=t, x=X, y=Y, dxdtheta=St / sc, dydtheta=dY_scaled / sc,
                         params=list(params), theta=th, scale=sc, outputs=list(model.outputs),
                         stats=stats)


# -------------------------------------------------- UKF Fisher information
def ukf_fisher(model, t, u, y, theta, params: Sequence[str], x0=None, P0=None,
               options: UKFOptions | None = None, rel_step: float = 1e-6):
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
    from bondgraph.inference.fisher import derivatives
    from bondgraph.inference.ukf import default_P0

    idx = model.param_indices(params)
    th = np.asarray(theta, dtype=float)
    x0a = model.x0.copy() if x0 is None else np.asarray(x0, dtype=float)
    P0a = default_P0(model, x0a) if P0 is None else P0
    lo, hi = model.lower[idx], model.upper[idx]
    width = np.maximum(hi - lo, 1e-300)
    xv = th[idx]
    steps = rel_step * np.maximum(np.abs(xv), 1e-3 * width)
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
    information.

    Parameters
    ----------
    F : array (k, k)
        Fisher information in model units (or already relative with
        ``scale=None``).
    names : sequence of str (k)
    scale : array (k,), optional
        Parameter scales s (:func:`parameter_scale`): the analysis is in
        relative coordinates θ_j / s_j, F̃ = diag(s) F diag(s).
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
        ``condition`` (of F̃), ``collinearity_index`` γ (Brun et al. 2001),
        ``full_rank`` (bool), ``std (k,)``, ``rel_std (k,)``, ``corr (k, k)``
        (NaN when singular), ``null_directions`` (list of {param: weight}
        in relative coordinates d θ_j / s_j), ``flags`` (list of dicts with
        ``type`` in {"no_sensitivity", "singular", "product", "ratio",
        "correlated", "crb"}, ``params``, ``value``, ``message``) and
        ``unidentifiable`` (sorted names appearing in a flag).
    """
    names = list(names)
    k = len(names)
    F = np.asarray(F, dtype=float)
    if F.shape != (k, k):
        raise SensitivityError(f"information matrix has shape {F.shape}, expected ({k}, {k})")
    s = np.ones(k) if scale is None else np.asarray(scale, dtype=float)
    Fs = 0.5 * (F + F.T) * np.outer(s, s)
    d = np.sqrt(np.clip(np.diag(Fs), 0.0, None))
    dmax = float(d.max()) if k else 0.0
    dead = d <= 1e-12 * max(dmax, 1e-300)
    dd = np.where(dead, 1.0, d)
    C = Fs / np.outer(dd, dd)
    C[dead, :] = 0.0
    C[:, dead] = 0.0
    np.fill_diagonal(C, np.where(dead, 0.0, 1.0))
    flags: list[dict] = []
    for i in np.flatnonzero(dead):
        flags.append(_flag("no_sensitivity", [names[i]], 0.0,
                           f"{names[i]}: the record carries no information on it (zero "
                           f"sensitivity)"))
    live = np.flatnonzero(~dead)
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
    lam_s = np.linalg.eigvalsh(Fs) if k else np.zeros(0)
    out: dict[str, Any] = dict(
        params=names, scale=s, F_rel=Fs, cosine=C, eigenvalues=lam_s,
        condition=float(lam_s[-1] / lam_s[0]) if k and lam_s[0] > 0 else float("inf"),
        collinearity_index=float("inf"), full_rank=False,
        std=np.full(k, np.nan), rel_std=np.full(k, np.nan), corr=np.full((k, k), np.nan),
        null_directions=[], flags=flags)
    if k and not dead.any():
        lam, V = np.linalg.eigh(C)
        if lam[0] > 0:
            out["collinearity_index"] = float(1.0 / np.sqrt(lam[0]))
        if lam[0] <= rcond:
            for m_ in np.flatnonzero(lam <= rcond):
                v = V[:, m_]
                w = v / d                                    # relative coordinates
                w = w / np.max(np.abs(w))
                terms = {names[i]: float(w[i]) for i in np.argsort(-np.abs(w)) if abs(w[i]) > 0.05}
                out["null_directions"].append(terms)
                txt = " ".join(f"{c:+.2f}·δ{p}" for p, c in terms.items())
                flags.append(_flag("singular", list(terms), float(lam[m_]),
                                   f"information singular (normalised eigenvalue {lam[m_]:.2g})"
                                   f": the direction {txt} (relative changes δθ = dθ/s) is not identified"))
        else:
            cov = np.linalg.inv(Fs)
            rel = np.sqrt(np.diag(cov))
            corr = cov / np.outer(rel, rel)
            out.update(full_rank=True, rel_std=rel, std=rel * s, corr=corr)
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
    elif k and dead.any() and len(live):
        sub = identifiability(Fs[np.ix_(live, live)], [names[i] for i in live], None,
                              corr_max=corr_max, rel_crb_max=rel_crb_max,
                              parallel_tol=parallel_tol, rcond=rcond)
        out["collinearity_index"] = sub["collinearity_index"]
        flags.extend(f for f in sub["flags"] if f["type"] not in ("product", "ratio"))
        out["null_directions"] = [{names[i]: 1.0} for i in np.flatnonzero(dead)]
        out["null_directions"] += sub["null_directions"]
        if sub["full_rank"]:
            # bounds of the others with the insensitive ones fixed; infinite for those
            out["rel_std"][dead] = np.inf
            out["rel_std"][live] = sub["rel_std"]
            out["std"] = out["rel_std"] * s
            out["corr"][np.ix_(live, live)] = sub["corr"]
    out["unidentifiable"] = sorted({p for f in flags for p in f["params"]})
    return out


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
        max_abs_corr``), thresholds.
    """
    names = list(names)
    k = len(names)
    s = np.ones(k) if scale is None else np.asarray(scale, dtype=float)
    Fs = 0.5 * (np.asarray(F, float) + np.asarray(F, float).T) * np.outer(s, s)
    pairs = identifiability(F, names, s, parallel_tol=parallel_tol, rcond=rcond,
                            corr_max=corr_max, rel_crb_max=rel_crb_max)
    partners: dict[str, list[str]] = {}
    for fl in pairs["flags"]:
        if fl["type"] in ("product", "ratio"):
            a, b = fl["params"]
            partners.setdefault(a, []).append(f"the {fl['type']} with {b}")
            partners.setdefault(b, []).append(f"the {fl['type']} with {a}")
    selected: list[int] = []
    undecided = list(range(k))
    decisions = []
    top = None
    rank = 0
    while undecided:
        # Schur complement of Fs on the selected set: orthogonal components
        if selected:
            A = Fs[np.ix_(selected, selected)]
            Bm = Fs[np.ix_(selected, undecided)]
            try:
                sol = np.linalg.solve(A, Bm)
            except np.linalg.LinAlgError:
                sol = np.linalg.lstsq(A, Bm, rcond=None)[0]
            res = np.array([Fs[j, j] for j in undecided]) - np.einsum("ij,ij->j", Bm, sol)
        else:
            res = np.array([Fs[j, j] for j in undecided])
        res = np.clip(res, 0.0, None)
        pick = int(np.argmax(res))
        j = undecided.pop(pick)
        rank += 1
        norm = float(np.sqrt(res[pick]))
        if top is None:
            top = norm if norm > 0 else 1.0
        p = names[j]
        dec = dict(param=p, rank=rank, orthogonal_norm=norm / top, rel_crb=None)
        trial = selected + [j]
        Ft = Fs[np.ix_(trial, trial)]
        ident = identifiability(Ft, [names[i] for i in trial], None, corr_max=corr_max,
                                rel_crb_max=rel_crb_max, parallel_tol=parallel_tol, rcond=rcond)
        if norm <= np.sqrt(rcond) * top or not ident["full_rank"]:
            why = (f"adds no independent direction (orthogonalised sensitivity "
                   f"{norm / top:.1e} of the first)")
            if p in partners:
                why = f"enters only as {', '.join(partners[p])}: " + why
            elif selected:
                why += f"; information singular with {', '.join(names[i] for i in selected)}"
            dec.update(decision="fix", reason=why)
        else:
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
                selected.append(j)
        decisions.append(dec)
    est = [names[i] for i in selected]
    check = identifiability(Fs[np.ix_(selected, selected)], est, None, corr_max=corr_max,
                            rel_crb_max=rel_crb_max, parallel_tol=parallel_tol, rcond=rcond) \
        if selected else None
    final_rel = dict(zip(est, check["rel_std"])) if check else {}
    for dec in decisions:
        if dec["decision"] == "estimate":
            r = float(final_rel[dec["param"]])
            dec["rel_crb"] = r
            dec["reason"] = (f"rank {dec['rank']} (orthogonalised sensitivity "
                             f"{dec['orthogonal_norm']:.2g} of the first), relative CRB "
                             f"{r:.2%} in the recommended set")
    summary = None
    if check is not None:
        kk = len(est)
        offd = np.abs(check["corr"][~np.eye(kk, dtype=bool)]) if kk > 1 else np.zeros(0)
        summary = dict(full_rank=bool(check["full_rank"]), condition=check["condition"],
                       collinearity_index=check["collinearity_index"],
                       max_rel_crb=float(np.max(check["rel_std"])),
                       max_abs_corr=float(offd.max()) if offd.size else 0.0,
                       corr=check["corr"], rel_crb=check["rel_std"])
    return dict(experiment=experiment, estimate=est,
                fix=[d["param"] for d in decisions if d["decision"] == "fix"],
                decisions=decisions, check=summary,
                thresholds=dict(rel_crb_max=rel_crb_max, corr_max=corr_max, rcond=rcond,
                                parallel_tol=parallel_tol),
                method="orthogonalised sensitivity ranking (Yao et al. 2003) with subset "
                       "selection on the relative Fisher information of the UKF likelihood")


# ----------------------------------------------------------------- global
def _pow2(n: int) -> int:
    n = max(int(n), 2)
    return 1 << (n - 1).bit_length()


def sobol_indices(fun: Callable[[np.ndarray], np.ndarray], names: Sequence[str], lower, upper,
                  N: int, *, second_order: bool = True, seed: int | None = 0,
                  chunk: int | None = None, conf_level: float = 0.95, num_resamples: int = 100,
                  output_names: Sequence[str] | None = None, progress: bool = False,
                  desc: str = "sobol",
                  transforms: Mapping[str, Callable[[np.ndarray], np.ndarray]] | None = None
                  ) -> dict:
    """Sobol' indices of a batched function over a box (SALib).

    Parameters
    ----------
    fun : callable
        ``fun(X (S, k)) -> (S,)`` or ``(S, m)``: evaluates a whole chunk of
        the sample in one call.
    names : sequence of str (k)
    lower, upper : arrays (k,)
        The box (uniform distributions).
    N : int
        Base sample size, rounded up to a power of two (Sobol' sequence);
        ``N (2k + 2)`` evaluations with second-order indices, ``N (k + 2)``
        without.
    second_order : bool
    seed : int, optional
        Scrambling of the sequence and bootstrap.
    chunk : int, optional
        Largest number of rows per call of ``fun`` (default: all at once).
    conf_level : float
        Level of the bootstrap confidence intervals.
    num_resamples : int
    output_names : sequence of str (m), optional
    progress : bool
        tqdm progress bar over the chunks.
    transforms : dict output name -> callable, optional
        Applied to an output's whole column (after non-finite values are
        replaced) before the analysis, e.g. :func:`log_excess`.

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
        Bad box or all evaluations non-finite.
    """
    from SALib.analyze import sobol as sobol_analyze
    from SALib.sample import sobol as sobol_sample

    names = list(names)
    k = len(names)
    lo, hi = np.asarray(lower, float), np.asarray(upper, float)
    if lo.shape != (k,) or hi.shape != (k,) or not np.all(hi > lo):
        raise SensitivityError(f"the box must have lower < upper for each of {names}")
    if k < 2:
        raise SensitivityError("Sobol' indices need at least two parameters")
    Np = _pow2(N)
    problem = dict(num_vars=k, names=names, bounds=[[float(a), float(b)] for a, b in zip(lo, hi)])
    X = sobol_sample.sample(problem, Np, calc_second_order=second_order, seed=seed)
    S = X.shape[0]
    step = int(chunk) if chunk else S
    parts = []
    it = range(0, S, step)
    if progress:
        from tqdm.auto import tqdm

        it = tqdm(it, desc=desc, unit="chunk", total=(S + step - 1) // step, leave=False)
    t_wall = time.perf_counter()
    for a in it:
        parts.append(np.asarray(fun(X[a:a + step]), dtype=float).reshape(min(step, S - a), -1))
    Y = np.concatenate(parts, axis=0)
    m = Y.shape[1]
    onames = list(output_names) if output_names is not None else (
        ["y"] if m == 1 else [f"y{i}" for i in range(m)])
    if len(onames) != m:
        raise SensitivityError(f"{len(onames)} output names for {m} outputs")
    out: dict[str, Any] = dict(N=Np, evaluations=int(S), names=names, lower=lo, upper=hi,
                               conf_level=conf_level, second_order=second_order, failed={},
                               wall_time_s=time.perf_counter() - t_wall, indices={})
    for c, on in enumerate(onames):
        yc = Y[:, c].copy()
        bad = ~np.isfinite(yc)
        out["failed"][on] = int(bad.sum())
        if bad.all():
            raise SensitivityError(f"every evaluation of '{on}' is non-finite")
        if bad.any():
            yc[bad] = np.max(yc[~bad])
        if transforms and on in transforms:
            yc = np.asarray(transforms[on](yc), dtype=float)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            Si = sobol_analyze.analyze(problem, yc, calc_second_order=second_order,
                                       conf_level=conf_level, num_resamples=num_resamples,
                                       seed=seed)
        d = {key: np.asarray(Si[key], dtype=float) for key in ("S1", "S1_conf", "ST", "ST_conf")}
        if second_order:
            d["S2"] = np.asarray(Si["S2"], dtype=float)
            d["S2_conf"] = np.asarray(Si["S2_conf"], dtype=float)
        d["variance"] = float(np.var(yc))
        out["indices"][on] = d
    return out


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


def simulate_batch(model, t, u, thetas, x0, *, method: str = "ros2", substeps: int = 2,
                   hold: str = "zoh") -> np.ndarray:
    """Noise-free outputs of many parameter sets at once (fixed-step,
    batched over the sets).

    Parameters
    ----------
    model : Model
    t : array (N,)
    u : array (N, n_u)
    thetas : array (P, n_theta)
    x0 : array (n_x,) or (P, n_x)
    method : {"ros2", "rk4"}
    substeps : int
    hold : {"zoh", "mean"}
        Input over an interval: u_k or (u_k + u_k+1)/2.

    Returns
    -------
    ndarray (N, P, n_y)
        NaN from the sample where a set's state turned non-finite.
    """
    from bondgraph.numerics.integrators import make_step

    th = np.atleast_2d(np.asarray(thetas, float))
    P = th.shape[0]
    x = np.broadcast_to(np.asarray(x0, float), (P, model.n_x)).copy()
    u = np.asarray(u, float).reshape(t.size, -1)
    step = make_step(model, method, substeps)
    Y = np.full((t.size, P, model.n_y), np.nan)
    with np.errstate(all="ignore"):
        Y[0] = model.h(x, u[0][None], th)
        for k_ in range(t.size - 1):
            uk = u[k_] if hold == "zoh" else 0.5 * (u[k_] + u[k_ + 1])
            x = step(x, uk[None], th, t[k_ + 1] - t[k_])
            bad = ~np.isfinite(x).all(axis=1)
            if bad.any():
                x[bad] = np.nan
            Y[k_ + 1] = model.h(x, u[k_ + 1][None], th)
    return Y


def global_sensitivity(model, t, u, y, params: Sequence[str], N: int, *, theta=None, x0=None,
                       P0=None, ukf: UKFOptions | None = None,
                       outputs: Sequence[str] = (), box: tuple | None = None,
                       box_rel: float | None = None, chunk: int = 256, seed: int | None = 0,
                       second_order: bool = True, progress: bool = False,
                       conf_level: float = 0.95, nll_transform: str = "log") -> dict:
    """Sobol' indices of the UKF NLL (and of the time-means of chosen
    outputs) over a parameter box.

    Parameters
    ----------
    model : Model
    t, u, y : arrays (N,), (N, n_u), (N, n_y)
        Record (y is used by the NLL only).
    params : sequence of str (k)
    N : int
        Base sample size (power of two; N (2k + 2) evaluations).
    theta : array (n_theta,), optional
        Values of the parameters outside ``params``.
    x0, P0 : UKF prior / initial state
    ukf : UKFOptions, optional
        Filter options (:func:`bondgraph.inference.ukf.ukf_nll`); the
        outputs' simulation uses its method, substeps and hold too.
    outputs : sequence of str
        Model outputs whose time-mean over the record (noise-free, batched
        fixed-step simulation with the UKF's method and substeps) also gets
        indices.
    box : (lower (k,), upper (k,)), optional
        Default: the model's bounds, or θ (1 ± box_rel) if ``box_rel``.
    chunk : int
        Parameter sets per batched UKF run.
    seed, second_order, progress, conf_level :
        See :func:`sobol_indices`.
    nll_transform : {"log", "none"}
        Indices of ln(1 + NLL − min NLL) (:func:`log_excess`, default) or of
        the NLL itself.

    Returns
    -------
    dict
        As :func:`sobol_indices`, outputs named ``"NLL"`` and
        ``"mean(<output>)"``; ``nll_transform``, ``nll_min``, ``nll_max``.
    """
    if nll_transform not in ("log", "none"):
        raise SensitivityError(f"unknown NLL transform '{nll_transform}' (log, none)")
    from bondgraph.inference.ukf import default_P0, ukf_nll

    params = check_params(model, params)
    idx = model.param_indices(params)
    th = _theta_vector(model, theta)
    x0a = _state_vector(model, x0)
    P0a = default_P0(model, x0a) if P0 is None else P0
    ukf = ukf_options(ukf)
    oidx = [model.output_index(o) for o in outputs]
    if box is not None:
        lo, hi = (np.asarray(b, float) for b in box)
    elif box_rel is not None:
        c = th[idx]
        w = np.abs(c) * box_rel
        w = np.where(w > 0, w, box_rel * (model.upper[idx] - model.lower[idx]))
        lo, hi = c - w, c + w
    else:
        lo, hi = model.lower[idx], model.upper[idx]

    def fun(X):
        sets = model.expand_theta(params, X, th)
        r = ukf_nll(model, t, u, y, sets, x0a, P0a, options=ukf)
        cols = [r.nll]
        if oidx:
            Ys = simulate_batch(model, t, u, sets, x0a, method=ukf.method,
                                substeps=ukf.substeps, hold=ukf.hold)
            for j in oidx:
                cols.append(np.mean(Ys[:, :, j], axis=0))
        return np.column_stack(cols)

    onames = ["NLL"] + [f"mean({o})" for o in outputs]
    seen: dict[str, float] = {}

    def tr(yv):
        seen.update(nll_min=float(np.min(yv)), nll_max=float(np.max(yv)))
        return log_excess(yv) if nll_transform == "log" else yv

    res = sobol_indices(fun, params, lo, hi, N, second_order=second_order, seed=seed,
                        chunk=chunk, conf_level=conf_level, output_names=onames,
                        progress=progress, desc="Sobol NLL", transforms={"NLL": tr})
    res.update(nll_transform="ln(1 + NLL - min NLL)" if nll_transform == "log" else "none",
               **seen)
    res["box"] = "custom" if box is not None else (f"theta*(1±{box_rel:g})" if box_rel
                                                   else "model bounds")
    return res


# ---------------------------------------------------------- full analysis
def initial_state(model, experiment) -> tuple[np.ndarray, str]:
    """Initial state of the analysis: the record's rule
    (:meth:`bondgraph.data.records.Experiment.initial_state`: state columns,
    else sidecar x0, else the model's X0).

    Returns
    -------
    (x0 (n_x,), description)
    """
    return experiment.initial_state(model), "record state columns / sidecar x0"


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
        from bondgraph.inference.estimate import json_ready

        d = dict(format="bondgraph-sensitivity/1", model=self.model, experiment=self.experiment,
                 params=self.params, theta=self.theta, scale=self.scale, local=self.local,
                 recommendation=self.recommendation, settings=self.settings)
        d["global"] = self.global_
        return json_ready(d)

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
        fl = self.local.get("identifiability", {}).get("flags", [])
        for f in fl:
            if f["type"] in ("product", "ratio", "singular", "correlated", "no_sensitivity"):
                lines.append(f"flag: {f['message']}")
        g = self.global_
        if g:
            ind = g["indices"]["NLL"]
            order = np.argsort(-np.asarray(ind["ST"]))
            what = "ln(1 + NLL - min)" if g.get("nll_transform", "none") != "none" else "the NLL"
            lines.append(f"Sobol' indices of {what} (N = {g['N']}, {g['evaluations']} "
                         f"evaluations, {g['failed'].get('NLL', 0)} failed; "
                         f"{int(100 * g['conf_level'])} % confidence):")
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
        return "\n".join(lines)


def analyse(model, experiment, params: Sequence[str] | None = None, *, theta=None, x0=None,
            P0=None, p0_rel: float = 0.05,
            ukf: UKFOptions | None = None, global_N: int | None = None,
            outputs: Sequence[str] = (), box_rel: float | None = None, chunk: int = 256,
            seed: int = 0, rel_crb_max: float = REL_CRB_MAX, corr_max: float = CORR_MAX,
            sensitivities: bool = True, sens_method: str = "LSODA", sens_rtol: float = 1e-6,
            sens_atol: float = 1e-8, progress: bool = False, log=None,
            nll_transform: str = "log") -> SensitivityReport:
    """Local (and optionally global) sensitivity and identifiability analysis
    of one record, with a recommendation of the parameters to estimate.

    Parameters
    ----------
    model : Model or str
        Filter model.
    experiment : Experiment, path of a CSV record, or (t, u, y)
    params : sequence of str, optional
        Candidates (default :func:`free_parameters`).
    theta : array or dict, optional
        Parameter values of the analysis (default: model defaults; a dict
        overrides named ones).
    x0 : array (n_x,) or dict, optional
        Initial state (default: :func:`initial_state`, the record's rule).
    P0 : array, optional
        UKF prior covariance (default ``default_P0(model, x0, p0_rel)``).
    ukf : UKFOptions, optional
        Filter options (:func:`bondgraph.inference.ukf.ukf_nll`).
    global_N : int, optional
        Base sample size of the Sobol' analysis (None: local only).
    outputs : sequence of str
        Outputs whose time-means also get Sobol' indices.
    box_rel : float, optional
        Sobol' box θ (1 ± box_rel) instead of the model's bounds.
    chunk : int
        Parameter sets per batched UKF run in the global analysis.
    nll_transform : {"log", "none"}
        Sobol' indices of ln(1 + NLL − min NLL) or of the NLL
        (:func:`global_sensitivity`).
    rel_crb_max, corr_max : float
        Selection thresholds (:func:`recommend`).
    sensitivities : bool
        Also integrate the forward sensitivity equations (output-error
        information, sensitivity plots).
    sens_method, sens_rtol, sens_atol :
        Solver of :func:`output_sensitivities`.
    log : callable, optional
        Progress messages.

    Returns
    -------
    SensitivityReport

    Raises
    ------
    ModelError, SensitivityError, DataError
        Unknown names, bad options, bad records.
    NumericalError
        If the UKF fails at θ.
    """
    from bondgraph.inference.record import record_arrays
    from bondgraph.inference.ukf import default_P0

    say = log or (lambda *_: None)
    model = _resolve_model(model)
    params = check_params(model, params)
    th = _theta_vector(model, theta)
    t, u, y, ename, meta = record_arrays(model, experiment)
    if x0 is None:
        if isinstance(experiment, tuple):
            x0a, x0_how = model.x0.copy(), "model X0"
        else:
            exp = experiment
            if isinstance(exp, (str, Path)):
                from bondgraph.data.records import Experiment

                exp = Experiment.load(exp)
            x0a, x0_how = initial_state(model, exp)
    else:
        x0a, x0_how = _state_vector(model, x0), "given"
    P0a = default_P0(model, x0a, p0_rel) if P0 is None else np.asarray(P0, float)
    ukf = ukf_options(ukf)
    scale = parameter_scale(model, params, th)
    timing: dict[str, float] = {}
    t0 = time.perf_counter()
    say(f"UKF Fisher information: {len(params) + 1} parameter sets in one batched run ...")
    try:
        D = ukf_fisher(model, t, u, y, th, params, x0a, P0a, ukf)
    except FloatingPointError as exc:
        raise NumericalError(f"UKF fails at the analysis point: {exc}") from None
    timing["ukf_fisher_s"] = time.perf_counter() - t0
    ident = identifiability(D.F, params, scale, corr_max=corr_max, rel_crb_max=rel_crb_max)
    rec = recommend(D.F, params, scale, rel_crb_max=rel_crb_max, corr_max=corr_max,
                    experiment=ename)
    ranking = orthogonal_ranking(ident["F_rel"], params)
    local: dict[str, Any] = dict(
        nll=D.nll, grad=D.grad, fisher=D.F, fisher_rel=ident["F_rel"],
        identifiability={k_: ident[k_] for k_ in (
            "std", "rel_std", "corr", "cosine", "eigenvalues", "condition", "collinearity_index",
            "full_rank", "null_directions", "flags", "unidentifiable")},
        ranking=[dict(param=p, orthogonal_norm=n_) for p, n_ in ranking],
        relative_information=np.sqrt(np.clip(np.diag(ident["F_rel"]), 0, None)))
    sens = None
    if sensitivities:
        t0 = time.perf_counter()
        say(f"forward sensitivities ({sens_method}, {model.n_x} + {model.n_x}·{len(params)} "
            f"states) ...")
        hold = "zoh" if ukf.hold == "zoh" else "linear"
        sens = output_sensitivities(model, t, u, th, x0a, params, method=sens_method,
                                    rtol=sens_rtol, atol=sens_atol, hold=hold)
        timing["sensitivities_s"] = time.perf_counter() - t0
        sigma = np.asarray(model.meas_std(th), float)
        mask = np.isfinite(y)
        Z = sens.scaled(sigma)
        Zm = np.where(mask[:, :, None], Z, 0.0)
        F_oe = sens.information(sigma, mask)
        ident_oe = identifiability(F_oe, params, None, corr_max=corr_max,
                                   rel_crb_max=rel_crb_max)
        local["output_error"] = dict(
            description="no process noise, known x0: F = Σ_k (∂y_k/∂θ)ᵀ R⁻¹ ∂y_k/∂θ from the "
                        "forward sensitivity equations, relative coordinates",
            fisher_rel=F_oe, rel_std=ident_oe["rel_std"], full_rank=ident_oe["full_rank"],
            flags=ident_oe["flags"], collinearity_index=ident_oe["collinearity_index"],
            rms_scaled=np.sqrt(np.sum(Zm ** 2, axis=0) / np.maximum(mask.sum(axis=0), 1)[:, None]).T,
            outputs=list(model.outputs), solver=sens.stats)
    glob = None
    if global_N:
        t0 = time.perf_counter()
        say(f"Sobol' indices: N = {_pow2(global_N)} ...")
        glob = global_sensitivity(model, t, u, y, params, global_N, theta=th, x0=x0a, P0=P0a,
                                  ukf=ukf, outputs=outputs, box_rel=box_rel,
                                  chunk=chunk, seed=seed, progress=progress,
                                  nll_transform=nll_transform)
        timing["global_s"] = time.perf_counter() - t0
    return SensitivityReport(
        model=model.name, experiment=ename, params=list(params),
        theta={p: float(th[model.param_index(p)]) for p in params},
        scale=scale.tolist(), local=local, recommendation=rec, global_=glob,
        settings=dict(samples=int(t.size), duration_s=float(t[-1] - t[0]), x0=x0a.tolist(),
                      x0_rule=x0_how, P0_diag=np.diag(P0a).tolist(),
                      ukf=ukf.to_dict(),
                      theta_full=th.tolist(), timing=timing,
                      units=[model.param_units[i] for i in model.param_indices(params)]),
        sensitivities=sens)


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
        _resolve_model(model).param_indices(names)
    return names


# -------------------------------------------------------------------- CLI

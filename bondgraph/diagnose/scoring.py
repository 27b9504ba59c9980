"""Evidence for the candidate effects of one loop step.

* **Additive** effects (friction laws, drags, offsets, gains, sensor
  offset/gain/rectification) are all added at once to a *probe* model at
  their neutral value β = 0 (:func:`bondgraph.diagnose.effects.probe_graph`).
  One batched UKF run with each β nudged gives the innovation signatures
  J = ∂ε/∂β; with whitened innovations e and signatures G the efficient score
  (Lagrange-multiplier) statistic of a candidate with columns c, the
  currently estimated parameters partialled out, is LM = bᵀ A⁻¹ b with
  b = Σ G_cᵀ e, A = Σ G_cᵀ G_c: how much of the innovation energy the
  candidate's signature explains; under "the effect is absent" LM ~ χ²(k)
  (Rao 1948; Engle 1984). A second batched run, the *line probe*, evaluates
  each candidate at multiples of its one-step estimate and replaces the score
  statistic by the likelihood gain where that is larger. Candidates whose
  signatures are indistinguishable are grouped (``Candidate.equivalent``).
* **Structural** effects (slip, compliance, low-pass, saturation, dead zone,
  end stops, backlash, disturbance) have no neutral value: each is built and
  evaluated over a grid of its parameter in one batched UKF run, profiled over
  factors of the estimated noise intensities, giving the likelihood-ratio
  statistic LR = 2 (NLL₀ − NLL₁) ~ χ²(k) (Wilks 1938).

Both statistics are χ²(k): candidates are ranked by the predicted decrease of
AIC, statistic − 2k (Akaike 1974), which is comparable between them.

References
----------
Rao, C. R. (1948). Large sample tests of statistical hypotheses concerning
several parameters. Proc. Cambridge Phil. Soc. 44, 50-57. Engle, R. F. (1984).
Wald, likelihood ratio and Lagrange multiplier tests in econometrics.
Handbook of Econometrics II, ch. 13. Wilks, S. S. (1938). The large-sample
distribution of the likelihood ratio. Ann. Math. Stat. 9, 60-62. Akaike, H.
(1974). A new look at the statistical model identification. IEEE TAC 19(6),
716-723.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass, replace
from types import SimpleNamespace

import numpy as np

from bondgraph.core import progress
from bondgraph.core.deferred import chi2
from bondgraph.diagnose.effects import Scales, get_effect, probe_graph
from bondgraph.diagnose.fit import (Context, Fit, at_step, model_of, noise_params,
                                    problem_for)
from bondgraph.diagnose.inference_calls import (
    Problem,
    fisher_fit,
    fisher_steps,
    predicted_step_gain,
    run_ukf,
)
from bondgraph.diagnose.parallel import distributed, local_map, run_tasks
from bondgraph.diagnose.result import Candidate
from bondgraph.diagnose.scales import operating_scales  # noqa: F401 (public name)
from bondgraph.diagnose.scales import record_scales
from bondgraph.diagnose.screen import output_error_screen
from bondgraph.errors import BondGraphError
from bondgraph.inference.ukf_numba import while_compiling
from bondgraph.numerics.compiled import (
    build_ahead,
    cancel_ahead,
    compile_ahead,
    is_compiled,
    kernel_kind,
)
from bondgraph.numerics.model import Model

#: factors applied to the estimated noise intensities when a structural
#: candidate is screened: a missing effect inflates them, so a candidate's
#: likelihood is profiled over them (their likelihood is far from quadratic
#: near zero)
NOISE_FACTORS = (1.0, 0.3, 0.1, 0.01, 0.001)
#: the same for the line probe of the additive candidates
LINE_NOISE_FACTORS = (1.0, 0.1, 0.01)
#: two nudge sizes of each probe parameter (linearity check of the signature)
LADDER = (1.0, 1e-2)
#: a structural candidate is profiled (:func:`grid_starts`,
#: :func:`profile_declared`) only when its grid's likelihood ratio plus this
#: many times the gain one scoring step from the grid's best predicts,
#: 2·½gᵀF⁻¹g, reaches the critical χ² of the step's significance test
#: (:func:`worth_profiling`). Measured on 391 structural candidates of the
#: bundled cases (the vehicle coast-downs, belt slip, engine saturation, CED,
#: EMPS, Silverbox, the Camry cold start) and a user's DC motor: the
#: profile's final ratio exceeded the grid's plus 4 predicted gains only on
#: candidates already above the critical value (a sensor low-pass whose grid
#: time constant was far off: 27 + 4·134 < 1840); of the 163 it would not
#: have profiled none reached half the critical value (with 2: one, CED's
#: Dahl friction, 13.7 of 14.5)
PROFILE_REACH = 4.0


def noise_variants(model: Model, fit: Fit, base: np.ndarray, factors) -> list:
    """Copies of ``base`` (n_theta,) with the estimated noise intensities of
    ``fit`` (:func:`bondgraph.diagnose.fit.noise_params`) scaled by each
    factor, clipped to their box, each distinct copy once (an intensity on
    the bottom of its box, as after an effect that explains the record,
    gives the same copy for every factor below 1: its filter runs would
    repeat one another); ``[base]`` if none is estimated."""
    noise = noise_params(fit.model)
    names = [n for n in fit.params if n in noise and n in model.params]
    if not names:
        return [base]
    out: list = []
    for f in factors:
        th = base.copy()
        for n in names:
            j = model.param_index(n)
            th[j] = float(np.clip(base[j] * f, model.lower[j], model.upper[j]))
        if not any(np.array_equal(th, o) for o in out):
            out.append(th)
    return out


# --------------------------------------------------------------- additive
@dataclass
class Probe:
    """The probe model of one step and what the score test needs of it:
    its columns (:class:`bondgraph.diagnose.effects.ProbeColumn`), θ with the
    current estimates and every β = 0, its problem (the record arrays, the
    UKF prior, the held noise levels), and the θ indices of the probe
    parameters and of the estimated ones."""

    model: Model
    cols: list
    base: np.ndarray
    problem: Problem
    idx: list
    nuis: list

    @property
    def t(self) -> np.ndarray:
        """Sample times (N,) [s]."""
        return self.problem.t

    @property
    def u(self) -> np.ndarray:
        """Inputs (N, n_u) in the probe model's units."""
        return self.problem.u

    @property
    def y(self) -> np.ndarray:
        """Measured outputs (N, n_y), NaN where missing."""
        return self.problem.y


def build_probe(ctx: Context, fit: Fit, scales: Scales, effects) -> Probe | None:
    """The probe model of ``fit``'s graph with every additive effect of
    ``effects`` at β = 0; targets on a causal path the model cannot be built
    with are dropped (logged). None if no additive candidate is left.

    Raises
    ------
    BondGraphError
        If the probe model fails for a reason no target explains.
    """
    exclude: set = set()
    while True:
        pg, cols = probe_graph(fit.graph, effects, scales, exclude)
        if not cols:
            return None
        try:
            pm = model_of(pg)
            break
        except BondGraphError as exc:
            # drop the targets on the failing causal path and retry
            bad = {e.replace("probe.", "", 1) for e in exc.elements} & \
                {c.target.name for c in cols}
            if not bad:
                raise
            ctx.log(f"  probe: no additive effects at {', '.join(sorted(bad))} "
                    f"({str(exc).splitlines()[0][:120]})")
            exclude |= bad
    base = pm.theta0.copy()
    for n in fit.model.params:
        base[pm.param_index(n)] = fit.theta[fit.model.param_index(n)]
    return Probe(pm, cols, base, problem_for(ctx, pm), [pm.param_index(c.param) for c in cols],
                 [pm.param_index(n) for n in fit.params])


def score_additive(ctx: Context, fit: Fit, scales: Scales, effects,
                   screen: bool = True) -> list[Candidate]:
    """Efficient score test (Rao 1948) of every additive candidate with one
    probe model, then the line probe (:func:`line_probe`), the output-error
    screen (:func:`~bondgraph.diagnose.screen.output_error_screen`, unless
    ``screen`` is False) and the equivalence groups (:func:`mark_equivalent`).

    Parameters
    ----------
    ctx : Context
    fit : Fit
        The current model's fit (its estimated parameters are nuisance
        parameters, partialled out).
    scales : Scales
    effects : sequence of Effect
        Only the additive ones are scored.

    Returns
    -------
    list of Candidate
        One per (effect, target), ``kind="score"``, ``values`` the one-step
        estimates, ``explained`` the share of the whitened innovation energy.
    """
    probe = build_probe(ctx, fit, scales, effects)
    if probe is None:
        return []
    deltas, nuis_delta = nudge_sizes(probe, fit, scales.dt)
    eps0, S0, D, Dn, fails = signature_runs(ctx, probe, deltas, nuis_delta)
    J = signatures(eps0, D, Dn, deltas, nuis_delta)
    ew, Gw = whiten(eps0, S0, J)
    total = float(np.sum(ew**2))
    A = np.einsum("kic,kid->cd", Gw, Gw)
    b = np.einsum("kic,ki->c", Gw, ew)
    # columns are scaled to unit norm before solving (conditioning)
    norm = np.sqrt(np.maximum(np.diag(A), 1e-300))
    An = A / np.outer(norm, norm)
    bn = b / norm
    out, col_of = score_groups(ctx, probe.cols, len(probe.nuis), An, bn, norm, total, fails,
                               nuisance=list(fit.params))
    ctx.cache[("score_gram", id(fit), fit.nll)] = (An, bn, norm, col_of, len(probe.nuis))
    mark_equivalent(out, col_of, An, list(range(len(probe.nuis))))
    line_probe(ctx, probe, fit, out)
    if screen:
        output_error_screen(ctx, probe, fit, out)
    rank_nested(out, col_of, An, ctx.settings.accept.significance)
    return out


def rank_nested(cands, col_of, An, alpha: float, tol: float = 0.9999) -> list[tuple]:
    """Rank a candidate that nests another one below it unless its extra
    parameters are significant. Candidate A nests B when they share the
    target and every column of B equals a column of A (|correlation| >
    ``tol`` in the normalised Gram matrix ``An``; a 3rd-order sensor
    calibration nests the 2nd-order one). A then leads only if its extra
    likelihood gain passes the nested likelihood-ratio test,
    stat_A − stat_B > χ²_{1−α}(k_A − k_B) (Wilks 1938); otherwise its score
    becomes score_B − (critical − gain), just below B. AIC's penalty of 2
    per parameter lets the larger model lead in 16 % of the records where
    the smaller one is true.

    Returns
    -------
    list of (A, B) pairs demoted (A's ``score`` changed in place)."""
    demoted = []
    for a in cands:
        for b in cands:
            ca, cb = col_of.get((a.effect, a.target)), col_of.get((b.effect, b.target))
            if a is b or a.target != b.target or not ca or not cb or len(cb) >= len(ca) \
                    or not np.isfinite(a.score) or not np.isfinite(b.score):
                continue
            if not all(max(abs(An[i, j]) for j in ca) > tol for i in cb):
                continue
            gain = a.statistic - b.statistic
            crit = float(chi2.isf(alpha, len(ca) - len(cb)))
            if a.score > b.score and gain <= crit:
                a.score = b.score - (crit - gain)
                demoted.append((a, b))
    return demoted


def nudge_sizes(probe: Probe, fit: Fit, dt: float) -> tuple[np.ndarray, list]:
    """Nudge of each probe parameter (makes its one-sample state or output
    change 1e-3 of the state or output scale along the filtered states) and
    of each estimated parameter (1e-4 relative)."""
    pm, base, u, y = probe.model, probe.base, probe.u, probe.y
    nuis_delta = [1e-4 * max(abs(base[j]), 1e-3 * (pm.upper[j] - pm.lower[j]), 1e-12)
                  for j in probe.nuis]
    X = fit.ukf.x_filt[:, 0, :]
    ok = np.all(np.isfinite(X), axis=1)
    sel = np.flatnonzero(ok)[:: max(1, ok.sum() // 200)]
    xs, us = X[sel], u[sel]
    xscale = np.maximum(np.nanstd(X, axis=0), 1e-9)
    measured = np.isfinite(y).any(axis=0)     # an output the record lacks: NaN, ignored below
    yscale = np.full(y.shape[1], np.nan)
    yscale[measured] = np.maximum(np.nanstd(y[:, measured], axis=0), 1e-12)
    F0 = pm.f(xs, us, base)
    H0 = pm.h(xs, us, base)
    deltas = []
    for j in probe.idx:
        # the term is linear in its coefficient: the change at a value v
        # scales with v. At v = 1 a term of tiny SI magnitude (k3·q³ of an
        # accumulator, q ~ 1e-3 m³, beside 1e7 Pa) is below the rounding
        # of f and h, the change exactly 0, and the nudge was 1e297, which
        # the filter could not run: v grows until the change shows
        v, sens = 1.0, 0.0
        for _ in range(50):
            th = base.copy()
            th[j] = v
            with np.errstate(all="ignore"):
                change = max(np.nanmax(np.abs((pm.f(xs, us, th) - F0) * dt / xscale)),
                             np.nanmax(np.abs((pm.h(xs, us, th) - H0) / yscale)))
            if not np.isfinite(change):
                v *= 1e-8               # an overflow: a smaller value
                continue
            sens = change / v
            if change > 1e-9:
                break
            v *= 1e8
        deltas.append(1e-3 / sens if sens > 0 else 1e-3)
    return np.array(deltas), nuis_delta


def signature_runs(ctx: Context, probe: Probe, deltas: np.ndarray, nuis_delta: list):
    """Batched UKF runs at β = 0, at each probe parameter nudged by each
    :data:`LADDER` step, and at each estimated parameter nudged.

    Returns
    -------
    eps0 : array (N, n_y)
        Innovations at β = 0; ``S0`` (N, n_y, n_y) their covariances.
    D : array (len(LADDER), n_cols, N, n_y)
        Innovations with each probe parameter nudged (NaN where the UKF failed).
    Dn : array (n_nuis, N, n_y)
        Innovations with each estimated parameter nudged.
    fails : dict
        Probe column -> the filter's failure reason, for the columns whose
        nudged runs all failed (their candidates are reported as failed).
    """
    pm, base, t = probe.model, probe.base, probe.t
    sets = [base]
    for j, d in zip(probe.idx, deltas):
        for s in LADDER:
            th = base.copy()
            th[j] = d * s
            sets.append(th)
    for j, d in zip(probe.nuis, nuis_delta):
        th = base.copy()
        th[j] = base[j] + d
        sets.append(th)
    sets = np.array(sets)
    n_lad = 1 + len(probe.idx) * len(LADDER)
    Dn = np.empty((len(probe.nuis), t.size, pm.n_y))
    eps0 = S0 = None
    D = np.empty((len(LADDER), len(probe.cols)) + (t.size, pm.n_y))
    chunk = ctx.settings.evaluation.chunk
    reasons: dict = {}
    for a in range(0, len(sets), chunk):
        r = run_ukf(probe.problem, sets[a:a + chunk], store=True)
        for q in range(r.nll.size):
            if 0 < a + q < n_lad and not np.isfinite(r.nll[q]):
                reasons.setdefault((a + q - 1) // len(LADDER), []).append(str(r.reasons[q]))
        for q in range(r.nll.size):
            gi = a + q
            if gi == 0:
                eps0 = r.innovations[:, 0, :].copy()
                S0 = r.S[:, 0, :, :].copy()
                continue
            if gi >= n_lad:
                Dn[gi - n_lad] = r.innovations[:, q, :] if np.isfinite(r.nll[q]) else np.nan
                continue
            c, l = divmod(gi - 1, len(LADDER))
            D[l, c] = r.innovations[:, q, :] if np.isfinite(r.nll[q]) else np.nan
    fails = {c: why[0] for c, why in reasons.items() if len(why) == len(LADDER)}
    return eps0, S0, D, Dn, fails


def signatures(eps0, D, Dn, deltas, nuis_delta) -> np.ndarray:
    """Innovation signatures J (N, n_y, n_nuis + n_cols) by forward
    differences: estimated parameters first, then the probe columns, each
    from the larger nudge unless it is nonlinear (differs from the smaller by
    more than 5 %) or failed."""
    nn = len(nuis_delta)
    J = np.empty(eps0.shape + (nn + D.shape[1],))
    for a_, d in enumerate(nuis_delta):
        J[:, :, a_] = (Dn[a_] - eps0) / d
    for c in range(D.shape[1]):
        j_big = (D[0, c] - eps0) / (deltas[c] * LADDER[0])
        j_small = (D[1, c] - eps0) / (deltas[c] * LADDER[1])
        # a smaller nudge that failed throughout (NaN) is not compared: the
        # larger one stands (numpy's nanmax would warn on the user's terminal)
        use_small = ~np.all(np.isfinite(j_big)) or (np.isfinite(j_small).any() and (
            np.nanmax(np.abs(j_big - j_small)) > 0.05 * np.nanmax(np.abs(j_small)) + 1e-300))
        J[:, :, nn + c] = j_small if use_small else j_big
    return J


def whiten(eps0: np.ndarray, S0: np.ndarray, J: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Whitened innovations e (N, n_y) and signatures G (N, n_y, m): by the
    Cholesky factor of S, or by its diagonal when outputs are missing
    (missing entries are zero)."""
    e = np.nan_to_num(eps0)
    valid = np.isfinite(eps0)
    n_y = eps0.shape[1]
    L = np.linalg.cholesky(np.where(np.isfinite(S0), S0, 0) + np.eye(n_y) * 1e-300)
    Jv = np.where(valid[:, :, None] & np.isfinite(J), J, 0.0)
    # rows of missing outputs: remove from S too (use the diagonal then)
    if not valid.all():
        sd = np.sqrt(np.einsum("kii->ki", S0))
        ew = np.where(valid, e / sd, 0.0)
        Gw = Jv / sd[:, :, None]
    else:
        ew = np.linalg.solve(L, e[:, :, None])[:, :, 0]
        Gw = np.linalg.solve(L, Jv)
    return ew, np.where(np.isfinite(Gw), Gw, 0.0)


def _explained(An: np.ndarray, bn: np.ndarray, norm: np.ndarray, cs: list):
    """Innovation energy explained by the columns ``cs`` (least squares on
    the normalised normal equations) and their coefficients."""
    if not cs:
        return 0.0, np.zeros(0)
    sol = np.linalg.lstsq(An[np.ix_(cs, cs)], bn[cs], rcond=1e-9)[0]
    return float(bn[cs] @ sol), sol / norm[cs]


def _one_sided(An: np.ndarray, bn: np.ndarray, norm: np.ndarray, base: list, cs: list,
               signed: list[int]) -> tuple[float, np.ndarray]:
    """:func:`_explained` over ``base + cs`` with the one-step estimates
    β = −coefficient of the columns ``cs[i]``, i in ``signed``, kept >= 0:
    the largest energy explained over the subsets of those columns held at
    β = 0 whose free fit keeps the others' β >= 0 (an exact active-set
    search; the effects have at most a few such columns), their
    coefficients 0 in the returned solution (len(base) + len(cs),).

    The one-sided score test of a parameter with a physical sign
    (Silvapulle & Silvapulle 1995): a score that asks for a negative
    Stribeck excess or drag coefficient is no evidence for the effect. On
    the bundled EMPS case the two-sided test gave the Stribeck excess
    χ² 1134 and the quadratic drag 584 with negative one-step estimates;
    their refits, started at |β|, ended at 0 with LR 0, after two
    confirmations each (with their tanh widths profiled). The χ²(k)
    p-value is kept: above the χ̄² mixture's, it is conservative."""
    e, sol = _explained(An, bn, norm, base + cs)
    nb = len(base)
    if not signed or all(-sol[nb + i] >= 0 for i in signed):
        return e, sol
    best = (-np.inf, None)
    for mask in range(1, 2 ** len(signed)):
        held = {signed[j] for j in range(len(signed)) if mask >> j & 1}
        free = [c for i, c in enumerate(cs) if i not in held]
        ef, sf = _explained(An, bn, norm, base + free)
        full = np.zeros(nb + len(cs))
        full[:nb] = sf[:nb]
        rest = iter(sf[nb:])
        for i in range(len(cs)):
            if i not in held:
                full[nb + i] = next(rest)
        if all(-full[nb + i] >= -1e-300 for i in signed) and ef > best[0]:
            best = (ef, full)
    if best[1] is None:         # nothing feasible but all held: the base alone
        e0, s0 = _explained(An, bn, norm, base)
        full = np.zeros(nb + len(cs))
        full[:nb] = s0
        return e0, full
    return best


def conditional_score(ctx: Context, fit: Fit, given: Candidate,
                      other: Candidate) -> tuple[float, int] | None:
    """The efficient score statistic of ``other`` with ``given``'s columns
    partialled out beside the estimated parameters (Rao 1948): the
    innovation energy the two explain together minus what ``given``
    explains alone, from the normal equations of :func:`score_additive`'s
    probe run at ``fit`` (no filter run). Under the hypothesis that
    ``other`` adds nothing to ``given`` it is χ²(k), k its columns.

    Parameters
    ----------
    ctx : Context
    fit : Fit
        The fit :func:`score_additive` scored (its normal equations cached
        in ``ctx.cache``).
    given, other : Candidate
        Additive candidates of that scoring.

    Returns
    -------
    (float, int) or None
        The statistic and k; None when either is not an additive candidate
        of that run (a structural one) or the equations are singular.
    """
    hit = ctx.cache.get(("score_gram", id(fit), fit.nll))
    if hit is None:
        return None
    An, bn, norm, col_of, nn = hit
    ca, cb = col_of.get((given.effect, given.target)), col_of.get((other.effect, other.target))
    if ca is None or cb is None:
        return None
    base = list(range(nn)) + list(ca)
    try:
        e_a, _ = _explained(An, bn, norm, base)
        e_ab, _ = _explained(An, bn, norm, base + [c for c in cb if c not in ca])
    except np.linalg.LinAlgError:
        return None
    stat = max(0.0, e_ab - e_a)
    return (stat, len(cb)) if np.isfinite(stat) else None


def score_groups(ctx: Context, cols: list, nn: int, An, bn, norm, total: float,
                 fails: dict | None = None, nuisance: list | None = None):
    """One :class:`Candidate` per (effect, target) of the probe columns: LM =
    energy explained with its columns minus that of the ``nn`` estimated
    parameters alone, χ²(k) p-value, one-step estimates β = −coefficients;
    an additive effect's ``nonnegative`` parameters (a friction level, a
    drag coefficient: their sign is the law's passivity) kept at β >= 0
    (:func:`_one_sided`).
    A candidate with a column in ``fails`` (column -> reason: its filter
    runs failed) is reported as failed: NaN statistic, the reason named.
    With ``nuisance`` (the ``nn`` estimated parameters' names) each
    candidate's ``joint_step`` holds β and the change of the estimated
    parameters in the same least-squares step (−their coefficients).

    Returns
    -------
    (list of Candidate, dict (effect, target) -> column indices)
    """
    base_cols = list(range(nn))
    e_base, _ = _explained(An, bn, norm, base_cols)
    col_of: dict = {}
    out = []
    groups: dict[tuple, list[int]] = {}
    for c, col in enumerate(cols):
        groups.setdefault((col.effect, col.target), []).append(nn + c)
    for (ename, tgt), cs in groups.items():
        eff = get_effect(ename, ctx.settings.effects)
        why = [fails[c - nn] for c in cs if fails and (c - nn) in fails]
        if why:
            col_of[(ename, tgt)] = cs
            out.append(failed_candidate(eff, tgt, "score", len(cs), why[0]))
            continue
        est = [p.name for p in eff.params if p.estimated]
        signed = [i for i, p in enumerate(q for q in eff.params if q.estimated)
                  if eff.additive and p.nonnegative and i < len(cs)]
        try:
            e_all, sol = _one_sided(An, bn, norm, base_cols, cs, signed)
        except np.linalg.LinAlgError:
            continue
        lm = max(0.0, e_all - e_base)
        if not np.isfinite(lm):
            continue
        k = len(cs)
        col_of[(ename, tgt)] = cs
        beta = -sol[nn:]
        values = {est[i]: float(beta[i]) for i in range(min(k, len(est)))}
        out.append(Candidate(ename, eff.title, tgt, "score", lm, k, float(chi2.sf(lm, k)),
                             lm - 2 * k, lm / total if total > 0 else None, values))
        if nuisance is not None and np.all(np.isfinite(sol)):
            out[-1].joint_step = {"effect": dict(values), "estimated": {
                n: float(-sol[a]) for a, n in enumerate(nuisance[:nn])}}
    return out, col_of


def failed_candidate(eff, tgt, kind: str, dof: int, reason: str) -> Candidate:
    """A candidate whose test could not be computed (the filter failed):
    NaN statistic, p-value and score, and the reason."""
    nan = float("nan")
    return Candidate(eff.name, eff.title, tgt, kind, nan, dof, nan, nan, None, {},
                     last_resort=getattr(eff, "last_resort", False),
                     failed=f"the filter failed: {reason}")


def mark_equivalent(cands, col_of, An, base_cols, tol: float = 0.999) -> None:
    """Fill ``Candidate.equivalent`` for single-column candidates whose
    signatures, with the estimated parameters (``base_cols``) partialled out,
    have |correlation| > ``tol`` (from the normalised Gram matrix ``An``),
    and set ``Candidate.absorbed`` for those whose signature the estimated
    parameters' span reproduces (multiple correlation > ``tol``: residual
    share of the unit-norm column below 1 − tol²)."""
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
    for c in singles:
        i = idx[id(c)]
        c.absorbed = bool(B) and An[i, i] > 0.5 and var[id(c)] < 1.0 - tol**2
    for i, a in enumerate(singles):
        for b in singles[i + 1:]:
            va, vb = var[id(a)], var[id(b)]
            if va <= 0 or vb <= 0:
                continue
            r = resid(idx[id(a)], idx[id(b)]) / np.sqrt(va * vb)
            if abs(r) > tol:
                a.equivalent.append(b.label)
                b.equivalent.append(a.label)


def line_probe(ctx: Context, probe: Probe, fit: Fit, cands: list[Candidate]) -> None:
    """Second batched run: every additive candidate at 0.5, 1 and 2 times its
    one-step estimate and at its natural values, nuisance parameters held,
    profiled over :data:`LINE_NOISE_FACTORS`. The likelihood gain found (LR, a
    lower bound of the candidate's full LR) replaces the score statistic
    (and ``values``) where it is larger: the score test is local and misses
    effects to which the filter reacts nonlinearly (at λ = 0 a filter bends
    its states towards a rectified measurement)."""
    sets, owner = _line_sets(ctx, probe, fit, cands)
    if not sets:
        return
    sets = np.array(sets)
    nll = np.empty(len(sets))
    chunk = ctx.settings.evaluation.chunk
    for a in range(0, len(sets), chunk):
        nll[a:a + chunk] = run_ukf(probe.problem, sets[a:a + chunk]).nll
    best: dict = {}
    for (cand, tr), v in zip(owner, nll):
        if np.isfinite(v) and (id(cand) not in best or v < best[id(cand)][0]):
            best[id(cand)] = (v, tr)
    for cand in cands:
        if id(cand) not in best:
            continue
        v, tr = best[id(cand)]
        lr = 2.0 * (fit.nll - v)
        if lr > cand.statistic:
            eff = get_effect(cand.effect, ctx.settings.effects)
            est = [p.name for p in eff.params if p.estimated]
            cand.statistic = float(lr)
            cand.p_value = float(chi2.sf(lr, cand.dof))
            cand.score = float(lr - 2 * cand.dof)
            cand.values.update({n: float(x) for n, x in zip(est, tr)})


def _line_sets(ctx: Context, probe: Probe, fit: Fit, cands: list[Candidate]):
    """Parameter sets (n_theta,) of the line probe and, for each, the
    (candidate, trial β) it evaluates."""
    pm = probe.model
    index = {(c.effect, c.target): [] for c in cands}
    for col in probe.cols:
        if (col.effect, col.target) in index:
            index[(col.effect, col.target)].append(pm.param_index(col.param))
    sets, owner = [], []
    for cand in cands:
        eff = get_effect(cand.effect, ctx.settings.effects)
        est = [p.name for p in eff.params if p.estimated]
        js = index[(cand.effect, cand.target)]
        beta = np.array([cand.values.get(n, 0.0) for n in est[:len(js)]])
        trials = [beta * f for f in (0.5, 1.0, 2.0)] if np.any(beta) else []
        for pt in eff.natural_points(cand.target):
            trials.append(np.array([pt.get(n, b) for n, b in zip(est, beta)]))
        for tr in trials:
            th = probe.base.copy()
            th[js] = tr
            for thv in noise_variants(pm, fit, th, LINE_NOISE_FACTORS):
                sets.append(thv)
                owner.append((cand, tr))
    return sets, owner


# ------------------------------------------------------------- structural
def score_structural(ctx: Context, fit: Fit, scales: Scales, effects,
                     places: set | None = None, todo: list | None = None,
                     others: int = 0, ahead: list[Candidate] = ()) -> list[Candidate]:
    """Likelihood-ratio statistic of every structural effect of ``effects``
    at every place it can attach (and is not yet present; only the targets
    in ``places``, a set of (kind, name), if given), each from one batched
    UKF run over its grid (:func:`structural_candidate`); a progress bar
    when ``ctx.progress``. On one machine every candidate's model is built
    first and their kernels are compiled ahead in the background while
    this process scores them in order, on threads
    (:func:`~bondgraph.diagnose.parallel.local_map`; :func:`structural_todo`;
    ``todo``: its result, when the caller started it earlier). ``others``:
    the candidates of the step already scored; with these the family of
    the step's significance test (Bonferroni) whose critical value decides
    which grids are profiled (:func:`worth_profiling`; logged); ``ahead``:
    those already scored, whose scores decide too: a grid that cannot
    reach the step's confirmations is not profiled (:func:`confirm_bar`)."""
    if distributed(ctx):
        todo = structural_targets(fit, effects, places)
        ctx.log(f"  scoring {len(todo)} structural candidates on the Dask workers")
        family = others + len(todo)
        found = run_tasks(ctx, _structural_task,
                          (fit, scales, family, confirm_bar(ctx, ahead, family)), todo)
        return _not_profiled_note(ctx, [c for c in found if c is not None])
    if todo is None:
        todo = structural_todo(ctx, fit, scales, effects, places)
    family = others + len(todo)
    bar = confirm_bar(ctx, ahead, family)
    try:
        found = list(progress.bar(
            local_map(ctx, lambda c, item: structural_candidate(c, fit, scales, *item,
                                                                family=family, bar=bar), todo),
            total=len(todo), desc="structural candidates", unit="cand", leave=False,
            disable=not ctx.progress))
    finally:
        cancel_ahead()
    return _not_profiled_note(ctx, [c for c in found if c is not None])


def _not_profiled_note(ctx: Context, cands: list[Candidate]) -> list[Candidate]:
    """``cands``, after one log line naming how many were not profiled."""
    n = sum(1 for c in cands if not c.profiled)
    if n:
        ctx.log(f"  {n} of {len(cands)} structural candidates not profiled: their grid's "
                f"likelihood ratio plus {PROFILE_REACH:g} times the gain a scoring step "
                f"predicts stays below the critical χ², or below the scores of as many "
                f"candidates as the step confirms at most (their statistic is the grid's)")
    return cands


def confirm_bar(ctx: Context, ahead, family: int) -> float:
    """The score (statistic − 2k) a structural candidate must be able to
    reach to be among a step's confirmations: that of the
    ``confirm_top`` x ``confirm_rounds``-th best significant candidate of
    ``ahead`` (the step's candidates already scored, significant at
    ``settings.accept.significance`` / ``family``, Bonferroni), −inf when
    there are fewer. The step confirms candidates best score first, at
    most that many (:func:`bondgraph.diagnose.runner.confirm_in_rounds`),
    so a candidate whose score stays below so many others' is never
    confirmed; its profile would only refine a statistic no decision reads.
    On the default coast-down record 20 structural candidates were
    profiled in step 1, where nine additive ones scored above 23 000 and
    the best structural one reached 22 563."""
    s = ctx.settings
    budget = int(s.search.confirm_top) * int(s.search.confirm_rounds)
    level = s.accept.significance / max(family, 1)
    scores = sorted((c.score for c in ahead
                     if np.isfinite(c.score) and c.p_value < level), reverse=True)
    return float(scores[budget - 1]) if budget >= 1 and len(scores) >= budget else -np.inf


def structural_targets(fit: Fit, effects, places: set | None = None) -> list[tuple]:
    """(effect, target) of every structural effect of ``effects`` at every
    place of ``fit``'s graph it can attach to and is not yet present (only
    the targets in ``places``, a set of (kind, name), if given)."""
    return [(eff, tgt) for eff in effects if not eff.additive
            for tgt in eff.targets(fit.graph) if not eff.present(fit.graph, tgt)
            and (places is None or (tgt.kind, tgt.name) in places)]


def structural_todo(ctx: Context, fit: Fit, scales: Scales, effects,
                    places: set | None = None) -> list[tuple]:
    """``(effect, target, built)`` of :func:`structural_targets` with each
    candidate built (:func:`build_candidate`; those that cannot be built are
    logged and left out), and their numba kernels queued for the background
    compiler (:func:`bondgraph.numerics.compiled.compile_ahead`, numba
    backend only): the loop builds them before it scores the additive
    candidates, so that the background compiles while this process works."""
    todo = structural_targets(fit, effects, places)
    built = [build_candidate(ctx, fit, scales, eff, tgt) for eff, tgt in todo]
    todo = [(eff, tgt, b) for (eff, tgt), b in zip(todo, built) if b is not None]
    if ctx.problem.disc.backend == "numba":
        compile_ahead([b[-1] for _, _, b in todo])
    return todo


def compile_first_step_ahead(ctx: Context, graph) -> bool:
    """On a first run, compile the point kernels of the first step's
    structural candidates while this process waits for the filter kernel's
    background compile (:func:`bondgraph.inference.ukf_numba.while_compiling`):
    the declared graph plus each physical structural effect at each place,
    built with empty scales (:func:`_ahead_of_need`). A candidate's kernels
    depend on its laws, not on the default values and boxes the scales set
    (:func:`bondgraph.numerics.compiled.kernel_key_text`), so the step finds
    them compiled; on the bundled default case and a user's CED graph all
    25 and 17 of them.

    Why: a first run waits about 10-20 s for the filter kernel before its
    first fit, one core idle, and then spends its first step compiling
    every candidate's kernels (about 1 s of the C compiler each) beside the
    scoring. Measured on the bundled default case with fresh caches (four
    runs each, alternating): step 1 scored in 10.9-14.2 s instead of
    17.2-18.7 s, the first fit 2 s later (the compile waited for shares the
    machine), the whole run 54.5-66.5 s instead of 62.1-70.1 s. Only with
    the C compiler's kernels (:func:`~bondgraph.numerics.compiled.kernel_kind`)
    and the numba backend, structural candidates scored in process and not
    skipped by a threshold; the probe model of the additive candidates
    embeds its scales and is left to the step.

    Returns
    -------
    bool
        Whether the work was queued (False without a background compile
        to wait for: a warm run).
    """
    work = _ahead_work(ctx)
    if work is None:
        return False
    quiet, scales, effects = work
    return while_compiling(lambda done: _ahead_of_need(quiet, graph, scales, effects, done))


def _ahead_work(ctx: Context) -> tuple | None:
    """``(quiet context, scales, effects)`` for compiling structural
    candidates ahead of need, or None where that does not apply: structural
    candidates scored in process and not skipped by a threshold, the numba
    backend and the C compiler's kernels (:func:`compile_first_step_ahead`,
    :func:`compile_step_ahead`)."""
    s = ctx.settings
    if not s.search.structural or s.search.structural_threshold is not None \
            or distributed(ctx) or ctx.problem.disc.backend != "numba" \
            or kernel_kind() != "c":
        return None
    effects = [e for e in s.effects if not getattr(e, "last_resort", False)]
    quiet = Context(ctx.problem, s, log=lambda msg: None, progress=False)
    return quiet, record_scales(ctx.problem.t), effects


def compile_step_ahead(ctx: Context, graph) -> threading.Event | None:
    """Compile the C kernels of the structural candidates of ``graph`` (the
    model a step is likely to accept: the current graph plus the step's best
    candidate) on a daemon thread while the step confirms its candidates
    (:func:`_ahead_of_need`), so that the next step finds them compiled;
    returns the event that stops it (set it when the step ends), or None
    where :func:`compile_first_step_ahead`'s conditions do not hold. On a
    warm run the first candidate is found compiled and the thread stops.

    Why: a first run compiled every candidate of its second step in that
    step (the bundled default case: step 2 scored its 80 candidates in
    17.2 s against 7.5 s warm), while the first step's confirmations
    (about 8 s) left a core partly idle."""
    work = _ahead_work(ctx)
    if work is None:
        return None
    quiet, scales, effects = work
    done = threading.Event()
    threading.Thread(target=_ahead_of_need, name="bondgraph-ahead", daemon=True,
                     args=(quiet, graph, scales, effects, done, True)).start()
    return done


def _ahead_of_need(ctx: Context, graph, scales: Scales, effects, done,
                   warm_stop: bool = False) -> None:
    """Build the structural candidates of ``graph`` and their C kernels one
    at a time in this thread (:func:`bondgraph.numerics.compiled.build_ahead`),
    until ``done`` is set (with ``warm_stop``, also when the first one is
    compiled already: a warm run). An error ends the work ahead quietly: the
    step builds its candidates itself and reports what fails."""
    stub = SimpleNamespace(graph=graph)     # what the two read of a fit: its graph
    try:
        for eff, tgt in structural_targets(stub, effects):
            if done.is_set():
                return
            built = build_candidate(ctx, stub, scales, eff, tgt)
            if built is None:
                continue
            if warm_stop and is_compiled(built[-1]):
                return
            warm_stop = False
            build_ahead(built[-1])
    except Exception:   # noqa: BLE001 - work ahead of need; the step reports its own errors
        return


def _structural_task(ctx: Context, shared, item) -> Candidate | None:
    """:func:`structural_candidate` as a task of :func:`run_tasks`."""
    fit, scales, family, bar = shared
    eff, tgt = item
    return structural_candidate(ctx, fit, scales, eff, tgt, family=family, bar=bar)


def grid_starts(ctx: Context, fit: Fit, model: Model, sets: list, grid_of: list,
                net: np.ndarray) -> tuple[float, np.ndarray, int]:
    """The best start of a structural candidate's profile: the
    ``settings.search.structural_starts`` best grid values (each at its best noise
    variant; NLLs ``net`` (n_sets,) of ``sets``) get one Fisher-scoring step
    over the declared estimated parameters alone, the effect's held at the
    grid value (a profile likelihood over the grid, Cox & Hinkley 1974,
    §9.2 (iii)), the starts' steps batched in two UKF runs
    (:func:`~bondgraph.diagnose.inference_calls.fisher_steps`).

    Why: the declared fit has already compensated for the missing effect
    (a peak torque lowered to the level of a saturation), so with the
    declared parameters frozen the grid favours the weakest effect values,
    and a joint scoring step from there follows a curved valley slowly. On
    the vehicle_engine_saturation record the frozen grid's best (L = 80 N m)
    scores LR 10 300, 15 joint steps reach 19 400; one declared-only step
    from L = 50 N m reaches 35 000 (the truth 38 000).

    Returns
    -------
    (nll, theta, i)
        The best NLL, its θ (n_theta,) and the index of its grid value in
        ``grid_of`` (the frozen best when no profiled start improves on it).
    """
    i0 = int(np.argmin(net))
    best, th_best, i_best = float(net[i0]), np.array(sets[i0]), i0
    n = int(ctx.settings.search.structural_starts)
    noise = noise_params(fit.model)
    names = [p for p in fit.params if p in model.params and p not in noise]
    if n <= 0 or not names or not np.isfinite(best):
        return best, th_best, i_best
    first: dict = {}
    for j in np.argsort(net):
        key = tuple(sorted(grid_of[j].items()))
        if np.isfinite(net[j]) and key not in first:
            first[key] = int(j)
    idx = [model.param_index(p) for p in names]
    starts = list(first.values())[:n]
    steps = fisher_steps(problem_for(ctx, model), [np.array(sets[j]) for j in starts], idx,
                         model.bounds(names))
    for j, stepped in zip(starts, steps):
        if stepped is not None and np.isfinite(stepped[1]) and stepped[1] < best:
            best, th_best, i_best = stepped[1], stepped[0], j
    return best, th_best, i_best


def places_of(graph, cand: Candidate) -> set:
    """The places (kind, name) of ``cand``'s target: the target itself and,
    for a source, the inputs its value reads (where an input delay attaches)."""
    out = {(cand.target.kind, cand.target.name)}
    if cand.target.kind == "source" and cand.target.name in graph.elements:
        value = getattr(graph.element(cand.target.name), "value", None)
        names = {s.name for s in getattr(value, "free_symbols", ())}
        out |= {("input", n) for n in graph.inputs if n in names}
    return out


def profile_declared(ctx: Context, fit: Fit, model: Model, new: list[str], theta: np.ndarray,
                     nll: float) -> tuple[float, np.ndarray] | None:
    """A few Fisher-scoring steps (``settings.search.structural_refit``) over the
    declared estimated parameters together with the effect's ``new`` ones,
    from the best grid point ``theta`` (n_theta,), all inside their declared
    boxes: the declared fit may have moved a parameter to compensate for the
    missing effect (a peak torque lowered for a saturation), which a score
    with the declared parameters frozen cannot undo.

    Returns
    -------
    (nll, theta, converged) or None
        The profiled point when it improves on ``nll``, and whether the
        scoring stopped by its convergence test (not by
        ``structural_refit``); None when it does not improve, when
        ``structural_refit`` is 0, or when the scoring fails.
    """
    iters = int(ctx.settings.search.structural_refit)
    names = [n for n in fit.params if n in model.params] + list(new)
    if iters <= 0 or not names:
        return None
    pb = problem_for(ctx, model)
    lo, hi = model.bounds(names)
    idx = [model.param_index(n) for n in names]
    th = theta.copy()
    th[idx] = np.clip(th[idx], lo, hi)
    noise = noise_params(fit.model)
    scale = np.array([n in noise and lo[j] > 0 for j, n in enumerate(names)])
    try:
        fitted = fisher_fit(pb, th, idx, (lo, hi), iters, log_scale=scale, information=False)
    except (FloatingPointError, np.linalg.LinAlgError):
        return None
    th, f = fitted[0], fitted[7]          # the NLL at th: no run of its own
    return (f, th, bool(fitted[2])) if np.isfinite(f) and f < nll else None


def build_candidate(ctx: Context, fit: Fit, scales: Scales, eff, tgt) -> tuple | None:
    """``fit``'s graph plus ``eff`` at ``tgt`` (its first grid value, the
    grid's span as box): ``(grid, spans, P, model)``, or None (logged) if the
    effect cannot be built there."""
    try:
        g = fit.graph.copy(f"{fit.graph.name}__{eff.name}")
        grid = eff.grid(g, tgt, scales)
        # the span from the graph before the effect is applied: applying
        # it may replace the target (a slip fragment replaces its bond)
        spans = eff.grid_span(g, tgt, scales)
        P = eff.apply(g, tgt, grid[0], scales)
        for k, span in spans.items():
            P[k].bounds = span
        return grid, spans, P, model_of(g)
    except BondGraphError as exc:
        ctx.log(f"  skip {eff.name} @ {tgt.name}: {str(exc).splitlines()[0]}")
        return None


def structural_candidate(ctx: Context, fit: Fit, scales: Scales, eff, tgt,
                         built: tuple | None = None, family: int | None = None,
                         bar: float = -np.inf) -> Candidate | None:
    """Build ``fit``'s graph plus ``eff`` at ``tgt`` (or take ``built``, what
    :func:`build_candidate` returned) and evaluate the NLL over
    the effect's grid × :data:`NOISE_FACTORS` (current estimates held) in one
    batched UKF run; from the best point a few scoring steps over the
    declared and the effect's parameters (:func:`grid_starts`,
    :func:`profile_declared`); the
    result gives LR = 2 (NLL₀ − NLL₁), χ²(k) with k the effect's estimated
    parameters. With ``family`` (the number of candidates of the step's
    significance test) the scoring steps are taken only when
    :func:`worth_profiling` says they could make the candidate significant
    and lift its score to ``bar`` (:func:`confirm_bar`);
    otherwise the statistic is the grid's (``profiled`` False). None
    (logged) if the effect cannot be
    built there; a failed candidate (:func:`failed_candidate`) if the UKF
    fails at every grid point."""
    built = built or build_candidate(ctx, fit, scales, eff, tgt)
    if built is None:
        return None
    grid, spans, P, model = built
    base = model.theta0.copy()
    for n in fit.model.params:
        if n in model.params:
            base[model.param_index(n)] = fit.theta[fit.model.param_index(n)]
    sets, grid_of = [], []
    for vals in grid:
        th = base.copy()
        for k, v in vals.items():
            if k in P:
                th[model.param_index(P[k].name)] = v
        for thv in noise_variants(model, fit, th, NOISE_FACTORS):
            sets.append(thv)
            grid_of.append(vals)
    ctx, r = finer_if_failed(ctx, model, np.array(sets), f"{eff.name} @ {tgt.name}")
    k = sum(1 for p in eff.params if p.estimated)
    if not np.any(np.isfinite(r.nll)):
        return failed_candidate(eff, tgt, "likelihood ratio", k, str(r.reasons[0]))
    net = np.where(np.isfinite(r.nll), r.nll, np.inf)
    new = {p.name: P[p.name].name for p in eff.params if p.estimated and p.name in P}
    i0 = int(np.argmin(net))
    search = ctx.settings.search
    profiling = search.structural_starts > 0 or search.structural_refit > 0
    if family is not None and profiling and not worth_profiling(
            ctx, fit, model, np.array(sets[i0]), list(new.values()), float(net[i0]), k, family,
            bar):
        values = dict(grid_of[i0])
        lr = max(0.0, 2 * (fit.nll - float(net[i0])))
        return Candidate(eff.name, eff.title, tgt, "likelihood ratio", lr, k,
                         float(chi2.sf(lr, k)), lr - 2 * k, None, values,
                         last_resort=getattr(eff, "last_resort", False),
                         limit_of=at_limits(eff, tgt, values, spans), profiled=False)
    best, th_best, i = grid_starts(ctx, fit, model, sets, grid_of, net)
    values, declared = dict(grid_of[i]), {}
    if best < float(np.min(net)):
        declared = {n: float(th_best[model.param_index(n)]) for n in fit.params
                    if n in model.params}
    prof = profile_declared(ctx, fit, model, list(new.values()), th_best, best)
    th, converged = th_best, False
    if prof is not None:
        best, th, converged = prof
        values.update({k: float(th[model.param_index(n)]) for k, n in new.items()})
        declared = {n: float(th[model.param_index(n)]) for n in fit.params if n in model.params}
    lr = max(0.0, 2 * (fit.nll - best))
    return Candidate(eff.name, eff.title, tgt, "likelihood ratio", lr, k, float(chi2.sf(lr, k)),
                     lr - 2 * k, None, values,
                     last_resort=getattr(eff, "last_resort", False), profile=declared,
                     limit_of=at_limits(eff, tgt, values, spans),
                     reach=lr if converged else profile_reach(ctx, fit, model, th,
                                                              list(new.values()), lr))


#: the factors by which a structural candidate's RK4 substeps grow when its
#: filter fails at every point of its grid (:func:`finer_if_failed`)
FINER_FACTORS = (2, 4, 8)


def finer_if_failed(ctx: Context, model: Model, sets: np.ndarray, label: str):
    """``(context, result)``: the batched UKF run of ``model`` at the
    parameter sets ``sets`` (n_sets, n_theta) with ``ctx``'s filter; where it
    fails at every set and the filter is RK4, run again with 2, 4, then 8
    times its substeps until one set runs (logged), and that context with
    it. A candidate that brings a stiff element (a compliance or an end stop
    at its grid's stiffness) can put a mode outside RK4's stability region
    at the step the model without it needed; unscored, it could not compete
    (a user's CVT driveline at 20 Hz: the compliance and the slip behind the
    belt, an end stop on the shaft and Dahl friction in its twist all failed
    at the second sample). The confirmation refits choose their own stable
    substeps (:func:`bondgraph.diagnose.confirm.stable_context`)."""
    r = run_ukf(problem_for(ctx, model), sets)
    disc = ctx.problem.disc if ctx.problem is not None else None
    if np.any(np.isfinite(r.nll)) or disc is None or disc.method != "rk4":
        return ctx, r
    for factor in FINER_FACTORS:
        n = factor * int(disc.substeps)
        finer = at_step(ctx, replace(disc, substeps=n, refine=()))
        rf = run_ukf(problem_for(finer, model), sets)
        if np.any(np.isfinite(rf.nll)):
            ctx.log(f"  {label}: the filter fails at every point of its grid with "
                    f"rk4({disc.substeps}) ({str(r.reasons[0]).splitlines()[0]}); scored with "
                    f"rk4({n})")
            return finer, rf
    return ctx, r


def profile_reach(ctx: Context, fit: Fit, model: Model, theta: np.ndarray, new: list[str],
                  lr: float) -> float | None:
    """How far a structural candidate's refit could lift its likelihood
    ratio ``lr`` (profiled at ``theta`` (n_theta,), a few scoring steps
    only, :func:`profile_declared`): ``lr`` plus :data:`PROFILE_REACH`
    times the likelihood-ratio gain one more full scoring step over the
    declared (noise intensities excepted) and the effect's ``new``
    parameters predicts from there (one batched run of k + 1 sets,
    :func:`~bondgraph.diagnose.inference_calls.predicted_step_gain`); the
    same bound :func:`worth_profiling` applies to the grid's best. A
    profile that stopped short of its optimum has a reach far above its
    statistic (a user's two tanks: the pump saturation profiled to 3107,
    its next step predicting 1752 more, its refit reaching 13317; a profile
    that converged, cold_start's 4201, predicts 6; one whose scoring
    stopped by its convergence test is not asked). None when there is
    nothing to step over, no profiling (``structural_refit`` 0), or the
    prediction fails (:func:`bondgraph.diagnose.runner.within_reach` then
    uses the statistic)."""
    if ctx.settings.search.structural_refit <= 0:
        return None
    try:
        gain = step_lr_gain(ctx, fit, model, theta, new)
    except (FloatingPointError, np.linalg.LinAlgError):
        return None
    if gain is None:
        return None
    return lr + PROFILE_REACH * gain if np.isfinite(gain) and gain > 0 else lr


def step_lr_gain(ctx: Context, fit: Fit, model: Model, theta: np.ndarray,
                 new: list[str]) -> float | None:
    """The likelihood-ratio gain, 2·½gᵀF⁻¹g, one full Fisher-scoring step
    over ``fit``'s estimated parameters (noise intensities excepted) and the
    effect's ``new`` ones predicts from ``theta`` (n_theta,) of ``model``,
    inside their boxes (one batched run of k + 1 sets,
    :func:`~bondgraph.diagnose.inference_calls.predicted_step_gain`); None
    when there is nothing to step over.

    Raises
    ------
    FloatingPointError, numpy.linalg.LinAlgError
        When the UKF or the scoring fails at ``theta``.
    """
    noise = noise_params(fit.model)
    names = [n for n in fit.params if n in model.params and n not in noise] + list(new)
    if not names:
        return None
    lo, hi = model.bounds(names)
    return 2.0 * predicted_step_gain(problem_for(ctx, model), theta,
                                     [model.param_index(n) for n in names], (lo, hi))


def worth_profiling(ctx: Context, fit: Fit, model: Model, theta: np.ndarray, new: list[str],
                    nll: float, k: int, family: int, bar: float = -np.inf) -> bool:
    """Whether a structural candidate's grid best ``theta`` (n_theta,; NLL
    ``nll``) is worth the scoring steps of :func:`grid_starts` and
    :func:`profile_declared` (about 60 filter runs of the record): its
    grid likelihood ratio 2 (NLL₀ − ``nll``) plus :data:`PROFILE_REACH`
    times the likelihood-ratio gain one full scoring step over the declared
    (noise intensities excepted) and the effect's ``new`` parameters
    predicts from there (2·½gᵀF⁻¹g, one batched run of k + 1 sets,
    :func:`~bondgraph.diagnose.inference_calls.predicted_step_gain`) reaches
    the critical value of the step's significance test, χ²(k) at
    ``settings.accept.significance`` / ``family`` (Bonferroni, as
    :func:`bondgraph.diagnose.accept.significant`). A candidate below it
    cannot be significant unless its likelihood curves far from the
    quadratic model (:data:`PROFILE_REACH` says how far was seen); when
    the prediction fails it is profiled. Nor is one whose score, that
    reach less 2k, stays below ``bar`` (:func:`confirm_bar`: the step
    confirms at most as many candidates as score above it).

    Returns
    -------
    bool
    """
    crit = float(chi2.isf(ctx.settings.accept.significance / max(family, 1), max(k, 1)))
    lr = 2.0 * (fit.nll - nll)
    if lr >= crit and lr - 2 * k >= bar:
        return True
    try:
        gain = step_lr_gain(ctx, fit, model, theta, new)
    except (FloatingPointError, np.linalg.LinAlgError):
        return True
    if gain is None:
        return False
    reach = lr + PROFILE_REACH * max(gain, 0.0)
    return not (np.isfinite(gain) and (reach < crit or reach - 2 * k < bar))


#: a parameter within this relative distance of an end of its span is on it
LIMIT_REL = 1e-3


def at_limits(eff, tgt, values: dict, spans: dict) -> list[str]:
    """Labels of the candidates ``eff`` at ``tgt`` became with ``values``: a
    parameter on the end of its span (within :data:`LIMIT_REL`) that
    ``eff.limits`` names."""
    out = []
    for p, (side, other) in getattr(eff, "limits", {}).items():
        v, span = values.get(p), spans.get(p)
        if v is None or span is None:
            continue
        end = span[1] if side == "upper" else span[0]
        if abs(v - end) <= LIMIT_REL * abs(end):
            out.append(f"{other} @ {tgt.name}")
    return out


def mark_limits(cands: list[Candidate]) -> None:
    """A structural candidate scored at a limit where it is another candidate
    (``limit_of``) joins that candidate's equivalence group (both ways, with
    the group's other members): the record showed the simpler effect (a Dahl
    friction whose rest stiffness ran to the top of its span scored as the
    Coulomb friction it then is, a little above it for its extra
    parameter)."""
    by = {c.label: c for c in cands}
    for c in cands:
        for label in c.limit_of:
            other = by.get(label)
            if other is None:
                continue
            group = [other, *(by[g] for g in other.equivalent if g in by)]
            for o in group:
                if o.label not in c.equivalent:
                    c.equivalent.append(o.label)
                if c.label not in o.equivalent:
                    o.equivalent.append(c.label)

"""Passivity of a discovered law: what a bond graph promises of the element
the law will become, checked over the range the record visits.

The law ``d = Σ c_k b_k`` of a port (a missing effort entering a 1-junction,
or a missing flow entering a 0-junction) is split by the variables its terms
read:

* **R part**: terms of the junction's own variable z only (its flow at a
  1-junction, its effort at a 0-junction). Together with the declared R
  laws that share z on the junction (effort laws on a 1-junction, flow laws
  on a 0-junction, at the declared values) they must dissipate: the power
  P(z) = (Σ φ_R(z) − d_R(z))·z is >= 0 over the visited range of z widened
  by ``margin`` (Karnopp, Margolis & Rosenberg, *System Dynamics*, §4.1: a
  resistor's law lies in the first and third quadrants). The law becomes an
  R element in parallel with them, judged with them by the loop's
  admissibility check (:func:`bondgraph.numerics.admissible.check_admissible`),
  so a term that lowers a declared resistance is kept as long as the sum
  dissipates.
* **storage part**: terms of one bonded storage state s only (a capacitance's
  displacement at a 1-junction, an inertia's momentum at a 0-junction). They
  change that storage's law Ψ(s) (its effort, resp. flow) into Ψ(s) − d_S(s);
  its stored energy H(s) = ∫₀ˢ (Ψ − d_S) ds' must stay >= 0 over the
  widened range of s (a storage function bounded below with its minimum
  at rest; Willems 1972).
* **coupled part**: products of z and another variable: with the R part, the
  power −(d_R + d_M)·z must be >= 0 at the record's own samples.
* **memory part**: a term lp(x, τ) of a filtered variable (the law's one
  memory term) has a state of its own, so its power −d·z may change sign
  along a cycle while the element stays passive (a Maxwell element's lag).
  It is checked by the dissipation inequality along the record's
  trajectory, the memory state w = lp(x, τ) computed on it
  (:func:`~bondgraph.diagnose.discover.law.lowpass`): the energy the
  junction's dissipative laws absorb, W(t) = ∫₀ᵗ (φ_R(z) − d_R − d_M − d_M')·z dt'
  (declared R laws φ_R, the kept R and coupled terms d_R, d_M', the memory
  term d_M), plus, when x is a bonded storage state s, the energy H(s(t))
  that storage holds with its kept terms, must stay >= 0 (Willems 1972:
  a passive element never returns more energy than it took and held; the
  memory's own initial energy is taken as 0, which is conservative). Without
  the record's times it is refused, with that reason.
* **sources**: a constant or input terms are not passive by nature (a bias,
  an actuator's gain): they are kept and listed as unchecked.

A part that violates its condition loses the terms that violate it alone;
if what remains still violates it, the part is dropped whole. The result
names every dropped term and why (:class:`PassivityReport`).

The ranges and tolerance are those of
:mod:`bondgraph.numerics.admissible` (``visited_grid``, ``violation``).
The storage check assumes the graph's storage elements take power from the
junction (the bond points from the junction to them, the usual drawing).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
import sympy as sp

from bondgraph.diagnose.discover.law import lowpass
from bondgraph.numerics.admissible import MARGIN, visited_grid, violation


@dataclass
class PartCheck:
    """One check of a part of a law.

    Attributes
    ----------
    part : {"R", "storage", "coupled", "memory"}
    variable : str
        The variable the part reads (the storage state for ``"storage"``,
        the memory term's name for ``"memory"``).
    ok : bool
        Passive over the range (after the drops, when any).
    worst : float
        The most negative power (W, the port's effort × flow unit), stored
        energy or (``"memory"``) absorbed energy found before any drop.
    at : float
        Where (the variable's value; for ``"memory"`` the time, s).
    """

    part: str
    variable: str
    ok: bool
    worst: float
    at: float


@dataclass
class PassivityReport:
    """What :func:`make_passive` found.

    Attributes
    ----------
    law : DiscoveredLaw
        The law with the offending terms dropped (``law.dropped`` names them).
    checks : list of PartCheck
    dropped : dict str -> str
        Each dropped term and the reason.
    unchecked : list of str
        Source-like terms (a constant, inputs) kept without a check.
    """

    law: object
    checks: list = field(default_factory=list)
    dropped: dict = field(default_factory=dict)
    unchecked: list = field(default_factory=list)

    @property
    def refused(self) -> bool:
        """True when a term was dropped."""
        return bool(self.dropped)

    def summary(self) -> str:
        """One line per check and per dropped term."""
        lines = [f"{c.part} part in {c.variable}: {'passive' if c.ok else 'NOT passive'} "
                 + (f"(least absorbed energy {c.worst:.4g} at t = {c.at:.4g} s)"
                    if c.part == "memory" else f"(worst {c.worst:.4g} at {c.variable} = {c.at:.4g})")
                 for c in self.checks]
        lines += [f"dropped {k}: {v}" for k, v in self.dropped.items()]
        why = ("a sensor's output, no power" if getattr(self.law, "kind", None) == "output"
               else "source-like")
        lines += [f"unchecked ({why}): {k}" for k in self.unchecked]
        return "\n".join(lines) or "no term to check"


def _fn(expr, sym):
    f = sp.lambdify([sym], expr, "numpy")

    def value(z):
        with np.errstate(all="ignore"):   # a user's sqrt(e) on the grid's e < 0: NaN
            return np.broadcast_to(np.asarray(f(z), float), np.shape(z))
    return value


def _energy(psi: np.ndarray, grid: np.ndarray) -> np.ndarray:
    """∫₀ˢ ψ ds' at every grid point (trapezoid; ``grid`` sorted, contains 0)."""
    cum = np.concatenate([[0.0], np.cumsum(0.5 * (psi[1:] + psi[:-1]) * np.diff(grid))])
    return cum - cum[int(np.argmin(np.abs(grid)))]


def _split(law, own: str):
    """Terms by part: {"R": [...], "coupled": [...], "source": [...],
    ("storage", s): [...]}."""
    parts: dict = {}
    for tm in law.terms:
        names = {str(s) for s in tm.basis.free_symbols}
        if getattr(tm, "memory", None) is not None:
            key = "memory"
        elif not names or names - set(law.symbols) or names & set(law.inputs):
            key = "source"
        elif names == {own}:
            key = "R"
        elif own in names:
            key = "coupled"
        elif len(names) == 1:
            key = ("storage", names.pop())
        else:
            key = "source"
        parts.setdefault(key, []).append(tm)
    return parts


def make_passive(law, graph, values: dict, *, params=None, margin: float = MARGIN, t=None):
    """Check a discovered law's passivity and drop the terms that break it.

    Parameters
    ----------
    law : DiscoveredLaw
    graph : BondGraph
        The declared graph (the storage laws of the port's neighbours).
    values : dict str -> ndarray (N,)
        The port's variables along the record (``Reconstruction.variables``).
    params : dict, optional
        Parameter values of ``graph`` by name (default its defaults).
    margin : float
        Widening of each visited range, fraction of its span (default
        :data:`bondgraph.numerics.admissible.MARGIN`).
    t : ndarray (N,), optional
        The record's sample times (s), along which a memory term's
        dissipation is checked; without them a memory term is dropped.

    Returns
    -------
    PassivityReport

    Notes
    -----
    Method: module docstring (KMR §4.1-4.3; Willems 1972). A law at a
    sensor's output (``law.kind`` ``"output"``) changes no power: every
    term is kept and listed as unchecked.
    """
    if law.kind == "output":
        return PassivityReport(law, unchecked=[tm.name for tm in law.terms])
    own = next(k for k in law.symbols if k == f"{law.port}.f" or k == f"{law.port}.e")
    theta = {n: p.default for n, p in graph.params.items()}
    theta.update(params or {})
    parts = _split(law, own)
    rep = PassivityReport(law)
    rep.unchecked = [tm.name for tm in parts.get("source", [])]
    keep = list(parts.get("source", []))
    z = law.symbols[own]
    grid = visited_grid(values[own], margin)
    decl = _declared_r(graph, law.port, theta, z)
    kept_r = _check_r(parts.get("R", []), z, grid, own, rep, decl)
    keep += kept_r
    kept_c = _check_coupled(parts.get("coupled", []), kept_r, law, values, own, rep)
    keep += kept_c
    stored = {}
    for key, terms in parts.items():
        if isinstance(key, tuple):
            kept_s = _check_storage(terms, key[1], graph, theta, law, values, margin, rep)
            keep += kept_s
            stored[key[1]] = kept_s
    if parts.get("memory"):
        keep += _check_memory(parts["memory"], kept_r + kept_c, law, values, t, rep,
                              (graph, theta, decl, stored))
    order = {tm.name: i for i, tm in enumerate(law.terms)}
    kept = sorted(keep, key=lambda tm: order[tm.name])
    rep.law = replace(law, terms=kept, dropped=list(law.dropped) + list(rep.dropped))
    return rep


def _power(terms, z, grid, decl=None):
    """(decl(z) − Σ terms(z))·z on ``grid``: the power the declared R laws
    ``decl`` (a sympy expression of z, or None) and the terms draw."""
    expr = sp.Add(*(-sp.Float(tm.coef) * tm.basis for tm in terms))
    if decl is not None:
        expr = expr + decl
    if expr == 0:
        return np.zeros_like(grid)
    return _fn(expr, z)(grid) * grid


def _declared_r(graph, port: str, theta: dict, z):
    """Σ sᵢ φᵢ(z) of the R elements bonded to junction ``port`` that share
    its variable z (effort laws on a 1-junction, flow laws on a
    0-junction; sᵢ = +1 when the half-arrow points into the R), at the
    parameter values ``theta``; laws that read anything else (a modulated
    R) are left out. None when there is none: the grouping of
    :func:`bondgraph.numerics.admissible.check_admissible`."""
    j = graph.element(port)
    form = "effort" if type(j).__name__ == "One" else "flow"
    subs = {graph.params[n]: v for n, v in theta.items() if n in graph.params}
    total = sp.Integer(0)
    for p in j.ports:
        el = p.bond.other(p).element if p.bond is not None else None
        if type(el).__name__ != "R" or getattr(el, "form", None) != form:
            continue
        var = el.f if form == "effort" else el.e
        phi = sp.sympify(el.law).xreplace(subs).xreplace({var: z})
        if phi.free_symbols <= {z}:
            total += el.port.bond.sign_at(el) * phi
    return None if total == 0 else total


def _check_r(terms, z, grid, own, rep, decl=None) -> list:
    """The R terms kept: those that dissipate with the declared R laws
    ``decl`` (module docstring); the part dropped whole when what remains
    does not."""
    if not terms:
        return []
    P = _power(terms, z, grid, decl)
    i, bad = violation(P)
    kept = list(terms)
    if bad:
        kept = [tm for tm in terms if not violation(_power([tm], z, grid, decl))[1]]
        for tm in terms:
            if tm not in kept:
                rep.dropped[tm.name] = f"generates power at {own} (−d·{own} < 0)"
        if kept and violation(_power(kept, z, grid, decl))[1]:
            for tm in kept:
                rep.dropped[tm.name] = f"the R part at {own} generates power with it"
            kept = []
    rep.checks.append(PartCheck("R", own, not violation(_power(kept, z, grid, decl))[1],
                                float(P[i]), float(grid[i])))
    return kept


def _law_values(terms, law, values, own) -> np.ndarray:
    """Σ c_k b_k of memoryless ``terms`` at the record's samples (N,)."""
    if not terms:
        return np.zeros(np.shape(values[own]))
    expr = sp.Add(*(sp.Float(tm.coef) * tm.basis for tm in terms))
    names = list(law.symbols)
    f = sp.lambdify([law.symbols[k] for k in names], expr, "numpy")
    with np.errstate(all="ignore"):
        v = f(*[np.asarray(values[k], float) for k in names])
    return np.broadcast_to(np.asarray(v, float), np.shape(values[own]))


def _coupled_power(terms, law, values, own):
    return -_law_values(terms, law, values, own) * np.asarray(values[own], float)


def _check_coupled(terms, r_terms, law, values, own, rep) -> list:
    """The coupled terms with the kept R part, at the record's samples."""
    if not terms:
        return []
    P = _coupled_power(list(r_terms) + list(terms), law, values, own)
    i, bad = violation(P)
    kept = list(terms)
    if bad:
        kept = [tm for tm in terms if not violation(_coupled_power([tm], law, values, own))[1]]
        if violation(_coupled_power(list(r_terms) + kept, law, values, own))[1]:
            kept = []
        for tm in terms:
            if tm not in kept:
                rep.dropped[tm.name] = f"generates power at {own} at the record's samples"
    ok = not violation(_coupled_power(list(r_terms) + kept, law, values, own))[1]
    rep.checks.append(PartCheck("coupled", own, ok, float(P[i]), float(values[own][i])))
    return kept


def _storage_law(graph, state: str, theta: dict):
    """The declared law Ψ(s) of the storage element whose state is ``state``
    (its effort for a C, its flow for an I), parameters substituted."""
    for el in graph.storage_elements():
        if getattr(el, "state", None) is not None and el.state.name == state:
            law = sp.sympify(el.law)
            return law.subs({graph.params[n]: v for n, v in theta.items()
                             if n in graph.params}), el.state
    return None, None


def _check_storage(terms, state, graph, theta, law, values, margin, rep) -> list:
    psi, sym = _storage_law(graph, state, theta)
    s = law.symbols[state]
    if psi is None:
        psi, sym = sp.Integer(0), s
    grid = visited_grid(values[state], margin)
    decl = _fn(psi, sym)(grid)

    def energy(ts):
        added = _fn(sp.Add(*(sp.Float(tm.coef) * tm.basis for tm in ts)), s)(grid) if ts else 0.0
        return _energy(decl - added, grid)

    H = energy(terms)
    i, bad = violation(H)
    kept = list(terms)
    if bad:
        kept = [tm for tm in terms if not violation(_energy(
            -_fn(sp.Float(tm.coef) * tm.basis, s)(grid), grid))[1]]
        if violation(energy(kept))[1]:
            kept = []
        for tm in terms:
            if tm not in kept:
                rep.dropped[tm.name] = f"makes the energy stored in {state} negative"
    rep.checks.append(PartCheck("storage", state, not violation(energy(kept))[1],
                                float(H[i]), float(grid[i])))
    return kept


def _check_memory(terms, dissipative, law, values, t, rep, context) -> list:
    """The memory term kept if the dissipation inequality holds along the
    record (module docstring); ``context`` = (graph, theta, the declared R
    laws' expression in z or None, the kept storage terms by state)."""
    graph, theta, decl, stored = context
    own = next(k for k in law.symbols if k == f"{law.port}.f" or k == f"{law.port}.e")
    names = ", ".join(tm.name for tm in terms)
    if t is None:
        for tm in terms:
            rep.dropped[tm.name] = ("has memory: its dissipation is checked along the record, "
                                    "whose times were not given")
        rep.checks.append(PartCheck("memory", names, False, float("nan"), float("nan")))
        return []
    t = np.asarray(t, float)
    z = np.asarray(values[own], float)
    d = _law_values(list(dissipative), law, values, own)
    for tm in terms:
        d = d + tm.coef * lowpass(values[tm.memory.variable], t, tm.memory.tau)
    phi = _fn(decl, law.symbols[own])(z) if decl is not None else 0.0
    P = (phi - d) * z
    W = np.concatenate([[0.0], np.cumsum(0.5 * (P[1:] + P[:-1]) * np.diff(t))])
    for tm in terms:
        state = tm.memory.variable
        if state != own and state in law.symbols and state not in law.inputs:
            W = W + _held_energy(graph, theta, law, state, stored.get(state, []),
                                 np.asarray(values[state], float))
    i, bad = violation(W)
    if bad:
        for tm in terms:
            rep.dropped[tm.name] = (f"with memory, the port's laws return more energy than "
                                    f"they took: the absorbed energy falls to {W[i]:.4g} "
                                    f"(effort × flow × s) at t = {t[i]:.4g} s")
    rep.checks.append(PartCheck("memory", names, not bad, float(W[i]), float(t[i])))
    return [] if bad else list(terms)


def _held_energy(graph, theta, law, state, terms, s) -> np.ndarray:
    """H(s) at the samples ``s``: the energy the storage of ``state`` holds
    with its kept added terms, ∫₀ˢ (Ψ − d_S) ds' (0 where the graph has no
    such storage)."""
    psi, sym = _storage_law(graph, state, theta)
    sy = law.symbols[state]
    if psi is None:
        psi, sym = sp.Integer(0), sy
    grid = np.union1d(visited_grid(s, 0.0), [0.0])
    added = _fn(sp.Add(*(sp.Float(tm.coef) * tm.basis for tm in terms)), sy)(grid) if terms \
        else 0.0
    return np.interp(s, grid, _energy(_fn(psi, sym)(grid) - added, grid))

"""Physical admissibility of a fitted bond graph: what a bond graph promises
of its elements, checked numerically over the operating range a record
visits.

- Every R element dissipates: the power into it, P = e·f, is >= 0 wherever
  the input x of its law goes (its flow for an effort law e = φ(f), its
  effort for a flow law f = φ(e)), i.e. x·φ(x) >= 0 (Karnopp, Margolis
  & Rosenberg, *System Dynamics*, 5th ed., §4.1: a resistor's constitutive
  law lies in the first and third quadrants). R elements in parallel on one
  junction that share x (effort laws on a 1-junction, flow laws on a
  0-junction) are checked as one R-field: x·Σφᵢ(x) >= 0, so that a
  correction term beside a declared law is judged with it; so are the Rs
  of junctions whose variables are rigidly tied along the trajectory
  (x_j = k_j x: 1-junctions bonded directly or through a transformer with
  no storage between them), Σ_j k_j x·φ_j(k_j x) >= 0.
- Every C element in integral causality stores its energy in one well: its
  effort e = Ψ(q) restores towards the lowest point of its stored energy
  H(q) = ∫Ψ dq over the range of its state (Ψ >= 0 to the well's right,
  <= 0 to its left), so that H rises away from the well, bounded below by
  it: a valid storage function that no state can run away from over a
  barrier (KMR §4.2-4.3; Willems 1972). A preloaded spring e = F₀ + k q (a
  CVT's springs; its well below the range) passes, as does a potential
  energy that is not convex: a pendulum's m g l sin θ past 90°, a
  softening spring k q − β q³ past its turning point q² = k/(3β) while it
  still restores (a user's swing arm, gravity declared as a linear spring:
  the cubic term's refit, −0.175 θ³ beside 1.19 θ, has a negative stiffness
  past 1.5 rad, as the truth has past π/2; refused as "not convex", the
  loop took Dahl friction instead, held out 0.108 against 0.023). Past the
  barrier's top, q² > k/β, or for a negative spring, it does not. Every I
  element's Φ(p) has dΦ/dp >= 0 (a convex kinetic energy: a mass or an
  inductance is positive everywhere).

"The range a record visits" is the interval of the element's variable along
a state trajectory (the filtered states of a fit) widened by ``margin`` of
its span on each side and made to contain zero: a law that turns active just
beyond what the record reached (an orifice whose outflow falls as its level
rises: x·φ(x) < 0 past a level the model will reach on the next record) is
refused before it diverges. Laws that read other variables (a modulated R,
a friction scaled by a normal force) are checked at the trajectory's own
samples, their input scaled by 1 + ``margin``. Multiport fields (RField,
CField, IField) and storages in derivative causality are not checked (listed
in :attr:`Admissibility.unchecked`).

The parameter signs of the effect library (``EffectParam.nonnegative``,
declared boxes) make most refits admissible by construction; this check is
what holds for any law, the user's own and the loop's, at the fitted
values.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import lru_cache
from typing import Mapping, Sequence

import numpy as np
import sympy as sp

from bondgraph.core.elements import C, I, R
from bondgraph.core.graph import BondGraph
from bondgraph.errors import ModelError

#: widening of the visited range on each side, as a fraction of its span
MARGIN = 0.25
#: points of the grid over the widened range
GRID_POINTS = 401
#: a power or stiffness below −TOLERANCE × (its largest magnitude on the
#: range) is a violation; above it, the tails of the library's smooth laws
#: (a softplus overflow's flow at a negative effort, a smoothed sign) and
#: rounding. An R field's power is also a violation where it is below
#: −TOLERANCE × the gross power of its terms there (Σ |x·termᵢ(x)|: a term
#: that produces power outweighs the ones that dissipate) and below
#: −FLOOR × its largest magnitude (:func:`_r_worst`)
TOLERANCE = 1e-3
#: the smallest power, as a fraction of the largest on the range, that the
#: local (gross-power) test counts: below it, rounding of terms that vanish
#: together at x = 0
FLOOR = 1e-9


@dataclass(frozen=True)
class Violation:
    """One element's law that breaks what a bond graph promises.

    Attributes
    ----------
    element : str
        The element's name.
    kind : {"R", "C", "I"}
    what : str
        ``"produces power"`` (R), :data:`ESCAPES` (C) or ``"has a negative
        stiffness (its stored energy is not convex)"`` (I).
    variable : str
        The law's input: ``"flow"``/``"effort"`` (R) or the state's name.
    at : float
        The value of that variable where the violation is worst [its unit].
    value : float
        The power [W] (e·f, in the graph's units), the C's effort there
        (pushing away from its well) or the I's dΦ/dp there (< 0).
    visited : (float, float)
        The range of the variable along the trajectory.
    """

    element: str
    kind: str
    what: str
    variable: str
    at: float
    value: float
    visited: tuple

    def __str__(self) -> str:
        lo, hi = self.visited
        return (f"{self.kind} '{self.element}' {self.what}: {self.value:.3g} at "
                f"{self.variable} = {self.at:.4g} (the record visits [{lo:.4g}, {hi:.4g}])")


@dataclass
class Admissibility:
    """The result of :func:`check_admissible`.

    Attributes
    ----------
    violations : list of Violation
    checked : list of str
        Elements whose law was checked.
    unchecked : list of str
        Elements not checked, with the reason (``"name: reason"``).
    inherited : list of Violation
        Violations left out of ``violations`` because the model compared
        with already has them (:func:`without_inherited`).
    """

    violations: list = field(default_factory=list)
    checked: list = field(default_factory=list)
    unchecked: list = field(default_factory=list)
    inherited: list = field(default_factory=list)

    @property
    def ok(self) -> bool:
        """True when no checked law breaks passivity."""
        return not self.violations

    def reason(self) -> str:
        """One line naming every violation (empty when admissible)."""
        return "; ".join(str(v) for v in self.violations)


#: a violation at an element the compared model already violates is that
#: model's (inherited) while its power or stiffness is at most this factor
#: larger in magnitude
INHERITED_SLACK = 1.1


def without_inherited(adm: Admissibility, base: Admissibility) -> Admissibility:
    """``adm`` (a refit's check) without the violations that ``base`` (the
    check of the model it is compared with) already has: the same element
    and kind, no more than :data:`INHERITED_SLACK` times as large. A
    candidate is refused for what it breaks, not for a declared law that
    produced power before it was added (a user's road load A + B v + C v²,
    its A fixed, produces power at negative speeds a dyno never visits:
    every candidate was refused for it). A violation the refit makes worse,
    or one at another element (a correction term that joins the declared
    law's R-field under another name), stays.

    Returns
    -------
    Admissibility
        A copy; the left-out violations in ``inherited``.
    """
    had = {(v.element, v.kind): abs(v.value) for v in base.violations}
    keep, old = [], []
    for v in adm.violations:
        ref = had.get((v.element, v.kind))
        (old if ref is not None and abs(v.value) <= INHERITED_SLACK * ref else keep).append(v)
    return Admissibility(keep, list(adm.checked), list(adm.unchecked), old)


def check_admissible(graph: BondGraph, ss, theta: Mapping[str, float], x: np.ndarray,
                     u: np.ndarray, *, margin: float = MARGIN) -> Admissibility:
    """Check every R, C and I law of ``graph`` at the parameter values
    ``theta`` over the range a trajectory visits (module docstring): R laws
    (alone, or in parallel on a junction) absorb power, C and I laws have
    a non-negative stiffness.

    Parameters
    ----------
    graph : BondGraph
        The graph (its elements' laws).
    ss : StateSpace
        Its derived equations (:func:`bondgraph.core.equations.derive`), for
        the port variables as functions of the states and inputs.
    theta : mapping str -> float
        Every parameter of the graph by name (in its declared unit).
    x : ndarray (N, n_x)
        A state trajectory, columns in the order of ``ss.states`` (the
        filtered states of a fit); rows with a non-finite value are ignored.
    u : ndarray (N, n_u)
        The inputs at those samples, columns in the order of ``ss.inputs``.
    margin : float
        Widening of the visited range on each side, as a fraction of its span.

    Returns
    -------
    Admissibility

    Raises
    ------
    ModelError
        If ``theta`` lacks a parameter of the graph, or the shapes of ``x``
        and ``u`` do not match the model.

    References
    ----------
    Karnopp, Margolis & Rosenberg, *System Dynamics: Modeling, Simulation,
    and Control of Mechatronic Systems*, 5th ed., Wiley 2012, §4.1-4.3.
    Willems, "Dissipative dynamical systems", Arch. Rational Mech. Anal. 45
    (1972) 321-351.
    """
    x, u = np.atleast_2d(np.asarray(x, float)), np.asarray(u, float).reshape(len(x), -1)
    if x.shape[1] != len(ss.states) or u.shape[1] != len(ss.inputs):
        raise ModelError(f"check_admissible: states {x.shape} / inputs {u.shape} do not match "
                         f"the model's {len(ss.states)} states and {len(ss.inputs)} inputs")
    missing = [p.name for p in ss.params if p.name not in theta]
    if missing:
        raise ModelError(f"check_admissible: no value for parameter(s) {missing}")
    keep = np.all(np.isfinite(x), axis=1) & np.all(np.isfinite(u), axis=1)
    env = _Env(ss, {p: float(theta[p.name]) for p in ss.params}, x[keep], u[keep])
    out = Admissibility()
    resistors = [graph.elements[n] for n in sorted(graph.elements)
                 if isinstance(graph.elements[n], R)]
    for junctions, members in _tied(env, _parallel_groups(graph, resistors)):
        _check_r(env, junctions, members, margin, out)
    for name in sorted(graph.elements):
        el = graph.elements[name]
        if isinstance(el, R):
            continue
        elif isinstance(el, (C, I)):
            _check_storage(env, el, margin, out)
        elif getattr(el, "kind", None) in ("R", "C", "I"):
            out.unchecked.append(f"{name}: multiport field")
    return out


class _Env:
    """Numeric values of the trajectory's states, inputs and the parameters
    by sympy symbol, and the evaluation of expressions over them."""

    def __init__(self, ss, params: dict, x: np.ndarray, u: np.ndarray):
        self.ss, self.n = ss, len(x)
        self.params = set(params)
        self.values = dict(params)
        self.values.update({s: x[:, i] for i, s in enumerate(ss.states)})
        self.values.update({s: u[:, j] for j, s in enumerate(ss.inputs)})

    def known(self, expr: sp.Expr, extra: Sequence = ()) -> bool:
        """True when every free symbol of ``expr`` has a value (or is in ``extra``)."""
        return all(s in self.values or s in extra for s in expr.free_symbols)

    def evaluate(self, expr: sp.Expr, at: Mapping | None = None) -> np.ndarray:
        """``expr`` at the trajectory's values, the symbols of ``at``
        (symbol -> array) at those instead; broadcast to one array."""
        at = at or {}
        syms = tuple(sorted(expr.free_symbols, key=lambda s: s.name))
        fn = _numpy_function(syms, expr)
        args = [at[s] if s in at else self.values[s] for s in syms]
        with np.errstate(all="ignore"):
            val = np.asarray(fn(*args), dtype=float)
        shapes = [np.shape(a) for a in args] + [val.shape]
        return np.broadcast_to(val, np.broadcast_shapes(*shapes)).astype(float)


#: the port variable x of :func:`_check_r`'s power x·Σ sᵢ φᵢ(x): one symbol
#: for every check, so that the same laws give the same expressions (and
#: :func:`_numpy_function` makes each once)
_PORT = sp.Dummy("x")


@lru_cache(maxsize=1024)
def _numpy_function(syms: tuple, expr: sp.Expr):
    """``expr`` as a numpy function of ``syms`` (``sympy.lambdify``), made
    once per expression: every refit of the loop checks the same laws with
    other values, and lambdify's preprocessing of a law with ``Abs`` and
    ``tanh`` (sympy's assumptions on each substituted symbol) cost 0.4 s
    per check (6.5 s of the EMPS loop's 46 s under cProfile)."""
    return sp.lambdify(syms, expr, "numpy")


def _widened(v: np.ndarray, margin: float) -> np.ndarray:
    """A grid (GRID_POINTS,) over [min(v, 0), max(v, 0)] widened by ``margin``
    of its span on each side, with 0 and the extremes of ``v`` on it."""
    lo, hi = min(float(np.min(v)), 0.0), max(float(np.max(v)), 0.0)
    span = hi - lo if hi > lo else max(abs(hi), abs(lo), 1.0)
    g = np.linspace(lo - margin * span, hi + margin * span, GRID_POINTS)
    return np.unique(np.concatenate([g, [0.0, float(np.min(v)), float(np.max(v))]]))


def visited_grid(v: np.ndarray, margin: float = MARGIN) -> np.ndarray:
    """The grid (about GRID_POINTS,) over the range ``v`` visits, made to
    contain 0 and widened by ``margin`` of its span on each side: where a
    law is checked (a discovered law's passivity,
    :mod:`bondgraph.diagnose.discover.passivity`, as the R, C and I laws here)."""
    return _widened(np.asarray(v, float), margin)


def violation(values: np.ndarray) -> tuple[int, bool]:
    """Index of the most negative of ``values`` (a power or a stored energy
    that must be >= 0) and whether it is a violation (below −TOLERANCE × the
    largest magnitude)."""
    return _worst(np.asarray(values, float), np.asarray(values, float))


def _worst(values: np.ndarray, where: np.ndarray) -> tuple[int, bool]:
    """Index of the most negative of ``values`` and whether it is a
    violation (below −TOLERANCE × the largest magnitude)."""
    ok = np.isfinite(values)
    if not np.any(ok):
        return 0, False
    vals = np.where(ok, values, np.inf)
    i = int(np.argmin(vals))
    scale = float(np.max(np.abs(values[ok])))
    return i, bool(vals[i] < -TOLERANCE * scale)


def _r_worst(power: np.ndarray, gross: np.ndarray) -> tuple[int, bool]:
    """Index of the worst point of an R field's ``power`` (e·f summed over
    its laws) and whether it is a violation: below −TOLERANCE × the largest
    magnitude on the range (:func:`_worst`), or below −TOLERANCE × the
    ``gross`` power there (the sum of its terms' |x·termᵢ(x)|) and below
    −FLOOR × the largest magnitude. The second test sees a term that
    produces power where the others are small: on a user's geared motor a
    square-root term β·sgn(ω)√|ω| with β < 0 beside the rotor's viscous
    friction b·ω made the bearing a source for |ω| < 4.6 rad/s, −3e-4 W
    where the range's largest power is 1 W: within the global tolerance,
    yet a law in the second and fourth quadrants there (KMR §4.1)."""
    ok = np.isfinite(power) & np.isfinite(gross)
    if not np.any(ok):
        return 0, False
    i, bad = _worst(power, power)
    if bad:
        return i, True
    scale = float(np.max(np.abs(power[ok])))
    local = ok & (power < -TOLERANCE * gross) & (power < -FLOOR * scale)
    if not np.any(local):
        return i, False
    return int(np.argmin(np.where(local, power, np.inf))), True


def _parallel_groups(graph: BondGraph, resistors: list) -> list[tuple[str, list]]:
    """The R elements whose laws are checked together: those on one
    1-junction written as effort laws (they share its flow: their efforts
    add) and those on one 0-junction written as flow laws (they share its
    effort: their flows add), named by the junction; every other R alone.
    A correction the loop adds beside a declared law (an asymmetric
    friction term whose slope offsets part of the viscous friction's) need
    not dissipate alone: their sum at the common variable must."""
    groups: dict = {}
    for el in resistors:
        other = el.port.bond.other(el.port).element
        kind = type(other).__name__
        if (kind == "One" and el.form == "effort") or (kind == "Zero" and el.form == "flow"):
            key = (kind, other.name)
        else:
            key = ("R", el.name)
        groups.setdefault(key, []).append(el)
    return [(key[1] if key[0] != "R" else "", els) for key, els in groups.items()]


def _shared(env: _Env, els: list) -> np.ndarray | None:
    """The values along the trajectory of the variable a group of
    :func:`_parallel_groups` shares (its first R's flow for effort laws,
    effort for flow laws); None where it is not a function of the states
    and inputs alone."""
    b = els[0].port.bond
    solved = env.ss.variable(b.f if els[0].form == "effort" else b.e)
    if not env.known(solved) or env.n == 0:
        return None
    return np.broadcast_to(env.evaluate(solved), (env.n,))


#: two groups' shared variables are rigidly tied when one is a constant
#: multiple of the other at every sample, within this fraction of its size
TIED = 1e-9
#: ... over at least this many samples where it is not 0 (two values of any
#: two variables are proportional)
TIED_SAMPLES = 3


def _tied(env: _Env, groups: list) -> list[tuple[list, list]]:
    """The groups of :func:`_parallel_groups` joined where their shared
    variables are rigidly tied along the trajectory, x_j = k_j x: the flows
    of two 1-junctions bonded directly or through a transformer with no
    storage between them (a motor's rotor and the load behind a ball
    screw; one inertia then in derivative causality). Their Rs are one
    R-field at the common variable, Σ_j k_j x·φ_j(k_j x) >= 0: a
    direction-dependent friction at the load, which needs the Coulomb level
    it modifies, is judged with that Coulomb friction at the rotor (a
    user's EMPS graph: refused as "produces power" while the drive as a
    whole dissipated). Returns ``[(junction names, [(els, k), ...])]``,
    each first member with k = 1."""
    values = [(_shared(env, els), els[0].form) for _, els in groups]
    owner = list(range(len(groups)))
    ratio = [1.0] * len(groups)
    for j, (xj, form) in enumerate(values):
        for i in range(j):
            xi = values[i][0]
            if owner[i] != i or xj is None or xi is None or values[i][1] != form \
                    or not groups[i][0] or not groups[j][0]:
                continue
            ii = float(xi @ xi)
            k = float(xi @ xj) / ii if np.count_nonzero(xi) >= TIED_SAMPLES else 0.0
            if k != 0.0 and np.all(np.isfinite(xj)) and \
                    np.max(np.abs(xj - k * xi)) <= TIED * np.max(np.abs(xj)):
                owner[j], ratio[j] = i, k
                break
    out = []
    for i, (junction, els) in enumerate(groups):
        if owner[i] != i:
            continue
        tied = [j for j in range(i + 1, len(groups)) if owner[j] == i]
        out.append(([junction] + [groups[j][0] for j in tied],
                    [(els, 1.0)] + [(groups[j][1], ratio[j]) for j in tied]))
    return out


def _check_r(env: _Env, junctions: list, members: list, margin: float,
             out: Admissibility) -> None:
    """x·Σ sᵢ φᵢ(x) >= 0 for the R laws of ``members`` (``[(els, k)]``: the
    laws ``els`` read k·x) sharing the variable x (the flow for effort
    laws, the effort for flow laws; sᵢ = +1 when the bond's half-arrow
    points into the R, −1 otherwise): the power they absorb together,
    Σ k x·φ(k x) for the members tied to the first one (:func:`_tied`)."""
    els = [e for group, _ in members for e in group]
    el0 = els[0]
    variable = "flow" if el0.form == "effort" else "effort"
    names = " + ".join(e.name for e in els)
    X = _PORT
    power, terms = sp.Integer(0), []
    for group, k in members:
        kx = X if k == 1.0 else sp.Float(k) * X
        for el in group:
            port_var = el.f if el.form == "effort" else el.e
            law = el.port.bond.sign_at(el) * el.law.xreplace({port_var: kx})
            power += kx * law
            terms += [kx * t for t in sp.Add.make_args(sp.expand_mul(law))]
    power = sp.sympify(power)
    gross = sp.Add(*[sp.Abs(t) for t in terms])
    others = [s for s in power.free_symbols if s != X and s not in env.params]
    b = el0.port.bond
    solved = env.ss.variable(b.f if el0.form == "effort" else b.e)
    if not env.known(solved) or not env.known(power, [X]) or env.n == 0:
        out.unchecked.append(f"{names}: its {variable} is not a function of the states and "
                             f"inputs alone")
        return
    xs = np.broadcast_to(env.evaluate(solved), (env.n,))
    if others:
        grid = np.concatenate([xs, xs * (1.0 + margin)])
        p = np.concatenate([env.evaluate(power, at={X: xs}),
                            env.evaluate(power, at={X: xs * (1.0 + margin)})])
        g = np.concatenate([env.evaluate(gross, at={X: xs}),
                            env.evaluate(gross, at={X: xs * (1.0 + margin)})])
    else:
        grid = _widened(xs, margin)
        p = np.broadcast_to(env.evaluate(power, at={X: grid}), grid.shape)
        g = np.broadcast_to(env.evaluate(gross, at={X: grid}), grid.shape)
    out.checked.extend(e.name for e in els)
    i, bad = _r_worst(p, g)
    if bad:
        named = [j for j in junctions if j]
        where = ("" if len(els) == 1 else
                 f" (in parallel on junction '{named[0]}')" if len(named) == 1 and
                 len(members) == 1 else
                 f" (on junctions {', '.join(repr(j) for j in named)}, whose {variable}s are "
                 f"rigidly tied)")
        out.violations.append(Violation(names + where, "R", "produces power", variable,
                                        float(grid[i]), float(p[i]),
                                        (float(np.min(xs)), float(np.max(xs)))))


def _check_storage(env: _Env, el, margin: float, out: Admissibility) -> None:
    """An I law's dΦ/dp >= 0 (secant slopes on the grid: a convex kinetic
    energy); a C law's effort Ψ(q) restoring towards the well of its stored
    energy H = ∫Ψ dq over the widened range of its state
    (:func:`_escape`)."""
    state = el.state
    if state not in env.values or env.n == 0:
        out.unchecked.append(f"{el.name}: no state of its own (derivative causality)")
        return
    law = el.law
    if any(s != state and s not in env.params for s in law.free_symbols):
        out.unchecked.append(f"{el.name}: its law reads variables other than its state")
        return
    qs = env.values[state]
    grid = _widened(qs, margin)
    law_g = np.broadcast_to(env.evaluate(law, at={state: grid}), grid.shape)
    out.checked.append(el.name)
    visited = (float(np.min(qs)), float(np.max(qs)))
    if el.kind == "C":
        i, bad = _escape(grid, law_g)
        if bad:
            out.violations.append(Violation(el.name, el.kind, ESCAPES, state.name,
                                            float(grid[i]), float(law_g[i]), visited))
        return
    mid = 0.5 * (grid[1:] + grid[:-1])
    stiffness = np.diff(law_g) / np.diff(grid)
    i, bad = _worst(stiffness, mid)
    if bad:
        out.violations.append(Violation(el.name, el.kind, "has a negative stiffness "
                                        "(its stored energy is not convex)", state.name,
                                        float(mid[i]), float(stiffness[i]), visited))


#: what a C law whose effort reverses past its well breaks (:func:`_escape`)
ESCAPES = ("has an effort that reverses past the well of its stored energy (beyond it the "
           "energy falls: the state runs away)")


def _escape(grid: np.ndarray, effort: np.ndarray) -> tuple[int, bool]:
    """Whether a C law's ``effort`` Ψ on ``grid``, an ascending grid of its
    state (about GRID_POINTS,), pushes away from the well of its stored energy
    H = ∫Ψ dq anywhere: H is to rise on both sides of its lowest point on
    the grid, Ψ >= 0 to its right and <= 0 to its left, up to −TOLERANCE ×
    the largest |Ψ|. Returns the index of the worst such point and whether
    there is one. A preloaded spring (Ψ > 0 throughout: the well lies
    beyond the range) passes; so does a pendulum's m g l sin θ past 90° or
    a softening spring past its turning point while it still restores (a
    stiffness < 0 there, but no energy below the well's); a negative spring,
    or a softening one past the top of its barrier (k q − β q³ beyond
    q² = k/β), does not."""
    ok = np.isfinite(effort)
    if not np.any(ok):
        return 0, False
    psi = np.where(ok, effort, 0.0)
    H = np.concatenate([[0.0], np.cumsum(0.5 * (psi[1:] + psi[:-1]) * np.diff(grid))])
    m = int(np.argmin(H))
    tol = TOLERANCE * float(np.max(np.abs(psi)))
    away = np.where(np.arange(psi.size) > m, -psi, psi)     # < 0 where it restores
    away[m] = -np.inf
    i = int(np.argmax(away))
    return i, bool(away[i] > tol)

"""A discovered law as a loop effect, and the loop with discovery.

:class:`DiscoveredEffect` attaches a :class:`~bondgraph.diagnose.discover.law.DiscoveredLaw`
``d = Σ c_k b_k`` (an effort entering its 1-junction, a flow entering its
0-junction) as bond-graph elements, part by part
(:meth:`DiscoveredEffect.placement`, the parts of
:mod:`bondgraph.diagnose.discover.passivity`):

* the **R part** (terms of the junction's own variable z, alone or times a
  bonded storage state) becomes one R element ``<effect>.<port>.R`` on the
  junction with the law e_R = −d_R(f_R) (1-junction) or f_R = −d_R(e_R)
  (0-junction): its power e_R·f_R = −d_R·z is what a resistor must keep
  >= 0;
* each **storage part** (terms of one bonded storage state s: a C's
  displacement at a 1-junction, an I's momentum at a 0-junction) changes
  that element's law into Ψ(s) − d_S(s) (its energy by
  :func:`antiderivative`);
* the rest (a constant, inputs) stays a modulated effort (flow) source
  ``<effect>.<port>``, named source-like in the placement;
* a **memory term** c·lp(x, τ) (the law's one low-pass of a variable x,
  :func:`~bondgraph.diagnose.discover.law.memory_candidates`) gives the
  model a state of its own, as the Bouc-Wen element does
  (:mod:`bondgraph.diagnose.effects.hysteresis`): a signal state
  ``<effect>.<port>.w`` with dw/dt = (x − w)/τ, acting through a modulated
  effort (flow) source ``<effect>.<port>.lp`` of value c·w; τ is a
  parameter ``<effect>.<port>.tau`` (s) refitted with the coefficients in
  the box [τ/10, 10·τ] around the discovered one. Its passivity is checked
  at discovery along the record
  (:mod:`bondgraph.diagnose.discover.passivity`, memory part).

So the loop's own admissibility check
(:func:`bondgraph.numerics.admissible.check_admissible`: R laws dissipate,
alone or in parallel with the declared ones on the junction; a C law
restores towards its energy's well, an I law keeps a non-negative slope)
judges the law at every refitted value: a refit that makes the R part
produce power or the storage push away from its well is refused with the
element named (the equations are those of a single modulated source, the
attachment of issue 29's first version).

Each coefficient ``c_k`` is a parameter (``discovered.<port>.c<k>``, unit:
the port's effort over the basis' unit, so the graph's unit check holds).
It is a structural effect of the loop (:mod:`bondgraph.diagnose.scoring`):
scored by the likelihood ratio at the discovered coefficients (× 0.7, 1,
1.4), refitted with every declared parameter by maximum likelihood,
confirmed and accepted like any library effect (likelihood-ratio test,
held-out error, admissibility). Each coefficient keeps the sign the
passivity check accepted or vanishes (its box is [0, 10 c]).

:func:`discover_effect` runs reconstruction, discovery and the passivity
check at one port; :func:`loop_with_discovery` runs the loop, and when it
accepts no physical effect (none, or only a last-resort disturbance) or the
accepted ones leave innovations that are not white, every junction's law is
discovered and the loop runs again with them beside the library: the law of
the port where the reconstruction gains most likelihood, each port's sparse
alternative (at most two terms) and the other ports' laws
(:func:`law_alternatives`), each effect under its own name; the loop's
likelihood ratio and accept rule choose.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field, replace

import numpy as np
import sympy as sp

from bondgraph.core import units
from bondgraph.core.elements import C, I, One, Zero
from bondgraph.diagnose.discover.law import (
    DiscoveredLaw,
    DiscoverOptions,
    discover_law,
    memory_name,
    threshold_law,
)
from bondgraph.diagnose.discover.passivity import PassivityReport, make_passive
from bondgraph.diagnose.discover.reconstruct import (
    Reconstruction,
    ReconstructOptions,
    port_values,
    reconstruct,
    reconstruct_sensor,
)
from bondgraph.diagnose.effects.base import EffectParam, Target, _new_param, _Structural
from bondgraph.errors import BondGraphError, GraphError
from bondgraph.inference.estimate import Criterion, cramer_rao, hessian_batched
from bondgraph.inference.problem import make_problem
from bondgraph.numerics.admissible import Violation
from bondgraph.numerics.model import Model

#: how far a refitted coefficient may move from the discovered one (factor)
COEF_REACH = 10.0
#: the grid of the structural score, as multiples of the discovered coefficients
GRID_FACTORS = (0.7, 1.0, 1.4)
#: most terms of a port's sparse alternative law (:func:`sparse_alternative`)
SPARSE_TERMS = 2
#: most discovered laws put beside the library in one loop run
#: (:func:`discovered_effect`: the best port's, then the alternatives)
MAX_LAWS = 6
#: most laws at sensors' outputs put beside them (:func:`law_alternatives`)
MAX_OUTPUT_LAWS = 4
#: most threshold laws put beside them (:func:`threshold_alternative`)
MAX_THRESHOLD_LAWS = 3


def _tau_box(tau: float) -> tuple[float, float]:
    """[τ/COEF_REACH, τ·COEF_REACH]: a memory's time constant stays
    positive."""
    return (tau / COEF_REACH, tau * COEF_REACH)


def _sign_box(c: float) -> tuple[float, float]:
    """[0, c·COEF_REACH], ordered: the coefficient keeps its sign or
    vanishes (a spurious term the refit removes)."""
    return (min(0.0, c * COEF_REACH), max(0.0, c * COEF_REACH))


class DiscoveredEffect(_Structural):
    """A discovered law at its junction (module docstring): its R part an R
    element on the junction, its storage part in the bonded C (I) law, the
    rest a modulated effort (flow) source.

    Parameters
    ----------
    law : DiscoveredLaw
        At least one term; its symbols named as the port's variables
        (``"<port>.f"``, storage state names, input names); at most one
        memory term.
    name : str
        The effect's name (default ``"discovered"``; unique in a library).

    Raises
    ------
    GraphError
        A law without terms, of another kind, or with two memory terms.
    """

    target_kind = "junction"
    #: the law kinds this class attaches
    kinds = ("effort", "flow")

    def __init__(self, law: DiscoveredLaw, name: str = "discovered"):
        if not law.terms:
            raise GraphError(f"discovered law at '{law.port}' has no term")
        if law.kind not in self.kinds:
            raise GraphError(f"discovered law at '{law.port}': kind '{law.kind}' is neither "
                             f"an effort (1-junction) nor a flow (0-junction)")
        if sum(tm.memory is not None for tm in law.terms) > 1:
            raise GraphError(f"discovered law at '{law.port}' has more than one memory term")
        self.law = law
        self.name = name
        self.title = f"discovered law {law.readable(3)}"
        self.params = tuple(EffectParam(f"c{k}", coefficient_unit(law.unit, tm.unit),
                                        f"coefficient of {tm.name}",
                                        bounds=_sign_box(tm.coef))
                            for k, tm in enumerate(law.terms))
        mem = law.memory_term
        if mem is not None:
            self.params += (EffectParam("tau", "s", f"time constant of {mem.name}",
                                        bounds=_tau_box(mem.memory.tau)),)

    def readable(self, values: dict | None = None, std: dict | None = None,
                 target: Target | None = None, digits: int = 4) -> str:
        """The law with refitted coefficients, each with its Cramér-Rao std
        where known: ``"v effort [N] = -2854(±12)·q_spring^5 - ..."``.

        Parameters
        ----------
        values, std : dict, optional
            By full parameter name (``discovered.<port>.c<k>``, a loop
            step's ``parameters``) or local name (``c<k>``); missing: the
            discovered coefficient, no std.
        """
        tgt = target or self.target()
        values, std = dict(values or {}), dict(std or {})

        def get(dct, loc, default=None):
            return dct.get(self.pname(tgt, loc), dct.get(loc, default))

        parts = []
        for k, tm in enumerate(self.law.terms):
            c, s = float(get(values, f"c{k}", tm.coef)), get(std, f"c{k}")
            err = f"(±{s:.2g})" if s is not None and np.isfinite(s) else ""
            name = tm.name
            if tm.memory is not None:
                tau, ts = float(get(values, "tau", tm.memory.tau)), get(std, "tau")
                name = memory_name(tm.memory.variable, tau)
                if ts is not None and np.isfinite(ts):
                    name = name.replace(" s)", f"(±{ts:.2g}) s)")
            parts.append(("- " if c < 0 else "+ ") + f"{abs(c):.{digits}g}{err}·{name}")
        text = " ".join(parts)
        text = text[2:] if text.startswith("+ ") else "-" + text[2:]
        return f"{self.law.port} {self.law.kind} [{self.law.unit}] = {text}"

    def target(self) -> Target:
        """The law's one target (its junction; a sensor for
        :class:`DiscoveredSensorEffect`)."""
        return Target(self.target_kind, self.law.port)

    def targets(self, graph):
        el = graph.elements.get(self.law.port)
        kind = One if self.law.kind == "effort" else Zero
        return [Target("junction", self.law.port)] if isinstance(el, kind) else []

    def grid(self, graph, target, scales):
        mem = self.law.memory_term
        tau = {"tau": mem.memory.tau} if mem is not None else {}
        return [{**{f"c{k}": f * tm.coef for k, tm in enumerate(self.law.terms)}, **tau}
                for f in GRID_FACTORS]

    def grid_span(self, graph, target, scales):
        return self.box(graph, target, scales)

    def box(self, graph, target, scales):
        out = {f"c{k}": _sign_box(tm.coef) for k, tm in enumerate(self.law.terms)}
        if self.law.memory_term is not None:
            out["tau"] = _tau_box(self.law.memory_term.memory.tau)
        return out

    def variables(self, graph) -> dict:
        """The law's variables as ``graph``'s expressions, by symbol.

        Raises
        ------
        GraphError
            A variable of the law that ``graph`` does not have.
        """
        j = graph.element(self.law.port)
        states = {s.name: s for s in graph.all_states()}
        subs = {}
        for name, sym in self.law.symbols.items():
            if name == f"{self.law.port}.f":
                subs[sym] = j.f
            elif name == f"{self.law.port}.e":
                subs[sym] = j.e
            elif name in states:
                subs[sym] = states[name]
            elif name in graph.inputs:
                subs[sym] = graph.inputs[name]
            else:
                raise GraphError(f"discovered law at '{self.law.port}': graph '{graph.name}' "
                                 f"has no variable '{name}'")
        return subs

    def bases(self, graph, w=None) -> list:
        """The terms' bases in ``graph``'s symbols; a memory term's is its
        state ``w`` (made by :meth:`memory_state`).

        Raises
        ------
        GraphError
            A variable of the law that ``graph`` does not have, or a memory
            term and no ``w``.
        """
        subs = self.variables(graph)
        mem = self.law.memory_term
        if mem is not None:
            if w is None:
                raise GraphError(f"discovered law at '{self.law.port}': the memory term "
                                 f"{mem.name} needs its state w")
            subs[mem.basis] = w
        return [tm.basis.xreplace(subs) for tm in self.law.terms]

    def memory_state(self, graph, target, tau):
        """The memory term's signal state w (``<effect>.<port>.w``) with
        dw/dt = (x − w)/τ, x its filtered variable in ``graph``, from the
        value the record started with (None when the law has no memory).

        Parameters
        ----------
        graph : BondGraph
        target : Target
        tau : Parameter
            The time constant (s).

        Returns
        -------
        StateVar or None
        """
        mem = self.law.memory_term
        if mem is None:
            return None
        subs = self.variables(graph)
        x = next(e for sym, e in subs.items() if str(sym) == mem.memory.variable)
        return graph.state(f"{self.name}.{target.tag}.w", rhs=lambda w: (x - w) / tau,
                           unit=None if mem.unit in ("", "1") else mem.unit,
                           initial=mem.memory.initial,
                           description=f"memory {mem.name} of the discovered law at "
                                       f"{target.name}")

    def placement(self, graph, target: Target | None = None) -> list:
        """Where each term goes in ``graph`` (module docstring): the R part
        (the junction's own variable, alone or times a bonded storage state)
        as one R element, each storage part into the law of its C (at a
        1-junction) or I (at a 0-junction), the rest as a modulated source.

        Returns
        -------
        list of Placement
            One per part that has terms, in the order R, storage, source.
        """
        tgt = target or self.target()
        j = graph.element(self.law.port)
        own = f"{self.law.port}.f" if self.law.kind == "effort" else f"{self.law.port}.e"
        store = C if self.law.kind == "effort" else I
        bonded = {}
        for p in j.ports:
            el = p.bond.other(p).element if p.bond is not None else None
            if isinstance(el, store) and getattr(el, "state", None) is not None:
                bonded[el.state.name] = el.name
        parts: dict = {}
        for k, tm in enumerate(self.law.terms):
            names = {str(s) for s in tm.basis.free_symbols}
            if tm.memory is not None:
                key = ("memory", f"{self.name}.{tgt.tag}.lp",
                       f"memory term: a modulated source of the signal state "
                       f"{self.name}.{tgt.tag}.w, dw/dt = ({tm.memory.variable} − w)/τ "
                       f"(dissipation checked along the record)")
            elif names and own in names and not names - {own} - set(bonded):
                key = ("R", f"{self.name}.{tgt.tag}.R",
                       "dissipative part: an R law of the junction's "
                       + ("flow" if self.law.kind == "effort" else "effort"))
            elif len(names) == 1 and next(iter(names)) in bonded:
                el = bonded[next(iter(names))]
                key = ("storage", el, f"storage part: added to the law of {el}")
            else:
                why = ("a constant or an input" if not names - set(bonded) - {own}
                       or names & set(self.law.inputs) else f"reads {sorted(names)}")
                key = ("source", f"{self.name}.{tgt.tag}",
                       f"source-like ({why}): a modulated source, not checked")
            parts.setdefault(key, []).append(k)
        order = {"R": 0, "storage": 1, "memory": 2, "source": 3}
        return [Placement(part, el, tuple(ks), why)
                for (part, el, why), ks in sorted(parts.items(), key=lambda kv: order[kv[0][0]])]

    def apply(self, graph, target, values=None, scales=None):
        j = graph.element(target.name)
        P = self._declare(graph, target, values, scales, f"at {target.name}")
        bases = self.bases(graph, self.memory_state(graph, target, P.get("tau")))

        def part(ks):
            return sp.Add(*(P[f"c{k}"] * bases[k] for k in ks))

        for pl in self.placement(graph, target):
            if pl.part == "R":
                _attach_r(graph, j, pl.element, part(pl.terms), self.law.kind)
            elif pl.part == "storage":
                el = graph.element(pl.element)
                d = part(pl.terms)
                sign = el.port.bond.sign_at(el)
                el.law = el.law - sign * d
                if el.energy is not None:
                    el.energy = el.energy - sign * sp.Add(*(
                        P[f"c{k}"] * antiderivative(bases[k], el.state) for k in pl.terms))
            else:
                src = graph.MSe if self.law.kind == "effort" else graph.MSf
                graph.connect(src(pl.element, part(pl.terms)), j)
        return P

    def refitted_law(self, target, values: dict) -> DiscoveredLaw:
        """The law with its coefficients and τ at ``values`` (local names
        ``c<k>``, ``tau``; a name missing keeps the discovered value)."""
        tau = values.get("tau")
        terms = [replace(tm, coef=float(values.get(f"c{k}", tm.coef)),
                         memory=None if tm.memory is None or tau is None
                         else replace(tm.memory, tau=float(tau)))
                 for k, tm in enumerate(self.law.terms)]
        return replace(self.law, terms=terms)

    def refit_violations(self, graph, target, fit, inputs, t) -> list:
        """The law's memory and coupled parts checked again at a refit, as at
        discovery (:func:`~bondgraph.diagnose.discover.passivity.make_passive`:
        the dissipation inequality along the record, the coupled power at
        its samples), with the refitted coefficients and τ along the refit's
        filtered states: these parts are modulated sources or laws of two
        variables, which the loop's admissibility check of R, C and I laws
        does not judge (a refit may move a memory term's coefficient past
        what the port's dissipation absorbs). Returns the
        :class:`~bondgraph.numerics.admissible.Violation` of each part that
        fails (empty when none does)."""
        model = fit.model
        x = getattr(fit.ukf, "x_filt", None)
        ss = getattr(model.module, "__state_space__", None)
        if x is None or ss is None or self.law.kind not in ("effort", "flow"):
            return []           # a law at a sensor's output carries no power
        theta = np.asarray(fit.theta, float)
        local = {p.name: float(theta[model.param_index(self.pname(target, p.name))])
                 for p in self.params if self.pname(target, p.name) in model.params}
        law = self.refitted_law(target, local)
        values = port_values(fit.graph, ss, self.law.port, np.asarray(x)[:, 0, :], inputs, theta)
        declared = {n: float(theta[model.param_index(n)]) for n in graph.params
                    if n in model.params}
        rep = make_passive(law, graph, values, params=declared, t=t)
        own = values[next(k for k in law.symbols if k in (f"{law.port}.f", f"{law.port}.e"))]
        out = []
        for c in rep.checks:
            if c.ok or c.part not in ("memory", "coupled"):
                continue
            if c.part == "memory":
                out.append(Violation(f"{self.name}.{target.tag}.lp", "memory",
                                     "returns more energy than the port's laws absorbed "
                                     "(absorbed energy)", "t", c.at, c.worst,
                                     (float(t[0]), float(t[-1]))))
            else:
                out.append(Violation(f"{self.name}.{target.tag}", "coupled",
                                     "produces power with the law's R part", c.variable,
                                     c.at, c.worst, (float(np.min(own)), float(np.max(own)))))
        return out

    def _declare(self, graph, target, values, scales, where: str) -> dict:
        """The effect's parameters declared in ``graph`` (the coefficients
        ``c<k>``, and ``tau`` for a memory term), at ``values`` (local
        names) or the discovered ones."""
        values = dict(values or {})
        boxes = self.box(graph, target, scales)
        start = {f"c{k}": tm.coef for k, tm in enumerate(self.law.terms)}
        if self.law.memory_term is not None:
            start["tau"] = self.law.memory_term.memory.tau
        return {spc.name: _new_param(graph, self.pname(target, spc.name),
                                     float(values.get(spc.name, start[spc.name])), spc.unit,
                                     boxes[spc.name], f"{spc.description} {where}")
                for spc in self.params}


@dataclass(frozen=True)
class Placement:
    """Where a part of a discovered law is attached
    (:meth:`DiscoveredEffect.placement`).

    Attributes
    ----------
    part : {"R", "storage", "source", "sensor"}
    element : str
        The element that carries it: the new R element, the bonded C or I
        whose law it changes, the new modulated source, or the sensor whose
        measurement it changes.
    terms : tuple of int
        Indices of the law's terms.
    why : str
        Readable reason of the placement.
    """

    part: str
    element: str
    terms: tuple
    why: str


def _attach_r(graph, j, name: str, d, kind: str) -> None:
    """An R element ``name`` on junction ``j`` (bond from the junction to
    it) whose law takes ``d`` (the effort, resp. flow, the law adds to the
    junction) out of it: e_R = −d(f_R) at a 1-junction, f_R = −d(e_R) at a
    0-junction, so that its power e_R·f_R = −d·z is what the passivity
    check requires to be >= 0."""
    if kind == "effort":
        r = graph.R(name, effort=lambda f: -d.xreplace({j.f: f}))
    else:
        r = graph.R(name, flow=lambda e: -d.xreplace({j.e: e}))
    graph.connect(j, r)


class DiscoveredSensorEffect(DiscoveredEffect):
    """A discovered law at a sensor's output: y = h(x, u, θ) + Σ c_k b_k,
    the bases b_k functions of the sensed quantity h (``"<sensor>.y"``)
    and of the inputs (:func:`~bondgraph.diagnose.discover.reconstruct.reconstruct_sensor`).
    A sensor takes no power from the graph: no passivity condition applies
    (:func:`~bondgraph.diagnose.discover.passivity.make_passive` keeps every
    term and says so). A structural effect like :class:`DiscoveredEffect`:
    scored at its discovered coefficients, each coefficient's box
    [0, 10 c].

    Parameters
    ----------
    law : DiscoveredLaw
        ``kind`` ``"output"``, ``port`` the sensor's name.
    name : str
        The effect's name.

    Raises
    ------
    GraphError
        A law without terms or of another kind.
    """

    target_kind = "sensor"
    kinds = ("output",)

    def targets(self, graph):
        return [self.target()] if self.law.port in graph.sensors else []

    def variables(self, graph) -> dict:
        """The law's variables as ``graph``'s expressions, by symbol:
        ``"<sensor>.y"`` is the sensor's expression in ``graph`` (before
        this law is added).

        Raises
        ------
        GraphError
            ``graph`` has no such sensor, or the law reads a variable
            ``graph`` does not have.
        """
        if self.law.port not in graph.sensors:
            raise GraphError(f"graph '{graph.name}' has no sensor '{self.law.port}'")
        subs = {}
        for name, sym in self.law.symbols.items():
            if name == f"{self.law.port}.y":
                subs[sym] = graph.sensors[self.law.port].expr
            elif name in graph.inputs:
                subs[sym] = graph.inputs[name]
            else:
                raise GraphError(f"discovered law at the output '{self.law.port}': graph "
                                 f"'{graph.name}' has no variable '{name}'")
        return subs

    def placement(self, graph, target: Target | None = None) -> list:
        """One part: every term added to the sensor's measurement.

        Returns
        -------
        list of Placement
        """
        mem = "" if self.law.memory_term is None else (
            f"; its memory term through the signal state {self.name}.{self.target().tag}.w")
        return [Placement("sensor", self.law.port, tuple(range(len(self.law.terms))),
                          "output law: added to the measurement (a sensor takes no power)"
                          + mem)]

    def apply(self, graph, target, values=None, scales=None):
        P = self._declare(graph, target, values, scales, f"at the output {target.name}")
        bases = self.bases(graph, self.memory_state(graph, target, P.get("tau")))
        sen = graph.sensors[target.name]
        sen.expr = sen.expr + sp.Add(*(P[f"c{k}"] * b for k, b in enumerate(bases)))
        return P


def effect_for(law: DiscoveredLaw, name: str = "discovered") -> DiscoveredEffect:
    """The loop effect of a discovered law: :class:`DiscoveredSensorEffect`
    for a law at a sensor's output (``kind`` ``"output"``), else
    :class:`DiscoveredEffect`.

    Raises
    ------
    GraphError
        A law without terms.
    """
    cls = DiscoveredSensorEffect if law.kind == "output" else DiscoveredEffect
    return cls(law, name)


def antiderivative(basis, s):
    """∫₀ˢ basis ds' of a term of one storage state ``s`` (its energy), in
    closed form for the dictionary's shapes
    (:func:`bondgraph.diagnose.discover.law.dictionary`): polynomials,
    |s|·s -> |s|·s²/3, tanh(a·s) -> log(cosh(a·s))/a,
    s/(1 + a·|s|) -> |s|/a − log(1 + a·|s|)/a² (a > 0); otherwise sympy's
    ``integrate``.

    Raises
    ------
    GraphError
        No closed form (sympy returns an unevaluated integral).
    """
    a = sp.Wild("a", exclude=[s])
    if basis.is_polynomial(s):
        return sp.integrate(basis, (s, 0, s))
    if sp.simplify(basis - sp.Abs(s) * s) == 0:
        return sp.Abs(s) * s ** 2 / 3
    m = basis.match(sp.tanh(a * s))
    if m and m[a] != 0:
        return sp.log(sp.cosh(m[a] * s)) / m[a]
    m = basis.match(s / (1 + a * sp.Abs(s)))
    if m and m[a].is_positive:
        return sp.Abs(s) / m[a] - sp.log(1 + m[a] * sp.Abs(s)) / m[a] ** 2
    x = sp.Dummy("x", real=True)
    out = sp.integrate(basis.xreplace({s: x}), (x, 0, s))
    if out.has(sp.Integral):
        raise GraphError(f"discovered law: no closed-form energy of the term {basis} in {s}")
    return out


def coefficient_unit(port_unit: str, basis_unit: str) -> str:
    """The unit of a coefficient, ``port_unit / basis_unit``, in pint's
    compact form (``"N*s**3/m**3"``; :func:`bondgraph.core.units.parse`
    refuses an exponent followed by a parenthesis, ``"(N)/((m)^3)"``)."""
    q = units.parse(port_unit or "1") / units.parse(basis_unit or "1")
    text = format(q.units, "~C")
    return text if text and text != "dimensionless" else "1"


@dataclass
class Discovery:
    """What :func:`discover_effect` found at one port.

    Attributes
    ----------
    reconstruction : Reconstruction
    law : DiscoveredLaw
        As regressed (before the passivity check).
    passivity : PassivityReport
        ``passivity.law`` is the law kept.
    effect : DiscoveredEffect or None
        None when no term is left.
    gain : float
        Likelihood gain of the reconstruction: the UKF's NLL at the grid's
        smallest intensity minus the NLL at the chosen one (nats; 0 when the
        intensity was given).
    placement : list of Placement
        Where the effect's parts go in the declared graph.
    alternatives : list of Discovery
        Further laws the loop compares with this one
        (:func:`discovered_effect`): the sparse alternative at this port
        and the laws of the other ports, each effect under its own name.
    """

    reconstruction: Reconstruction
    law: DiscoveredLaw
    passivity: PassivityReport
    effect: DiscoveredEffect | None
    gain: float
    placement: list = field(default_factory=list)
    alternatives: list = field(default_factory=list)

    def effects(self) -> list:
        """This discovery's effect, then its alternatives' (those with one).

        Returns
        -------
        list of DiscoveredEffect
            Each under its own name (``discovered``, ``discovered_2``, ...).
        """
        return [d.effect for d in [self] + list(self.alternatives) if d.effect is not None]

    def accepted_in(self, result) -> "Discovery":
        """The discovery (this one or an alternative) whose effect the loop
        result ``result`` accepted, alone or in a pair; this one when none
        was.

        Parameters
        ----------
        result : LoopResult
            A loop run with :meth:`effects` beside the library.

        Returns
        -------
        Discovery
        """
        names = {s.effect for s in getattr(result, "steps", [])}
        names |= {w.split(" @ ")[0] for s in getattr(result, "steps", [])
                  for w in getattr(s, "together_with", [])}
        return next((d for d in [self] + list(self.alternatives)
                     if d.effect is not None and d.effect.name in names), self)

    def summary(self) -> str:
        """Readable lines: the law, the passivity verdict, the gain."""
        return "\n".join([f"reconstruction at '{self.law.port}': likelihood gain "
                          f"{self.gain:.4g} nats, q = {self.reconstruction.q:.4g}",
                          f"regressed: {self.law.readable()}",
                          self.passivity.summary(),
                          f"kept: {self.passivity.law.readable()}"])


def discover_effect(graph, record, port: str, *, params=None,
                    reconstruction: ReconstructOptions | None = None,
                    discovery: DiscoverOptions | None = None,
                    name: str = "discovered", sensor: bool = False) -> Discovery:
    """Reconstruct the effort missing at ``port``, discover its law, keep its
    passive terms and make it a loop effect.

    Parameters
    ----------
    graph : BondGraph
        The declared graph.
    record : Experiment
    port : str
        A junction of ``graph`` (1-junction: a missing effort; 0-junction:
        a missing flow).
    params : dict, optional
        Parameter values of ``graph`` by name (default its defaults).
    reconstruction : ReconstructOptions, optional
    discovery : DiscoverOptions, optional
    name : str
        The effect's name.
    sensor : bool
        ``port`` names a sensor: the offset missing at its output is
        reconstructed (:func:`~bondgraph.diagnose.discover.reconstruct.reconstruct_sensor`)
        and its law becomes a :class:`DiscoveredSensorEffect`.

    Returns
    -------
    Discovery

    Raises
    ------
    GraphError
        ``port`` is not a junction (not a sensor, with ``sensor``).
    NumericalError
        The filter or smoother fails.
    """
    how = reconstruct_sensor if sensor else reconstruct
    rec = how(graph, record, port, params=params, options=reconstruction)
    law = discover_law(rec, options=discovery)
    rep = make_passive(law, graph, rec.variables, params=params, t=rec.t)
    kept = rep.law
    eff = effect_for(kept, name) if kept.terms else None
    gain = float(rec.nll_grid[-1] - np.min(rec.nll_grid)) if rec.nll_grid.size else 0.0
    placed = eff.placement(graph) if eff is not None else []
    return Discovery(rec, law, rep, eff, gain, placed)


def coefficient_std(graph, record, effect: DiscoveredEffect, estimates: dict, *,
                    ukf=None, step: float = 1e-4) -> dict:
    """Cramér-Rao standard deviations of the estimated parameters of
    ``graph`` with ``effect`` attached, from the UKF likelihood's difference
    Hessian (:func:`bondgraph.inference.estimate.hessian_batched`,
    :func:`~bondgraph.inference.estimate.cramer_rao`) at ``estimates``.

    Parameters
    ----------
    graph : BondGraph
        The declared graph.
    record : Experiment
        The record the estimates were fitted on.
    effect : DiscoveredEffect
    estimates : dict str -> float
        Every estimated parameter by full name (a loop step's
        ``{name: parameters[name]["estimate"]}``): the declared ones and the
        effect's ``<effect>.<port>.c<k>``.
    ukf : UKFOptions, optional
        The filter options of the fit.
    step : float
        Relative difference step.

    Returns
    -------
    dict str -> float
        Std by name (NaN where the Hessian is not positive definite). A
        parameter on a bound of its box gets the std of the interior
        Hessian: a local measure, not a confidence interval.

    Raises
    ------
    GraphError
        The effect cannot be attached.
    """
    g = graph.copy(f"{graph.name}__{effect.name}")
    (tgt,) = effect.targets(g) or [None]
    if tgt is None:
        raise GraphError(f"graph '{graph.name}' has no junction '{effect.law.port}' of the "
                         f"law's kind")
    local = {n.rsplit(".", 1)[-1]: v for n, v in estimates.items()
             if n.startswith(f"{effect.name}.")}
    effect.apply(g, tgt, local)
    model = Model.from_graph(g, lazy=("dfdtheta", "dhdtheta"))
    names = [n for n in estimates if n in model.params]
    fixed = {n: float(v) for n, v in estimates.items() if n in model.params}
    problem = make_problem(model, record, ukf=ukf, fixed=fixed)
    x = np.array([fixed[n] for n in names])
    H, _, _ = hessian_batched(Criterion(problem, names), x, step * np.maximum(np.abs(x), 1e-6))
    # the positive-definiteness test in coordinates of unit curvature (the
    # Hessian as a correlation matrix): a small coefficient is not taken
    # for an unidentified one
    diag = np.diag(H) if H is not None else np.ones(len(names))
    scale = np.where(np.isfinite(diag) & (diag > 0), 1.0 / np.sqrt(np.abs(diag)), 1.0)
    cr = cramer_rao(H, names, scale=scale)
    return {n: float(v) for n, v in zip(names, cr["std"])}


def loop_with_discovery(graph, record, settings, *, ports=None, log=None,
                        reconstruction: ReconstructOptions | None = None,
                        discovery: DiscoverOptions | None = None, sensors=None):
    """The loop, then, when it accepts no physical effect or the accepted
    ones leave coloured innovations, discovery at every port
    (:func:`discovered_effect`) and the loop again, from the declared graph,
    with the discovered laws beside the library (:func:`with_discovered`):
    the loop's likelihood-ratio test and accept rule choose among the laws
    and the library's effects.

    Parameters
    ----------
    graph : BondGraph
    record : Experiment
    settings : LoopSettings
    ports : sequence of str, optional
        The junctions to try (default every 1- and 0-junction of ``graph``).
    log : callable, optional
        Line logger (default ``print``).
    reconstruction, discovery : options, optional
        Default: :func:`reconstruction_options` of ``settings``, and
        ``DiscoverOptions()``.
    sensors : sequence of str, optional
        The sensors whose output offset is reconstructed too (default every
        sensor ``record`` measures; ``()``: none).

    Returns
    -------
    (LoopResult, Discovery or None)
        The second loop's result when it is better than the first's
        (:func:`discovery_not_better`; else the first's, the reason logged
        and in its warnings) and the discovery whose law it accepted (the
        best port's when it accepted none) when discovery ran, else the
        first loop's result and None.
    """
    from bondgraph.diagnose.runner import run_loop

    first = run_loop(graph, record, settings, log=log, progress=False)
    best = discovered_effect(graph, record, settings, first, ports=ports, log=log,
                             reconstruction=reconstruction, discovery=discovery,
                             sensors=sensors)
    if best is None:
        return first, None
    res = run_loop(graph, record, with_discovered(settings, *best.effects()), log=log,
                   progress=False)
    shown = best.accepted_in(res)
    res.discovery = discovery_plot(shown, res)
    why = discovery_not_better(first, res)
    if why is None:
        return res, shown
    (log or print)(f"discovery: {why}")
    first.warnings.append(why)
    return first, shown


def discovery_not_better(first, second) -> str | None:
    """Why the loop run again with discovered laws (``second``, a
    :class:`~bondgraph.diagnose.result.LoopResult`) does not replace the
    first loop's result ``first``, or None when it does: its final model's
    free-run error on the record that judges the loop (the validation or
    held-out record, else the estimation record) must be finite and lower
    than the first's, and on no further validation record higher. The
    second loop starts again from the declared graph and may take another
    path (a discovered law accepted early leaves out the library effects
    the first loop found): a user's cascaded tanks, run with ``--discover``,
    ended at 0.1865 on the held-out quarter where the library alone had
    reached 0.1217, and that model replaced the better one.

    Returns
    -------
    str or None
        The reason, naming both errors; None when ``second`` is better.
    """
    f1, f2 = first.final, second.final
    held = f1.validation_metric is not None and f2.validation_metric is not None
    e1, e2 = (f1.validation_metric, f2.validation_metric) if held else (f1.metric, f2.metric)
    where = "the validation record" if held else "the estimation record"
    if not (np.isfinite(e2) and (not np.isfinite(e1) or e2 < e1)):
        return (f"the loop with the discovered law(s) ends at {e2:.4g} on {where}, the "
                f"library's at {e1:.4g}: the library's model stands")
    for name, v2 in (getattr(f2, "more_metrics", None) or {}).items():
        v1 = (getattr(f1, "more_metrics", None) or {}).get(name)
        if v1 is not None and np.isfinite(v1) and not v2 <= v1:
            return (f"the loop with the discovered law(s) ends at {v2:.4g} on the validation "
                    f"record '{name}', the library's at {v1:.4g}: the library's model stands")
    return None


def with_discovered(settings, effect: DiscoveredEffect, *more: DiscoveredEffect):
    """The loop's settings with ``effect`` (and ``more``) beside the library.
    A discovered law is a structural effect: where ``settings`` skip the
    structural effects (``search.structural`` False: the Silverbox case),
    they are switched on and the library keeps only its additive effects,
    so that the laws are scored and the library's structural effects stay
    out as the settings asked.

    Parameters
    ----------
    settings : LoopSettings
    effect, *more : DiscoveredEffect
        Each under its own name.

    Returns
    -------
    LoopSettings
    """
    laws = (effect,) + tuple(more)
    if settings.search.structural:
        return replace(settings, effects=tuple(settings.effects) + laws)
    kept = tuple(e for e in settings.effects if getattr(e, "additive", False))
    return replace(settings, effects=kept + laws,
                   search=replace(settings.search, structural=True))


def reconstruction_options(settings) -> ReconstructOptions:
    """The reconstruction's options for a loop run with ``settings``: the
    loop's filter (its method, input hold, sigma-point spread) at one step
    per sample. The hold matters most: on Silverbox (a band-limited input
    on a 2x grid) the zero-order hold's error makes d̂ four times larger
    (12.6 against 2.9 mV RMS). The loop's substeps are not taken: at 4
    substeps the quintic spring of ``tests/test_discover_loop.py`` gave four
    look-alike terms instead of −2552·x⁵ − 75·x³ (1 substep, linear hold:
    −2570·x⁵ − 70·x³)."""
    return ReconstructOptions(ukf=replace(settings.ukf, substeps=1))


def discovered_effect(graph, record, settings, first, *, ports=None, log=None,
                      reconstruction: ReconstructOptions | None = None,
                      discovery: DiscoverOptions | None = None, sensors=None):
    """The discovery to add after the loop's result ``first``: None when
    ``first`` accepted a physical effect (not a last resort) and its final
    innovations are white (:meth:`~bondgraph.diagnose.residuals.ResidualReport.is_white`),
    or when no port gave a passive law; else the junction whose
    reconstruction gains most likelihood (a sensor's output only when no
    junction gave a law; every measured sensor is tried too), with its law as a loop effect
    (``Discovery.effect``) and, as ``Discovery.alternatives``, the laws the
    loop compares it with (:func:`law_alternatives`). Accepted effects that
    leave the innovations coloured are look-alikes or incomplete (a cubic
    stiffness for a quintic spring: whiteness 23 347 -> 23 214; the true
    cubic: 30 223 -> 19.3), so the law is then sought too and the second
    loop compares it with the library.

    The reconstruction runs the declared graph at its declared values
    (``settings.fixed`` over the graph's defaults), not at the initial fit,
    whose parameters have absorbed part of the missing law (on the quintic
    spring of ``tests/test_discover_loop.py`` the fitted stiffness and
    damping leave a power-generating damping term to the law): the port is
    localised and the law found with the declared model as it stands; the
    loop then refits everything.

    Parameters
    ----------
    graph, record, settings
        As for the loop.
    first : LoopResult
        The loop's result without discovery.
    ports, log, reconstruction, discovery, sensors
        As for :func:`loop_with_discovery`.

    Returns
    -------
    Discovery or None
    """
    say = log if log is not None else print
    if any(not _last_resort(settings, s.effect) for s in first.steps):
        res = first.final.residuals
        if res.is_white():
            return None
        say(f"discovery: the accepted effects leave innovations that are not white (whiteness "
            f"{res.whiteness:.4g}, χ²({res.whiteness_dof:g}) expected): a law is sought beside "
            f"the library")
    values = dict(settings.fixed)
    names = list(ports) if ports else [n for n, el in graph.elements.items()
                                       if isinstance(el, (One, Zero))]
    outs = [n for n in graph.sensors if n in record] if sensors is None else list(sensors)
    found = []
    opts = reconstruction or reconstruction_options(settings)
    initial = getattr(first, "initial", None)
    if opts.noise is None and initial is not None and initial.noise_estimates:
        # the loop's estimated noise levels, where the record declares none
        opts = replace(opts, noise=dict(initial.noise_estimates))
    for port, at_sensor in [(n, False) for n in names] + [(n, True) for n in outs]:
        where = f"the output '{port}'" if at_sensor else f"'{port}'"
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            try:
                found.append(discover_effect(graph, record, port, params=values,
                                             sensor=at_sensor, reconstruction=opts,
                                             discovery=discovery))
            except BondGraphError as exc:      # a port the filter cannot serve: skip it
                say(f"discovery at {where} skipped: {str(exc).splitlines()[0]}")
        note = warnings_note(caught)
        if note:
            say(f"  discovery at {where}: {note}")
    found = sorted((d for d in found if d.effect is not None),
                   key=lambda d: (d.law.kind == "output", -d.gain))
    if not found:
        say("discovery: no port gave a law")
        return None
    best = found[0]
    best.alternatives = law_alternatives(graph, found, values, discovery)
    say(best.summary())
    for alt in best.alternatives:
        say(f"beside it, {alt.effect.name}: {alt.passivity.law.readable()}")
    return best


def warnings_note(caught: list) -> str:
    """One line for the warnings ``caught`` (``warnings.WarningMessage``)
    while a port's law was sought (a smoother that overflows at a trial
    noise intensity, scikit-learn's orthogonal matching pursuit stopping
    on a dependent dictionary): how many, of which kinds, the first
    message; "" when there were none. Discovery tries every port, and
    those warnings, printed as they came, buried its result on a user's
    oven graph (twenty lines of numpy and scikit-learn)."""
    if not caught:
        return ""
    kinds = sorted({w.category.__name__ for w in caught})
    first = str(caught[0].message).splitlines()[0]
    return (f"{len(caught)} numerical warning(s) while reconstructing and regressing "
            f"({', '.join(kinds)}; first: {first})")


def law_alternatives(graph, found: list, params: dict,
                     discovery: DiscoverOptions | None = None) -> list:
    """The laws put beside the best port's (``found[0]``) in the loop: each
    port's sparse alternative (:func:`sparse_alternative`) and the other
    ports' laws, by decreasing reconstruction gain, each effect renamed
    ``discovered_<k>`` (k = 2, 3, ...), at most :data:`MAX_LAWS` junction
    laws, then the threshold laws of the first :data:`MAX_THRESHOLD_LAWS`
    junctions (:func:`threshold_alternative`), then at most
    :data:`MAX_OUTPUT_LAWS` laws at sensors' outputs.

    The sensors' laws come after the junctions' whatever their gain: an
    offset random walk at an output can follow any missing dynamics seen
    there (on the saturating damper of ``bench/discovery.py`` the position
    sensor's walk gains 1.0e4 nats with a linear gain-and-input law, a
    look-alike), so its gain does not rank it against a junction's; the
    loop's likelihood ratio decides among all.

    Why: the port of largest reconstruction gain need not be the port of the
    missing law (a random walk at a two-tank orifice's effort moves both
    tanks and gains more than the true outflow's at one tank), and the
    cross-validation on the smoothed d̂ may keep look-alike terms whose
    refit the loop refuses (four odd terms whose sum leaves the spring
    non-convex near rest, where −k5·x⁵ − k3·x³ was within two standard
    errors): the loop's likelihood ratio on the record, with every
    parameter refitted, is the better judge, and its accept rule is
    unchanged.

    Parameters
    ----------
    graph : BondGraph
        The declared graph.
    found : list of Discovery
        One per port with a passive law: the junctions' by decreasing gain,
        then the sensors' (:func:`discovered_effect`).
    params : dict
        The declared values of the reconstruction.
    discovery : DiscoverOptions, optional

    Returns
    -------
    list of Discovery
        Each with its own effect name.
    """
    out, seen = {False: [], True: [], "threshold": []}, set()
    for k, d in enumerate(found):
        sparse = sparse_alternative(graph, d, params, discovery)
        for cand in ([d] if k else []) + ([sparse] if sparse is not None else []):
            key = (cand.law.port, cand.law.kind,
                   tuple(tm.name for tm in cand.passivity.law.terms))
            if key in seen or cand.effect is None:
                continue
            seen.add(key)
            out[cand.law.kind == "output"].append(cand)
        seen.add((d.law.port, d.law.kind, tuple(tm.name for tm in d.passivity.law.terms)))
        dz = threshold_alternative(graph, d, params, discovery)
        if dz is not None:
            out["threshold"].append(dz)
    first = int(found[0].law.kind == "output")
    out = (out[False][:MAX_LAWS - 1 + first] + out["threshold"][:MAX_THRESHOLD_LAWS]
           + out[True][:MAX_OUTPUT_LAWS - first])
    name = found[0].effect.name
    return [replace(d, effect=effect_for(d.passivity.law, f"{name}_{i + 2}"))
            for i, d in enumerate(out)]


def threshold_alternative(graph, disc: Discovery, params: dict,
                          discovery: DiscoverOptions | None = None) -> Discovery | None:
    """The law of one dead-zone term of the port's own variable
    (:func:`~bondgraph.diagnose.discover.law.threshold_law`) on the same
    reconstruction as ``disc``, if the passivity check keeps it (a
    junction's law only; None at a sensor's output, or when no term is
    left).

    Parameters
    ----------
    graph : BondGraph
        The declared graph.
    disc : Discovery
    params : dict
        The declared values of the reconstruction.
    discovery : DiscoverOptions, optional

    Returns
    -------
    Discovery or None
    """
    rec = disc.reconstruction
    if disc.law.kind == "output":
        return None
    law = threshold_law(rec, options=discovery)
    return None if law is None else _alternative(graph, disc, law, params, same_ok=True)


def sparse_alternative(graph, disc: Discovery, params: dict,
                       discovery: DiscoverOptions | None = None) -> Discovery | None:
    """The law of at most :data:`SPARSE_TERMS` terms discovered on the same
    reconstruction as ``disc`` (:func:`~bondgraph.diagnose.discover.law.discover_law`
    with ``max_terms`` = 2, its passive terms kept), or None when it keeps
    no term or equals ``disc``'s law.

    Parameters
    ----------
    graph : BondGraph
        The declared graph.
    disc : Discovery
    params : dict
        The declared values of the reconstruction.
    discovery : DiscoverOptions, optional

    Returns
    -------
    Discovery or None
    """
    opts = discovery or DiscoverOptions()
    if opts.max_terms <= SPARSE_TERMS or len(disc.law.terms) <= SPARSE_TERMS:
        return None
    rec = disc.reconstruction
    law = discover_law(rec, options=replace(opts, max_terms=SPARSE_TERMS))
    return _alternative(graph, disc, law, params, same_ok=False)


def _alternative(graph, disc: Discovery, law, params: dict, same_ok: bool) -> Discovery | None:
    """``law`` (found on ``disc``'s reconstruction) as a Discovery of its
    own, its passive terms kept (:func:`make_passive`); None when no term
    is left, or (``same_ok`` False) when its terms are ``disc``'s."""
    rec = disc.reconstruction
    rep = make_passive(law, graph, rec.variables, params=params, t=rec.t)
    if not rep.law.terms or (not same_ok and [tm.name for tm in rep.law.terms]
                             == [tm.name for tm in disc.passivity.law.terms]):
        return None
    eff = effect_for(rep.law, disc.effect.name if disc.effect else "discovered")
    return Discovery(rec, law, rep, eff, disc.gain, eff.placement(graph))


def discovery_plot(disc: Discovery, result=None):
    """What the report shows of ``disc`` (:class:`~bondgraph.diagnose.result.DiscoveryPlot`):
    d̂(t) with its std and the kept law on the port's variables, at the
    coefficients the loop's ``result`` refitted when it accepted the law
    (with their Cramér-Rao std), else as discovered.

    Parameters
    ----------
    disc : Discovery
    result : LoopResult, optional
        The loop run with the discovered effect.

    Returns
    -------
    DiscoveryPlot
    """
    from bondgraph.diagnose.result import DiscoveryPlot

    eff, rec, law = disc.effect, disc.reconstruction, disc.passivity.law
    step = next((s for s in (result.steps if result is not None else [])
                 if eff is not None and s.effect == eff.name), None)
    values = {n: p["estimate"] for n, p in step.parameters.items()} if step else {}
    std = {n: p.get("std") for n, p in step.parameters.items()} if step else {}
    std = {n: v for n, v in std.items() if v is not None}
    tgt = eff.target() if eff is not None else Target("junction", law.port)
    tau = values.get(eff.pname(tgt, "tau")) if eff is not None else None
    terms = [replace(tm, coef=float(values.get(eff.pname(tgt, f"c{k}"), tm.coef)),
                     memory=tm.memory if tm.memory is None or tau is None
                     else replace(tm.memory, tau=float(tau)))
             for k, tm in enumerate(law.terms)] if eff is not None else []
    refit = replace(law, terms=terms)
    text = eff.readable(values, std) if eff is not None else law.readable()
    placed = [f"{pl.part}: {pl.element} ({pl.why})" for pl in disc.placement]
    return DiscoveryPlot(law.port, law.kind, law.unit, np.asarray(rec.t, float),
                         np.asarray(rec.d, float), np.asarray(rec.d_std, float),
                         np.asarray(refit.evaluate(rec.variables, rec.t), float), text,
                         "\n".join([disc.passivity.summary()] + placed), step is not None)


def _last_resort(settings, effect_name: str) -> bool:
    for e in settings.effects:
        if e.name == effect_name:
            return bool(getattr(e, "last_resort", False))
    return False

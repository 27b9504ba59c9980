"""The probe model of the score test: every additive effect at every target,
at its neutral value β = 0, in one graph.

Each additive effect names its probe site (:meth:`Effect.probe_site`); the
terms Σ β_k b_k of all effects at one site are installed together:

* ``junction``: one modulated effort source per 1-junction (effort = Σ β b);
* ``sensor``: added to the sensor's expression;
* ``source``: added to the source's value;
* ``resistor``: added to the R's law in its causal form
  (:func:`bondgraph.diagnose.effects.laws.add_to_r_law`);
* ``storage``: added to the C's effort law (an I's flow law), its integral
  to the energy;
* ``beside``: a modulated effort source on a 1-junction spliced into a C's
  bond (:func:`bondgraph.diagnose.effects.storage.install_beside`).
"""

from __future__ import annotations

from dataclasses import dataclass

import sympy as sp

from bondgraph.core.graph import BondGraph
from bondgraph.diagnose.effects.base import Scales, Target
from bondgraph.diagnose.effects.laws import add_to_r_law
from bondgraph.diagnose.effects.storage import (
    add_to_storage_law,
    install_beside,
    storage_variable,
)
from bondgraph.errors import GraphError


@dataclass
class ProbeColumn:
    """One probe parameter: effect, target, index of its basis function."""

    param: str
    effect: str
    target: Target
    k: int
    basis: sp.Expr


def probe_graph(graph: BondGraph, effects, scales: Scales,
                exclude: set | None = None) -> tuple[BondGraph, list[ProbeColumn]]:
    """A copy of ``graph`` with every additive effect at every target added
    as Σ β_k b_k with β = 0 (neutral), one parameter per basis function.

    Parameters
    ----------
    graph : BondGraph
    effects : sequence of Effect
        Only the additive ones are probed.
    scales : Scales
        Data scales of the shape constants.
    exclude : set of str, optional
        Target names to skip (e.g. on a causal path the model cannot be
        built with).

    Returns
    -------
    (BondGraph, list of ProbeColumn)
    """
    g = graph.copy(f"{graph.name}__probe")
    cols: list[ProbeColumn] = []
    per_site: dict[tuple[str, str], list] = {}
    for eff in effects:
        if not eff.additive:
            continue
        for tgt in eff.targets(graph):
            if eff.present(graph, tgt) or tgt.name in (exclude or ()):
                continue
            bases = eff.basis(g, tgt, scales)
            site = eff.probe_site(g, tgt)
            for k, b in enumerate(bases):
                pname = f"probe.{eff.name}.{tgt.tag}.{k}"
                p = g.param(pname, 0.0, "", (-1e12, 1e12), f"probe of {eff.title} at {tgt}")
                cols.append(ProbeColumn(pname, eff.name, tgt, k, b))
                per_site.setdefault(site, []).append(p * b)
    for (kind, name), terms in per_site.items():
        install_probe(g, kind, name, sp.Add(*terms))
    return g, cols


def install_probe(g: BondGraph, kind: str, name: str, term: sp.Expr) -> None:
    """Add ``term`` at the probe site ``(kind, name)`` of ``g`` (in place).

    Raises
    ------
    GraphError
        Unknown site kind.
    """
    if kind == "junction":
        j = g.element(name)
        g.connect(g.MSe(f"probe.{j.name}", term), j)
    elif kind == "sensor":
        g.sensors[name].expr = g.sensors[name].expr + term
    elif kind == "source":
        src = g.element(name)
        src.value = src.value + term
        src.modulated = True
    elif kind == "resistor":
        add_to_r_law(g, g.element(name), term)
    elif kind == "storage":
        el = g.element(name)
        add_to_storage_law(el, term, sp.integrate(term, storage_variable(el)))
    elif kind == "beside":
        install_beside(g, g.element(name), f"probe.{name}.beside", term)
    else:
        raise GraphError(f"unknown probe site kind '{kind}' (of '{name}')")

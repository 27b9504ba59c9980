"""Drawing a bond graph with its causal strokes (matplotlib + networkx layout).

Bonds are drawn as lines with a half-arrow at the head (positive power
direction) and a short perpendicular bar, the causal stroke, at the end that
receives effort.
"""

from __future__ import annotations

from pathlib import Path

import networkx as nx
import numpy as np

from bondgraph.core.causality import assign_causality
from bondgraph.core.graph import BondGraph
from bondgraph.report.plots import pyplot


#: colour of highlighted elements and bonds (:func:`draw` ``highlight``)
HIGHLIGHT = "tab:green"


def draw(graph: BondGraph, path: str | Path | None = None, *, causality=None, ax=None,
         seed: int = 1, title: str | None = None, highlight=(), positions: dict | None = None):
    """Draw ``graph`` with half-arrows and causal strokes.

    Parameters
    ----------
    graph : BondGraph
    path : str or Path, optional
        Write a PNG (or any format matplotlib knows from the suffix).
    causality : Causality, optional
        SCAP result; computed if omitted (if causality fails, bonds are drawn
        without strokes and the error is shown in the title).
    ax : matplotlib Axes, optional
    seed : int
        Layout seed (deterministic pictures).
    title : str, optional
        The title (default: the graph's name and what the marks mean).
    highlight : iterable of str
        Names of elements and bonds drawn in :data:`HIGHLIGHT` (thick
        bonds, green boxes; e.g. the fragment an effect added).
    positions : dict, optional
        Element name -> (x, y); elements it lacks are laid out
        (:func:`layout`). Pass the layout of a larger graph to draw a
        smaller one in the same places.

    Returns
    -------
    matplotlib.figure.Figure
    """
    plt = pyplot()
    err = None
    if causality is None:
        try:
            causality = assign_causality(graph)
        except Exception as exc:  # draw anyway, show why
            err = str(exc).splitlines()[0]
    pos = layout(graph, seed) if positions is None else _completed(graph, positions, seed)
    marked = set(highlight)
    n = max(len(graph.elements), 1)
    size = min(4 + 0.45 * n, 30)
    if ax is None:
        fig, ax = plt.subplots(figsize=(size, size * 0.75))
    else:
        fig = ax.figure
    lengths = [np.linalg.norm(np.subtract(pos[b.tail.element.name], pos[b.head.element.name]))
               for b in graph.bonds]
    ref = float(np.median(lengths)) if lengths else 1.0
    for b in graph.bonds:
        _draw_bond(ax, b, pos, causality, bar=0.07 * ref, shrink=0.22 * ref,
                   colour=HIGHLIGHT if b.name in marked else "k")
    deriv = set(causality.derivative) if causality is not None else set()
    _draw_elements(ax, graph, pos, deriv, marked)
    ax.set_axis_off()
    t = title or f"{graph.name}: half-arrow = power direction, red bar = causal stroke"
    if deriv:
        t += f"\nderivative causality (eliminated): {', '.join(sorted(deriv))}"
    if err:
        t += f"\ncausality failed: {err}"
    ax.set_title(t, fontsize=9)
    ax.set_aspect("equal", adjustable="datalim")
    fig.tight_layout()
    if path is not None:
        Path(path).parent.mkdir(parents=True, exist_ok=True)
        fig.savefig(path, dpi=110)
    return fig


def layout(graph: BondGraph, seed: int = 1) -> dict:
    """Element name -> (x, y): Kamada-Kawai layout of the element graph,
    else a seeded spring layout.

    Parameters
    ----------
    graph : BondGraph
    seed : int
        Seed of the spring layout.

    Returns
    -------
    dict
    """
    G = nx.Graph()
    for name in graph.elements:
        G.add_node(name)
    for b in graph.bonds:
        G.add_edge(b.tail.element.name, b.head.element.name)
    try:
        return nx.kamada_kawai_layout(G)
    except Exception:
        return nx.spring_layout(G, seed=seed)


def _completed(graph: BondGraph, positions: dict, seed: int) -> dict:
    """``positions`` for the elements it has, the others placed by
    :func:`layout`."""
    if all(name in positions for name in graph.elements):
        return positions
    return {**layout(graph, seed), **{k: v for k, v in positions.items()
                                      if k in graph.elements}}


def _draw_bond(ax, b, pos: dict, causality, *, bar: float, shrink: float,
               colour: str = "k") -> None:
    """A bond: a line shortened by ``shrink`` at both ends, a half-arrow at the
    head, and the causal stroke (a red bar) at the end that receives effort."""
    p0 = np.array(pos[b.tail.element.name])
    p1 = np.array(pos[b.head.element.name])
    d = p1 - p0
    L = np.linalg.norm(d) or 1.0
    u = d / L
    a = p0 + u * shrink
    c = p1 - u * shrink
    lw = 1.2 if colour == "k" else 2.6
    ax.plot([a[0], c[0]], [a[1], c[1]], color=colour, lw=lw, zorder=1)
    # half-arrow at head
    perp = np.array([-u[1], u[0]])
    tip = c
    barb = c - u * 1.6 * bar + perp * 1.1 * bar
    ax.plot([tip[0], barb[0]], [tip[1], barb[1]], color=colour, lw=lw, zorder=1)
    if causality is not None:
        end = causality.stroke[b.name]
        q = c if end == b.head.element.name else a
        s0, s1 = q + perp * 1.2 * bar, q - perp * 1.2 * bar
        ax.plot([s0[0], s1[0]], [s0[1], s1[1]], color="tab:red", lw=2.2, zorder=2)


def _draw_elements(ax, graph: BondGraph, pos: dict, deriv: set, marked=frozenset()) -> None:
    """Element labels in boxes: junctions blue, storages in derivative
    causality red, the others white; ``marked`` ones green with a thick
    green edge."""
    for name, el in graph.elements.items():
        x, y = pos[name]
        label = el.kind if el.kind in ("0", "1") else f"{el.kind}:{name}"
        color = "#fde2e2" if name in deriv else ("#e8f0fe" if el.kind in ("0", "1") else "white")
        edge, lw = (HIGHLIGHT, 1.8) if name in marked else ("0.5", 0.6)
        if name in marked:
            color = "#d6f5d6"
        ax.text(x, y, label, ha="center", va="center", fontsize=8, zorder=3,
                bbox=dict(boxstyle="round,pad=0.25", fc=color, ec=edge, lw=lw))

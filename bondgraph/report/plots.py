"""PNG plots of records and simulations (matplotlib, Agg canvas, no pyplot).

:func:`plot_record` draws one figure per group of columns — states, inputs,
outputs (measurements) — with one axis per column labelled ``name [unit]``
against ``t [s]``. Given a second record (``simulated=``), its columns of the
same names are drawn over the first: measured vs simulated.

CLI: ``bondgraph plot RECORD.csv [-o DIR] [--simulated SIM.csv] [--model NAME]``.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from bondgraph.data.binding import STATE_PREFIX
from bondgraph.data.records import Experiment
from bondgraph.errors import DataError
from bondgraph.numerics.model import Model
from bondgraph.numerics.simulate import SimResult

if TYPE_CHECKING:   # matplotlib is imported where a plot is drawn (~0.8 s of the start)
    from matplotlib.figure import Figure


def pyplot():
    """``matplotlib.pyplot`` on the non-interactive Agg backend (files only; no
    display needed)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


#: group order and titles
GROUPS = (("state", "states"), ("input", "inputs"), ("output", "outputs"),
          ("other", "other signals"))


def _as_experiment(obj: Any):
    """Experiment from a path, an Experiment or a SimResult (+ whether measured)."""
    if isinstance(obj, Experiment):
        return obj, "solver_stats" not in obj.meta
    if isinstance(obj, SimResult):
        return Experiment.from_simulation(obj), False
    if isinstance(obj, (str, Path)):
        exp = Experiment.load(obj)
        return exp, "solver_stats" not in exp.meta
    raise DataError(f"cannot plot a {type(obj).__name__}; give a CSV path, an Experiment or a "
                    f"SimResult")


def _roles(exp, model) -> dict[str, str]:
    """Role of every column: sidecar role, else from the model, else 'other'."""
    known = exp.roles
    mdl = model
    if mdl is None and exp.model_name:
        try:
            mdl = Model.load(exp.model_name)
        except Exception:  # the record's model need not be generated here
            mdl = None
    out = {}
    for c, r in known.items():
        if r is None:
            if c.startswith(STATE_PREFIX):
                r = "state"
            elif mdl is not None and c in mdl.inputs:
                r = "input"
            elif mdl is not None and c in mdl.outputs:
                r = "output"
            else:
                r = "other"
        out[c] = r if r in ("state", "input", "output") else "other"
    return out


def _label(name: str, unit: str | None) -> str:
    return f"{name} [{unit}]" if unit not in (None, "") else name


def _safe(name: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", name).strip("_") or "record"


def plot_record(record, out_dir: str | Path, *, simulated=None, model=None,
                prefix: str | None = None, max_per_figure: int = 8, dpi: int = 110,
                max_points: int = 20000) -> list[Path]:
    """Plot a record to PNG files, one figure per group of columns.

    Parameters
    ----------
    record : str, Path, Experiment or SimResult
        A CSV record (with its sidecar), an experiment or a simulation.
    out_dir : str or Path
        Directory for the PNGs (created).
    simulated : str, Path, Experiment or SimResult, optional
        A second record drawn over ``record`` (columns of the same names):
        measured (markers or thin line) vs simulated (line).
    model : Model or str, optional
        Classifies columns the sidecar gives no role (default: the record's
        ``meta["model"]`` if it is generated here).
    prefix : str, optional
        File-name prefix (default: the record name).
    max_per_figure : int
        Axes per figure; larger groups are split over numbered files.
    dpi : int
    max_points : int
        Longer records are decimated (every k-th sample) for drawing.

    Returns
    -------
    list of Path
        The PNG files written (``<prefix>_<group>[_<k>].png``).

    Raises
    ------
    DataError
        Unreadable record, or an object that is not a record.
    """
    if isinstance(model, str):
        model = Model.load(model)
    exp, measured = _as_experiment(record)
    sim = _as_experiment(simulated)[0] if simulated is not None else None
    roles = _roles(exp, model)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    prefix = _safe(prefix or exp.name)
    paths: list[Path] = []
    for role, title in GROUPS:
        cols = [c for c, r in roles.items() if r == role]
        if not cols:
            continue
        chunks = [cols[i:i + max_per_figure] for i in range(0, len(cols), max_per_figure)]
        for k, chunk in enumerate(chunks):
            group_title = ("measurements" if (role == "output" and measured) else title)
            suptitle = (f"{exp.name}: {group_title}"
                        + (f" ({k + 1}/{len(chunks)})" if len(chunks) > 1 else ""))
            fig = _group_figure(exp, sim, chunk, role, measured, suptitle, dpi, max_points)
            suffix = f"_{k + 1}" if len(chunks) > 1 else ""
            path = out_dir / f"{prefix}_{title.split()[0]}{suffix}.png"
            fig.savefig(path)
            paths.append(path)
    if not paths:
        raise DataError(f"record '{exp.name}' has no columns to plot", path=exp._where())
    return paths


def _group_figure(exp, sim, chunk: list[str], role: str, measured: bool, suptitle: str,
                  dpi: int, max_points: int) -> Figure:
    """One figure (Agg canvas) with an axis per column of ``chunk`` against t;
    the simulated record's column of the same name is drawn over it."""
    n = len(chunk)
    stride = max(1, int(np.ceil(len(exp) / max_points)))
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(9.0, 1.9 * n + 0.9), dpi=dpi, layout="constrained")
    FigureCanvasAgg(fig)
    axes = fig.subplots(n, 1, sharex=True, squeeze=False)[:, 0]
    fig.suptitle(suptitle)
    for ax, c in zip(axes, chunk):
        _draw_column(ax, exp, sim, c, role, measured, stride, max_points)
    axes[-1].set_xlabel("t [s]")
    return fig


def _draw_column(ax, exp, sim, c: str, role: str, measured: bool, stride: int,
                 max_points: int) -> None:
    """Column ``c`` (every ``stride``-th sample): markers where it has gaps or
    a simulation to compare with, else a line; the simulation as a red line;
    the number of missing samples in the title."""
    v = exp.columns[c][::stride]
    tt = exp.t[::stride]
    name = c[len("state."):] if c.startswith("state.") else c
    has_sim = sim is not None and c in sim.columns
    gaps = np.isnan(v).any()
    if has_sim or gaps:
        ax.plot(tt, v, ".", ms=2.0, color="C0",
                label=("measured" if measured and role == "output"
                       else "recorded" if measured else exp.name))
    else:
        ax.plot(tt, v, "-", lw=1.0, color="C0")
    if has_sim:
        s_stride = max(1, int(np.ceil(len(sim) / max_points)))
        ax.plot(sim.t[::s_stride], sim.columns[c][::s_stride], "-", lw=1.2,
                color="C3", label="simulated")
        ax.legend(loc="best", fontsize="small")
    ax.set_ylabel(_label(name, exp.units.get(c)))
    ax.grid(True, alpha=0.3)
    if gaps:
        ax.set_title(f"{int(np.isnan(exp.columns[c]).sum())} missing samples",
                     fontsize="small", loc="right")


def plot_comparison(comp, path: str | Path, *, before=None, dpi: int = 110,
                    max_points: int = 20000) -> Path:
    """One PNG of a model's free run against a record
    (:class:`bondgraph.diagnose.compare.Comparison`): per output, the
    measured samples and the simulated line (the samples before the judged
    window shaded), and below it the error, titled with the RMS error,
    the NRMSE and MATLAB ``compare``'s NRMSE fit.

    Parameters
    ----------
    comp : Comparison
    path : str or Path
        The PNG file (its folder is created).
    before : Comparison, optional
        Another model's comparison on the same record (a loop's declared
        fit), drawn grey and dashed with its error.
    dpi, max_points : int
        Resolution; longer records are decimated (every k-th sample).

    Returns
    -------
    Path
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    n = len(comp.outputs)
    stride = max(1, int(np.ceil(comp.t.size / max_points)))
    t = comp.t[::stride]
    fig = Figure(figsize=(9.0, 2.6 * n + 0.9), dpi=dpi, layout="constrained")
    FigureCanvasAgg(fig)
    axes = fig.subplots(2 * n, 1, sharex=True, squeeze=False,
                        gridspec_kw={"height_ratios": [3, 1] * n})[:, 0]
    fig.suptitle(f"{comp.record}: free run against the record (mean NRMSE "
                 + (f"{before.metric:.4g} before, {comp.metric:.4g} after)" if before is not None
                    else f"{comp.metric:.4g})"))
    for j, (o, unit) in enumerate(zip(comp.outputs, comp.units)):
        ax, ae = axes[2 * j], axes[2 * j + 1]
        y = comp.y[::stride, j]
        ax.plot(t, y, ".", ms=2.0, color="C0", label="measured")
        if before is not None and before.sim_y is not None:
            b = before.sim_y[::stride, j]
            ax.plot(t, b, "--", lw=1.0, color="0.45",
                    label=f"before (RMS {before.rms[j]:.4g})")
            ae.plot(t, y - b, "--", lw=0.8, color="0.45")
        if comp.sim_y is not None:
            s = comp.sim_y[::stride, j]
            ax.plot(t, s, "-", lw=1.2, color="C3", label="simulated" if before is None
                    else "after")
            ae.plot(t, y - s, "-", lw=0.8, color="C2")
        if comp.judged_from:
            for a in (ax, ae):
                a.axvspan(comp.t[0], comp.t[comp.judged_from - 1], color="0.85", lw=0,
                          label="sets the start" if a is ax else None)
        ax.set_title("not in the record" if np.isnan(comp.rms[j]) else
                     f"RMS error {comp.rms[j]:.4g}{' ' + unit if unit else ''}, "
                     f"NRMSE {comp.nrmse[j]:.4g}, "
                     f"fit {comp.fit_percent[j]:.1f} %", fontsize="small", loc="right")
        ax.set_ylabel(_label(o, unit))
        ae.set_ylabel("error")
        for a in (ax, ae):
            a.grid(True, alpha=0.3)
        ax.legend(loc="best", fontsize="small")
    axes[-1].set_xlabel("t [s]")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    return path

"""Options shared by the commands, declared and parsed in one place.

Every command that takes a model accepts a registered name,
``module:function`` or ``path/to/file.py:function`` (the current directory is
on the import path); ``--fixed``, ``--x0``, ``--p0-rel``, ``--method``,
``--substeps`` and ``--hold`` mean the same in every command.
"""

from __future__ import annotations

import argparse
from typing import Iterable

from bondgraph.errors import OptionError

MODEL_HELP = ("model: a registered name (`bondgraph models`), module:function or "
              "path/to/file.py:function returning a BondGraph (modules are imported from "
              "the current directory too)")


def parse_pairs(items: str | Iterable[str] | None, option: str) -> dict[str, float]:
    """``name=value`` pairs of an option, comma-separated or repeated.

    Parameters
    ----------
    items : str or iterable of str or None
        ``"a=1,b=2"`` or ``["a=1", "b=2"]``.
    option : str
        The option's name for messages (``"--fixed"``).

    Returns
    -------
    dict
        ``name -> float``.

    Raises
    ------
    OptionError
        An item without ``=`` or a value that is not a number.
    """
    if not items:
        return {}
    if isinstance(items, str):
        items = [items]
    out: dict[str, float] = {}
    for chunk in items:
        for item in chunk.split(","):
            if not item.strip():
                continue
            name, sep, val = item.partition("=")
            if not sep:
                raise OptionError(f"{option} expects name=value pairs separated by commas, got "
                                  f"'{item}'")
            try:
                out[name.strip()] = float(val)
            except ValueError:
                raise OptionError(f"{option}: value of '{name.strip()}' is not a number: "
                                  f"'{val}'") from None
    return out


def parse_names(text: str | None, option: str) -> list[str]:
    """Comma-separated names (``a,b,c``).

    Raises
    ------
    OptionError
        The option was given but holds no name.
    """
    if text is None:
        return []
    names = [s.strip() for s in text.split(",") if s.strip()]
    if not names:
        raise OptionError(f"{option}: no names given")
    return names


def parse_params(text: str, model=None) -> list[str]:
    """Parameters of ``--params``: ``a,b,c`` or ``recommended:<sensitivity.json>``
    (the set recommended by :func:`bondgraph.sensitivity.analysis.recommended_params`).

    Raises
    ------
    OptionError
        Empty list.
    SensitivityError
        Missing or malformed sensitivity file.
    ModelError
        A recommended parameter the model does not have.
    """
    text = (text or "").strip()
    if text.startswith("recommended:"):
        from bondgraph.sensitivity.analysis import recommended_params

        return recommended_params(text[len("recommended:"):], model)
    return parse_names(text, "--params")


# ------------------------------------------------------------ declarations
def add_model(p: argparse.ArgumentParser, *, positional: bool = False,
              required: bool = True) -> None:
    """``--model`` (or a positional ``model``)."""
    if positional:
        p.add_argument("model", help=MODEL_HELP)
    else:
        p.add_argument("--model", required=required, help=MODEL_HELP)


def add_data(p: argparse.ArgumentParser, *, required: bool = True) -> None:
    """``--data``: the record."""
    p.add_argument("--data", required=required,
                   help="record CSV with optional JSON sidecar (docs/data_format.md)")


def add_fixed(p: argparse.ArgumentParser) -> None:
    """``--fixed name=value,...``."""
    p.add_argument("--fixed", default=None,
                   help="name=value,... parameters held at given values")


def add_initial_state(p: argparse.ArgumentParser) -> None:
    """``--x0`` and ``--p0-rel``: the UKF prior of the initial state."""
    p.add_argument("--x0", default=None,
                   help="name=value,... initial states (default: the record's state columns or "
                        "sidecar x0 for states the model has, else the model's X0)")
    p.add_argument("--p0-rel", type=float, default=0.05,
                   help="prior std of each initial state, relative to max(|x0|, 1)")


def add_discretisation(p: argparse.ArgumentParser, *, hold_default: str = "zoh") -> None:
    """``--method``, ``--substeps``, ``--hold``: the UKF's transition."""
    p.add_argument("--method", choices=("ros2", "rk4"), default="ros2",
                   help="UKF discretisation of the state equations")
    p.add_argument("--substeps", type=int, default=1, help="integrator steps per sample")
    p.add_argument("--hold", choices=("zoh", "mean", "linear"), default=hold_default,
                   help="input over a sample interval: u_k (zoh), (u_k + u_k+1)/2 (mean), or "
                        "the first-order hold u_k + s (u_k+1 - u_k) (linear; for inputs sampled "
                        "from a continuous signal)")


def add_quiet(p: argparse.ArgumentParser) -> None:
    """``--quiet``."""
    p.add_argument("--quiet", action="store_true", help="no progress output")


def load_model(spec: str):
    """The :class:`~bondgraph.numerics.model.Model` named by ``--model``
    (:meth:`~bondgraph.numerics.model.Model.from_spec`)."""
    from bondgraph.numerics.model import Model

    return Model.from_spec(spec)


def initial_state(model, experiment, x0_text: str | None):
    """The initial state of a record (:meth:`~bondgraph.data.records.Experiment.initial_state`)
    with the ``--x0`` overrides applied.

    Raises
    ------
    OptionError
        Malformed ``--x0``.
    ModelError
        A state the model does not have.
    """
    x0 = experiment.initial_state(model)
    for k, v in parse_pairs(x0_text, "--x0").items():
        x0[model.state_index(k)] = v
    return x0

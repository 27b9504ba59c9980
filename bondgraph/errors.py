"""One exception hierarchy for the whole toolkit.

Every error the toolkit raises on bad input derives from :class:`BondGraphError`.
Graph errors carry the names of the elements and bonds involved (``elements``,
``bonds`` attributes) so that tools and tests can point at the culprit, and
their message names them too.

::

    BondGraphError
    ├── GraphError                 malformed declaration (validate())
    │   ├── InvalidNameError       an empty name, or one with white space
    │   ├── ParameterError         default not a number / outside its bounds, bad bounds
    │   ├── ElementError           an element's law missing or given twice, a bad domain
    │   ├── DuplicateNameError
    │   ├── ConnectionError
    │   ├── DanglingPortError
    │   ├── JunctionError
    │   ├── PortCountError
    │   ├── UndeclaredSymbolError
    │   └── UnitMismatchError
    ├── CausalityError             SCAP could not give an explicit ODE
    │   ├── CausalConflictError
    │   ├── AlgebraicLoopError
    │   └── DerivativeCausalityError
    ├── CodegenError
    │   └── StaleGeneratedCodeError
    ├── ModelError                 loading / using a generated model
    ├── DataError                  experiment files (line and column named)
    ├── NumericalError             diverging simulation or filter
    │   ├── FilterDivergenceError
    │   └── EstimationError        no parameter set of an estimation had a finite NLL
    ├── OptionError                invalid option value (also a ValueError)
    │   ├── UsageError             a command line argparse rejects
    │   └── CheckpointError        a missing checkpoint, or one of another problem
    ├── SensitivityError           invalid sensitivity options (also a ValueError)
    ├── ExportError                FMU export or linearisation (no C compiler, a failed
    │                              compile, unknown parameters, no equilibrium)
    └── OutputError                an output folder that is not empty or not writable

    BondGraphWarning (UserWarning)
    ├── IdentifiabilityWarning     Hessian not positive definite, estimate on a bound
    └── ColumnWarning              record columns that match no model name

The command line (:mod:`bondgraph.cli.main`) turns every :class:`BondGraphError`
into exit code 2 with its message.
"""

from __future__ import annotations

from typing import Iterable, Sequence


class BondGraphError(Exception):
    """Base class of every error raised by the toolkit.

    Parameters
    ----------
    message : str
        Human-readable message; it names the culprit.
    elements : sequence of str, optional
        Names of the elements involved.
    bonds : sequence of str, optional
        Names of the bonds involved.
    hint : str, optional
        A suggested remedy, appended to the message.
    """

    def __init__(self, message: str, *, elements: Iterable[str] = (),
                 bonds: Iterable[str] = (), hint: str | None = None):
        self.elements: tuple[str, ...] = tuple(elements)
        self.bonds: tuple[str, ...] = tuple(bonds)
        self.hint = hint
        text = message
        if hint:
            text = f"{message}\n  Remedy: {hint}"
        super().__init__(text)


class GraphError(BondGraphError):
    """A malformed graph declaration (raised by ``BondGraph.validate``)."""


class InvalidNameError(GraphError, ValueError):
    """A name that is not a non-empty string without white space."""


class ParameterError(GraphError, ValueError):
    """A parameter declaration that cannot be estimated or simulated: a
    default that is not a finite number, bounds that are not a finite
    interval (reversed, NaN), or a default outside its bounds."""


class ElementError(GraphError, ValueError):
    """An element declared wrongly: none or several of its alternative laws
    (``inertance=`` / ``flow=``), an unknown junction domain, a field without
    ports or with the wrong number of expressions."""


class DuplicateNameError(GraphError):
    """Two elements, parameters, inputs, sensors or states share a name."""


class ConnectionError(GraphError):  # noqa: A001 - deliberate, namespaced by the package
    """A bond that cannot be made (port in use, two-port without a port, ...)."""


class DanglingPortError(GraphError):
    """An element port without a bond."""


class JunctionError(GraphError):
    """A junction with fewer than two bonds."""


class PortCountError(GraphError):
    """A two-port (TF, GY, MTF, MGY) without exactly one bond per port."""


class UndeclaredSymbolError(GraphError):
    """An expression uses a symbol that the graph does not declare."""


class UnitMismatchError(GraphError):
    """Units that do not fit: effort x flow is not power on a bond, or two
    ends of a bond declare different units."""


class CausalityError(BondGraphError):
    """Causality assignment or equation derivation failed."""


class CausalConflictError(CausalityError):
    """Sources (or a source and the junction structure) impose contradicting
    causality. The message lists the causal path."""


class AlgebraicLoopError(CausalityError):
    """A zero-order causal loop that sympy could not solve. The message lists
    the loop's elements and bonds."""


class DerivativeCausalityError(CausalityError):
    """A storage element in derivative causality that cannot be eliminated
    (non-invertible law, multiport field, higher index)."""


class CodegenError(BondGraphError):
    """Code generation failed."""


class StaleGeneratedCodeError(CodegenError):
    """A module in ``generated/`` differs from what its graph produces."""


class ModelError(BondGraphError):
    """A generated model was used wrongly (unknown name, wrong shape, ...)."""


class DataError(BondGraphError):
    """A bad experiment or data file.

    Parameters
    ----------
    message : str
        What is wrong.
    path : str, optional
        File concerned.
    line : int, optional
        1-based line number in the file (header is line 1).
    column : str, optional
        Column name concerned.
    """

    def __init__(self, message: str, *, path: str | None = None,
                 line: int | None = None, column: str | None = None,
                 hint: str | None = None):
        self.path = path
        self.line = line
        self.column = column
        where = []
        if path is not None:
            where.append(str(path))
        if line is not None:
            where.append(f"line {line}")
        if column is not None:
            where.append(f"column '{column}'")
        prefix = (", ".join(where) + ": ") if where else ""
        super().__init__(prefix + message, hint=hint)


class NumericalError(BondGraphError):
    """A simulation or filter produced non-finite numbers."""


class FilterDivergenceError(NumericalError):
    """The UKF diverged: a non-positive-definite covariance or a non-finite
    state. ``step`` is the sample index, ``reason`` the cause."""

    def __init__(self, message: str, *, step: int | None = None,
                 reason: str | None = None, hint: str | None = None):
        self.step = step
        self.reason = reason
        super().__init__(message, hint=hint)


class SmootherRestartError(NumericalError):
    """The RTS smoother's backward pass diverged and restarted from the
    filter (no process noise through contracting dynamics): there is no
    initial state given the whole record. Expected for such models, not a
    failure of the fit; ``restarts`` is the number of samples it restarted at."""

    def __init__(self, message: str, *, restarts: int = 0, hint: str | None = None):
        self.restarts = restarts
        super().__init__(message, hint=hint)


class EstimationError(NumericalError):
    """An estimation found no parameter set with a finite negative
    log-likelihood: every evaluation failed (the causes are listed)."""


class DeclaredFitError(NumericalError):
    """The loop's fit of the declared model is unusable (a non-finite
    likelihood or free-run error on the record or the validation record):
    the loop stops before it scores or accepts any effect."""


class OptionError(BondGraphError, ValueError):
    """An invalid option value for filtering or estimation (α ≤ 0, unknown
    method, wrong array shape of a noise matrix, ...)."""


class UsageError(OptionError):
    """A command line that argparse rejects (unknown option, missing
    argument, a value of the wrong type or not among the choices)."""


class CheckpointError(OptionError):
    """``--resume`` without a checkpoint, or with a checkpoint written for
    another problem. ``differs`` lists what differs (data, model, parameter
    list, options, ...)."""

    def __init__(self, message: str, *, differs: Iterable[str] = (), hint: str | None = None):
        self.differs: tuple[str, ...] = tuple(differs)
        super().__init__(message, hint=hint)


class ExportError(BondGraphError):
    """An FMU export or a linearisation that cannot be done: no C compiler
    found, a compile that failed (its messages quoted), parameters the model
    does not have, an operating point naming unknown variables, or no
    equilibrium found for the given inputs."""


class OutputError(BondGraphError):
    """An output folder or file that cannot be written: not empty (without
    ``--overwrite``), not writable, or a file where a folder is needed.
    ``path`` is the culprit."""

    def __init__(self, message: str, *, path=None, hint: str | None = None):
        self.path = None if path is None else str(path)
        super().__init__(message, hint=hint)


class SensitivityError(BondGraphError, ValueError):
    """Invalid options of a sensitivity analysis (unknown parameter names, an
    empty parameter list, a malformed recommendation file, ...)."""


class BondGraphWarning(UserWarning):
    """Base class of the toolkit's warnings (the command line prints them as
    ``bondgraph CMD: warning: ...``)."""


class ColumnWarning(BondGraphWarning):
    """Columns of a record that match no input, output or state of the model
    (a misspelt name, e.g. ``xpos`` for ``x``); the message names them and
    the closest model names."""


class IdentifiabilityWarning(BondGraphWarning):
    """The Hessian of the NLL is not positive definite at the estimate: some
    direction of the parameter space is not identified by the record."""


class BackendWarning(UserWarning):
    """The compiled (numba) likelihood could not be used for a model (numba
    missing, a function numba cannot compile, no generated kernels); the
    numpy path, the reference, ran instead. The message names the model and
    the cause."""


def join_names(names: Sequence[str]) -> str:
    """Quote and join names for messages: ``'a', 'b' and 'c'``."""
    quoted = [f"'{n}'" for n in names]
    if len(quoted) <= 1:
        return "".join(quoted)
    return ", ".join(quoted[:-1]) + " and " + quoted[-1]

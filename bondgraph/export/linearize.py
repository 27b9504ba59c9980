"""The linearisation of a model at an operating point: A, B, C, D.

A = ∂f/∂x, B = ∂f/∂u, C = ∂h/∂x, D = ∂h/∂u at (x, u, θ), evaluated by
generated code: the model is derived once and its numpy module generated
in memory with ``dfdx``, ``dhdx`` (the committed generated modules'
functions) and ``dfdu``, ``dhdu`` (:data:`bondgraph.core.codegen.
OPTIONAL_FUNCTIONS`, generated on request only, so that the committed
modules stay as they are), all from the same sympy expressions. States not
given are found as an equilibrium f(x, u, θ) = 0 for the given inputs
(``scipy.optimize.root`` with the generated Jacobian).

The small-signal model about an equilibrium (x*, u*) is
dδx/dt = A δx + B δu, δy = C δx + D δu (Khalil, *Nonlinear Systems*, 3rd
ed., 2002, section 2.3; Franklin, Powell and Emami-Naeini, *Feedback
Control of Dynamic Systems*, section 9.2).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Mapping

import numpy as np
from scipy.optimize import root

from bondgraph.core.causality import STATIC_STATE
from bondgraph.core.domains import laws_at_their_boundary
from bondgraph.core.equations import derive
from bondgraph.core.graph import BondGraph
from bondgraph.errors import BondGraphError, ExportError
from bondgraph.export.params import model_graph
from bondgraph.numerics.model import Model
from bondgraph.numerics.simulate import simulate

#: the generated functions a linearisation evaluates
LINEAR_FUNCTIONS = ("f", "h", "dfdx", "dhdx", "dfdu", "dhdu")


@dataclass(frozen=True)
class Linearization:
    """A, B, C, D of a model at an operating point.

    Attributes
    ----------
    model : str
    A : ndarray (n_x, n_x)
        ∂f/∂x [state units / s per state unit].
    B : ndarray (n_x, n_u)
        ∂f/∂u.
    C : ndarray (n_y, n_x)
        ∂h/∂x.
    D : ndarray (n_y, n_u)
        ∂h/∂u.
    states, inputs, outputs : tuple of str
    x, u, theta : ndarray
        The operating point (model units) and the parameters.
    y : ndarray (n_y,)
        The outputs there.
    equilibrium : bool
        Whether the states were solved from f(x, u, θ) = 0.
    residual : float
        max |f(x, u, θ)| at the point (0 up to round-off at an equilibrium).
    warnings : tuple of str
        What makes the matrices doubtful at this point (a law on the boundary
        of its domain, :func:`boundary_warnings`), one line each.
    """

    model: str
    A: np.ndarray
    B: np.ndarray
    C: np.ndarray
    D: np.ndarray
    states: tuple
    inputs: tuple
    outputs: tuple
    x: np.ndarray
    u: np.ndarray
    theta: np.ndarray
    y: np.ndarray
    equilibrium: bool
    residual: float
    warnings: tuple = ()

    def poles(self) -> np.ndarray:
        """Eigenvalues of A [1/s], shape (n_x,), sorted by real part."""
        ev = np.linalg.eigvals(self.A) if self.A.size else np.zeros(0, complex)
        return ev[np.lexsort((ev.imag, ev.real))]

    def freqresp(self, w) -> np.ndarray:
        """Frequency response G(jω) = C (jω I - A)⁻¹ B + D.

        Parameters
        ----------
        w : array (n_w,)
            Angular frequencies [rad/s].

        Returns
        -------
        ndarray (n_w, n_y, n_u), complex
        """
        w = np.atleast_1d(np.asarray(w, dtype=float))
        eye = np.eye(self.A.shape[0])
        out = np.empty((w.size, self.C.shape[0], self.B.shape[1]), complex)
        for k, wk in enumerate(w):
            out[k] = self.C @ np.linalg.solve(1j * wk * eye - self.A, self.B) + self.D
        return out

    def to_control(self):
        """The linearisation as a ``control.StateSpace`` (python-control),
        with the state, input and output names.

        Raises
        ------
        ExportError
            python-control is not installed (``pip install 'bondgraph-toolkit[control]'``).
        """
        try:
            import control
        except ImportError:
            raise ExportError("python-control is not installed",
                              hint="pip install 'bondgraph-toolkit[control]' (or control)") from None
        return control.ss(self.A, self.B, self.C, self.D, states=list(self.states),
                          inputs=list(self.inputs), outputs=list(self.outputs),
                          name=self.model)

    def save(self, path: str | Path) -> Path:
        """Write ``.npz``: A, B, C, D, states, inputs, outputs, x, u, theta,
        y, equilibrium, residual, model. Returns the path."""
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        with open(path, "wb") as fh:
            np.savez(fh, A=self.A, B=self.B, C=self.C, D=self.D,
                     states=np.array(self.states, dtype=str),
                     inputs=np.array(self.inputs, dtype=str),
                     outputs=np.array(self.outputs, dtype=str), x=self.x, u=self.u,
                     theta=self.theta, y=self.y, equilibrium=self.equilibrium,
                     residual=self.residual, model=self.model)
        return path


def linear_model(model: str | BondGraph, params: Mapping[str, float] | None = None) -> Model:
    """The model with :data:`LINEAR_FUNCTIONS` generated in memory from its graph
    (``params`` as defaults; see :func:`bondgraph.export.params.model_graph`)."""
    return Model.from_graph(model_graph(model, params), functions=LINEAR_FUNCTIONS)


def _split_point(m: Model, at: Mapping[str, float]) -> tuple[dict, dict]:
    """``at`` as (states, inputs) by name.

    Raises
    ------
    ExportError
        A name that is neither a state nor an input, or a non-finite value.
    """
    xs, us = {}, {}
    for name, value in at.items():
        v = float(value)
        if not np.isfinite(v):
            raise ExportError(f"operating point: {name} = {value!r} is not finite")
        if name in m.states:
            xs[name] = v
        elif name in m.inputs:
            us[name] = v
        else:
            raise ExportError(f"operating point: '{name}' is neither a state nor an input of "
                              f"model '{m.name}' (states: {', '.join(m.states)}; inputs: "
                              f"{', '.join(m.inputs) or 'none'})")
    return xs, us


def equilibrium(m: Model, u: np.ndarray, theta: np.ndarray, guess: np.ndarray,
                tol: float = 1e-10) -> np.ndarray:
    """States x with f(x, u, θ) = 0 (``scipy.optimize.root``, Powell's hybrid
    method with the generated Jacobian, then Levenberg-Marquardt), from the
    guess and then from the states free runs with the inputs held reach
    (:func:`_relaxed_starts`).

    Parameters
    ----------
    m : Model
    u : ndarray (n_u,)
    theta : ndarray (n_theta,)
    guess : ndarray (n_x,)
        Start of the search.
    tol : float
        Accepted max |f| relative to the scale of the derivatives at the
        guess (and 1).

    Returns
    -------
    ndarray (n_x,)

    Raises
    ------
    ExportError
        No root found (the largest remaining derivative is named).
    """
    def fun(x):
        return m.f(x[None, :], u[None, :], theta[None, :])[0]

    def jac(x):
        return m.dfdx(x[None, :], u[None, :], theta[None, :])[0]

    scale = 1.0 + float(np.max(np.abs(fun(guess)))) if guess.size else 1.0
    best = guess
    for start in _relaxed_starts(m, u, theta, guess):
        for method in ("hybr", "lm"):
            with np.errstate(all="ignore"):
                sol = root(fun, start, jac=jac, method=method, tol=1e-14)
            r = fun(sol.x)
            if np.all(np.isfinite(r)) and np.max(np.abs(r), initial=0.0) <= tol * scale:
                return sol.x
            best = sol.x if np.all(np.isfinite(r)) else best
    r = fun(best)
    j = int(np.nanargmax(np.abs(r))) if r.size else 0
    raise ExportError(f"no equilibrium of model '{m.name}' found for the given inputs: "
                      f"d{m.states[j]}/dt stays {r[j]:.3g} (scipy.optimize.root)",
                      hint="give every state in --at (an operating point need not be an "
                           "equilibrium), or inputs that admit an equilibrium")


#: horizons [s] of the free runs whose end states restart the equilibrium search
RELAX_HORIZONS = (1.0, 10.0, 100.0, 1e3, 1e4, 1e5, 1e6)


def _relaxed_starts(m: Model, u: np.ndarray, theta: np.ndarray, guess: np.ndarray):
    """``guess``, then the states that a free run from it with the inputs held
    at ``u`` reaches after each of :data:`RELAX_HORIZONS` (LSODA): a stable
    equilibrium attracts them, where a root search from the guess can stall
    (two tanks that start empty, where a square-root outflow law has no slope
    to follow). Stops at the first run that fails."""
    yield guess
    x = guess
    for T in RELAX_HORIZONS:
        try:
            with np.errstate(all="ignore"):
                sim = simulate(m, np.array([0.0, T]), np.repeat(u[None, :], 2, axis=0),
                               x0=x, theta=theta, method="LSODA", rtol=1e-8, atol=1e-10)
        except BondGraphError:
            return
        x = sim.x[-1]
        yield x


def linearize(model: str | BondGraph | Model, at: Mapping[str, float] | None = None, *,
              params: Mapping[str, float] | None = None) -> Linearization:
    """A, B, C, D of a model at an operating point, from its generated
    Jacobians.

    Parameters
    ----------
    model : str, BondGraph or Model
        Registered name, ``module:function``, ``path/to/file.py:function``,
        a graph, or a Model made by :func:`linear_model`.
    at : mapping, optional
        ``name -> value`` of states and inputs (model units). Inputs not
        given take their defaults. When every state is given, that is the
        point; otherwise the states are an equilibrium f(x, u, θ) = 0 for
        the inputs (given states start the search, the others X0).
    params : mapping, optional
        Parameter values (e.g. :func:`bondgraph.export.params.read_params`);
        default the model's defaults.

    Returns
    -------
    Linearization

    Raises
    ------
    ExportError
        Unknown names in ``at`` or ``params``, no equilibrium found, or
        non-finite Jacobians at the point.
    ModelError
        Unknown model reference.
    """
    m = model if isinstance(model, Model) and hasattr(model, "dfdu") else \
        linear_model(model, params)
    xs, us = _split_point(m, dict(at or {}))
    theta = m.theta(params) if isinstance(model, Model) and params else m.theta0.copy()
    u = m.input(us)
    x = m.state(xs)
    solved = len(xs) < m.n_x
    if solved:
        x = equilibrium(m, u, theta, x)
    args = (x[None, :], u[None, :], theta[None, :])
    with np.errstate(all="ignore"):
        mats = {name: np.asarray(getattr(m, name)(*args)[0], dtype=float).reshape(shape)
                for name, shape in (("dfdx", (m.n_x, m.n_x)), ("dfdu", (m.n_x, m.n_u)),
                                    ("dhdx", (m.n_y, m.n_x)), ("dhdu", (m.n_y, m.n_u)))}
        f0 = np.asarray(m.f(*args)[0], dtype=float)
        y0 = np.asarray(m.h(*args)[0], dtype=float)
    for name, M in mats.items():
        if not np.all(np.isfinite(M)):
            raise ExportError(f"the Jacobian {name} of model '{m.name}' is not finite at the "
                              f"operating point (x = {x.tolist()}, u = {u.tolist()})")
    # the inert state a graph without a state of its own is given
    # (registry.with_a_state) is no dynamics of the system: its pole at 0 left out
    keep = [i for i, s in enumerate(m.states) if s != STATIC_STATE]
    A, B, C = mats["dfdx"][np.ix_(keep, keep)], mats["dfdu"][keep], mats["dhdx"][:, keep]
    warn = () if isinstance(model, Model) else boundary_warnings(m, model, params, x, u, theta)
    if solved and not warn:
        warn = continuum_warning([m.states[i] for i in keep], A, x[keep], given=xs)
    return Linearization(model=m.name, A=A, B=B, C=C, D=mats["dhdu"],
                         states=tuple(m.states[i] for i in keep), inputs=tuple(m.inputs),
                         outputs=tuple(m.outputs), x=x[keep], u=u, theta=theta, y=y0,
                         equilibrium=solved,
                         residual=float(np.max(np.abs(f0), initial=0.0)), warnings=warn)


#: A at an equilibrium whose smallest singular value is below this fraction
#: of its largest is singular: the equilibrium is not isolated
#: (:func:`continuum_warning`)
NULL_REL = 1e-10


def continuum_warning(states: list[str], A: np.ndarray, x: np.ndarray,
                      given: Mapping[str, float] | None = None) -> tuple:
    """One line when the Jacobian A (n_x, n_x) at a solved equilibrium is
    singular (its smallest singular value below :data:`NULL_REL` of its
    largest): the equilibria for the inputs then form a continuum (a
    position behind a free mass; a friction state that holds any force
    at rest, balanced by a controller's position error), a pole at 0
    belongs to it, and the point found is where the search from the start
    ended, not one the system picks. The line names the states that move
    along it (components of the null direction at least 1 % of the
    largest) and how to choose the point. Empty otherwise, and when the
    search ended where the user put each of those states (``given``, name
    -> value; ``x`` (n_x,), the equilibrium found).

    Examples: a user's EMPS drive in its position loop with Dahl friction
    and a drive lag, linearised at qg = 0.1 m: the search ended with the
    friction state at 507.6 N (its Fc 3.8 N) and q 0.33 mm short of qg,
    one of the rest states along (q, the lag's state, the friction's)."""
    if A.size == 0:
        return ()
    _, sv, vt = np.linalg.svd(A)
    if not sv[0] > 0 or sv[-1] > NULL_REL * sv[0]:
        return ()
    v = np.abs(vt[-1])
    names = [states[i] for i in np.argsort(-v) if v[i] >= 0.01 * v.max()]
    given = dict(given or {})
    if all(n in given and abs(x[states.index(n)] - given[n]) <= 1e-9 * (1 + abs(given[n]))
           for n in names):
        return ()
    return (f"the equilibrium is not isolated: A is singular (a pole at 0), and states along "
            f"{', '.join(names)} are equilibria for these inputs too; the one above is where the "
            f"search from its start ended. Give every state in --at for the point you mean (the "
            f"search then does not run)",)


def boundary_warnings(m: Model, model, params, x, u, theta) -> tuple:
    """One line per law continued past its domain (:mod:`bondgraph.core.domains`)
    whose base is 0 at the point (x, u, θ) and whose slope is infinite there
    (:func:`~bondgraph.core.domains.laws_at_their_boundary`: |base| within
    1e-9 of the point's largest state or input): the Jacobian there is the
    continuation's, not the law's. Empty when the model continues no law."""
    if not m.domain_notes:
        return ()
    ss = derive(model_graph(model, params))
    syms = list(ss.states) + list(ss.inputs) + list(ss.params)
    scale = max(float(np.max(np.abs(x), initial=0.0)), float(np.max(np.abs(u), initial=0.0)))
    at = laws_at_their_boundary(list(ss.f) + list(ss.h), syms,
                                [*map(float, x), *map(float, u), *map(float, theta)],
                                1e-9 * scale if scale > 0 else 1e-300)
    return tuple(f"{law} sits on the boundary of its domain at this point ({base} = 0), where "
                 f"its slope is infinite; the Jacobian takes the continued law's (0 there), "
                 f"so A, B, C, D do not describe "
                 f"small motions about this point: linearise where {base} > 0 (--at with "
                 f"inputs or states that put it there)" for law, base in at)

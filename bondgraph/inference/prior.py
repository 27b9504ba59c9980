"""The prior of the initial state: its mean and a covariance that follows
each state's own scale.

The spread of a state's prior is relative to that state's scale along the
record, not to ``max(|x0|, 1)``: a small momentum (0.002 kg m/s) next to a
large one (26 000 kg m/s) gets its own spread. The scale of state i is, in
this order (:func:`state_scales`):

1. its deterministic scale, the RMS of the state along a free-run
   simulation of the model with the record's inputs from the prior mean
   (fixed-step, the filter's discretisation), or ``|x0_i|`` if larger;
2. where that is 0 (a state nothing drives, e.g. a road grade that only
   process noise moves): the spread a random walk of the state's process
   noise reaches over the record, ``proc_std_i · sqrt(duration)``;
3. where that is 0 too: the scale the sensors give, std(y_j) / |∂h_j/∂x_i|
   at the prior mean, over the outputs that see the state;
4. else a tiny absolute floor (the state is neither driven nor seen).

The prior covariance (:func:`prior_covariance`) is diagonal with
``(rel · scale_i)²``, except where the record declares a spread: a
sidecar's ``x0_std`` (by state name) is the standard deviation of that
state's prior, its ``x0`` the mean (:meth:`bondgraph.data.records.Experiment.initial_state`).
A state whose initial value nothing gives (no state column, no sidecar
``x0``/``x0_std``, no user value: its mean is the model's X0, a guess) gets
the spread of its whole scale, ``UNKNOWN_REL · scale_i``: the filter then
learns it from the data instead of trusting the guess, and the RTS-smoothed
initial state (:mod:`bondgraph.inference.smoother`) estimates it.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Mapping, Sequence

import numpy as np

from bondgraph.errors import ModelError, OptionError
from bondgraph.inference import sim_numba, ukf_numba
from bondgraph.inference.options import P0_REL, P0_SCALES, Discretisation
from bondgraph.numerics import compiled
from bondgraph.numerics.integrators import hold_inputs, is_per_input, make_step, simulate_batch

#: ``rule`` strings of :meth:`PriorSpec.mean`
RULE_GIVEN = "given"
RULE_MODEL = "model X0"
RULE_RECORD = "record state columns / sidecar x0"
#: the spread of an initial state estimated jointly with θ, relative to its
#: prior std: the likelihood is conditional on it
X0_TOKEN = 1e-6

#: at most this many samples of the record are simulated for the scales
SCALE_SAMPLES = 20000
#: floor of a scale no rule could set (a state neither driven nor seen)
SCALE_FLOOR = 1e-9
#: prior std of an initial state nothing gives, relative to its scale
UNKNOWN_REL = 1.0
#: a candidate's free run whose RMS of a state exceeds this many times the
#: scale it inherits diverged in all but name (:func:`state_scales`)
WILD_RUN = 1e3


def simulated_rms(model, t, u, theta, x0, disc: Discretisation | None = None, *,
                  samples: int = SCALE_SAMPLES) -> np.ndarray:
    """RMS of every state along a fixed-step free run from ``x0`` with the
    record's inputs (the first ``samples`` samples). A run that does not
    reach its last sample (a non-finite state, or a singular ROS2 matrix
    I − γhJ) diverged; an RK4 run is then repeated with ROS2 (L-stable, the
    same substeps), and one that still diverges gives no scale: zeros, so that
    :func:`state_scales` takes its other rules. Its RMS up to the overflow
    would measure the blow-up, not the state: a user's DC motor with a Dahl
    friction candidate, whose free run at RK4(2) is unstable at one grid
    point, got a prior spread of 8e76 on the inductor's momentum, and every
    sigma point of every grid point diverged at the first sample.

    Parameters
    ----------
    model : Model
    t : array (N,)
    u : array (N, n_u)
    theta : array (n_theta,)
    x0 : array (n_x,)
    disc : Discretisation, optional
        The steps (:func:`bondgraph.numerics.integrators.make_step`,
        :func:`~bondgraph.numerics.integrators.hold_inputs`; default
        ``Discretisation().for_free_run()``), used as given. Its backend
        numba: the compiled free run (:func:`bondgraph.inference.sim_numba.free_run_rms`,
        the same steps, values equal to rounding; the model's kernels
        compiled if they are not in the cache); numpy: the numpy steps,
        sample by sample.
    samples : int
        At most this many samples are simulated.

    Returns
    -------
    ndarray (n_x,)
        0 where nothing finite was simulated, and everywhere when the run
        diverged.
    """
    disc = Discretisation().for_free_run() if disc is None else disc
    n = min(int(np.size(t)), int(samples))
    u = np.asarray(u, float).reshape(np.size(t), -1)[:n] if model.n_u else np.zeros((n, 0))
    t = np.asarray(t, float)[:n]
    rms = _free_run_rms(model, t, u, theta, x0, disc)
    if rms is None and disc.method == "rk4":
        # RK4 outside its stability region (a stiff candidate: a Dahl friction's
        # presliding stiffness) diverges where the L-stable ROS2 does not
        rms = _free_run_rms(model, t, u, theta, x0, replace(disc, method="ros2"))
    return np.zeros(model.n_x) if rms is None else rms


def _free_run_rms(model, t, u, theta, x0, disc: Discretisation) -> np.ndarray | None:
    """:func:`simulated_rms` of the samples ``t`` (N,), inputs ``u`` (N, n_u)
    with ``disc`` alone: the RMS (n_x,), or None when the run stops before
    its end (a state at rest throughout is 0, not a divergence)."""
    method, substeps, hold = disc.method, disc.substeps, disc.hold
    n = t.size
    kernels = free_run_kernels(model, disc.backend, method, hold)
    if kernels is not None:
        return sim_numba.free_run_rms(kernels, t, u, hold, theta, x0, method, substeps)
    held = hold_inputs(u, hold)
    step = make_step(model, method, substeps)
    th = np.asarray(theta, float)[None, :]
    x = np.asarray(x0, float)[None, :].copy()
    acc, count = np.zeros(model.n_x), 0
    with np.errstate(all="ignore"):
        for k in range(n):
            if not np.isfinite(x).all():
                break
            acc += x[0] ** 2
            count += 1
            if k < n - 1:
                uk, duk = held.interval(k)
                try:
                    x = step(x, uk, th, t[k + 1] - t[k], duk)
                except np.linalg.LinAlgError:    # a singular ROS2 matrix: the run ends here
                    break
    if count < n:
        return None
    return np.sqrt(acc / count) if count else np.zeros(model.n_x)


def free_run_kernels(model, backend: str, method: str, hold: str):
    """The model's compiled point kernels for a free run, or None (numpy):
    backend numpy, numba missing, a method or hold the kernel lacks, or
    kernels that do not load (the backend is the caller's choice, taken
    literally: never the state of the kernel cache)."""
    if (backend != "numba" or not compiled.NUMBA_AVAILABLE
            or method not in ukf_numba.METHOD_CODES
            or not (hold in ukf_numba.HOLD_CODES or is_per_input(hold))
            or not hasattr(model, "module")):
        return None
    try:
        return compiled.point_kernels(model)
    except Exception:  # no kernels for this model, or numba cannot compile them
        return None


def sensor_scales(model, u, y, theta, x0) -> np.ndarray:
    """Scale of each state as the sensors see it: min over the outputs j
    with ∂h_j/∂x_i ≠ 0 at the prior mean of std(y_j) / |∂h_j/∂x_i|; 0 for
    states no sensor sees.

    Parameters
    ----------
    u : array (N, n_u)
    y : array (N, n_y)
        Measured outputs (NaN where missing).
    """
    th = np.asarray(theta, float)[None, :]
    u0 = np.asarray(u, float)[:1] if model.n_u else np.zeros((1, 0))
    with np.errstate(all="ignore"):
        H = _output_jacobian(model, np.asarray(x0, float), u0, th)      # (n_y, n_x)
        sd = np.nanstd(np.asarray(y, float), axis=0)
    out = np.zeros(model.n_x)
    for i in range(model.n_x):
        g = np.abs(H[:, i])
        ok = np.isfinite(g) & (g > 0) & np.isfinite(sd) & (sd > 0)
        if ok.any():
            out[i] = float(np.min(sd[ok] / g[ok]))
    return out


def _output_jacobian(model, x0: np.ndarray, u0: np.ndarray, th: np.ndarray) -> np.ndarray:
    """∂h/∂x (n_y, n_x) at ``x0`` (n_x,): the generated ``dhdx``, or, for a
    model generated without it (the loop's candidates carry f, h and the
    state Jacobian only), central differences of ``h`` with steps
    1e-4·max(|x0_i|, 1) (exact for an output linear in the states, which
    the sensors of a bond graph mostly are)."""
    if hasattr(model, "dhdx"):
        return np.asarray(model.dhdx(x0[None, :], u0, th))[0]
    n = x0.size
    step = 1e-4 * np.maximum(np.abs(x0), 1.0)
    X = np.repeat(x0[None, :], 2 * n, axis=0)
    X[np.arange(n), np.arange(n)] += step
    X[n + np.arange(n), np.arange(n)] -= step
    Y = np.asarray(model.h(X, np.repeat(u0, 2 * n, axis=0), np.repeat(th, 2 * n, axis=0)))
    return ((Y[:n] - Y[n:]) / (2 * step)[:, None]).T


def state_scales(model, t, u, y, theta, x0, disc: Discretisation | None = None,
                 inherited: Mapping[str, float] | None = None
                 ) -> tuple[np.ndarray, list[str]]:
    """The scale of every state along the record (module docstring, rules 1-4;
    the states named in ``inherited`` take the scale given there).

    Parameters
    ----------
    model : Model
    t, u, y : arrays (N,), (N, n_u), (N, n_y)
        The record (y: NaN where missing).
    theta : array (n_theta,)
    x0 : array (n_x,)
        Prior mean.
    disc : Discretisation, optional
        Of the free run (:func:`simulated_rms`), used as given.
    inherited : dict, optional
        State name -> scale of the model this one modifies (a candidate of
        the loop: :meth:`bondgraph.inference.problem.Problem.with_model`), on
        the same record. Those states keep it (rule "inherited"), so that the
        models a likelihood ratio compares share the prior of their common
        states, and a candidate's free run at a poor grid value (a Dahl
        friction's stiffness at a body's pitch) does not set their spread.
        A free run that leaves an inherited scale by more than
        :data:`WILD_RUN` sets no other state's scale either (it measures the
        blow-up, not the state). Only the other states are simulated.

    Returns
    -------
    (scales (n_x,), rules)
        ``rules[i]`` names the rule that set state i: "inherited",
        "simulation", "process noise", "sensors" or "floor".
    """
    x0 = np.asarray(x0, float)
    theta = np.asarray(theta, float)
    inherited = {k: float(v) for k, v in (inherited or {}).items()
                 if k in model.states and np.isfinite(v) and v > 0}
    own = [i for i, n in enumerate(model.states) if n not in inherited]
    rms = simulated_rms(model, t, u, theta, x0, disc) if own else np.zeros(model.n_x)
    for name, sc in inherited.items():
        i = model.state_index(name)
        if not rms[i] <= WILD_RUN * max(sc, abs(x0[i])):      # NaN too
            rms = np.zeros(model.n_x)
            break
    for name, sc in inherited.items():
        rms[model.state_index(name)] = sc
    scale = np.maximum(rms, np.abs(x0))
    rules = ["inherited" if n in inherited else "simulation" if s > 0 and np.isfinite(s) else ""
             for n, s in zip(model.states, scale)]
    scale = np.where(np.isfinite(scale), scale, 0.0)
    duration = float(np.asarray(t, float)[-1] - np.asarray(t, float)[0]) if np.size(t) > 1 else 1.0
    with np.errstate(all="ignore"):
        q = np.asarray(model.proc_std(theta[None, :]), float)[0]
    walk = np.where(np.isfinite(q), np.abs(q), 0.0) * np.sqrt(max(duration, 0.0))
    sens = None
    for i in range(model.n_x):
        if rules[i]:
            continue
        if walk[i] > 0:
            scale[i], rules[i] = walk[i], "process noise"
            continue
        if sens is None:
            sens = sensor_scales(model, u, y, theta, x0)
        if sens[i] > 0:
            scale[i], rules[i] = sens[i], "sensors"
        else:
            scale[i], rules[i] = SCALE_FLOOR, "floor"
    return scale, rules


def declared_std(model, x0_std: Mapping[str, float] | None) -> np.ndarray:
    """The declared prior standard deviations (n_x,), NaN where none is declared.

    Raises
    ------
    ModelError
        A state the model does not have.
    OptionError
        A negative or non-finite spread.
    """
    out = np.full(model.n_x, np.nan)
    for name, sd in (x0_std or {}).items():
        i = model.state_index(name)
        sd = float(sd)
        if not np.isfinite(sd) or sd < 0:
            raise OptionError(f"x0_std of state '{name}' must be a finite number >= 0, got {sd!r}")
        out[i] = sd
    return out


def prior_covariance(model, scales: np.ndarray, *, rel: float = P0_REL,
                     x0_std: Mapping[str, float] | None = None,
                     unknown: Sequence[str] = ()) -> np.ndarray:
    """The prior covariance (n_x, n_x) of the initial state: diagonal,
    ``(rel · scale_i)²``, ``(UNKNOWN_REL · scale_i)²`` for the states in
    ``unknown``, with the declared spreads ``x0_std`` (name -> std) imposed.

    Parameters
    ----------
    model : Model
    scales : array (n_x,)
        :func:`state_scales`.
    rel : float
        Relative spread (> 0).
    x0_std : dict, optional
        Declared prior standard deviations by state name (a sidecar's
        ``x0_std``, a user's option).
    unknown : sequence of str
        States whose initial value nothing gives (their mean is a guess).

    Raises
    ------
    OptionError
        ``rel`` not positive, or wrong shape of ``scales``.
    ModelError
        Unknown state names in ``x0_std``.
    """
    if not (np.isfinite(rel) and rel > 0):
        raise OptionError(f"the relative prior spread must be > 0, got {rel!r}")
    scales = np.asarray(scales, float)
    if scales.shape != (model.n_x,):
        raise OptionError(f"state scales have shape {scales.shape}, expected ({model.n_x},)")
    sd = rel * scales
    for name in unknown:
        i = model.state_index(name)
        sd[i] = UNKNOWN_REL * scales[i]
    dec = declared_std(model, x0_std)
    sd = np.where(np.isfinite(dec), dec, sd)
    return np.diag(sd ** 2)


def record_prior(model, t, u, y, theta, x0, disc: Discretisation | None = None, *,
                 rel: float = P0_REL, x0_std: Mapping[str, float] | None = None,
                 unknown: Sequence[str] = (),
                 inherited: Mapping[str, float] | None = None) -> tuple[np.ndarray, dict]:
    """:func:`prior_covariance` with the scales of :func:`state_scales`
    (``disc``: the discretisation of the free run, used as given, default
    ``Discretisation().for_free_run()``; ``unknown``: the states whose
    initial value nothing gives; ``inherited``: state scales of the model
    this one modifies).

    Returns
    -------
    (P0 (n_x, n_x), info)
        ``info``: ``scales`` and ``rules`` by state name, ``rel``, ``unknown``.
    """
    if np.shape(x0) != (model.n_x,):
        raise ModelError(f"x0 has shape {np.shape(x0)}, expected ({model.n_x},)")
    scales, rules = state_scales(model, t, u, y, theta, x0, disc, inherited)
    P0 = prior_covariance(model, scales, rel=rel, x0_std=x0_std, unknown=unknown)
    info = {"rel": float(rel), "scales": dict(zip(model.states, scales.tolist())),
            "unknown": list(unknown),
            "rules": dict(zip(model.states, rules)),
            "declared_std": {k: float(v) for k, v in (x0_std or {}).items()}}
    return P0, info


def default_P0(model, x0: np.ndarray | None = None, rel: float = P0_REL) -> np.ndarray:
    """A diagonal initial covariance by magnitude: ``(rel·max(|x0_i|, 1))²``
    on the diagonal (``PriorSpec(scale="magnitude")``).

    Parameters
    ----------
    model : Model
    x0 : array (n_x,), optional
        Initial state (default ``model.x0``).
    rel : float
        Relative standard deviation (default :data:`~bondgraph.inference.options.P0_REL`).

    Returns
    -------
    ndarray (n_x, n_x)
    """
    x0 = model.x0 if x0 is None else np.asarray(x0, dtype=float)
    sd = rel * np.maximum(np.abs(x0), 1.0)
    return np.diag(sd ** 2)


def _frozen(mapping: Mapping[str, float] | None) -> dict[str, float]:
    """A copy of ``name -> float`` (picklable: problems travel to Dask
    workers; never written after the spec is made)."""
    return {str(k): float(v) for k, v in (mapping or {}).items()}


@dataclass(frozen=True, eq=False)
class PriorSpec:
    """What the prior of the initial state is made of: the toolkit's one
    initial-state rule (:meth:`mean`) and its one covariance policy
    (:meth:`covariance`).

    Parameters
    ----------
    rel : float
        Prior std of each initial state the record gives, relative to its
        scale (default :data:`~bondgraph.inference.options.P0_REL`, 5 %).
    scale : {"state", "magnitude"}
        The scale ``rel`` refers to: each state's own scale along the record
        (:func:`record_prior`; a state nothing gives gets its whole scale) or
        ``max(|x0|, 1)`` (:func:`default_P0`).
    x0 : array (n_x,), optional
        The whole prior mean, given (for the model of that size; a model
        with other states falls back to the rule).
    x0_set : dict, optional
        Initial states by name (``--x0``), imposed over the rule.
    P0 : array (n_x, n_x) or (n_x,), optional
        The whole prior covariance, given (a vector is a diagonal; for the
        model of that size).
    x0_std : dict, optional
        Prior standard deviations by state name declared by the user (e.g.
        the road grade of a level track), imposed last.
    estimated : dict, optional
        Initial states estimated jointly with θ (by name, at their
        estimates): the filter's prior holds them with a token spread,
        :data:`X0_TOKEN` of their prior std (Kristensen, Madsen & Jørgensen
        2004: the likelihood is conditional on them).
    scales : dict, optional
        State scales by name inherited from the model a candidate modifies,
        on the same record (:func:`state_scales`; set by
        :meth:`bondgraph.inference.problem.Problem.with_model`).

    Raises
    ------
    OptionError
        ``rel`` not a positive finite number, an unknown ``scale``.

    Notes
    -----
    The rule (:meth:`mean`): ``x0`` if given, else the record's own rule
    (:meth:`bondgraph.data.records.Experiment.initial_state`: state columns,
    else the sidecar's ``x0``, else the model's X0; the model's X0 for bare
    arrays), then ``x0_set`` and ``estimated`` imposed by name.
    """

    rel: float = P0_REL
    scale: str = "state"
    x0: tuple | None = None
    x0_set: Mapping[str, float] = field(default_factory=dict)
    P0: np.ndarray | None = None
    x0_std: Mapping[str, float] = field(default_factory=dict)
    estimated: Mapping[str, float] = field(default_factory=dict)
    scales: Mapping[str, float] = field(default_factory=dict)

    def __post_init__(self):
        rel = self.rel
        if isinstance(rel, bool) or not isinstance(rel, (int, float, np.floating)) \
                or not np.isfinite(rel) or rel <= 0:
            raise OptionError(f"PriorSpec.rel (--p0-rel) must be a number > 0, got {rel!r}")
        object.__setattr__(self, "rel", float(rel))
        if self.scale not in P0_SCALES:
            raise OptionError(f"PriorSpec.scale (--p0) must be one of {', '.join(P0_SCALES)}, "
                              f"got {self.scale!r}")
        if self.x0 is not None:
            object.__setattr__(self, "x0", tuple(np.asarray(self.x0, float).reshape(-1)))
        if self.P0 is not None:
            object.__setattr__(self, "P0", np.array(self.P0, dtype=float))
        for name in ("x0_set", "x0_std", "estimated", "scales"):
            object.__setattr__(self, name, _frozen(getattr(self, name)))

    def check(self, model) -> None:
        """Check the named states against ``model`` (the declared one).

        Raises
        ------
        ModelError
            A state of ``x0_set`` or ``x0_std`` the model does not have, or a
            given ``x0`` of the wrong length.
        """
        for name in [*self.x0_set, *self.x0_std]:
            model.state_index(name)
        if self.x0 is not None and len(self.x0) != model.n_x:
            raise ModelError(f"x0 has {len(self.x0)} values; model '{model.name}' expects "
                             f"{model.n_x} ({', '.join(model.states)})")

    def mean(self, model, record=None) -> tuple[np.ndarray, str]:
        """The prior mean of ``model``'s initial state on ``record`` (an
        :class:`~bondgraph.data.records.Experiment`, or None for bare arrays).

        Returns
        -------
        (x0 (n_x,), rule)
            ``rule`` is :data:`RULE_GIVEN`, :data:`RULE_RECORD` or
            :data:`RULE_MODEL` (how the vector was made before the named
            states were imposed).
        """
        if self.x0 is not None and len(self.x0) == model.n_x:
            x, rule = np.array(self.x0, dtype=float), RULE_GIVEN
        elif record is None:
            x, rule = np.array(model.x0, dtype=float), RULE_MODEL
        else:
            x, rule = np.asarray(record.initial_state(model), dtype=float).copy(), RULE_RECORD
        for name, v in {**self.x0_set, **self.estimated}.items():
            if name in model.states:
                x[model.state_index(name)] = float(v)
        return x, rule

    def unknown(self, model, record=None) -> list[str]:
        """The states whose initial value nothing gives (their mean is the
        model's X0, a guess): not in ``record`` (state column, sidecar
        ``x0``/``x0_std``), not set here (``x0``, ``x0_set``, ``x0_std``).
        Without a record, none (bare arrays: the caller's x0 is taken as known)."""
        if self.x0 is not None or record is None:
            return []
        given = set(record.given_initial_states(model)) | set(self.x0_set) | set(self.x0_std)
        return [n for n in model.states if n not in given]

    def covariance(self, model, arrays, theta, x0, disc: Discretisation,
                   record=None, *, token: bool = True) -> np.ndarray:
        """The prior covariance (n_x, n_x) at the prior mean ``x0``
        (:meth:`covariance_and_scales` without the scales)."""
        return self.covariance_and_scales(model, arrays, theta, x0, disc, record, token=token)[0]

    def covariance_and_scales(self, model, arrays, theta, x0, disc: Discretisation,
                              record=None, *, token: bool = True) -> tuple[np.ndarray, dict]:
        """The prior covariance (n_x, n_x) at the prior mean ``x0``, and the
        state scales it was made of.

        Parameters
        ----------
        model : Model
        arrays : tuple (t (N,), u (N, n_u), y (N, n_y))
            The record in the model's units.
        theta : array (n_theta,)
            Parameters of the free run that gives the state scales.
        x0 : array (n_x,)
            The prior mean (:meth:`mean`).
        disc : Discretisation
            The filter's; the free run takes :meth:`Discretisation.for_free_run`.
        record : Experiment, optional
            Its declared spreads (sidecar ``x0_std``) and given states.
        token : bool
            Shrink the ``estimated`` states to their token spread (False:
            a fit that estimates them again sees their whole spread).

        Returns
        -------
        (P (n_x, n_x), scales)
            ``P0`` if given for this model; else by :attr:`scale`; then the
            user's ``x0_std`` imposed, then the token spread of the
            ``estimated`` states. ``scales``: state name -> the scale of
            :func:`state_scales` (empty unless :attr:`scale` is "state" and
            no ``P0`` is given).
        """
        P, scales = None, {}
        if self.P0 is not None and self.P0.shape in ((model.n_x,), (model.n_x, model.n_x)):
            P = np.diag(self.P0) if self.P0.ndim == 1 else self.P0.copy()
        elif self.scale == "magnitude":
            P = default_P0(model, x0, self.rel)
        else:
            t, u, y = arrays
            declared = record.initial_state_std(model) if record is not None else {}
            P, info = record_prior(model, t, u, y, theta, x0, disc.for_free_run(), rel=self.rel,
                                   x0_std=declared, unknown=self.unknown(model, record),
                                   inherited=self.scales)
            scales = info["scales"]
        for name, sd in self.x0_std.items():
            if name in model.states:
                _set_std(P, model.state_index(name), sd)
        for name in self.estimated if token else ():
            if name in model.states:
                i = model.state_index(name)
                _set_std(P, i, X0_TOKEN * np.sqrt(max(P[i, i], 0.0)))
        return P, scales

    def conditioned_on(self, estimated: Mapping[str, float]) -> "PriorSpec":
        """This prior with the initial states ``estimated`` (by name; they
        replace the earlier estimates) at their estimates and a token spread."""
        return replace(self, estimated=estimated)

    def on_other_record(self) -> "PriorSpec":
        """This prior for another record (a validation record): its own
        initial state (the given mean, the named states and the estimates
        belong to the estimation record's first sample); the relative spread,
        the scale, a given P0 and the declared spreads kept; inherited
        scales dropped: they are of the estimation record)."""
        return replace(self, x0=None, x0_set={}, estimated={}, scales={})

    def inheriting(self, scales: Mapping[str, float]) -> "PriorSpec":
        """This prior with the state scales ``scales`` (name -> scale, of the
        model a candidate modifies on the same record) inherited."""
        return replace(self, scales=scales) if scales else self


def _set_std(P: np.ndarray, i: int, sd: float) -> None:
    """Row and column ``i`` of ``P`` zeroed, ``P[i, i] = sd²`` (in place)."""
    P[i, :] = 0.0
    P[:, i] = 0.0
    P[i, i] = float(sd) ** 2


def rk4_outputs(model, t, u, theta, x0, substeps: int, hold: str,
                backend: str = "numba") -> np.ndarray:
    """Outputs (N, n_y) of a noise-free fixed-step RK4 run of ``model`` from
    ``x0`` (n_x,), the inputs ``u`` (N, n_u) held as ``hold`` says, NaN from
    the first non-finite state on: compiled
    (:func:`bondgraph.inference.sim_numba.rk4_trajectory`) where
    :func:`free_run_kernels` gives kernels for ``backend``, else the numpy
    steps of :func:`bondgraph.numerics.integrators.simulate_batch` (the same
    arithmetic: the Silverbox arrow error agrees to 1e-14 mV, 0.02 s against
    6.9 s)."""
    return fixed_step_outputs(model, t, u, theta, x0, "rk4", substeps, hold, backend)


def fixed_step_outputs(model, t, u, theta, x0, method: str, substeps: int, hold: str,
                       backend: str = "numba") -> np.ndarray:
    """Outputs (N, n_y) of a noise-free fixed-step run of ``model`` by
    ``method`` ("rk4" or "ros2", ``substeps`` steps per sample interval) from
    ``x0`` (n_x,), the inputs ``u`` (N, n_u) held as ``hold`` says, NaN from
    the first non-finite state on: compiled
    (:func:`bondgraph.inference.sim_numba.rk4_trajectory`,
    :func:`~bondgraph.inference.sim_numba.ros2_trajectory`) where
    :func:`free_run_kernels` gives kernels for ``backend``, else the numpy
    steps of :func:`bondgraph.numerics.integrators.simulate_batch`. RK4 is
    the same arithmetic either way; ROS2 agrees to rounding (W is inverted
    by the filter kernel's elimination, not LAPACK): on a user's two-tank
    graph 164 free runs of 577 samples took 19 s in numpy steps."""
    th = np.asarray(theta, float)
    u = np.asarray(u, float).reshape(np.size(t), -1)
    kernels = free_run_kernels(model, backend, method, hold)
    if kernels is None:
        return simulate_batch(model, t, u, th[None, :], x0, method=method, substeps=substeps,
                              hold=hold)[:, 0, :]
    X = sim_numba.trajectory(kernels, t, u if model.n_u else np.zeros((np.size(t), 1)), hold, th,
                             np.asarray(x0, float), method, substeps)
    bad = ~np.isfinite(X).all(axis=1)
    if bad.any():
        X[int(np.argmax(bad)):] = np.nan
    with np.errstate(all="ignore"):
        return np.asarray(model.h(X, u, th[None, :]), float)

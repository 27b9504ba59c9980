"""What an estimation moves: model parameters θ, initial states x0 and
measurement-noise standard deviations, as one vector z.

An :class:`Estimand` maps values z (S, k) of its names to the arguments of
the batched UKF (:func:`bondgraph.inference.ukf.ukf_nll`): full parameter
vectors θ (S, n_θ), initial states x0 (S, n_x) and, when an output's noise
level is estimated or declared by the record, the measurement-noise
covariances R (S, n_y, n_y). Names:

* a parameter by its own name (``"m"``);
* an initial state as ``"x0.<state>"``: estimated jointly with θ, its prior
  covariance in the filter shrinks to a token spread so that the likelihood
  is conditional on it (the approach of Kristensen, Madsen & Jørgensen 2004);
* a measurement-noise standard deviation as ``"noise.<output>"`` (output
  units), for an output whose sensor declares a fixed number.

:func:`noise_plan` decides which noise levels an estimation moves when the
record does not declare them (the default of estimate and loop): parameters
that change only the noise intensities (proc_std, meas_std), and the noise
level of every output whose sensor noise is a fixed number the record does
not declare.

References
----------
Kristensen, N. R., Madsen, H., Jørgensen, S. B. (2004). Parameter estimation
in stochastic grey-box models. Automatica 40(2), 225-237.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Sequence

import numpy as np

from bondgraph.errors import ModelError, OptionError
# X0_TOKEN (the token spread of a jointly estimated initial state) is defined
# in prior and used here
from bondgraph.inference.prior import X0_TOKEN, default_P0

X0_PREFIX = "x0."
NOISE_PREFIX = "noise."
#: box of an estimated initial state: prior mean ± this many prior stds (or scales)
X0_BOX = 100.0
#: box of an estimated noise std: its start times / divided by this
NOISE_BOX = 1e4


@dataclass
class Estimand:
    """Parameters, initial states and noise levels estimated together.

    Attributes
    ----------
    model : Model
    params : list of str
        Estimated parameters.
    states : list of str
        Estimated initial states.
    noises : list of str
        Outputs whose measurement-noise standard deviation is estimated.
    theta : ndarray (n_theta,)
        Values of all parameters.
    x0 : ndarray (n_x,)
        Initial state (the prior mean for the states not estimated).
    sigma : ndarray (n_y,)
        Measurement-noise standard deviations that override ``meas_std(θ)``
        (NaN: not overridden). Declared noise levels and estimated ones.
    x0_scale : ndarray (n_x,)
        Spread of each initial state (the prior's std): sets the box of an
        estimated one.
    sigma_centre : ndarray (n_y,), optional
        The centre of an estimated noise std's box (the record's level; NaN
        or None: the std's current value).
    """

    model: object
    params: list
    states: list = field(default_factory=list)
    noises: list = field(default_factory=list)
    theta: np.ndarray = None
    x0: np.ndarray = None
    sigma: np.ndarray = None
    x0_scale: np.ndarray = None
    sigma_centre: np.ndarray = None

    def __post_init__(self):
        m = self.model
        self.params, self.states, self.noises = list(self.params), list(self.states), list(self.noises)
        for what, names in (("parameter", self.params), ("state", self.states),
                            ("output", self.noises)):
            if len(set(names)) != len(names):
                raise OptionError(f"{what} listed twice in {names}")
        self.theta = np.array(m.theta0 if self.theta is None else self.theta, dtype=float)
        self.x0 = np.array(m.x0 if self.x0 is None else self.x0, dtype=float)
        self.sigma = (np.full(m.n_y, np.nan) if self.sigma is None
                      else np.array(self.sigma, dtype=float))
        self.x0_scale = (np.maximum(np.abs(self.x0), 1e-9) if self.x0_scale is None
                         else np.array(self.x0_scale, dtype=float))
        self.p_idx = m.param_indices(self.params)
        self.s_idx = np.array([m.state_index(s) for s in self.states], dtype=int)
        self.n_idx = np.array([m.output_index(o) for o in self.noises], dtype=int)
        if np.any(~np.isfinite(self.sigma[self.n_idx])):
            meas = np.asarray(m.meas_std(self.theta[None, :]), float)[0]
            self.sigma[self.n_idx] = np.where(np.isfinite(self.sigma[self.n_idx]),
                                              self.sigma[self.n_idx], meas[self.n_idx])

    # ------------------------------------------------------------ names
    @property
    def names(self) -> list[str]:
        """``params``, then ``x0.<state>``, then ``noise.<output>``."""
        return (list(self.params) + [X0_PREFIX + s for s in self.states]
                + [NOISE_PREFIX + o for o in self.noises])

    @property
    def k(self) -> int:
        """Number of estimated quantities."""
        return len(self.params) + len(self.states) + len(self.noises)

    @property
    def uses_R(self) -> bool:
        """Whether some output's noise std overrides ``meas_std(θ)``."""
        return bool(np.isfinite(self.sigma).any())

    def value(self) -> np.ndarray:
        """The current values z (k,)."""
        return np.concatenate([self.theta[self.p_idx], self.x0[self.s_idx],
                               self.sigma[self.n_idx]])

    def at(self, z) -> "Estimand":
        """A copy whose estimated quantities take the values ``z`` (k,)."""
        th, x0, sig = self._split(np.asarray(z, float)[None, :])
        return replace(self, theta=th[0], x0=x0[0], sigma=sig[0])

    def values(self) -> dict[str, float]:
        """Name -> current value."""
        return dict(zip(self.names, self.value().tolist()))

    # ------------------------------------------------------------ maps
    def _split(self, Z: np.ndarray):
        Z = np.atleast_2d(np.asarray(Z, float))
        if Z.shape[1] != self.k:
            raise ModelError(f"expected {self.k} values for {self.names}, got shape {Z.shape}")
        S, a, b = Z.shape[0], len(self.params), len(self.params) + len(self.states)
        th = np.repeat(self.theta[None, :], S, axis=0)
        th[:, self.p_idx] = Z[:, :a]
        x0 = np.repeat(self.x0[None, :], S, axis=0)
        x0[:, self.s_idx] = Z[:, a:b]
        sig = np.repeat(self.sigma[None, :], S, axis=0)
        sig[:, self.n_idx] = Z[:, b:]
        return th, x0, sig

    def expand(self, Z) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        """UKF arguments of the values ``Z`` (S, k): θ (S, n_θ), x0 (S, n_x),
        and R (S, n_y, n_y) (``diag(σ²)``, σ from ``meas_std(θ)`` where not
        overridden), or None when no noise level is overridden."""
        th, x0, sig = self._split(Z)
        if not self.uses_R:
            return th, x0, None
        with np.errstate(all="ignore"):
            meas = np.asarray(self.model.meas_std(th), float)
        s = np.where(np.isfinite(sig), sig, meas)
        R = np.zeros(s.shape + (s.shape[1],))
        idx = np.arange(s.shape[1])
        R[:, idx, idx] = s ** 2
        return th, x0, R

    def prior_cov(self, P0: np.ndarray | None) -> np.ndarray | None:
        """The filter's prior covariance with the estimated initial states
        decoupled and shrunk to :data:`X0_TOKEN` of their spread (``P0``
        None: the UKF's default, :func:`~bondgraph.inference.ukf.default_P0`)."""
        if P0 is None and not self.s_idx.size:
            return None
        P = default_P0(self.model, self.x0) if P0 is None else np.array(P0, dtype=float)
        if P.ndim == 1:
            P = np.diag(P)
        if P.ndim != 2:
            raise OptionError(f"P0 must be (n_x,) or (n_x, n_x) with estimated initial "
                              f"states, got shape {P.shape}")
        for i in self.s_idx:
            sd = X0_TOKEN * max(float(self.x0_scale[i]), 1e-300)
            P[i, :] = 0.0
            P[:, i] = 0.0
            P[i, i] = sd ** 2
        return P

    # ------------------------------------------------------------ boxes
    def bounds(self, lower=None, upper=None) -> tuple[np.ndarray, np.ndarray]:
        """Box (k,) of every estimated quantity: the parameters' boxes
        (``lower``/``upper`` of the parameters, default the model's), an
        initial state ± :data:`X0_BOX` of its spread around its current value,
        a noise std within a factor :data:`NOISE_BOX` of its box's centre
        (``sigma_centre``, else its current value), reaching the current
        value where that lies outside."""
        if lower is None or upper is None:
            lower, upper = self.model.bounds(self.params)
        xs, ss = self.x0[self.s_idx], self.x0_scale[self.s_idx]
        sg = self.sigma[self.n_idx]
        c = sg if self.sigma_centre is None else np.asarray(self.sigma_centre, float)[self.n_idx]
        n_lo, n_hi = noise_box(np.where(np.isfinite(c) & (c > 0), c, sg), sg)
        lo = np.concatenate([np.asarray(lower, float), xs - X0_BOX * ss, n_lo])
        hi = np.concatenate([np.asarray(upper, float), xs + X0_BOX * ss, n_hi])
        return lo, hi

    def log_scale(self, noise_params: Sequence[str] = ()) -> np.ndarray:
        """Which quantities move in log scale: noise-intensity parameters
        (named in ``noise_params``) with a positive box, and noise stds."""
        lo, _ = self.model.bounds(self.params)
        np_set = set(noise_params)
        par = [n in np_set and lo[i] > 0 for i, n in enumerate(self.params)]
        return np.array(par + [False] * len(self.states) + [True] * len(self.noises), dtype=bool)


def noise_box(centre, start):
    """The box ``(lower, upper)`` of an estimated noise std: ×/÷
    :data:`NOISE_BOX` around ``centre`` (the record's level), reaching
    ``start`` (the fit's start) where that lies outside. Arrays or floats."""
    return np.minimum(centre / NOISE_BOX, start), np.maximum(centre * NOISE_BOX, start)


def moves_meas_std(model, theta, name: str, *, rel: float = 0.1) -> bool:
    """Whether moving the parameter ``name`` by ``rel`` (relative; to
    ``rel`` from 0) changes ``model.meas_std`` at ``theta`` (n_theta,): a
    sensor's noise std, where a noise intensity that does not is a process
    noise (of :func:`noise_parameters`, the two kinds told apart).

    Returns
    -------
    bool
    """
    th = np.asarray(theta, float)
    j = model.param_index(name)
    t1 = th.copy()
    t1[j] = th[j] * (1 + rel) if th[j] != 0 else rel
    with np.errstate(all="ignore"):
        return not np.allclose(np.asarray(model.meas_std(t1), float),
                               np.asarray(model.meas_std(th), float), rtol=0.0, atol=0.0)


def noise_parameters(model, theta, x=None, u=None, *, rel: float = 0.1) -> list[str]:
    """Parameters that change the noise intensities (``proc_std`` or
    ``meas_std``) but neither ``f`` nor ``h``: the noise intensities of the
    filter, detected numerically (each parameter moved by ``rel``).

    Parameters
    ----------
    model : Model
    theta : array (n_theta,)
    x, u : arrays (M, n_x), (M, n_u), optional
        Points where f and h are compared (default: x0 and u0 and two
        random perturbations of them).

    Returns
    -------
    list of str
    """
    th = np.asarray(theta, float)
    rng = np.random.default_rng(0)
    if x is None:
        base = np.asarray(model.x0, float)
        x = base[None, :] * (1.0 + 0.1 * rng.standard_normal((3, model.n_x))) + \
            0.1 * rng.standard_normal((3, model.n_x))
    if u is None:
        u = np.repeat(np.asarray(model.u0, float)[None, :], np.shape(x)[0], axis=0)
    out = []
    with np.errstate(all="ignore"):
        f0, h0 = model.f(x, u, th[None]), model.h(x, u, th[None])
        q0, r0 = np.asarray(model.proc_std(th), float), np.asarray(model.meas_std(th), float)
        for j, name in enumerate(model.params):
            t1 = th.copy()
            t1[j] = th[j] * (1 + rel) if th[j] != 0 else rel
            noise = (not np.allclose(np.asarray(model.proc_std(t1), float), q0, atol=0.0)
                     or not np.allclose(np.asarray(model.meas_std(t1), float), r0, atol=0.0))
            if not noise:
                continue
            if (np.allclose(model.f(x, u, t1[None]), f0, equal_nan=True)
                    and np.allclose(model.h(x, u, t1[None]), h0, equal_nan=True)):
                out.append(name)
    return out


def record_noise_level(y) -> np.ndarray:
    """Measurement-noise std of each output seen in a record: the robust
    scale of its second-difference pseudo-residuals.

    ``e_i = (y_{i-1} − 2 y_i + y_{i+1}) / √6`` has the noise's variance when
    the signal is locally linear over three samples; its scale is taken as
    1.4826 × the median absolute deviation (robust to steps and outliers;
    the plain std where that is zero). A signal that is not oversampled
    leaks into it, so the value is an upper estimate: a start for a fit that
    estimates the level, never a level to hold.

    Parameters
    ----------
    y : array (N, n_y)
        Measured outputs, NaN where missing (the finite samples of each
        output are taken in order).

    Returns
    -------
    ndarray (n_y,)
        Output units; NaN where an output has fewer than 3 finite samples or
        no variation at all.

    References
    ----------
    Gasser, T., Sroka, L., Jennen-Steinmetz, C. (1986). Residual variance and
    residual pattern in nonlinear regression. Biometrika 73(3), 625-633.
    """
    y = np.asarray(y, float)
    y = y.reshape(y.shape[0], -1)
    out = np.full(y.shape[1], np.nan)
    for j in range(y.shape[1]):
        v = y[np.isfinite(y[:, j]), j]
        if v.size < 3:
            continue
        e = (v[:-2] - 2.0 * v[1:-1] + v[2:]) / np.sqrt(6.0)
        s = 1.4826 * float(np.median(np.abs(e - np.median(e))))
        s = s if s > 0 else float(np.std(e))
        if np.isfinite(s) and s > 0:
            out[j] = s
    return out


def noise_plan(model, theta, params: Sequence[str], fixed: Sequence[str],
               declared: np.ndarray, y=None) -> tuple[list[str], list[str], np.ndarray, list[str]]:
    """Which noise levels an estimation moves by default.

    An output of which the record holds no finite sample (``y``'s column all
    NaN: a sensor of the graph the record lacks) gets no estimated level,
    and a noise-intensity parameter that changes only such outputs' noise is
    not added: the likelihood does not depend on them (zero Fisher
    information), so estimating them would make the Fisher matrix singular
    and leave every Cramér-Rao std unreported.

    Parameters
    ----------
    model : Model
    theta : array (n_theta,)
    params : sequence of str
        Parameters the user estimates.
    fixed : sequence of str
        Parameters the user holds fixed.
    declared : array (n_y,)
        Noise stds the record declares (NaN where it declares none), model units.
    y : array (N, n_y), optional
        The record's outputs: an estimated output whose sensor declares no
        positive level (``meas_std(θ)`` zero) starts from the level seen in
        them (:func:`record_noise_level`); outputs without a finite sample
        are left out (above). None: every output counts as measured.

    Returns
    -------
    (noise_params, noise_outputs, sigma, notes)
        Noise-intensity parameters added to the estimated ones (those not
        listed or fixed); outputs whose noise std is estimated (a fixed number
        in the model, undeclared by the record, measured at least once); the
        override vector σ (n_y,) (declared values, the record-based start of
        an estimated output whose sensor gives no level, NaN elsewhere);
        notes for the log.

    Raises
    ------
    OptionError
        An estimated output whose sensor gives no positive level and whose
        record (``y``) shows none either.
    """
    th = np.asarray(theta, float)
    declared = np.asarray(declared, float)
    unseen = _unseen_outputs(model, y)
    meas_dep = _meas_dependent(model, th)
    add = [p for p in noise_parameters(model, th) if p not in params and p not in fixed
           and not (p in meas_dep and np.isfinite(declared[meas_dep[p]]).all())
           and not (p in meas_dep and set(meas_dep[p]) <= unseen
                    and not _changes_proc_std(model, th, p))]
    sigma = np.full(model.n_y, np.nan)
    outs, notes = [], []
    param_driven = {j for js in meas_dep.values() for j in js}
    for j, o in enumerate(model.outputs):
        if np.isfinite(declared[j]):
            if j in param_driven and any(p in params for p, js in meas_dep.items() if j in js):
                notes.append(f"the record declares the noise of '{o}', but its noise parameter "
                             f"is estimated: the declaration is not used")
                continue
            sigma[j] = declared[j]
        elif j not in param_driven and j not in unseen:
            outs.append(o)
    if unseen:
        notes.append("no finite sample of output(s) " + ", ".join(
            model.outputs[j] for j in sorted(unseen)) + " in the record: no noise level "
            "estimated for them (the likelihood does not depend on it)")
    if add:
        notes.append(f"noise intensities estimated (the record does not declare them): "
                     f"{', '.join(add)}")
    if outs:
        notes.append(f"measurement-noise std estimated (the record does not declare it): "
                     f"{', '.join(outs)}")
    _start_bare_levels(model, th, outs, y, sigma, notes)
    return add, outs, sigma, notes


def _unseen_outputs(model, y) -> set[int]:
    """Indices of the outputs without a finite sample in ``y`` (N, n_y)
    (empty when ``y`` is None)."""
    if y is None:
        return set()
    y = np.asarray(y, float).reshape(np.shape(y)[0], -1)
    return {j for j in range(min(y.shape[1], model.n_y)) if not np.isfinite(y[:, j]).any()}


def _changes_proc_std(model, th, name: str) -> bool:
    """Whether moving parameter ``name`` by 10 % changes ``proc_std``."""
    t1 = th.copy()
    j = model.param_index(name)
    t1[j] = th[j] * 1.1 if th[j] != 0 else 0.1
    with np.errstate(all="ignore"):
        return not np.allclose(np.asarray(model.proc_std(t1), float),
                               np.asarray(model.proc_std(th), float), atol=0.0)


def _start_bare_levels(model, th, outs, y, sigma, notes) -> None:
    """Into ``sigma`` (n_y,), in place: the start of each estimated output's
    level that its sensor does not give (``meas_std`` not positive), the
    level seen in ``y`` (:func:`record_noise_level`), with a note.

    Raises
    ------
    OptionError
        Such an output whose record shows no level either.
    """
    with np.errstate(all="ignore"):
        meas = np.asarray(model.meas_std(th[None, :]), float).reshape(-1)
    bare = [model.output_index(o) for o in outs
            if not (np.isfinite(meas[model.output_index(o)]) and meas[model.output_index(o)] > 0)]
    if not bare:
        return
    seen = record_noise_level(y) if y is not None else np.full(model.n_y, np.nan)
    start = start_levels(y) if y is not None else seen
    missing = [model.outputs[j] for j in bare if not np.isfinite(seen[j])]
    if missing:
        raise OptionError(
            f"no measurement-noise level for output(s) {', '.join(map(repr, missing))} of "
            f"'{model.name}': the sensor declares none (noise_std), the record declares none "
            f"(columns.<output>.noise_std in its sidecar) and none can be seen in the record; "
            f"declare one of them")
    low = [j for j in bare if start[j] > seen[j]]
    sigma[bare] = start[bare]
    notes.append("no noise level declared by the sensor or the record: the estimate starts "
                 "from the level seen in the record's second differences (an upper "
                 "estimate): " + ", ".join(f"{model.outputs[j]} = {sigma[j]:.4g}" for j in bare)
                 + ("" if not low else
                    f" ({', '.join(model.outputs[j] for j in low)}: raised to the output's "
                    f"std / {NOISE_BOX:g}, so that the level's box reaches the output's own "
                    f"spread; the second differences show "
                    + ", ".join(f"{seen[j]:.3g}" for j in low) + ")"))


def start_levels(y) -> np.ndarray:
    """The start (n_y,) of each output's noise level that nothing declares:
    the level the record's second differences show
    (:func:`record_noise_level`), but at least the output's std /
    :data:`NOISE_BOX`. An estimated level's box is its start ×/÷ NOISE_BOX,
    and a start far below the output's spread (a quantised encoder whose
    second differences are mostly 0) would cap the level below the declared
    model's misfit. NaN where the record shows no level."""
    y = np.asarray(y, float)
    y = y.reshape(y.shape[0], -1)
    seen = record_noise_level(y)
    spread = np.array([np.nanstd(y[:, j]) if np.isfinite(y[:, j]).sum() > 1 else 0.0
                       for j in range(y.shape[1])])
    return np.where(np.isfinite(seen), np.maximum(seen, spread / NOISE_BOX), seen)


def _meas_dependent(model, th) -> dict[str, list[int]]:
    """Parameter -> outputs whose ``meas_std`` it changes."""
    out = {}
    with np.errstate(all="ignore"):
        r0 = np.asarray(model.meas_std(th), float)
        for j, name in enumerate(model.params):
            t1 = th.copy()
            t1[j] = th[j] * 1.1 if th[j] != 0 else 0.1
            d = np.flatnonzero(~np.isclose(np.asarray(model.meas_std(t1), float), r0, atol=0.0))
            if d.size:
                out[name] = d.tolist()
    return out


def x0_state_names(model, names: Sequence[str] | None, option: str = "--estimate-x0") -> list[str]:
    """The initial states to estimate: ``names`` checked against the model's
    states (``["all"]``: every state; None or empty: none).

    Parameters
    ----------
    model : Model
    names : sequence of str or None
    option : str
        Name of the option, for messages.

    Returns
    -------
    list of str

    Raises
    ------
    OptionError
        A name the model has no state of (the culprit and the states named),
        or a name given twice.
    """
    names = [str(n).strip() for n in (names or []) if str(n).strip()]
    if names == ["all"]:
        return list(model.states)
    bad = [n for n in names if n not in model.states]
    if bad:
        raise OptionError(f"{option}: model '{model.name}' has no state "
                          f"{', '.join(repr(b) for b in bad)} (states: "
                          f"{', '.join(model.states)}, or all)")
    if len(set(names)) != len(names):
        raise OptionError(f"{option}: a state is listed twice in {names}")
    return names


def check_noise_mode(mode: str, option: str = "--noise") -> str:
    """``mode`` if it is ``"auto"`` or ``"model"``.

    Raises
    ------
    OptionError
        Anything else (the value and the choices named).
    """
    if mode not in ("auto", "model"):
        raise OptionError(f"{option} = {mode!r} is not one of 'auto', 'model'")
    return mode


def plan_estimand(model, theta, params: Sequence[str], fixed: Sequence[str],
                  declared, *, noise: str = "auto", states: Sequence[str] = (),
                  x0=None, x0_scale=None, y=None) -> tuple[Estimand, list[str]]:
    """The :class:`Estimand` of an estimation and the log notes saying which
    noise levels it estimates and why.

    Parameters
    ----------
    model : Model
    theta : array (n_theta,)
        Values of all parameters (start of the estimated ones).
    params : sequence of str
        Parameters the user estimates.
    fixed : sequence of str
        Parameters the user holds fixed.
    declared : array (n_y,) or None
        Noise stds the record declares, model units (NaN: none; None: no
        record declarations, e.g. bare arrays).
    noise : {"auto", "model"}
        ``"auto"``: :func:`noise_plan` (declared levels held at the declared
        value, undeclared ones estimated); ``"model"``: the graph's own
        sensor noise and noise-intensity values (nothing added).
    states : sequence of str
        Initial states estimated jointly with θ (Kristensen, Madsen &
        Jørgensen 2004).
    x0, x0_scale : arrays (n_x,), optional
        Prior mean and spread of the initial state (:class:`Estimand`).
    y : array (N, n_y), optional
        The record's outputs (:func:`noise_plan`: the start of a level no
        sensor declares).

    Returns
    -------
    (Estimand, notes)

    Raises
    ------
    OptionError
        An unknown noise mode; ModelError: unknown names.
    """
    check_noise_mode(noise, "noise")
    params, notes = list(params), []
    if noise == "model":
        return Estimand(model, params, states=list(states), theta=theta, x0=x0,
                        x0_scale=x0_scale), ["noise levels: the model's own (--noise model)"]
    dec = np.full(model.n_y, np.nan) if declared is None else np.asarray(declared, float)
    add, outs, sigma, notes = noise_plan(model, theta, params, fixed, dec, y)
    held = [o for j, o in enumerate(model.outputs) if np.isfinite(sigma[j]) and o not in outs]
    if held:
        notes.append("measurement-noise std held at the record's declaration: " + ", ".join(
            f"{o} = {sigma[model.output_index(o)]:.4g}" for o in held))
    if not (add or outs or held):
        notes.append("noise levels: the model's own (nothing to estimate or hold)")
    est = Estimand(model, params + add, states=list(states), noises=outs, theta=theta, x0=x0,
                   sigma=sigma, x0_scale=x0_scale)
    return est, notes

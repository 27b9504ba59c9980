"""The estimation problem as one immutable object.

A :class:`Problem` is a model bound to a record: the record's arrays in the
model's units, the prior of the initial state (:class:`~bondgraph.inference.prior.PriorSpec`:
the toolkit's one initial-state rule and covariance policy), the
measurement-noise levels (:class:`NoiseSpec`), the fixed parameter values
and the filter's options (:class:`~bondgraph.inference.options.UKFOptions`,
whose :class:`~bondgraph.inference.options.Discretisation` the UKF, the
prior's free run and the discretisation check all read). It is built by
exactly one function, :func:`make_problem`; what a fit learns (noise
levels, initial states, more substeps) makes a new problem
(:meth:`Problem.conditioned_on`), never a change of shared settings; the
same problem for another model of the same record (a candidate of the
loop) is :meth:`Problem.with_model`, for another record of the same model
(a validation record) :meth:`Problem.on_record`.

The filter, the likelihood and the smoother read it: :meth:`Problem.nll`
(:func:`bondgraph.inference.ukf.ukf_nll`), :meth:`Problem.smoothed_initial_state`
(:func:`bondgraph.inference.smoother.rts_smooth`) and
:meth:`Problem.discretisation_check`.

References
----------
Wan, E. A., van der Merwe, R. (2000). The unscented Kalman filter for
nonlinear estimation. Proc. IEEE AS-SPCC, 153-158.
Kristensen, N. R., Madsen, H., Jørgensen, S. B. (2004). Parameter estimation
in stochastic grey-box models. Automatica 40(2), 225-237.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any, Mapping, Sequence

import numpy as np

from bondgraph.errors import ModelError, NumericalError, OptionError, SmootherRestartError
from bondgraph.inference.estimand import noise_parameters, record_noise_level
from bondgraph.inference.options import NOISE_MODES, Discretisation, UKFOptions, ukf_options
from bondgraph.inference.prior import PriorSpec
from bondgraph.inference.record import as_record
from bondgraph.inference.smoother import rts_smooth
from bondgraph.inference.ukf import (
    UKFResult,
    discretisation_check,
    discretisation_errors,
    rk4_stable_substeps,
    sigma_point_errors,
    ukf_nll,
)
from bondgraph.numerics.model import Model
from bondgraph.numerics.integrators import split_hold

__all__ = ["NoiseSpec", "Problem", "make_problem", "noise_covariance", "noise_parameters"]


def noise_covariance(model, thetas: np.ndarray, sigma: np.ndarray) -> np.ndarray:
    """Measurement-noise covariances ``diag(σ²)`` (P, n_y, n_y): σ held
    where ``sigma`` is finite, ``meas_std(θ)`` elsewhere.

    Parameters
    ----------
    model : Model
    thetas : array (P, n_theta)
    sigma : array (n_y,) or (P, n_y)
        Held measurement-noise stds in output units, NaN where the model's own.

    Returns
    -------
    ndarray (P, n_y, n_y)
    """
    th = np.atleast_2d(np.asarray(thetas, float))
    with np.errstate(all="ignore"):
        meas = np.asarray(model.meas_std(th), float)
    sig = np.broadcast_to(np.asarray(sigma, float), meas.shape)
    s = np.where(np.isfinite(sig), sig, meas)
    R = np.zeros(s.shape + (s.shape[1],))
    idx = np.arange(s.shape[1])
    R[:, idx, idx] = s ** 2
    return R


@dataclass(frozen=True)
class NoiseSpec:
    """The measurement-noise levels of a problem.

    Parameters
    ----------
    mode : {"auto", "model"}
        ``"auto"``: a level the record declares is held at it, the others
        estimated with θ (:func:`bondgraph.inference.estimand.noise_plan`);
        ``"model"``: the graph's own sensor noise and noise intensities.
    held : dict
        Output -> measurement-noise std held in every filter run (output
        units); the others come from ``meas_std(θ)``.
    estimated : sequence of str
        Outputs whose noise std a fit estimates with θ (``noise.<output>``).
    centre : dict
        Output -> the centre of its estimated level's box (×/÷
        :data:`~bondgraph.inference.estimand.NOISE_BOX`): the level the
        first fit started from (the record's). A refit's box reaches it
        whatever the earlier fits estimated, so that the box does not
        drift away from the record's level one refit at a time. An output
        without one has its box centred on the level the fit starts from.

    Raises
    ------
    OptionError
        An unknown mode, or a held level or centre that is not a finite
        number > 0.

    Notes
    -----
    Which parameters are noise intensities (they change ``proc_std`` or
    ``meas_std`` but neither f nor h) is decided by one detector,
    :func:`bondgraph.inference.estimand.noise_parameters`.
    """

    mode: str = "auto"
    held: Mapping[str, float] = field(default_factory=dict)
    estimated: tuple = ()
    centre: Mapping[str, float] = field(default_factory=dict)

    def __post_init__(self):
        if self.mode not in NOISE_MODES:
            raise OptionError(f"NoiseSpec.mode (--noise) must be one of "
                              f"{', '.join(NOISE_MODES)}, got {self.mode!r}")
        for name, what in (("held", "held measurement-noise std"),
                           ("centre", "centre of the measurement-noise box")):
            levels = {}
            for o, v in dict(getattr(self, name) or {}).items():
                v = float(v)
                if not np.isfinite(v) or v <= 0:
                    raise OptionError(f"{what} of '{o}' must be a finite number > 0, "
                                      f"got {v!r}")
                levels[str(o)] = v
            object.__setattr__(self, name, levels)
        object.__setattr__(self, "estimated", tuple(str(o) for o in self.estimated))

    def sigma(self, model) -> np.ndarray:
        """The held stds (n_y,) in ``model``'s output order, NaN where not held."""
        return np.array([float(self.held.get(o, np.nan)) for o in model.outputs])

    def centres(self, model) -> np.ndarray:
        """The boxes' centres (n_y,) in ``model``'s output order, NaN where none."""
        return np.array([float(self.centre.get(o, np.nan)) for o in model.outputs])

    def covariance(self, model, thetas) -> np.ndarray | None:
        """The filter's R (P, n_y, n_y) with the held levels
        (:func:`noise_covariance`), or None when no level is held."""
        sig = self.sigma(model)
        if not np.isfinite(sig).any():
            return None
        return noise_covariance(model, thetas, sig)

    def outputs(self, model) -> list[str]:
        """The estimated outputs that ``model`` has."""
        return [o for o in self.estimated if o in model.outputs]

    def holding(self, levels: Mapping[str, float], estimated: Sequence[str] | None = None
                ) -> "NoiseSpec":
        """This spec with ``levels`` held too (over the earlier ones) and,
        if given, ``estimated`` as the estimated outputs."""
        return replace(self, held={**self.held, **levels},
                       estimated=self.estimated if estimated is None else tuple(estimated))


@dataclass(frozen=True, eq=False)
class Problem:
    """A model bound to a record: what every likelihood, fit, smoother and
    check of an estimation reads. Build it with :func:`make_problem`.

    Attributes
    ----------
    model : Model
        The generated model (:class:`bondgraph.numerics.model.Model`).
    record : Experiment or None
        The record (:class:`bondgraph.data.records.Experiment`); None for
        bare arrays.
    t : ndarray (N,)
        Sample times [s].
    u : ndarray (N, n_u)
        Inputs in the model's units (inputs the record lacks at their
        defaults when the builder was told so).
    y : ndarray (N, n_y)
        Measured outputs in the model's units, NaN where missing.
    theta : ndarray (n_theta,)
        The model's defaults with the fixed values; the start of fits and
        the parameters of the prior's free run.
    fixed : mapping
        The fixed parameter values by name.
    prior : PriorSpec
        The prior's specification.
    noise : NoiseSpec
        The measurement-noise levels.
    ukf : UKFOptions
        The filter's options; ``ukf.discretisation`` is the problem's
        :class:`~bondgraph.inference.options.Discretisation`.
    x0 : ndarray (n_x,)
        The prior mean (:meth:`PriorSpec.mean`).
    x0_rule : str
        How it was made (given, the record's rule, the model's X0).
    P0 : ndarray (n_x, n_x)
        The filter's prior covariance (:meth:`PriorSpec.covariance`, the
        jointly estimated initial states at a token spread).
    defaults_ok : bool
        Inputs the record lacks took the model's defaults (else they were
        an error); the problems derived from this one do the same.
    scales : mapping
        The state scales the prior was made of, by state name
        (:func:`bondgraph.inference.prior.state_scales`; empty for a prior
        by magnitude or a given P0): a candidate model's problem
        (:meth:`with_model`) inherits them.

    Notes
    -----
    Frozen: a problem never changes (its arrays are its own copies, shared
    by the problems derived from it: never write into them). :meth:`conditioned_on`,
    :meth:`with_model` and :meth:`on_record` return new problems, so a
    result never depends on the calls made before it.

    References
    ----------
    Wan & van der Merwe (2000) for the filter; Kristensen, Madsen &
    Jørgensen (2004) for initial states and noise levels estimated with θ.
    """

    model: Any
    record: Any
    t: np.ndarray
    u: np.ndarray
    y: np.ndarray
    theta: np.ndarray
    fixed: Mapping[str, float]
    prior: PriorSpec
    noise: NoiseSpec
    ukf: UKFOptions
    x0: np.ndarray
    x0_rule: str
    P0: np.ndarray
    defaults_ok: bool = False
    scales: Mapping[str, float] = field(default_factory=dict)

    # ------------------------------------------------------------ views
    @property
    def disc(self) -> Discretisation:
        """The problem's :class:`~bondgraph.inference.options.Discretisation`."""
        return self.ukf.discretisation

    @property
    def name(self) -> str:
        """The record's name ("arrays" for bare arrays)."""
        return getattr(self.record, "name", None) or "arrays"

    @property
    def meta(self) -> dict:
        """The record's metadata (empty for bare arrays)."""
        return dict(getattr(self.record, "meta", None) or {})

    @property
    def arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(t, u, y)``."""
        return self.t, self.u, self.y

    def full_prior(self) -> np.ndarray:
        """The prior covariance without the token spread of the jointly
        estimated initial states (n_x, n_x): what a fit that estimates them
        again starts from."""
        if not any(n in self.model.states for n in self.prior.estimated):
            return self.P0.copy()
        return self.prior.covariance(self.model, self.arrays, self.theta, self.x0, self.disc,
                                     self.record, token=False)

    # ------------------------------------------------------------ derived problems
    def conditioned_on(self, *, x0: Mapping[str, float] | None = None,
                       noise_levels: Mapping[str, float] | None = None,
                       noise_outputs: Sequence[str] | None = None,
                       disc: Discretisation | None = None) -> "Problem":
        """A new problem with what a fit learned.

        Parameters
        ----------
        x0 : dict, optional
            The initial states estimated with θ (by name; they replace the
            earlier estimates): the prior mean takes them, the filter holds
            them at a token spread. None: the earlier estimates stay.
        noise_levels : dict, optional
            Measurement-noise stds (output -> std) held from now on.
        noise_outputs : sequence of str, optional
            The outputs whose noise std later fits estimate.
        disc : Discretisation, optional
            Another discretisation (e.g. the substeps the check asked for).

        Returns
        -------
        Problem
        """
        same = x0 is None or dict(self.prior.estimated) == {k: float(v) for k, v in x0.items()}
        prior = self.prior if same else self.prior.conditioned_on(x0)
        noise = self.noise
        if noise_levels is not None or noise_outputs is not None:
            noise = noise.holding(noise_levels or {}, noise_outputs)
        ukf = self.ukf if disc is None else self.ukf.with_discretisation(disc)
        if prior is self.prior and ukf == self.ukf:
            return replace(self, noise=noise)       # the prior does not depend on the noise
        return make_problem(self.model, self.record, prior=prior, noise=noise, ukf=ukf,
                            fixed=self.fixed, arrays=self.arrays, defaults_ok=self.defaults_ok)

    def with_model(self, model) -> "Problem":
        """The same record, prior, noise, fixed values and options for
        another model (a candidate of the loop). The states it shares with
        this problem's model (by name) inherit their scales
        (:meth:`PriorSpec.inheriting`): the models a likelihood ratio
        compares share the prior of their common states, and only the new
        states are scaled by the candidate's own free run."""
        rec = self.record if self.record is not None else self.arrays   # bare arrays: as they are
        return make_problem(model, rec, prior=self.prior.inheriting(self.scales),
                            noise=self.noise, ukf=self.ukf, fixed=self.fixed,
                            defaults_ok=self.defaults_ok)

    def with_fixed(self, fixed: Mapping[str, float]) -> "Problem":
        """The same problem with more parameter values fixed (over the
        earlier ones; a later stage of :func:`bondgraph.inference.estimate.two_stage`)."""
        if not fixed:
            return self
        return make_problem(self.model, self.record if self.record is not None else self.arrays,
                            prior=self.prior, noise=self.noise, ukf=self.ukf,
                            fixed={**self.fixed, **fixed}, arrays=self.arrays,
                            defaults_ok=self.defaults_ok)

    def on_record(self, record, scales: Mapping[str, float] | None = None) -> "Problem":
        """The same model and policies on another record (a validation
        record): its own initial state and state scales
        (:meth:`PriorSpec.on_other_record`), those of ``scales`` (name ->
        scale on ``record``, of the model this one modifies) inherited; a
        refined discretisation (chosen for this record's intervals) at its
        largest substeps throughout (:meth:`UKFOptions.uniform`)."""
        return make_problem(self.model, record,
                            prior=self.prior.on_other_record().inheriting(scales or {}),
                            noise=self.noise, ukf=self.ukf.uniform(), fixed=self.fixed,
                            defaults_ok=self.defaults_ok)

    # ------------------------------------------------------------ evaluations
    def nll(self, theta, *, store: bool | str = False) -> UKFResult:
        """The batched UKF over the record (:func:`bondgraph.inference.ukf.ukf_nll`)
        with the problem's prior, held noise levels and filter options.

        Parameters
        ----------
        theta : array (P, n_theta) or (n_theta,)
        store : bool or "full"
            Keep innovations, covariances and filtered states.

        Returns
        -------
        UKFResult
            ``nll`` (P,); a set that fails gets +inf and a reason.
        """
        th = np.atleast_2d(np.asarray(theta, float))
        return ukf_nll(self.model, self.t, self.u, self.y, th, self.x0, self.P0,
                       options=self.ukf, store=store, R=self.noise.covariance(self.model, th))

    def smoothed_initial_state(self, theta) -> np.ndarray:
        """x̂_0|N (n_x,): the initial state given the whole record, from the
        unscented RTS smoother at ``theta`` (n_theta,)
        (:func:`bondgraph.inference.smoother.rts_smooth`; Särkkä 2008).

        Raises
        ------
        NumericalError
            If the filter or the backward pass fails.
        SmootherRestartError
            (a NumericalError) If the backward pass diverged and restarted
            from the filter (``Smoothed.restarts``: no process noise through
            contracting dynamics): its x̂_0 would then hold the record's
            start only, not the whole record.
        """
        th = np.asarray(theta, float)
        R = self.noise.covariance(self.model, th[None, :])
        sm = rts_smooth(self.model, self.t, self.u, self.y, th, self.x0, self.P0,
                        options=self.ukf, R=None if R is None else R[0])
        if sm.restarts:
            many = "s" if sm.restarts != 1 else ""
            raise SmootherRestartError(
                f"without process noise the smoother gives no initial state given the whole "
                f"record here (its backward pass through contracting dynamics restarted from "
                f"the filter at {sm.restarts} sample{many})", restarts=int(sm.restarts))
        return sm.x[0]

    def discretisation_check(self, theta, *, substeps: int | None = None,
                             free_run: bool = True) -> dict:
        """:func:`bondgraph.inference.ukf.discretisation_check` of the
        problem's discretisation (``substeps`` overriding its own) at
        ``theta`` from the prior mean: ``one_step`` and ``free_run`` (n_y,)
        in measurement-noise standard deviations."""
        d = self.disc if substeps is None else replace(self.disc, substeps=int(substeps))
        return discretisation_check(self.model, self.t, self.u, theta, self.x0, disc=d,
                                    sigma=self.noise_scale(theta), free_run=free_run,
                                    states=lambda: self.filtered_states(theta))

    def filtered_states(self, theta) -> np.ndarray | None:
        """The filter's state estimates x̂_k|k (N, n_x) at ``theta``
        (n_theta,) by ROS2 (L-stable) with the problem's substeps and hold,
        or None where the filter fails: where the states go when they
        follow the record (:func:`bondgraph.inference.ukf.discretisation_errors`
        judges an RK4 step's stability there too)."""
        th = np.asarray(theta, float).reshape(1, -1)
        p = self if self.disc.method == "ros2" else self.conditioned_on(
            disc=replace(self.disc, method="ros2"))
        try:
            with np.errstate(all="ignore"):
                res = p.nll(th, store=True)
        except (FloatingPointError, np.linalg.LinAlgError, NumericalError):
            return None
        if not np.isfinite(res.nll[0]) or res.x_filt is None:
            return None
        x = res.x_filt[:, 0]
        return x if np.isfinite(x).all() else None

    def rk4_stable_substeps(self, theta, states=None) -> int | None:
        """The fewest substeps at which the problem's RK4 filter is stable
        along ``states`` (N, n_x; default its own state estimates at
        ``theta`` (n_theta,) by ROS2, :meth:`filtered_states`):
        :func:`bondgraph.inference.ukf.rk4_stable_substeps` — None when its
        own substeps are (or its method is ROS2, or the filter fails there),
        0 when none up to 64 is."""
        if self.disc.method != "rk4":
            return None
        x = states if states is not None else self.filtered_states(theta)
        return rk4_stable_substeps(self.model, self.t, self.u, self.disc, theta, x)

    def one_step_errors(self, theta, substeps: Sequence[int], *, sigma=None,
                        cache: dict | None = None) -> np.ndarray:
        """The largest one-step output error over outputs and samples of the
        problem's method with each of ``substeps`` (k,) at ``theta`` from the
        prior mean, in units of ``sigma`` (n_y,; default :meth:`noise_scale`),
        against one fine reference shared by all of them
        (:func:`bondgraph.inference.ukf.discretisation_errors`; ``cache``
        keeps it for later calls at the same θ). Returns (k,); inf where no
        reference is finite."""
        discs = [replace(self.disc, substeps=int(n)) for n in substeps]
        return np.array([o for o, _ in self.step_errors(theta, discs, sigma=sigma, cache=cache)])

    def step_errors(self, theta, discs: Sequence, *, sigma=None, cache: dict | None = None,
                    free_run: bool = False, directions=None) -> list[tuple[float, float]]:
        """``(one_step, bias)`` of each discretisation of ``discs`` at
        ``theta``: the largest one-step output error over outputs and samples
        in units of ``sigma`` (default :meth:`noise_scale`) and, with
        ``free_run``, the free run's bias in Cramér-Rao std (its output
        error in σ projected onto the sensitivities along ``directions``
        (p, n_theta), the estimated parameters' steps; without them the
        bound, the root sum of squares; NaN without ``free_run``), against
        one fine reference shared by all of them
        (:func:`bondgraph.inference.ukf.discretisation_errors`, ``cache``
        keeps it). inf where no reference is finite."""
        sig = self.noise_scale(theta) if sigma is None else sigma
        errs = discretisation_errors(self.model, self.t, self.u, theta, self.x0, list(discs),
                                     sigma=sig, cache=cache, free_run=free_run,
                                     states=lambda: self.filtered_states(theta),
                                     directions=directions)
        return [(float(np.max(e["one_step"], initial=0.0)), float(e["free_run_bias"]))
                for e in errs]

    def interval_errors(self, theta, substeps: Sequence[int], *,
                        sigma=None) -> tuple[np.ndarray, np.ndarray] | None:
        """Each interval's one-step output error (k, N − 1) with each of
        ``substeps`` (k,) throughout at ``theta`` (n_theta,), in units of
        ``sigma`` (default :meth:`noise_scale`): at the filter's own sigma
        points (:func:`bondgraph.inference.ukf.sigma_point_errors` along
        this problem's filter at ``theta``), and along the reference
        trajectory of the discretisation check
        (:func:`~bondgraph.inference.ukf.discretisation_errors`' ``intervals``,
        from the prior mean). None when the filter fails."""
        th = np.asarray(theta, float)
        res = self.nll(th[None, :], store="full")
        if not np.isfinite(res.nll[0]):
            return None
        sig = self.noise_scale(th) if sigma is None else sigma
        at_sigma = sigma_point_errors(self.model, self.t, self.u, th, res.x_filt[:, 0],
                                      res.P_filt[:, 0], self.ukf, substeps, sig)
        discs = [replace(self.disc, substeps=int(n), refine=()) for n in substeps]
        along = discretisation_errors(self.model, self.t, self.u, th, self.x0, discs, sigma=sig,
                                      states=res.x_filt[:, 0])
        return at_sigma, np.array([e["intervals"] for e in along]).reshape(at_sigma.shape)

    def noise_scale(self, theta) -> np.ndarray:
        """The measurement-noise std of each output (n_y,) that errors are
        measured in: the held level (a record's declaration, a fit's
        estimate), else ``meas_std(theta)``, else the level seen in the
        record (:func:`~bondgraph.inference.estimand.record_noise_level`);
        inf (left out of a comparison) where none is positive and finite."""
        th = np.asarray(theta, float).reshape(1, -1)
        with np.errstate(all="ignore"):
            meas = np.asarray(self.model.meas_std(th), float).reshape(-1)
        held = self.noise.sigma(self.model)
        sig = np.where(np.isfinite(held), held, meas)
        bad = ~(np.isfinite(sig) & (sig > 0))
        if bad.any():
            sig = np.where(bad, record_noise_level(self.y), sig)
        return np.where(np.isfinite(sig) & (sig > 0), sig, np.inf)

    def noise_parameters(self) -> list[str]:
        """The model's noise-intensity parameters (the one detector,
        :func:`bondgraph.inference.estimand.noise_parameters`)."""
        return noise_parameters(self.model, self.theta)


def _record_arrays(model, record, defaults_ok: bool):
    """``(t, u, y)`` of a record (Experiment or tuple of arrays) for ``model``."""
    if isinstance(record, tuple):
        t, u, y = record
        return np.asarray(t, float), np.asarray(u, float), np.asarray(y, float)
    t = np.asarray(record.t, dtype=float)
    if model.n_u:
        u = record.inputs_for(model, defaults_ok=True) if defaults_ok else record.inputs_for(model)
    else:
        u = np.zeros((t.size, 0))
    return t, u, record.outputs_for(model)


def _with_states(model: Model) -> Model:
    """``model``, which must have a state: the filter's sigma points need
    one (ModelError naming the remedy otherwise)."""
    if model.n_x == 0:
        raise ModelError(f"model '{model.name}' has no state (its outputs are algebraic "
                         f"functions of its inputs: every storage in derivative causality); "
                         f"the filter needs one",
                         hint="build it with bondgraph.numerics.registry.with_a_state(graph), "
                              "which adds an inert state (the commands do so themselves)")
    return model


def make_problem(model, record, *, prior: PriorSpec | None = None,
                 noise: NoiseSpec | None = None, ukf: UKFOptions | None = None,
                 fixed: Mapping[str, float] | None = None, arrays=None,
                 defaults_ok: bool = False) -> Problem:
    """Bind a model to a record: the one builder of :class:`Problem`.

    Parameters
    ----------
    model : Model or str
        A generated model or its reference (:meth:`~bondgraph.numerics.model.Model.from_spec`).
    record : Experiment, path of a CSV record, or tuple ``(t, u, y)``
        The record (a path is loaded; a tuple is taken as arrays in the
        model's units, with the model's X0 as the prior mean unless the
        prior gives one).
    prior : PriorSpec, optional
        Default ``PriorSpec()`` (5 % of each state's scale).
    noise : NoiseSpec, optional
        Default ``NoiseSpec()`` (``"auto"``: the levels the record declares
        held, the others estimated with θ,
        :func:`bondgraph.inference.estimand.noise_plan`); for bare arrays,
        which declare none, ``NoiseSpec("model")`` (the graph's own levels).
    ukf : UKFOptions, optional
        Default ``UKFOptions()``.
    fixed : dict, optional
        Parameter values by name over the model's defaults.
    arrays : tuple (t, u, y), optional
        The record's arrays for this model, already resolved (a problem
        conditioned on a fit reuses its own).
    defaults_ok : bool
        Inputs the record lacks take the model's defaults (default False:
        :class:`~bondgraph.errors.DataError` naming them).

    Returns
    -------
    Problem

    Raises
    ------
    DataError
        A record that cannot be read or bound to the model (units, columns).
    ModelError
        A fixed parameter the model does not have (named), or a model
        without a state (:func:`bondgraph.numerics.registry.with_a_state`).
    OptionError
        Options of the wrong type, a per-input hold whose length is not
        the model's number of inputs (the inputs named), or refined runs
        (``ukf.refine``) beyond the record's intervals.
    """
    model = _with_states(Model.from_spec(model))
    rec = as_record(record)
    prior = PriorSpec() if prior is None else prior
    if noise is None:       # bare arrays declare no level: the graph's own
        noise = NoiseSpec("model") if isinstance(rec, tuple) else NoiseSpec()
    if not isinstance(prior, PriorSpec) or not isinstance(noise, NoiseSpec):
        raise OptionError(f"make_problem needs a PriorSpec and a NoiseSpec, got "
                          f"{type(prior).__name__} and {type(noise).__name__}")
    ukf = ukf_options(ukf)
    try:
        split_hold(ukf.hold, model.n_u)
    except OptionError as e:
        raise OptionError(f"hold: {e} (inputs of '{model.name}': "
                          f"{', '.join(model.inputs) or 'none'})") from None
    t, u, y = _record_arrays(model, rec, defaults_ok) if arrays is None else arrays
    if arrays is None:        # the problem's own copies, never the record's arrays
        t, u, y = (np.array(a, dtype=float) for a in (t, u, y))
    rec = None if isinstance(rec, tuple) else rec
    if ukf.refine and ukf.refine[-1][1] > t.size - 1:
        raise OptionError(f"UKFOptions.refine reaches interval {ukf.refine[-1][1] - 1}, beyond "
                          f"the record's {t.size - 1} intervals: it was chosen for another "
                          f"record (UKFOptions.uniform() takes its largest substeps throughout)")
    fixed = {k: float(v) for k, v in (fixed or {}).items()}
    theta = model.theta(fixed)                  # ModelError naming an unknown parameter
    x0, rule = prior.mean(model, rec)
    P0, scales = prior.covariance_and_scales(model, (t, u, y), theta, x0, ukf.discretisation,
                                             rec)
    return Problem(model, rec, t, u, y, theta, fixed, prior, noise, ukf, x0, rule, P0,
                   defaults_ok, scales)

"""Online parameter tracking and change detection with the augmented-state UKF.

A :class:`TrackingModel` is the model of an augmented graph
(:func:`bondgraph.core.augment.augment`: each tracked parameter a random-walk
state, its box kept by a logit transform). The batch tracker :func:`track`
runs the toolkit's batched UKF (:func:`bondgraph.inference.ukf.ukf_nll`, the
compiled kernel with the numba backend) over a record, stores the filtered
means and covariances, and gives per sample the estimate and std of each
tracked parameter, filtered and RTS-smoothed
(:func:`bondgraph.inference.smoother.rts_backward`).

Change detection (:mod:`bondgraph.inference.changes`): the standardised
updates of each tracked parameter's state are watched by a windowed GLR
test whose threshold gives one false alarm per ``false_alarm_hours`` at
most. At an alarm the change time ĵ is the GLR's estimate; the filter is
restarted at ĵ from its posterior at ĵ − 1 with the changed parameter's
variance reset (``TrackOptions.reset_rel`` of its value, cross covariances
zero) and the original states' prior covariance added (they went through
the samples between the change and the alarm with the old value), so that
the new value is re-estimated from the change time on (Willsky & Jones
1976), not reached by the random walk. The restarted segment is filtered
twice: the second pass starts from the first pass's final value with the
same wide spread (the augmented filter's transient from a far start biases
a multiplicative parameter; Ljung 1979). The detector ignores the first
``holdoff_s`` of a restarted segment.

Observability: per sample, the information the update carries about each
tracked parameter, summed over a trailing window of
``TrackOptions.observable_s``, against the reference prior std σ₀ (the
``prior_rel`` rule at the start value): where the window's data alone
would leave more than ``observable_ratio`` of σ₀² the parameter is not
observable there (:func:`bondgraph.inference.changes.observable_mask`);
its updates there are skipped by the detector and no alarm is raised for
it (a record at rest says nothing about a damping: what the filter does
there is noise, not a change).

The filter's step (:func:`choose_substeps`): a changed parameter can bring
about stretches the constant-parameter check never sees (a tire slipping
past its friction peak after the friction dropped), where a coarse step
mispredicts and the filter explains its own step error by moving the
tracked parameters, with a std that does not know it. The substeps are
chosen from the tracked record: the runs with s, 2s, 4s substeps compared
window by window in their log-likelihood's sampling std (Richardson, with
the observed contraction).

Estimates and std in the parameter's unit: p̂ = g(ẑ) and σ_p = |g'(ẑ)| σ_z
(first order) for the transform g of
:class:`~bondgraph.core.augment.TrackedParameter`.

The streaming :class:`Tracker` runs the same predict/update steps
(:func:`bondgraph.inference.ukf.predict`, :func:`~bondgraph.inference.ukf.update`)
one sample at a time, and the same change detection as each sample arrives
(:class:`OnlineWatch`: what it cannot do without the future is said there).

References
----------
Jazwinski, A. H. (1970). Stochastic Processes and Filtering Theory, ch. 8.
Willsky, A. S., Jones, H. L. (1976). A generalized likelihood ratio approach
to the detection and estimation of jumps in linear systems. IEEE TAC 21(1).
Basseville, M., Nikiforov, I. V. (1993). Detection of Abrupt Changes.
Särkkä, S. (2008). Unscented Rauch-Tung-Striebel smoother. IEEE TAC 53(3).
"""

from __future__ import annotations

from collections import deque
from dataclasses import asdict, dataclass, field, replace
from typing import Mapping, NamedTuple, Sequence

import numpy as np

from bondgraph.core.augment import augment, tracked_parameters
from bondgraph.core.deferred import stats
from bondgraph.errors import ModelError, NumericalError, OptionError
from bondgraph.inference.changes import (
    first_alarm,
    glr_threshold,
    information_gain,
    observable_mask,
    serial_inflation,
    standardised_increments,
)
from bondgraph.inference.options import TrackOptions, UKFOptions, _checked
from bondgraph.inference.smoother import rts_backward
from bondgraph.inference.ukf import ukf_nll
from bondgraph.numerics.model import Model


# ------------------------------------------------------------------ the model
@dataclass(frozen=True)
class TrackingModel:
    """The generated model of an augmented graph and what it tracks.

    Attributes
    ----------
    model : Model
        The augmented model (states: the original ones and ``tracked.<p>``).
    tracked : tuple of TrackedParameter
    base_params : tuple of str
        The parameters of the original graph.
    """

    model: Model
    tracked: tuple
    base_params: tuple

    @classmethod
    def from_graph(cls, graph, track: Sequence[str], drift: Mapping[str, float] | None = None,
                   *, transform: str = "logit", start: Mapping[str, float] | None = None
                   ) -> "TrackingModel":
        """Augment ``graph`` (:func:`bondgraph.core.augment.augment`, same
        arguments), derive and generate it in memory."""
        aug = augment(graph, track, drift, transform=transform, start=start)
        return cls(Model.from_graph(aug), tracked_parameters(aug), tuple(graph.params))

    @property
    def names(self) -> list[str]:
        """The tracked parameters."""
        return [tp.name for tp in self.tracked]

    @property
    def state_indices(self) -> np.ndarray:
        """Indices of their states in the augmented model (k,)."""
        return np.array([self.model.state_index(tp.state) for tp in self.tracked], int)

    def theta(self, values: Mapping[str, float], drift: Mapping[str, float] | None = None
              ) -> np.ndarray:
        """The augmented model's parameter vector (n_theta,).

        Parameters
        ----------
        values : dict
            Values of the original parameters by name (the tracked ones
            are ignored: they are states); the others keep their defaults.
        drift : dict, optional
            Drift intensities by tracked parameter (over the defaults).

        Raises
        ------
        ModelError
            A drift for a parameter that is not tracked.
        """
        th = self.model.theta0.copy()
        for name, v in values.items():
            if name in self.model.params:
                th[self.model.param_index(name)] = float(v)
        for name, q in (drift or {}).items():
            tp = self._spec(name)
            th[self.model.param_index(tp.drift_param)] = float(q)
        return th

    def _spec(self, name: str):
        for tp in self.tracked:
            if tp.name == name:
                return tp
        raise ModelError(f"'{name}' is not tracked (tracked: {', '.join(self.names)})")

    def values(self, x: np.ndarray, P: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Parameter estimates and std (..., k) from state means (..., n_x)
        and covariances (..., n_x, n_x): p = g(z), ``σ_p = |g(z + σ_z) − g(z − σ_z)| / 2``
        (``|g'(z)| σ_z`` to first order; near a bound of the box, where the
        logit's slope vanishes, the secant keeps the spread the state still
        has instead of reporting a parameter known exactly)."""
        idx = self.state_indices
        z = x[..., idx]
        var = np.maximum(np.diagonal(P, axis1=-2, axis2=-1)[..., idx], 0.0)
        sz = np.sqrt(var)
        est = np.stack([tp.value(z[..., i]) for i, tp in enumerate(self.tracked)], -1)
        hi = np.stack([tp.value(z[..., i] + sz[..., i]) for i, tp in enumerate(self.tracked)], -1)
        lo = np.stack([tp.value(z[..., i] - sz[..., i]) for i, tp in enumerate(self.tracked)], -1)
        return est, 0.5 * np.abs(hi - lo)


def tracking_prior(problem, tm: TrackingModel, start: Mapping[str, float] | None = None,
                   std: Mapping[str, float] | None = None, rel: float = 0.1):
    """Prior mean, covariance and parameter vector of the tracking filter.

    Parameters
    ----------
    problem : Problem
        The original model on the record (its prior of the original states,
        its fixed values).
    tm : TrackingModel
    start : dict, optional
        Start value of each tracked parameter (default: ``problem.theta``'s).
    std : dict, optional
        Prior std of each tracked parameter in its unit (default ``rel`` ×
        |start|, or ``rel`` × its box width at a start of 0).
    rel : float

    Returns
    -------
    x0 : ndarray (n_x,)
    P0 : ndarray (n_x, n_x)
        The problem's prior of the original states, block-diagonal with the
        tracked states' variances (in the transformed coordinate).
    theta : ndarray (n_theta,)

    Raises
    ------
    ModelError
        A start or std for a parameter not tracked, or a problem whose model
        lacks a state of the augmented model.
    """
    base = dict(zip(problem.model.params, problem.theta))
    start, std = dict(start or {}), dict(std or {})
    for name in [*start, *std]:
        tm._spec(name)
    m = tm.model
    x0, P0 = np.zeros(m.n_x), np.zeros((m.n_x, m.n_x))
    bi = [problem.model.state_index(s) for s in m.states if s in problem.model.states]
    ai = [m.state_index(s) for s in m.states if s in problem.model.states]
    if len(ai) + len(tm.tracked) != m.n_x:
        raise ModelError(f"the tracking model's states {m.states} are not those of "
                         f"'{problem.model.name}' plus the tracked ones")
    x0[ai] = problem.x0[bi]
    P0[np.ix_(ai, ai)] = problem.P0[np.ix_(bi, bi)]
    for i, tp in zip(tm.state_indices, tm.tracked):
        p0 = float(start.get(tp.name, base[tp.name]))
        sd = float(std.get(tp.name, rel * (abs(p0) if p0 != 0 else tp.upper - tp.lower)))
        x0[i] = float(tp.state_of(p0))
        P0[i, i] = float(tp.std_of(p0, sd)) ** 2
    return x0, P0, tm.theta(base)


def filter_options(ukf: UKFOptions, tm: TrackingModel, options: TrackOptions) -> UKFOptions:
    """The UKF options of the tracking filter: the problem's, with κ' = κ − k
    when ``options.match_spread`` (:class:`~bondgraph.inference.options.TrackOptions`),
    a refinement at its largest substeps throughout (:meth:`UKFOptions.uniform`:
    the tracker filters parts of the record and streams samples, whose
    intervals are not the record's)."""
    ukf = ukf.uniform()
    if not options.match_spread:
        return ukf
    return replace(ukf, kappa=ukf.kappa - len(tm.tracked))


# ------------------------------------------------------------------ results
@dataclass
class Change:
    """A detected change of a tracked parameter.

    Attributes
    ----------
    parameter : str
    index, alarm_index : int
        Sample of the estimated change (ĵ) and of the alarm.
    time, alarm_time : float
        Their times [s]; ``alarm_time − time`` is the detection delay.
    before, before_std : float
        Filtered estimate and std just before the change (sample ĵ − 1).
    after, after_std : float
        The re-estimate from the change on: the filtered value at the end
        of the segment that starts at ĵ (the next change or the record's end).
    statistic, threshold : float
        The GLR statistic at the alarm and the threshold [nats].
    detected : str
        The parameter whose standardised updates raised the alarm; the
        change is attributed (``parameter``) to the one whose restart
        explains the samples from ĵ to the alarm plus one window best
        (``isolation``).
    isolation : dict
        Parameter -> negative log-likelihood of those samples [nats] with
        that parameter restarted at ĵ, minus the smallest (0 for
        ``parameter``); parameters not observable at ĵ are left out.
    attributed_time : float or None
        The streaming :class:`Tracker`: the time [s] of the sample at which
        the change was attributed and the filter restarted (at the alarm
        or up to one window after it, :meth:`Tracker._attribute`); None
        from :func:`track`, which attributes with the whole record at hand.
    at_start : bool
        The record's first change, its onset within the detector's window of
        the sample its parameter first became observable: the detector cannot
        tell it from a start value (the prior, e.g. ``bondgraph track
        --from``'s estimate from another record) that does not hold on this
        record (:func:`mark_at_start`).
    """

    parameter: str
    index: int
    alarm_index: int
    time: float
    alarm_time: float
    statistic: float
    threshold: float
    detected: str = ""
    isolation: dict = field(default_factory=dict)
    before: float = np.nan
    before_std: float = np.nan
    after: float = np.nan
    after_std: float = np.nan
    attributed_time: float | None = None
    at_start: bool = False

    def to_dict(self) -> dict:
        """Plain dict (JSON-able through :mod:`bondgraph.core.jsonsafe`)."""
        return asdict(self)


@dataclass
class TrackResult:
    """What :func:`track` returns. Arrays are indexed by sample (N) and
    tracked parameter (k).

    Attributes
    ----------
    t : ndarray (N,)
    names, units : list of str
    estimate, std : ndarray (N, k)
        Filtered estimates and std (parameter units).
    smoothed, smoothed_std : ndarray (N, k) or None
        RTS-smoothed, within each segment between detected changes.
    x_filt : ndarray (N, n_x)
        Filtered states of the augmented model (``states``).
    states : list of str
    nll : float
        Negative log-likelihood of the reported filter over the record [nats]:
        each sample's term from the segment that reports it (the filter
        restarted at each change; one pass when nothing changed).
    increments, statistic : ndarray (N, k)
        Standardised parameter updates and the GLR statistic.
    information : ndarray (N, k)
        Information of each sample's update about each parameter
        [1/unit²] (:func:`bondgraph.inference.changes.information_gain`).
    nis, nis_dof : ndarray (N,)
        The tracking filter's normalised innovation squared per sample (NaN
        without an update) and the number of outputs measured there (its χ²
        degrees of freedom when the model is right; :meth:`inconsistent`).
    nll_terms : ndarray (N,)
        Each sample's term of ``nll`` [nats] (:func:`choose_substeps`
        compares them window by window).
    observable : ndarray of bool (N, k)
        Whether each parameter is observable from the record at each sample
        (``TrackOptions.observable_s``, ``observable_ratio``).
    threshold : float or None
    changes : list of Change
    settings : dict
    """

    t: np.ndarray
    names: list
    units: list
    estimate: np.ndarray
    std: np.ndarray
    x_filt: np.ndarray
    states: list
    nll: float
    increments: np.ndarray
    statistic: np.ndarray
    threshold: float | None
    changes: list = field(default_factory=list)
    information: np.ndarray | None = None
    nis: np.ndarray | None = None
    nis_dof: np.ndarray | None = None
    nll_terms: np.ndarray | None = None
    observable: np.ndarray | None = None
    smoothed: np.ndarray | None = None
    smoothed_std: np.ndarray | None = None
    settings: dict = field(default_factory=dict)

    def columns(self) -> dict[str, np.ndarray]:
        """The per-sample table (``track.csv``): ``t``, then per parameter
        ``<p>``, ``<p>.std``, when smoothed ``<p>.smoothed``, ``<p>.smoothed_std``,
        and ``observable_<p>`` (1 or 0)."""
        out = {"t": self.t}
        for i, n in enumerate(self.names):
            out[n], out[f"{n}.std"] = self.estimate[:, i], self.std[:, i]
            if self.smoothed is not None:
                out[f"{n}.smoothed"] = self.smoothed[:, i]
                out[f"{n}.smoothed_std"] = self.smoothed_std[:, i]
            if self.observable is not None:
                out[f"observable_{n}"] = self.observable[:, i].astype(float)
        return out

    def inconsistent(self, window_s: float = 10.0, level: float = 1e-3) -> list[tuple[float, float]]:
        """Windows where the innovations are larger than the model allows.

        The record is cut into windows of ``window_s`` seconds; in each, the
        sum of the NIS is χ² with the summed degrees of freedom when the
        model (with the tracked parameters) is right and its innovations
        white (Bar-Shalom, Li & Kirubarajan 2001, §5.4). A window whose sum
        exceeds the ``1 − level`` quantile is listed. Many such windows mean
        model error the tracker may read as parameter changes: a missing
        effect, not a changed parameter (``bondgraph loop`` finds it).

        Returns
        -------
        list of (t_start, t_end) [s]
        """
        if self.nis is None or self.t.size < 2:
            return []
        dt = float(np.median(np.diff(self.t)))
        w = max(1, int(round(window_s / dt)))
        out = []
        for a in range(0, self.t.size, w):
            nis, dof = self.nis[a:a + w], self.nis_dof[a:a + w]
            ok = np.isfinite(nis)
            m = int(dof[ok].sum())
            if m and float(nis[ok].sum()) > stats.chi2.isf(level, m):
                out.append((float(self.t[a]), float(self.t[min(a + w, self.t.size) - 1])))
        return out

    def unobservable(self, name: str) -> list[tuple[float, float]]:
        """The stretches ``(t_start, t_end)`` [s] where ``name`` is not
        observable (first and last sample of each run), in time order.

        Raises
        ------
        ModelError
            ``name`` is not tracked.
        """
        if name not in self.names:
            raise ModelError(f"'{name}' is not tracked (tracked: {', '.join(self.names)})")
        if self.observable is None:
            return []
        bad = ~self.observable[:, self.names.index(name)]
        edges = np.diff(np.concatenate([[0], bad.astype(int), [0]]))
        return [(float(self.t[a]), float(self.t[b - 1]))
                for a, b in zip(np.flatnonzero(edges == 1), np.flatnonzero(edges == -1))]


def mark_at_start(changes: Sequence[Change], names: Sequence[str],
                  observable: np.ndarray | None, window: int) -> None:
    """Set :attr:`Change.at_start` on the first of ``changes`` when its
    onset (``index``) lies within ``window`` samples (the GLR window) of the
    first sample at which its parameter (one of ``names``) is observable
    (``observable``, (N, k)), or before it: the detector sums a window to
    decide, and a jump inside the first window of informative samples is
    not told from a start value (the prior) that does not hold on the
    record. A user's CVT driveline tracked with its loop's Coulomb level
    (148.6 ± 0.27 N, the Cramér-Rao std on another record) raised a change
    at 4.8 s to 149.1 N, as the level became observable at 4.95 s, before
    the real one (150 -> 250 N at 100 s)."""
    if not changes or observable is None:
        return
    first = changes[0]
    seen = np.flatnonzero(np.asarray(observable, bool)[:, list(names).index(first.parameter)])
    first.at_start = _within_first_window(int(seen[0]) if seen.size else -1, first.index, window)


def _within_first_window(first_observable: int, onset: int, window: int) -> bool:
    """Whether a change with onset ``onset`` (its sample) lies within
    ``window`` samples of the sample its parameter first became observable
    (-1: not before the onset), or before it (:func:`mark_at_start`)."""
    return first_observable < 0 or onset - 1 - first_observable <= window


# ------------------------------------------------------------------ batch tracker
@dataclass
class _Segment:
    start: int
    x: np.ndarray
    P: np.ndarray
    prior: tuple
    nll: float
    S: np.ndarray
    G: np.ndarray
    info: np.ndarray
    end: int = -1
    nis: np.ndarray | None = None       # (n,) normalised innovation squared, NaN: no update
    dof: np.ndarray | None = None       # (n,) outputs measured at each sample
    terms: np.ndarray | None = None     # (n,) per-sample NLL terms [nats]


def track(problem, tm: TrackingModel, *, start: Mapping[str, float] | None = None,
          std: Mapping[str, float] | None = None, drift: Mapping[str, float] | None = None,
          options: TrackOptions | None = None) -> TrackResult:
    """Track parameters over a whole record, with change detection.

    Parameters
    ----------
    problem : Problem
        The original model bound to the record
        (:func:`bondgraph.inference.problem.make_problem`): record arrays,
        prior of the states, fixed values, noise levels, UKF options.
    tm : TrackingModel
        The augmented model (its original graph is ``problem.model``'s).
    start, std : dict, optional
        Start values and prior std of the tracked parameters
        (:func:`tracking_prior`).
    drift : dict, optional
        Drift intensities [unit/sqrt(s)] over those of ``tm``.
    options : TrackOptions, optional

    Returns
    -------
    TrackResult

    Raises
    ------
    NumericalError
        The filter fails (the reason named).
    ModelError, OptionError
        A parameter not tracked; options of the wrong type.

    Notes
    -----
    The method: the augmented-state UKF (Jazwinski 1970), the windowed GLR
    test of :mod:`bondgraph.inference.changes` (Basseville & Nikiforov
    1993) on the clipped updates, restart at the estimated change time
    (Willsky & Jones 1976) and the unscented RTS smoother per segment
    (Särkkä 2008). Where the updates of that pass are serially correlated
    (``options.calibrate``, :func:`~bondgraph.inference.changes.serial_inflation`
    >= 2), the record is tracked once more with them divided by √λ
    (``settings["inflation"]``).
    """
    opts = _checked(options, TrackOptions, "track options")
    x0, P0, th = tracking_prior(problem, tm, start, std, opts.prior_rel)
    th = th if not drift else tm.theta(dict(zip(problem.model.params, problem.theta)), drift)
    ukf = filter_options(problem.ukf, tm, opts)
    R = problem.noise.covariance(tm.model, th[None, :])
    t, u, y = problem.t, problem.u, problem.y
    dt = float(np.median(np.diff(t))) if t.size > 1 else 1.0
    window, obs_window = opts.samples(dt)
    h = (None if opts.false_alarm_hours is None else
         glr_threshold(opts.false_alarm_hours * 3600.0, dt, window, len(tm.tracked)))
    sigma0 = reference_std(tm, x0, opts)
    lam = np.ones(len(tm.tracked))
    segs, changes = _segments(tm, (t, u, y), th, (x0, P0), ukf, R, (h, lam), window, opts, std)
    res = _stitch(tm, t, segs, changes, h)
    if h is not None and opts.calibrate:    # the updates' own spread, the changes restarted
        obs = observable_mask(res.information, sigma0, obs_window, opts.observable_ratio)
        lam = np.array([serial_inflation(np.where(obs[:, c], res.increments[:, c], np.nan),
                                         window) for c in range(lam.size)])
        if np.any(lam > 1.0):               # once more, the test calibrated to it
            segs, changes = _segments(tm, (t, u, y), th, (x0, P0), ukf, R, (h, lam), window,
                                      opts, std)
            res = _stitch(tm, t, segs, changes, h)
    res.observable = observable_mask(res.information, sigma0, obs_window, opts.observable_ratio)
    mark_at_start(res.changes, res.names, res.observable, window)
    if opts.smooth:
        res.smoothed, res.smoothed_std = _smoothed(tm, t, u, th, segs, ukf)
    res.settings = dict(ukf=ukf.to_dict(), track=opts.to_dict(), window=window, dt=dt,
                        theta=dict(zip(tm.model.params, th.tolist())),
                        sigma0=dict(zip(tm.names, sigma0.tolist())),
                        inflation=dict(zip(tm.names, lam.tolist())),
                        boxes={tp.name: (tp.lower, tp.upper) for tp in tm.tracked
                               if tp.transform == "logit"})
    return res


def _filter_segment(tm, rec, th, prior, ukf, R, s0: int, s1: int | None = None) -> _Segment:
    """The UKF from sample ``s0`` (prior ``(x, P)`` there) to the end (to
    ``s1``, exclusive, when given)."""
    t, u, y = rec
    x, P = prior
    t, u, y = t[:s1], u[:s1], y[:s1]
    res = ukf_nll(tm.model, t[s0:], u[s0:], y[s0:], th[None, :], x, P, options=ukf, R=R,
                  store="full")
    if not np.isfinite(res.nll[0]):
        raise NumericalError(f"the tracking filter fails: {res.reasons[0]}")
    xf, Pf = res.x_filt[:, 0], res.P_filt[:, 0]
    idx = tm.state_indices
    q2 = np.asarray(tm.model.proc_std(th[None, :]), float)[0][idx] ** 2
    dts = np.concatenate([[0.0], np.diff(t[s0:])])
    S = np.stack([standardised_increments(xf[:, i], Pf[:, i, i], x[i], P[i, i], q2[c] * dts)
                  for c, i in enumerate(idx)], -1)
    info = np.stack([information_gain(Pf[:, i, i], P[i, i], q2[c] * dts,
                                      tm.tracked[c].slope(xf[:, i]))
                     for c, i in enumerate(idx)], -1)
    return _Segment(s0, xf, Pf, (x, P), float(res.nll[0]), S, np.zeros_like(S), info,
                    nis=res.nis[:, 0], dof=np.isfinite(y[s0:]).sum(axis=1),
                    terms=res.nll_terms[:, 0])


def reference_std(tm: TrackingModel, x0, options: TrackOptions) -> np.ndarray:
    """σ₀ of the observability test (k,) [unit]: ``prior_rel`` × |start|
    (× the box width at a start of 0), whatever prior std was given."""
    out = []
    for tp, i in zip(tm.tracked, tm.state_indices):
        p0 = float(tp.value(x0[i]))
        out.append(options.prior_rel * (abs(p0) if p0 != 0 else tp.upper - tp.lower))
    return np.array(out)


def _segments(tm, rec, th, prior, ukf, R, detector, window, opts, std):
    """The filter over the record, restarted at each detected change.
    ``detector`` is ``(h, lam)``: the threshold (None: no detection) and
    each parameter's serial inflation (its updates divided by √λ before the
    test)."""
    t, u, y = rec
    h, lam = detector
    unit = 1.0 / np.sqrt(lam)
    holdoff = window if opts.holdoff_s is None else int(round(opts.holdoff_s / (
        np.median(np.diff(t)) if t.size > 1 else 1.0)))
    dt = np.median(np.diff(t)) if t.size > 1 else 1.0
    ow, sigma0 = opts.samples(dt)[1], reference_std(tm, prior[0], opts)
    s0, segs, changes = 0, [], []
    changed, P_start, bare = None, _states_prior(tm, prior[1]), prior
    while True:
        if not segs and h is not None:  # to the first alarm only: filtered again from there
            seg, alarm, obs = _first_pass(tm, (t, u, y), th, prior, ukf, R,
                                          (h, window, ow, sigma0, unit), opts)
        elif changed is None:
            seg = _filter_segment(tm, (t, u, y), th, prior, ukf, R, s0)
        else:
            seg, prior = _restarted(tm, (t, u, y), th, prior, bare, ukf, R, s0)
        if changed is not None:         # once more, from the change time, centred on
            i = int(tm.state_indices[changed])      # what the first pass found
            x = prior[0].copy()
            x[i] = seg.x[-1, i]
            prior = (x, _reset(tm, changed, x, prior[1], std, opts, None))
            seg = _filter_segment(tm, (t, u, y), th, prior, ukf, R, s0)
        if segs and h is not None:
            watched = seg.S * unit
            if segs:                     # a restart: skip the re-estimation's transient
                watched[:holdoff] = np.nan
            obs = observable_mask(seg.info, sigma0, ow, opts.observable_ratio)
            watched[~obs] = np.nan       # not observable there: its updates are noise
            alarm, seg.G = first_alarm(watched, h, window, allowed=obs, clip=opts.glr_clip)
        elif h is None:
            alarm = None
        segs.append(seg)
        if alarm is None or len(changes) >= opts.max_changes:
            seg.end = t.size
            return segs, changes
        ka, j, c0, g = alarm
        cidx = max(s0 + j, s0 + 2)
        seg.end = cidx
        x, P = seg.x[cidx - 1 - s0].copy(), seg.P[cidx - 1 - s0].copy()
        ok = [k for k in range(len(tm.tracked)) if obs[cidx - 1 - s0, k]] or [c0]
        y = y.copy()
        y[cidx - 1] = np.nan            # its update is already in the prior
        c, iso = _isolate(tm, (t, u, y), th, (x, P), ukf, R,
                          (cidx - 1, min(t.size, s0 + ka + window + 1)),
                          lambda k: _reset(tm, k, x, P, std, opts, P_start), ok)
        changes.append(Change(tm.names[c], cidx, s0 + ka, float(t[cidx]), float(t[s0 + ka]),
                              g, h, tm.names[c0], iso))
        prior = (x, _reset(tm, c, x, P, std, opts, P_start))
        bare = (x, _reset(tm, c, x, P, std, opts, None))
        s0, changed = cidx - 1, c


def _restarted(tm, rec, th, prior, bare, ukf, R, s0) -> tuple:
    """``(segment, prior)``: the filter restarted at a change from
    ``prior`` (the original states' prior covariance added,
    :func:`_reset`), or, where that filter fails, from ``bare`` (only the
    changed parameter's variance reset). The added covariance spreads the
    sigma points over the states' whole scales, where a stiff law can take
    a step outside RK4's stability region: a user's closed-loop drive with
    Dahl friction (rest stiffness 33 000 N/m against Fc 3.8 N) had its
    friction state spread over hundreds of newtons at a restart, and the
    command ended with "the tracking filter fails" at the restart's first
    sample.

    Raises
    ------
    NumericalError
        The filter fails from ``bare`` too.
    """
    try:
        return _filter_segment(tm, rec, th, prior, ukf, R, s0), prior
    except NumericalError:
        return _filter_segment(tm, rec, th, bare, ukf, R, s0), bare


#: the first pass of :func:`track` filters chunks of this length [s] (at least
#: four detector windows) and stops after the chunk of the first alarm
CHUNK_S = 10.0


def _first_pass(tm, rec, th, prior, ukf, R, detector, opts):
    """The first pass over the record, stopped at the first alarm: the
    filter in chunks of :data:`CHUNK_S` s, each restarted from the previous
    one's filtered mean and covariance at its last sample (that sample's
    update not repeated), the detector run on each new chunk with the
    trailing history its windows need (the previous chunk). The same
    numbers as one pass to the end, up to the end of the alarm's chunk:
    the filter is the same recursion and the GLR and observability windows
    are trailing; the samples after the alarm are filtered again from the
    change anyway.

    ``detector`` is ``(h, window, ow, sigma0, unit)`` (threshold, GLR
    window, observability window, reference std, the factor of each
    parameter's updates, 1/√λ). Returns the segment (``G``
    filled, ``end`` unset), the first alarm (:func:`first_alarm`'s, sample
    indices from 0) or None, and the observability mask (N_seg, k).
    """
    t, u, y = rec
    h, window, ow, sigma0, unit = detector
    dt = float(np.median(np.diff(t))) if t.size > 1 else 1.0
    step = max(int(round(CHUNK_S / dt)), 4 * max(window, ow), 2)
    parts, a, alarm = [], 0, None
    while a < t.size and alarm is None:
        b = min(t.size, a + step)
        if not parts:
            part = _filter_segment(tm, rec, th, prior, ukf, R, 0, b)
        else:
            yy = y[a - 1:b].copy()
            yy[0] = np.nan                  # its update is in the prior already
            part = _filter_segment(tm, (t[a - 1:b], u[a - 1:b], yy), th,
                                   (parts[-1].x[-1], parts[-1].P[-1]), ukf, R, 0)
            part = _dropped_first(part, a)
        lo = parts[-1].start if parts else 0
        info = np.concatenate([p.info for p in parts[-1:]] + [part.info])
        obs = observable_mask(info, sigma0, ow, opts.observable_ratio)
        watched = np.concatenate([p.S for p in parts[-1:]] + [part.S]) * unit
        watched[~obs] = np.nan
        allowed = obs.copy()
        allowed[:a - lo] = False            # judged with the previous chunk already
        alarm, G = first_alarm(watched, h, window, allowed=allowed, clip=opts.glr_clip)
        part.G = G[a - lo:]
        alarm = None if alarm is None else (alarm[0] + lo, alarm[1] + lo, *alarm[2:])
        parts.append(part)
        a = b
    seg = _Segment(0, *(np.concatenate([getattr(p, f) for p in parts]) for f in ("x", "P")),
                   prior, float(sum(p.nll for p in parts)),
                   *(np.concatenate([getattr(p, f) for p in parts]) for f in ("S", "G", "info")),
                   nis=np.concatenate([p.nis for p in parts]),
                   dof=np.concatenate([p.dof for p in parts]),
                   terms=np.concatenate([p.terms for p in parts]))
    return seg, alarm, observable_mask(seg.info, sigma0, ow, opts.observable_ratio)


def _dropped_first(seg: _Segment, start: int) -> _Segment:
    """A chunk's segment without its first sample (the previous chunk's
    last, repeated as the restart's prior), starting at ``start``."""
    return _Segment(start, seg.x[1:], seg.P[1:], seg.prior, seg.nll, seg.S[1:], seg.G[1:],
                    seg.info[1:], nis=seg.nis[1:], dof=seg.dof[1:], terms=seg.terms[1:])


def _isolate(tm, rec, th, prior, ukf, R, span, reset, candidates) -> tuple[int, dict]:
    """Which tracked parameter changed: the filter from ``span[0]`` to
    ``span[1]`` restarted with each candidate's variance reset
    (``reset(k)``), the one of smallest negative log-likelihood wins (the
    GLR over a set of change signatures; Willsky & Jones 1976). Returns its
    column and the NLL differences by name."""
    t, u, y = rec
    a, e = span
    x = prior[0]
    if len(candidates) == 1:
        return candidates[0], {tm.names[candidates[0]]: 0.0}
    nll = {}
    for k in candidates:
        res = ukf_nll(tm.model, t[a:e], u[a:e], y[a:e], th[None, :], x, reset(k), options=ukf,
                      R=R)
        nll[k] = float(res.nll[0]) if np.isfinite(res.nll[0]) else np.inf
    best = min(nll, key=nll.get)
    return best, {tm.names[k]: v - nll[best] for k, v in nll.items()}


#: |z| of a logit-tracked parameter at a restart: p within 4.5e-5 of the box's
#: width from a bound, where the transform's slope is still 4.5e-5 x the width
LOGIT_LIMIT = 10.0


def _states_prior(tm, P0) -> np.ndarray:
    """The prior covariance of the original states (tracked rows and columns zero)."""
    P = np.array(P0, float)
    idx = tm.state_indices
    P[idx, :] = 0.0
    P[:, idx] = 0.0
    return P


def _reset(tm, c: int, x, P, std, opts: TrackOptions, P_start) -> np.ndarray:
    """P at a restart: the tracked parameter ``c``'s variance reset
    (``opts.reset_rel`` of its value, at least its prior rule; a logit
    state's at most the box's own spread,
    :data:`~bondgraph.core.augment.LOGIT_UNIFORM_STD`) and its cross
    covariances zero; with ``P_start``, the original states' prior
    covariance added (their estimates went through the samples between
    the change and its detection with the old value). A logit state is
    first brought within ±:data:`LOGIT_LIMIT` (in place in ``x``)."""
    tp, i = tm.tracked[c], int(tm.state_indices[c])
    if tp.transform == "logit":     # restart inside the box: the slope of a state
        x[i] = np.clip(x[i], -LOGIT_LIMIT, LOGIT_LIMIT)     # run onto a bound is 0
    p = float(tp.value(x[i]))
    scale = abs(p) if p != 0 else tp.upper - tp.lower
    sd = max(float((std or {}).get(tp.name, opts.prior_rel * scale)), opts.reset_rel * scale)
    P = P.copy()
    P[i, :] = 0.0
    P[:, i] = 0.0
    P[i, i] = float(tp.std_of(p, sd)) ** 2     # at most the box's own spread (logit)
    return P if P_start is None else P + P_start


def _kept(seg: _Segment, first: bool) -> tuple[int, int]:
    """Absolute range [a, e) of the samples a segment reports."""
    return (seg.start if first else seg.start + 1), seg.end


def _stitch(tm, t, segs, changes, h) -> TrackResult:
    """One result from the segments' kept ranges, the changes completed."""
    N, k, n = t.size, len(tm.tracked), tm.model.n_x
    xs, Ps = np.full((N, n), np.nan), np.full((N, n, n), np.nan)
    S, G, info = np.full((N, k), np.nan), np.zeros((N, k)), np.zeros((N, k))
    nis, dof, terms = np.full(N, np.nan), np.zeros(N, dtype=int), np.zeros(N)
    for i, seg in enumerate(segs):
        a, e = _kept(seg, i == 0)
        r = slice(a - seg.start, e - seg.start)
        xs[a:e], Ps[a:e], S[a:e], G[a:e] = seg.x[r], seg.P[r], seg.S[r], seg.G[r]
        info[a:e], nis[a:e], dof[a:e] = seg.info[r], seg.nis[r], seg.dof[r]
        terms[a:e] = seg.terms[r]
    est, sd = tm.values(xs, Ps)
    for ch, seg in zip(changes, segs[1:]):
        c = tm.names.index(ch.parameter)
        ch.before, ch.before_std = float(est[ch.index - 1, c]), float(sd[ch.index - 1, c])
        ch.after, ch.after_std = float(est[seg.end - 1, c]), float(sd[seg.end - 1, c])
    return TrackResult(t=t, names=tm.names, units=[tp.unit for tp in tm.tracked], estimate=est,
                       std=sd, x_filt=xs, states=list(tm.model.states),
                       nll=float(np.sum(terms)), increments=S, statistic=G,
                       threshold=h, changes=changes, information=info, nis=nis,
                       nis_dof=dof, nll_terms=terms)


def _smoothed(tm, t, u, th, segs, ukf):
    """RTS-smoothed estimates and std (N, k), segment by segment."""
    N, k = t.size, len(tm.tracked)
    est, sd = np.full((N, k), np.nan), np.full((N, k), np.nan)
    for i, seg in enumerate(segs):
        e = seg.end - seg.start
        xs, Ps = rts_backward(tm.model, t[seg.start:seg.end], u[seg.start:seg.end], th,
                              seg.x[:e], seg.P[:e], options=ukf)
        a, b = _kept(seg, i == 0)
        est[a:b], sd[a:b] = tm.values(xs[a - seg.start:], Ps[a - seg.start:])
    return est, sd


def check_tracked(names: Sequence[str], model) -> None:
    """Raise :class:`~bondgraph.errors.OptionError` for an empty list of
    tracked parameters or one the model lacks (named)."""
    if not names:
        raise OptionError("no parameter to track: give at least one (--track p1,p2)")
    for n in names:
        if n not in model.params:
            raise OptionError(f"cannot track '{n}': model '{model.name}' has no such parameter "
                              f"(parameters: {', '.join(model.params)})")


# ------------------------------------------------------------------ discretisation
#: the most substeps :func:`choose_substeps` tries
MAX_SUBSTEPS = 128
#: the largest accepted discretisation error of a window's log-likelihood, in
#: units of that log-likelihood's own sampling std √(m/2)
SUBSTEP_TOLERANCE = 1.0


@dataclass(frozen=True)
class SubstepChoice:
    """What :func:`choose_substeps` found.

    Attributes
    ----------
    substeps : int
        The substeps chosen: the first that passed, else the largest tried.
    ok : bool
        Whether it passed (False: :data:`MAX_SUBSTEPS` reached first).
    difference : dict
        s -> D(s, 2s): the largest |ΔNLL_w| / √(m_w/2) over the windows
        between the filters with s and 2s substeps.
    error : dict
        s -> the estimated error of s in the same unit (inf outside the
        asymptotic range).
    worst : dict
        s -> ``(t_start, t_end)`` [s] of the window of D(s, 2s).
    method : str
    window_s : float
    """

    substeps: int
    ok: bool
    difference: dict
    error: dict
    worst: dict
    method: str
    window_s: float

    def line(self) -> str:
        """One line: what was chosen and the evidence."""
        tried = "; ".join(f"{s}: {self.error[s]:.3g} (D {self.difference[s]:.3g} at "
                          f"{self.worst[s][0]:.4g}-{self.worst[s][1]:.4g} s)"
                          for s in self.error)
        verdict = "chosen" if self.ok else f"NOT converged within {MAX_SUBSTEPS} substeps"
        return (f"tracking filter {self.method}({self.substeps}) {verdict}: estimated error of "
                f"a {self.window_s:g} s window's log-likelihood in its sampling std "
                f"(tolerance {SUBSTEP_TOLERANCE:g}) by substeps: {tried}")


def choose_substeps(problem, tm: TrackingModel, *, start: Mapping[str, float] | None = None,
                    std: Mapping[str, float] | None = None,
                    drift: Mapping[str, float] | None = None,
                    options: TrackOptions | None = None, window_s: float | None = None,
                    max_substeps: int = MAX_SUBSTEPS) -> SubstepChoice:
    """The tracking filter's substeps, from the record it tracks.

    :func:`track` is run with s, 2s, 4s substeps (the problem's method,
    hold, prior; the same detector; no smoothing) and the record cut into
    windows of ``window_s``. D(s, 2s) is the largest difference of two
    filters' negative log-likelihoods in a window, in units of that
    log-likelihood's sampling std under the model, √(m_w/2) (half a χ² with
    m_w degrees of freedom, m_w the values measured in w). With the observed
    contraction r = D(s, 2s)/D(2s, 4s), the error of s is estimated as
    D(s, 2s)·r/(r − 1) (Richardson; r ≈ 2^p for a method of order p), and as
    infinite when r <= 1: the steps are outside their asymptotic range
    (Roache 1998), e.g. all so long against a stiff mode that they damp it
    alike. The first s whose error is at most :data:`SUBSTEP_TOLERANCE` is
    chosen, so that no stretch of the record tells the filter from a finer
    one; else s doubles.

    Why the tracked record and not :func:`bondgraph.inference.discretise.choose_discretisation`:
    that check runs from the prior mean with the parameters constant, so it
    never sees the stretches a changed parameter brings about (a tire
    slipping past its friction peak after the friction dropped), where a
    coarse step mispredicts by many noise std and the filter explains its
    own discretisation error by moving the tracked parameters, with a std
    that does not know it. The window is local (the observability window)
    because such a stretch lasts a second or two: summed over the record it
    would be lost in the total.

    Parameters
    ----------
    problem : Problem
        The original model on the record (its ``ukf`` gives the method and
        the first substeps tried).
    tm : TrackingModel
    start, std, drift, options
        As for :func:`track`.
    window_s : float, optional
        The windows [s] (default the observability window,
        ``options.seconds(dt)[1]``).
    max_substeps : int
        The most substeps run (>= 4 x the problem's).

    Returns
    -------
    SubstepChoice
        ``problem.conditioned_on(disc=replace(problem.disc, substeps=c.substeps))``
        is the problem to track with.

    Raises
    ------
    OptionError
        ``window_s`` not > 0 or ``max_substeps`` below 4 x the problem's.

    References
    ----------
    Roache, P. J. (1998). Verification and Validation in Computational
    Science and Engineering, ch. 5 (observed order, asymptotic range).
    """
    opts = replace(_checked(options, TrackOptions, "track options"), smooth=False)
    t = problem.t
    w_s = float(opts.seconds(float(np.median(np.diff(t))) if t.size > 1 else 1.0)[1]
                if window_s is None else window_s)
    s = int(problem.ukf.substeps)
    if not (np.isfinite(w_s) and w_s > 0) or int(max_substeps) < 4 * s:
        raise OptionError(f"choose_substeps: window_s must be > 0 and max_substeps >= {4 * s}, "
                          f"got {window_s!r}, {max_substeps!r}")
    runs = _SubstepRuns(problem, tm, dict(start=start, std=std, drift=drift, options=opts), w_s)
    err = {}
    while 4 * s <= int(max_substeps):
        err[s] = richardson_error(runs.difference(s), runs.difference(2 * s))
        if err[s] <= SUBSTEP_TOLERANCE:
            return runs.choice(s, True, err)
        s *= 2
    done = [n for n, v in runs.runs.items() if v is not None]      # the finest that ran
    return runs.choice(max(done, default=s), False, err)


def richardson_error(d1: float, d2: float) -> float:
    """The error of the coarsest of three discretisations s, 2s, 4s.

    Parameters
    ----------
    d1, d2 : float
        D(s, 2s) and D(2s, 4s), differences of a quantity between
        successive discretisations (>= 0, any unit).

    Returns
    -------
    float
        d1·r/(r − 1) with the observed contraction r = d1/d2 (Richardson
        extrapolation; r ≈ 2^p for a method of order p), in d1's unit; inf
        when r <= 1 (outside the asymptotic range: the differences do not
        shrink) or d1 is not finite; 0 when both are 0.

    References
    ----------
    Roache, P. J. (1998). Verification and Validation in Computational
    Science and Engineering, ch. 5.
    """
    if not np.isfinite(d1):
        return float("inf")
    if d1 == 0.0 and d2 == 0.0:
        return 0.0
    r = np.inf if d2 == 0.0 else d1 / d2
    return float(d1) if r == np.inf else (float(d1 * r / (r - 1.0)) if r > 1.0 else float("inf"))


class _SubstepRuns:
    """The tracker's runs by substeps (None where the filter failed) and the
    window differences between s and 2s, each computed once."""

    def __init__(self, problem, tm, kwargs, window_s):
        self.problem, self.tm, self.kwargs, self.window_s = problem, tm, kwargs, window_s
        self.runs, self.diff, self.worst = {}, {}, {}

    def run(self, n: int):
        if n not in self.runs:
            pr = self.problem.conditioned_on(disc=replace(self.problem.disc, substeps=n))
            try:
                self.runs[n] = track(pr, self.tm, **self.kwargs)
            except NumericalError:
                self.runs[n] = None
        return self.runs[n]

    def difference(self, n: int) -> float:
        if n not in self.diff:
            a, b = self.run(n), self.run(2 * n)
            t = self.problem.t
            self.diff[n], self.worst[n] = ((np.inf, (float(t[0]), float(t[-1])))
                                           if a is None or b is None
                                           else window_excess(a, b, self.window_s))
        return self.diff[n]

    def choice(self, n: int, ok: bool, err: dict) -> SubstepChoice:
        return SubstepChoice(n, ok, dict(self.diff), dict(err), dict(self.worst),
                             self.problem.ukf.method, self.window_s)


def window_excess(a: TrackResult, b: TrackResult, window_s: float) -> tuple[float, tuple]:
    """How far two tracking results on one record differ, window by window.

    Parameters
    ----------
    a, b : TrackResult
        Two runs over the same samples (``nll_terms`` and ``nis_dof`` set).
    window_s : float
        Window length [s] (> 0); the record is cut into consecutive windows.

    Returns
    -------
    excess : float
        The largest |Σ_w (ℓ_a − ℓ_b)| / √(m_w/2) over the windows w, ℓ the
        per-sample NLL terms [nats] and m_w the values measured in w: the
        difference in units of the window log-likelihood's sampling std
        under the model (half a χ² with m_w degrees of freedom); inf where a
        term is not finite. 0 when nothing is measured.
    window : tuple of float
        ``(t_start, t_end)`` [s] of that window (the whole record for 0).
    """
    t = a.t
    dt = float(np.median(np.diff(t))) if t.size > 1 else 1.0
    n = max(1, int(round(window_s / dt)))
    d = np.nan_to_num(a.nll_terms - b.nll_terms, nan=np.inf, posinf=np.inf, neginf=np.inf)
    best, where = 0.0, (float(t[0]), float(t[-1]))
    for i in range(0, t.size, n):
        m = float(np.sum(a.nis_dof[i:i + n]))
        if m > 0:
            e = abs(float(np.sum(d[i:i + n]))) / np.sqrt(0.5 * m)
            if e > best:
                best, where = e, (float(t[i]), float(t[min(i + n, t.size) - 1]))
    return best, where


# ------------------------------------------------------------------ drift intensities
def estimate_drift(problem, tm: TrackingModel, names: Sequence[str] | None = None, *,
                   start: Mapping[str, float] | None = None,
                   std: Mapping[str, float] | None = None, fit=None,
                   options: TrackOptions | None = None):
    """Maximum-likelihood drift intensities, with their Cramér-Rao std.

    The likelihood is the tracking filter's (the augmented-state UKF with
    the prior of :func:`tracking_prior`, no change detection), maximised by
    :func:`bondgraph.inference.estimate.estimate` over the parameters
    ``drift.<p>`` of the augmented model.

    Parameters
    ----------
    problem : Problem
        The original model on the record.
    tm : TrackingModel
    names : sequence of str, optional
        Tracked parameters whose drift is estimated (default all).
    start, std : dict, optional
        As for :func:`track`.
    fit : FitOptions, optional
    options : TrackOptions, optional
        ``prior_rel`` and ``match_spread`` are read.

    Returns
    -------
    EstimationResult
        ``params`` are ``drift.<p>`` [unit/sqrt(s)], with ``std`` from the
        Hessian of the NLL (Cramér-Rao).

    Raises
    ------
    ModelError
        A name that is not tracked.
    EstimationError
        No finite likelihood in the search.
    """
    from bondgraph.inference.estimate import estimate
    from bondgraph.inference.prior import PriorSpec
    from bondgraph.inference.problem import make_problem

    opts = _checked(options, TrackOptions, "track options")
    x0, P0, th = tracking_prior(problem, tm, start, std, opts.prior_rel)
    drift = [tm._spec(n).drift_param for n in (names or tm.names)]
    fixed = {p: v for p, v in zip(tm.model.params, th) if p not in drift}
    aug = make_problem(tm.model, problem.arrays, prior=PriorSpec(x0=x0, P0=P0),
                       noise=problem.noise, ukf=filter_options(problem.ukf, tm, opts),
                       fixed=fixed)
    return estimate(aug, drift, fit=fit)


# ------------------------------------------------------------------ streaming
class Tracker:
    """Streaming tracker: one sample per :meth:`update`, the same predict
    and update steps as the batch filter, so that it equals :func:`track`
    without change detection sample for sample. With the numba backend
    (the default of :class:`UKFOptions`) each sample is one call of the
    compiled kernel on arrays allocated once
    (:class:`~bondgraph.inference.ukf_numba.StepKernel`); with numpy, or
    options the kernel lacks, :func:`bondgraph.inference.ukf.predict` and
    :func:`~bondgraph.inference.ukf.update`.

    Parameters
    ----------
    tm : TrackingModel
    theta : array (n_theta,)
        The augmented model's parameters (:meth:`TrackingModel.theta`).
    x0 : array (n_x,)
    P0 : array (n_x, n_x)
        Prior at the first sample (:func:`tracking_prior`).
    ukf : UKFOptions, optional
        The filter's options (as given: :func:`filter_options` is the
        caller's; :meth:`from_problem` applies it).
    R : array (n_y, n_y), optional
        Measurement-noise covariance (default ``meas_std(θ)²``).
    observe : tuple (sigma0 (k,), window, ratio), optional
        The observability test of :func:`track`
        (:func:`~bondgraph.inference.changes.observable_mask`: reference std
        [unit], trailing window [samples], ρ_max); after each update the
        attributes ``information`` (k,) [1/unit²] and ``observable`` (k,)
        hold the sample's values (:meth:`from_problem` sets it as
        :func:`track` does). Default: not tested.
    watch : OnlineWatch, optional
        Change detection on-line (needs ``observe``; :meth:`from_problem`
        sets both from the :class:`~bondgraph.inference.options.TrackOptions`
        unless its ``false_alarm_hours`` is None). After each update:
        ``statistic`` (k,) the GLR statistic [nats]; ``suspected`` an alarm
        whose parameter is not yet decided (or None); ``alarm`` the
        :class:`Change` attributed at this sample (or None), also appended
        to ``changes``. Default: no detection.

    Raises
    ------
    NumericalError
        The filter cannot start (the reason named).
    OptionError
        ``watch`` without ``observe``.

    Examples
    --------
    >>> trk = Tracker.from_problem(problem, tm)            # doctest: +SKIP
    >>> for k in range(N):                                  # doctest: +SKIP
    ...     est, sd = trk.update(t[k], u[k], y[k])
    ...     if trk.alarm is not None:
    ...         print(trk.alarm.parameter, trk.alarm.time)

    References
    ----------
    Basseville & Nikiforov (1993), §2.4.3 (the windowed GLR); Willsky &
    Jones (1976) (restart at the change time, the change isolated by
    likelihood).
    """

    def __init__(self, tm: TrackingModel, theta, x0, P0, *, ukf: UKFOptions | None = None,
                 R=None, observe: tuple | None = None, watch: "OnlineWatch | None" = None):
        from bondgraph.inference.options import ukf_options
        from bondgraph.inference.sigma import merwe_weights
        from bondgraph.inference.ukf import FilterBatch, ROS2_JACOBIAN
        from bondgraph.numerics.integrators import make_step

        self.tm, self.opts = tm, ukf_options(ukf).uniform()     # no record: no refined runs
        m = tm.model
        self.wts = merwe_weights(m.n_x, self.opts.alpha, self.opts.beta, self.opts.kappa)
        self.step = make_step(m, self.opts.method, self.opts.substeps,
                              jacobian=ROS2_JACOBIAN[self.opts.jacobian])
        R = None if R is None else np.asarray(R, float).reshape(1, m.n_y, m.n_y)
        self.batch = FilterBatch(m, [np.nan], np.asarray(theta, float)[None, :],
                                 np.asarray(x0, float)[None, :],
                                 np.asarray(P0, float)[None, :, :], None, R)
        self.batch.t = []
        self.k, self._u, self._t = 0, None, None
        self._stepper = self._compiled_step(m)
        idx = tm.state_indices
        self._idx, self._Pz = idx, np.asarray(P0, float)[idx, idx]
        self._q2 = np.asarray(m.proc_std(np.asarray(theta, float)[None, :]), float)[0][idx] ** 2
        self.information = np.zeros(len(idx))
        self._box = (np.array([tp.lower for tp in tm.tracked]),
                     np.array([tp.upper - tp.lower for tp in tm.tracked]),
                     np.array([tp.transform == "logit" for tp in tm.tracked]))
        self.observable = None
        if observe is not None:
            sigma0, window, ratio = observe
            self._need = np.asarray(sigma0, float) ** 2, 1.0 / float(ratio) - 1.0
            self._ring, self._sum = np.zeros((max(1, int(window)), len(idx))), np.zeros(len(idx))
            self.observable = np.zeros(len(idx), bool)
        #: the sample at which each parameter first became observable (-1: not yet)
        self._first_observable = np.full(len(idx), -1)
        self._z, self._R, self.watch = np.asarray(x0, float)[idx].copy(), R, watch
        self.changes: list[Change] = []
        self.alarm: Change | None = None
        self.suspected: _Suspected | None = None
        self.statistic = np.zeros(len(idx))
        if watch is not None:
            if observe is None:
                raise OptionError("Tracker: change detection (watch) needs the observability "
                                  "test (observe): Tracker.from_problem sets both")
            self._det = _OnlineDetector(watch, len(idx))

    def _compiled_step(self, m):
        """The compiled one-sample step (:class:`~bondgraph.inference.ukf_numba.StepKernel`)
        when the options' backend is numba and the kernel serves them; else
        None (numpy's predict and update)."""
        from bondgraph.inference.ukf import _backend_for
        from bondgraph.inference.ukf_numba import StepKernel

        if not self.batch.size:
            raise NumericalError(f"the tracker cannot start: {self.batch.reasons[0]}")
        kernels, _, _ = _backend_for(m, self.opts)
        return None if kernels is None else StepKernel(kernels, self.batch, m.n_u, self.opts,
                                                       self.wts)

    @classmethod
    def from_problem(cls, problem, tm: TrackingModel, *, start=None, std=None, drift=None,
                     options: TrackOptions | None = None,
                     inflation: Mapping[str, float] | None = None) -> "Tracker":
        """A tracker with the prior, parameters, noise and options that
        :func:`track` uses for ``problem`` (same arguments), detecting
        changes on-line unless ``options.false_alarm_hours`` is None
        (:class:`OnlineWatch`). ``inflation``: parameter -> λ, the serial
        inflation of its updates (:func:`~bondgraph.inference.changes.serial_inflation`;
        ``settings["inflation"]`` of a :func:`track` run on a recorded
        drive): an on-line tracker has no second pass to measure it; default
        1 (white updates).

        Raises
        ------
        ModelError
            ``inflation`` names a parameter not tracked.
        OptionError
            A λ that is not a finite number >= 1.
        """
        opts = _checked(options, TrackOptions, "track options")
        x0, P0, th = tracking_prior(problem, tm, start, std, opts.prior_rel)
        th = th if not drift else tm.theta(dict(zip(problem.model.params, problem.theta)), drift)
        R = problem.noise.covariance(tm.model, th[None, :])
        t = problem.t
        dt = float(np.median(np.diff(t))) if t.size > 1 else 1.0
        window, ow = opts.samples(dt)
        observe = (reference_std(tm, x0, opts), ow, opts.observable_ratio)
        watch = None
        if opts.false_alarm_hours is not None:
            lam = np.ones(len(tm.tracked))
            for name, v in dict(inflation or {}).items():
                tm._spec(name)
                if not (np.isfinite(v) and v >= 1.0):
                    raise OptionError(f"Tracker: inflation of '{name}' must be a number >= 1, "
                                      f"got {v!r}")
                lam[tm.names.index(name)] = float(v)
            holdoff = window if opts.holdoff_s is None else int(round(opts.holdoff_s / dt))
            watch = OnlineWatch(glr_threshold(opts.false_alarm_hours * 3600.0, dt, window,
                                              len(tm.tracked)),
                                window, holdoff, 1.0 / np.sqrt(lam), opts, dict(std or {}),
                                _states_prior(tm, P0))
        return cls(tm, th, x0, P0, ukf=filter_options(problem.ukf, tm, opts),
                   R=None if R is None else R[0], observe=observe, watch=watch)

    def update(self, t: float, u, y) -> tuple[np.ndarray, np.ndarray]:
        """Filter one sample.

        Parameters
        ----------
        t : float
            Its time [s] (after the previous one).
        u : array (n_u,)
            Inputs (model units).
        y : array (n_y,)
            Outputs, NaN where not measured.

        Returns
        -------
        (estimate (k,), std (k,))
            The tracked parameters after the update (parameter units); at
            a sample where a change is attributed (``alarm``), the restarted
            filter's.

        Raises
        ------
        NumericalError
            The filter fails (the reason named), or time does not increase.
        """
        from bondgraph.inference.ukf import predict, update
        from bondgraph.numerics.integrators import hold_inputs

        b, u, y = self.batch, np.asarray(u, float).reshape(-1), np.asarray(y, float).reshape(-1)
        if self._t is not None and not t > self._t:
            raise NumericalError(f"Tracker.update: time {t!r} does not follow {self._t!r}")
        if self._stepper is not None:
            _, reason = self._stepper.step(b.x[0], b.P[0], self._t, t, self._u, u, y)
            if reason is not None:
                raise NumericalError(f"the tracker fails at t = {t:.6g} s: {reason}")
        else:
            b.t.append(float(t))
            if self.k > 0:
                uk, duk = hold_inputs(np.stack([self._u, u]), self.opts.hold).interval(0)
                predict(b, self.step, uk, b.t[-1] - b.t[-2], self.wts, self.k, duk)
            if b.size and np.isfinite(y).any():
                update(b, self.tm.model, u, y, self.wts, self.k)
            if not b.size:
                raise NumericalError(f"the tracker fails: {b.reasons[0]}")
        z, Pz = b.x[0][self._idx], b.P[0][self._idx, self._idx]
        est, slope = self._transform(z)
        dt = t - self._t if self.k > 0 else 0.0
        s = self._increment(z, Pz, dt)      # before _observe moves the previous variance on
        self._observe(dt, Pz, slope)
        self.k, self._u, self._t = self.k + 1, u, float(t)
        sz = np.sqrt(np.maximum(Pz, 0.0))
        sd = 0.5 * np.abs(self._transform(z + sz)[0] - self._transform(z - sz)[0])
        self.alarm = None
        if self.watch is not None:
            est, sd = self._detect(float(t), u, y, s, est, sd)
        return est, sd

    def _increment(self, z, Pz, dt: float) -> np.ndarray:
        """The standardised update of each tracked state at this sample (k,)
        (:func:`~bondgraph.inference.changes.standardised_increments`, one
        sample), NaN where it carried no information."""
        s = np.array([standardised_increments(z[c:c + 1], Pz[c:c + 1], self._z[c], self._Pz[c],
                                              self._q2[c:c + 1] * dt)[0]
                      for c in range(z.size)])
        self._z = np.array(z, float)
        return s

    def _watched(self, s, k: int) -> np.ndarray:
        """What the detector adds for sample ``k`` (k,): the updates times
        1/√λ, NaN in a restart's holdoff and where not observable, clipped
        (as :func:`track`'s test)."""
        w, d = self.watch, self._det
        row = np.array(s, float) * w.unit
        if d.restarted and k - d.seg0 < w.holdoff:
            row[:] = np.nan
        row[~self.observable] = np.nan
        c = w.options.glr_clip
        return row if c is None else np.clip(row, -c, c)

    def _detect(self, t: float, u, y, s, est, sd):
        """The on-line GLR test at the sample just filtered; at an alarm,
        the change attributed (:meth:`_attribute`). Returns the tracked
        estimates and std at this sample (after a restart, the restarted
        filter's)."""
        d, w, k = self._det, self.watch, self.k - 1
        b = self.batch
        d.hist.append(_Kept(k, t, u.copy(), y.copy(), b.x[0].copy(), b.P[0].copy(),
                            est, sd, self.observable.copy()))
        if self.suspected is not None:
            return self._attribute(est, sd)
        g, L = d.push(self._watched(s, k), self.observable)
        self.statistic = g
        hit = g > w.h
        if hit.any() and len(self.changes) < w.options.max_changes:
            c0 = int(np.argmax(np.where(hit, g, -np.inf)))
            kept = {e.k: e for e in d.hist}
            cidx = min(max(k - int(L[c0]) + 1, d.seg0 + 2, min(kept) + 1), k)
            if cidx - 1 in kept:            # else at a segment's first sample: nothing to restart
                e0 = kept[cidx - 1]
                ok = [c for c in range(len(self.tm.tracked)) if e0.obs[c]] or [c0]
                self.suspected = _Suspected(self.tm.names[c0], cidx, k, float(kept[cidx].t), t,
                                            float(g[c0]), ok)
                return self._attribute(est, sd)
        if self.changes:                    # the re-estimate since the last change
            c = self.tm.names.index(self.changes[-1].parameter)
            self.changes[-1].after, self.changes[-1].after_std = float(est[c]), float(sd[c])
        return est, sd

    def _attribute(self, est, sd):
        """Which parameter changed (:func:`_isolate`, a restart per observable
        candidate over the kept samples from the change to now), checked
        at 0, 1, 2, 4, ... samples after the alarm: decided once the best
        explains them better than every other by more than the threshold h
        [nats], or one window after the alarm (:func:`track`'s look-ahead),
        then :meth:`_restart`. Until then the estimates are the unrestarted
        filter's."""
        p, w, tm, k = self.suspected, self.watch, self.tm, self.k - 1
        m = k - p.alarm_index
        if m < p.due and m < w.window:
            return est, sd
        kept = {e.k: e for e in self._det.hist}
        span = [kept[i] for i in range(p.index - 1, k + 1)]
        t, u = np.array([e.t for e in span]), np.stack([e.u for e in span])
        y = np.stack([e.y for e in span])
        y[0] = np.nan                       # its update is already in the prior
        x, P = span[0].x.copy(), span[0].P.copy()
        c, iso = _isolate(tm, (t, u, y), self.batch.th[0], (x, P), self.opts, self._R,
                          (0, t.size), lambda i: _reset(tm, i, x, P, w.std, w.options,
                                                        w.P_start), p.candidates)
        margin = min([v for n, v in iso.items() if n != tm.names[c]], default=np.inf)
        if margin <= w.h and m < w.window:
            p.due = max(1, 2 * m)
            return est, sd
        return self._restart(span, (t, u, y), (x, P), c, iso)

    def _restart(self, span: list, rec, prior, c: int, iso: dict):
        """The filter restarted at the suspected change (its sample ``span[0]``
        + 1) with parameter ``c``'s variance reset, as :func:`track` restarts
        (twice: the second pass centred on the first's value now), over the
        kept samples ``span`` (``rec``: their arrays, the first output
        masked; ``prior``: the filtered mean and covariance at the first);
        the change appended to ``changes`` and set as ``alarm``."""
        w, tm, p, th = self.watch, self.tm, self.suspected, self.batch.th[0]
        x, P = prior
        prior = (x, _reset(tm, c, x, P, w.std, w.options, w.P_start))
        seg = _filter_segment(tm, rec, th, prior, self.opts, self._R, 0)
        i = int(tm.state_indices[c])        # once more, centred on what that pass found
        x2 = prior[0].copy()
        x2[i] = seg.x[-1, i]
        prior = (x2, _reset(tm, c, x2, prior[1], w.std, w.options, None))
        seg = _filter_segment(tm, rec, th, prior, self.opts, self._R, 0)
        e0 = span[0]
        est, sd = self._resume(seg, span, p.index - 1)
        ch = Change(tm.names[c], p.index, p.alarm_index, p.time, p.alarm_time, p.statistic,
                    w.h, p.detected, iso, before=float(e0.est[c]), before_std=float(e0.sd[c]),
                    after=float(est[c]), after_std=float(sd[c]),
                    attributed_time=float(span[-1].t))
        ch.at_start = not self.changes and _within_first_window(
            int(self._first_observable[c]), p.index, w.window)
        self.changes.append(ch)
        self.alarm, self.suspected = ch, None
        return est, sd

    def _resume(self, seg: _Segment, span: list, s0: int):
        """The filter, the observability test and the detector from the
        restarted segment ``seg`` (over the kept samples ``span``, from
        sample ``s0``) on, as :func:`track` watches a restarted segment.
        Returns the estimates and std at the last sample (k,)."""
        b, d, idx = self.batch, self._det, self._idx
        b.x[0][:], b.P[0][:] = seg.x[-1], seg.P[-1]
        self._z, self._Pz = seg.x[-1][idx].copy(), seg.P[-1][idx, idx].copy()
        self._ring[:], self._sum[:] = 0.0, 0.0
        d.restart(s0)
        est, sd = self.tm.values(seg.x, seg.P)
        for r, e in enumerate(span):
            self.information = seg.info[r]
            self._push_observed(s0 + r)
            self.statistic, _ = d.push(self._watched(seg.S[r], s0 + r), self.observable)
            d.hist.append(_Kept(e.k, e.t, e.u, e.y, seg.x[r], seg.P[r], est[r], sd[r],
                                self.observable.copy()))
        return est[-1], sd[-1]

    def _transform(self, z):
        """p(z) and dp/dz of every tracked parameter at once (k,)
        (:meth:`TrackedParameter.value`, :meth:`~TrackedParameter.slope`)."""
        lo, width, logit = self._box
        with np.errstate(over="ignore"):
            s = 1.0 / (1.0 + np.exp(-z))
        return (np.where(logit, lo + width * s, z),
                np.where(logit, width * s * (1.0 - s), 1.0))

    def _observe(self, dt: float, Pz, slope) -> None:
        """The sample's information about each parameter (k,)
        (:func:`~bondgraph.inference.changes.information_gain`, for all
        parameters at once) and, with ``observe``, whether each is observable
        (:func:`track`'s test, sample by sample)."""
        tiny = np.finfo(float).tiny
        Pm = self._Pz + self._q2 * dt
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            info = (1.0 / np.maximum(Pz, tiny) - 1.0 / np.maximum(Pm, tiny)) / slope ** 2
        self.information = np.where(np.isfinite(info) & (info > 0), info, 0.0)
        self._Pz = Pz
        self._push_observed(self.k)

    def _push_observed(self, k: int) -> None:
        """``information`` into the trailing window of the observability
        test at sample ``k`` and ``observable`` updated (with ``observe``)."""
        if self.observable is not None:
            r = k % len(self._ring)
            self._sum += self.information - self._ring[r]
            self._ring[r] = self.information
            self.observable = self._need[0] * self._sum >= self._need[1]
            self._first_observable[self.observable & (self._first_observable < 0)] = k


class _Kept(NamedTuple):
    """A sample the on-line detector keeps to restart from: index, time,
    inputs, outputs, the filtered mean and covariance, the tracked
    estimates and std and the observability there."""
    k: int
    t: float
    u: np.ndarray
    y: np.ndarray
    x: np.ndarray
    P: np.ndarray
    est: np.ndarray
    sd: np.ndarray
    obs: np.ndarray


@dataclass
class _Suspected:
    """An alarm not yet attributed (:meth:`Tracker._attribute`): the
    parameter whose updates raised it, the change's sample and the alarm's,
    their times, the statistic, the candidate columns, and the next check
    (samples after the alarm)."""
    detected: str
    index: int
    alarm_index: int
    time: float
    alarm_time: float
    statistic: float
    candidates: list
    due: int = 0


@dataclass
class OnlineWatch:
    """Change detection of the streaming :class:`Tracker`, as :func:`track`
    detects (:meth:`Tracker.from_problem` makes it from the same
    :class:`~bondgraph.inference.options.TrackOptions`): the windowed GLR
    test of the clipped standardised updates
    (:mod:`bondgraph.inference.changes`) evaluated at each sample as it
    arrives. At an alarm the changed parameter is chosen by likelihood over
    the samples from the estimated change time on, as they come: decided as
    soon as restarting one parameter explains them better than restarting
    any other by more than h, at the latest one window after the alarm
    (:func:`track` always takes that window; it has the record at hand).
    Then the filter restarts at the change time from the samples it keeps
    (the last 2 ``window`` + 3) and runs to the current sample, re-centred
    on that restart's value there (:func:`track`: at its segment's end). So
    up to the first alarm the statistic and the alarm are :func:`track`'s;
    after it the two may differ. An on-line tracker has no second pass to
    measure the serial inflation of the updates: ``unit`` (1/√λ) is given.

    Attributes
    ----------
    h : float
        Threshold [nats] (:func:`~bondgraph.inference.changes.glr_threshold`).
    window : int
        GLR window M [samples].
    holdoff : int
        Samples of a restarted segment not watched.
    unit : ndarray (k,)
        Each tracked parameter's updates are multiplied by it (1/√λ).
    options : TrackOptions
        ``reset_rel``, ``prior_rel``, ``glr_clip``, ``max_changes``.
    std : dict
        Prior std by parameter [its unit] (the restart's rule, :func:`track`'s ``std``).
    P_start : ndarray (n_x, n_x)
        The original states' prior covariance, added at a restart.
    """

    h: float
    window: int
    holdoff: int
    unit: np.ndarray
    options: TrackOptions
    std: dict
    P_start: np.ndarray


class _OnlineDetector:
    """The on-line detector's state: the watched values of the current
    segment's last ``window`` samples (a ring), the segment's start, and the
    kept samples (:class:`_Kept`)."""

    def __init__(self, watch: OnlineWatch, k: int):
        self.M = max(1, int(watch.window))
        self.ring, self.pos, self.count = np.full((self.M, k), np.nan), 0, 0
        self.seg0, self.restarted = 0, False
        self.hist: deque = deque(maxlen=2 * self.M + 3)   # from a change to its attribution

    def restart(self, s0: int) -> None:
        """A new segment from sample ``s0``: the window emptied, the kept
        samples from ``s0`` on to be appended again."""
        self.ring[:], self.pos, self.count = np.nan, 0, 0
        self.seg0, self.restarted = s0, True
        while self.hist and self.hist[-1].k >= s0:
            self.hist.pop()

    def push(self, row, allowed) -> tuple[np.ndarray, np.ndarray]:
        """Add a sample's watched values (k,); the GLR statistic g (k,) over
        the window's trailing sums (:func:`~bondgraph.inference.changes.glr_mean_jump`
        at the newest sample, 0 where not ``allowed``) and the length L (k,)
        of each maximising window (the change at the newest sample − L + 1)."""
        self.ring[self.pos] = row
        self.pos, self.count = (self.pos + 1) % self.M, min(self.count + 1, self.M)
        W = self.ring[(self.pos - 1 - np.arange(self.count)) % self.M]    # newest first
        ok = np.isfinite(W)
        C, n = np.cumsum(np.where(ok, W, 0.0), axis=0), np.cumsum(ok, axis=0)
        val = np.where(n > 0, C * C / (2.0 * np.maximum(n, 1)), 0.0)
        L = np.argmax(val, axis=0)          # the first maximum: the shorter window
        g = val[L, np.arange(val.shape[1])]
        return np.where(allowed, g, 0.0), L + 1

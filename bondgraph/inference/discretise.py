"""Choose the filter's discretisation from evidence: the input hold from the
record, the method and substeps from the discretisation check.

Two questions, answered from two kinds of evidence:

* **The input hold** (how the input moved between two samples). The
  discretisation check cannot answer it: its fine reference holds the inputs
  as the candidate does, so a wrong hold is invisible to it. It comes from
  the record: a declaration (the sidecar's per-column ``"hold"``,
  ``docs/data_format.md``), else the shape of each input
  (:func:`input_holds`): a staircase (a change flanked by unchanged samples)
  is a digital command, held (``"zoh"``); a change that continues the
  previous or the next one with a similar step is a sampled continuous
  signal, interpolated (``"linear"``); changes that are neither (a sequence
  that jumps at every sample) give no evidence for interpolation, so they are
  held. Each input is held as its own evidence says: a record with a
  digital command beside a sampled continuous signal gets a per-input hold
  (``"zoh,linear"``, :func:`supported_hold`). Where the shape is ambiguous
  (neither share reaches :data:`CLEAR_SHARE`), the fitted model's likelihood
  decides: the estimate command fits under both holds, the loop fits its
  declared model under both (:func:`alternative_hold`), and each keeps the
  likelier.
* **The step** (method and substeps). The candidates
  (:data:`CANDIDATES`, cheapest first) are compared with a fine RK4 reference
  of the same hold, one step from the reference state at every sample
  (:func:`bondgraph.inference.ukf.discretisation_errors`); the cheapest whose
  error is at most :data:`TOLERANCE` measurement-noise standard deviations
  per sample is chosen (:func:`choose_discretisation`). A filter without
  process noise predicts by the free run once its covariance has collapsed,
  and small one-step errors add up along it (ROS2(1) at 0.05 σ per sample
  moved a damper 60 standard deviations): then the free run's error must
  also bound the bias of every estimate by :data:`BIAS_TOLERANCE` Cramér-Rao
  standard deviations.

References
----------
Franklin, G. F., Powell, J. D., Workman, M. L. (1998). Digital Control of
Dynamic Systems, 3rd ed., ch. 4 (zero- and first-order holds; the
zero-order hold's half-sample delay).
Hairer, E., Wanner, G. (1996). Solving Ordinary Differential Equations II,
§IV.7 (Rosenbrock and W-methods).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Mapping, Sequence

import numpy as np

from bondgraph.data.record_io import INPUT_HOLDS
from bondgraph.errors import NumericalError, OptionError
from bondgraph.inference.options import UKF_METHODS, Discretisation
from bondgraph.inference.ukf import discretisation_errors
from bondgraph.numerics.integrators import is_per_input, join_hold, split_hold

__all__ = ["BIAS_TOLERANCE", "CANDIDATES", "CLEAR_SHARE", "DECLARED_HOLDS", "HOLD_CHECK_MARGIN",
           "HOLD_MARGIN",
           "TOLERANCE", "DiscretisationChoice", "InputHold", "alternative_hold", "hold_verdict",
           "check_discretisation", "choose_discretisation", "declared_holds", "holds_against",
           "hold_check_line", "input_holds", "likelier_hold_at", "moved_most", "no_process_noise",
           "other_hold_warning", "record_hold", "record_input_holds",
           "refined_runs", "step_cost", "supported_hold"]

#: the largest accepted one-step discretisation error, in measurement-noise
#: standard deviations per sample
TOLERANCE = 0.1
#: the largest accepted free-run bias bound, in Cramér-Rao standard deviations
#: (the criterion of a filter without process noise, :func:`choose_discretisation`)
BIAS_TOLERANCE = 0.5
#: the holds a record may declare for an input, and that the evidence chooses
#: between (:data:`bondgraph.data.record_io.INPUT_HOLDS`)
DECLARED_HOLDS = INPUT_HOLDS
#: the substeps per sample tried, fewest first: the loop's ladder too
#: (:data:`bondgraph.diagnose.runner.SUBSTEP_LADDER`); between the powers of
#: two, 3, 6 and 12 (the error of an order-p method falls as the substeps to
#: the p-th power: where 4 is the first power of two within, 3 often is, at
#: three quarters of the cost)
SUBSTEPS = (1, 2, 3, 4, 6, 8, 12, 16)


def step_cost(method: str, substeps: float) -> float:
    """The cost per sample of ``method`` with ``substeps`` (a mean over the
    intervals for a refined discretisation), counted in f evaluations: RK4 4
    per substep, ROS2 2 per substep and 2 more per sample (its Jacobian and
    factorisation; the order of :data:`CANDIDATES`)."""
    return 4.0 * substeps if method == "rk4" else 2.0 * substeps + 2.0


#: (method, substeps) candidates in order of cost per sample, counted in f
#: evaluations: RK4 4 per substep, ROS2 2 per substep and one Jacobian (with
#: its factorisation, about 2 more) per sample; on a tie the fewer substeps
#: first (RK4(2) before ROS2(3): the order of the powers of two is kept, so a
#: step they chose is still chosen unless a cheaper one passes), and of ROS2(1)
#: and RK4(1) ROS2 first (L-stable: a stiff model's step that RK4 cannot take
#: is not finite and fails the check, so the list serves stiff models too)
CANDIDATES = tuple(sorted(((m, s) for s in SUBSTEPS for m in ("ros2", "rk4")),
                          key=lambda c: (step_cost(*c), c[1], c[0] != "ros2")))


#: intervals either side of one that needs more substeps that take them too
#: (:func:`refined_runs`): the filter's sigma points meet a non-smooth
#: stretch (a friction law's zero crossing) a little earlier or later than
#: the noise-free reference trajectory the errors are measured along
REFINE_MARGIN = 3


def refined_runs(errors, ladder: Sequence[int], limit: float = TOLERANCE, *,
                 margin: int = REFINE_MARGIN, base=None) -> tuple | None:
    """The refined runs of a discretisation (:attr:`~bondgraph.inference.options.Discretisation.refine`):
    each interval takes the fewest substeps of ``ladder`` whose one-step
    error there is within ``limit``, held over ``margin`` intervals either
    side (an interval a neighbour's substeps reach takes the fewest at least
    as many that are within the limit there too: the error need not fall
    with every substep, a friction law's RK4 error at one EMPS interval read
    0.048 σ at 4 substeps and 0.112 σ at 6); the runs of intervals that take
    more than ``ladder[0]``.

    A record's discretisation error is often not spread over it: at the
    filter's sigma points the EMPS drive's Coulomb friction at RK4(2)
    exceeds 0.1 noise std on 46 of its 4967 intervals (around its
    velocity's zero crossings). One step count for the whole record, the
    worst interval's, makes every other interval pay for them.

    Parameters
    ----------
    errors : array (k, M)
        Each interval's one-step error (:meth:`bondgraph.inference.problem.Problem.interval_errors`,
        in noise stds) at each of the ``ladder``'s substeps.
    ladder : sequence of int (k,)
        Increasing substeps; ``ladder[0]`` is the base (every interval's
        at least).
    limit : float
        The largest accepted error per interval (noise stds).
    margin : int
        Intervals either side that take a refined interval's substeps too.
    base : array (M,) of int, optional
        Substeps per interval that stay at least (an earlier refinement).

    Returns
    -------
    tuple of (start, stop, substeps) or None
        The runs (empty: the base meets ``limit`` everywhere); None when an
        interval meets it at no substeps of the ladder.
    """
    E = np.asarray(errors, float)
    lad = np.asarray(ladder, dtype=np.int64)
    if E.ndim != 2 or E.shape[0] != lad.size:
        raise OptionError(f"refined_runs: errors of shape {E.shape} for {lad.size} substeps")
    ok = E <= limit
    if not ok.any(axis=0).all():
        return None
    need = lad[np.argmax(ok, axis=0)]
    if margin > 0 and need.size:
        padded = np.pad(need, margin, mode="edge")
        need = np.lib.stride_tricks.sliding_window_view(padded, 2 * margin + 1).max(axis=1)
    if base is not None:
        need = np.maximum(need, np.asarray(base, dtype=np.int64))
    # the fewest substeps at least ``need`` that are within the limit there
    fits = ok & (lad[:, None] >= need[None, :])
    beyond = need > lad[-1]                 # an earlier refinement's, kept
    if not (fits.any(axis=0) | beyond).all():
        return None
    need = np.where(beyond, need, lad[np.argmax(fits, axis=0)])
    runs, k, M = [], 0, need.size
    while k < M:
        j = k
        while j < M and need[j] == need[k]:
            j += 1
        if need[k] > lad[0]:
            runs.append((k, j, int(need[k])))
        k = j
    return tuple(runs)


def cost_rank(disc) -> int:
    """The place of ``disc``'s method and substeps in :data:`CANDIDATES`
    (cheapest first); one past the last for a pair not among them."""
    key = (disc.method, disc.substeps)
    return CANDIDATES.index(key) if key in CANDIDATES else len(CANDIDATES)


#: an input's shape is clear evidence of its hold when at least this share
#: of its change continues a similar step (linear) or is in isolated steps
#: (zoh); below it on both (a sequence that mostly jumps from sample to
#: sample: a filtered noise, a noisy measurement of a smooth signal, a digital
#: command updated at every sample) the shape is ambiguous and the
#: likelihood chooses (:func:`alternative_hold`). The real records' inputs:
#: EMPS 0.86, Silverbox 0.88, the Camry's speed 0.93 and acceleration 0.75
#: continuing, CED 1.0 isolated; a 5-sample moving average of white noise
#: 0.43, white noise 0.19 continuing.
CLEAR_SHARE = 0.7
#: the NLL [nats] by which a fit under the other hold of an ambiguous input
#: (:func:`alternative_hold`) must beat the fit under the shape's hold to be
#: kept: the two models have the same parameters, and 1 nat is an Akaike
#: weight of 0.88
HOLD_MARGIN = 1.0
#: the NLL [nats] by which the loop's final model, refitted with an input
#: held the other way than its shape says, must beat its fit to be reported
#: (:func:`bondgraph.diagnose.runner.hold_at_final`): a warning, not a
#: choice, so clear evidence only (a mass under a force held zero-order
#: over each sample whose shape reads continuous: 744 nats)
HOLD_CHECK_MARGIN = 10.0
#: two successive steps of the same sign whose sizes differ by at most this
#: fraction of the larger are one continuing variation (a sampled continuous signal)
SIMILAR_STEP = 0.5
#: a sampled continuous input whose linear-hold midpoints differ from its
#: band-limited (sinc) interpolation by more than this fraction of its std
#: (RMS) is worth a finer grid (:func:`band_limits`): Silverbox's V1, a
#: voltage with content to 200 Hz sampled at 610 Hz, 0.20; EMPS's motor
#: position 0.0005, the Camry's dyno speed 0.003
BAND_LIMITED_MIDPOINT = 0.05
#: ... when it is band-limited: its power above 0.8 × Nyquist is below this
#: fraction of its power in 0.4 - 0.8 × Nyquist (Silverbox's V1 1e-5; a
#: smooth signal with 5 % white noise 0.5: noise, not a signal to interpolate)
NEAR_NYQUIST = 0.01


@dataclass(frozen=True)
class InputHold:
    """How one input was held between samples, and why that is believed.

    Attributes
    ----------
    name : str
        The model's input.
    hold : {"zoh", "linear"} or None
        The supported hold; None for an input that never changes (any hold
        is exact).
    source : {"declared", "shape", "constant"}
        The record's declaration, the input's shape, or no change at all.
    continuing, isolated, erratic : float
        Shares (summing to 1 over the changes, weighted by |Δu|) of changes
        that continue a neighbouring change with a similar step (a sampled
        continuous signal), of changes flanked by unchanged samples (the
        steps of a staircase), and of the others (NaN when declared or
        constant).
    """

    name: str
    hold: str | None
    source: str
    continuing: float = float("nan")
    isolated: float = float("nan")
    erratic: float = float("nan")

    @property
    def ambiguous(self) -> bool:
        """The shape decided the hold without clear evidence: neither share
        of continuing nor of isolated change reaches :data:`CLEAR_SHARE`."""
        return (self.source == "shape" and self.hold is not None
                and max(self.continuing, self.isolated) < CLEAR_SHARE)

    def describe(self) -> str:
        """One clause: ``"F: linear (a sampled continuous signal: 99% of its
        change continues a similar step)"``, ``"u: zoh (a staircase: 100% of
        its change in isolated steps)"``, ``"F: zoh (declared by the record)"``."""
        if self.source == "declared":
            return f"{self.name}: {self.hold} (declared by the record)"
        if self.source == "constant":
            return f"{self.name}: constant (any hold)"
        if self.hold == "linear":
            return (f"{self.name}: linear (a sampled continuous signal: {self.continuing:.0%} of "
                    f"its change continues a similar step)")
        what = ("a staircase: " + f"{self.isolated:.0%} of its change in isolated steps"
                if self.isolated >= self.erratic else
                f"{self.erratic:.0%} of its change jumps from sample to sample")
        return f"{self.name}: zoh ({what}{'; ambiguous' if self.ambiguous else ''})"


def declared_holds(record, names: Sequence[str]) -> dict[str, str]:
    """The holds the record declares for the inputs ``names``: the sidecar's
    ``columns.<name>.hold`` (``"zoh"`` or ``"linear"``); an input ``der(r)``
    takes the declaration of ``r``.

    Parameters
    ----------
    record : Experiment or None
        None (bare arrays) declares nothing.
    names : sequence of str
        The model's inputs.

    Returns
    -------
    dict
        Input -> declared hold.

    Raises
    ------
    OptionError
        A declaration that is not one of :data:`DECLARED_HOLDS` (named).
    """
    cols = ((getattr(record, "meta", None) or {}).get("columns") or {}) if record is not None \
        else {}
    out = {}
    for n in names:
        base = n[4:-1] if n.startswith("der(") and n.endswith(")") else n
        hold = (cols.get(n) or cols.get(base) or {}).get("hold")
        if hold is None:
            continue
        if hold not in DECLARED_HOLDS:
            raise OptionError(f"the record declares hold {hold!r} for input '{n}'; use one of "
                              f"{', '.join(repr(h) for h in DECLARED_HOLDS)}")
        out[n] = hold
    return out


def input_holds(u, names: Sequence[str], declared: Mapping[str, str] | None = None,
                ) -> list[InputHold]:
    """The hold each input's samples support.

    A change Δu_k = u_k+1 − u_k ≠ 0 is *isolated* when both neighbouring
    changes are zero (a step of a staircase: the signal was held before and
    after), *continuing* when a neighbouring change has the same sign and a
    size within :data:`SIMILAR_STEP` of it (a sampled continuous signal
    moves by similar steps), and *erratic* otherwise. Weighted by |Δu| (the
    size of the error a wrong hold makes), an input whose continuing share
    is at least one half supports the linear hold; otherwise the zero-order
    hold. A declaration wins over the shape.

    Parameters
    ----------
    u : array (N, n_u)
        The sampled inputs (any units: only each input's own steps are
        compared).
    names : sequence of str
        The n_u input names.
    declared : mapping, optional
        Input -> declared hold (:func:`declared_holds`).

    Returns
    -------
    list of InputHold
        One per input, in order.

    Raises
    ------
    OptionError
        ``names`` not matching the columns of ``u``, or a declared hold
        not in :data:`DECLARED_HOLDS`.

    Notes
    -----
    A digital command updated at every sample along a smooth path looks
    like a sampled continuous signal; a smooth signal quantised so coarsely
    that it rests for several samples between changes looks like a
    staircase. The shape cannot tell these apart: the record's declaration
    can (``docs/data_format.md``).
    """
    u = np.asarray(u, float)
    u = u.reshape(u.shape[0], -1)
    names = list(names)
    if len(names) != u.shape[1]:
        raise OptionError(f"input_holds: {len(names)} names for {u.shape[1]} input columns")
    declared = dict(declared or {})
    out = []
    for j, n in enumerate(names):
        if n in declared:
            if declared[n] not in DECLARED_HOLDS:
                raise OptionError(f"declared hold {declared[n]!r} of input '{n}' is not one of "
                                  f"{', '.join(repr(h) for h in DECLARED_HOLDS)}")
            out.append(InputHold(n, declared[n], "declared"))
            continue
        out.append(_shape_hold(n, u[:, j]))
    return out


def _shape_hold(name: str, col: np.ndarray) -> InputHold:
    """:class:`InputHold` of one input from its successive changes."""
    d = np.diff(col)
    scale = max(float(np.max(np.abs(col), initial=0.0)), np.finfo(float).tiny)
    d = np.where(np.abs(d) <= 1e-12 * scale, 0.0, d)
    moving = np.flatnonzero(d)
    if moving.size == 0:
        return InputHold(name, None, "constant")
    prev = np.concatenate([[0.0], d[:-1]])[moving]
    nxt = np.concatenate([d[1:], [0.0]])[moving]
    dk = d[moving]

    def similar(a):
        return (np.sign(a) == np.sign(dk)) & (np.abs(a - dk) <= SIMILAR_STEP
                                              * np.maximum(np.abs(a), np.abs(dk)))

    cont = similar(prev) | similar(nxt)
    iso = ~cont & (prev == 0.0) & (nxt == 0.0)
    w = np.abs(dk) / np.sum(np.abs(dk))
    c, i = float(np.sum(w[cont])), float(np.sum(w[iso]))
    e = max(0.0, 1.0 - c - i)
    return InputHold(name, "linear" if c >= 0.5 else "zoh", "shape", c, i, e)


@dataclass(frozen=True)
class BandLimit:
    """Whether a sampled continuous input is band-limited with content up
    to where the linear hold misses its values between samples.

    Attributes
    ----------
    name : str
    midpoint : float
        RMS difference of the linear-hold midpoints from the band-limited
        ones (:func:`band_limited_midpoints`), over the input's std.
    near_nyquist : float
        The input's power above 0.8 × Nyquist over its power in
        0.4 - 0.8 × Nyquist (Welch periodogram).
    """

    name: str
    midpoint: float
    near_nyquist: float

    @property
    def band_limited(self) -> bool:
        """Worth interpolating: the linear hold is off by more than
        :data:`BAND_LIMITED_MIDPOINT` and the content stops short of Nyquist
        (:data:`NEAR_NYQUIST`)."""
        return self.midpoint > BAND_LIMITED_MIDPOINT and self.near_nyquist < NEAR_NYQUIST

    def describe(self) -> str:
        """One clause for a log line."""
        return (f"{self.name}: band-limited (the linear hold's midpoints are {self.midpoint:.0%} "
                f"of its std off its band-limited interpolation; power above 0.8 Nyquist "
                f"{self.near_nyquist:.1g} of that in 0.4-0.8 Nyquist)")


def band_limited_midpoints(col) -> np.ndarray:
    """The values midway between successive samples of a band-limited signal
    (N - 1,): the polyphase interpolation by 2 of
    :func:`scipy.signal.resample_poly` (a Kaiser-windowed sinc; the record's
    ends extended linearly, ``padtype="line"``).

    Raises
    ------
    OptionError
        Fewer than 4 samples, or a value that is not finite.
    """
    from scipy.signal import resample_poly

    col = np.asarray(col, float).reshape(-1)
    if col.size < 4 or not np.isfinite(col).all():
        raise OptionError("band_limited_midpoints: needs at least 4 finite samples")
    up = resample_poly(col, 2, 1, padtype="line")
    return np.asarray(up[1:2 * col.size - 1:2], float)


def band_limits(t, u, names: Sequence[str], holds: Sequence[InputHold]) -> list[BandLimit]:
    """:class:`BandLimit` of every input whose shape supports the linear
    hold (a sampled continuous signal, not declared), on a uniform time grid
    of at least 64 samples; [] otherwise.

    Parameters
    ----------
    t : array (N,)
    u : array (N, n_u)
    names : sequence of str
    holds : sequence of InputHold
        :func:`input_holds` of the same inputs.
    """
    from scipy.signal import welch

    t = np.asarray(t, float)
    u = np.asarray(u, float).reshape(t.size, -1)
    dt = np.diff(t)
    if t.size < 64 or np.ptp(dt) > 1e-6 * np.median(dt):
        return []
    out = []
    for j, (n, h) in enumerate(zip(names, holds)):
        col = u[:, j]
        if h.source != "shape" or h.hold != "linear" or not np.isfinite(col).all():
            continue
        sd = float(np.std(col))
        if sd <= 0:
            continue
        lin = 0.5 * (col[:-1] + col[1:])
        edge = min(20, col.size // 10)
        d = (band_limited_midpoints(col) - lin)[edge:col.size - 1 - edge]
        f, P = welch(col - np.mean(col), nperseg=min(col.size, 1024))
        mid = float(np.sum(P[(f >= 0.2) & (f < 0.4)]))
        top = float(np.sum(P[f >= 0.4]))
        out.append(BandLimit(n, float(np.sqrt(np.mean(d ** 2))) / sd,
                             top / mid if mid > 0 else float("inf")))
    return out


#: the largest share of a signal's power above 1/K of the Nyquist frequency
#: for the record to count as K times oversampled (:func:`oversampling`)
OVERSAMPLED_SHARE = 1e-3


def oversampling(t, columns, factors: Sequence[int] = (10, 5, 4, 2)) -> tuple[int, float]:
    """How many times faster than its content a record was sampled: the
    largest K of ``factors`` for which every column's power above 1/K of the
    Nyquist frequency is below :data:`OVERSAMPLED_SHARE` of its own (Welch
    spectra of the linearly detrended columns), and that worst share; (1,
    share at the smallest K) when none qualifies, (1, nan) on a grid whose
    steps vary by more than 0.1 %, with fewer than 256 samples or a column
    not finite. A proxy for "the system is slower than the sampling": the
    outputs hold nothing a coarser grid could not resolve, and measurement
    noise counts against it (a white floor spreads over the whole band).

    Parameters
    ----------
    t : array (N,)
    columns : sequence of arrays (N,)
        The record's inputs and outputs.
    factors : sequence of int
        Candidates K, tried from the largest.

    Returns
    -------
    (int, float)
    """
    from scipy.signal import detrend, welch

    t = np.asarray(t, float)
    dt = np.diff(t)
    cols = [np.asarray(c, float) for c in columns]
    if (t.size < 256 or not cols or np.ptp(dt) > 1e-3 * np.median(dt)
            or not all(np.isfinite(c).all() for c in cols)):
        return 1, float("nan")
    spectra = []
    for c in cols:
        f, P = welch(detrend(c), nperseg=min(c.size, 4096))
        if np.sum(P) > 0:
            spectra.append((f, P / np.sum(P)))
    if not spectra:
        return 1, float("nan")
    worst = float("nan")
    for k in sorted(factors, reverse=True):
        worst = max(float(np.sum(P[f >= 0.5 / k])) for f, P in spectra)
        if worst < OVERSAMPLED_SHARE:
            return int(k), worst
    return 1, worst


def finer_grid_record(exp, inputs: Sequence[str]):
    """``(record, why)``: ``exp`` and None, or, when an input is band-limited
    with content where the linear hold misses its values between samples
    (:func:`band_limits`), the record on a grid twice as fine
    (:meth:`~bondgraph.data.records.Experiment.on_finer_grid`) and the
    reason: those inputs interpolated band-limited between the samples
    (:func:`band_limited_midpoints`) and held linearly over the finer
    intervals, the other inputs as their own hold has them there
    (zero-order: the sample before; linear: the mean of the two), the
    outputs missing there.

    Parameters
    ----------
    exp : Experiment
    inputs : sequence of str
        The model's inputs (the record's columns of those names are its
        inputs; the others it lacks or computes, as ``der(r)``).
    """
    names = [n for n in inputs if n in exp.columns]
    if not names:
        return exp, None
    u = np.column_stack([np.asarray(exp.columns[n], float) for n in names])
    if not np.isfinite(u).all():
        return exp, None
    holds = record_input_holds(exp, names, u)
    chosen = [b for b in band_limits(exp.t, u, names, holds) if b.band_limited]
    if not chosen:
        return exp, None
    fine = {b.name for b in chosen}
    mids = {n: (band_limited_midpoints(u[:, j]) if n in fine else
                u[:-1, j] if h.hold == "zoh" else 0.5 * (u[:-1, j] + u[1:, j]))
            for j, (n, h) in enumerate(zip(names, holds))}
    why = "; ".join(b.describe() for b in chosen)
    return exp.on_finer_grid(mids, linear=sorted(fine), note=why), why


def supported_hold(inputs: Sequence[InputHold]) -> tuple[str, str]:
    """The filter's hold that the evidence supports, and why: each input held
    as its own evidence says.

    Inputs that never change have no say: any hold is exact for them, and
    they take the hold of the inputs that do change (of the most of them; a
    tie: ``"zoh"``, the sampled-data convention). When the changing inputs
    agree, the hold is that one name; when they disagree, one per input
    (``"zoh,linear"``, :func:`bondgraph.numerics.integrators.split_hold`),
    which every filter, free run and check holds column by column.

    Parameters
    ----------
    inputs : sequence of InputHold
        One per model input, in the model's input order.

    Returns
    -------
    hold : str
        ``"zoh"``, ``"linear"``, or one of them per input comma-joined.
    reason : str
        One clause for a log line.
    """
    said = [h for h in inputs if h.hold is not None]
    if not said:
        return "zoh", "no input changes (any hold is exact)"
    count = {"zoh": 0, "linear": 0}
    for h in said:
        count[h.hold] += 1
    rest = "linear" if count["linear"] > count["zoh"] else "zoh"
    hold = join_hold([h.hold if h.hold is not None else rest for h in inputs])
    reason = "; ".join(h.describe() for h in said)
    if is_per_input(hold):
        reason += " — each input held as its evidence says"
    return hold, reason


def alternative_hold(inputs: Sequence[InputHold], hold: str) -> str | None:
    """``hold`` with every input whose shape is ambiguous
    (:attr:`InputHold.ambiguous`) held the other way (zero-order <-> linear),
    the other inputs as ``hold`` has them; None when no input is ambiguous.

    The shape cannot tell a held sequence that jumps at every sample from a
    sampled continuous signal with noise or fast content; the likelihood of
    the fitted model can (a linear hold of a held input spreads each step
    over the sample before it, a zero-order hold of a continuous one delays
    it by half a sample). Compare the fits under ``hold`` and under this one.

    Parameters
    ----------
    inputs : sequence of InputHold
        One per model input, in order (:func:`input_holds`).
    hold : str
        The filter's hold, one name or one per input.

    Raises
    ------
    OptionError
        An unknown hold, or a per-input hold of another length.
    """
    holds = list(split_hold(hold, len(inputs)))
    flipped = False
    for j, h in enumerate(inputs):
        if h.ambiguous and holds[j] in ("zoh", "linear"):
            holds[j] = "linear" if holds[j] == "zoh" else "zoh"
            flipped = True
    return join_hold(holds) if flipped else None


def holds_against(inputs: Sequence[InputHold], hold: str) -> list[InputHold]:
    """The inputs with evidence that ``hold`` holds against it: zero-order
    where the evidence says linear, or interpolated (``"mean"`` or
    ``"linear"``) where it says zoh. An ambiguous shape
    (:attr:`InputHold.ambiguous`) is no such evidence.

    Parameters
    ----------
    inputs : sequence of InputHold
        One per model input, in order.
    hold : str
        A filter hold, one name or one per input.

    Raises
    ------
    OptionError
        An unknown hold, or a per-input hold of another length.
    """
    holds = split_hold(hold, len(inputs))
    return [h for h, fh in zip(inputs, holds)
            if h.hold is not None and not h.ambiguous
            and ("zoh" if fh == "zoh" else "linear") != h.hold]


#: how a line names an RK4 step whose one-step error is infinite
#: (:func:`bondgraph.inference.ukf.rk4_unstable`), the first time
UNSTABLE = "unstable (a fast mode outside RK4's stability region, or not finite)"


def step_error(method: str, error: float, unit: str = "σ") -> str:
    """A one-step discretisation error for a line: ``"0.061 σ"`` (``unit``
    after the number); an RK4 step's infinite one named unstable
    (:data:`UNSTABLE`). Every command's line says it this way."""
    if method == "rk4" and error == np.inf:
        return UNSTABLE
    return f"{error:.2g} {unit}"


@dataclass(frozen=True)
class DiscretisationChoice:
    """The discretisation chosen for a problem at one θ, and the evidence.

    Attributes
    ----------
    disc : Discretisation
        The chosen method, substeps and hold (the problem's backend).
    ok : bool
        The chosen candidate meets the criteria; False when no candidate
        does (then the most accurate one tried is chosen).
    hold_reason : str
        Why this hold (declared, the inputs' shape, or given).
    inputs : list of InputHold
        Each input's evidence.
    tried : list of (Discretisation, ndarray (n_y,), float)
        Every candidate checked, in order: its one-step error per output
        and its free-run bias bound (NaN when not computed), both in
        measurement-noise standard deviations.
    sigma : ndarray (n_y,)
        The measurement-noise standard deviations of the comparison.
    free_run : bool
        The free-run bound was a criterion (the filter has no process noise).
    given : dict
        The fields the caller fixed (``method``, ``substeps``, ``hold``).
    tolerance, bias_tolerance : float
    """

    disc: Discretisation
    ok: bool
    hold_reason: str
    inputs: list
    tried: list
    sigma: np.ndarray
    free_run: bool = False
    given: dict = field(default_factory=dict)
    tolerance: float = TOLERANCE
    bias_tolerance: float = BIAS_TOLERANCE

    def _entry(self, disc: Discretisation):
        for d, e, r in self.tried:
            if (d.method, d.substeps, d.hold) == (disc.method, disc.substeps, disc.hold):
                return e, r
        return None, None

    def error_of(self, disc: Discretisation) -> float | None:
        """The worst one-step error of ``disc`` if it was tried, else None."""
        e, _ = self._entry(disc)
        return None if e is None else float(np.max(e, initial=0.0))

    @property
    def error(self) -> float:
        """The chosen candidate's worst one-step error [σ per sample]."""
        return self.error_of(self.disc)

    @property
    def bias_bound(self) -> float:
        """The chosen candidate's free-run bias bound [Cramér-Rao std] (NaN if not computed)."""
        return float(self._entry(self.disc)[1])

    def line(self, where: str = "") -> str:
        """One line: what was chosen, at which error, and why.

        ``"discretisation at the start θ: rk4(1), linear hold — one-step error
        1.2e-05 σ <= 0.1 σ per sample, free-run bias bound 0.0033 <= 0.5 std
        (ros2(1): 0.061 σ, bound 2.4e+02); hold: F: linear (...)"``.
        """
        others = [f"{d.method}({d.substeps}): {step_error(d.method, np.max(e, initial=0))}"
                  + (f", bound {r:.2g}" if np.isfinite(r) or r == np.inf else "")
                  for d, e, r in self.tried if d != self.disc][:3]
        others = [o if i == next((j for j, x in enumerate(others) if UNSTABLE in x), None)
                  else o.replace(UNSTABLE, "unstable") for i, o in enumerate(others)]
        verdict = "within" if self.ok else "the best tried, NOT within"
        fixed = (" [given: " + ", ".join(f"--{k} {v}" for k, v in self.given.items()) + "]"
                 if self.given else "")
        bound = (f", free-run bias bound {self.bias_bound:.2g} std (<= {self.bias_tolerance:g}; "
                 f"no process noise)" if self.free_run else "")
        return (f"discretisation{' ' + where if where else ''}: {self.disc.method}"
                f"({self.disc.substeps}), {self.disc.hold} hold{fixed} — {verdict}: one-step "
                f"error {self.error:.2g} σ per sample (<= {self.tolerance:g}){bound}"
                + (f"; tried {'; '.join(others)}" if others else "")
                + f"; hold: {self.hold_reason}")

    def to_dict(self) -> dict:
        """JSON-able summary."""
        return dict(chosen=self.disc.to_dict(), ok=self.ok, error=self.error,
                    bias_bound=self.bias_bound, tolerance=self.tolerance,
                    bias_tolerance=self.bias_tolerance, free_run=self.free_run,
                    hold_reason=self.hold_reason, given=dict(self.given),
                    sigma=np.asarray(self.sigma, float).tolist(),
                    tried=[dict(method=d.method, substeps=d.substeps, hold=d.hold,
                                one_step=np.asarray(e, float).tolist(), bias_bound=float(r))
                           for d, e, r in self.tried])


def choose_discretisation(problem, theta, *, given: Mapping | None = None, sigma=None,
                          tolerance: float = TOLERANCE, bias_tolerance: float = BIAS_TOLERANCE,
                          free_run: bool | None = None, hold: str | None = None,
                          why: str | None = None) -> DiscretisationChoice:
    """The cheapest discretisation that meets its check at ``theta``, with the
    hold the record supports.

    The hold: ``given["hold"]`` if given, else the record's declarations and
    the inputs' shape (:func:`declared_holds`, :func:`input_holds`,
    :func:`supported_hold`; ``"mean"`` is never chosen, only kept when
    given). The step: :data:`CANDIDATES` (restricted to ``given["method"]``
    and ``given["substeps"]`` when given) in order of cost, each compared with
    a fine reference of the same hold from the problem's prior mean
    (:func:`bondgraph.inference.ukf.discretisation_errors`): the first whose
    one-step error is at most ``tolerance`` measurement-noise standard
    deviations per sample and, when the filter has no process noise (its
    prediction is then the free run), whose free-run bias bound (the root sum
    of squares of the free run's output error in σ, an upper bound of the
    bias it causes in any estimate, in Cramér-Rao standard deviations) is at
    most ``bias_tolerance``; else the most accurate one tried.

    Parameters
    ----------
    problem : Problem
        The model bound to the record (:func:`bondgraph.inference.problem.make_problem`);
        its backend is kept.
    theta : array (n_theta,)
        Where to check (the start of a fit, or its estimate).
    given : mapping, optional
        Fields the user fixed: ``method``, ``substeps``, ``hold``.
    sigma : array (n_y,), optional
        Measurement-noise standard deviations (output units). Default: the
        levels the problem holds (a record's declarations), else
        ``meas_std(theta)``. An output without a positive finite level takes
        the level seen in the record (:func:`~bondgraph.inference.estimand.record_noise_level`),
        else is left out of the comparison.
    tolerance : float
        Largest one-step error [σ per sample] (> 0).
    bias_tolerance : float
        Largest free-run bias bound [Cramér-Rao std] (> 0).
    free_run : bool, optional
        Apply the free-run criterion (default: when ``proc_std(theta)`` is
        zero for every state).
    hold : str, optional
        A hold chosen by other evidence (the likelihood of fits under both,
        :func:`alternative_hold`), in place of the record's when the user
        gave none; ``why`` says why.
    why : str, optional

    Returns
    -------
    DiscretisationChoice

    Raises
    ------
    OptionError
        An unknown field or value in ``given``, a tolerance that is not > 0,
        a bad declared hold, or no output with a noise level to compare with.

    References
    ----------
    Ljung, L. (1999). System Identification, 2nd ed., §8.3 (the limit of a
    prediction-error estimate under a model error) for the bias bound.
    """
    given = dict(given or {})
    _check_given(given, tolerance)
    if not (np.isfinite(bias_tolerance) and bias_tolerance > 0):
        raise OptionError(f"choose_discretisation: bias_tolerance must be > 0, got "
                          f"{bias_tolerance!r}")
    model = problem.model
    th = np.asarray(theta, float).reshape(-1)
    sig = comparison_sigma(problem, th, sigma)
    if free_run is None:
        free_run = no_process_noise(model, th)
    inputs = record_input_holds(problem.record, model.inputs, problem.u)
    hold, reason = _hold_for(inputs, given, hold, why)
    cands = [Discretisation(m, s, hold, problem.disc.backend) for m, s in _candidates(given)]
    disc, ok, tried = _first_within(problem, th, cands, sig, free_run, tolerance, bias_tolerance)
    return DiscretisationChoice(disc, ok, reason, inputs, tried, sig, free_run, given, tolerance,
                                bias_tolerance)


def hold_verdict(other: str, other_nll: float, mine: str, mine_nll: float, *,
                 criterion: str = "likelihood", where: str = "",
                 note: str = "", margin: float = HOLD_MARGIN) -> tuple[bool, str]:
    """Whether the model under the ``other`` hold is likelier than under
    ``mine`` (its NLL ``other_nll`` finite and lower than ``mine_nll`` by
    more than ``margin`` nat, default :data:`HOLD_MARGIN`), and the log line that says so:
    ``"input hold by likelihood: linear NLL -1500.3, zoh NLL 28260.5 (each
    fitted): linear kept"``.

    Parameters
    ----------
    other, mine : str
        The two holds (``mine``: the shape's).
    other_nll, mine_nll : float
        Their negative log-likelihoods [nat]; not finite counts as +inf.
    criterion, where, note : str
        Words of the line (``"output-error likelihood"``; ``"at the analysed
        θ"``; ``"(each fitted)"``).
    margin : float
        [nat].

    Returns
    -------
    (bool, str)
    """
    a = other_nll if np.isfinite(other_nll) else np.inf
    b = mine_nll if np.isfinite(mine_nll) else np.inf
    better = bool(np.isfinite(a) and a < b - margin)
    close = "" if better or not a < b else (f" (the other is not lower by more than "
                                             f"{margin:g} nat)")
    return better, (f"input hold by {criterion}{' ' + where if where else ''}: {other} NLL "
                    f"{other_nll:.6g}, {mine} NLL {mine_nll:.6g}{' ' + note if note else ''}: "
                    f"{other if better else mine} kept{close}")


def moved_most(names: Sequence[str], new: Mapping[str, float], old: Mapping[str, float],
               std: Mapping[str, float | None], n: int = 3, least: float = 3.0) -> str:
    """``"M 2.0003 (was 2.021, 42 std), Fv 4 (was 3.9978, 9 std)"``: the (at
    most ``n``) estimates that moved most from ``old`` to ``new`` in their
    Cramér-Rao std (``std``; names without a positive finite std are left
    out), those that moved by more than ``least``; "" when none did."""
    moves = []
    for name in names:
        sd = std.get(name)
        if name not in new or name not in old or not sd or not np.isfinite(sd) or sd <= 0:
            continue
        z = abs(float(new[name]) - float(old[name])) / float(sd)
        if z > least:
            moves.append((z, name, float(new[name]), float(old[name])))
    moves.sort(reverse=True)
    return ", ".join(f"{nm} {a:.5g} (was {b:.5g}, {z:.0f} std)" for z, nm, a, b in moves[:n])


def hold_check_line(name: str, where: str, flipped: str, nll_other: float, mine: str,
                    nll_mine: float, better: bool) -> str:
    """The log line of a hold check: ``"input hold of 'F' at the final
    model: zoh NLL -6176.36, linear (its shape's) NLL -5427.72, each
    fitted: the record prefers zoh"`` (``"the filter fails under zoh"``
    when ``nll_other`` is not finite)."""
    them = (f"{flipped} NLL {nll_other:.6g}" if np.isfinite(nll_other) else
            f"the filter fails under {flipped}")
    return (f"input hold of '{name}' {where}: {them}, {mine} (its shape's) NLL {nll_mine:.6g}, "
            f"each fitted" + (f": the record prefers {flipped}" if better else ""))


def other_hold_warning(name: str, flipped: str, mine: str, nll_other: float, nll_mine: float,
                       how: str, moves: str, advice: str) -> str:
    """The warning that a record is likelier with input ``name`` held
    ``flipped`` than ``mine``, as its shape says: the NLL gap, both NLLs
    (``how`` they were fitted), the estimates that move (:func:`moved_most`)
    and ``advice``. The loop's final check
    (:func:`bondgraph.diagnose.runner.hold_at_final`) and ``bondgraph
    estimate``'s both say it so."""
    return (f"the record is {nll_mine - nll_other:.0f} nats likelier with input '{name}' held "
            f"{flipped} than {mine} as its shape says ({how}: NLL {nll_other:.6g} against "
            f"{nll_mine:.6g}){'; under it ' + moves if moves else ''}. '{name}' may be a command "
            f"held over each sample whose steps vary smoothly (or a sampled signal that looks "
            f"held). {advice}")


def likelier_hold_at(problem, theta, choice: DiscretisationChoice, *, sigma=None,
                     where: str = "at the analysed θ") -> tuple[DiscretisationChoice, str | None]:
    """``choice``, or the choice under the other hold where an input's shape
    is ambiguous: the filter's NLL at ``theta`` under ``choice`` and under
    :func:`alternative_hold` (its step chosen as ``choice``'s was,
    :func:`choose_discretisation`), the other kept when its NLL is lower by
    more than :data:`HOLD_MARGIN` nat (or the first is not finite).

    For a command that analyses or tracks a model at given parameters
    (sensitivity, track), where the estimate command compares the fits
    under both holds: the likelihood at those parameters is what their
    result rests on. A run that fails counts as an infinite NLL.

    Parameters
    ----------
    problem : Problem
        The model bound to the record.
    theta : array (n_theta,)
        Where to compare (the analysed θ, the tracking start).
    choice : DiscretisationChoice
        What :func:`choose_discretisation` chose at ``theta``; nothing is
        compared when its hold was given or no input is ambiguous.
    sigma : array (n_y,), optional
        As for :func:`choose_discretisation`.
    where : str
        For the reason and the line ("at the analysed θ").

    Returns
    -------
    (DiscretisationChoice, str or None)
        The kept choice (its ``hold_reason`` says why) and one line for the
        log (None when nothing was compared).

    Raises
    ------
    OptionError
        As :func:`choose_discretisation`.
    """
    alt = None if "hold" in choice.given else alternative_hold(choice.inputs, choice.disc.hold)
    if alt is None:
        return choice, None
    th = np.asarray(theta, float).reshape(-1)
    why = f"the likelihood {where} under both holds (the shape is ambiguous)"
    other = choose_discretisation(problem, th, given=choice.given, sigma=sigma,
                                  tolerance=choice.tolerance,
                                  bias_tolerance=choice.bias_tolerance,
                                  free_run=choice.free_run, hold=alt, why=why)
    nll = []
    for c in (choice, other):
        try:
            with np.errstate(all="ignore"):
                v = float(problem.conditioned_on(disc=c.disc).nll(th).nll[0])
        except (FloatingPointError, np.linalg.LinAlgError, NumericalError):
            v = float("inf")
        nll.append(v if np.isfinite(v) else float("inf"))
    better, line = hold_verdict(other.disc.hold, nll[1], choice.disc.hold, nll[0], where=where)
    if better:
        return other, line
    return replace(choice, hold_reason=f"{choice.hold_reason}; kept by {why}"), line


def _once(fn):
    """``fn`` called at most once; later calls return its first result."""
    memo = []

    def call():
        if not memo:
            memo.append(fn())
        return memo[0]
    return call


def _first_within(problem, th, cands, sig, free_run: bool, tolerance: float,
                  bias_tolerance: float) -> tuple[Discretisation, bool, list]:
    """``(disc, ok, tried)``: the first candidate within both criteria (the
    free run computed only for a candidate within the one-step one), else
    the most accurate tried."""
    model = problem.model
    cache: dict = {}
    tried = []
    states = _once(lambda: problem.filtered_states(th))
    for chunk in (cands[:2], cands[2:6], cands[6:]):     # stop early on the cheap ones
        if not chunk:
            continue
        errs = discretisation_errors(model, problem.t, problem.u, th, problem.x0, chunk,
                                     sigma=sig, cache=cache, states=states)
        for d, r in zip(chunk, errs):
            one, rss = r["one_step"], float("nan")
            step_ok = np.max(one, initial=0.0) <= tolerance
            if step_ok and free_run:
                rss = discretisation_errors(model, problem.t, problem.u, th, problem.x0, [d],
                                            sigma=sig, free_run=True,
                                            cache=cache)[0]["free_run_rss"]
            tried.append((d, one, rss))
            if step_ok and (not free_run or rss <= bias_tolerance):
                return d, True, tried
    best = min(tried, key=lambda e: (np.nan_to_num(e[2], nan=np.inf) if free_run else 0.0,
                                     float(np.max(e[1], initial=0.0))))[0]
    return best, False, tried


def check_discretisation(problem, theta, disc: Discretisation | None = None, *, sigma=None,
                         tolerance: float = TOLERANCE, bias_tolerance: float = BIAS_TOLERANCE,
                         free_run: bool | None = None) -> tuple[bool, float, float]:
    """Does ``disc`` (default the problem's) meet the criteria of
    :func:`choose_discretisation` at ``theta``?

    Returns
    -------
    (ok, one-step error [σ per sample], free-run bias bound [std], NaN when
    the free run is not a criterion)
    """
    disc = problem.disc if disc is None else disc
    th = np.asarray(theta, float).reshape(-1)
    sig = comparison_sigma(problem, th, sigma)
    if free_run is None:
        free_run = no_process_noise(problem.model, th)
    r = discretisation_errors(problem.model, problem.t, problem.u, th, problem.x0, [disc],
                              sigma=sig, free_run=free_run,
                              states=lambda: problem.filtered_states(th))[0]
    one = float(np.max(r["one_step"], initial=0.0))
    rss = float(r["free_run_rss"])
    return bool(one <= tolerance and (not free_run or rss <= bias_tolerance)), one, rss


def no_process_noise(model, theta) -> bool:
    """True when ``proc_std(theta)`` is zero for every state (the filter's
    prediction becomes the free run)."""
    with np.errstate(all="ignore"):
        q = np.asarray(model.proc_std(np.asarray(theta, float).reshape(1, -1)), float)
    return bool(np.all(q == 0.0))


def record_hold(problem) -> tuple[str, str]:
    """The hold that ``problem``'s record supports for its model's inputs
    (declared, else each input's shape: :func:`supported_hold`), and why.

    Parameters
    ----------
    problem : Problem

    Returns
    -------
    (hold, reason) : (str, str)
    """
    return supported_hold(record_input_holds(problem.record, problem.model.inputs, problem.u))


def record_input_holds(record, names: Sequence[str], u) -> list[InputHold]:
    """Each input's evidence in a record: its declaration
    (:func:`declared_holds`), else its shape (:func:`input_holds`).

    Parameters
    ----------
    record : Experiment or None
    names : sequence of str
        The model's inputs, in order.
    u : array (N, n_u)
        Their samples.

    Returns
    -------
    list of InputHold
    """
    return input_holds(u, names, declared_holds(record, names))


def _hold_for(inputs, given: dict, hold: str | None = None,
              why: str | None = None) -> tuple[str, str]:
    """The hold and its reason: given (noting a record that supports
    another), else ``hold`` (chosen by other evidence, ``why``), else
    :func:`supported_hold`."""
    if "hold" not in given and hold is not None:
        split_hold(hold, len(inputs))
        return hold, why or "chosen by the caller"
    if "hold" not in given:
        return supported_hold(inputs)
    hold, reason = given["hold"], f"given (--hold {given['hold']})"
    support, _ = supported_hold(inputs)
    if "mean" not in split_hold(hold) and holds_against(inputs, hold):
        reason += f"; the record supports {support}"
    return hold, reason


def _check_given(given: dict, tolerance: float) -> None:
    """Check the caller's fixed fields and the tolerance."""
    unknown = sorted(set(given) - {"method", "substeps", "hold"})
    if unknown:
        raise OptionError(f"choose_discretisation: unknown given field(s) {unknown} "
                          f"(method, substeps, hold)")
    if "method" in given and given["method"] not in UKF_METHODS:
        raise OptionError(f"--method {given['method']!r} is not one of {', '.join(UKF_METHODS)}")
    if "hold" in given:
        try:
            split_hold(given["hold"])
        except OptionError as e:
            raise OptionError(f"--hold: {e}") from None
    s = given.get("substeps", 1)
    if isinstance(s, bool) or not isinstance(s, (int, np.integer)) or s < 1:
        raise OptionError(f"--substeps must be an integer >= 1, got {s!r}")
    if not (np.isfinite(tolerance) and tolerance > 0):
        raise OptionError(f"choose_discretisation: tolerance must be > 0, got {tolerance!r}")


def _candidates(given: dict) -> list[tuple[str, int]]:
    """:data:`CANDIDATES` restricted to the given method and substeps."""
    if "substeps" in given:
        methods = [given["method"]] if "method" in given else ["ros2", "rk4"]
        return [(m, int(given["substeps"])) for m in methods]
    return [(m, s) for m, s in CANDIDATES if given.get("method", m) == m]


def comparison_sigma(problem, th: np.ndarray, sigma=None) -> np.ndarray:
    """The comparison's σ (n_y,): given, else :meth:`Problem.noise_scale`
    (the held level, ``meas_std(θ)``, the level seen in the record); a given
    entry that is not positive and finite takes the latter too; inf (left
    out) where none is.

    Raises
    ------
    OptionError
        No output has a level to compare with.
    """
    model = problem.model
    scale = problem.noise_scale(th)
    if sigma is None:
        sig = scale
    else:
        sig = np.broadcast_to(np.asarray(sigma, float), (model.n_y,)).copy()
        sig = np.where(np.isfinite(sig) & (sig > 0), sig, scale)
    good = np.isfinite(sig) & (sig > 0)
    if not good.any():
        raise OptionError(f"choose_discretisation: no output of '{model.name}' has a positive "
                          f"measurement-noise level to compare the discretisation error with "
                          f"(got {sig.tolist()})")
    return np.where(good, sig, np.inf)

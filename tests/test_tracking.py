"""Parameter tracking and change detection (issue 28): augmented graphs,
the batch tracker, the GLR test; numbers against hand-derived equations,
the constant-parameter UKF, scipy and the simulated truth."""

import numpy as np
import pytest
import sympy as sp
from scipy import stats

from bondgraph.catalog.reference import hydraulic_tanks, mass_spring_damper
from bondgraph.core.augment import augment, tracked_parameters
from bondgraph.core.equations import derive
from bondgraph.errors import ModelError, OptionError, ParameterError
from bondgraph.inference.changes import glr_mean_jump, glr_threshold
from bondgraph.inference.options import TrackOptions, UKFOptions
from bondgraph.inference.problem import make_problem
from bondgraph.inference.track import TrackingModel, track
from bondgraph.numerics.model import Model
from bondgraph.numerics.simulate import simulate

DT, T_END, T_CHANGE = 0.01, 60.0, 30.0
UKF = UKFOptions(method="rk4", substeps=2, backend="numpy")


def msd_record(seed, c_after=None):
    """The mass-spring-damper driven by random force steps (0.5 s), damping
    1.5 N s/m switched to ``c_after`` at T_CHANGE; noisy x and v."""
    base = Model.from_graph(mass_spring_damper())
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, T_END + DT / 2, DT)
    F = np.repeat(rng.normal(0.0, 5.0, int(T_END / 0.5) + 1), 50)[:t.size, None]
    if c_after is None:
        y = simulate(base, t, F, theta={"c": 1.5}, hold="zoh").y
    else:
        i = int(np.searchsorted(t, T_CHANGE))
        s1 = simulate(base, t[:i + 1], F[:i + 1], theta={"c": 1.5}, hold="zoh")
        s2 = simulate(base, t[i:], F[i:], x0=s1.x[-1], theta={"c": c_after}, hold="zoh")
        y = np.vstack([s1.y[:-1], s2.y])
    y = y + rng.normal(0.0, 1.0, y.shape) * np.array([0.002, 0.01])
    return base, t, F, y


# ---------------------------------------------------------------- augment
def test_augmented_equations_equal_hand_substituted():
    g = mass_spring_damper()
    ss = derive(augment(g, ["c"], {"c": 0.2}))
    sym = {s.name: s for s in [*ss.states, *ss.inputs, *ss.params]}
    p, q, z = sym["p_mass"], sym["q_spring"], sym["tracked.c"]
    m, k, F = sym["m"], sym["k"], sym["F"]
    lo, hi = sym["tracked.c.lower"], sym["tracked.c.upper"]
    c = lo + (hi - lo) / (1 + sp.exp(-z))            # the logit transform, by hand
    hand = {p: F - k * q - c * p / m, q: p / m, z: sp.Integer(0)}
    for s, f in zip(ss.states, ss.f):
        assert sp.simplify(f - hand[s]) == 0, s
    # process noise of z: q / (dc/dz at c0) = 0.2 (hi - lo) / ((c0 - lo)(hi - c0))
    c0, (l0, h0) = 1.5, (0.1, 20.0)
    noise = dict(zip([s.name for s in ss.states], ss.process_noise))["tracked.c"]
    val = float(noise.subs(sym["drift.c"], 0.2))
    assert val == pytest.approx(0.2 * (h0 - l0) / ((c0 - l0) * (h0 - c0)), rel=1e-12)
    tp, = tracked_parameters(augment(g, ["c"]))
    assert tp.value(tp.state_of(2.7)) == pytest.approx(2.7, rel=1e-14)


def test_augment_rejects_bad_requests():
    g = mass_spring_damper()
    with pytest.raises(ModelError, match="no parameter 'cc'"):
        augment(g, ["cc"])
    with pytest.raises(ModelError, match="not tracked"):
        augment(g, ["c"], {"k": 1.0})
    with pytest.raises(ModelError, match=">= 0"):
        augment(g, ["c"], {"c": -1.0})
    with pytest.raises(OptionError, match="transform"):
        augment(g, ["c"], transform="log10")
    with pytest.raises(ParameterError, match="box"):
        augment(g, ["c"], start={"c": 20.0})
    with pytest.raises(OptionError, match="prior_rel"):
        TrackOptions(prior_rel=0)


@pytest.mark.parametrize("backend", ["numpy", "numba"])
@pytest.mark.parametrize("graph,param", [(mass_spring_damper, "m"), (hydraulic_tanks, "Rh12")])
def test_zero_drift_equals_constant_parameter_ukf(graph, param, backend):
    g = graph()
    base = Model.from_graph(g)
    rng = np.random.default_rng(3)
    t = np.arange(0.0, 20.0, 0.05)
    u = np.repeat(rng.normal(0.0, 1.0, t.size // 20 + 1), 20)[:t.size, None]
    u = u * (5.0 if graph is mass_spring_damper else 1e-4)
    sim = simulate(base, t, u, hold="zoh")
    y = sim.y + rng.normal(0.0, 1.0, sim.y.shape) * base.meas_std(base.theta0[None])[0]
    pr = make_problem(base, (t, u, y), ukf=UKFOptions(method="ros2", substeps=2,
                                                       backend=backend))
    tm = TrackingModel.from_graph(g, [param])
    res = track(pr, tm, std={param: 0.0}, options=TrackOptions(false_alarm_hours=None,
                                                               smooth=False))
    ref = pr.nll(pr.theta).nll[0]
    assert np.isfinite(ref)
    assert res.nll == pytest.approx(ref, rel=1e-9, abs=1e-9)
    assert np.all(res.estimate == pytest.approx(base.theta0[base.param_index(param)], rel=1e-12))


# ---------------------------------------------------------------- the GLR test
def test_glr_statistic_equals_closed_form_likelihood_ratio():
    rng = np.random.default_rng(7)
    s = rng.normal(0.0, 1.0, 120)
    s[70:] += 0.8                         # a mean jump
    s[[5, 90]] = np.nan                   # samples without information
    M = 40
    g, start = glr_mean_jump(s, M)
    for k in range(s.size):
        best, arg = 0.0, k
        for j in range(max(0, k - M + 1), k + 1):
            w = s[j:k + 1][np.isfinite(s[j:k + 1])]
            if w.size == 0:
                continue
            nu = w.mean()                 # the MLE of the jump
            llr = stats.norm.logpdf(w, nu).sum() - stats.norm.logpdf(w, 0.0).sum()
            if llr > best:
                best, arg = llr, j
        assert g[k] == pytest.approx(best, rel=1e-9, abs=1e-12)
        if best > 0:
            assert start[k] == arg
    assert glr_threshold(3600.0, 1.0, 1) == pytest.approx(0.5 * stats.chi2.isf(1 / 3600, 1))


def test_glr_threshold_false_alarm_rate_bound_on_white_noise():
    rng = np.random.default_rng(11)
    N, M, T = 400_000, 50, 20_000.0      # one false alarm per 20 000 samples at most
    g, _ = glr_mean_jump(rng.normal(0.0, 1.0, N), M)
    h = glr_threshold(T, 1.0, M)
    onsets = np.count_nonzero((g[1:] > h) & (g[:-1] <= h))
    assert onsets <= N / T               # the union bound: at most 20 expected


def test_clipped_glr_ignores_one_spike_and_still_detects_a_shift():
    """Huber's ψ on the GLR: one sample adds at most c²/2 nats. The spike has
    the shape a fuel sensor's 1 s spike gave on the Camry record (s = -7.5,
    then +4.1 as the filter pulls back); the shift is 1 std from sample 300."""
    M, c = 50, 3.0
    spike = np.zeros(200)
    spike[100], spike[101] = -7.5, 4.1
    g, _ = glr_mean_jump(spike, M)
    assert g[100] == pytest.approx(7.5 ** 2 / 2)           # the plain test: 28.1 nats
    gc, _ = glr_mean_jump(spike, M, clip=c)
    assert gc.max() == pytest.approx(c * c / 2)             # 4.5 nats, under any threshold
    h = glr_threshold(10 * 3600.0, 1.0, M)                  # one false alarm per 10 h at 1 Hz
    assert h > c * c / 2 and g[100] > h
    rng = np.random.default_rng(3)
    s = rng.normal(0.0, 1.0, 600)
    s[300:] += 1.0
    first = [int(np.flatnonzero(glr_mean_jump(s, M, clip=cl)[0] > h)[0]) for cl in (None, c)]
    assert 300 <= first[1] <= first[0] + 3                  # detected, at most 3 samples later
    with pytest.raises(OptionError, match="clip"):
        glr_mean_jump(s, M, clip=0.0)


def test_serial_inflation_is_the_long_run_variance_and_ignores_a_jump():
    """λ of white noise is 1; of an AR(1) with φ = 0.6 and unit variance its
    long-run variance (1 + φ)/(1 − φ) = 4 (Hamilton 1994, eq. 7.2.8); a
    jump of the mean by 5 std in the middle changes neither (it moves one
    difference of block sums)."""
    from bondgraph.inference.changes import INFLATION_MIN, serial_inflation

    rng = np.random.default_rng(5)
    N, phi = 20_000, 0.6
    white = rng.normal(0.0, 1.0, N)
    ar = np.empty(N)
    ar[0] = white[0]
    for k in range(1, N):                   # stationary, unit variance
        ar[k] = phi * ar[k - 1] + np.sqrt(1 - phi * phi) * white[k]
    lam = serial_inflation(ar, 500)
    assert lam == pytest.approx((1 + phi) / (1 - phi), rel=0.35)
    jump = np.where(np.arange(N) >= N // 2, 5.0, 0.0)
    assert serial_inflation(ar + jump, 500) == pytest.approx(lam, rel=0.2)
    assert serial_inflation(white, 500) == 1.0
    assert serial_inflation(white + jump, 500) == 1.0
    assert serial_inflation(1.3 * white, 500) == 1.0 < INFLATION_MIN      # under 2: as is
    assert serial_inflation(ar[:100], 500) == 1.0                 # too few blocks: as is
    # under 2 but serially correlated (lag-1 autocorrelation within the blocks 0.3, z ~ 40):
    # applied. AR(1), φ = 0.3: long-run variance (1 + φ)/(1 − φ) = 1.86
    weak = np.empty(N)
    weak[0] = white[0]
    for k in range(1, N):
        weak[k] = 0.3 * weak[k - 1] + np.sqrt(1 - 0.09) * white[k]
    assert serial_inflation(weak, 500) == pytest.approx(1.3 / 0.7, rel=0.35)
    assert 1.0 < serial_inflation(weak, 500) < INFLATION_MIN
    assert serial_inflation(weak + jump, 500) == pytest.approx(serial_inflation(weak, 500),
                                                               rel=0.2)


def test_a_logit_prior_is_never_wider_than_its_box():
    """std_of: first order (σ_p / g'(z)) while that is below π/√3, the std of
    z = logit of a parameter uniform over its box; wider is capped."""
    tm = TrackingModel.from_graph(mass_spring_damper(), ["c"])
    tp = tm.tracked[0]
    lo, hi = tp.lower, tp.upper
    p = lo + 0.3 * (hi - lo)
    slope = (p - lo) * (hi - p) / (hi - lo)
    assert float(tp.std_of(p, 0.01 * slope)) == pytest.approx(0.01)
    assert float(tp.std_of(p, 100 * slope)) == pytest.approx(np.pi / np.sqrt(3))
    z = stats.logistic.rvs(size=200_000, random_state=1)    # p uniform over the box
    assert np.std(z) == pytest.approx(np.pi / np.sqrt(3), rel=0.01)


# ---------------------------------------------------------------- the tracker
@pytest.fixture(scope="module")
def tracking_model():
    return TrackingModel.from_graph(mass_spring_damper(), ["c"])


def test_step_in_damping_detected_and_reestimated(tracking_model):
    base, t, F, y = msd_record(seed=1, c_after=3.0)
    pr = make_problem(base, (t, F, y), ukf=UKF)
    res = track(pr, tracking_model, options=TrackOptions(false_alarm_hours=10.0))
    assert len(res.changes) == 1
    ch = res.changes[0]
    assert ch.parameter == "c"
    assert 0.0 <= ch.alarm_time - T_CHANGE <= 1.0          # detected within 1 s
    assert abs(ch.time - T_CHANGE) <= 0.2                  # change time within 0.2 s
    assert abs(ch.before - 1.5) <= 3 * ch.before_std
    assert abs(ch.after - 3.0) <= 3 * ch.after_std
    k = int(np.searchsorted(t, 45.0))                       # 15 s after: filtered and smoothed
    assert abs(res.estimate[k, 0] - 3.0) <= 3 * res.std[k, 0]
    assert abs(res.smoothed[k, 0] - 3.0) <= 3 * res.smoothed_std[k, 0]
    k = int(np.searchsorted(t, 15.0))
    assert abs(res.smoothed[k, 0] - 1.5) <= 3 * res.smoothed_std[k, 0]


def test_a_restart_the_added_state_covariance_breaks_falls_back_to_the_reset_alone(
        tracking_model, monkeypatch):
    """At a change the tracker restarts with the original states' prior
    covariance added (``track._reset`` with ``P_start``); where that filter
    fails (a stiff law, e.g. Dahl friction, stepped outside RK4's stability
    region by sigma points spread over the states' scales: a user's
    closed-loop drive ended "the tracking filter fails" at the restart's
    first sample), the restart is taken with the changed parameter's
    variance reset alone (``track._restarted``). Injected here by a
    non-finite added covariance: the result is the one of a tracker that
    adds none, and the change is found and re-estimated (truth by the
    generated model's simulation, c 1.5 -> 3.0 at 30 s)."""
    from bondgraph.inference import track as T

    base, t, F, y = msd_record(seed=1, c_after=3.0)
    pr = make_problem(base, (t, F, y), ukf=UKF)
    opts = TrackOptions(false_alarm_hours=10.0, smooth=False)
    n = base.n_x
    monkeypatch.setattr(T, "_states_prior", lambda tm, P0: np.zeros_like(P0))
    ref = track(pr, tracking_model, options=opts)
    broken = np.zeros((n + 1, n + 1))
    broken[:n, :n] = np.nan
    monkeypatch.setattr(T, "_states_prior", lambda tm, P0: broken)
    res = track(pr, tracking_model, options=opts)
    assert [(c.parameter, c.index) for c in res.changes] == \
        [(c.parameter, c.index) for c in ref.changes] == [("c", ref.changes[0].index)]
    np.testing.assert_array_equal(res.estimate, ref.estimate)
    np.testing.assert_array_equal(res.std, ref.std)
    ch = res.changes[0]
    assert abs(ch.time - T_CHANGE) <= 0.2 and abs(ch.after - 3.0) <= 3 * ch.after_std


@pytest.mark.parametrize("seed, c_after", [(1, 3.0), (2, None)])
def test_first_pass_in_chunks_equals_one_pass_to_the_end(tracking_model, monkeypatch, seed,
                                                         c_after):
    """The first pass stops after the chunk of the first alarm
    (``track.CHUNK_S``); with a chunk longer than the record it is one pass
    to the end (as before chunks). Both give the same changes, estimates,
    statistics and NLL: the chunks restart the same recursion and the
    detector's windows are trailing."""
    from bondgraph.inference import track as T

    base, t, F, y = msd_record(seed=seed, c_after=c_after)
    pr = make_problem(base, (t, F, y), ukf=UKF)
    opts = TrackOptions(false_alarm_hours=10.0, smooth=False)
    chunked = track(pr, tracking_model, options=opts)
    monkeypatch.setattr(T, "CHUNK_S", 10 * T_END)
    whole = track(pr, tracking_model, options=opts)
    assert len(chunked.changes) == len(whole.changes) == (0 if c_after is None else 1)
    for a, b in zip(chunked.changes, whole.changes):
        assert (a.parameter, a.index, a.alarm_index) == (b.parameter, b.index, b.alarm_index)
        assert a.statistic == pytest.approx(b.statistic, rel=1e-9)
        assert a.after == pytest.approx(b.after, rel=1e-9)
    np.testing.assert_allclose(chunked.estimate, whole.estimate, rtol=1e-9, atol=0)
    np.testing.assert_allclose(chunked.std, whole.std, rtol=1e-7, atol=0)
    np.testing.assert_allclose(chunked.statistic, whole.statistic, rtol=1e-7, atol=1e-9)
    assert chunked.nll == pytest.approx(whole.nll, rel=1e-10)


def test_no_false_alarm_and_white_increments_without_change(tracking_model):
    base, t, F, y = msd_record(seed=2)
    pr = make_problem(base, (t, F, y), ukf=UKF)
    res = track(pr, tracking_model, options=TrackOptions(false_alarm_hours=10.0))
    assert res.changes == []
    s = res.increments[:, 0]
    s = s[np.isfinite(s)]
    assert s.size > 5000
    assert abs(s.mean()) < 4 / np.sqrt(s.size)            # N(0, 1) before a change
    assert abs(s.var() - 1.0) < 0.1
    assert abs(res.estimate[-1, 0] - 1.5) <= 3 * res.std[-1, 0]


@pytest.mark.parametrize("backend,tol", [("numpy", 1e-11), ("numba", 1e-8)])
def test_streaming_tracker_equals_batch_tracker(tracking_model, backend, tol):
    from bondgraph.inference.track import Tracker

    base, t, F, y = msd_record(seed=4, c_after=2.5)
    t, F, y = t[:1500], F[:1500], y[:1500].copy()
    y[100:110, 1] = np.nan                                  # missing samples
    pr = make_problem(base, (t, F, y), ukf=UKFOptions(method="ros2", substeps=2,
                                                       backend=backend))
    opts = TrackOptions(false_alarm_hours=None, smooth=False)
    batch = track(pr, tracking_model, drift={"c": 0.05}, options=opts)
    tm = tracking_model
    trk = Tracker.from_problem(pr, tm, drift={"c": 0.05}, options=opts)
    info, obs = np.zeros(t.size), np.zeros(t.size, bool)
    for k in range(t.size):
        est, sd = trk.update(t[k], F[k], y[k])
        assert est[0] == pytest.approx(batch.estimate[k, 0], rel=tol)
        assert sd[0] == pytest.approx(batch.std[k, 0], rel=max(tol, 1e-9))
        info[k], obs[k] = trk.information[0], trk.observable[0]
    # the observability test, sample by sample (measured: 0 and 2.6e-11 relative, no
    # sample of the mask different)
    assert info == pytest.approx(batch.information[:, 0], rel=1e-8, abs=1e-9 * info.max())
    assert (obs == batch.observable[:, 0]).all()
    assert 0.9 < obs.mean() < 1.0


def _streamed(trk, t, u, y):
    """Feed a record to a streaming tracker: its statistic (N, k) and the
    samples at which it raised ``alarm``."""
    G, alarms = np.zeros((t.size, len(trk.tm.tracked))), []
    for k in range(t.size):
        trk.update(t[k], u[k], y[k])
        G[k] = trk.statistic
        if trk.alarm is not None:
            alarms.append(k)
    return G, alarms


ONLINE = UKFOptions(method="ros2", substeps=2, backend="numba")
#: the detector as both trackers run it in the on-line tests (no second pass)
ONLINE_OPTS = TrackOptions(false_alarm_hours=10.0, smooth=False, calibrate=False)


def _batch_and_stream(tm, seed, c_after=None, **stream):
    """The batch tracker and the streaming one (``stream``: more arguments of
    :meth:`Tracker.from_problem`) on :func:`msd_record`; returns the problem,
    the batch result, the tracker, its statistic and alarm samples."""
    from bondgraph.inference.track import Tracker

    base, t, F, y = msd_record(seed=seed, c_after=c_after)
    pr = make_problem(base, (t, F, y), ukf=ONLINE)
    batch = track(pr, tm, options=ONLINE_OPTS)
    trk = Tracker.from_problem(pr, tm, options=ONLINE_OPTS, **stream)
    return pr, batch, trk, *_streamed(trk, t, F, y)


def test_online_detection_finds_the_batch_trackers_change(tracking_model):
    """The streaming tracker's GLR test, sample by sample, against the batch
    tracker's: the same statistic up to the change (measured 2.5e-14), the
    same change sample, alarm and parameter, and after the restart the
    same re-estimate (the batch centres its restart on the record's end,
    the stream on the alarm: measured 8e-7 relative)."""
    _, batch, trk, G, alarms = _batch_and_stream(tracking_model, 4, 2.5)
    ch, = batch.changes
    on, = trk.changes
    assert 0.0 <= ch.time - T_CHANGE < 0.5               # the next force step shows it
    assert (on.index, on.alarm_index, on.parameter) == (ch.index, ch.alarm_index, "c")
    assert alarms == [ch.alarm_index]                   # one parameter: attributed at once
    assert on.attributed_time == on.alarm_time
    np.testing.assert_allclose(G[:ch.index, 0], batch.statistic[:ch.index, 0], atol=1e-9)
    assert on.statistic == pytest.approx(ch.statistic, rel=1e-9)
    assert on.before == pytest.approx(ch.before, rel=1e-9)
    assert on.after == pytest.approx(ch.after, rel=1e-4)
    assert on.after == pytest.approx(2.5, abs=3 * on.after_std + 0.01)


def test_online_detection_without_change_and_with_an_inflation(tracking_model):
    """No change, no alarm; the statistic is the windowed GLR of the clipped
    standardised updates (:func:`glr_mean_jump` on the batch tracker's
    increments, where observable), with a given λ = 4 on the updates halved."""
    from bondgraph.inference.track import Tracker

    base, t, F, y = msd_record(seed=2)
    pr = make_problem(base, (t, F, y), ukf=ONLINE)
    opts = TrackOptions(false_alarm_hours=10.0, smooth=False, calibrate=False)
    batch = track(pr, tracking_model, options=opts)
    assert batch.changes == []
    obs = batch.observable[:, 0]
    window = opts.samples(DT)[0]
    for lam in (1.0, 4.0):
        trk = Tracker.from_problem(pr, tracking_model, options=opts, inflation={"c": lam})
        G, alarms = _streamed(trk, t, F, y)
        assert alarms == [] and trk.changes == []
        ref, _ = glr_mean_jump(np.where(obs, batch.increments[:, 0] / np.sqrt(lam), np.nan),
                               window, clip=opts.glr_clip)
        np.testing.assert_allclose(G[:, 0], np.where(obs, ref, 0.0), atol=1e-9)
        assert G.max() < trk.watch.h
    with pytest.raises(ModelError, match="'k'"):
        Tracker.from_problem(pr, tracking_model, options=opts, inflation={"k": 2.0})
    with pytest.raises(OptionError, match=">= 1"):
        Tracker.from_problem(pr, tracking_model, options=opts, inflation={"c": 0.5})
    quiet = Tracker.from_problem(pr, tracking_model, options=TrackOptions(false_alarm_hours=None))
    assert quiet.watch is None


def test_online_detection_attributes_the_change_among_two_parameters():
    """Two tracked parameters (damping and stiffness), the damping steps: the
    stream attributes the change to c as the batch tracker does, once the
    restart of c explains the samples since the change better than the
    restart of k by more than the threshold, within one window after the
    alarm (the batch tracker's look-ahead). Measured: raised by k's updates
    at 30.09 s, attributed to c at 30.13 s (margin 22.3 nats, h 20.6)."""
    tm = TrackingModel.from_graph(mass_spring_damper(), ["c", "k"])
    pr, batch, trk, G, alarms = _batch_and_stream(tm, 4, 2.5)
    t, opts = pr.t, ONLINE_OPTS
    ch, on = batch.changes[0], trk.changes[0]
    assert (on.index, on.alarm_index, on.parameter) == (ch.index, ch.alarm_index, "c")
    assert on.detected == ch.detected
    assert set(on.isolation) == {"c", "k"}
    assert on.alarm_time <= on.attributed_time <= on.alarm_time + opts.seconds(DT)[0]
    if on.attributed_time < on.alarm_time + opts.seconds(DT)[0]:
        assert on.isolation["k"] > trk.watch.h            # decided by the margin
    assert alarms[0] == int(np.searchsorted(t, on.attributed_time))
    assert on.after == pytest.approx(ch.after, rel=1e-3)


def test_drift_intensity_estimated_by_maximum_likelihood():
    from bondgraph.inference.options import FitOptions
    from bondgraph.inference.track import estimate_drift

    # a random walk of constant intensity in c's unit: the model of transform "none"
    # (the logit's walk is in z: its intensity in c's unit follows the slope)
    q_true, seg = 0.08, 0.5                 # N s/m per sqrt(s); c held over 0.5 s pieces
    g = mass_spring_damper()
    base = Model.from_graph(g)
    rng = np.random.default_rng(5)
    dt, T = 0.02, 120.0
    t = np.arange(0.0, T + dt / 2, dt)
    F = np.repeat(rng.normal(0.0, 5.0, int(T / seg) + 1), int(seg / dt))[:t.size, None]
    c = 1.5 + np.cumsum(rng.normal(0.0, q_true * np.sqrt(seg), int(T / seg) + 1))
    assert c.min() > 0.5 and c.max() < 5.0
    y, x = [], base.x0
    n = int(round(seg / dt))
    for i in range(0, t.size - 1, n):
        j = min(i + n, t.size - 1)
        s = simulate(base, t[i:j + 1], F[i:j + 1], x0=x, theta={"c": c[i // n]}, hold="zoh")
        y.append(s.y[:-1])
        x = s.x[-1]
    y.append(s.y[-1:])
    y = np.vstack(y) + rng.normal(0.0, 1.0, (t.size, 2)) * np.array([0.002, 0.01])
    pr = make_problem(base, (t, F, y), ukf=UKFOptions(method="rk4", substeps=2))
    tm = TrackingModel.from_graph(g, ["c"], {"c": 0.2}, transform="none")
    res = estimate_drift(pr, tm, fit=FitOptions(particles=8, iterations=8, seed=0, progress=False,
                                                check_discretisation=False))
    q, sd = res.estimates[0], res.std[0]
    print("drift MLE", q, sd)
    assert np.isfinite(sd) and sd > 0
    assert abs(q - q_true) <= 3 * sd


def test_track_command_writes_table_changes_and_plots(tmp_path, capsys, monkeypatch):
    import json

    from bondgraph.cli.main import main
    from bondgraph.data.records import Experiment

    base, t, F, y = msd_record(seed=1, c_after=3.0)
    rec = Experiment.from_arrays(t, model=base, u=F, y=y,
                                 noise_std={"x": 0.002, "v": 0.01},
                                 meta={"true_parameters": {"c": 1.5}})
    path = tmp_path / "msd_step.csv"
    rec.save(path)
    out = tmp_path / "out"
    code = main(["track", "--model", "mass_spring_damper", "--data", str(path), "--track", "c",
                 "--out", str(out), "--method", "rk4", "--substeps", "2", "--hold", "zoh",
                 "--backend", "numpy", "--online"])
    assert code == 0
    text = capsys.readouterr().out
    assert "1 change(s)" in text
    changes = json.loads((out / "changes.json").read_text())["changes"]
    assert len(changes) == 1 and changes[0]["parameter"] == "c"
    # --online: the record replayed through the streaming tracker finds the same change,
    # raised at the same sample (one parameter: attributed there)
    online = json.loads((out / "changes_online.json").read_text())["changes"]
    assert [(c["index"], c["alarm_index"], c["parameter"]) for c in online] == [
        (changes[0]["index"], changes[0]["alarm_index"], "c")]
    assert online[0]["attributed_time"] == online[0]["alarm_time"]
    assert online[0]["after"] == pytest.approx(changes[0]["after"], rel=1e-3)
    assert "on-line (the streaming tracker, each sample as it arrives): 1 change(s)" in text
    assert "(as the batch run)" in text
    assert abs(changes[0]["time"] - T_CHANGE) <= 0.2
    assert abs(changes[0]["after"] - 3.0) <= 3 * changes[0]["after_std"]
    table = np.genfromtxt(out / "track.csv", delimiter=",", names=True)
    assert table.size == t.size
    assert abs(table["c"][-1] - 3.0) <= 3 * table["cstd"][-1]
    # observability: forced throughout, so all but the record's first window (2 s at most)
    obs = table["observable_c"]
    assert set(np.unique(obs)) <= {0.0, 1.0} and obs[t >= 2.0].all() and obs[0] == 0.0
    frac = 100 * obs.mean()
    assert f"observable {frac:.3g} % of the record; not observable 0-" in text
    assert (out / "track_c.png").stat().st_size > 1000
    monkeypatch.chdir(tmp_path)          # without --out: track_<model>_<record>, as estimate
    assert main(["track", "--model", "mass_spring_damper", "--data", str(path), "--track", "c",
                 "--method", "rk4", "--substeps", "2", "--hold", "zoh", "--backend", "numpy",
                 "--no-plots"]) == 0
    default, = tmp_path.glob("track_*_msd_step")
    again = json.loads((default / "changes.json").read_text())["changes"]
    assert [c["index"] for c in again] == [c["index"] for c in changes]
    code = main(["track", "--model", "mass_spring_damper", "--data", str(path), "--track",
                 "cc", "--out", str(tmp_path / "o2")])
    assert code == 2
    assert "cannot track 'cc'" in capsys.readouterr().err


# ---------------------------------------------------------------- observability
def test_information_gain_and_observable_mask_against_closed_forms():
    from bondgraph.inference.changes import first_alarm, information_gain, observable_mask

    # a scalar Kalman filter on y = H z + e, z a random walk: 1/P+ - 1/P- = H²/R exactly
    H, R, q2dt, P = np.array([2.0, 0.0, 0.5, 3.0]), 0.04, 0.01, 0.3
    Pp, prior = [], P
    for h in H:
        Pm = P + q2dt if Pp else P
        P = 1.0 / (1.0 / Pm + h * h / R)
        Pp.append(P)
    dts = np.array([0.0, q2dt, q2dt, q2dt])
    info = information_gain(np.array(Pp), prior, dts, np.ones(4))
    assert info == pytest.approx(H ** 2 / R, rel=1e-9, abs=1e-9)
    # with the logit's slope g' = 0.5: information in p's unit is that in z's over g'²
    assert information_gain(np.array(Pp), prior, dts, 0.5 * np.ones(4)) == pytest.approx(
        4 * H ** 2 / R, rel=1e-9, abs=1e-9)
    # the mask: sigma0² · (sum over the trailing window) >= 1/ratio - 1
    i = np.zeros((10, 1))
    i[4:] = 1.0                           # 1 per sample from sample 4
    obs = observable_mask(i, [0.5], window=3, ratio=0.5)    # needs 0.25 · I_w >= 1: I_w >= 4
    assert not obs.any()
    obs = observable_mask(i, [0.5], window=4, ratio=0.5)
    assert np.flatnonzero(obs[:, 0]).tolist() == [7, 8, 9]
    # sigma0 = 1, ratio 0.5: I_w >= 1, reached at the first informative sample
    assert observable_mask(i, [1.0], window=2, ratio=0.5)[:, 0].tolist() == \
        [False] * 4 + [True] * 6
    # ratio 0.2: I_w >= 4, more than a window of 2 can hold
    assert not observable_mask(i, [1.0], window=2, ratio=0.2).any()
    # the detector raises no alarm where the parameter is not observable
    rng = np.random.default_rng(3)
    s = rng.normal(0.0, 1.0, (600, 1))
    s[200:400] += 3.0                     # a mean shift over samples 200..399
    h = glr_threshold(1e6, 1.0, 50)
    alarm, _ = first_alarm(s, h, 50)
    assert alarm is not None and 200 <= alarm[0] < 230
    allowed = np.ones((600, 1), bool)
    allowed[150:450] = False
    alarm, G = first_alarm(np.where(allowed, s, np.nan), h, 50, allowed=allowed)
    assert alarm is None and not G[150:450].any()


@pytest.mark.parametrize("seed", [1, 4])
def test_damping_not_observable_at_rest_and_no_alarm_there(tracking_model, seed):
    # random force steps, but none over [T0, T1): the mass rings down and rests
    T0, T1, T = 20.0, 50.0, 70.0
    base = Model.from_graph(mass_spring_damper())
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, T + DT / 2, DT)
    F = np.repeat(rng.normal(0.0, 5.0, int(T / 0.5) + 1), 50)[:t.size, None]
    F[(t >= T0) & (t < T1)] = 0.0
    sim = simulate(base, t, F, theta={"c": 1.5}, hold="zoh")
    sv = 0.01
    y = sim.y + rng.normal(0.0, 1.0, sim.y.shape) * np.array([0.002, sv])
    opts = TrackOptions(false_alarm_hours=10.0)
    res = track(make_problem(base, (t, F, y), ukf=UKF), tracking_model, drift={"c": 0.5},
                options=opts)
    obs = res.observable[:, 0]
    # hand bound: the free response's velocity envelope decays as exp(-c t / 2m); after
    # T_ring = (2m/c) ln(A sqrt(W) / sv) it is below what a window of W samples can resolve
    # (the sensor noise sv averaged over W), so no window ending after T_ring + W·dt
    # holds information about c
    w_obs = opts.seconds(DT)[1]                       # the default: 2 s (200 samples)
    assert w_obs == 2.0
    m, c, W = 2.0, 1.5, int(round(w_obs / DT))
    A = np.abs(sim.y[(t >= T0) & (t < T0 + 1.0), 1]).max()
    t_ring = 2 * m / c * np.log(A * np.sqrt(W) / sv)
    assert 10.0 < t_ring < 25.0
    core = (t >= T0 + t_ring + w_obs) & (t < T1)
    assert core.sum() > 500 and not obs[core].any()
    # forced: observable, but for the record's first window and, after T1, until the
    # first force piece of at least half the force's std (5 N) has acted for its 0.5 s
    # (a near-zero piece leaves the mass near rest: seed 4's first two are 0.45, 0.6 N)
    t_back = t[(t >= T1) & (np.abs(F[:, 0]) >= 2.5)][0] + 0.5
    forced = ((t >= w_obs) & (t < T0)) | (t >= t_back)
    assert obs[forced].all()
    (a, b), = [s for s in res.unobservable("c") if s[1] > T0]
    print("unobservable stretch", a, b, "hand bound", T0 + t_ring, "back by", t_back,
          "observable fraction", obs.mean())
    assert T0 < a <= T0 + t_ring and T1 <= b < t_back
    # the drift lets the estimate wander at rest (several prior std), yet no alarm
    rest = (t >= a) & (t <= b)
    assert np.ptp(res.estimate[rest, 0]) > 3 * 0.15
    assert res.changes == []
    assert not (res.statistic[~obs] > 0).any()
    # the table
    assert res.columns()["observable_c"].tolist() == obs.astype(float).tolist()


def test_unrecorded_vibration_at_rest_is_no_change_where_damping_is_not_observable(
        tracking_model):
    # at rest over [T0, T1) the mass is shaken by an unrecorded 0.05 N square wave
    # (0.3 Hz): the record's input says 0, the filter's updates there are model error
    T0, T1, T = 20.0, 50.0, 70.0
    base = Model.from_graph(mass_spring_damper())
    rng = np.random.default_rng(1)
    t = np.arange(0.0, T + DT / 2, DT)
    F = np.repeat(rng.normal(0.0, 5.0, int(T / 0.5) + 1), 50)[:t.size, None]
    rest = (t >= T0) & (t < T1)
    F[rest] = 0.0
    shaken = F.copy()
    shaken[rest, 0] = 0.05 * np.sign(np.sin(2 * np.pi * 0.3 * t[rest]))
    sim = simulate(base, t, shaken, theta={"c": 1.5}, hold="zoh")
    y = sim.y + rng.normal(0.0, 1.0, sim.y.shape) * np.array([0.002, 0.01])
    pr = make_problem(base, (t, F, y), ukf=UKF)
    res = track(pr, tracking_model, drift={"c": 0.5}, options=TrackOptions())
    assert res.changes == []
    (a, b), = [s for s in res.unobservable("c") if s[1] > T0]
    assert T0 < a < T1 - 10.0 and T1 <= b < T1 + 1.0
    # the same detector with (almost) no observability test reports the model error
    # as a change of c inside the stretch (measured: at 33.2 s, alarm at 34.2 s)
    blind = track(pr, tracking_model, drift={"c": 0.5},
                  options=TrackOptions(observable_ratio=1 - 1e-9, smooth=False))
    assert len(blind.changes) >= 1 and T0 < blind.changes[0].time < T1


def test_inconsistent_innovations_flag_model_error_not_a_clean_record():
    """The NIS windows (χ² of the summed NIS per 10 s): a record of the right
    model (damping stepping 1.5 -> 2.5, tracked) leaves at most one window
    above the 0.999 quantile; the same model tracking c on a record whose
    spring has an unmodelled cubic term k3 x³ (scipy from the hand-written
    equations m dv/dt = F - k x - k3 x³ - c v) is flagged in most windows:
    there the tracker would read model error as changes of c (measured: the
    clean record's mean NIS 2.05 for 2 outputs and one window flagged, the
    change's; with the cubic spring all 7 windows, mean NIS 7282)."""
    base, t, F, y = msd_record(seed=8, c_after=2.5)
    tm = TrackingModel.from_graph(mass_spring_damper(), ["c"], {"c": 0.05})
    opts = TrackOptions(false_alarm_hours=None, smooth=False)
    clean = track(make_problem(base, (t, F, y), ukf=UKF), tm, options=opts)
    assert len(clean.inconsistent()) <= 1
    assert np.nanmean(clean.nis) == pytest.approx(2.0, rel=0.1)      # two outputs
    from scipy.integrate import solve_ivp

    k3 = 4000.0
    def rhs(tt, z):
        i = min(int(tt / DT), F.shape[0] - 1)                      # zero-order hold
        x, v = z
        return [v, (F[i, 0] - 50.0 * x - k3 * x ** 3 - 1.5 * v) / 2.0]
    sol = solve_ivp(rhs, (0.0, t[-1]), [0.0, 0.0], t_eval=t, rtol=1e-9, atol=1e-12,
                    max_step=DT / 2)
    rng = np.random.default_rng(9)
    yc = sol.y.T + rng.normal(0.0, 1.0, (t.size, 2)) * np.array([0.002, 0.01])
    assert np.abs(k3 * sol.y[0] ** 3).max() > 0.2 * np.abs(50.0 * sol.y[0]).max()
    bad = track(make_problem(base, (t, F, yc), ukf=UKF), tm, options=opts)
    n_win = int(np.ceil(t.size / round(10.0 / DT)))
    assert len(bad.inconsistent()) >= n_win - 1            # measured: all 7; clean: 1
    assert np.nanmean(bad.nis) > 100.0                     # measured: 7282


def test_track_from_an_estimate_result_or_a_loop_report(tmp_path):
    """``bondgraph track --from``: the start values and prior std from
    ``bondgraph estimate``'s result.json or ``bondgraph loop``'s report.json
    (its final fit; a parameter on its box has std null)."""
    import json

    from bondgraph.cli.track import _from_result
    from bondgraph.errors import DataError

    est = tmp_path / "result.json"
    est.write_text(json.dumps({"params": ["c", "k"], "estimates": [1.6, 49.0],
                               "std": [0.01, "inf"]}))
    assert _from_result(est) == ({"c": 1.6, "k": 49.0}, {"c": 0.01})
    # an estimate on its box has std null in result.json (was a TypeError,
    # reported as "neither ... nor")
    est.write_text(json.dumps({"params": ["c", "k", "tau"], "estimates": [1.6, 49.0, 0.2],
                               "std": [0.01, 0.5, None]}))
    assert _from_result(est) == ({"c": 1.6, "k": 49.0, "tau": 0.2}, {"c": 0.01, "k": 0.5})
    rep = tmp_path / "report.json"
    rep.write_text(json.dumps({"final_fit": {"estimates": {"c": 1.7, "k": 51.0},
                                             "std": {"c": 0.02, "k": None}}}))
    assert _from_result(rep) == ({"c": 1.7, "k": 51.0}, {"c": 0.02})
    bad = tmp_path / "other.json"
    bad.write_text(json.dumps({"something": 1}))
    with pytest.raises(DataError, match="neither a `bondgraph estimate` result.json nor"):
        _from_result(bad)
    # the fit's measurement-noise levels, held for the outputs nothing else
    # gives one: an estimate's noise.<output>, a loop report's estimated
    # levels (final_fit.noise_estimates) over the ones it held (before, a
    # report's were not read: the record's second differences were held)
    from bondgraph.cli.track import _from_levels

    est.write_text(json.dumps({"params": ["c", "noise.x"], "estimates": [1.6, 0.002],
                               "std": [0.01, 1e-4]}))
    assert _from_levels(est) == {"x": 0.002}
    rep.write_text(json.dumps({
        "final_fit": {"estimates": {"c": 1.7}, "noise_estimates": {"x": 0.003}},
        "settings": {"noise_levels": {"x": 0.05, "v": 0.01}}}))
    assert _from_levels(rep) == {"x": 0.003, "v": 0.01}
    with pytest.raises(DataError, match="--from .*other.json"):
        _from_levels(bad)


def test_substeps_chosen_from_the_tracked_record_remove_false_changes_and_bias():
    """A record sampled at 20 Hz with tiny noise (2 mm, 1 cm/s): a coarse
    ROS2 step mispredicts it by many noise std, and the tracker reads its own
    discretisation error as changes of c. ``choose_substeps`` doubles the
    substeps until the Richardson estimate of a 2 s window's log-likelihood
    error is within one sampling std. Against the truth c = 1.5 (scipy's
    solve_ivp): with ROS2(2) false changes and c 50 std off at the end
    (measured: 5 changes, 1.3762 +- 0.0025; the step's error correlates the
    updates, and the calibrated test reports fewer); with the chosen substeps
    (measured: 32; 16 still 1.87 window std from 32) no change and c within
    3 std over the whole record after 10 s (measured: at most 2.03)."""
    from dataclasses import replace

    from bondgraph.inference.track import choose_substeps

    base = Model.from_graph(mass_spring_damper())
    rng = np.random.default_rng(1)
    dt, t_end = 0.05, 60.0
    t = np.arange(0.0, t_end + dt / 2, dt)
    F = np.repeat(rng.normal(0.0, 5.0, int(t_end / 0.5) + 2), 10)[:t.size, None]
    y = simulate(base, t, F, theta={"c": 1.5}, hold="zoh").y
    y = y + rng.normal(0.0, 1.0, y.shape) * np.array([0.002, 0.01])
    tm = TrackingModel.from_graph(mass_spring_damper(), ["c"], {"c": 1e-3})
    opts = TrackOptions(false_alarm_hours=10.0, smooth=False)
    pr = make_problem(base, (t, F, y), ukf=UKFOptions(method="ros2", substeps=2))
    coarse = track(pr, tm, options=replace(opts, calibrate=False))
    assert len(coarse.changes) >= 3
    assert abs(coarse.estimate[-1, 0] - 1.5) > 10 * coarse.std[-1, 0]
    calibrated = track(pr, tm, options=opts)      # the step's error correlates the updates:
    assert calibrated.settings["inflation"]["c"] >= 2.0     # the test calibrated to it
    assert len(calibrated.changes) < len(coarse.changes)
    choice = choose_substeps(pr, tm, options=opts)
    assert choice.ok and choice.substeps in (16, 32)
    assert choice.error[2] > 100.0 and choice.error[choice.substeps] <= 1.0
    fine = track(pr.conditioned_on(disc=replace(pr.disc, substeps=choice.substeps)), tm,
                 options=opts)
    assert fine.changes == []
    z = (fine.estimate[:, 0] - 1.5) / fine.std[:, 0]
    assert np.abs(z[t >= 10.0]).max() <= 3.0


def test_default_windows_span_enough_samples_on_a_slowly_sampled_record():
    """TrackOptions.seconds: the default GLR and observability windows are
    10 s and 2 s (at 40 Hz 400 and 80 samples), stretched to 20 and 10
    samples where that is longer (10 s sampling: 200 s and 100 s, where 10 s
    would be one sample); windows given are kept as given."""
    opts = TrackOptions()
    assert opts.seconds(0.025) == (10.0, 2.0) and opts.samples(0.025) == (400, 80)
    assert opts.seconds(10.0) == (200.0, 100.0) and opts.samples(10.0) == (20, 10)
    given = TrackOptions(window_s=10.0, observable_s=2.0)
    assert given.seconds(10.0) == (10.0, 2.0) and given.samples(10.0) == (1, 1)
    with pytest.raises(OptionError):
        TrackOptions(window_s=0.0)


@pytest.mark.parametrize("method_free", [True, False])
def test_track_takes_rk4_where_ros2_does_not_converge(monkeypatch, method_free):
    """cli.track.tracking_discretisation: when the model's method (ROS2)
    does not converge within MAX_SUBSTEPS on the tracked record and no
    --method was given, RK4 is chosen the same way and taken when it
    converges (a user's drive: ROS2 over 128 substeps, RK4 4); a --method
    given is kept whatever its verdict."""
    from bondgraph.cli import track as cli_track
    from bondgraph.inference.track import SubstepChoice

    def fake(problem, tm, **kw):
        m = problem.ukf.method
        return SubstepChoice(128 if m == "ros2" else 4, m == "rk4", {}, {}, {}, m, 2.0)

    monkeypatch.setattr(cli_track, "choose_substeps", fake)
    t = np.arange(0.0, 1.0, 0.01)
    pr = make_problem(Model.from_spec("mass_spring_damper"),
                      (t, np.ones((t.size, 1)), np.zeros((t.size, 2))),
                      ukf=UKFOptions(method="ros2", substeps=1))
    got = cli_track.tracking_discretisation(pr, None, {}, TrackOptions(), method_free)
    want = ("rk4", 4) if method_free else ("ros2", 128)
    assert (got.ukf.method, got.ukf.substeps) == want


def test_the_window_a_parameter_needs_to_be_observable():
    """cli.track.needed_window: σ₀² Ī W >= 1/ρ − 1 solved for W (hand
    computed: σ₀ 0.1, Ī 2 per sample, ρ 0.5: W = 1 / (0.01 · 2) = 50
    samples, 5 s at dt 0.1 s), the option a quarter above it rounded up to
    two digits (6.3 s: at 5 s itself half the windows of an even record fall
    short; a user's Camry graph on 1 Hz, told "--observable-s 4.8e+02",
    stayed 0 % observable there, its windows at 0.9956 of the bound); a
    record that holds less than that in all says it cannot be tracked from
    it."""
    from types import SimpleNamespace

    from bondgraph.cli.track import needed_window

    def res(n):
        return SimpleNamespace(t=np.arange(n) * 0.1, information=np.full((n, 1), 2.0),
                               units=["kg"], settings={"sigma0": {"m": 0.1}, "dt": 0.1,
                                                       "track": {"observable_ratio": 0.5}})
    assert "observable over windows of about 5 s (--observable-s 6.3;" in needed_window(
        res(400), "m", 0)
    assert "not trackable from this record" in needed_window(res(30), "m", 0)
    assert needed_window(SimpleNamespace(settings={}, information=None), "m", 0) == ""
    # the typical sample's information, not the mean's: a few samples of
    # extreme information (a parameter pinned on its box) do not shrink the
    # window (the mean's here: 1e-37 s)
    spiky = res(400)
    spiky.information[:3] = 1e40
    assert "observable over windows of about 5 s (--observable-s 6.3;" in needed_window(
        spiky, "m", 0)


def test_a_start_value_the_record_disagrees_with_is_no_change():
    """The tracker started at c = 1.6 ± 0.01 N s/m (a prior from another
    record, tight) on a record whose damping is 1.5 until it steps to 3.0 at
    30 s: the first alarm, its onset within the GLR window of the first
    observable sample, is the start value corrected (``at_start``; the
    re-estimate 1.5 within 0.3 %), by the batch and the streaming tracker
    alike; the step at 30 s is a change. The summary counts one change."""
    from bondgraph.cli.track import summary
    from bondgraph.inference.track import Tracker

    tm = TrackingModel.from_graph(mass_spring_damper(), ["c"])
    base, t, F, y = msd_record(seed=1, c_after=3.0)
    pr = make_problem(base, (t, F, y), ukf=ONLINE)
    prior = dict(start={"c": 1.6}, std={"c": 0.01}, options=ONLINE_OPTS)
    res = track(pr, tm, **prior)
    first, step = res.changes
    (a, b), = res.unobservable("c")
    window = res.settings["window"]
    assert a == 0.0 and 0 < first.index - 1 - int(round(b / DT)) <= window
    assert first.at_start and not step.at_start
    # the re-estimates within 0.3 % of the truth (ROS2(2) at 100 Hz: measured 1.4970, 2.9957)
    assert first.before == pytest.approx(1.6, abs=0.01) and abs(first.after - 1.5) < 0.005
    assert abs(step.time - T_CHANGE) <= 0.2 and abs(step.after - 3.0) < 0.01
    text = summary(res)
    assert "at the start: c 1.59902" in text and "\n1 change(s)\n" in text
    trk = Tracker.from_problem(pr, tm, **prior)
    _streamed(trk, t, F, y)
    assert [(c.index, c.at_start) for c in trk.changes] == [(first.index, True),
                                                            (step.index, False)]
    # started at the record's own value, nothing at the start
    assert not any(c.at_start for c in track(pr, tm, start={"c": 1.5}, std={"c": 0.01},
                                             options=ONLINE_OPTS).changes)

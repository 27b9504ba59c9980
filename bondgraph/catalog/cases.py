"""The toolkit's bundled real-data loop cases (``bondgraph loop --case NAME``).

* ``emps``: the EMPS ball-screw drive (Janot et al. 2019) starting from mass
  and viscous friction; Coulomb and direction-dependent friction are missing.
* ``ced``: the coupled electric drives (Wigren & Schoukens 2017) starting from
  the linear drive; the sign-blind speed sensor is missing.
* ``silverbox``: the Silverbox electronic Duffing oscillator (Wigren &
  Schoukens 2013) declared as a linear mass-spring-damper; the cubic
  stiffness is missing.
* ``camry_cold``: the 2018 Camry's fuel flow on the cold-start UDDS bag
  (ANL D3), declared warm; the engine's warm-up is missing.

All read the local data folder (:mod:`bondgraph.data.datasets`).
"""

from __future__ import annotations

import functools

import numpy as np
from scipy.optimize import least_squares

from bondgraph.catalog.benchmarks import (
    CAMRY_HOT_FIT,
    camry_fuel,
    camry_warm,
    ced_linear,
    emps_arrays,
    emps_decimate,
    emps_filtered_signals,
    emps_viscous,
    silverbox_linear,
)
from bondgraph.core.graph import BondGraph
from bondgraph.core.smooth import smooth_clip
from bondgraph.data.datasets import camry_dyno, ced, emps, silverbox
from bondgraph.data.records import Experiment
from bondgraph.diagnose.cases import LoopCase, declared_builder
from bondgraph.diagnose.effects import DEFAULT_EFFECTS, OPTIONAL_EFFECTS
from bondgraph.diagnose.settings import FreeRunOptions, LoopSettings, SearchOptions
from bondgraph.inference.options import UKFOptions
from bondgraph.inference.prior import PriorSpec, rk4_outputs
from bondgraph.numerics.model import Model
from bondgraph.numerics.simulate import simulate

#: registered cases (``bondgraph.cases`` entry point)
CASES: dict[str, str] = {
    "emps": "bondgraph.catalog.cases:case_emps",
    "ced": "bondgraph.catalog.cases:case_ced",
    "silverbox": "bondgraph.catalog.cases:case_silverbox",
    "camry_cold": "bondgraph.catalog.cases:case_camry_cold",
}


def emps_declared() -> BondGraph:
    """EMPS starting graph: mass and viscous friction (bondgraph.catalog.benchmarks)."""
    return emps_viscous()


def _emps_record(decimate: int = 5, part: str = "estimation"):
    """The EMPS record ``part`` (``"estimation"``, or ``"validation"``: the
    force-pulse run the benchmark cross-validates on) for the filter,
    decimated; ``meta["emps_part"]`` names the part (:class:`EmpsForceError`
    reads it)."""
    exp = emps(part, download=False)
    t, u, y = emps_arrays(exp, decimate=decimate)
    dm = Model.from_graph(emps_declared())
    meta = {"description": f"EMPS {part} record (Janot et al. 2019), decimated x{decimate} "
                           f"(vir averaged over each interval)", "x0": {"q": float(y[0, 0])},
            "emps_part": part}
    tag = "estimation" if part == "estimation" else "validation_pulses"
    return Experiment.from_arrays(t, model=dm, u=u, y=y, meta=meta,
                                  name=f"emps_{tag}_{int(round(1 / (t[1] - t[0])))}Hz")


class EmpsForceError:
    """Force relative error of the fitted model's inverse dynamics on the
    benchmark's filtered signals, ||τ - τ̂|| / ||τ|| [%] (Janot et al. 2019):
    τ̂ is the drive force that makes the model's momentum equation hold for
    the measured q, q̇, q̈ (the model is affine in the input). The signals
    are those of the record's EMPS part (``meta["emps_part"]``, default the
    estimation run; ``"validation"``: the force-pulse run, the published
    cross-validation, 5.98 % for the symmetric IDIM-LS model).

    With ``sign_limit`` (default) the tanh widths of the friction laws
    (parameters named ``*eps``: fixed shape constants, 2 % of the speed
    scale, that regularise sign(q̇) for the integrators) are taken to their
    limit (1e-9) in the inverse model, whose law is then the published
    protocol's sign(q̇); the fitted parameters are unchanged. Without it the
    smooth law of the fitted model is evaluated (on the estimation run its
    1.8 mm/s width alone costs 0.9 points: the loop's final model reads
    4.18 % smooth, 3.34 % with sign(q̇)).
    """

    def __init__(self, sign_limit: bool = True):
        self.sign_limit = bool(sign_limit)
        self.name = ("EMPS force relative error of the inverse model [%] (Janot et al. 2019 "
                     "protocol" + (", friction laws at their sign limit)" if sign_limit else ")"))
        self._sig = {"estimation": emps_filtered_signals()}

    def signals(self, part: str) -> dict:
        """The filtered signals of EMPS ``part`` (cached)."""
        if part not in self._sig:
            self._sig[part] = emps_filtered_signals(emps(part, download=False))
        return self._sig[part]

    def __call__(self, fit, data) -> float:
        tau, tau_hat = self.forces(fit, data)
        return float(100.0 * np.linalg.norm(tau - tau_hat) / np.linalg.norm(tau))

    def errors(self, fit, data) -> np.ndarray:
        """Per-sample force errors (N, 1), (τ − τ̂) / RMS(τ): the errors whose
        squares the accept rule's error-decrease test compares."""
        tau, tau_hat = self.forces(fit, data)
        return ((tau - tau_hat) / np.sqrt(np.mean(tau**2)))[:, None]

    def forces(self, fit, data) -> tuple[np.ndarray, np.ndarray]:
        """The measured drive force τ (N,) and the inverse model's τ̂ (N,) [N],
        τ̂ computed at the full rate and both decimated in parallel
        (:func:`bondgraph.catalog.benchmarks.emps_decimate`, the protocol's)."""
        m = fit.model
        th = np.array(fit.theta, dtype=float)
        if self.sign_limit:
            for j, n in enumerate(m.params):
                if n.endswith("eps"):
                    th[j] = 1e-9
        M = th[m.param_index("M")]
        gtau = th[m.param_index("gtau")]
        exp = getattr(data, "exp", None)
        s = self.signals(getattr(exp, "meta", {}).get("emps_part", "estimation"))
        x = np.zeros((s["q"].size, m.n_x))
        x[:, m.state_index("p_M")] = M * s["qd"]
        x[:, m.state_index("q")] = s["q"]
        i = m.state_index("p_M")
        f0 = m.f(x, np.zeros((x.shape[0], m.n_u)), th)[:, i]
        f1 = m.f(x, np.ones((x.shape[0], m.n_u)), th)[:, i]
        vir_hat = (M * s["qdd"] - f0) / (f1 - f0)
        return emps_decimate(s["tau"], s["step"]), emps_decimate(gtau * vir_hat, s["step"])


def emps_closed_loop(graph: BondGraph) -> BondGraph:
    """The EMPS drive in its PD position loop (the benchmark's controller):
    vir = sat(kp kv (qg - q) - kv q̇ + pulse), |vir| <= 10 V, with the
    reference qg and the injected pulses as inputs (velocity from the model,
    not from the 2-tap averaged positions)."""
    g = graph.copy(f"{graph.name}_closed_loop")
    qg = g.input("qg", "m", 0.0, "reference position")
    pulse = g.input("pulse", "V", 0.0, "injected force pulses (validation record)")
    kp = g.param("kp", 160.18, "1/s", (100, 200), "position gain")
    kv = g.param("kv", 243.45, "V*s/m", (100, 400), "velocity gain")
    motor = g.element("motor")
    vir = g.inputs.pop("vir")
    q = g.signal_states["q"].state
    v = g.element("v").f
    vmax = g.param("vir_max", 10.0, "V", (5.0, 15.0), "drive command saturation")
    nu = kp * kv * (qg - q) - kv * v + pulse
    # saturation in per-unit of vmax, so that the clip's constants are dimensionless
    motor.value = motor.value.xreplace({vir: vmax * smooth_clip(nu / vmax, -1, 1, 0.001)})
    return g


def emps_validation_error(graph: BondGraph, estimates: dict) -> dict:
    """Closed-loop simulation of ``graph`` (fitted) on the validation record
    (force pulses), position relative error [%] against qm."""
    val = emps("validation", download=False)
    cl = emps_closed_loop(graph)
    for k, v in estimates.items():
        if k in cl.params:
            cl.params[k].default = float(v)
    m = Model.from_graph(cl)
    t = val.t
    # the injected force pulses (0 / 5 V, pulses_N) add to the controller output
    u = {"qg": val["qg"], "pulse": val["pulses_N"]}
    x0 = m.state(q=float(val["qm"][0]))
    sim = simulate(m, t, u, x0=x0, method="BDF", rtol=1e-7, atol=1e-10, max_step=1e-3)
    e = sim.y[:, m.output_index("qm")] - val["qm"]
    return {"position_relerr_percent": float(100 * np.linalg.norm(e) / np.linalg.norm(val["qm"])),
            "published_percent": 0.0080}


def case_emps() -> LoopCase:
    return LoopCase(
        "emps",
        "EMPS ball-screw drive (real data, Janot et al. 2019): starting from mass + viscous "
        "friction, the loop must find Coulomb friction and then the direction-dependent "
        "friction. Published IDIM-LS force error: 4.08 % (symmetric), 3.11 % (asymmetric).",
        declared_builder(emps_declared),
        _emps_record,
        # validation: the benchmark's force-pulse run (its own held-out record)
        LoopSettings(["M", "Fv", "q_F"], metric=EmpsForceError(), fixed={"sigma_q": 1.5e-8},
                     validation=_emps_record(part="validation"),
                     prior=PriorSpec(x0_std={"p_M": 1.0, "q": 1e-5}),
                     ukf=UKFOptions(method="rk4", substeps=2, alpha=1.0),
                     # the metric is the inverse model's force error: the free
                     # runs only check that a fit simulates. Fixed-step RK4 at 4x
                     # the filter's substeps, compiled, as a user's graph gets
                     # (LSODA: the loop 61 s against 52 s, the same figures to the bit)
                     free_run=FreeRunOptions(method="fine"),
                     # the filter takes the substeps its discretisation check asks
                     # for at each accepted fit: the profiled Coulomb width needs 8
                     # (rk4(2) was 0.6-1.2 noise stds per sample off there, and a
                     # fourth step, a force offset, was accepted; 93.6 s -> 163 s)
                     search=SearchOptions(structural=False, auto_substeps=True)),
        ("coulomb", "v"))


# ------------------------------------------------------------- real data: CED
def ced_declared() -> BondGraph:
    """CED linear belt-and-pulley drive (bondgraph.catalog.benchmarks.ced_linear)
    with process noise on the pulley momentum (unmodelled torques)."""
    g = ced_linear()
    q = g.param("q_T", 1e-3, "N*m*s^0.5", (1e-6, 1.0), "process noise on the pulley: unmodelled "
                                                       "torque intensity")
    g.set_process_noise("p_J_p", q)
    return g


def _ced_record(run: str = "prbs_1"):
    exp = ced(run, download=False)
    dm = Model.from_graph(ced_declared())
    return Experiment.from_arrays(exp.t, model=dm, u=exp["u"][:, None], y=exp["z"][:, None],
                                  name=f"ced_{run}",
                                  meta={"description": f"CED run {run} (Wigren & Schoukens "
                                                       f"2017): u [V] and the counter output z"})


def case_ced() -> LoopCase:
    return LoopCase(
        "ced",
        "CED coupled electric drives (real data, Wigren & Schoukens 2017), PRBS run u1: "
        "starting from the linear drive, the loop must find the sign-blind speed sensor. "
        "Published reference (report eq. 9): RMS 2.10 linear -> 0.166 with |.| on u1; on the "
        "held-out run u3 (A = 0.5 V) eq. 9 gives 0.906 -> 0.246.",
        declared_builder(ced_declared),
        _ced_record,
        # the declared linear part is the report's eq. (9) model: evaluated as
        # given (only the noise intensity fitted), as in the published baseline.
        # Validation: the data set's own other PRBS run u3 (held out). The PRBS
        # input is held by the drive between samples: the free run holds it as
        # the filter does. The filter takes the substeps its discretisation
        # check asks for (ROS2 with one step is 6.7 noise stds off per sample
        # at the declared fit, enough to pull the likelihood fit onto the box
        # edges), or RK4 where that meets the check for fewer f evaluations
        # (auto_method: RK4(3) after the low-pass where ROS2 needed 16
        # substeps, 45 -> 35 s, the same effects), and the confirmation goes
        # on in rounds, so that a candidate scoring below others that raise
        # the error is still tried.
        # noise "model": the figures were established with the graph's speed-sensor
        # noise (the record declares none; "auto" would estimate it)
        LoopSettings(["R_a", "b_m", "k_b", "k_y", "q_T"], noise="model", metric="rmse_sim",
                     initial_params=["q_T"], validation=_ced_record("prbs_3"),
                     free_run=FreeRunOptions(hold="filter"),
                     search=SearchOptions(auto_substeps=True, auto_method=True, confirm_rounds=3)),
        ("sensor_rectification", "speed"))



# ------------------------------------------------------- real data: Silverbox
#: training window of the Silverbox case: the first multisine realisation of
#: the official train block (8192 samples, 13.4 s: one period, all ~1340
#: lines), which reaches |y| = 0.2 V, where the cubic stiffness is plain. An
#: output-error fit of the cubic model on 8192 or 16 384 samples gives the
#: same test errors (0.948 mV on the arrow either way), at half the UKF cost.
SILVERBOX_WINDOW = 8192
#: input hold of the Silverbox case (UKF and free runs): V1 is measured after
#: the generator's analogue reconstruction filter, a continuous band-limited
#: voltage (content to 200 Hz at fs = 610 Hz, ωTs ≈ 0.7 at resonance), so the
#: first-order hold is the closest of the holds. Output-error fits of the
#: cubic model on the sampled grid (RK4 x 4, 16 384 samples) give 0.95 mV on
#: the arrow with it, 2.2 mV with the interval mean held, 12.6 mV with a
#: zero-order hold; on the 2x grid of band-limited V1 (SILVERBOX_UPSAMPLE) 0.48 mV.
SILVERBOX_HOLD = "linear"
#: RK4 steps per grid interval: on the 2x grid one step (Ts/2) is enough
#: (output-error fits: 0.478 mV on the arrow at 1 step per Ts/2, 0.479 at 2;
#: on the sampled grid 0.99 / 0.950 / 0.948 mV at 1 / 2 / 4 steps per Ts)
SILVERBOX_SUBSTEPS = 1
#: filter/simulation grid points per sample interval of the Silverbox case:
#: V1 is band-limited, so its values between samples are known from the
#: samples (periodic FFT interpolation of the whole record, Shannon); the
#: grid is refined by this factor, V2 is missing (NaN) between samples and
#: the first-order hold bridges the finer intervals. 1 keeps the sampled grid.
SILVERBOX_UPSAMPLE = 2


@functools.lru_cache(maxsize=4)
def _silverbox_signals(upsample: int) -> tuple[np.ndarray, np.ndarray, float]:
    """(u_fine, y, Ts) of the whole record SNLS80mV, the training block's
    means removed (the upstream README's advice: offsets of a few mV); u on a
    grid ``upsample`` times finer (:func:`scipy.signal.resample`: the
    band-limited, periodic interpolation; 2^17 samples, the record begins and
    ends without excitation)."""
    tr = silverbox("train", download=False)
    full = silverbox("full", download=False)
    u = full["V1"] - float(np.mean(tr["V1"]))
    y = full["V2"] - float(np.mean(tr["V2"]))
    ts = float(full.t[1] - full.t[0])
    from scipy.signal import resample   # deferred: not needed at import

    return (u if upsample == 1 else resample(u, upsample * u.size)), y, ts


def _silverbox_arrays(part: str, upsample: int = SILVERBOX_UPSAMPLE):
    """(t, u, y) of a Silverbox part on the case's grid: ``upsample`` points
    per sample interval (t from the part's first sample), V1 interpolated
    (:func:`_silverbox_signals`), V2 at the samples and NaN between them.
    The case's filter and free runs hold V1 linearly over each grid interval
    (:data:`SILVERBOX_HOLD`)."""
    e = silverbox(part, download=False)
    uf, y, ts = _silverbox_signals(int(upsample))
    k0, n = int(round(e.t[0] / ts)), e.t.size
    idx = upsample * k0 + np.arange(upsample * (n - 1) + 1)
    yy = np.full(idx.size, np.nan)
    yy[::upsample] = y[k0:k0 + n]
    return idx * (ts / upsample), uf[idx], yy


def _silverbox_record(window: int = SILVERBOX_WINDOW, upsample: int = SILVERBOX_UPSAMPLE):
    t, u, y = _silverbox_arrays("train", upsample)
    dm = Model.from_graph(silverbox_linear())
    n = min(upsample * (int(window) - 1) + 1, t.size)
    return Experiment.from_arrays(
        t[:n] - t[0], model=dm, u=u[:n, None], y=y[:n, None], name="silverbox_train",
        meta={"description": f"Silverbox SNLS80mV, first {window} samples of the official train "
                             f"block (Wigren & Schoukens 2013); training means removed; "
                             f"{upsample} grid points per sample (V1 band-limited "
                             f"interpolation, V2 missing between samples)"})


def silverbox_sim_error(model, theta, part: str, substeps: int = SILVERBOX_SUBSTEPS,
                        hold: str = SILVERBOX_HOLD, upsample: int = SILVERBOX_UPSAMPLE,
                        backend: str = "numba") -> float:
    """Simulation RMS error [mV] of a fitted model on a Silverbox test part
    (the published protocol: the first 50 samples may set the initial state,
    the RMS is over the rest).

    Parameters
    ----------
    model : Model
        With an output ``V2`` whose first two states (momentum and
        displacement, or flux and charge) the initial-state fit sets; the
        others start at the model's X0. With a parameter ``m`` (a mass), the
        fit's scales are m·30 and 0.1, else its Jacobian's.
    theta : array (n_theta,)
    part : str
        ``"test_arrow"``, ``"test_multisine"``, ... (:func:`bondgraph.data.datasets.silverbox`).
    substeps : int
        RK4 steps per sample.
    hold : {"zoh", "mean", "linear"}
        Input between grid points (:func:`bondgraph.numerics.integrators.hold_inputs`).
    upsample : int
        Grid points per sample interval (:func:`_silverbox_arrays`).
    backend : {"numba", "numpy"}
        ``"numba"``: the model's compiled RK4 trajectory where its kernels
        load, else the numpy steps (:func:`bondgraph.inference.prior.rk4_outputs`).

    Returns
    -------
    float
        RMS error in mV. The initial state is the least-squares fit of the
        simulated to the measured output over the first 50 samples; the free
        run is fixed-step RK4 (:func:`bondgraph.numerics.integrators.simulate_batch`).
    """
    t, u, y = _silverbox_arrays(part, upsample)
    t = t - t[0]
    iy = model.output_index("V2")
    n0 = 50 * upsample
    th = np.asarray(theta, float)
    seen = np.isfinite(y)

    def run(z, n):
        x0 = np.array(model.x0, float)
        x0[:2] = z * scale
        return rk4_outputs(model, t[:n], u[:n, None], th, x0, substeps, hold, backend)[:, iy]

    if "m" in model.params:
        scale = np.array([th[model.param_index("m")] * 30.0, 0.1])
    else:           # another user's graph (a series RLC): its own scales
        scale = np.ones(2)

    def resid(z):
        return (run(z, n0) - y[:n0])[seen[:n0]]

    z = least_squares(resid, np.zeros(2), x_scale=1.0 if "m" in model.params else "jac").x
    e = (run(z, t.size) - y)[n0:][seen[n0:]]
    return float(1e3 * np.sqrt(np.mean(e**2)))


class SilverboxError:
    """Silverbox simulation RMS error [mV] on a test part (``test_arrow``,
    ``test_multisine``), :func:`silverbox_sim_error`."""

    def __init__(self, part: str = "test_arrow"):
        self.part = part
        self.name = f"Silverbox simulation RMS error on {part} [mV]"

    def __call__(self, fit, data) -> float:
        return silverbox_sim_error(fit.model, fit.theta, self.part)


def case_silverbox() -> LoopCase:
    return LoopCase(
        "silverbox",
        "Silverbox electronic Duffing oscillator (real data, Wigren & Schoukens 2013): declared "
        "as a linear mass-spring-damper driven by the input voltage, the loop must add the "
        "cubic stiffness. Published simulation RMS on the arrow test: best linear 13.7 mV, "
        "physical-parameter model 0.96 mV, best black-box 0.26 mV.",
        declared_builder(silverbox_linear),
        _silverbox_record,
        # the output noise is estimated too: held at its declared 0.1 mV the
        # likelihood explains the cubic model's residual by process noise and
        # the confirmed k3 came out 15 % low (3.30 vs 3.86; arrow 3.1 mV)
        LoopSettings(["m", "d", "k", "q_F", "sigma_y"], metric=SilverboxError("test_arrow"),
                     prior=PriorSpec(x0_std={"p_mass": 1e-4, "q_spring": 0.05}),
                     ukf=UKFOptions(method="rk4", substeps=SILVERBOX_SUBSTEPS,
                                    hold=SILVERBOX_HOLD, alpha=1.0),
                     # the metric simulates the test record itself: the free runs
                     # of the estimation record only check that a fit simulates
                     free_run=FreeRunOptions(method="fine"),
                     search=SearchOptions(structural=False)),
        ("cubic_stiffness", "spring"))


# ------------------------------------------------------- real data: Camry
#: the cold-start bag of test 61811011: the cold UDDS, 0-1366 s (data
#: README). On its first 700 s alone the loop ranks the cold start first too
#: (LR 133.4; error 0.3847 -> 0.3493 cm³/s)
CAMRY_COLD_BAG = 1367
#: the hot-cycle tests the declared parameters are fitted on
#: (:data:`bondgraph.catalog.benchmarks.CAMRY_HOT_FIT`) and the hot UDDS held out
CAMRY_HOT_TESTS = ("61811013", "61811014")
CAMRY_HELD_OUT = "61811012"


def camry_arrays(test, samples: int | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A Camry dyno test as arrays of :func:`~bondgraph.catalog.benchmarks.camry_fuel`.

    Parameters
    ----------
    test : str or int
        ``"61811011"`` .. ``"61811014"`` (or 11 .. 14).
    samples : int, optional
        Keep the first ``samples`` (1 Hz) samples.

    Returns
    -------
    t (N,) [s], u (N, 2) [v in m/s, der(v) in m/s²], y (N,) [cm³/s]
        dv/dt by second-order central differences (:func:`numpy.gradient`).

    Raises
    ------
    DataError
        The data folder lacks the test (no download is attempted).
    """
    d = camry_dyno(test, download=False)
    n = len(d) if samples is None else int(samples)
    t = d["Time[s]"].to_numpy(float)[:n]
    t = t - t[0]
    v = d["v [m/s]"].to_numpy(float)[:n]
    return t, np.column_stack([v, np.gradient(v, t)]), d["Eng_FuelFlow_Direct_DI[ccps]"] \
        .to_numpy(float)[:n]


def camry_record(test="61811011", samples: int | None = CAMRY_COLD_BAG) -> Experiment:
    """A Camry test as a record of :func:`~bondgraph.catalog.benchmarks.camry_fuel`
    (default: the cold-start bag of test 61811011), the measured first fuel
    flow as the initial state of ``Q``."""
    t, u, y = camry_arrays(test, samples)
    dm = Model.from_graph(camry_fuel())
    tid = camry_dyno(test, download=False).attrs["test"]
    return Experiment.from_arrays(
        t, model=dm, u=u, y=y[:, None], name=f"camry_{tid}_{t.size}s",
        meta={"description": f"ANL D3 2018 Camry, test {tid}, first {t.size} s (1 Hz): dyno "
                             f"speed and fuel flow", "x0": {"Q": float(y[0])}})


def camry_free_run(model, theta, test, samples: int | None = None,
                   x0: dict | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Free run of a fitted Camry model on a test (fixed-step RK4, 4 steps per
    second, speed held linearly between samples).

    Parameters
    ----------
    model : Model
        With the inputs ``v``, ``der(v)``, output ``fuel`` and the state ``Q``.
    theta : array (n_theta,)
    test : str or int
    samples : int, optional
        First samples only.
    x0 : dict, optional
        Initial states by name; ``Q`` defaults to the measured first fuel
        flow, every other state to 0 (a cold-start excess is absent on a hot
        start).

    Returns
    -------
    (y (N,), y_sim (N,)) in cm³/s
    """
    t, u, y = camry_arrays(test, samples)
    x = np.zeros(model.n_x)
    for k, val in {"Q": float(y[0]), **(x0 or {})}.items():
        x[model.state_index(k)] = val
    Y = rk4_outputs(model, t, u, theta, x, 4, "linear")
    return y, Y[:, model.output_index("fuel")]


def camry_fuel_error(model, theta, test=CAMRY_HELD_OUT, samples: int | None = None,
                     x0: dict | None = None) -> float:
    """Free-run fuel RMS error [cm³/s] of a fitted Camry model on a test
    (:func:`camry_free_run`; default the held-out hot UDDS 61811012)."""
    y, ys = camry_free_run(model, theta, test, samples, x0)
    return float(np.sqrt(np.mean((ys - y) ** 2)))


def camry_hot_fit(tests=CAMRY_HOT_TESTS, params=("eta", "Q_idle")) -> dict[str, float]:
    """Output-error fit of the warm graph's powertrain parameters on hot
    cycles (the values of :data:`~bondgraph.catalog.benchmarks.CAMRY_HOT_FIT`).

    Least squares (:func:`scipy.optimize.least_squares`, inside the
    parameters' boxes) of the free-run fuel errors of every test together
    (:func:`camry_free_run`, from the measured first fuel flow); the other
    parameters at the graph's defaults (EPA road load, τ_f 0.5 s).

    Returns
    -------
    dict
        The estimates by name and ``rms`` [cm³/s], the RMS error over all
        samples of the tests.
    """
    m = Model.from_graph(camry_fuel())
    lo, hi = m.bounds(list(params))
    base = m.theta({"tau_f": CAMRY_HOT_FIT["tau_f"]})

    def resid(z):
        th = m.expand_theta(list(params), z, base)
        return np.concatenate([np.subtract(*camry_free_run(m, th, k)[::-1]) for k in tests])

    z0 = np.array([CAMRY_HOT_FIT[p] for p in params])
    r = least_squares(resid, np.clip(z0, lo, hi), bounds=(lo, hi), x_scale=0.1)
    return {**{p: float(v) for p, v in zip(params, r.x)},
            "rms": float(np.sqrt(np.mean(r.fun ** 2)))}


def camry_held_out_line(result) -> str:
    """The camry_cold case's held-out line (:attr:`LoopCase.held_out`): the
    free-run fuel RMS error on the hot UDDS 61811012 (:func:`camry_fuel_error`,
    a hot start: an effect's own states at 0, no cold-start excess) of the
    declared graph at the initial fit and of the final graph at the final
    fit. The cold start changes nothing on a hot start, so the two should
    read the same: a model that compensated the warm-up with its declared
    parameters reads worse there."""
    m0 = Model.from_graph(camry_warm())
    before = camry_fuel_error(m0, m0.theta({k: v for k, v in result.initial.estimates.items()
                                            if k in m0.params}))
    m1 = Model.from_graph(result.final_graph) if result.final_graph is not None else m0
    after = camry_fuel_error(m1, m1.theta({k: v for k, v in result.final.estimates.items()
                                           if k in m1.params}))
    return (f"  held out, the hot UDDS {CAMRY_HELD_OUT} (hot start, where a cold start adds "
            f"nothing): fuel RMS error before {before:.4g}   after {after:.4g} cm^3/s")


def case_camry_cold() -> LoopCase:
    return LoopCase(
        "camry_cold",
        "2018 Camry on a chassis dyno (real data, ANL D3, 1 Hz): the warm powertrain fuel-flow "
        "model, started from its fit on the hot cycles 61811013-14, on the cold-start UDDS bag "
        "of 61811011 (0-1366 s; the data README: +16.8 % fuel in the first 505 s against the hot "
        "test 61811012); the loop must find the engine's warm-up. Held out: the hot UDDS "
        "61811012 (catalog.cases.camry_fuel_error).",
        declared_builder(camry_warm),
        camry_record,
        # powertrain efficiency and idle fuel re-estimated on the cold bag
        # (the hot-cycle fit starts them) and the fuel sensor's noise std
        # (noise "auto": the record declares none). The road load and test
        # weight are the EPA proxies, fixed; τ_f stays at the lower end of its
        # box, where the hot fit put it. The fuel state's process noise is
        # held small (0.02 cm³/s^1.5), so that the likelihood judges the
        # model's own fuel prediction: estimated, q_Q runs to 0.30, a random
        # walk that follows the measurement (the Willans line's own errors:
        # fuel cut-off on braking, efficiency varying with load), and then
        # absorbs any slow effect (the cold start scored LR 0).
        # Tried and left: (1) η and Q_idle held at a hot fit on 61811012 and
        # 61811014 (61811013 held out): the cold start ranks first (LR 239.5,
        # error 0.3213 -> 0.312, z 0.36: rejected) and a sensor offset of
        # +0.062 cm³/s is accepted, the slow part of the warm-up read as a
        # constant; (2) CED's pattern, only the noise in the initial fit and
        # η, Q_idle refitted with every candidate: an actuator saturation of
        # the speed at 54 m/s (never reached on the UDDS) is accepted, its
        # error decrease (0.3213 -> 0.3136) being the declared refit's.
        LoopSettings(["eta", "Q_idle"], metric="rmse_sim",
                     effects=DEFAULT_EFFECTS + OPTIONAL_EFFECTS, fixed={"q_Q": 0.02},
                     ukf=UKFOptions(method="rk4", substeps=4, hold="linear"),
                     free_run=FreeRunOptions(hold="filter"),
                     search=SearchOptions(auto_substeps=True)),
        ("cold_start", "injector"), held_out=camry_held_out_line)

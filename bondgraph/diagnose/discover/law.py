"""Discovery of the law of a reconstructed effort or flow: a sparse
regression of d̂(t) on a dictionary of candidate terms in the port's own
variables.

Dictionary (:func:`dictionary`), for each primary variable z of the port
(:attr:`~bondgraph.diagnose.discover.reconstruct.Reconstruction.primary`)
with its RMS s along the record:

* powers z, z², z³, z⁵ and the signed square |z|·z;
* a smooth sign tanh(z/ε) at ε = 0.02 s and ε = 0.1 s (Coulomb-like laws);
* a saturation z/(1 + |z/s|);
* at a sensor's output only, a smooth saturation tanh(z/s) (a sensor's
  curve: on the tanh sensor of ``bench/discovery.py``, d̂ = 5·tanh(y/5) −
  y, the two terms z and tanh(z/s) leave 0.066 V RMS, the reconstruction's
  own error against the truth, where the dictionary without it left
  0.127 V). Not at junctions: there it displaced the saturation in the
  Bouc-Wen case's law (gap closed 0.753 -> 0.415) and changed the cubic
  spring's law of ``tests/test_discover_report.py``;
* the products z_i·z_j of two primary variables;
* each input, linearly, and a constant;
* memory terms (:func:`memory_candidates`): first-order low-passes
  lp(z, τ) = z/(τ·s + 1) of each primary variable, τ at
  :data:`MEMORY_TAUS` times the variable's own time scale
  (:func:`time_scale`), computed on the record by the exact discretisation
  of dw/dt = (z − w)/τ with z linear between samples (:func:`lowpass`). A
  law holds at most one of them (issue 29: "one filtered (memory) term");
  it becomes a signal state of the model
  (:class:`~bondgraph.diagnose.discover.effect.DiscoveredEffect`).

Regression (:func:`discover_law`): the rows are weighted by 1/std² of the
smoother (weighted least squares as ordinary least squares on rows scaled by
1/std), the columns scaled to unit norm. Candidate sets of terms come
from orthogonal matching pursuit (scikit-learn's ``orthogonal_mp``; Pati,
Rezaiifar & Krishnaprasad 1993) and from sequentially thresholded least
squares (PySINDy's ``STLSQ``; Brunton et al. 2016); the set is chosen by
cross-validation on contiguous time blocks (scikit-learn's ``GroupKFold``,
so that a held-out block is not predicted from its autocorrelated
neighbours) with the one-standard-error rule (the fewest terms whose
held-out error is within one standard error of the best; Hastie,
Tibshirani & Friedman 2009, §7.10). The chosen terms are refitted by least
squares, so the coefficients are not shrunk. Every candidate set holds at
most one memory term (:func:`candidate_supports`); the memoryless sets are
chosen among themselves as above, and a memory set replaces their choice
only when it is better by more than its own standard error (:func:`_choose`).

References
----------
Pati, Y. C., Rezaiifar, R., Krishnaprasad, P. S. (1993). Orthogonal
matching pursuit. Proc. 27th Asilomar Conf. Signals, Systems and Computers.
Brunton, S. L., Proctor, J. L., Kutz, J. N. (2016). Discovering governing
equations from data by sparse identification of nonlinear dynamical
systems. PNAS 113(15), 3932-3937 (the dictionary idea).
Hastie, T., Tibshirani, R., Friedman, J. (2009). The Elements of
Statistical Learning, 2nd ed., Springer.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from itertools import combinations

import warnings

import numpy as np
import sympy as sp
from sklearn.linear_model import orthogonal_mp
from pysindy.optimizers import STLSQ
from sklearn.model_selection import GroupKFold

from bondgraph.core import units as units_
from bondgraph.errors import NumericalError, OptionError

#: thresholds of STLSQ as fractions of the target's norm (:func:`candidate_supports`)
STLSQ_THRESHOLDS = (0.3, 0.1, 0.03, 0.01, 0.003)
#: smooth-sign widths as fractions of the variable's RMS
SIGN_WIDTHS = (0.02, 0.1)
#: smooth-saturation widths tanh(z/w) of an output law, fractions of the
#: variable's RMS
SATURATION_WIDTHS = (1.0,)
#: time constants of the memory terms lp(z, τ), multiples of the variable's
#: own time scale (:func:`time_scale`)
MEMORY_TAUS = (0.3, 1.0, 3.0)


@dataclass(frozen=True)
class DiscoverOptions:
    """How the law is discovered.

    Parameters
    ----------
    max_terms : int
        Most terms of the law (default 6).
    folds : int
        Contiguous time blocks of the cross-validation (default 10).
    trim : float
        Fraction of the record left out at each end, where the smoother
        sees one side only (default 0.02).
    products : bool
        Products of two primary variables in the dictionary (default True).
    inputs : bool
        The inputs, linearly, in the dictionary (default True).
    memory : bool
        First-order low-passes of the primary variables in the dictionary,
        at most one per law (default True; :func:`memory_candidates`).

    Raises
    ------
    OptionError
        ``max_terms < 1``, ``folds < 2``, ``trim`` outside [0, 0.4).
    """

    max_terms: int = 6
    folds: int = 10
    trim: float = 0.02
    products: bool = True
    inputs: bool = True
    memory: bool = True

    def __post_init__(self):
        if int(self.max_terms) != self.max_terms or self.max_terms < 1:
            raise OptionError(f"DiscoverOptions.max_terms must be an integer >= 1, "
                              f"got {self.max_terms}")
        if int(self.folds) != self.folds or self.folds < 2:
            raise OptionError(f"DiscoverOptions.folds must be an integer >= 2, got {self.folds}")
        if not 0 <= self.trim < 0.4:
            raise OptionError(f"DiscoverOptions.trim must be in [0, 0.4), got {self.trim}")


@dataclass(frozen=True)
class Memory:
    """What a memory term filters: w = lp(variable, τ), dw/dt = (x − w)/τ.

    Attributes
    ----------
    variable : str
        The filtered variable (a primary variable of the port).
    tau : float
        The time constant τ (s, > 0).
    initial : float
        w at the record's first sample (the variable's value there: the
        filter starts at rest; the variable's unit).
    """

    variable: str
    tau: float
    initial: float = 0.0


def memory_name(variable: str, tau: float) -> str:
    """The readable name of a memory term, ``"lp(v.f, τ=0.35 s)"``."""
    return f"lp({variable}, τ={tau:.3g} s)"


@dataclass
class Term:
    """One term of a discovered law: ``coef · basis``.

    Attributes
    ----------
    name : str
        Readable name of the basis (e.g. ``"tanh(v.f/0.0212)"``).
    basis : sympy.Expr
        The basis function of the port's variables (symbols named as them).
    coef : float
        Its coefficient (the port's unit over the basis' unit).
    rms : float
        RMS of ``coef · basis`` along the record (the port's unit).
    unit : str
        The basis' unit (the coefficient's is the port's unit over it).
    memory : Memory or None
        For a memory term, what it filters (its basis is then a symbol
        named as the term, standing for the filter's state w).
    """

    name: str
    basis: sp.Expr
    coef: float
    rms: float
    unit: str = "1"
    memory: Memory | None = None


@dataclass
class DiscoveredLaw:
    """A law ``d = Σ coef_k · basis_k`` of the port's variables.

    Attributes
    ----------
    port, kind, unit : str
        The junction, ``"effort"`` or ``"flow"``, the law's unit.
    symbols : dict str -> sympy.Symbol
        The variables the law reads, by name.
    terms : list of Term
        The chosen terms, largest contribution first.
    dictionary : list of str
        Every candidate's name.
    candidates : list of tuple of str
        The candidate sets of terms the cross-validation compared.
    cv_error : ndarray (n_candidates,)
        Their held-out weighted mean squared errors.
    cv_se : ndarray (n_candidates,)
        Its standard error over the folds.
    rms_d, rms_residual : float
        RMS of d̂ and of d̂ minus the law over the fitted samples.
    ranges : dict str -> (float, float)
        The range of each variable the record visits.
    dropped : list of str
        Terms removed since (:func:`bondgraph.diagnose.discover.passivity.make_passive`).
    inputs : list of str
        The inputs among :attr:`symbols` (their terms are source-like).
    """

    port: str
    kind: str
    unit: str
    symbols: dict
    terms: list
    dictionary: list
    candidates: list
    cv_error: np.ndarray
    cv_se: np.ndarray
    rms_d: float
    rms_residual: float
    ranges: dict
    dropped: list = field(default_factory=list)
    inputs: list = field(default_factory=list)

    @property
    def expr(self) -> sp.Expr:
        """The law as one sympy expression of :attr:`symbols`."""
        return sp.Add(*(sp.Float(tm.coef) * tm.basis for tm in self.terms))

    @property
    def memory_term(self) -> Term | None:
        """The law's memory term (None when it has none)."""
        return next((tm for tm in self.terms if tm.memory is not None), None)

    def evaluate(self, values: dict, t=None) -> np.ndarray:
        """The law (N,) at the variables' values (dict name -> (N,)); a
        memory term filtered along ``t`` (N,) (s) from rest at the first
        sample (:func:`lowpass`).

        Raises
        ------
        OptionError
            A memory term and no ``t``.
        """
        plain = [tm for tm in self.terms if tm.memory is None]
        out = 0.0 * _first(values)
        if plain:
            cols = _columns([tm.basis for tm in plain], self.symbols, values, _length(values))
            out = out + cols @ np.array([tm.coef for tm in plain])
        for tm in self.terms:
            if tm.memory is not None:
                if t is None:
                    raise OptionError(f"DiscoveredLaw.evaluate at '{self.port}': the term "
                                      f"{tm.name} has memory; give the sample times t")
                out = out + tm.coef * lowpass(values[tm.memory.variable], t, tm.memory.tau)
        return out

    def readable(self, digits: int = 4) -> str:
        """``"<port> <effort|flow> = c1·b1 + c2·b2 ..."`` with ``digits``
        significant digits."""
        if not self.terms:
            return f"{self.port} {self.kind} = 0"
        parts = []
        for tm in self.terms:
            c = f"{abs(tm.coef):.{digits}g}"
            parts.append(("- " if tm.coef < 0 else "+ ") + f"{c}·{tm.name}")
        text = " ".join(parts)
        text = text[2:] if text.startswith("+ ") else "-" + text[2:]
        return f"{self.port} {self.kind} [{self.unit}] = {text}"

    def __str__(self) -> str:
        return self.readable()


def _length(values: dict) -> int:
    return int(np.asarray(next(iter(values.values()))).size)


def _first(values: dict) -> np.ndarray:
    return np.asarray(next(iter(values.values())), float)


def _columns(bases, symbols: dict, values: dict, n: int) -> np.ndarray:
    names = list(symbols)
    fn = sp.lambdify([symbols[k] for k in names], bases, "numpy")
    cols = fn(*[np.asarray(values[k], float) for k in names])
    return np.column_stack([np.broadcast_to(np.asarray(c, float), (n,)) for c in cols])


def _fmt(x: float) -> str:
    return f"{x:.3g}"


def dictionary(primary, inputs, scales: dict, *, products: bool = True,
               units: dict | None = None, smooth_saturation: bool = False) -> list:
    """The candidate terms (module docstring).

    Parameters
    ----------
    primary : sequence of str
        The port's primary variables.
    inputs : sequence of str
        The inputs (linear terms).
    scales : dict str -> float
        RMS of each primary variable (> 0; the widths of the sign and
        saturation terms).
    products : bool
    units : dict str -> str, optional
        Each variable's unit (default dimensionless).
    smooth_saturation : bool
        Add tanh(z/(w·s)) for w in :data:`SATURATION_WIDTHS` (a law at a
        sensor's output; default False).

    Returns
    -------
    list of (str, sympy.Expr, str)
        Name, basis (symbols named as the variables) and the basis' unit of
        each candidate.
    """
    un = {k: (units or {}).get(k, "") or "1" for k in list(primary) + list(inputs)}

    def pw(u, n):
        return "1" if u == "1" else f"({u})^{n}"

    out = [("1", sp.Integer(1), "1")]
    for name in primary:
        z, s, u = sp.Symbol(name), float(scales[name]), un[name]
        out += [(name, z, u), (f"{name}^2", z ** 2, pw(u, 2)), (f"{name}^3", z ** 3, pw(u, 3)),
                (f"{name}^5", z ** 5, pw(u, 5)), (f"|{name}|·{name}", sp.Abs(z) * z, pw(u, 2))]
        for w in SIGN_WIDTHS:
            out.append((f"tanh({name}/{_fmt(w * s)})", sp.tanh(z / sp.Float(w * s)), "1"))
        out.append((f"{name}/(1+|{name}/{_fmt(s)}|)", z / (1 + sp.Abs(z / sp.Float(s))), u))
        for w in SATURATION_WIDTHS if smooth_saturation else ():
            out.append((f"tanh({name}/{_fmt(w * s)})", sp.tanh(z / sp.Float(w * s)), "1"))
    if products:
        for a, b in combinations(primary, 2):
            out.append((f"{a}·{b}", sp.Symbol(a) * sp.Symbol(b), units_.product(un[a], un[b])))
    out += [(name, sp.Symbol(name), un[name]) for name in inputs]
    return out


def lowpass(x, t, tau: float, initial: float | None = None) -> np.ndarray:
    """w = lp(x, τ): the first-order low-pass dw/dt = (x − w)/τ, i.e.
    H(s) = 1/(τ·s + 1), along the samples ``x`` at times ``t``.

    Exact for x linear between samples (first-order hold, the input
    interpolation of scipy's ``lsim``): over a step h, with a = e^(−h/τ)
    and c = τ·(1 − a)/h, w⁺ = a·w + (1 − c)·x⁺ + (c − a)·x. On a uniform
    grid one ``scipy.signal.lfilter`` pass; otherwise step by step.

    Parameters
    ----------
    x, t : array_like (N,)
        The variable (any unit) and strictly increasing times (s).
    tau : float
        Time constant (s, > 0).
    initial : float, optional
        w at ``t[0]`` (default ``x[0]``: the filter at rest).

    Returns
    -------
    ndarray (N,)
        w at ``t``, in x's unit.

    Raises
    ------
    OptionError
        ``tau`` not positive and finite, ``x`` and ``t`` not of one shape
        (N,) with N >= 1, ``t`` not strictly increasing.
    NumericalError
        ``x`` or ``t`` not finite.
    """
    x, t = np.asarray(x, float), np.asarray(t, float)
    if not (np.isfinite(tau) and tau > 0):
        raise OptionError(f"lowpass: the time constant tau must be positive, got {tau}")
    if x.ndim != 1 or x.shape != t.shape or x.size == 0:
        raise OptionError(f"lowpass: x {x.shape} and t {t.shape} must be one shape (N,), N >= 1")
    if not (np.all(np.isfinite(x)) and np.all(np.isfinite(t))):
        raise NumericalError(f"lowpass: x or t is not finite at "
                             f"{int(np.sum(~(np.isfinite(x) & np.isfinite(t))))} samples")
    h = np.diff(t)
    if np.any(h <= 0):
        raise OptionError("lowpass: the times t must be strictly increasing")
    w0 = float(x[0] if initial is None else initial)
    if x.size == 1:
        return np.array([w0])
    a = np.exp(-h / tau)
    c = tau * -np.expm1(-h / tau) / h
    if np.allclose(h, h[0], rtol=1e-9, atol=0.0):
        from scipy.signal import lfilter

        b = [1.0 - c[0], c[0] - a[0]]
        w, _ = lfilter(b, [1.0, -a[0]], x, zi=[w0 - b[0] * x[0]])
        return w
    w = np.empty_like(x)
    w[0] = w0
    for k in range(x.size - 1):
        w[k + 1] = a[k] * w[k] + (1.0 - c[k]) * x[k + 1] + (c[k] - a[k]) * x[k]
    return w


def time_scale(x, t) -> float | None:
    """The variable's own time scale std(x)/RMS(dx/dt) (s; 1/ω for a sine
    of angular frequency ω), dx/dt by ``numpy.gradient``; None when x is
    constant."""
    x, t = np.asarray(x, float), np.asarray(t, float)
    if x.size < 3:
        return None
    sd, rate = float(np.std(x)), float(np.sqrt(np.mean(np.gradient(x, t) ** 2)))
    return sd / rate if sd > 0 and rate > 0 and np.isfinite(sd / rate) else None


def memory_candidates(primary, values: dict, t, units: dict | None = None) -> list:
    """The memory terms of the dictionary: lp(z, τ) (:func:`lowpass`, from
    rest at the first sample) of each primary variable z, τ at
    :data:`MEMORY_TAUS` times z's time scale (:func:`time_scale`), kept
    within [2 sample intervals, half the record]; none for a constant z.

    Parameters
    ----------
    primary : sequence of str
    values : dict str -> array (N,)
        The variables along the whole record.
    t : array (N,)
        Sample times (s).
    units : dict str -> str, optional

    Returns
    -------
    list of (str, sympy.Symbol, str, Memory, ndarray (N,))
        Name, basis symbol, unit (the variable's), what it filters, and its
        column along the record.
    """
    t = np.asarray(t, float)
    span, dt = float(t[-1] - t[0]), float(np.median(np.diff(t)))
    out = []
    for name in primary:
        x = np.asarray(values[name], float)
        base = time_scale(x, t)
        if base is None:
            continue
        taus = sorted({float(f"{min(max(f * base, 2 * dt), 0.5 * span):.3g}")
                       for f in MEMORY_TAUS})
        for tau in taus:
            label = memory_name(name, tau)
            out.append((label, sp.Symbol(label), (units or {}).get(name, "") or "1",
                        Memory(name, tau, float(x[0])), lowpass(x, t, tau)))
    return out


def discover_law(rec, *, options: DiscoverOptions | None = None) -> DiscoveredLaw:
    """Discover the law of a reconstructed effort or flow.

    Parameters
    ----------
    rec : Reconstruction
        From :func:`~bondgraph.diagnose.discover.reconstruct.reconstruct`
        (or ``reconstruct_sensor``): d̂ (N,), its std (N,), the variables,
        the sample times (N,).
    options : DiscoverOptions, optional

    Returns
    -------
    DiscoveredLaw
        The chosen terms with their coefficients (port unit over the basis
        unit), at most one of them a memory term, the cross-validation path.

    Raises
    ------
    OptionError
        Fewer samples than ``folds × (max_terms + 1)`` after trimming.
    NumericalError
        d̂ or its std is not finite on the fitted samples (a port whose
        missing effort or flow the record does not observe: the flow
        entering a 0-junction whose effort a source imposes), or no
        candidate term is finite and non-zero there: no law to regress.

    Notes
    -----
    Method: weighted OMP and STLSQ, the terms by block cross-validation
    with the one-standard-error rule (module docstring).
    """
    opts = options or DiscoverOptions()
    n = rec.t.size
    cut = int(round(opts.trim * n))
    keep = slice(cut, n - cut)
    if (n - 2 * cut) < opts.folds * (opts.max_terms + 1):
        raise OptionError(f"discover_law: {n - 2 * cut} samples are too few for "
                          f"{opts.folds} folds of {opts.max_terms} terms")
    values = {k: np.asarray(v, float)[keep] for k, v in rec.variables.items()}
    inputs = [k for k in rec.variables if k in rec.model.inputs] if opts.inputs else []
    symbols = {k: sp.Symbol(k) for k in list(rec.primary) + inputs}
    cands, Phi = _design(rec, opts, values, inputs, symbols, keep)
    d = np.asarray(rec.d, float)[keep]
    d_std = np.asarray(rec.d_std, float)[keep]
    bad = int(np.sum(~(np.isfinite(d) & np.isfinite(d_std))))
    if bad:
        raise NumericalError(f"discover_law at '{rec.port.port}': the reconstructed "
                             f"{rec.port.kind} or its std is not finite at {bad} of {d.size} "
                             f"samples (the record does not observe it there)")
    w = 1.0 / np.maximum(d_std, 1e-12 * (np.abs(d).max() or 1.0))
    A, b = Phi * w[:, None], d * w
    norms = np.linalg.norm(A, axis=0)
    ok = np.isfinite(norms) & (norms > 0)
    if not ok.any():
        raise NumericalError(f"discover_law at '{rec.port.port}': no candidate term is finite "
                             f"and non-zero along the record")
    A = A[:, ok] / norms[ok]
    mem = np.array([c[3] is not None for c in cands])[ok]
    inp = np.array([c[0] in inputs and c[3] is None for c in cands])[ok]
    supports = candidate_supports(A, b, int(min(opts.max_terms, A.shape[1])), memory=mem,
                                  inputs=inp)
    err, se = _cv_errors(A, b, supports, opts.folds)
    best = _choose(err, se, supports, mem)
    coef = np.zeros(Phi.shape[1])
    sup = list(supports[best])
    if sup:
        c = np.linalg.lstsq(A[:, sup], b, rcond=None)[0]
        coef[np.flatnonzero(ok)[sup]] = c / norms[ok][sup]
    fit = Phi @ coef
    terms = [Term(cands[i][0], cands[i][1], float(coef[i]),
                  float(np.sqrt(np.mean((coef[i] * Phi[:, i]) ** 2))), cands[i][2], cands[i][3])
             for i in np.flatnonzero(coef)]
    terms.sort(key=lambda tm: -tm.rms)
    ranges = {k: (float(values[k].min()), float(values[k].max())) for k in symbols}
    return DiscoveredLaw(rec.port.port, rec.port.kind, rec.port.unit, symbols, terms,
                         [c[0] for c in cands],
                         [tuple(cands[i][0] for i in np.flatnonzero(ok)[list(sp_)]) for sp_ in supports],
                         err, se, float(np.sqrt(np.mean(d ** 2))),
                         float(np.sqrt(np.mean((d - fit) ** 2))), ranges, [], list(inputs))


def _design(rec, opts: DiscoverOptions, values: dict, inputs: list, symbols: dict, keep):
    """The candidates (name, basis, unit, Memory or None) and their columns
    on the fitted samples ``keep`` (n, m): the dictionary (:func:`dictionary`),
    then the memory terms (:func:`memory_candidates`, filtered along the
    whole record, then trimmed)."""
    scales = {k: float(np.sqrt(np.mean(values[k] ** 2))) or 1.0 for k in rec.primary}
    cands = [c + (None,) for c in dictionary(rec.primary, inputs, scales,
                                              products=opts.products, units=rec.units,
                                              smooth_saturation=rec.port.kind == "output")]
    n = _length(values)
    Phi = _columns([c[1] for c in cands], symbols, values, n)
    if opts.memory:
        mem = memory_candidates(rec.primary, rec.variables, rec.t, rec.units)
        cands += [m[:4] for m in mem]
        Phi = np.column_stack([Phi] + [m[4][keep] for m in mem])
    return cands, Phi


def candidate_supports(A: np.ndarray, b: np.ndarray, kmax: int, memory=None,
                       inputs=None) -> list:
    """Candidate sets of terms (column indices of ``A``, its columns of unit
    norm): the empty set, every set of one or two terms, the
    orthogonal-matching-pursuit path (1..kmax
    terms; scikit-learn's ``orthogonal_mp``) and the sets of the sequentially
    thresholded least squares (PySINDy's ``STLSQ``; Brunton et al. 2016) at
    thresholds of 30 % down to 0.3 % of the target's norm, those of at most
    ``kmax`` terms. With ``memory`` (bool (m,), the memory columns) no set
    holds two memory columns, and with ``inputs`` (bool (m,), the input
    columns) no set holds a memory column and an input column: OMP and STLSQ
    run on the memoryless columns, then on the memoryless non-input columns
    with each memory column in turn.

    Why no input beside a memory term: the memory term of a variable and an
    input rebuild the port's own balance from the reconstruction (a
    filtered state is a state minus τ times its rate: with the input, the
    inertia's equation m·v̇ = F − ...), a tautology that fits d̂ better than
    the missing law (on the Coulomb friction of ``tests/test_discover.py``
    the law became −0.65·F + 32.9·lp(q, 0.23 s) + ..., held-out error 19.2
    against 62.6 for the tanh law).

    OMP is greedy and can start from a look-alike of a sum of two terms;
    STLSQ starts from the full least squares and can keep cancelling
    look-alikes; the sets of one or two terms (all of them: a few hundred
    least-squares fits of two columns) hold the simple laws neither may
    reach: the cross-validation chooses among all.
    """
    m = A.shape[1]
    mem = np.zeros(m, bool) if memory is None else np.asarray(memory, bool)
    inp = np.zeros(m, bool) if inputs is None else np.asarray(inputs, bool)
    out = [()] + [(i,) for i in range(m)]
    if kmax >= 2:
        out += [p for p in combinations(range(m), 2)
                if not (mem[list(p)].any() and (mem[list(p)].all() or inp[list(p)].any()))]
    plain, other = np.flatnonzero(~mem), np.flatnonzero(~mem & ~inp)
    out += [tuple(int(plain[i]) for i in sup) for sup in _greedy_supports(A[:, plain], b, kmax)]
    for k in np.flatnonzero(mem):
        # only the sets that hold k: the memoryless sets stay those of the
        # memoryless columns alone (their choice is unchanged, _choose)
        cols = np.append(other, k)
        out += [tuple(sorted(int(cols[i]) for i in sup))
                for sup in _greedy_supports(A[:, cols], b, kmax) if len(cols) - 1 in sup]
    return list(dict.fromkeys(out))


def _greedy_supports(A: np.ndarray, b: np.ndarray, kmax: int) -> list:
    """The OMP path and the STLSQ sets of :func:`candidate_supports` on the
    columns of ``A``."""
    out = []
    if A.shape[1] == 0:
        return out
    kmax = min(kmax, A.shape[1])
    path = np.asarray(orthogonal_mp(A, b, n_nonzero_coefs=kmax, return_path=True))
    path = path.reshape(A.shape[1], -1)
    for j in range(path.shape[1]):
        out.append(tuple(np.flatnonzero(path[:, j])))
    bn = float(np.linalg.norm(b)) or 1.0
    for tau in STLSQ_THRESHOLDS:
        opt = STLSQ(threshold=tau * bn, alpha=0.0, max_iter=50)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            opt.fit(A, b)
        sup = tuple(np.flatnonzero(np.asarray(opt.coef_).ravel()))
        if 0 < len(sup) <= kmax:
            out.append(sup)
    return out


#: a held-out mean squared error below this fraction of the target's mean
#: square (a relative RMS error of 1e-10) is round-off (:func:`discover_law`)
ROUNDOFF = 1e-20


def _cv_errors(A: np.ndarray, b: np.ndarray, supports: list, folds: int):
    """Held-out mean squared error of each support's least-squares fit and
    its standard error over contiguous time blocks (``GroupKFold``); an
    error below :data:`ROUNDOFF` times the target's mean square is raised to
    it. Errors at round-off are ties: on a noise-free target every superset
    of the exact support fits to the last bits too, and which of them the
    arithmetic ranks first differs between machines (an AMD EPYC chose six
    terms for three); tied, :func:`_choose` keeps the fewest terms."""
    n = b.size
    groups = np.minimum((np.arange(n) * folds) // n, folds - 1)
    errs = np.zeros((folds, len(supports)))
    for f, (tr, te) in enumerate(GroupKFold(n_splits=folds).split(A, b, groups)):
        for j, sup in enumerate(supports):
            pred = 0.0
            if sup:
                cols = list(sup)
                c = np.linalg.lstsq(A[np.ix_(tr, cols)], b[tr], rcond=None)[0]
                pred = A[np.ix_(te, cols)] @ c
            errs[f, j] = np.mean((b[te] - pred) ** 2)
    err = np.maximum(errs.mean(axis=0), ROUNDOFF * float(np.mean(b ** 2)))
    return err, errs.std(axis=0, ddof=1) / np.sqrt(folds)


def _choose(err: np.ndarray, se: np.ndarray, supports: list, memory: np.ndarray) -> int:
    """The chosen candidate set: the memoryless sets' by the
    one-standard-error rule (:func:`_one_se`), unless the memory sets' own
    choice is better by more than its standard error (its error plus its
    standard error below the memoryless one's error): a state of its own
    counts as more complex than any number of memoryless terms. Chosen
    together, a memory set's low error narrows the one-standard-error band
    and the rule then keeps more memoryless look-alikes (the diode-like
    resistor of ``bench/discovery.py``: six terms for two)."""
    has = np.array([bool(memory[list(s)].any()) for s in supports])
    sizes = np.array([len(s) for s in supports])
    plain, mem = np.flatnonzero(~has), np.flatnonzero(has)
    best = int(plain[_one_se(err[plain], se[plain], sizes[plain])])
    if mem.size:
        other = int(mem[_one_se(err[mem], se[mem], sizes[mem])])
        if err[other] + se[other] < err[best]:
            return other
    return best


def _one_se(err: np.ndarray, se: np.ndarray, sizes) -> int:
    """The candidate with the fewest terms whose held-out error is within one
    standard error of the smallest (Hastie et al. 2009, §7.10); among equal
    sizes the smaller error."""
    best = int(np.argmin(err))
    ok = np.flatnonzero(err <= err[best] + se[best])
    return int(min(ok, key=lambda j: (sizes[j], err[j])))


# ------------------------------------------------------------ a threshold law
#: thresholds of a dead-zone term, as quantiles of the variable's visited values
#: (upper quantiles for a term above the threshold, lower for one below)
THRESHOLD_QUANTILES = (0.5, 0.7, 0.85)
#: exponents p of a dead-zone term max(±(z − a), 0)^p
THRESHOLD_POWERS = (1.0, 1.5, 2.0)


def dead_zone(z: sp.Symbol, a: float, side: int, p: float) -> sp.Expr:
    """max(side·(z − a), 0)^p written with |·| (the generated code's
    functions): (w + |w|)/2 · |w|^(p − 1), w = side·(z − a). Not
    ((w + |w|)/2)^p: sympy rewrites w + |w| and its rounding leaves
    −1e-17 below the threshold, whose power 1.5 is NaN.

    Parameters
    ----------
    z : sympy.Symbol
    a : float
        The threshold (z's unit).
    side : {1, -1}
        Above (1) or below (−1) the threshold.
    p : float
        Exponent (>= 1).
    """
    w = side * (z - sp.Float(a))
    base = (w + sp.Abs(w)) / 2
    return base if p == 1 else base * sp.Abs(w) ** (sp.Integer(1) if p == 2 else sp.Float(p - 1))


def threshold_law(rec, *, options: DiscoverOptions | None = None) -> DiscoveredLaw | None:
    """The law of one dead-zone term of the port's own variable z (its first
    primary variable): d = c·max(±(z − a), 0)^p, the threshold a at a
    quantile of the visited z (:data:`THRESHOLD_QUANTILES`), p in
    :data:`THRESHOLD_POWERS`, the one of least weighted squared residual
    (each a one-coefficient weighted least squares, rows weighted by the
    smoother's 1/std as in :func:`discover_law`).

    A weir or an overflow that starts above a level, a contact or a stop:
    a shape the smooth dictionary of :func:`discover_law` does not hold
    (a tank's overflow c·max(p − 220 Pa, 0)^1.5 came out as −4.8e-16·p⁵).
    It is not in that dictionary: there its columns lowered the
    cross-validation's minimum and the one-standard-error rule then kept
    look-alike terms beside a Coulomb friction (benchmarks.md); as a law of
    its own the loop's likelihood ratio judges it.

    Parameters
    ----------
    rec : Reconstruction
    options : DiscoverOptions, optional
        Only ``trim`` is used.

    Returns
    -------
    DiscoveredLaw or None
        One term; None when d̂ or its std is not finite or no term is
        non-zero on the fitted samples.
    """
    opts = options or DiscoverOptions()
    n = rec.t.size
    cut = int(round(opts.trim * n))
    keep = slice(cut, n - cut)
    own = rec.primary[0]
    z = np.asarray(rec.variables[own], float)[keep]
    d, d_std = np.asarray(rec.d, float)[keep], np.asarray(rec.d_std, float)[keep]
    if not (np.all(np.isfinite(d)) and np.all(np.isfinite(d_std))):
        return None
    w = 1.0 / np.maximum(d_std, 1e-12 * (np.abs(d).max() or 1.0))
    sym = sp.Symbol(own)
    unit = (rec.units or {}).get(own, "") or "1"
    best = None
    for side, qs in ((1, THRESHOLD_QUANTILES), (-1, tuple(1 - q for q in THRESHOLD_QUANTILES))):
        for q in qs:
            a = float(np.quantile(z, q))
            col = np.maximum(side * (z - a), 0.0)
            for p in THRESHOLD_POWERS:
                phi = col ** p
                den = float(np.sum((w * phi) ** 2))
                if not den > 0:
                    continue
                c = float(np.sum(w * phi * w * d)) / den
                sse = float(np.sum((w * (d - c * phi)) ** 2))
                if best is None or sse < best[0]:
                    best = (sse, side, a, p, c, phi)
    if best is None:
        return None
    _, side, a, p, c, phi = best
    name = (f"max({own}-{_fmt(a)},0)" if side > 0 else f"max({_fmt(a)}-{own},0)") + (
        f"^{p:g}" if p != 1 else "")
    term = Term(name, dead_zone(sym, a, side, p), c, float(np.sqrt(np.mean((c * phi) ** 2))),
                unit if p == 1 or unit == "1" else f"({unit})^{p:g}")
    return DiscoveredLaw(rec.port.port, rec.port.kind, rec.port.unit, {own: sym}, [term], [name],
                         [(name,)], np.array([best[0] / d.size]), np.zeros(1),
                         float(np.sqrt(np.mean(d ** 2))),
                         float(np.sqrt(np.mean((d - c * phi) ** 2))),
                         {own: (float(z.min()), float(z.max()))}, [], [])

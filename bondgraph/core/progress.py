"""Signs of life on long computations: tqdm bars that appear only when a
pass takes long.

A long record makes a single UKF pass take minutes; the bars of this module
say what is being done (``"UKF pass: 30 parameter sets x 200000 samples"``),
how far it is and how long is left. A bar is shown only

* when bars are switched on (:func:`enabled`; the command line switches them
  on unless ``--quiet``, :func:`bondgraph.inference.estimate.estimate`
  follows ``FitOptions.progress``), and
* once the pass has run for ``delay`` seconds, so short passes (the usual
  case, thousands per estimation) cost one clock read every ``every`` steps
  and print nothing.
"""

from __future__ import annotations

import contextlib
import sys
import threading
import time
from contextvars import ContextVar

from tqdm import tqdm

#: whether long passes show bars (off by default in the library)
_ENABLED: ContextVar[bool] = ContextVar("bondgraph_progress", default=False)


@contextlib.contextmanager
def enabled(flag: bool = True):
    """Switch the bars of long passes on (or off) inside a ``with`` block."""
    token = _ENABLED.set(bool(flag))
    try:
        yield
    finally:
        _ENABLED.reset(token)


def is_enabled() -> bool:
    """Whether bars are switched on here."""
    return _ENABLED.get()


def long_range(total: int, desc: str, unit: str = "sample", *, delay: float = 2.0,
               every: int = 64):
    """``range(total)`` with a :class:`LongPass` bar (``delay``, ``every``:
    its options); the bar is removed when the loop ends or is left (``break``)."""
    bar = LongPass(total, desc, unit, delay=delay, every=every)
    try:
        for k in range(int(total)):
            bar.step(k)
            yield k
    finally:
        bar.close()


class LongPass:
    """Progress of one long loop: call :meth:`step` with the index of every
    step; a bar appears after ``delay`` seconds (if bars are enabled) and is
    removed by :meth:`close`.

    Parameters
    ----------
    total : int
        Number of steps.
    desc : str
        What is being done.
    unit : str
        Name of a step (``"sample"``).
    delay : float
        Seconds before a bar is shown.
    every : int
        Steps between two looks at the clock.
    """

    def __init__(self, total: int, desc: str, unit: str = "step", *, delay: float = 2.0,
                 every: int = 64):
        self.total, self.desc, self.unit = int(total), desc, unit
        self.delay, self.every = delay, max(1, int(every))
        self.on = is_enabled()
        self.t0 = time.monotonic()
        self.bar = None

    def step(self, k: int) -> None:
        """Step ``k`` (0-based) is done or under way."""
        if not self.on or k % self.every:
            return
        if self.bar is None:
            if time.monotonic() - self.t0 < self.delay:
                return
            self.bar = bar(total=self.total, initial=k, desc=self.desc, unit=self.unit,
                           leave=False, dynamic_ncols=True, mininterval=0.5)
            return
        self.bar.update(k - self.bar.n)

    def close(self) -> None:
        """Remove the bar (if one was shown)."""
        if self.bar is not None:
            self.bar.close()
            self.bar = None

    def __enter__(self) -> "LongPass":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


@contextlib.contextmanager
def announced(what: str, *, delay: float = 2.0, note: str = "", stream=None,
              tick: float = 0.5, heartbeat: float = 2.0):
    """Say what is being done when a block runs longer than ``delay``
    seconds (a compile the user waits for: ``"compiling the fused UKF
    kernel"``), keep a live elapsed-time bar on a terminal while it runs, and
    say how long it took when it ends; nothing for a short block (a cache
    load) or when bars are switched off (:func:`enabled`).

    On a terminal (``stream.isatty()``) the announcement is a tqdm line whose
    elapsed time a background thread refreshes every ``tick`` seconds, so
    nothing is silent for longer than ``delay``; elsewhere (a log file, a
    pipe) the announcement is one line without redraws, to which a dot is
    appended every ``heartbeat`` seconds while the block runs (a reader of
    the pipe sees it is alive; the log keeps one line).

    Parameters
    ----------
    what : str
        What the block does.
    delay : float
        Seconds of silence before the announcement [s].
    note : str
        Appended to the announcement (e.g. "once: numba caches it on disk").
    stream : file-like, optional
        Where to write (default: ``sys.stderr`` at the call).
    tick : float
        Seconds between two refreshes of the live bar [s].
    heartbeat : float
        Seconds between two dots off a terminal [s].
    """
    if not is_enabled():
        yield
        return
    out = sys.stderr if stream is None else stream
    t0 = time.perf_counter()
    label = f"{what} ({note})" if note else what
    done = threading.Event()
    ticker = threading.Thread(target=_announce,
                              args=(label, out, delay, (tick, heartbeat), done), daemon=True)
    ticker.start()
    try:
        yield
    finally:
        done.set()
        ticker.join()
        took = time.perf_counter() - t0
        if took >= delay:
            print(f"  ... {what}: done in {took:.0f} s", file=out, flush=True)


def bar(iterable=None, **kwargs):
    """A tqdm bar on stderr (``kwargs``: tqdm's) that is drawn only on a
    terminal: in a pipe or a log file each redraw would stay behind as text
    (``\\r``-separated copies of the bar); there :func:`watchdog` names a
    long silent phase instead. ``disable=True`` still switches it off."""
    kwargs.setdefault("file", sys.stderr)
    kwargs["disable"] = bool(kwargs.get("disable")) or not _is_terminal(kwargs["file"])
    return tqdm(iterable, **kwargs)


def _is_terminal(stream) -> bool:
    """Whether ``stream`` is a terminal (a live bar would be overwritten in place)."""
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError):
        return False


def _announce(label: str, out, delay: float, ticks: tuple[float, float],
              done: threading.Event) -> None:
    """The announcing thread of :func:`announced`: after ``delay`` s (unless
    ``done``), the line, then on a terminal a tqdm bar of the elapsed
    seconds refreshed every ``ticks[0]`` s until ``done``, elsewhere a dot
    appended every ``ticks[1]`` s and the line ended at ``done``."""
    tick, heartbeat = ticks
    if done.wait(delay):
        return
    with _ANNOUNCING_LOCK:         # from its line on, its own dots or bar keep the output alive
        _ANNOUNCING[0] += 1
    try:
        _announce_shown(label, out, delay, ticks, done)
    finally:
        with _ANNOUNCING_LOCK:
            _ANNOUNCING[0] -= 1


def _announce_shown(label: str, out, delay: float, ticks: tuple[float, float],
                    done: threading.Event) -> None:
    """:func:`_announce` once its line is due: the line with its dots, or
    the live bar on a terminal, until ``done``."""
    tick, heartbeat = ticks
    if not _is_terminal(out):
        print(f"  ... {label}", file=out, end="", flush=True)
        while not done.wait(heartbeat):
            print(" .", file=out, end="", flush=True)
        print(file=out, flush=True)
        return
    bar = tqdm(total=None, desc=f"  ... {label}", file=out, leave=False, dynamic_ncols=True,
               bar_format="{desc}: {elapsed} elapsed", mininterval=0, miniters=1,
               initial=0)
    bar.start_t = bar.last_print_t = time.time() - delay   # count from the block's start
    try:
        while not done.wait(tick):
            bar.update(1)
    finally:
        bar.close()


#: what the program is doing, innermost last: (text, start time) pairs
#: (:func:`phase`), named by :func:`watchdog`'s lines
_PHASES: list[tuple[str, float]] = []
#: announced blocks whose line is shown (:func:`announced`): their own dots
#: keep the output alive, so :func:`watchdog` stays quiet meanwhile (not
#: during an announcement's first ``delay`` seconds, which print nothing)
_ANNOUNCING = [0]
_ANNOUNCING_LOCK = threading.Lock()


@contextlib.contextmanager
def phase(what: str):
    """Name what a stretch of work does (``"step 2: scoring the
    candidates"``) for the lines of :func:`watchdog`; phases nest."""
    _PHASES.append((what, time.monotonic()))
    try:
        yield
    finally:
        _PHASES.pop()


#: held while the watchdog's line is written and while other output ends it
_LINE_LOCK = threading.RLock()


class _Stamped:
    """A text stream that records when it was last written (``clock[0]``,
    monotonic seconds) and first ends the :func:`watchdog`'s open line
    (``opened[0]``: the stream it is open on, or None); everything else is
    the stream's."""

    def __init__(self, stream, clock: list, opened: list):
        self._stream, self._clock, self._opened = stream, clock, opened

    def write(self, text):
        with _LINE_LOCK:            # the watchdog's dots never land inside this text
            line = self._opened[0]
            if line is not None:
                self._opened[0] = None
                line.write("\n")
                line.flush()
            self._clock[0] = time.monotonic()
            return self._stream.write(text)

    def __getattr__(self, name):
        return getattr(self._stream, name)


@contextlib.contextmanager
def watchdog(quiet_after: float = 1.5, poll: float = 0.25):
    """Nothing silent for long (a command's whole run): while the block
    runs with bars switched on (:func:`enabled`), whenever neither stdout
    nor stderr has been written for ``quiet_after`` seconds and no
    :func:`announced` block is adding its dots, one line on stderr says
    what is being done and for how long: ``"  ... step 2: scoring the
    candidates (6 s)"`` (the innermost :func:`phase`). A long phase without
    other output keeps that line and adds a dot every ``quiet_after``
    seconds (``"... (6 s) . . ."``; a line per tick filled a user's log
    with 400 lines in one loop); other output, or another phase, ends it.

    Parameters
    ----------
    quiet_after : float
        Seconds of silence before a line [s] (1.5: with ``poll`` and a busy
        interpreter's thread switches a line still came 2.4 s after the
        last one at 2.0; nothing is to be silent for more than 2 s).
    poll : float
        Seconds between two looks at the clock [s].
    """
    if not is_enabled():
        yield
        return
    clock, opened, shown = [time.monotonic()], [None], [None]
    out, err = sys.stdout, sys.stderr
    sys.stdout, sys.stderr = _Stamped(out, clock, opened), _Stamped(err, clock, opened)
    stop = threading.Event()
    t0 = time.monotonic()

    def watch():
        while not stop.wait(poll):
            now = time.monotonic()
            if _ANNOUNCING[0] or now - clock[0] < quiet_after:
                continue
            what, since = _PHASES[-1] if _PHASES else ("working", t0)
            with _LINE_LOCK:
                if opened[0] is not None and shown[0] == (what, since):
                    err.write(" .")
                else:
                    if opened[0] is not None:
                        err.write("\n")
                    err.write(f"  ... {what} ({now - since:.0f} s)")
                    opened[0], shown[0] = err, (what, since)
                err.flush()
                clock[0] = time.monotonic()

    th = threading.Thread(target=watch, daemon=True)
    th.start()
    try:
        yield
    finally:
        stop.set()
        th.join()
        with _LINE_LOCK:
            if opened[0] is not None:
                err.write("\n")
                err.flush()
        sys.stdout, sys.stderr = out, err

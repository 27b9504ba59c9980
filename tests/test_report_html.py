"""The loop's report.html in a real browser (issue 30): headless Chromium
opens it, no console error or uncaught exception, every image loads
(naturalWidth > 0), a click on a column head sorts a ranking table, and a
screenshot shows the plots (not a blank page). The browser is driven over
the DevTools protocol (websocket-client); the driver is checked on a
deliberately broken page (an exception, a console.error, a missing image).

The test skips with its reason where Chromium or websocket-client is absent
(CI installs Chromium, .ci/run)."""

from __future__ import annotations

import base64
import io
import json
import os
import re
import shutil
import subprocess
import tempfile
import time
from html.parser import HTMLParser
from pathlib import Path

import numpy as np
import pytest

from bondgraph.catalog.reference import mass_spring_damper
from bondgraph.diagnose.cases import synthesize
from bondgraph.diagnose.effects import apply_effect
from bondgraph.diagnose.loop import run_loop
from bondgraph.diagnose.settings import LoopSettings, SearchOptions
from bondgraph.report.html import graph_changes
from bondgraph.report.loop_report import LoopReporter

CHROMIUM = next((p for p in (shutil.which(n) for n in ("chromium", "chromium-browser",
                                                        "google-chrome", "chrome")) if p), None)
FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
         "--disable-background-networking", "--disable-component-update", "--disable-sync",
         "--disable-dev-shm-usage", "--remote-allow-origins=*", "--remote-debugging-port=0",
         "--window-size=1300,2000"]
#: guard against a hung browser (not a timing assertion)
PATIENCE = 60.0


def _needs_browser():
    if CHROMIUM is None:
        pytest.skip("Chromium is not installed (apt-get install chromium; CI installs it)")
    try:
        import websocket  # noqa: F401
    except ImportError:
        pytest.skip("websocket-client is not installed (pip install -e '.[dev]')")


class Browser:
    """Headless Chromium with a fresh profile, one page, driven over the
    DevTools protocol."""

    def __init__(self):
        import websocket
        self.profile = tempfile.mkdtemp(prefix="chromium-profile-")
        self.proc = subprocess.Popen([CHROMIUM, *FLAGS, f"--user-data-dir={self.profile}",
                                      "about:blank"], stdout=subprocess.DEVNULL,
                                     stderr=subprocess.PIPE, text=True)
        url = self._devtools_url()
        self.ws = websocket.create_connection(url, timeout=PATIENCE, suppress_origin=True,
                                              http_no_proxy=["127.0.0.1", "localhost"])
        self.n, self.events = 0, []
        target = self.call("Target.createTarget", url="about:blank")["targetId"]
        self.session = self.call("Target.attachToTarget", targetId=target,
                                 flatten=True)["sessionId"]
        for domain in ("Page", "Runtime", "Log"):
            self.call(f"{domain}.enable", session=True)

    def _devtools_url(self) -> str:
        """The browser's websocket address, read from its stderr."""
        for line in self.proc.stderr:
            m = re.search(r"DevTools listening on (ws://\S+)", line)
            if m:
                return m.group(1)
        raise RuntimeError(f"Chromium exited ({self.proc.wait()}) without a DevTools address")

    def call(self, method: str, session: bool = False, **params) -> dict:
        """Send one command; keep the events that arrive before its answer."""
        self.n += 1
        msg = {"id": self.n, "method": method, "params": params}
        if session:
            msg["sessionId"] = self.session
        self.ws.send(json.dumps(msg))
        while True:
            m = json.loads(self.ws.recv())
            if m.get("id") == self.n:
                if "error" in m:
                    raise RuntimeError(f"{method}: {m['error']}")
                return m.get("result", {})
            self.events.append(m)

    def open(self, path: Path) -> None:
        """Load ``path`` and wait for its load event."""
        self.events.clear()
        self.call("Page.navigate", session=True, url=path.resolve().as_uri())
        deadline = time.monotonic() + PATIENCE
        while not any(e.get("method") == "Page.loadEventFired" for e in self.events):
            if time.monotonic() > deadline:
                raise RuntimeError(f"{path} did not load")
            self.events.append(json.loads(self.ws.recv()))
        self.evaluate("new Promise(r => setTimeout(r, 200))")   # late console messages

    def evaluate(self, expression: str):
        """The value of a JavaScript expression in the page (promises awaited)."""
        r = self.call("Runtime.evaluate", session=True, expression=expression,
                      returnByValue=True, awaitPromise=True)
        if "exceptionDetails" in r:
            raise RuntimeError(f"{expression}: {r['exceptionDetails']}")
        return r["result"].get("value")

    def errors(self) -> list[str]:
        """Uncaught exceptions, console.error calls and error log entries."""
        out = []
        for e in self.events:
            m, p = e.get("method"), e.get("params", {})
            if m == "Runtime.exceptionThrown":
                d = p["exceptionDetails"]
                out.append("exception: " + d.get("exception", {}).get("description", d["text"]))
            elif m == "Runtime.consoleAPICalled" and p["type"] in ("error", "assert"):
                out.append("console: " + " ".join(str(a.get("value", a.get("description")))
                                                  for a in p["args"]))
            elif m == "Log.entryAdded" and p["entry"]["level"] == "error":
                out.append("log: " + p["entry"]["text"])
        return out

    def screenshot(self) -> np.ndarray:
        """The whole page as an RGB(A) array."""
        import matplotlib.image
        data = self.call("Page.captureScreenshot", session=True, format="png",
                         captureBeyondViewport=True)["data"]
        return matplotlib.image.imread(io.BytesIO(base64.b64decode(data)), format="png")

    def close(self) -> None:
        try:
            self.ws.close()
        finally:
            self.proc.terminate()
            try:
                self.proc.wait(10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
            shutil.rmtree(self.profile, ignore_errors=True)


@pytest.fixture(scope="module")
def browser():
    _needs_browser()
    b = Browser()
    yield b
    b.close()


@pytest.fixture(scope="module")
def report(tmp_path_factory):
    """The report of a short loop that accepts Coulomb friction on a
    mass-spring-damper (score tests only, one step)."""
    declared, truth = mass_spring_damper(), mass_spring_damper()
    truth.name = "truth"
    apply_effect(truth, "coulomb", ("junction", "v"), {"Fc": 2.0})
    levels = np.random.default_rng(0).normal(0, 20, 20)
    t = np.arange(400) * 0.01
    exp = synthesize(truth, declared, t,
                     {"F": lambda tt: levels[np.minimum((np.asarray(tt) / 0.2).astype(int), 19)]},
                     {}, {"m": 2.0, "k": 50.0, "c": 1.5}, 5, "coulomb", "")
    out = tmp_path_factory.mktemp("loop") / "report"
    rep = LoopReporter(out)
    res = run_loop(declared, exp, LoopSettings(params=["m", "k", "c"], search=SearchOptions(
        max_steps=1, structural=False)), log=rep.log, on_update=rep.update, progress=False)
    assert [s.effect for s in res.steps] == ["coulomb"], "the fixture must accept an effect"
    return out, res


class _Parts(HTMLParser):
    """What report.html holds: image sources, script sources, links, ids."""

    def __init__(self):
        super().__init__()
        self.img, self.script_src, self.ids, self.href = [], [], [], []

    def handle_starttag(self, tag, attrs):
        a = dict(attrs)
        if tag == "img":
            self.img.append(a.get("src", ""))
        if tag in ("script", "link") and (a.get("src") or a.get("href")):
            self.script_src.append(a.get("src") or a.get("href"))
        if tag == "a":
            self.href.append(a.get("href", ""))
        if "id" in a:
            self.ids.append(a["id"])


def test_report_html_is_self_contained(report):
    out, res = report
    text = (out / "report.html").read_text()
    parts = _Parts()
    parts.feed(text)
    # every plot inline, nothing fetched: no external script or style, no http(s)
    assert parts.img and all(s.startswith("data:image/png;base64,") for s in parts.img)
    assert len(parts.img) == 5      # graph before/after, fit, innovations, evidence of step 1
    assert parts.script_src == [] and "http://" not in text and "https://" not in text
    assert set(parts.href) == {"report.md", "report.json", "loop.log"}
    # the warnings come first, before the result
    assert parts.ids[:2] == (["warnings", "result"] if res.final.at_bound or res.warnings
                             else ["result", "graph"])
    # every parameter with its std
    for name, v in res.final.estimates.items():
        assert f"<td>{name}</td>" in text and f"{v:.6g}" in text
        if res.final.std.get(name) is not None:
            assert f"{res.final.std[name]:.3g}" in text
    added = graph_changes(res.declared_graph, res.final_graph)
    assert any(n in res.final_graph.elements for n in added)
    assert "added elements in green: " in text


def test_report_html_escapes_what_it_shows(report, tmp_path):
    from bondgraph.report.html import page
    out, res = report
    import copy
    evil = copy.copy(res)
    evil.warnings = ["<script>alert(1)</script> & more"]
    text = page(evil, out, [])
    assert "<script>alert(1)</script>" not in text
    assert "&lt;script&gt;alert(1)&lt;/script&gt; &amp; more" in text


def test_browser_driver_sees_a_broken_page(browser, tmp_path):
    """The driver must really see errors: an uncaught exception, a
    console.error and an image that does not load."""
    bad = tmp_path / "broken.html"
    bad.write_text("<!DOCTYPE html><html><body><img id=i src='missing.png'>"
                   "<script>console.error('deliberate');</script>"
                   "<script>undefinedFunction();</script></body></html>")
    browser.open(bad)
    errors = browser.errors()
    assert any("deliberate" in e for e in errors), errors
    assert any("undefinedFunction" in e for e in errors), errors
    assert browser.evaluate("document.getElementById('i').naturalWidth") == 0


def test_report_html_opens_in_chromium(browser, report):
    out, _ = report
    browser.open(out / "report.html")
    assert browser.errors() == []
    widths = browser.evaluate("Array.from(document.images).map(i => i.complete && i.naturalWidth)")
    assert len(widths) == 5 and all(w > 0 for w in widths), widths
    # a click on 'χ²' sorts the ranking table by it (up, then down)
    col = """(function () {
      var t = document.querySelector('#evidence ~ table.sortable');
      var i = Array.from(t.tHead.rows[0].cells).findIndex(c => c.textContent === 'χ²');
      t.tHead.rows[0].cells[i].click();
      return Array.from(t.tBodies[0].rows).map(r => Number(r.cells[i].dataset.v));
    })()"""
    up = browser.evaluate(col)
    assert len(up) > 3 and up == sorted(up)
    assert browser.evaluate(col) == sorted(up, reverse=True)
    assert browser.errors() == []
    shot = browser.screenshot()[..., :3]
    assert shot.shape[0] > 2000           # the whole page, not the first screen
    # the plots are on it: many distinct colours, not a blank white page
    colours = np.unique((shot.reshape(-1, 3) * 255).astype(np.uint8), axis=0)
    assert len(colours) > 200 and float(shot.std()) > 0.05
    assert (shot < 0.9).mean() > 0.05     # not mostly white
    if os.environ.get("BONDGRAPH_KEEP_SCREENSHOT"):
        import matplotlib.image
        matplotlib.image.imsave(os.environ["BONDGRAPH_KEEP_SCREENSHOT"], shot)


def test_a_process_noise_floor_is_no_warning():
    """html._warnings: an estimate on its box is a warning, a process-noise
    intensity on the floor of its box (FitSummary.noise_floor) is not (the
    default coast-down's q_grade once the drag is accepted)."""
    from types import SimpleNamespace

    from bondgraph.report.html import _warnings

    final = SimpleNamespace(at_bound=["q_grade", "c"], noise_floor=["q_grade"], flat=[])
    (block,) = _warnings(SimpleNamespace(warnings=[], final=final))
    assert "estimates on a bound of their box (no Cramér-Rao std): c</li>" in block
    assert "q_grade" not in block
    final.at_bound = ["q_grade"]
    assert _warnings(SimpleNamespace(warnings=[], final=final)) == []


def test_the_ridge_sentence_says_how_far_each_parameter_is_known():
    """report.md's not-identified sentence gives each flat parameter's robust
    std as a share of its value (loop_report._ridge_width), what the accept
    rule's identification test reads: Fv 41.4 of 207 is 20 %, Fc 2 of -20
    is 10 %; β has no robust std and is left out."""
    from bondgraph.report.loop_report import _ridge_width

    text = _ridge_width(["Fv", "Fc", "beta"], {"Fv": 41.4, "Fc": 2.0},
                        {"Fv": 207.0, "Fc": -20.0, "beta": 1.0})
    assert text == (" Their robust std as a share of their values: Fv 20 %, Fc 10 % (the accept "
                    "rule counts a parameter known within 10% as determined).")
    assert _ridge_width(["beta"], {}, {"beta": 1.0}) == ""


def test_an_intermediate_report_is_written_beside_the_loop_from_a_copy(report, tmp_path,
                                                                       monkeypatch):
    """LoopReporter.update writes an intermediate version on a thread of its
    own from a copy of the result: what the loop changes after the call is
    not in it, its files are those the loop's own thread writes (byte for
    byte, the log aside), and a failure is raised by the next update."""
    import copy
    import threading

    from bondgraph.errors import OutputError
    from bondgraph.report import loop_report

    res = copy.deepcopy(report[1])
    res.finished = False
    threads = []
    original = loop_report.write

    def spy(*a, **k):
        threads.append(threading.current_thread().name)
        return original(*a, **k)

    monkeypatch.setattr(loop_report, "write", spy)
    beside = LoopReporter(tmp_path / "beside")
    beside.update(res)
    res.warnings.append("LATE: after the update")
    beside.wait()
    inline = LoopReporter(tmp_path / "inline", background=False)
    inline.update(res)
    assert threads == ["loop-report", "MainThread"]
    a, b = tmp_path / "beside", tmp_path / "inline"
    names = sorted(p.name for p in a.iterdir())
    assert names == sorted(p.name for p in b.iterdir()) and "fit_before_after.png" in names
    assert "LATE" not in (a / "report.json").read_text()
    assert "LATE" in (b / "report.json").read_text()
    res.warnings.pop()
    inline2 = LoopReporter(tmp_path / "inline2", background=False)
    inline2.update(res)
    for n in names:
        if (a / n).is_file() and n != "loop.log" and n != "augmented_model.py":
            assert (a / n).read_bytes() == (tmp_path / "inline2" / n).read_bytes(), n

    def fail(*a, **k):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(loop_report, "write", fail)
    beside.update(res)                     # returns at once; the writer fails
    with pytest.raises(OutputError, match="No space left on device"):
        beside.update(res)
    monkeypatch.setattr(loop_report, "write", spy)
    beside.update(res)
    beside.wait()
    res.finished = True
    beside.update(res)
    assert json.loads((a / "report.json").read_text())["finished"] is True

"""``replay --html`` in a real headless Chromium (issue 26 item 6): the page's scripts run without an
error, both plots are drawn with a size, and a click on the cloud's slider moves the cursor of every time
plot to that step's time (read from the log, not from the page).

Chromium is driven over the DevTools protocol on a pipe (``--remote-debugging-pipe``: JSON messages
separated by NUL on file descriptors 3 and 4), so no browser driver or websocket package is needed.
Skipped when no Chromium is installed (``make images`` installs one through apt).
"""

from __future__ import annotations

import json
import os
import select
import shutil
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest
from test_report import bowl_run  # noqa: F401  (the module's fixture: a short run and its report)

pytest.importorskip("plotly")

DEADLINE_S = 60.0  # every wait below is bounded by this (a loaded 2-core machine)


def _chromium() -> str | None:
    for name in ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable"):
        path = shutil.which(name)
        if path:
            return path
    return None


CHROMIUM = _chromium()
pytestmark = pytest.mark.skipif(CHROMIUM is None, reason="no headless Chromium installed "
                                "(apt-get install chromium; make images installs it)")


class Browser:
    """One headless Chromium page driven over the DevTools protocol on a pipe."""

    def __init__(self, tmp_path: Path):
        to_child_r, self._to_child = os.pipe()
        self._from_child, from_child_w = os.pipe()

        def fds() -> None:  # the protocol's fixed descriptors: 3 in, 4 out
            os.dup2(to_child_r, 3)
            os.dup2(from_child_w, 4)

        self.proc = subprocess.Popen(
            [CHROMIUM, "--headless", "--no-sandbox", "--disable-gpu", "--remote-debugging-pipe",
             "--no-first-run", "--no-default-browser-check", f"--user-data-dir={tmp_path / 'profile'}",
             "--window-size=1400,900", "about:blank"],
            stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
            preexec_fn=fds, pass_fds=(3, 4), start_new_session=True)  # kept after preexec_fn
        os.close(to_child_r)
        os.close(from_child_w)
        self._buf, self._id, self.events = b"", 0, []
        target = self.call("Target.createTarget", url="about:blank")["targetId"]
        self.session = self.call("Target.attachToTarget", targetId=target, flatten=True)["sessionId"]
        for domain in ("Runtime", "Page", "Log"):
            self.call(f"{domain}.enable", session=True)
        # a new target's viewport is 800 x 600 whatever the window: the size ``make images`` shoots
        self.call("Emulation.setDeviceMetricsOverride", session=True, width=1400, height=900, deviceScaleFactor=1,
                  mobile=False)

    def _message(self, timeout: float) -> dict | None:
        end = time.monotonic() + timeout
        while b"\0" not in self._buf:
            left = end - time.monotonic()
            if left <= 0 or not select.select([self._from_child], [], [], left)[0]:
                return None
            chunk = os.read(self._from_child, 1 << 20)
            assert chunk, "Chromium closed its DevTools pipe"
            self._buf += chunk
        msg, self._buf = self._buf.split(b"\0", 1)
        return json.loads(msg)

    def call(self, method: str, session: bool = False, **params) -> dict:
        self._id += 1
        msg = {"id": self._id, "method": method, "params": params}
        if session:
            msg["sessionId"] = self.session
        os.write(self._to_child, json.dumps(msg).encode() + b"\0")
        end = time.monotonic() + DEADLINE_S
        while time.monotonic() < end:
            reply = self._message(end - time.monotonic())
            if reply is None:
                break
            if reply.get("id") == self._id:
                assert "error" not in reply, (method, reply["error"])
                return reply.get("result", {})
            self.events.append(reply)
        raise AssertionError(f"Chromium did not answer {method} within {DEADLINE_S:.0f} s")

    def wait_event(self, method: str) -> dict:
        end = time.monotonic() + DEADLINE_S
        while time.monotonic() < end:
            for ev in self.events:
                if ev.get("method") == method:
                    self.events.remove(ev)
                    return ev
            ev = self._message(end - time.monotonic())
            if ev is not None:
                self.events.append(ev)
        raise AssertionError(f"no {method} within {DEADLINE_S:.0f} s")

    def js(self, expression: str):
        res = self.call("Runtime.evaluate", session=True, expression=expression, returnByValue=True,
                        awaitPromise=True)
        assert "exceptionDetails" not in res, res["exceptionDetails"]
        return res["result"].get("value")

    def click(self, x: float, y: float) -> None:
        for kind in ("mouseMoved", "mousePressed", "mouseReleased"):
            self.call("Input.dispatchMouseEvent", session=True, type=kind, x=x, y=y, button="left",
                      clickCount=1 if kind != "mouseMoved" else 0)

    def errors(self) -> list[str]:
        """Script exceptions and console/log errors seen so far."""
        out = []
        for ev in self.events:
            p = ev.get("params", {})
            if ev.get("method") == "Runtime.exceptionThrown":
                out.append(json.dumps(p["exceptionDetails"])[:300])
            elif ev.get("method") == "Runtime.consoleAPICalled" and p.get("type") == "error":
                out.append(json.dumps(p.get("args"))[:300])
            elif ev.get("method") == "Log.entryAdded" and p["entry"].get("level") == "error" \
                    and p["entry"].get("source") not in ("network", "rendering"):
                out.append(p["entry"].get("text", "")[:300])
        return out

    def close(self) -> None:
        self.proc.kill()
        self.proc.wait()
        os.close(self._to_child)
        os.close(self._from_child)


@pytest.fixture
def browser(tmp_path):
    b = Browser(tmp_path)
    try:
        yield b
    finally:
        b.close()


def _until(browser: Browser, expression: str) -> None:
    end = time.monotonic() + DEADLINE_S
    while not browser.js(expression):
        assert time.monotonic() < end, f"never true: {expression}"
        time.sleep(0.1)


CURSORS = ("(document.getElementById('tergodic-series').layout.shapes || [])"
           ".filter(s => s.name === 'cursor').map(s => s.x0)")


def test_the_report_renders_and_its_slider_moves_the_cursors(bowl_run, browser):  # noqa: F811
    _, page, data = bowl_run
    browser.call("Page.navigate", session=True, url=page.resolve().as_uri())
    browser.wait_event("Page.loadEventFired")
    _until(browser, "document.querySelectorAll('.js-plotly-plot').length === 2")

    sizes = browser.js("""Array.from(document.querySelectorAll('.js-plotly-plot')).map(d => {
        const r = d.getBoundingClientRect(); return [d.id, r.width, r.height]; })""")
    assert sorted(s[0] for s in sizes) == ["tergodic-cloud", "tergodic-series"]
    for _, w, h in sizes:
        assert w > 300 and h > 300, sizes
    # the time plots are SVG lines with points; the cloud is a WebGL scene with its canvas drawn
    assert browser.js("document.querySelectorAll('#tergodic-series .scatterlayer path.js-line').length") >= 3
    assert browser.js("document.querySelectorAll('#tergodic-cloud canvas').length") >= 1
    assert browser.js("document.getElementById('tergodic-cloud')._fullLayout.sliders.length") == 1
    assert browser.errors() == []

    times = {int(c.step): float(data.series["t"][data.index_of(c.step)]) for c in data.clouds}
    steps = sorted(times)
    assert len(steps) == 3
    # the page opens at the last cloud, every cursor on its time
    cur = browser.js(CURSORS)
    assert len(cur) >= 3
    np.testing.assert_allclose(cur, times[steps[-1]], rtol=0, atol=1e-9)

    # a real click on the slider's first tick: the cloud moves to that step and every cursor with it
    box = browser.js("""(() => { const e = document.querySelector('#tergodic-cloud .slider-rail-touch-rect');
        e.scrollIntoView({block: 'center'}); const r = e.getBoundingClientRect(); return [r.left, r.top, r.width, r.height]; })()""")
    left, top, width, height = box
    x, y = left + 0.02 * width, top + height / 2
    assert browser.js(f"document.elementFromPoint({x}, {y}).classList.contains('slider-rail-touch-rect')")
    browser.click(x, y)
    _until(browser, f"{CURSORS}.every(x => Math.abs(x - {times[steps[0]]!r}) < 1e-9)")
    active = browser.js("document.getElementById('tergodic-cloud')._fullLayout.sliders[0].active")
    assert active == 0
    assert browser.errors() == []

"""The web viewer in a real browser: the system's Chromium, headless, driven over the DevTools
protocol (``tests/cdp.py``), against a real service with a simulated glove streaming into it.
Checks what a person sees: the session list, the hand side, the status (waiting for a source, live,
refused), the angles changing, gesture events listed, the angle plot and the hand drawn, the token
kept out of the address, a new address hash reconnecting, and no redrawing without new data.
Skips where Chromium is missing (Debian: ``apt-get install chromium``).

``FINGERTRACK_VIEWER_SCREENSHOT=docs/viewer.png`` also writes the screenshot for the docs."""
import asyncio
import json
import os
import shutil

import pytest

from clients.glove import stream_glove
from service.api.config import ServiceSettings
from service.api.server import ServerThread
from service.sim.motions import sequence_motion
from service.sim.session import SimConfig

from cdp import Browser, find_chromium
from test_service import ADMIN, SOURCE, VIEWER

pytestmark = pytest.mark.usefixtures("one_hand_worker")     # conftest: one hand worker per service

# Counts each canvas's redraws (every draw starts with clearRect) and finished /v1/sessions requests.
INSTRUMENT = """
window.__draws = {};
const clearRect = CanvasRenderingContext2D.prototype.clearRect;
CanvasRenderingContext2D.prototype.clearRect = function (...a) {
  window.__draws[this.canvas.id] = (window.__draws[this.canvas.id] || 0) + 1;
  return clearRect.apply(this, a);
};
window.__polls = 0;
const realFetch = window.fetch;
window.fetch = function (...a) {
  const p = realFetch.apply(this, a);
  if (String(a[0]).includes("/v1/sessions")) p.finally(() => { window.__polls += 1; }).catch(() => {});
  return p;
};
"""
# Pixels of a canvas within `tol` (per channel) of each colour, counted in the page.
COUNT_COLOURS = """((id, colours, tol) => {
  const c = document.getElementById(id), d = c.getContext("2d").getImageData(0, 0, c.width, c.height).data;
  const rgb = colours.map((h) => [1, 3, 5].map((i) => parseInt(h.slice(i, i + 2), 16)));
  const n = rgb.map(() => 0);
  for (let i = 0; i < d.length; i += 4) {
    if (d[i + 3] < 200) continue;
    rgb.forEach((c, k) => { if (Math.abs(d[i] - c[0]) <= tol && Math.abs(d[i + 1] - c[1]) <= tol && Math.abs(d[i + 2] - c[2]) <= tol) n[k] += 1; });
  }
  return n;
})"""
FINGER_COLOURS = ["#d62728", "#1f77b4", "#2ca02c", "#9467bd", "#e67e00"]     # viewer.js COLORS
BONE, RAY = "#444466", "#ee9900"
ANIMATION_FRAMES = "new Promise((r) => { let n = 0; const f = () => (++n >= 30 ? r(n) : requestAnimationFrame(f)); requestAnimationFrame(f); })"


@pytest.fixture(scope="module")
def chromium():
    exe = find_chromium()
    if exe is None:
        pytest.skip("needs Chromium to open the viewer (Debian: apt-get install chromium; "
                    "or FINGERTRACK_CHROMIUM=path); no browser is downloaded")
    return exe


@pytest.fixture(scope="module")
def server(chromium):
    """Started only where there is a browser to open it (the tests' skip starts no service)."""
    settings = ServiceSettings.load(port=0, tokens={SOURCE: "source", VIEWER: "viewer"}, admin_token=ADMIN)
    with ServerThread(settings) as srv:
        yield srv


def _text(id_):
    return f"document.getElementById({json.dumps(id_)}).textContent"


def _state(session, state):
    return f"{_text('current')} === {json.dumps(session)} && document.getElementById('status').dataset.state === {json.dumps(state)}"


async def _history_urls(page):
    return [e["url"] for e in (await page.send("Page.getNavigationHistory"))["entries"]]


async def _scenario(server, exe, tmp_path):
    async with Browser(exe, tmp_path / "profile") as browser:
        page = await browser.new_page(INSTRUMENT)
        await page.navigate(f"{server.url}/viewer/#session=br1&token={VIEWER}")

        # a session nobody streams to says so; the token given in the hash left the address
        await page.wait_for(_state("br1", "waiting"), "br1 waiting for a source")
        assert "waiting for a source" in await page.evaluate(_text("status"))
        assert await page.evaluate("location.hash") == "#session=br1"
        assert all(VIEWER not in url for url in await _history_urls(page))
        assert await page.evaluate("sessionStorage.getItem('fingertrack.viewer.token')") == VIEWER
        # only a source creates a session: br1 enters the session list with its glove
        assert await page.evaluate("document.querySelector('#sessions li[data-session=\"br1\"]') === null")

        # a left glove: grasp, open, point
        config = SimConfig(motion="sequence", noise="white", seed=7, hand="left", hand_motion="slow-rotation",
                           finger_motion=sequence_motion(steps=(("grasp", 0.5), ("open", 0.4), ("point", 1.2))))
        glove = asyncio.create_task(stream_glove(server.url, "br1", SOURCE, config, speed=1.0))
        await page.wait_for(_state("br1", "live"), "br1 live")
        await page.wait_for("document.querySelector('#sessions li[data-session=\"br1\"]')", "br1 in the session list")
        assert await page.evaluate(_text("side")) == "left hand"
        finger_lines = "document.getElementById('angles').textContent.split('\\n').slice(0, 5).join('\\n')"
        first = await page.wait_for(finger_lines, "joint angles")
        assert first.startswith("thumb ") and "index " in first
        await page.wait_for(f"{finger_lines} !== {json.dumps(first)}", "the angles changing")
        await page.wait_for(f"{_text('events')}.includes('grasp start')", "the grasp listed")
        await page.wait_for(f"{_text('angles')}.includes('active point')", "the hand pointing")
        await page.wait_for(f"{_text('events')}.includes('point start')", "the point listed")
        shot = await page.screenshot()
        assert (await page.evaluate(f"{COUNT_COLOURS}('hand3d', {json.dumps([BONE, RAY])}, 12)"))[1] > 20, "no pointing ray"
        pub = await glove
        await pub.close()
        assert not pub.errors

        # the plot: a line for every joint angle, in every finger's colour
        legend = await page.evaluate("[...document.querySelectorAll('#legend span')].map((s) => s.textContent)")
        assert legend == ["thumb mcp", "thumb ip"] + [f"{f} {j}" for f in ("index", "middle", "ring", "little")
                                                      for j in ("mcp", "pip", "dip")]
        bone, _ = await page.evaluate(f"{COUNT_COLOURS}('hand3d', {json.dumps([BONE, RAY])}, 12)")
        assert bone > 100, "no hand drawn"
        per_finger = await page.evaluate(f"{COUNT_COLOURS}('plot', {json.dumps(FINGER_COLOURS)}, 40)")
        # the script curls middle, ring and little together (grasp, open, point), so their lines
        # coincide and the last one drawn (little) may cover the other two entirely
        thumb, index, middle, ring, little = per_finger
        assert thumb > 50 and index > 50 and middle + ring + little > 150, per_finger

        # the source left: said so, and nothing is redrawn while no data comes
        await page.wait_for(_state("br1", "waiting"), "br1 waiting again after the glove left")
        assert "the source has left" in await page.evaluate(_text("status"))
        draws, polls = await page.evaluate("JSON.stringify(window.__draws)"), await page.evaluate("window.__polls")
        assert json.loads(draws)["plot"] > 10 and json.loads(draws)["hand3d"] > 10
        await page.wait_for(f"window.__polls >= {polls + 2}", "two more session-list updates")
        await page.evaluate(ANIMATION_FRAMES)
        assert await page.evaluate("JSON.stringify(window.__draws)") == draws

        # without a token: refused with the service's reason; a typed token and session connect,
        # and neither the typed token nor any earlier one is in the address or the tab's history
        await page.evaluate("sessionStorage.clear(); setTimeout(() => location.reload(), 0)")
        await page.wait_for("document.getElementById('status').dataset.state === 'refused'", "the refusal")
        assert "HTTP 401" in await page.evaluate(_text("status"))
        for field, value in (("session", "br2"), ("token", VIEWER)):
            await page.evaluate(f"document.getElementById('{field}').select()")
            await page.send("Input.insertText", {"text": value})
        for kind in ("keyDown", "keyUp"):
            await page.send("Input.dispatchKeyEvent", {"type": kind, "key": "Enter", "code": "Enter",
                                                       "windowsVirtualKeyCode": 13, "text": "\r"})
        await page.wait_for(_state("br2", "waiting"), "br2 waiting for a source")
        assert await page.evaluate("location.hash") == "#session=br2"
        assert all(VIEWER not in url for url in await _history_urls(page))

        # a new hash in the address bar reconnects to that session
        await page.navigate(f"{server.url}/viewer/#session=br1")
        await page.wait_for(_state("br1", "waiting"), "br1 after the hash changed")
        # (br2 never had a source, so it is no session: its waiting viewer left no entry behind)
        await page.wait_for("document.querySelector('#sessions li[data-session=\"br1\"]').textContent.includes(' 1 viewer,')"
                            " && document.querySelector('#sessions li[data-session=\"br2\"]') === null",
                            "br1 with one viewer and no br2", show="document.getElementById('sessions').textContent")
        assert page.exceptions() == []
        return shot


def test_the_viewer_in_chromium_shows_a_live_glove(server, chromium, tmp_path):
    shot = asyncio.run(_scenario(server, chromium, tmp_path))
    assert shot.startswith(b"\x89PNG")
    (tmp_path / "viewer.png").write_bytes(shot)
    if os.environ.get("FINGERTRACK_VIEWER_SCREENSHOT"):
        shutil.copyfile(tmp_path / "viewer.png", os.environ["FINGERTRACK_VIEWER_SCREENSHOT"])


def test_the_index_leads_to_the_viewer_and_the_docs(server, chromium, tmp_path):
    async def run():
        async with Browser(chromium, tmp_path / "profile") as browser:
            page = await browser.new_page()
            await page.navigate(server.url + "/")
            links = await page.wait_for("document.links.length >= 2 && [...document.links].map((a) => a.pathname)", "links")
            assert "/viewer/" in links and "/docs" in links
            # clicked once this evaluation has returned: the navigation then cannot cut it off
            await page.evaluate("setTimeout(() => [...document.links].find((a) => a.pathname === '/viewer/').click(), 0)")
            await page.wait_for("location.pathname === '/viewer/' && document.getElementById('status')"
                                " && document.getElementById('current').textContent === 'default'", "the viewer on session default")
    asyncio.run(run())

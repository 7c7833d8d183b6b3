"""A minimal Chrome DevTools Protocol driver for the browser tests: starts the system's Chromium
headless on a loopback debugging port (no browser is downloaded) and speaks CDP to it over the
``websockets`` package. Waits are for page states (a JavaScript condition polled inside the page),
with a generous deadline only as a guard against a hung test."""
from __future__ import annotations

import asyncio
import base64
import itertools
import json
import os
import re
import shutil
from pathlib import Path

from websockets.asyncio.client import connect

CHROMIUM_NAMES = ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable")
LISTENING = re.compile(r"DevTools listening on (ws://\S+)")
GUARD_S = 120.0
"""Deadline of any single wait: only a guard, far above what a loaded machine needs."""


def find_chromium() -> str | None:
    """The Chromium executable: ``FINGERTRACK_CHROMIUM`` if set, else the first on PATH."""
    if os.environ.get("FINGERTRACK_CHROMIUM"):
        return shutil.which(os.environ["FINGERTRACK_CHROMIUM"])
    return next((p for p in map(shutil.which, CHROMIUM_NAMES) if p), None)


class CdpError(RuntimeError):
    pass


class Browser:
    """``async with Browser(exe, profile_dir) as b: page = await b.new_page(url)``."""

    def __init__(self, exe: str, profile_dir: Path, width: int = 1280, height: int = 820):
        self.exe, self.profile_dir, self.size = exe, profile_dir, (width, height)
        self.stderr: list[str] = []
        self._ids = itertools.count(1)
        self._pending: dict[int, asyncio.Future] = {}
        self._events: dict[str, list[dict]] = {}

    async def __aenter__(self) -> "Browser":
        self.proc = await asyncio.create_subprocess_exec(
            self.exe, "--headless", "--no-sandbox", "--disable-gpu", "--no-first-run", "--no-default-browser-check",
            "--remote-debugging-address=127.0.0.1", "--remote-debugging-port=0", f"--user-data-dir={self.profile_dir}",
            "--disable-background-timer-throttling", "--disable-renderer-backgrounding",
            "--disable-backgrounding-occluded-windows", f"--window-size={self.size[0]},{self.size[1]}", "about:blank",
            stdin=asyncio.subprocess.DEVNULL, stdout=asyncio.subprocess.DEVNULL, stderr=asyncio.subprocess.PIPE)
        try:
            url = await asyncio.wait_for(self._endpoint(), GUARD_S)
        except BaseException:
            await self._stop()
            raise
        self._drain = asyncio.create_task(self._drain_stderr())
        self.ws = await connect(url, max_size=64 * 2**20)
        self._reader = asyncio.create_task(self._read())
        return self

    async def __aexit__(self, *exc) -> None:
        self._reader.cancel()
        await self.ws.close()
        await self._stop()
        self._drain.cancel()

    async def _stop(self) -> None:
        if self.proc.returncode is None:
            self.proc.terminate()
            try:
                await asyncio.wait_for(self.proc.wait(), 20)
            except asyncio.TimeoutError:
                self.proc.kill()
                await self.proc.wait()

    async def _endpoint(self) -> str:
        while True:
            line = (await self.proc.stderr.readline()).decode(errors="replace")
            if not line:
                raise CdpError("Chromium exited before opening its debugging port:\n" + "".join(self.stderr[-20:]))
            self.stderr.append(line)
            m = LISTENING.search(line)
            if m:
                return m.group(1)

    async def _drain_stderr(self) -> None:
        while line := await self.proc.stderr.readline():
            self.stderr.append(line.decode(errors="replace"))

    async def _read(self) -> None:
        async for raw in self.ws:
            msg = json.loads(raw)
            if "id" in msg:
                fut = self._pending.pop(msg["id"], None)
                if fut is not None and not fut.done():
                    if "error" in msg:
                        fut.set_exception(CdpError(f"{msg['error'].get('message')} ({msg['error'].get('data', '')})"))
                    else:
                        fut.set_result(msg.get("result", {}))
            else:
                self._events.setdefault(msg["method"], []).append(msg)

    async def send(self, method: str, params: dict | None = None, session: str | None = None) -> dict:
        i = next(self._ids)
        fut = asyncio.get_running_loop().create_future()
        self._pending[i] = fut
        msg = {"id": i, "method": method, "params": params or {}}
        if session:
            msg["sessionId"] = session
        await self.ws.send(json.dumps(msg))
        return await asyncio.wait_for(fut, GUARD_S)

    def events(self, method: str) -> list[dict]:
        return self._events.get(method, [])

    async def new_page(self, init_script: str = "") -> "Page":
        target = (await self.send("Target.createTarget", {"url": "about:blank"}))["targetId"]
        session = (await self.send("Target.attachToTarget", {"targetId": target, "flatten": True}))["sessionId"]
        page = Page(self, session)
        for domain in ("Page", "Runtime"):
            await page.send(f"{domain}.enable")
        await page.send("Emulation.setDeviceMetricsOverride",
                        {"width": self.size[0], "height": self.size[1], "deviceScaleFactor": 1, "mobile": False})
        if init_script:
            await page.send("Page.addScriptToEvaluateOnNewDocument", {"source": init_script})
        return page


class Page:
    def __init__(self, browser: Browser, session: str):
        self.browser, self.session = browser, session

    async def send(self, method: str, params: dict | None = None) -> dict:
        return await self.browser.send(method, params, self.session)

    async def navigate(self, url: str) -> None:
        result = await self.send("Page.navigate", {"url": url})
        if result.get("errorText"):
            raise CdpError(f"cannot open {url}: {result['errorText']}")

    async def evaluate(self, expression: str):
        """The value of a JavaScript expression (a promise is awaited); a page exception raises."""
        r = await self.send("Runtime.evaluate", {"expression": expression, "awaitPromise": True, "returnByValue": True})
        if "exceptionDetails" in r:
            d = r["exceptionDetails"]
            raise CdpError(f"{expression!r} threw: {d.get('exception', {}).get('description') or d.get('text')}")
        return r["result"].get("value")

    async def wait_for(self, condition: str, what: str, show: str = "document.body.innerText"):
        """Waits until the JavaScript expression ``condition`` is truthy in the page and returns its
        value; after the guard deadline fails naming ``what`` and showing ``show``'s value."""
        poll = f"new Promise((resolve) => {{ const check = () => {{ let v; try {{ v = ({condition}); }} catch (e) {{ v = null; }}" \
               f" if (v) resolve(v); else setTimeout(check, 25); }}; check(); }})"
        async def until():
            while True:
                try:
                    return await self.evaluate(poll)
                except CdpError as err:              # the page navigated meanwhile: ask the new one
                    if not any(w in str(err).lower() for w in ("context", "navigated")):
                        raise

        try:
            return await asyncio.wait_for(until(), GUARD_S)
        except asyncio.TimeoutError:
            raise AssertionError(f"the page never showed {what}; it shows:\n{await self.evaluate(show)}") from None

    async def screenshot(self) -> bytes:
        return base64.b64decode((await self.send("Page.captureScreenshot", {"format": "png"}))["data"])

    def exceptions(self) -> list[str]:
        """Uncaught exceptions and console errors of this page so far."""
        out = [e["params"]["exceptionDetails"].get("exception", {}).get("description", e["params"]["exceptionDetails"]["text"])
               for e in self.browser.events("Runtime.exceptionThrown") if e.get("sessionId") == self.session]
        out += [" ".join(str(a.get("value", a.get("description", ""))) for a in e["params"]["args"])
                for e in self.browser.events("Runtime.consoleAPICalled")
                if e.get("sessionId") == self.session and e["params"]["type"] in ("error", "assert")]
        return out

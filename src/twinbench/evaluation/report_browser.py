"""Open an HTML page in headless Chromium over the DevTools protocol: console errors, image/video load
state and a full-page screenshot. Uses only the `websockets` package (no browser-automation deps)."""

from __future__ import annotations

import base64
import itertools
import json
import os
import shutil
import subprocess
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

CHROMIUM = "/usr/bin/chromium"
CHROMIUM_FLAGS = ("--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                  "--disable-background-networking", "--disable-component-update", "--disable-sync",
                  "--disable-dev-shm-usage", "--mute-audio", "--hide-scrollbars", "--remote-debugging-port=0")

# Waits for every <video> to load its first frame (or fail, or time out); reports every <img> and <video>.
_MEDIA_JS = """
(async () => {
  const vids = Array.from(document.querySelectorAll('video'));
  await Promise.all(vids.map(v => v.readyState >= 2 || v.error ? null : new Promise(res => {
    v.addEventListener('loadeddata', res, {once: true});
    v.addEventListener('error', res, {once: true});
    setTimeout(res, %d);
  })));
  return JSON.stringify({
    images: Array.from(document.images).map(i => ({alt: i.alt, complete: i.complete,
                                                   naturalWidth: i.naturalWidth})),
    videos: vids.map(v => ({readyState: v.readyState, error: v.error ? v.error.code : null,
                            videoWidth: v.videoWidth, duration: v.duration})),
    title: document.title,
    height: document.documentElement.scrollHeight,
  });
})()
"""


@dataclass
class PageCheck:
    """What the browser saw: console errors/exceptions, per-image and per-video state."""

    errors: list[str] = field(default_factory=list)
    images: list[dict] = field(default_factory=list)
    videos: list[dict] = field(default_factory=list)
    title: str = ""
    height: int = 0


class _Cdp:
    """Minimal DevTools-protocol session over one browser websocket (flattened target sessions)."""

    def __init__(self, ws_url: str, timeout_s: float):
        from websockets.sync.client import connect

        self._conn = connect(ws_url, max_size=None, open_timeout=timeout_s)
        self.ws = self._conn.__enter__()
        self.timeout_s = timeout_s
        self.ids = itertools.count(1)
        self.events: list[dict] = []

    def call(self, method: str, session: str | None = None, **params) -> dict:
        msg_id = next(self.ids)
        msg = {"id": msg_id, "method": method, "params": params}
        if session:
            msg["sessionId"] = session
        self.ws.send(json.dumps(msg))
        deadline = time.monotonic() + self.timeout_s
        while True:
            reply = json.loads(self.ws.recv(timeout=max(0.01, deadline - time.monotonic())))
            if reply.get("id") == msg_id:
                if "error" in reply:
                    raise RuntimeError(f"DevTools {method} failed: {reply['error']}")
                return reply.get("result", {})
            self.events.append(reply)

    def wait_event(self, method: str, timeout_s: float) -> dict | None:
        for ev in self.events:
            if ev.get("method") == method:
                return ev
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            try:
                ev = json.loads(self.ws.recv(timeout=max(0.01, deadline - time.monotonic())))
            except TimeoutError:
                break
            self.events.append(ev)
            if ev.get("method") == method:
                return ev
        return None

    def close(self) -> None:
        self._conn.__exit__(None, None, None)


def check_page(html_path: str | Path, screenshot: str | Path | None = None, *, width: int = 1280,
               timeout_s: float = 30.0, chromium: str = CHROMIUM) -> PageCheck:
    """Load `html_path` in headless Chromium; return console errors and media state, and save a
    full-page PNG screenshot when `screenshot` is given. Raises FileNotFoundError without Chromium."""
    if not Path(chromium).exists():
        raise FileNotFoundError(f"{chromium} not found; install it with `apt-get install -y chromium`")
    url = Path(html_path).resolve().as_uri()
    profile = tempfile.mkdtemp(prefix="twinbench-chromium-")
    proc = subprocess.Popen([chromium, *CHROMIUM_FLAGS, f"--user-data-dir={profile}", "about:blank"],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    cdp = None
    try:
        port_file = Path(profile) / "DevToolsActivePort"
        deadline = time.monotonic() + timeout_s
        while not (port_file.exists() and len(port_file.read_text().splitlines()) >= 2):
            if proc.poll() is not None:
                raise RuntimeError(f"{chromium} exited with code {proc.returncode} before DevTools started")
            if time.monotonic() > deadline:
                raise TimeoutError(f"{chromium} did not open a DevTools port within {timeout_s} s")
            time.sleep(0.05)
        port, ws_path = port_file.read_text().splitlines()[:2]
        cdp = _Cdp(f"ws://127.0.0.1:{port}{ws_path}", timeout_s)
        target = cdp.call("Target.createTarget", url="about:blank")["targetId"]
        sid = cdp.call("Target.attachToTarget", targetId=target, flatten=True)["sessionId"]
        for domain in ("Page", "Runtime", "Log"):
            cdp.call(f"{domain}.enable", sid)
        cdp.call("Emulation.setDeviceMetricsOverride", sid, width=width, height=900, deviceScaleFactor=1,
                 mobile=False)
        cdp.call("Page.navigate", sid, url=url)
        if cdp.wait_event("Page.loadEventFired", timeout_s) is None:
            raise TimeoutError(f"{url} did not finish loading within {timeout_s} s")
        res = cdp.call("Runtime.evaluate", sid, expression=_MEDIA_JS % int(timeout_s * 500),
                       awaitPromise=True, returnByValue=True)
        if "exceptionDetails" in res:
            raise RuntimeError(f"media check script failed: {res['exceptionDetails']}")
        state = json.loads(res["result"]["value"])
        if screenshot is not None:
            height = max(1, int(state["height"]))
            shot = cdp.call("Page.captureScreenshot", sid, format="png", captureBeyondViewport=True,
                            clip={"x": 0, "y": 0, "width": width, "height": height, "scale": 1})
            Path(screenshot).write_bytes(base64.b64decode(shot["data"]))
        cdp.wait_event("__drain__", 0.2)  # collect late console events
        errors = []
        for ev in cdp.events:
            method, params = ev.get("method"), ev.get("params", {})
            if method == "Runtime.consoleAPICalled" and params.get("type") in ("error", "assert"):
                errors.append("console: " + " ".join(str(a.get("value", a.get("description", "")))
                                                     for a in params.get("args", [])))
            elif method == "Runtime.exceptionThrown":
                det = params.get("exceptionDetails", {})
                desc = det.get("exception", {}).get("description", det.get("text", ""))
                errors.append(f"exception: {desc}")
            elif method == "Log.entryAdded" and params.get("entry", {}).get("level") == "error":
                entry = params["entry"]
                errors.append(f"log[{entry.get('source')}]: {entry.get('text')} {entry.get('url', '')}")
        return PageCheck(errors=errors, images=state["images"], videos=state["videos"],
                         title=state["title"], height=int(state["height"]))
    finally:
        if cdp is not None:
            try:
                cdp.call("Browser.close")
            except Exception:  # noqa: BLE001 - the browser may already be gone
                pass
            cdp.close()
        try:
            proc.wait(timeout=5)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, 9)
            proc.wait()
        shutil.rmtree(profile, ignore_errors=True)

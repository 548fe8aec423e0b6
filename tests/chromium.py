"""Headless Chromium for page tests, driven over the DevTools protocol on a pipe (no network port).

``open_page`` starts Chromium with WebGL on SwiftShader (software; no GPU needed), opens a URL,
waits until the page's title says ``ready`` (or fails with the page's error), and hands back a
``Tab`` that evaluates JavaScript and takes screenshots as ``(H, W, 3)`` uint8 arrays.
"""
from __future__ import annotations

import base64
import contextlib
import fcntl
import io
import json
import os
import select
import shutil
import subprocess
import time
from pathlib import Path
from typing import Iterator

import numpy as np
from PIL import Image

FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
         "--disable-background-networking", "--disable-component-update", "--disable-sync", "--no-first-run",
         "--no-default-browser-check", "--mute-audio", "--remote-debugging-pipe"]


def find_chromium() -> str | None:
    for name in ("chromium", "chromium-browser", "google-chrome"):
        if path := shutil.which(name):
            return path
    return None


class Tab:
    def __init__(self, to_browser: int, from_browser: int, timeout: float) -> None:
        self._w, self._r, self.timeout = to_browser, from_browser, timeout
        self._buf = b""
        self._id = 0
        self.session: str | None = None

    def call(self, method: str, params: dict | None = None, browser: bool = False) -> dict:
        self._id += 1
        msg = {"id": self._id, "method": method, "params": params or {}}
        if not browser and self.session:
            msg["sessionId"] = self.session
        os.write(self._w, json.dumps(msg).encode() + b"\0")
        deadline = time.time() + self.timeout
        while True:
            while b"\0" not in self._buf:
                left = deadline - time.time()
                if left <= 0 or not select.select([self._r], [], [], left)[0]:
                    raise TimeoutError(f"Chromium did not answer {method} in {self.timeout} s")
                chunk = os.read(self._r, 1 << 20)
                if not chunk:
                    raise RuntimeError("Chromium closed the DevTools pipe")
                self._buf += chunk
            raw, self._buf = self._buf.split(b"\0", 1)
            reply = json.loads(raw)
            if reply.get("id") == self._id:                                  # events are skipped
                if "error" in reply:
                    raise RuntimeError(f"{method}: {reply['error']}")
                return reply.get("result", {})

    def evaluate(self, expression: str):
        res = self.call("Runtime.evaluate", {"expression": expression, "awaitPromise": True, "returnByValue": True})
        if "exceptionDetails" in res:
            raise RuntimeError(f"{expression}: {res['exceptionDetails']}")
        return res["result"].get("value")

    def wait_title(self, ready: str, failed: str, timeout: float) -> str:
        deadline = time.time() + timeout
        title = ""
        while time.time() < deadline:
            title = self.evaluate("document.title") or ""
            if title.startswith(ready):
                return title
            if title.startswith(failed):
                raise AssertionError(f"the page failed: {title}")
            time.sleep(0.25)
        raise TimeoutError(f"the page was not ready in {timeout} s (title: {title!r})")

    def screenshot(self) -> np.ndarray:
        self.evaluate("new Promise(r => requestAnimationFrame(() => requestAnimationFrame(() => r(0))))")
        data = self.call("Page.captureScreenshot", {"format": "png"})["data"]
        return np.asarray(Image.open(io.BytesIO(base64.b64decode(data))).convert("RGB"))


def _pipe() -> tuple[int, int]:
    """``os.pipe()`` with both ends numbered 10 or more, clear of the 3 and 4 the child needs."""
    ends = []
    for fd in os.pipe():
        ends.append(fcntl.fcntl(fd, fcntl.F_DUPFD_CLOEXEC, 10))
        os.close(fd)
    return ends[0], ends[1]


@contextlib.contextmanager
def open_page(chromium: str, url: str, profile: Path, size: tuple[int, int] = (640, 480),
              ready: str = "nefii view: ready", failed: str = "nefii view: error", timeout: float = 120.0
              ) -> Iterator[Tab]:
    cmd_r, cmd_w = _pipe()                                                  # we write, Chromium reads fd 3
    out_r, out_w = _pipe()                                                  # Chromium writes fd 4, we read
    # bash (dash takes single-digit fds only) puts the pipe ends where --remote-debugging-pipe wants them,
    # then becomes Chromium
    shell = f'exec "$0" "$@" 3<&{cmd_r} 4>&{out_w} {cmd_r}<&- {out_w}>&-'
    proc = subprocess.Popen(["bash", "-c", shell, chromium, *FLAGS, f"--user-data-dir={profile}",
                             f"--window-size={size[0]},{size[1]}", "about:blank"], pass_fds=(cmd_r, out_w),
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    os.close(cmd_r)
    os.close(out_w)
    tab = Tab(cmd_w, out_r, timeout)
    try:
        target = tab.call("Target.createTarget", {"url": "about:blank"},
                          browser=True)["targetId"]
        tab.session = tab.call("Target.attachToTarget", {"targetId": target, "flatten": True},
                               browser=True)["sessionId"]
        tab.call("Emulation.setDeviceMetricsOverride",
                 {"width": size[0], "height": size[1], "deviceScaleFactor": 1, "mobile": False})
        tab.call("Page.navigate", {"url": url})
        tab.wait_title(ready, failed, timeout)
        yield tab
    finally:
        with contextlib.suppress(Exception):
            tab.call("Browser.close", browser=True)
        try:
            proc.wait(timeout=20)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
        os.close(cmd_w)
        os.close(out_r)

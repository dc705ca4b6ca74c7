"""Drive headless Debian chromium over the DevTools protocol on a pipe (``--remote-debugging-pipe``).

No websocket client or browser-automation package is needed: chromium reads NUL-separated JSON commands from
fd 3 and writes replies to fd 4. The child is started with ``os.posix_spawn`` so the two pipe ends land on
fds 3 and 4 without a ``preexec_fn`` (unsafe in a process that runs Zenoh threads).
"""

from __future__ import annotations

import base64
import io
import json
import os
import shutil
import signal
import tempfile
import threading
import time
from concurrent.futures import Future
from typing import Any

import numpy as np

CHROMIUM_NAMES = ("chromium", "chromium-browser")


def find_chromium() -> str | None:
    """The Debian chromium binary, or None (the page tests then skip)."""
    for name in CHROMIUM_NAMES:
        path = shutil.which(name)
        if path:
            return path
    return None


class CDPError(RuntimeError):
    pass


class Chromium:
    """One headless chromium with one page target, sized ``width`` × ``height`` CSS px at scale 1."""

    def __init__(self, binary: str, width: int = 1280, height: int = 800) -> None:
        self.width, self.height = width, height
        self._profile = tempfile.mkdtemp(prefix="jg-chromium-")
        to_child_r, self._to_child = os.pipe()
        self._from_child, from_child_w = os.pipe()
        devnull = os.open(os.devnull, os.O_RDWR)
        argv = [binary, "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                "--disable-background-networking", "--disable-component-update", "--disable-sync",
                "--disable-dev-shm-usage", "--hide-scrollbars", "--mute-audio", "--force-device-scale-factor=1",
                f"--user-data-dir={self._profile}", f"--window-size={width},{height}",
                "--remote-debugging-pipe", "about:blank"]
        actions = [(os.POSIX_SPAWN_DUP2, to_child_r, 3), (os.POSIX_SPAWN_DUP2, from_child_w, 4),
                   (os.POSIX_SPAWN_DUP2, devnull, 0), (os.POSIX_SPAWN_DUP2, devnull, 1),
                   (os.POSIX_SPAWN_DUP2, devnull, 2)]
        self.pid = os.posix_spawn(binary, argv, os.environ, file_actions=actions)
        for fd in (to_child_r, from_child_w, devnull):
            os.close(fd)
        self._ids = iter(range(1, 1 << 30))
        self._pending: dict[int, Future] = {}
        self._lock = threading.Lock()
        self.events: list[dict[str, Any]] = []
        self._reader = threading.Thread(target=self._read, name="cdp-reader", daemon=True)
        self._reader.start()
        target = self.call("Target.createTarget", {"url": "about:blank"})["targetId"]
        self.session = self.call("Target.attachToTarget", {"targetId": target, "flatten": True})["sessionId"]
        self.page("Emulation.setDeviceMetricsOverride",
                  {"width": width, "height": height, "deviceScaleFactor": 1, "mobile": False})
        self.page("Page.enable")
        self.page("Runtime.enable")

    # ------------------------------------------------------------------ protocol

    def _read(self) -> None:
        buf = b""
        while True:
            try:
                chunk = os.read(self._from_child, 1 << 16)
            except OSError:
                chunk = b""
            if not chunk:
                with self._lock:
                    for fut in self._pending.values():
                        fut.set_exception(CDPError("chromium closed the pipe"))
                    self._pending.clear()
                return
            buf += chunk
            while b"\0" in buf:
                raw, buf = buf.split(b"\0", 1)
                msg = json.loads(raw)
                if "id" in msg:
                    with self._lock:
                        fut = self._pending.pop(msg["id"], None)
                    if fut is not None:
                        if "error" in msg:
                            fut.set_exception(CDPError(f"{msg['error']}"))
                        else:
                            fut.set_result(msg.get("result", {}))
                else:
                    self.events.append(msg)

    def call(self, method: str, params: dict[str, Any] | None = None, session: str | None = None,
             timeout: float = 30.0) -> dict[str, Any]:
        msg: dict[str, Any] = {"id": next(self._ids), "method": method, "params": params or {}}
        if session:
            msg["sessionId"] = session
        fut: Future = Future()
        with self._lock:
            self._pending[msg["id"]] = fut
        os.write(self._to_child, json.dumps(msg).encode() + b"\0")
        return fut.result(timeout=timeout)

    def page(self, method: str, params: dict[str, Any] | None = None, timeout: float = 30.0) -> dict[str, Any]:
        return self.call(method, params, session=self.session, timeout=timeout)

    # ------------------------------------------------------------------ conveniences

    def navigate(self, url: str) -> None:
        self.page("Page.navigate", {"url": url})

    def eval(self, expression: str) -> Any:
        """Evaluate JS in the page; returns the value (JSON-able), raises on a JS exception."""
        r = self.page("Runtime.evaluate", {"expression": expression, "returnByValue": True, "awaitPromise": True})
        if "exceptionDetails" in r:
            raise CDPError(f"JS error: {r['exceptionDetails'].get('text')} "
                           f"{r['exceptionDetails'].get('exception', {}).get('description', '')}")
        return r.get("result", {}).get("value")

    def wait_js(self, expression: str, timeout: float = 20.0, period: float = 0.1) -> Any:
        """Poll a JS expression until truthy; returns its value (a bounded wait, not a timing check)."""
        deadline = time.monotonic() + timeout
        while True:
            value = self.eval(expression)
            if value:
                return value
            if time.monotonic() > deadline:
                raise TimeoutError(f"page never satisfied: {expression}")
            time.sleep(period)

    def screenshot(self) -> np.ndarray:
        """The viewport as an ``(H, W, 3)`` uint8 RGB array."""
        from PIL import Image

        data = base64.b64decode(self.page("Page.captureScreenshot", {"format": "png"})["data"])
        return np.asarray(Image.open(io.BytesIO(data)).convert("RGB"))

    def screenshot_png(self, path: str) -> None:
        data = base64.b64decode(self.page("Page.captureScreenshot", {"format": "png"})["data"])
        with open(path, "wb") as f:
            f.write(data)

    def mouse(self, kind: str, x: float, y: float) -> None:
        params: dict[str, Any] = {"type": kind, "x": x, "y": y}
        if kind in ("mousePressed", "mouseReleased"):
            params.update(button="left", clickCount=1)
        self.page("Input.dispatchMouseEvent", params)

    def click(self, x: float, y: float) -> None:
        self.mouse("mouseMoved", x, y)
        self.mouse("mousePressed", x, y)
        self.mouse("mouseReleased", x, y)

    def click_element(self, selector: str) -> None:
        """Click the centre of the element matched by ``selector`` with real mouse events."""
        box = self.eval(f"(() => {{ const r = document.querySelector({json.dumps(selector)}).getBoundingClientRect();"
                        f" return [r.left + r.width / 2, r.top + r.height / 2]; }})()")
        self.click(box[0], box[1])

    def type_into(self, selector: str, text: str) -> None:
        """Focus an input by clicking it, select its content and type ``text`` (real input events)."""
        self.click_element(selector)
        self.eval(f"document.querySelector({json.dumps(selector)}).select()")
        self.page("Input.insertText", {"text": text})

    def close(self) -> None:
        try:
            self.call("Browser.close", timeout=5)
        except Exception:
            pass
        deadline = time.monotonic() + 5
        while time.monotonic() < deadline:
            pid, _ = os.waitpid(self.pid, os.WNOHANG)
            if pid:
                break
            time.sleep(0.05)
        else:
            os.kill(self.pid, signal.SIGKILL)
            os.waitpid(self.pid, 0)
        for fd in (self._to_child, self._from_child):
            try:
                os.close(fd)
            except OSError:
                pass
        shutil.rmtree(self._profile, ignore_errors=True)

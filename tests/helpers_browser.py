"""Headless Chromium (Debian package) driven over the DevTools protocol, for the viewer's browser tests."""

from __future__ import annotations

import base64
import json
import re
import shutil
import subprocess
import threading
import urllib.request

import cv2
import numpy as np
import websockets.sync.client

CHROMIUM = next((shutil.which(name) for name in ("chromium", "chromium-browser", "google-chrome") if shutil.which(name)), None)


class DevToolsPage:
    """One Chromium page driven over the DevTools protocol (only what the test needs)."""

    def __init__(self, profile_dir: str, width: int = 1200, height: int = 800):
        self.process = subprocess.Popen(
            [CHROMIUM, "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
             "--disable-background-networking", "--disable-component-update", "--disable-sync",
             f"--user-data-dir={profile_dir}", "--remote-debugging-port=0", f"--window-size={width},{height}",
             "about:blank"],
            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
        )
        endpoint = self._devtools_endpoint(timeout=60.0)
        pages = json.load(urllib.request.urlopen(f"http://{endpoint}/json/list", timeout=10))
        target = next(page for page in pages if page["type"] == "page")
        self.socket = websockets.sync.client.connect(target["webSocketDebuggerUrl"], max_size=None)
        self._next_id = 0

    def _devtools_endpoint(self, timeout: float) -> str:
        found: list[str] = []
        ready = threading.Event()

        def read_stderr() -> None:  # keep draining: Chromium logs a lot and would block on a full pipe
            for line in self.process.stderr:
                match = re.search(r"DevTools listening on ws://([^/\s]+)/", line)
                if match and not found:
                    found.append(match.group(1))
                    ready.set()

        threading.Thread(target=read_stderr, daemon=True).start()
        if not ready.wait(timeout):
            raise RuntimeError("Chromium did not start its DevTools endpoint")
        return found[0]

    def call(self, method: str, **params):
        self._next_id += 1
        self.socket.send(json.dumps({"id": self._next_id, "method": method, "params": params}))
        while True:
            reply = json.loads(self.socket.recv(timeout=60))
            if reply.get("id") == self._next_id:
                if "error" in reply:
                    raise RuntimeError(f"{method}: {reply['error']}")
                return reply["result"]

    def screenshot(self) -> np.ndarray:
        png = base64.b64decode(self.call("Page.captureScreenshot", format="png")["data"])
        return cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)[..., ::-1]

    def close(self) -> None:
        self.socket.close()
        self.process.terminate()
        try:
            self.process.wait(timeout=10)
        except subprocess.TimeoutExpired:
            self.process.kill()
            self.process.wait()

    def evaluate(self, expression: str):
        """The value of a JavaScript expression in the page."""
        result = self.call("Runtime.evaluate", expression=expression, returnByValue=True)
        if "exceptionDetails" in result:
            raise RuntimeError(f"page script failed: {result['exceptionDetails']}")
        return result["result"].get("value")

    def click_text(self, label: str) -> bool:
        """Click the last element whose own text is ``label`` (a GUI button or folder title; the click
        reaches its handler by bubbling); False when the page shows none."""
        return bool(self.evaluate(
            "(() => { const hits = [...document.querySelectorAll('body *')].filter(e => [...e.childNodes].some("
            f"n => n.nodeType === 3 && n.textContent.trim() === {json.dumps(label)})); if (!hits.length) return false;"
            " hits[hits.length - 1].click(); return true; })()"))

"""A real headless Chromium (the system's package) driven over the Chrome DevTools Protocol on a pipe
(``--remote-debugging-pipe``: JSON messages ending in NUL on file descriptors 3 and 4), standard library only."""

from __future__ import annotations

import base64
import fcntl
import json
import os
import select
import shutil
import subprocess
import time
from pathlib import Path

NAMES = ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable")
# WebGL/WebGPU without a GPU: SwiftShader, Chromium's software renderer
FLAGS = ("--headless=new", "--no-sandbox", "--no-first-run", "--no-default-browser-check", "--disable-gpu-sandbox",
         "--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--disable-dev-shm-usage")


def find_chromium() -> str | None:
    """A Chromium binary: $EBRL_CHROMIUM, or one of NAMES on PATH."""
    exe = os.environ.get("EBRL_CHROMIUM")
    return exe if exe and os.path.exists(exe) else next(filter(None, map(shutil.which, NAMES)), None)


def _child_fds(read_fd: int, write_fd: int) -> None:
    """In the child: the pipe ends as fds 3 (commands in) and 4 (replies out), by way of high numbers first
    so that neither overwrites the other."""
    high_read, high_write = fcntl.fcntl(read_fd, fcntl.F_DUPFD, 100), fcntl.fcntl(write_fd, fcntl.F_DUPFD, 100)
    os.dup2(high_read, 3)
    os.dup2(high_write, 4)


class Chromium:
    """One headless browser with one page; :meth:`send` a CDP command to the page, get its result."""

    def __init__(self, exe: str, profile: Path, width: int = 1600, height: int = 1000):
        to_child, self._out = os.pipe()
        self._in, from_child = os.pipe()
        self.log = profile.with_suffix(".log")
        with open(self.log, "wb") as log:
            self.proc = subprocess.Popen(
                [exe, *FLAGS, f"--user-data-dir={profile}", f"--window-size={width},{height}",
                 "--remote-debugging-pipe", "about:blank"],
                stdin=subprocess.DEVNULL, stdout=log, stderr=log, pass_fds=(3, 4),
                preexec_fn=lambda: _child_fds(to_child, from_child))
        os.close(to_child)
        os.close(from_child)
        self._buf, self._id, self.session = b"", 0, None
        targets = self.send("Target.getTargets")["targetInfos"]
        page = next(t["targetId"] for t in targets if t["type"] == "page")
        self.session = self.send("Target.attachToTarget", targetId=page, flatten=True)["sessionId"]

    def send(self, method: str, timeout: float = 120.0, **params):
        self._id += 1
        message = {"id": self._id, "method": method, "params": params}
        if self.session and not method.startswith("Target."):
            message["sessionId"] = self.session
        os.write(self._out, json.dumps(message).encode() + b"\0")
        deadline = time.monotonic() + timeout
        while True:
            while b"\0" not in self._buf:
                left = deadline - time.monotonic()
                if left <= 0 or not select.select([self._in], [], [], left)[0]:
                    raise TimeoutError(f"chromium did not answer {method} within {timeout:.0f} s")
                chunk = os.read(self._in, 1 << 20)
                if not chunk:
                    raise RuntimeError(f"chromium exited (code {self.proc.poll()}); its log: {self.log}")
                self._buf += chunk
            raw, self._buf = self._buf.split(b"\0", 1)
            reply = json.loads(raw)
            if reply.get("id") == self._id:  # events (no id) are dropped
                if "error" in reply:
                    raise RuntimeError(f"{method}: {reply['error']}")
                return reply["result"]

    def evaluate(self, expression: str):
        return self.send("Runtime.evaluate", expression=expression, returnByValue=True)["result"].get("value")

    def screenshot(self, path: Path, clip: tuple[int, int, int, int] | None = None) -> Path:
        """A PNG of the page (or of ``clip`` = x, y, width, height in CSS pixels) written to ``path``."""
        params = {"format": "png"}
        if clip:
            params["clip"] = dict(zip(("x", "y", "width", "height"), clip), scale=1)
        path.write_bytes(base64.b64decode(self.send("Page.captureScreenshot", **params)["data"]))
        return path

    def close(self) -> None:
        try:
            self.send("Browser.close", timeout=10)
        except (RuntimeError, TimeoutError, OSError):
            pass
        try:
            self.proc.wait(10)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
        os.close(self._in)
        os.close(self._out)


# --- what rerun's web viewer holds ---------------------------------------------------------------------------

# Epoch nanoseconds between 2001 and 2065: the times of a recording's timelines (wall, log_time) in a viewer's
# state, told apart from the state's other integers (counts, enums, lengths) by their size alone.
_EPOCH_NS = (10 ** 18, 3 * 10 ** 18)


def _varint(data: bytes, i: int) -> tuple[int, int]:
    value = shift = 0
    while True:
        byte = data[i]
        i += 1
        value |= (byte & 0x7F) << shift
        shift += 7
        if byte < 0x80:
            return value, i


def _epoch_times(data: bytes, out: list[int]) -> list[int]:
    """Every varint of protobuf message ``data`` (its nested messages too) that reads as epoch nanoseconds.
    Raises ValueError where ``data`` is not a protobuf message (a string field is then skipped by the caller)."""
    i = 0
    while i < len(data):
        key, i = _varint(data, i)
        wire = key & 7
        if wire == 0:
            value, i = _varint(data, i)
            if _EPOCH_NS[0] < value < _EPOCH_NS[1]:
                out.append(value)
        elif wire == 1:
            i += 8
        elif wire == 5:
            i += 4
        elif wire == 2:
            size, i = _varint(data, i)
            found: list[int] = []
            try:
                out.extend(_epoch_times(data[i:i + size], found))
            except (ValueError, IndexError):
                pass  # a string or bytes field
            i += size
        else:
            raise ValueError(f"wire type {wire}")
    if i != len(data):
        raise ValueError("truncated")
    return out


def newest_time(page: Chromium) -> float | None:
    """The newest time (epoch seconds) of the data rerun's web viewer on ``page`` holds: the end of its
    recordings' timelines, read from its Viewer Control state (``window._handle.viewer_state()``, the encoded
    ``GetStateResponse`` that rerun's page exposes); None before the viewer has started or received anything.
    ``time.time() - newest_time(page)`` is how far behind the run the page is (what its "latency" readout says)."""
    state = page.evaluate("window._handle && window._handle.viewer_state ? "
                          "Array.from(window._handle.viewer_state()) : null")
    if not state:
        return None
    times = _epoch_times(bytes(state), [])
    return max(times) / 1e9 if times else None

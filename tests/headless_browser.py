"""Screenshots of a web page in headless Chromium (Debian's `chromium`), driven over the DevTools protocol.

Chromium's own `--screenshot` fires on virtual time, before a page that waits on a websocket (viser's viewer waits
for rendered frames) has drawn anything, so the page is opened with `--remote-debugging-port` instead and the
screenshot is taken once the server says it has sent what the page should show and the page says it shows it.
WebGL runs in software (SwiftShader) with `--disable-gpu`.

    python tests/headless_browser.py RUN_OR_PLY OUT.png    # the README's viewer screenshot
"""

from __future__ import annotations

import base64
import itertools
import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
import urllib.request
from pathlib import Path
from typing import Callable

import numpy as np
from websockets.sync.client import connect

CHROMIUM_FLAGS = ("--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                  "--disable-background-networking", "--disable-component-update", "--disable-sync",
                  "--remote-debugging-port=0")

# Whether viser's page shows a background image as large as its canvas, read from the client state that viser
# exposes for end-to-end tests. The canvas also has to be opaque: viser keeps it at 5% opacity until its environment
# map is decoded, then fades it in over 5 frames, which in software WebGL on a busy machine ends seconds after the
# frame has arrived.
VISER_SHOWS_FULL_FRAME = """(() => {
    const viewer = window.__viserMutable;
    const image = viewer?.backgroundMaterial?.uniforms.colorMap.value?.image;
    return image !== undefined && image.width === viewer.canvas.width && image.height === viewer.canvas.height
        && getComputedStyle(viewer.canvas).opacity === "1";
})()"""


def find_chromium() -> str | None:
    """The Chromium binary, or None."""
    return shutil.which("chromium") or shutil.which("chromium-browser")


class DevTools:
    """One page's DevTools connection: `call(method, **params)` returns the command's result."""

    def __init__(self, websocket_url: str):
        self._socket = connect(websocket_url, max_size=None)
        self._ids = itertools.count(1)

    def call(self, method: str, **params) -> dict:
        command_id = next(self._ids)
        self._socket.send(json.dumps({"id": command_id, "method": method, "params": params}))
        while True:  # events arrive between the replies; skip them
            message = json.loads(self._socket.recv(timeout=60))
            if message.get("id") == command_id:
                if "error" in message:
                    raise RuntimeError(f"{method}: {message['error']}")
                return message["result"]

    def evaluate(self, expression: str):
        """The value of a JavaScript expression in the page."""
        result = self.call("Runtime.evaluate", expression=expression, returnByValue=True)
        if "exceptionDetails" in result:
            raise RuntimeError(f"{expression}: {result['exceptionDetails']}")
        return result["result"].get("value")

    def close(self) -> None:
        self._socket.close()


def _devtools_port(profile: Path, process: subprocess.Popen, timeout: float) -> int:
    port_file = profile / "DevToolsActivePort"
    deadline = time.monotonic() + timeout
    while not port_file.is_file() or not port_file.read_text().strip():
        if process.poll() is not None or time.monotonic() > deadline:
            raise RuntimeError(f"chromium did not open its DevTools port (exit code {process.poll()})")
        time.sleep(0.1)
    return int(port_file.read_text().split()[0])


def _stop_process_group(process: subprocess.Popen, timeout: float = 10.0) -> None:
    """Terminate the process group `process` leads and wait until none of its processes is left."""
    try:
        os.killpg(process.pid, signal.SIGTERM)
    except ProcessLookupError:  # the browser exited on its own, its helpers with it
        process.wait()
        return
    try:
        process.wait(timeout=timeout)
    except subprocess.TimeoutExpired:
        os.killpg(process.pid, signal.SIGKILL)
        process.wait()
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        try:
            os.killpg(process.pid, signal.SIGKILL)  # helpers that ignored SIGTERM
        except ProcessLookupError:
            return
        time.sleep(0.05)


def screenshot(url: str, out: Path, ready: Callable[[], bool], shown: str, size: tuple[int, int] = (800, 600),
               timeout: float = 60.0, script: str | None = None) -> Path:
    """Open `url` at `size`, wait until both `ready()` (the server's side) and the JavaScript expression `shown`
    (the page's side) are true, polled together; run `script` (JavaScript) if given and write a PNG screenshot to
    `out`.

    Raises:
        RuntimeError: no Chromium, or the two not both true after `timeout` seconds.
    """
    chromium = find_chromium()
    if chromium is None:
        raise RuntimeError("chromium is not installed (apt-get install chromium)")
    # Chromium's helper processes (renderer, GPU, crash handler) outlive the browser process by a moment and keep
    # writing to the profile: the whole process group is stopped before the profile is removed.
    with tempfile.TemporaryDirectory(prefix="chromium-") as profile:
        process = subprocess.Popen([chromium, *CHROMIUM_FLAGS, f"--user-data-dir={profile}", "about:blank"],
                                   stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
        try:
            port = _devtools_port(Path(profile), process, timeout)
            pages = json.load(urllib.request.urlopen(f"http://127.0.0.1:{port}/json/list", timeout=10))
            page = DevTools(next(p for p in pages if p["type"] == "page")["webSocketDebuggerUrl"])
            try:
                page.call("Emulation.setDeviceMetricsOverride", width=size[0], height=size[1],
                          deviceScaleFactor=1, mobile=False)
                page.call("Page.navigate", url=url)
                deadline = time.monotonic() + timeout
                while not (ready() and page.evaluate(shown) is True):
                    if time.monotonic() > deadline:
                        raise RuntimeError(f"{url} was not ready after {timeout:.0f} s")
                    time.sleep(0.1)
                if script is not None:
                    page.evaluate(script)
                    time.sleep(0.2)
                data = page.call("Page.captureScreenshot", format="png")["data"]
            finally:
                page.close()
        finally:
            _stop_process_group(process)
    out.write_bytes(base64.b64decode(data))
    return out


def initial_view_frame(viewer):
    """The full-resolution frame a browser's renderer rests on, seen from the viewer's initial camera, or None.

    A browser reports viser's default camera first and moves to the initial camera only once it has applied the
    server's settings, so a full-resolution frame can come from the default camera."""
    initial = viewer.server.initial_camera.position
    for renderer in list(viewer.renderers.values()):
        # at rest: full resolution, and showing the browser's current camera (no other follows until it moves)
        frame = renderer.last_frame
        at_rest = frame.full_resolution and frame.camera_time == renderer.client.camera.update_timestamp
        if at_rest and np.allclose(np.linalg.inv(frame.viewmat)[:3, 3], initial):  # the camera centre
            return frame
    return None


def _viewer_screenshot(path: str, out: str) -> None:
    """A screenshot of `warpbags view PATH`, with the browser's software-WebGL notice closed."""
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    from warpbags.viewer import Viewer, load_viewer_content  # noqa: PLC0415

    viewer = Viewer(load_viewer_content(path), port=0, device="cpu")
    try:
        close_notices = "document.querySelectorAll('.mantine-Notification-closeButton').forEach(b => b.click())"
        screenshot(viewer.url, Path(out), lambda: initial_view_frame(viewer) is not None, VISER_SHOWS_FULL_FRAME,
                   script=close_notices)
    finally:
        viewer.stop()


if __name__ == "__main__":
    _viewer_screenshot(*sys.argv[1:3])

"""`Viewer`: a viser web server that shows a run's Gaussians, rendered by warpbags, and its training cameras.

The scene holds the training cameras as frustums in three colours: the start (poses_start.npy, where the
optimization began), the optimized poses (with their images; a click on one moves the browser's camera there) and
the reference poses aligned to the model's frame. A slider replays the optimized poses over the run's pose history.
The Gaussians themselves are not scene nodes: each browser gets them as a background image rendered from its own
camera (`ClientRenderer`).
"""

from __future__ import annotations

import contextlib
import errno
import io
import socket
import sys
import threading
from typing import Callable

import numpy as np
import viser

from warpbags.errors import WarpbagsError
from warpbags.viewer.content import TrainingCameras, ViewerContent
from warpbags.viewer.render import ClientRenderer, DeviceGaussians, FrameStats, camera_to_world

FRUSTUM_COLORS = {"start": (225, 50, 60), "optimized": (30, 110, 230), "reference": (30, 160, 80)}
FRUSTUM_LABELS = {"start": "start, red", "optimized": "optimized, blue", "reference": "reference, green"}
FRUSTUM_SIZE = 0.08  # of the cameras' median distance to the object


PORTS_TRIED = 100  # from --port upward, as viser moves to the next port when one is busy


def listen_port(host: str, port: int) -> int:
    """The first port from `port` on (at most `PORTS_TRIED` of them) that a server can listen on at `host`; 0 stays 0
    (the system chooses). Viser, given a port out of range or an address it cannot bind, fails or retries in its
    server thread while its constructor waits for it forever: so the port is found here and handed to it.

    Raises:
        WarpbagsError: the port is not 0-65535, the host is unknown or not an address of this machine, or no port
            of the range can be listened on (all busy, or below 1024 without the right to).
    """
    if not 0 <= port <= 65535:
        raise WarpbagsError(f"--port must be 0-65535, got {port}")
    try:
        family, kind, protocol, _, address = socket.getaddrinfo(host, 0, type=socket.SOCK_STREAM)[0]
    except socket.gaierror as error:
        raise WarpbagsError(f"--host {host!r}: unknown ({error.strerror})") from None
    last_error: OSError | None = None
    candidates = [0] if port == 0 else range(port, min(port + PORTS_TRIED, 65536))
    for candidate in candidates:
        with socket.socket(family, kind, protocol) as probe:
            # as asyncio's server (viser's) binds: a port a stopped viewer left in TIME_WAIT is free to it
            probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            try:
                probe.bind((address[0], candidate, *address[2:]))
            except OSError as error:
                if error.errno == errno.EADDRNOTAVAIL:  # the address, not the port
                    raise WarpbagsError(f"--host {host!r}: cannot listen there ({error.strerror})") from None
                last_error = error
                continue
        return candidate
    raise WarpbagsError(f"--port {port}: no port from {port} to {candidates[-1]} can be listened on at {host} "
                        f"({last_error.strerror if last_error else 'none tried'})")


# The hosts that mean every interface, and the name this machine reaches each at; "::" at IPv6's loopback, not at
# localhost: viser's server listens there on IPv6 alone (asyncio sets IPV6_V6ONLY), and localhost may name
# 127.0.0.1 alone (an /etc/hosts without a ::1 line), where the page does not open.
LOOPBACK_OF_ANY_ADDRESS = {"0.0.0.0": "localhost", "::": "::1"}


def page_url(host: str, port: int) -> str:
    """The address of the page served at `host`:`port` as a browser takes it: an address of every interface as
    this machine's loopback (`LOOPBACK_OF_ANY_ADDRESS`), an IPv6 address in brackets (http://[::1]:8080, RFC 3986)."""
    host = LOOPBACK_OF_ANY_ADDRESS.get(host, host)
    return f"http://{f'[{host}]' if ':' in host else host}:{port}"


class Viewer:
    """Serves `content` at http://host:port until `stop()`.

    Args:
        content: what to show (`load_viewer_content`).
        host: interface to listen on ("127.0.0.1": this machine only; "0.0.0.0": the network).
        port: TCP port; the next free one is taken when it is busy, 0 lets the system choose.
        device: where the Gaussians are rendered: "cpu" or "cuda"; None: CUDA when available.
    """

    def __init__(self, content: ViewerContent, host: str = "127.0.0.1", port: int = 8080, device: str | None = None):
        port = listen_port(host, port)
        self.content = content
        self.gaussians = DeviceGaussians(content, device)
        with contextlib.redirect_stdout(io.StringIO()):  # viser's own URL panel; `warpbags view` prints one line
            self.server = viser.ViserServer(host=host, port=port, label="warpbags", verbose=False)
        self.renderers: dict[int, ClientRenderer] = {}
        self.frustums: dict[str, list[viser.CameraFrustumHandle]] = {}
        self.history_slider: viser.GuiSliderHandle | None = None
        self._render_lock = threading.Lock()
        self._add_model_panel()
        if content.cameras is not None:
            self._add_cameras(content.cameras)
        self._set_initial_camera()
        self.server.on_client_connect(self._connect)
        self.server.on_client_disconnect(self._disconnect)

    @property
    def url(self) -> str:
        """The page to open (`page_url`)."""
        return page_url(self.server.get_host(), self.server.get_port())

    def stop(self) -> None:
        for renderer in self.renderers.values():
            renderer.stop()
        self.server.stop()

    # ------------------------------------------------------------------------------------------------ browsers
    def _connect(self, client: viser.ClientHandle) -> None:
        readout = client.gui.add_markdown("frame: waiting for the camera", order=100)
        renderer = ClientRenderer(client, self.gaussians, self._render_lock, on_frame=_frame_readout(readout),
                                  on_error=_error_readout(readout))
        self.renderers[client.client_id] = renderer
        renderer.start()

    def _disconnect(self, client: viser.ClientHandle) -> None:
        renderer = self.renderers.pop(client.client_id, None)
        if renderer is not None:
            renderer.stop()

    def _set_initial_camera(self) -> None:
        """Look at the object from above camera 0's side (not along its axis, where its frustum would hide the
        object), or from a diagonal for a bare PLY."""
        center = self.content.center()
        up = self.content.up()
        if up is None:  # a bare PLY: viser's +z up
            up = np.array([0.0, 0.0, 1.0])
            spread = np.quantile(np.linalg.norm(self.content.params["means"].double().numpy() - center, axis=1), 0.9)
            eye = center + 3.0 * max(spread, 1e-3) * np.array([0.6, -0.6, 0.5])
        else:
            _, camera_0 = camera_to_world(self.content.cameras.final[0])
            offset = camera_0 - center
            direction = offset / np.linalg.norm(offset) + up
            eye = center + 1.5 * np.linalg.norm(offset) * direction / np.linalg.norm(direction)
            self.server.scene.set_up_direction(up)
        self.server.initial_camera.up = up
        self.server.initial_camera.position = eye
        self.server.initial_camera.look_at = center

    # ------------------------------------------------------------------------------------------------ scene
    def _add_model_panel(self) -> None:
        count = len(self.content.params["means"])
        self.server.gui.add_markdown(f"**{self.content.name}**: {count:,} Gaussians, SH degree "
                                     f"{self.content.sh_degree}, rendered by warpbags on {self.gaussians.device.type}")

    def _add_cameras(self, cameras: TrainingCameras) -> None:
        centers = np.stack([camera_to_world(viewmat)[1] for viewmat in cameras.final])
        size = FRUSTUM_SIZE * float(np.median(np.linalg.norm(centers - self.content.center(), axis=1)))
        fov = 2 * np.arctan(0.5 * cameras.height / cameras.Ks[:, 1, 1])
        sets = {"start": cameras.start, "optimized": cameras.final, "reference": cameras.reference}
        folder = self.server.gui.add_folder("Training cameras")
        with folder:
            for name, viewmats in sets.items():
                if viewmats is None:
                    continue
                images = cameras.images if name == "optimized" else None
                self.frustums[name] = [
                    self._add_frustum(f"/cameras/{name}/{index}", viewmat, float(fov[index]),
                                      cameras.width / cameras.height, size, FRUSTUM_COLORS[name],
                                      None if images is None else images[index])
                    for index, viewmat in enumerate(viewmats)]
                self._add_visibility_toggle(name)
            self._add_history_slider(cameras)
        for index, frustum in enumerate(self.frustums["optimized"]):
            frustum.on_click(_move_camera_to(frustum, float(fov[index])))

    def _add_frustum(self, name: str, viewmat: np.ndarray, fov: float, aspect: float, size: float,
                     color: tuple[int, int, int], image: np.ndarray | None) -> viser.CameraFrustumHandle:
        wxyz, position = camera_to_world(viewmat)
        # Lines of constant screen width: world-width lines would cover the view from a camera next to them.
        return self.server.scene.add_camera_frustum(name, fov=fov, aspect=aspect, scale=size, color=color,
                                                    thickness=2.0, thickness_units="screen", image=image, wxyz=wxyz,
                                                    position=position)

    def _add_visibility_toggle(self, name: str) -> None:
        checkbox = self.server.gui.add_checkbox(FRUSTUM_LABELS[name], True)

        @checkbox.on_update
        def _(_) -> None:
            for frustum in self.frustums[name]:
                frustum.visible = checkbox.value

    def _add_history_slider(self, cameras: TrainingCameras) -> None:
        """An iteration slider that moves the optimized frustums through the recorded poses (hidden when the run
        holds one pose frame only)."""
        iterations = cameras.iterations
        slider = self.server.gui.add_slider(
            "iteration", int(iterations[0]), int(iterations[-1]), 1, int(iterations[-1]),
            marks=tuple(int(i) for i in (iterations[0], iterations[-1])), visible=len(iterations) > 1,
            hint=f"optimized poses over training ({len(iterations)} recorded frames); the Gaussians are the final ones",
        )

        @slider.on_update
        def _(_) -> None:
            self.show_pose_frame(int(np.searchsorted(iterations, slider.value, side="right")) - 1)

        self.history_slider = slider

    def show_pose_frame(self, frame: int) -> None:
        """Move the optimized frustums to the poses of pose frame `frame` (index into `cameras.iterations`)."""
        viewmats = self.content.cameras.frames[max(frame, 0)]
        with self.server.atomic():
            for frustum, viewmat in zip(self.frustums["optimized"], viewmats):
                frustum.wxyz, frustum.position = camera_to_world(viewmat)


def _frame_readout(readout: viser.GuiMarkdownHandle) -> Callable[[FrameStats], None]:
    """Shows each frame's size and render time in the browser's panel."""

    def show(stats: FrameStats) -> None:
        kind = "full resolution" if stats.full_resolution else "moving"
        readout.content = f"frame: {stats.width} x {stats.height} ({kind}), {1000 * stats.seconds:.0f} ms"

    return show


def _error_readout(readout: viser.GuiMarkdownHandle) -> Callable[[str], None]:
    """Shows a failed frame's message in the browser's panel, and prints each new message once on stderr (a
    failure that repeats at every camera move would otherwise flood the terminal)."""
    printed: set[str] = set()

    def show(message: str) -> None:
        readout.content = f"frame failed: {message}"
        if message not in printed:
            printed.add(message)
            print(f"warpbags view: a frame failed: {message}", file=sys.stderr)

    return show


def _move_camera_to(frustum: viser.CameraFrustumHandle, fov: float) -> Callable:
    """A click handler that puts the clicking browser's camera where the frustum is, with its field of view."""

    def move(event) -> None:
        camera = event.client.camera
        with event.client.atomic():
            camera.fov = fov
            camera.wxyz = frustum.wxyz
            camera.position = frustum.position

    return move

"""Rendering for one browser: the Gaussians from the browser's camera, at a resolution that keeps it interactive.

While the camera moves, frames are rendered at a fraction of the canvas that is steered so a frame takes about
`target_seconds` (nerfstudio's and nerfview's scheme); once the camera has rested for `STILL_AFTER` seconds, one
frame at the full canvas size follows. Frames go to the browser as its background image with a depth map, so the
camera frustums in front of the object hide it and those behind it are hidden.
"""

from __future__ import annotations

import contextlib
import math
import threading
import time
from dataclasses import dataclass
from typing import Callable

import numpy as np
import torch
import viser
import viser.transforms as vtf

from warpbags.cameras import camera_centers, viewmats_from_centers
from warpbags.devices import torch_device
from warpbags.errors import one_line
from warpbags.gaussians import render_gaussians
from warpbags.threads import torch_threads
from warpbags.viewer.content import ViewerContent

TARGET_SECONDS = {"cpu": 0.2, "cuda": 0.05}  # per frame while the camera moves
STILL_AFTER = 0.3  # s without camera messages before the full-resolution frame
MIN_SCALE = 0.06  # of the canvas side: 48 px on an 800 px canvas, the coarsest frame
MAX_SIDE = 1600  # px: the full-resolution frame is capped here (a 4K canvas would take seconds on a CPU)
FAR_DEPTH = 1e3  # depth sent where no Gaussian covers the pixel (viser clips it to its far limit)


def camera_to_world(viewmat: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """viser's (wxyz, position) of a [4,4] world-to-camera matrix; both use OpenCV axes (+z looks forward)."""
    return vtf.SO3.from_matrix(viewmat[:3, :3].T).wxyz, camera_centers(torch.from_numpy(viewmat)).numpy()


def world_to_camera(wxyz: np.ndarray, position: np.ndarray) -> np.ndarray:
    """[4,4] world-to-camera matrix of viser's camera-to-world (wxyz, position): the inverse of `camera_to_world`."""
    to_world = vtf.SO3(np.asarray(wxyz, dtype=np.float64)).as_matrix()
    center = torch.from_numpy(np.asarray(position, dtype=np.float64))
    return viewmats_from_centers(torch.from_numpy(to_world.T.copy()), center).numpy()


def pinhole_intrinsics(vertical_fov: float, width: int, height: int) -> np.ndarray:
    """[3,3] intrinsics of a width x height image with the browser's vertical field of view (radians)."""
    focal = 0.5 * height / math.tan(0.5 * vertical_fov)
    return np.array([[focal, 0.0, 0.5 * width], [0.0, focal, 0.5 * height], [0.0, 0.0, 1.0]])


def next_scale(scale: float, seconds: float, target_seconds: float) -> float:
    """The canvas fraction for the next moving frame: render time grows with the pixel count, i.e. the scale
    squared, so the side is scaled by sqrt(target / measured). The step is limited to x0.5-x2 so one slow frame
    (a kernel compiling, another process) does not throw the resolution to its floor."""
    factor = math.sqrt(target_seconds / max(seconds, 1e-4))
    return min(1.0, max(MIN_SCALE, scale * min(2.0, max(0.5, factor))))


class DeviceGaussians:
    """The Gaussians on the render device, ready to be drawn from any camera.

    Args:
        content: the viewer's content (its parameters stay on the CPU; a copy goes to `device`).
        device: "cpu" or "cuda"; None: CUDA when available.

    Raises:
        WarpbagsError: an unknown device, or cuda without a CUDA device.
    """

    def __init__(self, content: ViewerContent, device: str | None = None):
        self.device = torch_device(device)
        self.params = {name: value.to(self.device) for name, value in content.params.items()}
        self.sh_degree = content.sh_degree
        self.background = torch.tensor([content.background], dtype=torch.float32, device=self.device)

    def render(self, viewmat: np.ndarray, Ks: np.ndarray, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
        """One camera's view: ([H,W,3] uint8 RGB, [H,W] float32 depth along the optical axis, FAR_DEPTH where
        the Gaussians cover less than half the pixel)."""
        to_device = lambda array: torch.as_tensor(array, dtype=torch.float32, device=self.device)[None]  # noqa: E731
        threads = torch_threads(1) if self.device.type == "cpu" else contextlib.nullcontext()
        with torch.no_grad(), threads:  # Warp's host threads render; torch's OpenMP workers would fight them
            colors, alphas, _ = render_gaussians(self.params, to_device(viewmat), to_device(Ks), width, height,
                                                 sh_degree=self.sh_degree, backgrounds=self.background,
                                                 render_mode="RGB+ED")
        rgb = (colors[0, ..., :3].clamp(0, 1) * 255 + 0.5).to(torch.uint8).cpu().numpy()
        depth = torch.where(alphas[0, ..., 0] > 0.5, colors[0, ..., 3], FAR_DEPTH).cpu().numpy()
        return rgb, depth


@dataclass
class FrameStats:
    """The last frame sent to a browser."""

    width: int = 0
    height: int = 0
    seconds: float = 0.0
    full_resolution: bool = False
    viewmat: np.ndarray | None = None  # [4,4] world-to-camera of the browser's camera it shows
    camera_time: float = 0.0  # viser's update time of that camera: a later one means the camera has moved since


class ClientRenderer:
    """Renders one browser's view on a thread of its own whenever its camera changes.

    Args:
        client: the viser client.
        gaussians: what to render.
        render_lock: held while rendering; shared by every client, since on 2 cores parallel renders only slow
            each other down.
        on_frame: called with the stats of every frame sent (the GUI shows them).
        on_error: called with a one-line message when a frame fails (the GUI shows it); the thread goes on, so
            the next camera move tries again instead of leaving a browser whose view no longer follows.
    """

    def __init__(self, client: viser.ClientHandle, gaussians: DeviceGaussians, render_lock: threading.Lock,
                 on_frame: Callable[[FrameStats], None] = lambda stats: None,
                 on_error: Callable[[str], None] = lambda message: None):
        self.client, self.gaussians, self.render_lock = client, gaussians, render_lock
        self.on_frame, self.on_error = on_frame, on_error
        self.target_seconds = TARGET_SECONDS[gaussians.device.type]
        self.scale = 0.25  # the first moving frame; next_scale steers it from there
        self.last_frame = FrameStats()
        self._camera_moved = threading.Event()
        self._stopped = threading.Event()
        self._thread = threading.Thread(target=self._loop, name=f"warpbags-view-{client.client_id}", daemon=True)
        client.camera.on_update(lambda camera: self._camera_moved.set())

    def start(self) -> None:
        self._thread.start()

    def stop(self) -> None:
        self._stopped.set()

    def _loop(self) -> None:
        while not self._stopped.is_set():
            try:
                if self._camera_moved.wait(timeout=STILL_AFTER):
                    self._camera_moved.clear()
                    seconds = self._render(self.scale)
                    self.scale = next_scale(self.scale, seconds, self.target_seconds)
                elif self.last_frame.width and not self.last_frame.full_resolution:  # at rest: sharpen once
                    self._render(1.0)
            except Exception as error:  # noqa: BLE001 - any failure of one frame, reported; the view goes on
                self.last_frame = FrameStats()  # not "at rest": no sharpening retried until the camera moves
                self.on_error(one_line(error))

    def _render(self, scale: float) -> float:
        """Render at `scale` of the canvas (1 = full resolution) and send the frame; returns the render seconds."""
        camera = self.client.camera
        camera_time = camera.update_timestamp  # before the pose: a message meanwhile leaves the frame not at rest
        canvas_width, canvas_height = camera.image_width, camera.image_height
        capped = min(scale, MAX_SIDE / max(canvas_width, canvas_height, 1))
        width, height = max(1, round(canvas_width * capped)), max(1, round(canvas_height * capped))
        viewmat = world_to_camera(camera.wxyz, camera.position)
        Ks = pinhole_intrinsics(camera.fov, width, height)
        began = time.perf_counter()
        with self.render_lock:
            rgb, depth = self.gaussians.render(viewmat, Ks, width, height)
        seconds = time.perf_counter() - began
        if self._stopped.is_set():  # the browser left while this frame rendered
            return seconds
        full = scale >= 1.0
        self.client.scene.set_background_image(rgb, format="jpeg", jpeg_quality=90 if full else 75, depth=depth)
        self.last_frame = FrameStats(width, height, seconds, full, viewmat, camera_time)
        self.on_frame(self.last_frame)
        return seconds

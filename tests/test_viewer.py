"""`warpbags view`: pose history, PLY files of other tools, the viewer's cameras and frames, and the page in
headless Chromium."""

from __future__ import annotations

import json
import os
import re
import shutil
import threading
import time

import cv2
import numpy as np
import pytest
import torch
from headless_browser import VISER_SHOWS_FULL_FRAME, find_chromium, initial_view_frame, screenshot
from random_poses import generator, random_sim3, random_viewmats
from typer.testing import CliRunner

from warpbags.alignment import align_viewmats, pose_errors
from warpbags.camera_paths import mean_up_axis
from warpbags.cameras import camera_centers
from warpbags.cli.main import app
from warpbags.configs.train import load_preset
from warpbags.data import SyntheticOptions, ensure_synthetic_scene, load_scene
from warpbags.errors import WarpbagsError
from warpbags.gaussians import read_ply, write_ply
from warpbags.pose_history import read_pose_history, record_poses
from warpbags.trainer import start_or_resume, training_scene
from warpbags.viewer import Viewer, load_viewer_content
from warpbags.viewer.content import THUMBNAIL_SIDE
from warpbags.viewer.render import (MIN_SCALE, ClientRenderer, camera_to_world, next_scale, pinhole_intrinsics,
                                    world_to_camera)
from warpbags.viewer.server import FRUSTUM_LABELS, page_url

runner = CliRunner()
ITERS, RECORD_EVERY = 8, 2


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory):
    """A finished tiny run (4 noisy views at 64 px, 8 iterations) that recorded its poses every 2 iterations,
    the way the trainer is meant to."""
    scene_dir = ensure_synthetic_scene(SyntheticOptions(views=16, width=64, height=64),
                                       cache_dir=tmp_path_factory.mktemp("cache"))
    out = tmp_path_factory.mktemp("runs") / "run"
    # Without the quick preset's search over turns in round 2: the callback reads the trainer's poses, which in a
    # searched round are the kept trial's end for each of its iterations (`Trainer.train`).
    config = load_preset("quick", iters=ITERS, rot_noise_deg=4.0, trans_noise=0.05, render_threads=1,
                         camera={"hypotheses_round": 0})
    trainer = start_or_resume(training_scene(load_scene(scene_dir, name="tiny"), config), config, out,
                              log=lambda message: None)

    def record(_) -> None:
        if trainer.iteration % RECORD_EVERY == 0:
            record_poses(out, trainer.iteration, trainer.current_viewmats())

    trainer.train(callback=record)
    return out


# ------------------------------------------------------------------------------------------------ pose history
def test_pose_history_appends_and_follows_a_resume(tmp_path):
    viewmats = random_viewmats(3, generator(0)).float()
    assert read_pose_history(tmp_path) is None
    for iteration in (10, 20, 30):
        record_poses(tmp_path, iteration, viewmats + iteration)
    record_poses(tmp_path, 20, viewmats)  # resumed from the checkpoint at 10: 20 and 30 are replayed
    history = read_pose_history(tmp_path)
    assert history.iterations.tolist() == [10, 20] and history.viewmats.shape == (2, 3, 4, 4)
    np.testing.assert_array_equal(history.viewmats[1], viewmats.numpy())
    assert sorted(path.name for path in tmp_path.iterdir()) == ["poses_history.npz"]  # no temporary left
    with pytest.raises(WarpbagsError, match="holds 3 cameras"):
        record_poses(tmp_path, 40, viewmats[:2])


@pytest.mark.parametrize("damage", ["empty", "not a zip", "an .npy", "1-D viewmats", "scalar iterations",
                                    "unknown compression", "text"])
def test_an_unreadable_pose_history_is_one_line(tmp_path, damage):
    """An empty, damaged or foreign poses_history.npz raised EOFError, BadZipFile, IndexError, TypeError or
    NotImplementedError out of `warpbags view` and a resumed training run."""
    path = tmp_path / "poses_history.npz"
    if damage == "empty":
        path.write_bytes(b"")
    elif damage == "not a zip":
        path.write_bytes(b"PK not really a zip archive")
    elif damage == "text":  # numpy took it for pickled data and advised loading it with allow_pickle=True
        path.write_text("garbage\n")
    elif damage == "an .npy":
        with open(path, "wb") as handle:
            np.save(handle, np.zeros((2, 3, 4, 4)))
    else:
        with open(path, "wb") as handle:
            np.savez(handle, iterations=np.array(10) if damage == "scalar iterations" else np.array([10]),
                     viewmats=np.zeros(16) if damage == "1-D viewmats" else np.zeros((1, 3, 4, 4)))
    if damage == "unknown compression":  # one flipped byte pair: zipfile "That compression method is not supported"
        data = bytearray(path.read_bytes())
        entry = data.find(b"PK\x01\x02")  # the first central directory entry, whose method zipfile reads (the local
        data[entry + 10:entry + 12] = b"\xff\xff"  # header's, at +8, it does not)
        path.write_bytes(bytes(data))
    with pytest.raises(WarpbagsError, match=f"^{re.escape(str(path))}: ") as error:
        read_pose_history(tmp_path)
    assert "\n" not in str(error.value) and "allow_pickle" not in str(error.value)


# ------------------------------------------------------------------------------------------------ PLY
def test_read_ply_of_another_tool_layout(run_dir, tmp_path):
    """gsplat writes no normals; other tools reorder properties, write doubles or add colours. f_rest is 3DGS's
    channel-major order: all of red's coefficients, then green's, then blue's."""
    params = read_ply(run_dir / "gaussians.ply")
    count = len(params["means"])
    params["shN"] = torch.randn(count, 3, 3, generator=torch.Generator().manual_seed(0))  # SH degree 1
    columns = {"red": (np.arange(count) % 256).astype("u1"), "opacity": params["opacities"].numpy()}
    columns.update({f"rot_{i}": params["quats"][:, i].numpy() for i in range(4)})
    columns.update({axis: params["means"][:, i].numpy().astype("<f8") for i, axis in enumerate("xyz")})
    columns.update({f"scale_{i}": params["scales"][:, i].numpy() for i in range(3)})
    columns.update({f"f_dc_{i}": params["sh0"][:, 0, i].numpy() for i in range(3)})
    columns.update({f"f_rest_{3 * channel + k}": params["shN"][:, k, channel].numpy()
                    for channel in range(3) for k in range(3)})
    table = np.empty(count, dtype=[(name, array.dtype.str) for name, array in columns.items()])
    for name, array in columns.items():
        table[name] = array
    types = {"u1": "uchar", "f4": "float", "f8": "double"}
    header = "ply\nformat binary_little_endian 1.0\ncomment another tool, café\nelement vertex {}\n{}end_header\n"
    header = header.format(count, "".join(f"property {types[table.dtype[name].str[1:]]} {name}\n"
                                          for name in table.dtype.names))
    (tmp_path / "other.ply").write_bytes(header.encode("utf-8") + table.tobytes())  # a comment of any text
    again = read_ply(tmp_path / "other.ply")
    assert set(again) == set(params)
    for name in params:
        torch.testing.assert_close(again[name], params[name], rtol=0, atol=0)
    write_ply(tmp_path / "ours.ply", again)  # and back through write_ply
    torch.testing.assert_close(read_ply(tmp_path / "ours.ply")["shN"], params["shN"], rtol=0, atol=0)
    # 2 coefficients per channel beyond the DC term are no SH degree (a renderer would fail on them, not the reader)
    write_ply(tmp_path / "odd.ply", {**params, "shN": params["shN"][:, :2]})
    with pytest.raises(WarpbagsError, match="6 f_rest properties, where SH degrees 0-3 have 0, 9, 24 or 45"):
        read_ply(tmp_path / "odd.ply")
    # numbered with a gap (f_rest_1 missing, f_rest_99 instead) was a ValueError traceback
    data = (tmp_path / "ours.ply").read_bytes()
    (tmp_path / "gap.ply").write_bytes(data.replace(b"property float f_rest_1\n", b"property float f_rest_99\n", 1))
    with pytest.raises(WarpbagsError, match="not a 3DGS Gaussian PLY \\(missing f_rest_1; 9 f_rest properties"):
        read_ply(tmp_path / "gap.ply")


@pytest.mark.parametrize("sh_degree", [0, 1])
def test_written_ply_has_the_3dgs_property_layout_in_its_order(tmp_path, sh_degree):
    """Viewers of a fixed layout (SIBR, the 3DGS reference viewer) read the properties by position, not by name."""
    count, coefficients = 5, (sh_degree + 1) ** 2 - 1
    params = {"means": torch.randn(count, 3), "quats": torch.randn(count, 4), "scales": torch.randn(count, 3),
              "opacities": torch.randn(count), "sh0": torch.randn(count, 1, 3)}
    if coefficients:
        params["shN"] = torch.randn(count, coefficients, 3)
    write_ply(tmp_path / "gaussians.ply", params)
    header, data = (tmp_path / "gaussians.ply").read_bytes().split(b"end_header\n")
    rest = [f"f_rest_{index}" for index in range(3 * coefficients)]
    names = ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2", *rest, "opacity",
             "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    assert header.decode("ascii").splitlines() == ["ply", "format binary_little_endian 1.0", f"element vertex {count}",
                                                   *(f"property float {name}" for name in names)]
    table = np.frombuffer(data, dtype=[(name, "<f4") for name in names])
    assert len(table) == count and not table["nx"].any()
    np.testing.assert_array_equal(table["f_dc_1"], params["sh0"][:, 0, 1].numpy())
    for channel in range(3):  # f_rest channel-major: all of red's coefficients, then green's, then blue's
        for k in range(coefficients):
            np.testing.assert_array_equal(table[f"f_rest_{coefficients * channel + k}"],
                                          params["shN"][:, k, channel].numpy())
    np.testing.assert_array_equal(table["opacity"], params["opacities"].numpy())  # a logit, scales logs: as given
    np.testing.assert_array_equal(table["scale_2"], params["scales"][:, 2].numpy())
    np.testing.assert_array_equal(table["rot_0"], params["quats"][:, 0].numpy())


# ------------------------------------------------------------------------------------------------ cameras
def test_camera_conversions_follow_viser_conventions():
    viewmats = random_viewmats(5, generator(1)).numpy()
    for viewmat in viewmats:
        wxyz, position = camera_to_world(viewmat)
        np.testing.assert_allclose(world_to_camera(wxyz, position), viewmat, atol=1e-10)
        np.testing.assert_allclose(position, camera_centers(torch.from_numpy(viewmat)[None])[0].numpy(), atol=1e-10)
    # A camera at the origin with viser's identity rotation looks down +z (OpenCV): a point ahead lands in the
    # image centre, a point above (-y) in the top half.
    K = pinhole_intrinsics(np.deg2rad(60), 200, 100)
    assert K[1, 1] == pytest.approx(50 / np.tan(np.deg2rad(30)))
    viewmat = world_to_camera(np.array([1.0, 0, 0, 0]), np.zeros(3))
    ahead, above = (K @ (viewmat[:3, :3] @ point + viewmat[:3, 3]) for point in ([0, 0, 2.0], [0, -0.5, 2.0]))
    assert ahead[:2] / ahead[2] == pytest.approx([100, 50]) and above[1] / above[2] < 50


def test_resolution_adapts_to_the_render_time():
    assert next_scale(0.5, seconds=0.8, target_seconds=0.2) == pytest.approx(0.25)  # 4x too slow: half the side
    assert next_scale(0.5, seconds=0.05, target_seconds=0.2) == pytest.approx(1.0)  # 4x too fast: double
    assert next_scale(0.5, seconds=30.0, target_seconds=0.2) == pytest.approx(0.25)  # one stall: at most halved
    assert next_scale(MIN_SCALE, seconds=5.0, target_seconds=0.2) == MIN_SCALE
    assert next_scale(0.9, seconds=0.01, target_seconds=0.2) == 1.0


class _FakeCamera:
    """What `ClientRenderer` reads of a viser client's camera."""
    wxyz, position, fov = np.array([1.0, 0, 0, 0]), np.array([0.0, 0, -3]), 0.8
    image_width = image_height = 32
    update_timestamp = 0.0

    def __init__(self):
        self.listeners = []

    def on_update(self, listener):
        self.listeners.append(listener)

    def move(self):
        self.update_timestamp += 1.0
        for listener in self.listeners:
            listener(self)


class _FakeClient:
    client_id = 0

    def __init__(self):
        self.camera, self.frames = _FakeCamera(), []
        self.scene = type("Scene", (), {"set_background_image": lambda _, rgb, **kwargs: self.frames.append(rgb)})()


class _FailingOnce:
    """Gaussians whose first render fails, as an out-of-memory or a driver error would."""
    device = torch.device("cpu")

    def __init__(self):
        self.calls = 0

    def render(self, viewmat, Ks, width, height):
        self.calls += 1
        if self.calls == 1:
            raise RuntimeError("out of memory\nwhile rendering")
        return np.zeros((height, width, 3), np.uint8), np.ones((height, width), np.float32)


def test_a_failed_frame_is_reported_and_the_view_goes_on():
    client, errors = _FakeClient(), []
    renderer = ClientRenderer(client, _FailingOnce(), threading.Lock(), on_error=errors.append)
    renderer.start()
    try:
        client.camera.move()
        deadline = time.monotonic() + 10
        while not errors and time.monotonic() < deadline:
            time.sleep(0.01)
        assert errors == ["RuntimeError: out of memory"] and client.frames == []
        client.camera.move()  # the thread still serves the browser: the next move renders
        while not client.frames and time.monotonic() < deadline:
            time.sleep(0.01)
        assert len(client.frames) >= 1 and renderer._thread.is_alive()
    finally:
        renderer.stop()


def test_content_of_a_run(run_dir):
    content = load_viewer_content(run_dir, log=lambda message: None)
    cameras = content.cameras
    assert cameras.iterations.tolist() == list(range(0, ITERS + 1, RECORD_EVERY))  # start, history, final
    np.testing.assert_array_equal(cameras.frames[0], np.load(run_dir / "poses_start.npy"))
    np.testing.assert_array_equal(cameras.final, np.load(run_dir / "poses_final.npy"))
    assert cameras.images.shape[0] == 4 and cameras.images.dtype == np.uint8
    assert content.background == (1.0, 1.0, 1.0)


def test_start_cameras_are_the_start_poses_not_the_noisy_given_ones(run_dir):
    """The red frustums show poses_start.npy: the given, noisy poses (poses_init.npy) after the mask-centroid start
    and the silhouette-coherence solve. Their checkbox said "start (noisy)"."""
    cameras = load_viewer_content(run_dir, log=lambda message: None).cameras
    np.testing.assert_array_equal(cameras.start, np.load(run_dir / "poses_start.npy"))
    assert not np.allclose(cameras.start, np.load(run_dir / "poses_init.npy"), atol=1e-3)
    assert FRUSTUM_LABELS["start"] == "start, red"


def test_coarse_result_of_a_run_ends_at_the_coarse_iterations(run_dir, tmp_path):
    """RUN/coarse, the coarse stage's result written when a repair stage follows, holds the run's config.json (coarse
    and repair iterations) but no log.jsonl or pose history: its final poses are those after the coarse iterations,
    where the slider put them after the repair iterations too."""
    run = tmp_path / "run"
    shutil.copytree(run_dir, run, ignore=shutil.ignore_patterns("checkpoints"))
    info = json.loads((run / "config.json").read_text())
    info["config"]["repair"]["iters"] = 5
    (run / "config.json").write_text(json.dumps(info))
    coarse = run / "coarse"
    shutil.copytree(run, coarse, ignore=shutil.ignore_patterns("coarse", "log.jsonl", "poses_history.npz"))
    assert load_viewer_content(coarse, log=lambda message: None).cameras.iterations.tolist() == [0, ITERS]
    assert load_viewer_content(run, log=lambda message: None).cameras.iterations[-1] == ITERS + 5  # with its log


def test_reference_cameras_are_aligned_as_eval_does(run_dir, tmp_path):
    """Reference poses in another world frame (a sim(3) away) land exactly on the optimized cameras."""
    run = tmp_path / "run"
    shutil.copytree(run_dir, run, ignore=shutil.ignore_patterns("checkpoints"))
    final = torch.from_numpy(np.load(run / "poses_final.npy")).double()
    np.save(run / "poses_true.npy", align_viewmats(final, random_sim3(generator(2))).numpy())
    reference = load_viewer_content(run, log=lambda message: None).cameras.reference
    # exact up to the float32 the run stores its poses in (rotations orthonormal to ~2e-7, scaled by the sim(3)):
    # 1.1e-6 measured on one run, while a wrong alignment is off by the sim(3) itself
    np.testing.assert_allclose(reference, final.numpy(), atol=1e-5)
    # Reference poses that are not a sim(3) of the final ones: mapped by eval's alignment for this many cameras
    # (Procrustes on the centres for 3 or more), which another alignment would not reproduce.
    true = align_viewmats(final, random_sim3(generator(2)))
    true[:, :3, 3] += 0.05 * torch.randn(len(true), 3, generator=generator(3), dtype=torch.float64)
    np.save(run / "poses_true.npy", true.numpy())
    reference = load_viewer_content(run, log=lambda message: None).cameras.reference
    sim3 = pose_errors(final, true, alignment="procrustes")["sim3"]
    np.testing.assert_allclose(reference, align_viewmats(true, sim3.inverse()).numpy(), atol=1e-5)


def test_viewer_without_history_or_scene(run_dir, tmp_path):
    """A run without pose history slides from start to final; a moved scene folder leaves pictureless frustums."""
    run = tmp_path / "run"
    shutil.copytree(run_dir, run, ignore=shutil.ignore_patterns("checkpoints", "poses_history.npz"))
    info = json.loads((run / "config.json").read_text())
    (run / "config.json").write_text(json.dumps({**info, "scene_root": str(tmp_path / "gone")}))
    notes = []
    content = load_viewer_content(run, log=notes.append)
    assert content.cameras.iterations.tolist() == [0, ITERS] and content.cameras.images is None
    assert any("training images unavailable" in note for note in notes)
    viewer = Viewer(content, port=0, device="cpu")
    try:
        assert viewer.history_slider.visible and viewer.history_slider.max == ITERS
        viewer.history_slider.value = 0  # the slider's callback moves the optimized frustums to the start poses
        start_center = camera_to_world(np.load(run / "poses_start.npy")[1])[1]
        np.testing.assert_allclose(viewer.frustums["optimized"][1].position, start_center, atol=1e-5)
    finally:
        viewer.stop()


def test_initial_camera_stands_as_the_cameras_do_above_their_side_of_the_object(run_dir):
    """The browser's first view (and its "Reset View") has the training cameras' up and looks at the object from
    above, on the cameras' side: with the up negated the object stood on its head, seen from below."""
    content = load_viewer_content(run_dir, log=lambda message: None)
    final = np.load(run_dir / "poses_final.npy")
    up = mean_up_axis(torch.from_numpy(final).double()).numpy()
    center = content.center()
    centers = np.stack([camera_to_world(viewmat)[1] for viewmat in final])
    viewer = Viewer(content, port=0, device="cpu")
    try:
        initial = viewer.server.initial_camera
        np.testing.assert_allclose(initial.up, up, atol=1e-9)
        np.testing.assert_allclose(initial.look_at, center, atol=1e-9)
        eye = (initial.position - center) / np.linalg.norm(initial.position - center)
    finally:
        viewer.stop()
    assert ((centers - center) @ up > 0).all()  # this run's cameras are all above the object: the eye is too
    assert eye @ up > 0.5, eye @ up  # 0.80 measured
    towards_cameras = (centers.mean(axis=0) - center) / np.linalg.norm(centers.mean(axis=0) - center)
    assert eye @ towards_cameras > 0.5, eye @ towards_cameras  # 0.91 measured


def test_history_slider_shows_the_poses_of_each_recorded_iteration(run_dir):
    """An interior recorded iteration and the last one show their own pose frame, not the one before it."""
    content = load_viewer_content(run_dir, log=lambda message: None)
    iterations, frames = content.cameras.iterations, content.cameras.frames
    assert iterations.tolist() == [0, 2, 4, 6, 8]
    viewer = Viewer(content, port=0, device="cpu")
    try:
        for frame in (2, len(iterations) - 1):  # iteration 4, then 8 (a change of value: the callback runs)
            # the frame before is elsewhere (by 5e-3 or more in this run), so showing it is seen
            assert np.abs(frames[frame] - frames[frame - 1]).max() > 1e-3
            viewer.history_slider.value = int(iterations[frame])
            for frustum, viewmat in zip(viewer.frustums["optimized"], frames[frame]):
                wxyz, position = camera_to_world(viewmat)
                np.testing.assert_allclose(frustum.position, position, atol=1e-6)
                np.testing.assert_allclose(frustum.wxyz, wxyz, atol=1e-6)
    finally:
        viewer.stop()


def test_frustums_have_the_cameras_field_of_view_and_their_training_images(run_dir):
    """Each frustum opens as its camera's intrinsics (vertical fov, width / height), and each optimized one shows the
    training image of its camera's image name, not the scene's image at its index."""
    content = load_viewer_content(run_dir, log=lambda message: None)
    info = json.loads((run_dir / "config.json").read_text())
    Ks, width, height = np.load(run_dir / "intrinsics.npy"), info["width"], info["height"]
    scene = load_scene(info["scene_root"], resolution=info.get("resolution"), name=info.get("scene"),
                       load_depths=False)
    # the run trains on every 4th view: an image by index would be another view's
    assert [scene.image_names.index(name) for name in info["image_names"]] == [0, 4, 8, 12]
    viewer = Viewer(content, port=0, device="cpu")
    try:
        for name in ("start", "optimized", "reference"):
            for index, frustum in enumerate(viewer.frustums[name]):
                assert frustum.fov == pytest.approx(2 * np.arctan(0.5 * height / Ks[index, 1, 1]), rel=1e-9)
                assert frustum.aspect == pytest.approx(width / height, rel=1e-9)
                assert (frustum.image is None) == (name != "optimized"), name
        for frustum, image_name in zip(viewer.frustums["optimized"], info["image_names"]):
            image = scene.images[scene.image_names.index(image_name)].numpy()
            side = THUMBNAIL_SIDE  # the 64 px square images, resized to the thumbnails' longer side
            expected = cv2.resize(image, (side, side), interpolation=cv2.INTER_AREA) * 255
            assert frustum.image.shape == (side, side, 3) and frustum.image.dtype == np.uint8
            np.testing.assert_allclose(frustum.image, expected, atol=1, err_msg=image_name)
    finally:
        viewer.stop()


@pytest.mark.parametrize("arguments, message", [
    (["--port", "70000"], "--port must be 0-65535, got 70000"),
    (["--host", "no-such-host.invalid"], "--host 'no-such-host.invalid': unknown"),
    (["--host", "192.0.2.1"], "--host '192.0.2.1': cannot listen there"),  # TEST-NET-1: never this machine's
])
def test_view_address_it_cannot_listen_on_is_one_line_not_a_hang(run_dir, arguments, message):
    """Viser waits forever for a server thread that cannot bind; the viewer checks the address first."""
    result = runner.invoke(app, ["view", str(run_dir), *arguments])
    lines = [line for line in result.output.splitlines() if line.strip()]
    assert result.exit_code == 2 and len(lines) == 1 and message in lines[0], result.output


def test_view_takes_the_next_free_port_and_says_when_none_is_free(run_dir, monkeypatch):
    """Viser moves to the next port when one is busy, and hung forever (a traceback in its thread) when none it
    tried could be bound: the port is found first, and a range with none free is one line."""
    import socket

    from warpbags.viewer import server

    held = []
    while len(held) < 2:  # two adjacent ports held by this test
        first = socket.socket()
        first.bind(("127.0.0.1", 0))
        second = socket.socket()
        try:
            second.bind(("127.0.0.1", first.getsockname()[1] + 1))
            held = [first, second]
        except OSError:
            first.close()
            second.close()
    port = held[0].getsockname()[1]
    try:
        for sock in held:
            sock.listen()
        monkeypatch.setattr(server, "PORTS_TRIED", 3)
        assert server.listen_port("127.0.0.1", port) == port + 2
        monkeypatch.setattr(server, "PORTS_TRIED", 2)
        result = runner.invoke(app, ["view", str(run_dir), "--port", str(port)])
        lines = [line for line in result.output.splitlines() if line.strip()]
        assert result.exit_code == 2 and len(lines) == 1, result.output
        assert f"--port {port}: no port from {port} to {port + 1} can be listened on at 127.0.0.1" in lines[0]
    finally:
        for sock in held:
            sock.close()


def test_view_takes_a_port_a_stopped_viewer_left_in_time_wait():
    """A viewer stopped and started again on its port: the closed connection holds the port in TIME_WAIT, which
    viser's server (SO_REUSEADDR) binds; the probe skipped it for the next port."""
    import socket

    from warpbags.viewer import server

    listener = socket.socket()
    listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as viser's (asyncio's) server socket
    listener.bind(("127.0.0.1", 0))
    listener.listen()
    port = listener.getsockname()[1]
    client = socket.create_connection(("127.0.0.1", port))
    connection, _ = listener.accept()
    connection.close()  # the server's side closes first: its port goes to TIME_WAIT
    client.close()
    listener.close()
    assert server.listen_port("127.0.0.1", port) == port


def test_the_address_shown_for_an_ipv6_host_opens_the_page(run_dir):
    """`--host ::1` printed http://::1:8391 and `--host ::` http://:::8391, neither an address a browser opens: an IPv6
    address goes in brackets, and "::" (every interface) is shown as IPv6's loopback, as "0.0.0.0" is as localhost
    (not as localhost too: a server on "::" listens on IPv6 alone, and localhost may be 127.0.0.1 alone)."""
    import socket
    import urllib.request

    assert page_url("0.0.0.0", 8391) == "http://localhost:8391"
    assert page_url("127.0.0.1", 8391) == "http://127.0.0.1:8391"
    assert page_url("::1", 8391) == "http://[::1]:8391"
    assert page_url("::", 8391) == "http://[::1]:8391"
    assert page_url("fd00::5", 8391) == "http://[fd00::5]:8391"
    try:
        with socket.socket(socket.AF_INET6) as probe:
            probe.bind(("::1", 0))
    except OSError:
        pytest.skip("no IPv6 loopback on this machine")
    content = load_viewer_content(run_dir, log=lambda message: None)
    for host in ("::1", "::"):
        viewer = Viewer(content, host=host, port=0, device="cpu")
        try:
            assert viewer.url == f"http://[::1]:{viewer.server.get_port()}"
            with urllib.request.urlopen(viewer.url, timeout=30) as page:
                assert page.status == 200 and b"<html" in page.read().lower()
        finally:
            viewer.stop()


@pytest.mark.parametrize("case", ["missing", "no_ply", "not_ply"])
def test_view_bad_input_is_one_line(run_dir, tmp_path, case):
    path = {"missing": tmp_path / "nowhere", "no_ply": tmp_path, "not_ply": run_dir / "config.json"}[case]
    named = {"missing": path, "no_ply": path / "gaussians.ply", "not_ply": path}[case]
    result = runner.invoke(app, ["view", str(path), "--port", "0"])
    assert result.exit_code == 2, result.output
    assert str(named) in result.output and result.output.strip().count("\n") <= 1, result.output


# ------------------------------------------------------------------------------------------------ browser
def test_page_shows_the_object_and_the_frustums(run_dir, tmp_path):
    if find_chromium() is None:
        if os.environ.get("CI") == "true":
            pytest.fail("chromium is missing on CI: .ci/run installs Debian's chromium package")
        pytest.skip("needs Debian's chromium (apt-get install chromium)")
    content = load_viewer_content(run_dir, log=lambda message: None)
    viewer = Viewer(content, port=0, device="cpu")
    try:
        for name in ("start", "optimized", "reference"):
            for index in range(4):
                node = viewer.server.scene.get_handle_by_name(f"/cameras/{name}/{index}")
                assert node is not None and type(node).__name__ == "CameraFrustumHandle", (name, index)
        frames = []  # the frame the browser rests on, kept: its renderer goes when the browser closes

        def first_view_sent() -> bool:
            frame = initial_view_frame(viewer)
            if frame is not None:
                frames.append(frame)
            return frame is not None

        shot = screenshot(viewer.url, tmp_path / "viewer.png", ready=first_view_sent, shown=VISER_SHOWS_FULL_FRAME,
                          size=(800, 600), timeout=120)
    finally:
        viewer.stop()
    import cv2  # noqa: PLC0415

    pixels = cv2.cvtColor(cv2.imread(str(shot)), cv2.COLOR_BGR2RGB).astype(int)
    # The frame matches the canvas: 800 x 600, or 600 x 450 once viser's client lowers its pixel ratio to 0.75
    # for slow (software) WebGL.
    assert pixels.shape == (600, 800, 3) and frames[-1].width >= 600 and frames[-1].width * 3 == frames[-1].height * 4
    # The first camera looks at the Gaussians' centre: the object fills the middle of the canvas, on the run's
    # white background, which shows in the corners left of the GUI panel.
    not_white = (np.abs(pixels - 255).max(axis=-1) > 40)
    assert not_white[250:350, 350:450].mean() > 0.5, not_white[250:350, 350:450].mean()
    assert not_white[500:590, 100:300].mean() < 0.1

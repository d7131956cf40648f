"""Scenes and datasets: COLMAP/LLFF/transforms.json loaders, maryrose, the synthetic scene, bad input, `info`."""

from __future__ import annotations

import dataclasses
import functools
import io
import json
import math
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pycolmap
import pytest
import torch
from PIL import Image
from conftest import look_at, stopped_by_sigterm
from typer.testing import CliRunner
from warpbags.cli.main import app

from warpbags.data import (
    ORBIT_RADIUS,
    SceneNormalization,
    SyntheticOptions,
    farthest_views,
    generate_synthetic_scene,
    load_scene,
    object_center,
    open_scene,
)
from warpbags.data import loaders
from warpbags.data.catalog import packaged_scene_dir
from warpbags.data.colmap import read_model, write_model
from warpbags.data.images import read_image, read_images, read_masks, scene_bytes
from warpbags.data.synthetic import (LIGHT_DIRECTION, LIGHT_IN_CAMERA, OBJECT_CENTER, dome_viewmats, intrinsics,
                                     view_lighting)
from warpbags.errors import WarpbagsError

SYNTHETIC = SyntheticOptions(views=12, width=64, height=64, num_points=600)
# Wider than tall: a reader that swaps width and height, or x and y, gives other intrinsics (or refuses the images).
WIDE = SyntheticOptions(views=8, width=64, height=48, num_points=100)


def project(viewmats: torch.Tensor, Ks: torch.Tensor, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Pixel coordinates [C,P,2] (continuous, pixel centres at +0.5) and depths [C,P] of world points [P,3]."""
    camera = viewmats[:, None, :3, :3] @ points[None, :, :, None] + viewmats[:, None, :3, 3:]
    camera = camera[..., 0]
    pixels = (Ks[:, None] @ camera[..., None])[..., 0]
    return pixels[..., :2] / pixels[..., 2:], camera[..., 2]


@pytest.fixture(scope="module")
def synthetic_dir(tmp_path_factory) -> Path:
    return generate_synthetic_scene(tmp_path_factory.mktemp("synthetic") / "scene", SYNTHETIC)


@pytest.fixture(scope="module")
def synthetic(synthetic_dir):
    return load_scene(synthetic_dir)


@pytest.fixture(scope="module")
def tankard(tmp_path_factory):
    """The synthetic scene with the tankard instead of the excavator."""
    options = SyntheticOptions(**{**SYNTHETIC.__dict__, "object": "tankard"})
    return load_scene(generate_synthetic_scene(tmp_path_factory.mktemp("tankard") / "scene", options))


@pytest.fixture
def scene_copy(synthetic_dir, tmp_path) -> Path:
    """A writable copy of the synthetic scene, for corrupting."""
    return Path(shutil.copytree(synthetic_dir, tmp_path / "scene"))


@pytest.fixture(scope="module")
def wide_dir(tmp_path_factory) -> Path:
    """The synthetic scene of `WIDE`: 64 x 48 images."""
    return generate_synthetic_scene(tmp_path_factory.mktemp("wide") / "scene", WIDE)


@pytest.fixture(scope="module")
def maryrose():
    return open_scene("maryrose")


# ---------------------------------------------------------------------------------------------------------------
# COLMAP model


@pytest.mark.parametrize("binary", [True, False])
def test_colmap_model_round_trip(tmp_path, binary):
    options = SyntheticOptions(views=5, width=40, height=30)
    viewmats = dome_viewmats(options)
    Ks = np.tile(intrinsics(options), (5, 1, 1))
    Ks[:, 0, 0] += np.arange(5)  # distinct cameras
    names = [f"img_{index}.jpg" for index in (3, 1, 4, 0, 2)]
    rng = np.random.default_rng(0)
    points, colors = rng.normal(size=(20, 3)), rng.integers(0, 256, size=(20, 3)).astype(np.uint8)
    write_model(tmp_path, names, viewmats, Ks, 40, 30, points, colors, binary=binary)
    model = read_model(tmp_path)
    order = np.argsort(names)
    assert model.image_names == sorted(names)
    np.testing.assert_allclose(model.viewmats, viewmats[order], atol=1e-12)
    np.testing.assert_allclose(np.stack([camera.K for camera in model.cameras]), Ks[order], atol=1e-9)
    assert all((camera.width, camera.height, camera.model) == (40, 30, "PINHOLE") for camera in model.cameras)
    by_position = {tuple(np.round(p, 9)): c for p, c in zip(points, colors)}
    assert len(model.points) == 20
    for point, color in zip(model.points, model.colors):
        np.testing.assert_array_equal(by_position[tuple(np.round(point, 9))], color)


@pytest.mark.parametrize("stem", ["cameras", "images", "points3D", "rigs", "frames"])
def test_a_binary_colmap_file_cut_short_or_run_on_is_named_before_pycolmap_reads_it(tmp_path, stem):
    """pycolmap read on past the end of a file cut short (a count from beyond it: minutes, then MemoryError; or the
    missing bytes as garbage); each file's entries are walked first, so the file and the byte are named at once."""
    rng = np.random.default_rng(0)
    write_model(tmp_path, ["a.png", "b c.png"], np.eye(4)[None].repeat(2, 0), np.eye(3)[None].repeat(2, 0), 8, 8,
                rng.normal(size=(3, 3)), binary=True, distortions=np.array([[0.1, 0.0, 0.0, 0.0], [0.0] * 4]))
    path = tmp_path / f"{stem}.bin"
    data = path.read_bytes()
    for cut in range(1, len(data) + 1):
        path.write_bytes(data[:-cut])
        with pytest.raises(WarpbagsError, match=f"^COLMAP model file {re.escape(str(path))} is cut short: it ends "
                                                f"at byte {len(data) - cut}, within an entry"):
            read_model(tmp_path)
    path.write_bytes(data + b"\0")
    with pytest.raises(WarpbagsError, match=f"^COLMAP model file {re.escape(str(path))} goes on after its last entry "
                                            f"\\(byte {len(data)} of {len(data) + 1}\\)"):
        read_model(tmp_path)
    if stem == "cameras":  # a model id no camera model has: the size of its parameters is unknown
        path.write_bytes(data[:12] + (99).to_bytes(4, "little") + data[16:])
        with pytest.raises(WarpbagsError, match="camera 1 has unknown camera model id 99$"):
            read_model(tmp_path)
    path.write_bytes(data)
    assert read_model(tmp_path).image_names == ["a.png", "b c.png"]


# ---------------------------------------------------------------------------------------------------------------
# maryrose (the shipped real capture, LLFF layout)


def test_maryrose_loads_all_views_masks_and_splits(maryrose):
    assert maryrose.layout == "llff" and maryrose.num_views == 69
    assert maryrose.images.shape == (69, 432, 432, 3) and maryrose.images.dtype == torch.float32
    assert maryrose.masks.shape == (69, 432, 432) and set(maryrose.masks.unique().tolist()) == {0.0, 1.0}
    assert maryrose.depths is None
    assert maryrose.splits["4"] == [0, 16, 43, 57]
    assert maryrose.splits["6"] == [0, 7, 16, 43, 50, 57]
    assert maryrose.splits["9"] == [0, 7, 13, 16, 32, 43, 50, 57, 62]
    assert maryrose.splits["test"] == [1, 8, 15, 22, 28, 35, 41, 48, 55, 63]
    focal = np.load(Path(maryrose.root) / "poses_bounds.npy")[0, 14] / 8  # full-res focal, images_8
    torch.testing.assert_close(maryrose.Ks[0], torch.tensor([[focal, 0, 216], [0, focal, 216], [0, 0, 1]]).float())
    assert maryrose.orbit_radius() == pytest.approx(ORBIT_RADIUS, rel=1e-5)


def test_training_on_an_llff_scene_does_not_load_pycolmap():
    """pycolmap costs every process ~57 MiB of resident memory (bench/train_step.py compares peak RSS with
    OpenSplat's); only COLMAP models need it, and maryrose is LLFF."""
    code = ("import sys, warpbags.trainer\n"
            "from warpbags.data import open_scene\n"
            "open_scene('maryrose')\n"
            "print('pycolmap' in sys.modules)")
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr[-2000:]
    assert result.stdout.strip().splitlines()[-1] == "False"


def test_a_process_that_read_a_colmap_model_ends_quietly_on_sigterm(tmp_path):
    """pycolmap's import installs glog's SIGTERM handler, which printed a native stack dump when `kill` stopped
    `warpbags view` or a training run; reading a model keeps the handler SIGTERM had (Python's default here)."""
    options = SyntheticOptions(views=3, width=40, height=30)
    viewmats = dome_viewmats(options)
    write_model(tmp_path, ["a.jpg", "b.jpg", "c.jpg"], viewmats, np.tile(intrinsics(options), (3, 1, 1)), 40, 30)
    code = ("import os, signal, time\n"
            "from pathlib import Path\n"
            "from warpbags.data.colmap import read_model\n"
            f"read_model(Path({str(tmp_path)!r}))\n"
            "os.kill(os.getpid(), signal.SIGTERM)\n"
            "time.sleep(60)\n")
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert result.returncode == -15 and "stack trace" not in result.stderr, result.stderr[-2000:]


def test_maryrose_poses_agree_with_masks(maryrose):
    """The object centre (the origin after normalization) projects inside every view's mask: the LLFF
    down/right/back -> OpenCV conversion is right (any other axis order misses the masks by far)."""
    pixels, depths = project(maryrose.viewmats.double(), maryrose.Ks.double(), torch.zeros(1, 3, dtype=torch.float64))
    assert (depths > 0).all()
    columns, rows = pixels[:, 0, 0].long(), pixels[:, 0, 1].long()
    assert maryrose.masks[torch.arange(69), rows, columns].all()
    rotations = maryrose.viewmats[:, :3, :3]
    identity = torch.eye(3).expand(69, 3, 3)
    torch.testing.assert_close(rotations @ rotations.transpose(1, 2), identity, atol=1e-5, rtol=0)
    assert torch.allclose(torch.linalg.det(rotations), torch.ones(69), atol=1e-5)


def test_maryrose_normalization_is_unchanged(maryrose):
    """The object centre (mask-centroid rays met by `silhouette.rays_meeting_point`) and the scale, as first
    computed (b03b2db): every run's world frame depends on them. To 1e-12, not the last digit: a fresh setup on
    2026-12-02 (NumPy 2.4.6, unpinned) gives the centre's z 4e-17 away with the same code (at 8c3cf4b too)."""
    assert maryrose.normalization.center == pytest.approx(
        (-0.7887152026885462, 0.9009442736130013, 0.01981964168689295), rel=1e-12, abs=1e-15)
    assert maryrose.normalization.scale == pytest.approx(1.0488791952491046, rel=1e-12)


def test_farthest_point_choice_reproduces_maryrose_splits(maryrose):
    centers = maryrose.camera_centers().double().numpy()
    for size in (4, 6, 9):
        assert sorted(farthest_views(centers, size)) == maryrose.splits[str(size)]


# ---------------------------------------------------------------------------------------------------------------
# Synthetic scene


def test_synthetic_layout_and_scene(synthetic_dir, synthetic):
    for folder in ("images", "masks", "depths", "sparse/0"):
        assert (synthetic_dir / folder).is_dir()
    assert synthetic.layout == "colmap" and synthetic.num_views == 12
    assert synthetic.images.shape == (12, 64, 64, 3) and synthetic.depth_units == "scene"
    assert synthetic.orbit_radius() == pytest.approx(ORBIT_RADIUS, rel=1e-5)
    assert set(synthetic.splits) == {"4", "6", "9", "test"}
    assert all(source.startswith("sparse_") for source in synthetic.split_sources.values())
    assert 0.02 < float(synthetic.masks.mean()) < 0.6


@pytest.mark.parametrize("object_name", ["synthetic", "tankard"])
def test_synthetic_points_reproject_inside_masks(request, object_name):
    """Every 3D point lands inside every view's mask (dilated by one pixel for the pixel grid)."""
    synthetic = request.getfixturevalue(object_name)
    pixels, depths = project(synthetic.viewmats.double(), synthetic.Ks.double(), synthetic.points.double())
    assert (depths > 0).all()
    dilated = torch.nn.functional.max_pool2d(synthetic.masks[:, None], 3, stride=1, padding=1)[:, 0]
    columns = pixels[..., 0].floor().long().clamp(0, synthetic.width - 1)
    rows = pixels[..., 1].floor().long().clamp(0, synthetic.height - 1)
    inside_image = (pixels[..., 0] >= 0) & (pixels[..., 0] < synthetic.width)
    inside_image &= (pixels[..., 1] >= 0) & (pixels[..., 1] < synthetic.height)
    assert inside_image.all()
    views = torch.arange(synthetic.num_views)[:, None].expand_as(rows)
    assert dilated[views, rows, columns].bool().all()


# view 0 looks at the tankard's end, which the other views see at a grazing angle or not at all: fewer pixels agree
@pytest.mark.parametrize("object_name, seen_share", [("synthetic", 0.4), ("tankard", 0.3)])
def test_synthetic_depth_maps_agree_across_views(request, object_name, seen_share):
    """Pixels of view 0 lifted with its depth map land, in every other view, on the surface that view's depth map
    sees (or behind it, when occluded) — never in front of it."""
    synthetic = request.getfixturevalue(object_name)
    rows, columns = torch.nonzero(synthetic.masks[0] > 0, as_tuple=True)
    depth = synthetic.depths[0, rows, columns].double()
    assert (depth > 0).all()
    pixels = torch.stack([columns + 0.5, rows + 0.5, torch.ones_like(depth)], 1).double()
    camera = torch.linalg.solve(synthetic.Ks[0].double(), pixels.T).T * depth[:, None]
    viewmat = synthetic.viewmats[0].double()
    world = (viewmat[:3, :3].T @ (camera.T - viewmat[:3, 3:])).T
    projected, point_depths = project(synthetic.viewmats[1:].double(), synthetic.Ks[1:].double(), world)
    column_index = projected[..., 0].floor().long()
    row_index = projected[..., 1].floor().long()
    size = synthetic.width
    valid = (column_index >= 0) & (column_index < size) & (row_index >= 0) & (row_index < size)
    views = torch.arange(1, synthetic.num_views)[:, None].expand_as(row_index)
    seen = synthetic.depths[views, row_index.clamp(0, size - 1), column_index.clamp(0, size - 1)].double()
    relative = (point_depths - seen) / point_depths
    agree = valid & (relative.abs() < 0.02)
    in_front = valid & (seen > 0) & (relative < -0.05)
    assert agree.sum() > seen_share * valid.sum()  # the rest is occluded in that view
    assert in_front.sum() < 0.02 * valid.sum()  # only pixel-grid effects at silhouette edges


def test_synthetic_cache_folders_differ_by_optics():
    default = SyntheticOptions(views=16, width=96, height=96)
    assert default.folder_name() == "synthetic-v3-16views-96x96-seed0"  # older caches keep their names
    tele = SyntheticOptions(views=16, width=96, height=96, fov_deg=18.6, radius=5.6)
    assert tele.folder_name() == "synthetic-v3-16views-96x96-seed0-fov18.6-radius5.6"
    # The synthetic-tele preset sees the object with maryrose's field of view (18.6 deg) from further away.
    focal = intrinsics(tele)[0, 0]
    assert math.degrees(2 * math.atan(48 / focal)) == pytest.approx(18.6)
    viewmat = dome_viewmats(tele)[0]
    center = -viewmat[:3, :3].T @ viewmat[:3, 3]
    assert np.linalg.norm(center - OBJECT_CENTER) == pytest.approx(5.6)


def test_synthetic_poses_are_exact(synthetic_dir):
    scene = load_scene(synthetic_dir, normalize=False)
    truth = torch.from_numpy(dome_viewmats(SYNTHETIC)).float()
    torch.testing.assert_close(scene.viewmats, truth, atol=1e-6, rtol=0)
    torch.testing.assert_close(scene.Ks[0], torch.from_numpy(intrinsics(SYNTHETIC)).float())
    assert scene.normalization == SceneNormalization.identity()
    assert (scene.camera_centers() - torch.from_numpy(OBJECT_CENTER).float()).norm(dim=1).allclose(
        torch.full((12,), SYNTHETIC.radius), atol=1e-5
    )


# ---------------------------------------------------------------------------------------------------------------
# Normalization


def test_normalization_round_trips_and_preserves_projections(synthetic_dir, synthetic):
    raw = load_scene(synthetic_dir, normalize=False)
    normalization = synthetic.normalization
    close = functools.partial(torch.testing.assert_close, atol=1e-5, rtol=0)
    close(normalization.apply_viewmats(raw.viewmats.double()).float(), synthetic.viewmats)
    close(normalization.invert_viewmats(synthetic.viewmats.double()).float(), raw.viewmats)
    close(normalization.invert_points(synthetic.points.double()).float(), raw.points)
    close(normalization.apply_points(raw.points.double()).float(), synthetic.points)
    torch.testing.assert_close(synthetic.depths, raw.depths * normalization.scale)
    raw_pixels, raw_depths = project(raw.viewmats.double(), raw.Ks.double(), raw.points.double())
    pixels, depths = project(synthetic.viewmats.double(), synthetic.Ks.double(), synthetic.points.double())
    torch.testing.assert_close(pixels, raw_pixels, atol=1e-3, rtol=0)
    torch.testing.assert_close(depths, raw_depths * normalization.scale, atol=1e-4, rtol=0)
    homogeneous = torch.cat([raw.points.double(), torch.ones(len(raw.points), 1, dtype=torch.float64)], 1)
    matrix = torch.from_numpy(normalization.matrix())
    torch.testing.assert_close((homogeneous @ matrix.T)[:, :3].float(), synthetic.points, atol=1e-5, rtol=0)


# ---------------------------------------------------------------------------------------------------------------
# LLFF and transforms.json conventions, against the synthetic scene's exact poses


def _strip_to_images(scene_dir: Path, out: Path) -> Path:
    out.mkdir()
    shutil.copytree(scene_dir / "images", out / "images")
    shutil.copytree(scene_dir / "masks", out / "masks")
    return out


@pytest.mark.parametrize("scene_name, options", [("synthetic_dir", SYNTHETIC), ("wide_dir", WIDE)])
def test_llff_layout_matches_exact_poses(request, tmp_path, scene_name, options):
    """Also on 64 x 48 images: LLFF's hwf column is height, width, focal (read as width, height the calibration
    would be 48 x 64, for images of 64 x 48)."""
    folder = _strip_to_images(request.getfixturevalue(scene_name), tmp_path / "llff")
    np.save(folder / "poses_bounds.npy", _llff_poses_bounds(options))
    # a hidden copy (macOS's ._ files on a shared drive) is not an image: it was counted against poses_bounds.npy
    shutil.copy(folder / "images" / "view_000.png", folder / "images" / "._view_000.png")
    scene = load_scene(folder, normalize=False)
    assert scene.layout == "llff" and (scene.width, scene.height) == (options.width, options.height)
    torch.testing.assert_close(scene.viewmats, torch.from_numpy(dome_viewmats(options)).float(), atol=1e-5, rtol=0)
    torch.testing.assert_close(scene.Ks[0], torch.from_numpy(intrinsics(options)).float())


def _llff_poses_bounds(options: SyntheticOptions = SYNTHETIC) -> np.ndarray:
    """The exact cameras of the synthetic scene of `options` as LLFF's poses_bounds.npy rows."""
    camera_to_world = np.linalg.inv(dome_viewmats(options))
    right, down, forward = camera_to_world[:, :3, 0], camera_to_world[:, :3, 1], camera_to_world[:, :3, 2]
    hwf = np.tile([options.height, options.width, intrinsics(options)[0, 0]], (options.views, 1))
    matrices = np.stack([down, right, -forward, camera_to_world[:, :3, 3], hwf], axis=2)  # [C,3,5]
    return np.concatenate([matrices.reshape(options.views, 15), np.ones((options.views, 2))], 1)


@pytest.mark.parametrize("column,value", [(14, math.nan), (14, 0.0), (14, -77.0), (14, math.inf), (4, math.nan)])
def test_a_calibration_that_is_not_a_camera_is_refused_at_load(synthetic_dir, tmp_path, column, value):
    """A NaN, zero or infinite focal length (or image height) ended in a linear-algebra traceback; a negative one
    trained to nonsense, silently. The loader names the image and the file."""
    folder = _strip_to_images(synthetic_dir, tmp_path / "llff")
    poses_bounds = _llff_poses_bounds()
    poses_bounds[3, column] = value
    np.save(folder / "poses_bounds.npy", poses_bounds)
    _expect_error(folder, re.escape(f"{folder / 'poses_bounds.npy'}: the calibration of view_003.png is not a "
                                    "camera's"))


@pytest.mark.parametrize("content", [b"", b"0 1 2\n", np.array(["a"] * 17), "npz"])
def test_an_llff_poses_file_that_is_not_an_array_of_numbers_is_named(synthetic_dir, tmp_path, content):
    """An empty .npy made numpy raise EOFError, which the command line printed as a bare "Aborted."; text asked
    the user to load it with allow_pickle."""
    folder = _strip_to_images(synthetic_dir, tmp_path / "llff")
    if isinstance(content, bytes):
        (folder / "poses_bounds.npy").write_bytes(content)
    elif isinstance(content, str):  # an archive of arrays under the .npy name
        with open(folder / "poses_bounds.npy", "wb") as handle:
            np.savez(handle, poses=_llff_poses_bounds())
    else:
        np.save(folder / "poses_bounds.npy", content)
    _expect_error(folder, re.escape(f"LLFF poses {folder / 'poses_bounds.npy'} ")
                  + "(is not a NumPy array file|holds <U1 values, expected real numbers|is an archive of arrays)")


def test_transforms_json_matches_exact_poses(synthetic_dir, tmp_path):
    folder = _strip_to_images(synthetic_dir, tmp_path / "nerfstudio")
    viewmats = dome_viewmats(SYNTHETIC)
    opengl = np.linalg.inv(viewmats) @ np.diag([1.0, -1.0, -1.0, 1.0])
    frames = [
        {"file_path": f"images/view_{index:03d}", "transform_matrix": opengl[index].tolist()}
        for index in reversed(range(12))
    ]
    fov = math.radians(SYNTHETIC.fov_deg)
    (folder / "transforms.json").write_text(json.dumps({"camera_angle_x": fov, "frames": frames}))
    scene = load_scene(folder, normalize=False)
    assert scene.layout == "transforms" and scene.image_names[0] == "images/view_000.png"
    torch.testing.assert_close(scene.viewmats, torch.from_numpy(viewmats).float(), atol=1e-5, rtol=0)
    torch.testing.assert_close(scene.Ks[0], torch.from_numpy(intrinsics(SYNTHETIC)).float())
    assert scene.masks is not None


def test_transforms_json_mask_and_depth_files_are_said_not_read(synthetic_dir, tmp_path, caplog):
    """nerfstudio's mask_path (the pixels to train on) and depth_file_path were dropped without a word: a scene whose
    object masks sat there trained without masks."""
    folder = _strip_to_images(synthetic_dir, tmp_path / "nerfstudio")
    _write_transforms(folder, SYNTHETIC, {"camera_angle_x": math.radians(SYNTHETIC.fov_deg)})
    with caplog.at_level("WARNING", logger="warpbags.data"):
        load_scene(folder)
    assert "not read" not in caplog.text
    meta = json.loads((folder / "transforms.json").read_text())
    for frame in meta["frames"]:
        frame["mask_path"] = frame["file_path"].replace("images/", "segmentation/") + ".png"
    meta["frames"][0]["depth_file_path"] = "depth/view_011.png"
    (folder / "transforms.json").write_text(json.dumps(meta))
    with caplog.at_level("WARNING", logger="warpbags.data"):
        load_scene(folder)
    assert "its frames' mask_path files are not read (warpbags reads object masks in masks/<image name>)" in caplog.text
    assert "its frames' depth_file_path files are not read (warpbags reads depth maps in depths/" in caplog.text


def _write_transforms(folder: Path, options: SyntheticOptions, fields: dict) -> None:
    """A transforms.json in `folder` of the exact cameras of the synthetic scene of `options` (frames without
    extension, in reverse order), with the file-wide `fields` (intrinsics, distortion)."""
    opengl = np.linalg.inv(dome_viewmats(options)) @ np.diag([1.0, -1.0, -1.0, 1.0])
    frames = [{"file_path": f"images/view_{index:03d}", "transform_matrix": opengl[index].tolist()}
              for index in reversed(range(options.views))]
    (folder / "transforms.json").write_text(json.dumps({**fields, "frames": frames}))


@pytest.mark.parametrize("fields, fx, fy, cx, cy", [
    ({"fl_x": 70.0, "fl_y": 75.0}, 70.0, 75.0, 32.0, 24.0),  # the principal point by default the image's centre
    ({"fl_x": 70.0, "fl_y": 75.0, "cx": 30.5, "cy": 25.0}, 70.0, 75.0, 30.5, 25.0),
    ({"camera_angle_x": 2 * math.atan(32 / 70), "camera_angle_y": 2 * math.atan(24 / 75)}, 70.0, 75.0, 32.0, 24.0),
])
def test_transforms_json_intrinsics_of_non_square_images_are_read_axis_by_axis(wide_dir, tmp_path, fields, fx, fy,
                                                                               cx, cy):
    """64 x 48 images and fl_x != fl_y: fy is fl_y (or from camera_angle_y over the height), cx and cy are read as
    given, else half the width and half the height."""
    folder = _strip_to_images(wide_dir, tmp_path / "wide")
    _write_transforms(folder, WIDE, fields)
    scene = load_scene(folder, normalize=False)
    assert scene.layout == "transforms" and (scene.width, scene.height) == (64, 48)
    torch.testing.assert_close(scene.viewmats, torch.from_numpy(dome_viewmats(WIDE)).float(), atol=1e-5, rtol=0)
    K = torch.tensor([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
    torch.testing.assert_close(scene.Ks, K.expand(WIDE.views, 3, 3))


def test_transforms_json_distorted_images_are_undistorted_to_the_pinhole_view(wide_dir, tmp_path):
    """As a distorted COLMAP camera's (below): the k1, k2, p1, p2 of a transforms.json give back the pinhole
    images, here of 64 x 48."""
    folder = _strip_to_images(wide_dir, tmp_path / "distorted")
    K = intrinsics(WIDE)
    coefficients = {"k1": 0.4, "k2": 0.1, "p1": 0.02, "p2": -0.02}  # 1.4% of the interior mask pixels move
    _distort_images_and_masks(folder, K, list(coefficients.values()))
    _write_transforms(folder, WIDE, {"fl_x": K[0, 0], "fl_y": K[1, 1], **coefficients})
    scene = load_scene(folder, normalize=False)
    truth = load_scene(wide_dir, load_depths=False)
    torch.testing.assert_close(scene.Ks, truth.Ks)
    _assert_undistorted(folder, scene, truth, (slice(None), slice(8, 40), slice(8, 56)))


def test_a_frame_file_path_without_extension_finds_its_image_of_any_extension_read(synthetic_dir, tmp_path):
    """Blender writes "./train/r_0" for "./train/r_0.png": a file_path without extension was looked up as .png alone,
    and JPEGs were "missing (named by the camera file)". It is looked up with each extension the loader reads, also
    in a downsampled folder; where none exists the file_path is named."""
    folder = _strip_to_images(synthetic_dir, tmp_path / "jpegs")
    for path in (folder / "images").glob("*.png"):
        cv2.imwrite(str(path.with_suffix(".jpg")), cv2.imread(str(path)))
        path.unlink()
    opengl = np.linalg.inv(dome_viewmats(SYNTHETIC)) @ np.diag([1.0, -1.0, -1.0, 1.0])
    frames = [{"file_path": f"images/view_{i:03d}", "transform_matrix": opengl[i].tolist()} for i in range(12)]
    (folder / "transforms.json").write_text(json.dumps({"camera_angle_x": math.radians(SYNTHETIC.fov_deg), "w": 64,
                                                        "h": 64, "frames": frames}))
    assert load_scene(folder, normalize=False).image_names[0] == "images/view_000.jpg"
    (folder / "images").rename(folder / "images_2")
    assert load_scene(folder, normalize=False, resolution=2).image_names[0] == "images/view_000.jpg"
    (folder / "images_2" / "view_003.jpg").unlink()
    _expect_error(folder, re.escape(f"{folder / 'transforms.json'}: frame file_path 'images/view_003' has no "
                                    f"extension, and no image {folder / 'images' / 'view_003'}.png, .jpg, .jpeg, .PNG, "
                                    ".JPG or .JPEG exists"), resolution=2)


def test_a_pose_that_is_not_a_rotation_is_refused_at_load(synthetic_dir, tmp_path):
    """A transform_matrix with a scale (some exporters fold one in) would train as a wrong camera, and every reader
    of the run would refuse its poses afterwards: the loader names it."""
    folder = _strip_to_images(synthetic_dir, tmp_path / "scaled")
    opengl = np.linalg.inv(dome_viewmats(SYNTHETIC)) @ np.diag([1.0, -1.0, -1.0, 1.0])
    opengl[3, :3, :3] *= 1.5
    frames = [{"file_path": f"images/view_{i:03d}", "transform_matrix": opengl[i].tolist()} for i in range(12)]
    (folder / "transforms.json").write_text(json.dumps({"camera_angle_x": math.radians(SYNTHETIC.fov_deg),
                                                        "frames": frames}))
    _expect_error(folder, r"transforms\*\.json: the pose of images/view_003.png is not a rotation", normalize=False)


def test_blender_test_views_are_never_chosen_for_training(synthetic_dir, tmp_path):
    """With transforms_train.json / transforms_test.json, the 4/6/9-view splits and any other view count are chosen
    among the train views: the test views (here the first six names, where farthest-point sampling starts) stay
    held out."""
    folder = _strip_to_images(synthetic_dir, tmp_path / "blender")
    opengl = np.linalg.inv(dome_viewmats(SYNTHETIC)) @ np.diag([1.0, -1.0, -1.0, 1.0])
    fov = math.radians(SYNTHETIC.fov_deg)
    for name, indices in (("train", range(6, 12)), ("test", range(6))):
        frames = [{"file_path": f"./images/view_{i:03d}", "transform_matrix": opengl[i].tolist()} for i in indices]
        (folder / f"transforms_{name}.json").write_text(json.dumps({"camera_angle_x": fov, "frames": frames}))
    scene = load_scene(folder, normalize=False)
    assert scene.splits["test"] == [0, 1, 2, 3, 4, 5]
    for views in (4, 5, 6):
        assert set(scene.train_views(views)) <= set(range(6, 12)), views
    (folder / "sparse_4.txt").write_text("0\n6\n7\n8\n")
    _expect_error(folder, r"split 4 of scene .* \(sparse_4.txt\) uses test views \[0\]", normalize=False)


@pytest.mark.parametrize("fields, named", [
    ({"fl_x": "wide"}, "fl_x is 'wide', not a finite number"),  # was float()'s ValueError
    ({"fl_x": None}, "fl_x is None, not a finite number"),  # TypeError
    ({"fl_x": True}, "fl_x is True, not a finite number"),  # a focal length of 1 px
    ({"fl_x": 60, "fl_y": 0}, "fl_y is 0, not above 0"),
    ({"fl_x": 60, "w": "sixty-four", "h": 64}, "w is 'sixty-four', not a finite number"),  # TypeError of width / 2
    ({"fl_x": 60, "w": 64, "h": -64}, "h is -64, not above 0"),
    ({"fl_x": 60, "cx": [32]}, "cx is [32], not a finite number"),  # TypeError of the K array
    ({"fl_x": 60, "cy": "middle"}, "cy is 'middle', not a finite number"),
    ({"camera_angle_x": 0}, "camera_angle_x is 0, not between 0 and 3.14159"),  # ZeroDivisionError
    ({"camera_angle_y": "tall"}, "camera_angle_y is 'tall', not a finite number"),
    ({"k1": "barrel"}, "k1 is 'barrel', not a finite number"),
    # a fisheye or equirectangular camera was taken for a distorted pinhole (its images undistorted as one)
    ({"camera_model": "OPENCV_FISHEYE", "k1": 0.1}, "camera_model 'OPENCV_FISHEYE' is not one warpbags reads"),
    ({"camera_model": "EQUIRECTANGULAR"}, "camera_model 'EQUIRECTANGULAR' is not one warpbags reads"),
    ({"is_fisheye": True, "k1": 0.1}, "a fisheye camera (is_fisheye true) is not one warpbags reads"),  # instant-ngp
])
def test_transforms_json_intrinsics_that_are_no_numbers_are_one_line(synthetic_dir, tmp_path, fields, named):
    """A focal length, image size, principal point or distortion coefficient of a transforms.json frame that is no
    number (or no usable one) was a ValueError, TypeError or ZeroDivisionError traceback: it is one line naming the
    file, the frame and the field."""
    folder = _strip_to_images(synthetic_dir, tmp_path / "intrinsics")
    opengl = np.linalg.inv(dome_viewmats(SYNTHETIC)) @ np.diag([1.0, -1.0, -1.0, 1.0])
    frames = [{"file_path": f"images/view_{i:03d}", "transform_matrix": opengl[i].tolist()} for i in range(12)]
    frames[3].update(fields)
    (folder / "transforms.json").write_text(json.dumps({"camera_angle_x": math.radians(SYNTHETIC.fov_deg),
                                                        "frames": frames}))
    _expect_error(folder, re.escape(f"{folder / 'transforms.json'}: frame images/view_003.png: {named}"))


@pytest.mark.parametrize("damage, named", [
    (lambda frames: frames.__setitem__(3, 5), "a frame is 5, not an object with a file_path"),  # was a TypeError
    (lambda frames: frames[3].__setitem__("file_path", None), "a frame has no file_path (a path, got null)"),
    (lambda frames: frames.append(dict(frames[3])), "image images/view_003.png is named by two frames"),
])
def test_transforms_json_frames_that_name_no_image_or_one_twice_are_one_line(synthetic_dir, tmp_path, damage, named):
    """A frame that is no object was a TypeError traceback, a null file_path read as the image "None.png", and an
    image named by two frames trained as two views (a 9-view split held it twice)."""
    folder = _strip_to_images(synthetic_dir, tmp_path / "frames")
    opengl = np.linalg.inv(dome_viewmats(SYNTHETIC)) @ np.diag([1.0, -1.0, -1.0, 1.0])
    frames = [{"file_path": f"images/view_{i:03d}", "transform_matrix": opengl[i].tolist()} for i in range(12)]
    damage(frames)
    (folder / "transforms.json").write_text(json.dumps({"camera_angle_x": math.radians(SYNTHETIC.fov_deg),
                                                        "frames": frames}))
    _expect_error(folder, re.escape(f"{folder / 'transforms.json'}: {named}"))


def test_an_instant_ngp_fisheye_is_refused_as_a_fisheye_camera_model_is(synthetic_dir, tmp_path):
    """instant-ngp's colmap2nerf.py writes COLMAP's SIMPLE_RADIAL_FISHEYE and RADIAL_FISHEYE cameras as
    "is_fisheye": true with k1 and k2, and no camera_model: they were read as distorted pinholes, their images
    undistorted as such, silently. is_fisheye false is a pinhole's."""
    folder = _strip_to_images(synthetic_dir, tmp_path / "instant-ngp")
    fisheye = {"camera_angle_x": math.radians(SYNTHETIC.fov_deg), "is_fisheye": True, "k1": 0.05, "k2": 0.01}
    _write_transforms(folder, SYNTHETIC, fisheye)
    _expect_error(folder, re.escape(f"{folder / 'transforms.json'}: frame images/view_011.png: a fisheye camera "
                                    "(is_fisheye true) is not one warpbags reads (OPENCV, PINHOLE, SIMPLE_PINHOLE, "
                                    "SIMPLE_RADIAL, RADIAL; undistort the images first)"))
    _write_transforms(folder, SYNTHETIC, {**fisheye, "is_fisheye": False, "k1": 0.0, "k2": 0.0})
    assert load_scene(folder, normalize=False).num_views == 12


def test_transforms_json_null_intrinsics_are_absent_ones(synthetic_dir, tmp_path):
    """null for an optional field (principal point, distortion, image size) is read as its absence, as before the
    fields were checked: the same cameras as without them (each frame naming one of nerfstudio's perspective camera
    models, or null)."""
    folder = _strip_to_images(synthetic_dir, tmp_path / "nulls")
    opengl = np.linalg.inv(dome_viewmats(SYNTHETIC)) @ np.diag([1.0, -1.0, -1.0, 1.0])
    frames = [{"file_path": f"images/view_{i:03d}", "transform_matrix": opengl[i].tolist()} for i in range(12)]
    (folder / "transforms.json").write_text(json.dumps({"camera_angle_x": math.radians(SYNTHETIC.fov_deg),
                                                        "frames": frames}))
    plain = load_scene(folder, normalize=False)
    for frame, model in zip(frames, ["PINHOLE", "SIMPLE_PINHOLE", "OPENCV", "SIMPLE_RADIAL", "RADIAL", None] * 2):
        frame.update({key: None for key in ("cx", "cy", "k1", "k3", "k4", "w", "h")}, camera_model=model)
    (folder / "transforms.json").write_text(json.dumps({"camera_angle_x": math.radians(SYNTHETIC.fov_deg),
                                                        "frames": frames}))
    torch.testing.assert_close(load_scene(folder, normalize=False).Ks, plain.Ks, rtol=0, atol=0)


def test_frame_paths_outside_the_scene_folder_are_one_line(synthetic_dir, tmp_path):
    folder = _strip_to_images(synthetic_dir, tmp_path / "outside")
    frames = [{"file_path": "/elsewhere/view_000.png", "transform_matrix": np.eye(4).tolist()}]
    (folder / "transforms.json").write_text(json.dumps({"camera_angle_x": 0.5, "frames": frames}))
    _expect_error(folder, r"transforms.json: frame file_path '/elsewhere/view_000.png' is outside the scene folder")


def test_frames_in_a_linked_image_folder_and_by_absolute_paths_inside_the_scene_are_read(synthetic_dir, tmp_path):
    """images/ a symbolic link to elsewhere (a DVC or git-annex cache): inside the scene folder as written; and a
    frame named by its absolute path inside the folder. "../" out of the folder stays refused (above)."""
    folder = _strip_to_images(synthetic_dir, tmp_path / "linked")
    (folder / "images").rename(tmp_path / "cache")
    (folder / "images").symlink_to(tmp_path / "cache", target_is_directory=True)
    opengl = np.linalg.inv(dome_viewmats(SYNTHETIC)) @ np.diag([1.0, -1.0, -1.0, 1.0])
    frames = [{"file_path": f"images/view_{i:03d}.png", "transform_matrix": opengl[i].tolist()} for i in range(12)]
    frames[0]["file_path"] = str(folder / "images" / "view_000.png")
    (folder / "transforms.json").write_text(json.dumps({"camera_angle_x": math.radians(SYNTHETIC.fov_deg),
                                                        "frames": frames}))
    scene = load_scene(folder, normalize=False)
    assert scene.num_views == 12 and scene.image_names[0] == "images/view_000.png"
    # the scene folder reached through a link, its frame named by the real path
    (tmp_path / "link").symlink_to(folder, target_is_directory=True)
    assert load_scene(tmp_path / "link", normalize=False).image_names[0] == "images/view_000.png"
    frames[0]["file_path"] = "images/../../cache/view_000.png"
    (folder / "transforms.json").write_text(json.dumps({"camera_angle_x": 0.5, "frames": frames}))
    _expect_error(folder, r"frame file_path 'images/../../cache/view_000.png' is outside the scene folder")


def test_a_text_colmap_model_directly_in_sparse_is_read(scene_copy, synthetic):
    model = scene_copy / "sparse" / "0"
    write_model(scene_copy / "sparse", synthetic.image_names, synthetic.viewmats.double().numpy(),
                synthetic.Ks.double().numpy(), synthetic.width, synthetic.height, binary=False)
    shutil.rmtree(model)
    scene = load_scene(scene_copy)
    assert scene.num_views == synthetic.num_views and scene.layout == synthetic.layout


def test_a_colmap_model_without_its_points_file_is_named_and_one_without_points_is_read(scene_copy, synthetic):
    """pycolmap refused a model of known poses without points3D.txt in its own words ("Check failed:
    (file).is_open()")."""
    write_model(scene_copy / "sparse" / "0", synthetic.image_names, synthetic.viewmats.double().numpy(),
                synthetic.Ks.double().numpy(), synthetic.width, synthetic.height, binary=False)
    for path in (scene_copy / "sparse" / "0").glob("*.bin"):
        path.unlink()
    points = scene_copy / "sparse" / "0" / "points3D.txt"
    points.unlink()
    _expect_error(scene_copy, r"points3D.txt is missing \(COLMAP model incomplete \(a model without points holds an "
                  r"empty points3D.txt\)\)")
    points.write_text("")
    assert load_scene(scene_copy).num_views == synthetic.num_views


@pytest.mark.parametrize("field, value", [("distortion", math.inf), ("cx", math.nan)])
def test_a_colmap_calibration_that_is_not_finite_is_refused_by_name(scene_copy, synthetic, field, value):
    """An infinite distortion coefficient loaded, and undistorted the view into an all-black image with an empty
    mask; a NaN principal point was reported as bad focal lengths."""
    Ks = synthetic.Ks.double().numpy().copy()
    distortions = np.zeros((synthetic.num_views, 4))
    if field == "cx":
        Ks[3, 0, 2] = value
    else:
        distortions[3, 1] = value
    shutil.rmtree(scene_copy / "sparse" / "0")
    write_model(scene_copy / "sparse" / "0", synthetic.image_names, synthetic.viewmats.double().numpy(), Ks,
                synthetic.width, synthetic.height, distortions=distortions)
    _expect_error(scene_copy, "the calibration of view_003.png is not a camera's .*"
                  + ("cx nan" if field == "cx" else r"distortion 0, inf, 0, 0"))


# ---------------------------------------------------------------------------------------------------------------
# Resolutions, distortion, depth formats, splits


def test_downsampled_resolution_scales_intrinsics(synthetic_dir, synthetic):
    half = load_scene(synthetic_dir, resolution=2)
    assert (half.width, half.height) == (32, 32) and half.masks.shape == (12, 32, 32)
    torch.testing.assert_close(half.Ks[:, :2], synthetic.Ks[:, :2] / 2)
    # the object centre comes from the masks' centroids, so it moves slightly with the mask resolution
    torch.testing.assert_close(half.viewmats[:, :3, :3], synthetic.viewmats[:, :3, :3])
    torch.testing.assert_close(half.viewmats, synthetic.viewmats, atol=0.02, rtol=0)


def test_downsampled_pngs_of_jpeg_images_are_the_files_read(scene_copy):
    """images/ of JPEGs and images_2/ of PNGs made from them (some tools convert to PNG when downsampling): at
    resolution 2 the PNGs are read, not the JPEGs decoded at half their size."""
    (scene_copy / "images_2").mkdir()
    for path in sorted((scene_copy / "images").glob("*.png")):
        image = cv2.imread(str(path))
        cv2.imwrite(str(path.with_suffix(".jpg")), image)
        path.unlink()
        half = cv2.resize(image, (32, 32), interpolation=cv2.INTER_AREA)
        cv2.imwrite(str(scene_copy / "images_2" / path.name), half[:, ::-1])  # mirrored, told from the JPEG's
    _rename_in_model(scene_copy, [f"view_{index:03d}.jpg" for index in range(12)])
    pngs = [cv2.imread(str(path))[..., ::-1] for path in sorted((scene_copy / "images_2").glob("*.png"))]
    np.testing.assert_array_equal(load_scene(scene_copy, resolution=2).images.numpy(),
                                  np.stack(pngs).astype(np.float32) / 255)


def test_images_that_no_camera_names_are_said(scene_copy, caplog):
    """A COLMAP model that registered some of the photographs (failed SfM, or an images.txt written one line per
    image, whose every other line pycolmap reads as points) trained on the rest without a word."""
    with caplog.at_level("WARNING", logger="warpbags.data"):
        load_scene(scene_copy)
    assert "left out" not in caplog.text
    shutil.copy(scene_copy / "images" / "view_003.png", scene_copy / "images" / "view_100.png")
    shutil.copy(scene_copy / "images" / "view_003.png", scene_copy / "images" / "._view_003.png")  # macOS's copy
    (scene_copy / "images" / "notes.txt").write_text("not an image")
    with caplog.at_level("WARNING", logger="warpbags.data"):
        scene = load_scene(scene_copy)
    assert scene.num_views == 12
    said = "1 image(s) in images/ have no camera in its colmap poses (e.g. images/view_100.png): left out"
    assert said in caplog.text


def test_masks_that_mark_the_background_or_everything_are_said(scene_copy, caplog):
    """Inverted masks (or crop masks, which mark the pixels to train on) and a mask that is object everywhere trained
    without a word, the poses far off (a review: 4 deg moved without noise became 16.6 and 20.2)."""
    with caplog.at_level("WARNING", logger="warpbags.data"):
        load_scene(scene_copy)
    assert "mask" not in caplog.text
    paths = sorted((scene_copy / "masks").glob("*.png"))
    masks = [cv2.imread(str(path), cv2.IMREAD_GRAYSCALE) for path in paths]
    cv2.imwrite(str(paths[2]), np.full((64, 64), 255, np.uint8))
    with caplog.at_level("WARNING", logger="warpbags.data"):
        load_scene(scene_copy)
    assert "the mask of view_002.png marks every pixel as object: that view holds no silhouette" in caplog.text
    caplog.clear()
    for path, mask in zip(paths, masks):
        cv2.imwrite(str(path), 255 - mask)
    with caplog.at_level("WARNING", logger="warpbags.data"):
        load_scene(scene_copy)
    assert "the masks of 12 of 12 views mark most of the image border as object (e.g. view_000.png)" in caplog.text


def test_photographs_too_large_for_memory_are_read_at_a_factor_that_fits(synthetic_dir, synthetic, monkeypatch,
                                                                        caplog):
    """A folder of full-size photographs whose float32 images and masks would pass the memory budget (119 photographs
    of 3648 px take 25 GiB) is read at the finest factor that fits, said in one warning; asked for a factor, the
    loader reads that one."""
    monkeypatch.setattr(loaders, "IMAGE_MEMORY_BUDGET", scene_bytes(12, 64, 64, 2))
    with caplog.at_level("WARNING", logger="warpbags.data"):
        scene = load_scene(synthetic_dir)
    assert (scene.width, scene.height) == (32, 32) and scene.resolution == 2
    assert "12 images of 64x64 px: read at 1/2 (32x32)" in caplog.text
    torch.testing.assert_close(scene.images, load_scene(synthetic_dir, resolution=2).images)
    assert load_scene(synthetic_dir, resolution=1).width == 64
    monkeypatch.setattr(loaders, "IMAGE_MEMORY_BUDGET", scene_bytes(12, 64, 64, 1))
    assert load_scene(synthetic_dir).width == 64


def test_a_factor_whose_images_exceed_the_machines_memory_is_refused(scene_copy, monkeypatch):
    monkeypatch.setattr(loaders, "physical_memory", lambda: scene_bytes(12, 64, 64, 2))
    _expect_error(scene_copy, r"12 images of 64x64 px at resolution 1 take 0\.0 GiB, more than this machine's .*: "
                  r"choose a coarser --resolution", resolution=1)
    assert load_scene(scene_copy, resolution=2).width == 32


def test_jpeg_photographs_and_masks_are_decoded_reduced(synthetic_dir, tmp_path):
    """JPEGs read at 1/2, 1/4 or 1/8 are decoded at that size by libjpeg (8x faster for 1/8) and agree with a full
    decode resized by area."""
    image = np.kron(cv2.imread(str(synthetic_dir / "images" / "view_000.png")), np.ones((4, 4, 1), np.uint8))
    path = tmp_path / "photo.jpg"
    cv2.imwrite(str(path), image, [cv2.IMWRITE_JPEG_QUALITY, 98])
    for factor in (2, 4, 8):
        reduced = read_image(path, factor)
        full = cv2.resize(read_image(path), reduced.shape[1::-1], interpolation=cv2.INTER_AREA)
        assert reduced.shape == (256 // factor, 256 // factor, 3)
        assert np.abs(reduced - full).mean() < 0.01, factor
    mask = np.kron(cv2.imread(str(synthetic_dir / "masks" / "view_000.png"), cv2.IMREAD_GRAYSCALE),
                   np.ones((4, 4), np.uint8))
    masks = tmp_path / "masks"
    masks.mkdir()
    cv2.imwrite(str(masks / "photo.jpg"), mask, [cv2.IMWRITE_JPEG_QUALITY, 98])
    read = read_masks(tmp_path, ["photo.jpg"], 64, 64, 4)[0]
    expected = cv2.resize(mask.astype(np.float32) / 255, (64, 64), interpolation=cv2.INTER_AREA) >= 0.5
    assert np.mean(read == expected) > 0.99


def test_a_jpeg_whose_sides_the_reduction_does_not_divide_is_read_where_a_png_is(tmp_path):
    """libjpeg's 1/8 decode of a 2001-row image is 251 rows, its last from one row of pixels: stretched to the 250 rows
    the intrinsics scale to, an edge 20 rows from the bottom moved 0.86 px from where the same image as PNG put it."""
    photo = np.zeros((2001, 96, 3), np.uint8)
    photo[:1981] = 255  # white above a dark band along the bottom
    rows = {}
    for suffix in (".png", ".jpg"):
        path = tmp_path / f"edge{suffix}"
        cv2.imwrite(str(path), photo, [cv2.IMWRITE_JPEG_QUALITY, 100])
        images, _, width, height = read_images([path], [path], 8)  # a full-size file read at 1/8
        assert (width, height) == (12, 250)
        rows[suffix] = images[0, :, 4:8, 1].sum(axis=0).mean()  # the white rows, to a fraction of a row
    assert rows[".jpg"] == pytest.approx(rows[".png"], abs=0.05)
    assert rows[".png"] == pytest.approx(1981 / 2001 * 250, abs=0.05)


def test_a_jpeg_cut_short_is_refused_by_name_as_image_and_as_mask(synthetic_dir, tmp_path):
    """libjpeg decodes a JPEG whose data stops (a copy or download cut short), grey from there on, and only warns
    on stderr: such an image trained as it was. It is refused by name, at every reduction; a whole one, also with
    bytes after its end (as some cameras append), reads."""
    image = cv2.imread(str(synthetic_dir / "images" / "view_000.png"))
    whole = tmp_path / "whole.jpg"
    cv2.imwrite(str(whole), image, [cv2.IMWRITE_JPEG_QUALITY, 95])
    data = whole.read_bytes()
    cut = tmp_path / "cut.jpg"
    cut.write_bytes(data[: len(data) // 2])
    for reduction in (1, 2):
        with pytest.raises(WarpbagsError, match=f"image {re.escape(str(cut))} is cut short"):
            read_image(cut, reduction)
    trailed = tmp_path / "trailed.jpg"  # a motion photo's video after the picture: any bytes, markers among them
    trailer = np.random.default_rng(0).integers(0, 256, 100_000, dtype=np.uint8).tobytes()
    trailed.write_bytes(data + b"\xff\xda\x00\x08" + trailer)
    np.testing.assert_array_equal(read_image(trailed), read_image(whole))
    progressive = io.BytesIO()  # several scans, each cut in turn
    Image.fromarray(image[..., ::-1]).save(progressive, "JPEG", progressive=True, quality=90)
    progressive = progressive.getvalue()
    for end in range(len(progressive) // 8, len(progressive) - 2, len(progressive) // 8):
        cut.write_bytes(progressive[:end])
        with pytest.raises(WarpbagsError, match="is cut short"):
            read_image(cut)
    masks = tmp_path / "masks"
    masks.mkdir()
    (masks / "cut.jpg").write_bytes(data[: len(data) // 2])
    with pytest.raises(WarpbagsError, match="mask .*cut.jpg is cut short"):
        read_masks(tmp_path, ["cut.jpg"], 64, 64, 1)


def test_an_image_that_cannot_be_read_is_one_line(synthetic_dir, monkeypatch):
    """A file the process may not read was a PermissionError traceback once images were read as bytes."""
    real = Path.read_bytes

    def refused(path):
        if path.name == "view_000.png":
            raise PermissionError(13, "Permission denied", str(path))
        return real(path)

    monkeypatch.setattr(Path, "read_bytes", refused)
    with pytest.raises(WarpbagsError, match=r"image .*view_000.png is unreadable \(PermissionError: \[Errno 13\]"):
        read_image(synthetic_dir / "images" / "view_000.png")


def test_llff_images_are_listed_whatever_the_case_of_their_extension(tmp_path):
    """An LLFF folder's image listing skipped IMG_x.Jpg: "69 poses but ... holds 68 images"."""
    shipped = packaged_scene_dir("maryrose")
    scene = tmp_path / "maryrose"
    shutil.copytree(shipped, scene)
    first = sorted((scene / "images_8").iterdir())[0]
    first.rename(first.with_suffix(".Jpg"))  # shipped as .JPG
    plain = load_scene(shipped, normalize=False)
    renamed = load_scene(scene, normalize=False)
    assert renamed.num_views == plain.num_views
    torch.testing.assert_close(renamed.images, plain.images, rtol=0, atol=0)


def test_an_exif_orientation_is_ignored_at_every_reduction_as_colmap_does(synthetic_dir, tmp_path):
    """A portrait phone photo stored landscape with EXIF orientation 6: its pixels (and a JPEG mask's) are read as
    stored at full size and when libjpeg decodes it reduced, as COLMAP reads them for its poses."""
    from PIL import Image

    stored = np.kron(cv2.imread(str(synthetic_dir / "images" / "view_000.png")), np.ones((2, 4, 1), np.uint8))
    exif = Image.Exif()
    exif[0x0112] = 6  # rotate 90 deg clockwise to display
    Image.fromarray(stored[..., ::-1]).save(tmp_path / "photo.jpg", quality=98, exif=exif)
    assert read_image(tmp_path / "photo.jpg").shape == (128, 256, 3)
    assert read_image(tmp_path / "photo.jpg", 2).shape == (64, 128, 3)
    masks = tmp_path / "masks"
    masks.mkdir()
    mask = np.kron(cv2.imread(str(synthetic_dir / "masks" / "view_000.png"), cv2.IMREAD_GRAYSCALE),
                   np.ones((2, 4), np.uint8))
    Image.fromarray(mask).save(masks / "photo.jpg", quality=98, exif=exif)
    for width, height, resolution in ((256, 128, 1), (128, 64, 2)):
        assert read_masks(tmp_path, ["photo.jpg"], width, height, resolution).shape == (1, height, width)


def test_masks_saved_as_0_and_1_are_read_and_an_empty_mask_is_named(scene_copy):
    mask = cv2.imread(str(scene_copy / "masks" / "view_003.png"), cv2.IMREAD_GRAYSCALE)
    expected = load_scene(scene_copy).masks[3]
    cv2.imwrite(str(scene_copy / "masks" / "view_003.png"), (mask > 127).astype(np.uint8))  # 0 / 1
    assert torch.equal(load_scene(scene_copy).masks[3], expected)
    # 16-bit PNGs, 0 / 1 and 0 / 65535: decoded as 8 bits the first read as empty ("holds no object pixel")
    for level in (1, 65535):
        cv2.imwrite(str(scene_copy / "masks" / "view_003.png"), (mask > 127).astype(np.uint16) * level)
        assert torch.equal(load_scene(scene_copy).masks[3], expected)
    cv2.imwrite(str(scene_copy / "masks" / "view_003.png"), np.zeros_like(mask))
    _expect_error(scene_copy, r"mask .*view_003.png holds no object pixel")


def _palette_png(indices: np.ndarray, colours: list[tuple[int, int, int]], path: Path) -> None:
    """`indices` saved as a palette PNG listing `colours` (fewer than the indices used: PIL's own label images)."""
    image = Image.fromarray(indices.astype(np.uint8), "P")
    image.putpalette([level for colour in colours for level in colour])
    image.save(path)


@pytest.mark.parametrize("save", [
    # a background-removal cutout: the object's colours, alpha 255 on it and 0 around (its colour is no mask)
    lambda mask, image, path: cv2.imwrite(str(path), np.dstack([image * mask[..., None], mask * 255])),
    # a white silhouette on transparency: white everywhere, the object in the alpha alone
    lambda mask, image, path: cv2.imwrite(str(path), np.dstack([np.full_like(image, 255), mask * 255])),
    lambda mask, image, path: Image.fromarray(np.dstack([np.full_like(mask, 255), mask * 255]), "LA").save(path),
    lambda mask, image, path: cv2.imwrite(str(path), np.dstack([image, mask * 255]).astype(np.uint16) * 257),
    # an alpha opaque everywhere, as editors save a black and white mask, marks nothing: the colour is the mask
    lambda mask, image, path: cv2.imwrite(str(path), np.dstack([np.dstack([mask * 255] * 3), np.full_like(mask, 255)])),
    # nor does one a pixel short of opaque, and a black and white mask on a transparent canvas is its colour too
    lambda mask, image, path: cv2.imwrite(str(path), np.dstack([np.dstack([mask * 255] * 3), np.pad(
        np.full((63, 64), 255, np.uint8), ((0, 1), (0, 0)), constant_values=254)])),
    lambda mask, image, path: cv2.imwrite(str(path), np.dstack([np.dstack([mask * 255] * 3),
                                                                 np.pad(np.full((60, 60), 255, np.uint8), 2)])),
    # the colour of transparent pixels is not drawn: a black object on a canvas transparent white was its canvas,
    # and a transparent white border around a black and white mask was object
    lambda mask, image, path: cv2.imwrite(str(path), np.dstack([np.dstack([(1 - mask) * 255] * 3), mask * 255])),
    lambda mask, image, path: cv2.imwrite(str(path), np.dstack([np.dstack([np.pad(mask[2:-2, 2:-2] * 255, 2,
                                                                                  constant_values=255)] * 3),
                                                                 np.pad(np.full((60, 60), 255, np.uint8), 2)])),
], ids=["cutout", "white-on-transparent", "grey-and-alpha", "16-bit-cutout", "opaque-alpha", "nearly-opaque-alpha",
        "transparent-border", "black-on-transparent-white", "transparent-white-border"])
def test_a_mask_file_with_an_alpha_channel_is_read_by_its_alpha_where_that_marks_the_background(scene_copy, save):
    """A mask with an alpha channel was read by its colour: a white silhouette on transparency was the whole image,
    a cutout the object's bright pixels, silently. An alpha that marks no background, or the alpha of a mask drawn in
    black and white, is not the mask: read by the alpha, those were the whole image."""
    expected = load_scene(scene_copy).masks
    path = scene_copy / "masks" / "view_003.png"
    mask = (cv2.imread(str(path), cv2.IMREAD_GRAYSCALE) > 127).astype(np.uint8)
    image = cv2.imread(str(scene_copy / "images" / "view_003.png"))
    save(mask, image, path)
    torch.testing.assert_close(load_scene(scene_copy).masks, expected, rtol=0, atol=0)


@pytest.mark.parametrize("save", [
    # DAVIS-style labels: index 1, coloured (128, 0, 0), grey 38 when read by colour
    lambda mask, path: _palette_png(mask, [(0, 0, 0), (128, 0, 0)], path),
    lambda mask, path: _palette_png(mask, [(0, 0, 0)], path),  # index 1 past the palette: black when read by colour
    lambda mask, path: _palette_png(1 - mask, [(255, 255, 255), (0, 0, 0)], path),  # greys: read by colour
    # a colour mask quantized to a palette, its object first: no label image (index 0 is not black), read by colour
    lambda mask, path: _palette_png(1 - mask, [(0, 255, 0), (0, 0, 0)], path),
    lambda mask, path: cv2.imwrite(str(path), mask.astype(np.uint16) * 255),  # 8-bit levels in a 16-bit file
], ids=["palette-davis", "palette-unlisted", "palette-greys-white-first", "palette-colour-object-first",
        "16-bit-0-255"])
def test_palette_and_16_bit_0_255_masks_are_read_as_their_object(scene_copy, save):
    """A palette PNG of labels (DAVIS: index 1 the object) and a 16-bit mask holding 0 / 255 were refused as "0
    everywhere"; a palette PNG is read by index where it is a label image (index 0 black, the labels coloured), by
    colour otherwise."""
    expected = load_scene(scene_copy).masks
    path = scene_copy / "masks" / "view_003.png"
    save((cv2.imread(str(path), cv2.IMREAD_GRAYSCALE) > 127).astype(np.uint8), path)
    torch.testing.assert_close(load_scene(scene_copy).masks, expected, rtol=0, atol=0)


@pytest.mark.parametrize("save, holds", [
    (lambda mask, path: cv2.imwrite(str(path), mask * 0), r"0 everywhere; 255 or 1 marks the object"),
    (lambda mask, path: cv2.imwrite(str(path), mask * 100), r"its values are at most 100, under half of 255; 255 or 1"),
    (lambda mask, path: cv2.imwrite(str(path), mask.astype(np.uint16) * 1000),
     r"its values are at most 1000, under half of 65535; 65535, 255 or 1 marks the object"),
    (lambda mask, path: _palette_png(mask * 0, [(0, 0, 0), (128, 0, 0)], path),
     r"index 0 everywhere; in a palette PNG an index above 0 marks it"),
    (lambda mask, path: cv2.imwrite(str(path), np.dstack([np.full_like(mask, 255)] * 3 + [mask * 100])),
     r"its alpha channel, the mask in a file with one, is at most 100 of 255; more than half opaque"),
    # VOC's colour label (128, 0, 0) saved as RGB is grey 38, and which colour labels the object is not guessed
    (lambda mask, path: cv2.imwrite(str(path), np.dstack([mask * 0, mask * 0, mask * 128])),
     r"it is in colour \(its channels differ\) and read as grey its values are at most 38, under half of 255; a mask "
     r"is grey: 0 around the object, 255 or 1 on it"),
], ids=["zeros", "8-bit-0-100", "16-bit-0-1000", "palette-index-0", "faint-alpha", "colour-label"])
def test_a_mask_without_object_is_named_by_the_values_it_holds(scene_copy, save, holds):
    """A mask without object was said to be "0 everywhere" whatever it held (a 16-bit mask of 0 / 1000, a palette
    PNG, an alpha channel): the error says what the file holds, and what marks the object in it."""
    path = scene_copy / "masks" / "view_003.png"
    save((cv2.imread(str(path), cv2.IMREAD_GRAYSCALE) > 127).astype(np.uint8), path)
    _expect_error(scene_copy, rf"mask .*view_003.png holds no object pixel \({holds}")


def test_a_mask_whose_object_vanishes_at_a_resolution_says_so(scene_copy):
    """One object pixel of a 64 px mask is a quarter of a pixel at 32 px: not "0 everywhere", which it is not."""
    mask = np.zeros((64, 64), np.uint8)
    mask[10, 10] = 255
    cv2.imwrite(str(scene_copy / "masks" / "view_003.png"), mask)
    _expect_error(scene_copy, r"mask .*view_003.png holds no object pixel at 32x32 \(its object is smaller than a "
                  r"pixel there\)", resolution=2)


def test_images_and_calibration_of_another_shape_are_named(scene_copy):
    """A calibration of 64x64 for images cropped (or rotated) to another shape would scale fx and fy apart; a pixel
    less, as the rounding of a reduced size leaves (400 x 300 at 1/8: 50 x 38), is not another shape; a few rows of
    a larger image are."""
    paths = sorted((scene_copy / "images").glob("*.png"))
    for path in paths:
        cv2.imwrite(str(path), cv2.imread(str(path))[:63])
    for path in (scene_copy / "masks").glob("*.png"):
        cv2.imwrite(str(path), cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)[:63])
    assert load_scene(scene_copy).height == 63
    for path in paths:
        cv2.imwrite(str(path), cv2.imread(str(path))[:48])
    _expect_error(scene_copy, r"image .*view_000.png is 64x48, its camera is calibrated at 64x64: another shape")
    # a crop of under 1% of a larger image is as far from the calibration's shape (it took 3 rows of 640)
    shutil.rmtree(scene_copy / "depths")
    for folder in ("images", "masks"):
        for path in (scene_copy / folder).glob("*.png"):
            cv2.imwrite(str(path), cv2.resize(cv2.imread(str(path)), (640, 640), interpolation=cv2.INTER_NEAREST)[:637])
    _expect_error(scene_copy, r"image .*view_000.png is 640x637, its camera is calibrated at 64x64: another shape")


def test_an_alpha_channel_in_some_images_only_is_named_where_alphas_are_the_masks(scene_copy):
    path = scene_copy / "images" / "view_004.png"
    mask = cv2.imread(str(scene_copy / "masks" / "view_004.png"), cv2.IMREAD_GRAYSCALE)
    cv2.imwrite(str(path), np.dstack([cv2.imread(str(path)), mask]))
    assert load_scene(scene_copy).masks is not None  # masks/ holds the masks: the alpha channels are not read
    shutil.rmtree(scene_copy / "masks")
    _expect_error(scene_copy, r"image .*view_000.png has no alpha channel, .*view_004.png's cuts its object out: "
                  r"give every image one or none")


def _alphas_as_masks(scene: Path) -> np.ndarray:
    """The scene's masks/ replaced by its images' alpha channels: each mask blurred, for levels about half."""
    alphas = []
    for path in sorted((scene / "images").glob("*.png")):
        mask = cv2.imread(str(scene / "masks" / path.name), cv2.IMREAD_GRAYSCALE)
        alphas.append(cv2.GaussianBlur(mask, (7, 7), 2))
        cv2.imwrite(str(path), np.dstack([cv2.imread(str(path)), alphas[-1]]))
    shutil.rmtree(scene / "masks")
    return np.stack(alphas)


def test_the_alpha_channels_of_the_images_are_their_masks_without_a_masks_folder(scene_copy):
    alphas = _alphas_as_masks(scene_copy)
    scene = load_scene(scene_copy)
    np.testing.assert_array_equal(scene.masks.numpy(), (alphas / 255 > 0.5).astype(np.float32))


def test_an_image_whose_alpha_channel_holds_no_object_is_named(scene_copy):
    """An alpha channel below half everywhere made an empty mask, and training "diverged" at iteration 0."""
    _alphas_as_masks(scene_copy)
    path = scene_copy / "images" / "view_003.png"
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    image[..., 3] = np.minimum(image[..., 3], 100)
    cv2.imwrite(str(path), image)
    _expect_error(scene_copy, r"image .*view_003.png holds no object pixel at 64x64 \(its alpha channel, the mask "
                  r"without a masks/ folder, is at most 39% opaque there; more than half opaque marks the object\)")
    image[..., 3] = 0
    cv2.imwrite(str(path), image)
    _expect_error(scene_copy, r"image .*view_003.png holds no object pixel at 64x64 \(.* is transparent everywhere")


def test_image_alphas_opaque_everywhere_are_no_masks(scene_copy):
    """RGBA exports, alpha 255 everywhere, without masks/: their alphas were masks of the whole frame, silently,
    where a mask file's alpha opaque everywhere is no mask. They are none; beside alphas that cut the object out,
    the first opaque one is named (its mask would be the whole frame)."""
    _alphas_as_masks(scene_copy)
    paths = sorted((scene_copy / "images").glob("*.png"))
    for path in (paths[5], paths[3]):
        image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        image[..., 3] = 255
        cv2.imwrite(str(path), image)
    _expect_error(scene_copy, r"image .*view_003.png's alpha channel is opaque everywhere at 64x64 \(more than "
                  r"half\), which says nothing of its object, where .*view_000.png's cuts its object out")
    for path in paths:
        image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        image[..., 3] = 255
        cv2.imwrite(str(path), image)
    assert load_scene(scene_copy).masks is None
    cv2.imwrite(str(paths[0]), cv2.imread(str(paths[0])))  # without an alpha channel, as opaque
    assert load_scene(scene_copy).masks is None


def test_a_mask_in_the_images_subfolder_wins_over_one_of_the_same_stem_at_the_top(scene_copy):
    from warpbags.data.images import _find_by_stem

    (scene_copy / "masks" / "cam1").mkdir()
    (scene_copy / "masks" / "cam1" / "view_000.jpg").write_bytes(b"")
    for stem_shared in (False, True):
        assert _find_by_stem(scene_copy / "masks", "cam1/view_000.png", (".png", ".jpg"), stem_shared) == (
            scene_copy / "masks" / "cam1" / "view_000.jpg")
    assert _find_by_stem(scene_copy / "masks", "cam0/view_000.png", (".png", ".jpg"), stem_shared=False) == (
        scene_copy / "masks" / "view_000.png")
    assert _find_by_stem(scene_copy / "masks", "cam0/view_000.png", (".png", ".jpg"), stem_shared=True) is None


def test_masks_and_depth_maps_are_found_whatever_the_case_of_their_extension(scene_copy):
    """view_000.Png and view_001.NPY were "missing" on a case-sensitive file system (only .png/.PNG were tried)."""
    reference = load_scene(scene_copy, normalize=False)
    (scene_copy / "masks" / "view_000.png").rename(scene_copy / "masks" / "view_000.Png")
    (scene_copy / "depths" / "view_001.npy").rename(scene_copy / "depths" / "view_001.NPY")
    (scene_copy / "masks" / "view_0001.png").write_bytes(b"")  # another stem that starts alike is not taken
    scene = load_scene(scene_copy, normalize=False)
    np.testing.assert_array_equal(scene.masks, reference.masks)
    np.testing.assert_array_equal(scene.depths, reference.depths)
    (scene_copy / "masks" / "view_000.Png").rename(scene_copy / "masks" / "view_000.tiff")
    _expect_error(scene_copy, r"mask for image view_000.png is missing: expected .*masks/view_000.png or .jpg")


def _rename_in_model(scene: Path, names: list[str]) -> None:
    """The COLMAP model of `scene` (64 x 64 px) with its images, in their sorted order, named `names`."""
    model = read_model(scene / "sparse" / "0")
    write_model(scene / "sparse" / "0", names, model.viewmats, np.stack([camera.K for camera in model.cameras]), 64,
                64, model.points, model.colors)


def test_images_of_one_name_in_two_folders_never_take_each_others_mask(scene_copy):
    """cam0/view_0.png and cam1/view_0.png (two rigs' cameras) with a flat masks/ of cam0's masks: the fallback to
    the bare file name gave cam1's views cam0's masks, silently. The bare name is looked up only for an image whose
    name no other image has; the others' masks are expected in their sub-folders."""
    expected = load_scene(scene_copy).masks
    shutil.rmtree(scene_copy / "depths")
    names = [f"cam{index // 6}/view_{index % 6}.png" for index in range(12)]
    for index, name in enumerate(names):
        for folder in ("images", "masks"):
            (scene_copy / folder / name).parent.mkdir(exist_ok=True)
            (scene_copy / folder / f"view_{index:03d}.png").rename(scene_copy / folder / name)
    _rename_in_model(scene_copy, names)
    torch.testing.assert_close(load_scene(scene_copy).masks, expected, rtol=0, atol=0)  # each in its sub-folder
    masks = scene_copy / "masks"
    for name in names[:6]:  # cam0's masks flat, cam1's none
        (masks / name).rename(masks / Path(name).name)
    shutil.rmtree(masks / "cam1")
    expected_path = masks / "cam0" / "view_0"
    _expect_error(scene_copy, re.escape(f"mask for image cam0/view_0.png is missing: expected {expected_path}.png or "
                                        ".jpg (images in other folders are named view_0 too"))


def test_a_camera_model_it_cannot_undistort_is_refused(scene_copy):
    """(The models it undistorts are measured against the pinhole views below.)"""
    model = pycolmap.Reconstruction()
    model.read(str(scene_copy / "sparse" / "0"))
    for camera in model.cameras.values():
        fx, fy, cx, cy = camera.params
        camera.model = "FULL_OPENCV"
        camera.params = [fx, fy, cx, cy, 0.05, -0.01, 0.0, 0.0] + [0.0] * 4
    model.write(str(scene_copy / "sparse" / "0"))
    with pytest.raises(WarpbagsError, match="FULL_OPENCV"):
        load_scene(scene_copy)


def test_a_camera_no_posed_image_uses_is_not_read(scene_copy, synthetic):
    """An extra camera of a model warpbags cannot read, which no image uses, stopped the whole scene."""
    model = pycolmap.Reconstruction()
    model.read(str(scene_copy / "sparse" / "0"))
    unused = pycolmap.Camera(model="OPENCV_FISHEYE", width=64, height=64, params=[60.0, 60.0, 32.0, 32.0, 0.1, 0, 0, 0])
    unused.camera_id = max(model.cameras) + 1
    model.add_camera(unused)
    model.write(str(scene_copy / "sparse" / "0"))
    torch.testing.assert_close(load_scene(scene_copy).Ks, synthetic.Ks, rtol=0, atol=0)


@pytest.mark.parametrize("model_name", ["SIMPLE_RADIAL", "RADIAL", "OPENCV"])
def test_distorted_images_are_undistorted_to_the_pinhole_view(scene_copy, synthetic, model_name):
    """Distort the pinhole renders with OpenCV's forward model, declare the distortion in cameras.bin: the loader
    must give back the pinhole images (up to interpolation) with the same K."""
    distortion = {"SIMPLE_RADIAL": [0.3, 0, 0, 0], "RADIAL": [0.25, 0.1, 0, 0], "OPENCV": [0.25, 0.05, 0.01, -0.01]}
    k1, k2, p1, p2 = distortion[model_name]
    model = pycolmap.Reconstruction()
    model.read(str(scene_copy / "sparse" / "0"))
    camera = next(iter(model.cameras.values()))
    fx, fy, cx, cy = camera.params
    params = {
        "SIMPLE_RADIAL": [fx, cx, cy, k1],
        "RADIAL": [fx, cx, cy, k1, k2],
        "OPENCV": [fx, fy, cx, cy, k1, k2, p1, p2],
    }
    for camera in model.cameras.values():
        camera.model, camera.params = model_name, params[model_name]
    model.write(str(scene_copy / "sparse" / "0"))
    _distort_images_and_masks(scene_copy, np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1]]), [k1, k2, p1, p2])
    scene = load_scene(scene_copy, load_depths=False)
    torch.testing.assert_close(scene.Ks, synthetic.Ks)
    _assert_undistorted(scene_copy, scene, synthetic, (slice(None), slice(8, 56), slice(8, 56)))


def _distort_images_and_masks(folder: Path, K: np.ndarray, coefficients: list[float]) -> None:
    """Distort the pinhole renders in `folder`'s images/ and masks/ by OpenCV's forward model of `coefficients`
    (k1, k2, p1, p2) for intrinsics `K` (pixel centres at +0.5): each distorted pixel samples the pinhole image where
    its undistorted ray lands."""
    K_opencv = K.copy()
    K_opencv[:2, 2] -= 0.5
    height, width = cv2.imread(str(next((folder / "masks").iterdir()))).shape[:2]
    rows, columns = np.mgrid[0:height, 0:width].astype(np.float64)
    distorted = np.stack([columns.ravel(), rows.ravel()], 1)[:, None, :]
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-10)
    undistorted = cv2.undistortPoints(distorted, K_opencv, np.array(coefficients), P=K_opencv, criteria=criteria)
    map_x = undistorted[:, 0, 0].reshape(height, width).astype(np.float32)
    map_y = undistorted[:, 0, 1].reshape(height, width).astype(np.float32)
    for subfolder, interpolation in (("images", cv2.INTER_LINEAR), ("masks", cv2.INTER_NEAREST)):
        for path in (folder / subfolder).iterdir():
            cv2.imwrite(str(path), cv2.remap(cv2.imread(str(path)), map_x, map_y, interpolation))


def _assert_undistorted(folder: Path, scene, truth, interior: tuple[slice, ...]) -> None:
    """`scene`, loaded from `folder` of distorted images and masks, holds `truth`'s pinhole ones inside `interior`
    (away from the borders, which resampling loses)."""
    files = sorted((folder / "masks").iterdir())
    distorted_masks = torch.from_numpy(np.stack([cv2.imread(str(path), 0) > 127 for path in files])).float()
    mismatch_before = (distorted_masks[interior] != truth.masks[interior]).float().mean()
    mismatch_after = (scene.masks[interior] != truth.masks[interior]).float().mean()
    assert mismatch_before > 0.003  # the distortion is visible
    assert mismatch_after < 0.1 * mismatch_before, (mismatch_after, mismatch_before)
    assert (scene.images[interior] - truth.images[interior]).abs().mean() < 0.02  # texture: bilinear twice


def test_zoe_depth_png_millimetres(scene_copy):
    shutil.rmtree(scene_copy / "depths")
    (scene_copy / "zoe_depth").mkdir()
    for index in range(12):
        cv2.imwrite(str(scene_copy / "zoe_depth" / f"view_{index:03d}.png"), np.full((64, 64), 1500 + index, np.uint16))
    scene = load_scene(scene_copy)
    assert scene.depth_units == "relative"
    assert scene.depths[3, 10, 10].item() == pytest.approx(1.503)


def test_an_8_bit_zoe_depth_png_is_refused(scene_copy):
    """An 8-bit PNG (a picture of the depths, as depth estimators also save) was read as depths of at most 255 mm."""
    shutil.rmtree(scene_copy / "depths")
    (scene_copy / "zoe_depth").mkdir()
    for index in range(12):
        cv2.imwrite(str(scene_copy / "zoe_depth" / f"view_{index:03d}.png"), np.full((64, 64), 150, np.uint8))
    _expect_error(scene_copy, r"depth map .*view_000.png is not a single-channel 16-bit PNG")


def test_missing_split_files_use_preset_then_farthest_point(scene_copy, caplog):
    for path in scene_copy.glob("sparse_*.txt"):
        path.unlink()
    scene = load_scene(scene_copy, default_splits={"4": [1, 2, 3, 5]})
    assert scene.splits["4"] == [1, 2, 3, 5] and scene.split_sources["4"] == "preset"
    assert scene.split_sources["6"] == "farthest-point" and len(scene.splits["6"]) == 6
    assert scene.splits["6"] == sorted(farthest_views(scene.camera_centers().double().numpy(), 6))
    train = set(scene.splits["4"]) | set(scene.splits["6"]) | set(scene.splits["9"])
    assert not train & set(scene.splits["test"])
    assert "farthest-point" in caplog.text


def test_preset_splits_are_held_to_the_test_views_and_a_preset_test_split_is_held_out(scene_copy):
    for path in scene_copy.glob("sparse_*.txt"):
        path.unlink()
    (scene_copy / "sparse_test.txt").write_text("1\n7\n")
    _expect_error(scene_copy, r"split 4 of scene .* \(preset\) uses test views \[1\]",
                  default_splits={"4": [1, 2, 3, 5]})
    (scene_copy / "sparse_test.txt").unlink()
    scene = load_scene(scene_copy, default_splits={"test": [0, 1, 2, 3, 4, 5]})
    assert set(scene.splits["6"]) == set(range(6, 12))  # the farthest-point choice keeps the preset's test views out


def test_object_centre_of_forward_facing_views_falls_back_with_a_warning(caplog):
    # Three cameras side by side, all looking down +z: their optical axes never meet.
    viewmats = np.tile(np.eye(4), (3, 1, 1))
    viewmats[:, 0, 3] = [1.0, 0.0, -1.0]  # centres at x = -1, 0, 1
    Ks = np.tile(np.array([[50.0, 0.0, 16.0], [0.0, 50.0, 16.0], [0.0, 0.0, 1.0]]), (3, 1, 1))
    points = np.array([[0.0, 0.0, 5.0], [1.0, 0.0, 6.0], [0.0, 1.0, 9.0]])
    np.testing.assert_array_equal(object_center(viewmats, Ks, None, points), [0.0, 0.0, 6.0])
    assert "nearly parallel" in caplog.text and "median of the 3 SfM points" in caplog.text
    caplog.clear()
    np.testing.assert_array_equal(object_center(viewmats, Ks), [0.0, 0.0, 0.0])
    assert "nearly parallel" in caplog.text and "mean camera centre" in caplog.text
    caplog.clear()
    eyes = torch.tensor([[4.0, 0.0, 1.0], [0.0, 4.0, 1.0], [-4.0, 0.0, 1.0]], dtype=torch.float64)
    converging = torch.stack([look_at(eye, torch.zeros(3, dtype=torch.float64)) for eye in eyes]).numpy()
    np.testing.assert_allclose(object_center(converging, Ks, None, points), [0.0, 0.0, 0.0], atol=1e-12)
    assert caplog.text == ""  # the rays meet: no fallback, no warning


def test_train_views_and_noise(synthetic):
    assert synthetic.train_views(4) == synthetic.splits["4"]
    assert len(synthetic.train_views(5)) == 5
    from warpbags.data.noise import PoseNoise, noisy_viewmats

    noisy = noisy_viewmats(synthetic, PoseNoise(rot_fixed_deg=15.0, trans_std=0.0, seed=3))
    relative = noisy[:, :3, :3] @ synthetic.viewmats[:, :3, :3].transpose(1, 2)
    angles = torch.rad2deg(torch.arccos(((relative.diagonal(dim1=1, dim2=2).sum(-1) - 1) / 2).clamp(-1, 1)))
    torch.testing.assert_close(angles, torch.full((12,), 15.0), atol=1e-2, rtol=0)


# ---------------------------------------------------------------------------------------------------------------
# Bad input: one-line WarpbagsError naming the file or value, nothing written


def _snapshot(folder: Path) -> dict[str, int]:
    return {str(path.relative_to(folder)): path.stat().st_mtime_ns for path in folder.rglob("*")}


def _expect_error(folder: Path, match: str, **kwargs) -> None:
    before = _snapshot(folder) if folder.is_dir() else None
    with pytest.raises(WarpbagsError, match=match) as error:
        load_scene(folder, **kwargs)
    assert "\n" not in str(error.value)
    if before is not None:
        assert _snapshot(folder) == before


def test_a_resolution_the_scene_does_not_ship_names_the_folders_it_has(maryrose):
    """maryrose ships images_8/ only: -r 1 said its first image was missing, not that the folder was."""
    with pytest.raises(WarpbagsError, match=re.escape(f"no images_1/ or images/ folder in {maryrose.root} "
                                                      "(resolution 1); it has images_8/")):
        load_scene(maryrose.root, resolution=1)


def test_a_resolution_of_0_is_refused_for_a_preset_as_for_its_folder(maryrose):
    """`-r 0` loaded a preset at its own factor (0 read as "not given") and was refused for the same folder."""
    for scene in ("maryrose", maryrose.root):
        with pytest.raises(WarpbagsError, match="resolution must be 1, 2, 4 or 8, got 0"):
            open_scene(scene, resolution=0)


def test_missing_folder(tmp_path):
    _expect_error(tmp_path / "nowhere", "nowhere does not exist")


def test_a_scene_named_by_a_file_or_with_no_frames_says_so(synthetic_dir, tmp_path):
    """A file named as a scene was "no folder ... and no preset of that name"; an empty frames list "has no
    'frames' list"."""
    (tmp_path / "a-file").write_text("")
    with pytest.raises(WarpbagsError, match=f"{re.escape(str(tmp_path / 'a-file'))} is a file, not a scene folder"):
        open_scene(str(tmp_path / "a-file"))
    folder = _strip_to_images(synthetic_dir, tmp_path / "empty")
    (folder / "transforms.json").write_text(json.dumps({"camera_angle_x": 0.5, "frames": []}))
    _expect_error(folder, "transforms.json: its 'frames' list is empty")


def test_no_cameras(tmp_path):
    (tmp_path / "images").mkdir()
    _expect_error(tmp_path, "no cameras in")


@pytest.mark.parametrize("name", ["cameras.bin", "images.bin"])
def test_missing_model_file(scene_copy, name):
    (scene_copy / "sparse" / "0" / name).unlink()
    _expect_error(scene_copy, f"{name} is missing")


@pytest.mark.parametrize("name", ["cameras.bin", "images.bin"])
@pytest.mark.parametrize("content", ["garbage", "truncated"])
def test_corrupt_model_file(scene_copy, name, content):
    path = scene_copy / "sparse" / "0" / name
    data = path.read_bytes()
    path.write_bytes(b"\x07not a colmap file" if content == "garbage" else data[: len(data) // 2])
    _expect_error(scene_copy, "COLMAP model")


def test_image_named_by_model_absent(scene_copy):
    (scene_copy / "images" / "view_005.png").unlink()
    _expect_error(scene_copy, "view_005.png is missing")


def test_mask_missing(scene_copy):
    (scene_copy / "masks" / "view_007.png").unlink()
    _expect_error(scene_copy, "mask for image view_007.png is missing")


def test_mask_wrong_size(scene_copy):
    cv2.imwrite(str(scene_copy / "masks" / "view_002.png"), np.zeros((50, 70), np.uint8))
    _expect_error(scene_copy, r"mask .*view_002.png is 70x50, its image is 64x64")


@pytest.mark.parametrize("width, height", [(100, 80), (130, 130)])
def test_a_jpeg_mask_of_a_wrong_size_is_named_by_its_own_size_as_a_png_is(scene_copy, width, height):
    """A JPEG mask was checked after libjpeg decoded it at 1/2: 100 x 80 was named "50x40", and 130 x 130, for
    images of 64 px, passed as 65 px (where the same PNG is refused)."""
    path = scene_copy / "masks" / "view_002.png"
    mask = cv2.resize(cv2.imread(str(path), cv2.IMREAD_GRAYSCALE), (width, height), interpolation=cv2.INTER_NEAREST)
    cv2.imwrite(str(path.with_suffix(".jpg")), mask)
    path.unlink()
    _expect_error(scene_copy, rf"mask .*view_002.jpg is {width}x{height}, its image is 64x64")


def test_masks_of_one_resolution_only_are_named_at_the_others(scene_copy):
    """images/ and masks_2/ alone: the masks were read at resolution 2 and the scene had none at 1 or 4, silently."""
    (scene_copy / "masks").rename(scene_copy / "masks_2")
    assert load_scene(scene_copy, resolution=2).masks.shape == (12, 32, 32)
    for resolution in (1, 4):
        _expect_error(scene_copy, rf"no masks/ or masks_{resolution}/ folder in .*scene for resolution {resolution}, "
                      r"only masks_2/ \(for --resolution 2\): read the scene at a resolution that has masks, or add "
                      r"masks/", resolution=resolution)


@pytest.mark.parametrize("lines", ["0\n3\n7\n", "0\n3\n3\n7\n", ""])
def test_split_of_the_wrong_size_or_with_repeats(scene_copy, lines):
    (scene_copy / "sparse_4.txt").write_text(lines)
    _expect_error(scene_copy, r"sparse_4.txt: a split of 4 views needs 4 different view indices")


def test_split_index_out_of_range(scene_copy):
    (scene_copy / "sparse_4.txt").write_text("0\n3\n12\n7\n")
    _expect_error(scene_copy, r"sparse_4.txt:3: view index 12 out of range for 12 images")


def test_split_files_with_a_byte_order_mark_are_read_and_other_encodings_named(scene_copy):
    """Notepad's UTF-8 byte-order mark was "'\ufeff0' is not a view index", PowerShell's UTF-16 (its `>`) a
    UnicodeDecodeError traceback."""
    (scene_copy / "sparse_4.txt").write_text("0\n3\n5\n7\n", encoding="utf-8-sig")
    assert load_scene(scene_copy).splits["4"] == [0, 3, 5, 7]
    (scene_copy / "sparse_4.txt").write_text("0\n3\n5\n7\n", encoding="utf-16")
    _expect_error(scene_copy, r"sparse_4.txt is not UTF-8 text \(PowerShell's > writes UTF-16\): save it as UTF-8")


def test_unreadable_image(scene_copy):
    (scene_copy / "images" / "view_004.png").write_bytes(b"not a png")
    _expect_error(scene_copy, "view_004.png is unreadable")


def test_fewer_images_than_views(synthetic):
    with pytest.raises(WarpbagsError, match="12 images, fewer than --views 20"):
        synthetic.train_views(20)


def test_unknown_scene_and_missing_dataset(tmp_path):
    with pytest.raises(WarpbagsError, match="no preset of that name"):
        open_scene(str(tmp_path / "missing"))
    with pytest.raises(WarpbagsError, match=r"scene kitchen not found \(looked in .*360_v2.zip"):
        open_scene("kitchen", root=tmp_path)
    with pytest.raises(WarpbagsError, match=r"scene moldgoldcape not found .*git clone https://github.com/vork/mold"):
        open_scene("moldgoldcape", root=tmp_path)
    with pytest.raises(WarpbagsError, match=r"scene ethiopianhead not found .*git clone https://github.com/vork/ethi"):
        open_scene("ethiopianhead", root=tmp_path)


# ---------------------------------------------------------------------------------------------------------------
# CLI


def test_cli_info_prints_summary(synthetic_dir):
    result = CliRunner().invoke(app, ["info", str(synthetic_dir)])
    assert result.exit_code == 0, result.output
    for text in ("64 x 64", "split 4", "orbit radius", "4.0000", "masks", "depth maps", "fx "):
        assert text in result.output


def _info_rows(output: str) -> dict[str, str]:
    """The rows of `warpbags info`'s table, label to value; a value wrapped onto further lines joined by spaces."""
    rows, label = {}, None
    for line in output.splitlines():
        cells = re.split(r"[│|]", line)
        if len(cells) != 4:
            continue
        name, value = cells[1].strip(), cells[2].strip()
        if name:
            label, rows[name] = name, value
        elif label is not None:
            rows[label] += " " + value
    return rows


def test_cli_info_prints_the_masks_depth_maps_and_source_radius_it_has(synthetic_dir, scene_copy):
    """Values, not labels: masks and depth maps yes (no once removed); the source orbit radius, the mean distance
    of the cameras from the object centre before normalization, is the normalized radius over the scale."""
    result = CliRunner().invoke(app, ["info", str(synthetic_dir)])
    assert result.exit_code == 0, result.output
    rows = _info_rows(result.output)
    scene = load_scene(synthetic_dir)
    assert rows["masks"] == "yes" and rows["depth maps"] == f"yes ({scene.depth_units} units)"
    source = float(re.search(r"source orbit radius (\d+\.\d+)\)", rows["normalization"]).group(1))
    assert source == pytest.approx(ORBIT_RADIUS / scene.normalization.scale, abs=1e-4)
    raw = load_scene(synthetic_dir, normalize=False)
    center = torch.tensor(scene.normalization.center)
    assert source == pytest.approx(float((raw.camera_centers() - center).norm(dim=1).mean()), abs=1e-3)
    shutil.rmtree(scene_copy / "masks")
    shutil.rmtree(scene_copy / "depths")
    result = CliRunner().invoke(app, ["info", str(scene_copy)])
    assert result.exit_code == 0, result.output
    rows = _info_rows(result.output)
    assert rows["masks"] == "no" and rows["depth maps"] == "no"


def test_cli_info_of_a_preset_under_data_root_reads_that_folder(synthetic_dir, tmp_path, monkeypatch):
    """`info kitchen --data-root DIR` reads DIR/kitchen (a copy of the synthetic scene; $WARPBAGS_DATA names an empty
    folder, which --data-root overrides) at the preset's 1/4. A folder longer than the 80 columns of output that is
    not a terminal is folded onto further lines: the table cut it short with an ellipsis."""
    root = tmp_path / ("data-root-" + "d" * 80)
    shutil.copytree(synthetic_dir, root / "kitchen")
    (tmp_path / "elsewhere").mkdir()
    monkeypatch.setenv("WARPBAGS_DATA", str(tmp_path / "elsewhere"))
    result = CliRunner().invoke(app, ["info", "kitchen", "--data-root", str(root)])
    assert result.exit_code == 0, result.output
    rows = _info_rows(result.output)
    assert rows["folder"].replace(" ", "") == str(root / "kitchen")
    assert rows["resolution"] == "16 x 16"


def test_cli_info_at_a_resolution_prints_that_resolution(synthetic_dir):
    """`info SCENE -r 2`: the images and intrinsics at half the scene's 64 x 64."""
    result = CliRunner().invoke(app, ["info", str(synthetic_dir), "-r", "2"])
    assert result.exit_code == 0, result.output
    rows = _info_rows(result.output)
    assert rows["resolution"] == "32 x 32"
    assert rows["intrinsics"].startswith(f"fx {intrinsics(SYNTHETIC)[0, 0] / 2:.2f}  fy ")


@pytest.mark.parametrize("make_bad", ["missing_folder", "corrupt_cameras", "missing_kitchen"])
def test_cli_bad_input_exits_cleanly(scene_copy, tmp_path, make_bad):
    arguments = ["info", str(scene_copy)]
    if make_bad == "missing_folder":
        arguments = ["info", str(tmp_path / "absent")]
    elif make_bad == "corrupt_cameras":
        (scene_copy / "sparse" / "0" / "cameras.bin").write_bytes(b"junk")
    else:
        arguments = ["info", "kitchen", "--data-root", str(tmp_path / "empty")]
    result = CliRunner().invoke(app, arguments)
    assert result.exit_code == 2
    assert "Traceback" not in result.output and not isinstance(result.exception, WarpbagsError)
    assert result.output.count("error:") == 1


def test_cli_synth_writes_a_loadable_scene(tmp_path):
    result = CliRunner().invoke(app, ["synth", str(tmp_path / "out"), "--views", "6", "--size", "24"])
    assert result.exit_code == 0, result.output
    scene = load_scene(tmp_path / "out")
    assert scene.num_views == 6 and scene.width == 24 and scene.depths is not None
    again = CliRunner().invoke(app, ["synth", str(tmp_path / "out"), "--views", "6", "--size", "24"])
    assert again.exit_code == 2 and "not empty" in again.output
    (tmp_path / "a-file").write_text("")
    onto_a_file = CliRunner().invoke(app, ["synth", str(tmp_path / "a-file"), "--views", "6", "--size", "24"])
    assert onto_a_file.exit_code == 2 and "a-file is a file, not a folder" in " ".join(onto_a_file.output.split())


def _same_object_views(folders: list[Path], index: int) -> tuple[list, list, np.ndarray]:
    """View `index` of two synthetic scene folders that show the same object from the same cameras: their masks and
    depth maps are asserted equal; returns the masks, the images (int levels) and the first's background pixels
    (edge pixels, which mix object rays, left out)."""
    stem = f"view_{index:03d}"
    masks = [cv2.imread(str(folder / "masks" / f"{stem}.png")) for folder in folders]
    depths = [np.load(folder / "depths" / f"{stem}.npy") for folder in folders]
    assert np.array_equal(*masks) and np.array_equal(*depths), stem
    images = [cv2.imread(str(folder / "images" / f"{stem}.png")).astype(int) for folder in folders]
    return masks, images, cv2.dilate(masks[0][..., 0], np.ones((3, 3), np.uint8)) == 0


def test_synth_seed_changes_the_textures_and_sfm_points_not_the_object_or_cameras(tmp_path):
    """--seed picks the texture crops and the SfM points sampled from the masks; the object's shape and the dome of
    cameras stay (masks, depth maps, poses). Only the crops of the non-square photographs move (the coffee
    counterweight, the cat bucket): a few percent of the object's pixels."""
    for seed in (0, 1):
        result = CliRunner().invoke(app, ["synth", str(tmp_path / f"seed{seed}"), "--views", "4", "--size", "32",
                                          "--seed", str(seed)])
        assert result.exit_code == 0, result.output
    folders = [tmp_path / "seed0", tmp_path / "seed1"]
    assert [json.loads((folder / "synthetic.json").read_text())["seed"] for folder in folders] == [0, 1]
    for index in range(4):
        masks, images, background = _same_object_views(folders, index)
        changed = np.abs(images[0] - images[1]).max(2) > 10  # levels of 255
        assert not changed[background].any(), index
        assert changed[masks[0][..., 0] > 0].mean() > 0.02, index
    models = [read_model(folder / "sparse" / "0") for folder in folders]
    np.testing.assert_array_equal(models[0].viewmats, models[1].viewmats)
    assert models[0].points.shape == models[1].points.shape and not np.allclose(models[0].points, models[1].points)


def test_synthetic_preset_generated_once_into_cache(tmp_path, monkeypatch):
    import dataclasses

    from warpbags.data import catalog

    preset = dataclasses.replace(catalog.SCENES["synthetic"], synthetic={"views": 5, "width": 20, "height": 20})
    monkeypatch.setitem(catalog.SCENES, "synthetic", preset)
    monkeypatch.setenv("WARPBAGS_CACHE", str(tmp_path / "cache"))
    scene = open_scene("synthetic")
    assert scene.name == "synthetic" and scene.num_views == 5 and scene.root.parent == tmp_path / "cache"
    stamp = (scene.root / "synthetic.json").stat().st_mtime_ns
    assert open_scene("synthetic").num_views == 5
    assert (scene.root / "synthetic.json").stat().st_mtime_ns == stamp
    assert [path.name for path in (tmp_path / "cache").iterdir()] == [scene.root.name]


def test_synthetic_cache_keeps_the_scene_another_process_finished_first(tmp_path, monkeypatch):
    """Two benchmarks asking for one uncached scene at once: the one that finishes second finds the folder taken
    (its rename fails, as measured with two bench/pose_recovery.py processes) and keeps the other's copy."""
    import os

    from warpbags.data import synthetic
    from warpbags.data.synthetic import ensure_synthetic_scene

    options = SyntheticOptions(views=4, width=16, height=16, num_points=40)
    others = generate_synthetic_scene(tmp_path / "other", options)
    cache = tmp_path / "cache"
    real_replace = os.replace

    def the_other_lands_first(source, target):
        shutil.copytree(others, target, dirs_exist_ok=True)
        return real_replace(source, target)

    monkeypatch.setattr(synthetic.os, "replace", the_other_lands_first)
    folder = ensure_synthetic_scene(options, cache_dir=cache)
    assert folder == cache / options.folder_name() and (folder / "synthetic.json").is_file()
    assert [path.name for path in cache.iterdir()] == [folder.name]  # no staging folder left behind
    assert ensure_synthetic_scene(options, cache_dir=str(cache)) == folder  # a str folder too (was a TypeError)


@pytest.mark.parametrize("settings, flags, suffix", [
    (dict(light_jitter_deg=30.0, gain_jitter=0.1), ["--light-jitter-deg", "30", "--gain-jitter", "0.1"],
     "-light_jitter30-gain_jitter0.1"),
    (dict(turntable_light=True), ["--turntable-light"], "-turntable_light1"),
])
def test_synthetic_lighting_changes_the_images_and_nothing_else(tmp_path, settings, flags, suffix):
    plain = SyntheticOptions(views=4, width=24, height=24)
    lit = SyntheticOptions(views=4, width=24, height=24, **settings)
    assert lit.folder_name() == plain.folder_name() + suffix
    generate_synthetic_scene(tmp_path / "plain", plain)
    result = CliRunner().invoke(app, ["synth", str(tmp_path / "lit"), "--views", "4", "--size", "24", *flags])
    assert result.exit_code == 0, result.output
    folders = [tmp_path / "plain", tmp_path / "lit"]
    for index in range(4):
        _, images, background = _same_object_views(folders, index)
        assert np.array_equal(images[0][background], images[1][background])
        assert np.abs(images[0] - images[1])[~background].mean() > 3  # levels of 255


@pytest.mark.parametrize("flags, message", [
    (["--gain-jitter", "-1"], "gain jitter in [0, 1], got 0.0 and -1.0"),
    (["--gain-jitter", "1e6"], "gain jitter in [0, 1], got 0.0 and 1000000.0"),  # images of 0 and 255 only
    (["--light-jitter-deg", "720"], "light jitter must be in [0, 180] deg"),
    (["--object", "teapot"], "unknown synthetic object 'teapot'"),
    # NaN passes `>= 0` and wrote garbage images; a huge image ended in numpy's ArrayMemoryError, a negative seed in
    # numpy's ValueError
    (["--gain-jitter", "nan"], "gain_jitter must be a finite number, got nan"),
    (["--light-jitter-deg", "nan"], "light_jitter_deg must be a finite number, got nan"),
    (["--light-jitter-deg", "inf"], "light_jitter_deg must be a finite number, got inf"),
    (["--size", "100000000"], "at most 1000 views and 2048 pixels a side"),
    (["--views", "100000000"], "at most 1000 views and 2048 pixels a side"),
    (["--seed", "-1"], "seed must be >= 0, got -1"),
])
def test_synth_refuses_a_bad_setting_and_writes_nothing(tmp_path, flags, message):
    result = CliRunner().invoke(app, ["synth", str(tmp_path / "bad"), "--views", "4", *flags])
    lines = [line for line in result.output.splitlines() if line.strip()]
    assert result.exit_code == 2 and len(lines) == 1 and message in lines[0], result.output
    assert not (tmp_path / "bad").exists() and list(tmp_path.iterdir()) == []  # no staging folder left either


def test_masks_of_an_odd_size_are_read_at_a_downsampled_resolution(tmp_path):
    """A 33 px capture read at 1/2 has 16 px images (rounded as any downsampled read), and its 33 px masks were refused
    as "33x33, its image is 16x16"."""
    result = CliRunner().invoke(app, ["synth", str(tmp_path / "odd"), "--views", "4", "--size", "33"])
    assert result.exit_code == 0, result.output
    full, half = load_scene(tmp_path / "odd"), load_scene(tmp_path / "odd", resolution=2)
    assert (half.width, half.height) == (16, 16) and half.masks.shape == (4, 16, 16)
    resized = np.stack([cv2.resize(mask, (16, 16), interpolation=cv2.INTER_AREA) >= 0.5 for mask in full.masks.numpy()])
    np.testing.assert_array_equal(half.masks.numpy(), resized)
    # the same masks as JPEGs, which libjpeg would decode at 1/2 as 17 px: decoded whole instead
    for mask in sorted((tmp_path / "odd" / "masks").glob("*.png")):
        cv2.imwrite(str(mask.with_suffix(".jpg")), cv2.imread(str(mask), cv2.IMREAD_GRAYSCALE),
                    [cv2.IMWRITE_JPEG_QUALITY, 100])
        mask.unlink()
    np.testing.assert_array_equal(load_scene(tmp_path / "odd", resolution=2).masks.numpy(), resized)


def test_synth_into_the_current_folder_and_a_write_that_fails_are_one_line(tmp_path, monkeypatch):
    """`synth .` was a ValueError traceback (a path with no name to stage beside), a full disk an OSError one."""
    (tmp_path / "here").mkdir()
    monkeypatch.chdir(tmp_path / "here")
    inode = os.stat(".").st_ino
    result = CliRunner().invoke(app, ["synth", ".", "--views", "4", "--size", "16"])
    assert result.exit_code == 0, result.output
    assert load_scene(Path(".")).num_views == 4 and os.stat(".").st_ino == inode  # filled, not replaced

    def disk_full(*args, **kwargs):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(np, "save", disk_full)
    result = CliRunner().invoke(app, ["synth", str(tmp_path / "full"), "--views", "4", "--size", "16"])
    lines = [line for line in result.output.splitlines() if line.strip()]
    assert result.exit_code == 2 and len(lines) == 1, result.output
    assert f"cannot write the scene into {tmp_path / 'full'}: OSError: [Errno 28] No space left" in lines[0]
    assert sorted(path.name for path in tmp_path.iterdir()) == ["here"]  # no scene, no staging folder


def test_synth_stopped_by_sigterm_leaves_no_partial_scene(tmp_path):
    """The staging folder was removed on Ctrl-C only: SIGTERM's default ended the process with it half-written."""
    code, output = stopped_by_sigterm(["synth", str(tmp_path / "scene"), "--views", "400", "--size", "96"],
                                      lambda: any(tmp_path.glob(".scene.partial-*/images/*.png")))
    assert code == 143 and "stopped by SIGTERM" in output, output
    assert list(tmp_path.iterdir()) == []


def test_synth_writes_the_tankard_as_its_own_scene(tmp_path):
    result = CliRunner().invoke(app, ["synth", str(tmp_path / "tankard"), "--views", "4", "--size", "32",
                                      "--object", "tankard"])
    assert result.exit_code == 0, result.output
    options = SyntheticOptions(views=4, width=32, height=32, object="tankard")
    assert options.folder_name() == SyntheticOptions(views=4, width=32, height=32).folder_name() + "-objecttankard"
    assert json.loads((tmp_path / "tankard" / "synthetic.json").read_text())["object"] == "tankard"
    generate_synthetic_scene(tmp_path / "excavator", SyntheticOptions(views=4, width=32, height=32))
    for index in range(4):
        tankard, excavator = (cv2.imread(str(tmp_path / name / "masks" / f"view_{index:03d}.png"), 0) > 127
                              for name in ("tankard", "excavator"))
        assert tankard.any() and (tankard != excavator).mean() > 0.02


def test_turntable_light_stands_still_in_every_camera():
    turntable = SyntheticOptions(views=4, width=24, height=24, turntable_light=True)
    viewmats = dome_viewmats(turntable)
    lights = [light for light, _ in view_lighting(turntable, viewmats)]
    for viewmat, light in zip(viewmats, lights):  # the same light in each camera's axes: it turns with the camera
        assert np.allclose(viewmat[:3, :3] @ light, LIGHT_IN_CAMERA)
    assert np.degrees(np.arccos(np.clip(lights[0] @ lights[2], -1, 1))) > 45  # opposite sides, other lights
    plain = SyntheticOptions(views=4, width=24, height=24)
    assert all(np.array_equal(light, LIGHT_DIRECTION) for light, _ in view_lighting(plain, viewmats))


def test_on_background_puts_the_masked_object_on_a_grey_level_or_colour():
    from warpbags.data.scene import Scene

    images = torch.rand(2, 3, 4, 3, generator=torch.Generator().manual_seed(0))
    masks = torch.zeros(2, 3, 4)
    masks[:, 1:, 2:] = 1
    scene = Scene("s", Path("."), "colmap", ["a.png", "b.png"], images, masks, None, None,
                  torch.eye(4).repeat(2, 1, 1), torch.eye(3).repeat(2, 1, 1), 4, 3)
    white, coloured = scene.on_background(1.0), scene.on_background((0.25, 0.5, 0.75))
    inside = masks.bool()
    assert torch.equal(white[inside], images[inside]) and torch.equal(coloured[inside], images[inside])
    assert (white[~inside] == 1).all()
    assert torch.equal(coloured[~inside], torch.tensor([0.25, 0.5, 0.75]).expand(int((~inside).sum()), 3))
    unmasked = dataclasses.replace(scene, masks=None)
    assert unmasked.on_background(1.0) is images  # without masks there is no background to replace


def test_downscaling_refuses_a_view_whose_object_vanishes(synthetic):
    """A mask thresholded empty at the training size (or a pyramid level) would give that view unbounded silhouette
    distances (1e37: the chamfer became inf, "training diverged"): the view is named instead."""
    small = synthetic.downscaled(synthetic.width // 4)
    assert all(mask.any() for mask in small.masks)  # the object stays at a quarter of the size
    masks = synthetic.masks.clone()
    masks[2] = 0
    masks[2, 10:12, 10:12] = 1  # 4 object pixels: none left at a quarter of the size
    with pytest.raises(WarpbagsError, match=f"object of view {synthetic.image_names[2]} covers under half a pixel"):
        dataclasses.replace(synthetic, masks=masks).downscaled(synthetic.width // 4, keep_objects=True)
    # evaluation downscales held-out views too: there an empty mask only leaves a white target
    assert not dataclasses.replace(synthetic, masks=masks).downscaled(synthetic.width // 4).masks[2].any()


def test_a_synthetic_scene_of_an_odd_size_warns_of_nothing(tmp_path):
    """At 65 px a ray missing the sphere along an axis made numpy print 'invalid value encountered in multiply'
    to the user's terminal (its normal, unused, was inf * 0)."""
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        generate_synthetic_scene(tmp_path / "odd", SyntheticOptions(views=4, width=65, height=65, num_points=40))

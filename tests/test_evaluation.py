"""`warpbags eval`: pose accuracy and held-out image metrics of a finished run."""

from __future__ import annotations

import json
import math
import os
import re
import shutil
import sys
import types
from pathlib import Path

import numpy as np
import pytest
import torch
from conftest import stopped_by_sigterm
from typer.testing import CliRunner

from warpbags.alignment import centre_floor_errors
from warpbags.cli.main import app
from warpbags.data import ORBIT_RADIUS, SyntheticOptions, ensure_synthetic_scene, load_scene
from warpbags.data.colmap import read_model, write_model
from warpbags.errors import WarpbagsError
from warpbags.evaluation import (FlipMetric, LpipsMetric, comparison_file_names, evaluate_run, image_metrics,
                                 pose_accuracy)
from warpbags.run_folder import load_run
from warpbags.gaussians import read_ply, write_ply
from warpbags.losses import load_lpips

runner = CliRunner()


@pytest.fixture(scope="module")
def finished_run(tmp_path_factory):
    scene = ensure_synthetic_scene(SyntheticOptions(views=16, width=64, height=64),
                                   cache_dir=tmp_path_factory.mktemp("cache"))
    out = tmp_path_factory.mktemp("runs") / "run"
    result = runner.invoke(app, ["train", str(scene), "--iters", "8", "--rot-noise-deg", "4", "--trans-noise", "0.05",
                                 "--out", str(out)])
    assert result.exit_code == 0, result.output
    return out


def test_eval_writes_metrics_and_pictures(finished_run):
    result = runner.invoke(app, ["eval", str(finished_run), "--refine-iters", "3"])
    assert result.exit_code == 0, result.output
    report = json.loads((finished_run / "eval.json").read_text())
    assert report["test_views"] >= 2 and report["alignment"] == "procrustes"
    for name in ("procrustes", "pairwise"):
        for stage in ("initial", "final"):
            entry = report["poses"][name][stage]
            assert len(entry["rotation_deg"]) == 4 and entry["rotation_deg_mean"] >= 0
    # free gauge: all four cameras carry the injected noise (std 4 deg, so a mean |angle| of about 3.2 deg)
    initial = report["poses"]["procrustes"]["initial"]["rotation_deg"]
    assert 0.5 < float(np.mean(initial)) < 8.0
    # the centre floor: what the centres alone force, per camera and as the mean shown in the table (Procrustes only),
    # each stage's of its own poses
    run = load_run(finished_run)
    for stage, poses in (("initial", run.poses_init), ("final", run.poses_final)):
        entry = report["poses"]["procrustes"][stage]
        floor = centre_floor_errors(poses.double(), run.poses_true.double(), torch.zeros(3, dtype=torch.float64))
        np.testing.assert_allclose(entry["rotation_deg_centre_floor"], floor.numpy(), rtol=1e-6, atol=1e-9)
        assert entry["rotation_deg_centre_floor_mean"] == pytest.approx(np.mean(entry["rotation_deg_centre_floor"]))
        assert "rotation_deg_centre_floor" not in report["poses"]["pairwise"][stage]
    assert report["poses"]["procrustes"]["initial"]["rotation_deg_centre_floor"] != \
        report["poses"]["procrustes"]["final"]["rotation_deg_centre_floor"]
    # how far the pose errors move the object, per camera, under every alignment; noisy poses move it by pixels
    for name in ("procrustes", "pairwise"):
        for stage in ("initial", "final"):
            entry = report["poses"][name][stage]
            assert len(entry["reprojection_px"]) == 4
            assert entry["reprojection_px_mean"] == pytest.approx(np.mean(entry["reprojection_px"]))
    assert report["poses"]["procrustes"]["initial"]["reprojection_px_mean"] > 0.5
    assert "centre floor" in result.output and "px" in result.output
    assert report["pose_noise_injected"] is True and "training-camera pose error" in result.output
    for key in ("images", "images_after_test_pose_refinement"):
        mean = report[key]["mean"]
        assert 5.0 < mean["psnr"] < 60.0 and 0.0 < mean["ssim"] <= 1.0
        assert len(report[key]["per_view"]) == report["test_views"]
        # FLIP needs no weights: always a number here, the mean of the per-view values
        assert report["flip_unavailable"] is None and 0.0 < mean["flip"] < 1.0
        assert mean["flip"] == pytest.approx(np.mean([view["flip"] for view in report[key]["per_view"]]))
    assert "FLIP" in result.output
    # the refined row renders the refined test poses: every view's picture changes
    for before, after in zip(report["images"]["per_view"], report["images_after_test_pose_refinement"]["per_view"]):
        assert before["psnr"] != after["psnr"]
    # LPIPS is a number exactly when its network loads here (offline: never, and never a made-up number).
    _, unavailable = load_lpips()
    assert report["lpips_unavailable"] == unavailable
    for key in ("images", "images_after_test_pose_refinement"):
        values = [report[key]["mean"]["lpips"]] + [view["lpips"] for view in report[key]["per_view"]]
        assert all(value is None for value in values) if unavailable else all(value >= 0 for value in values)
    pictures = sorted((finished_run / "eval").glob("*.png"))
    assert len(pictures) == report["test_views"]


def test_pose_accuracy_is_zero_for_true_poses(finished_run):
    run = load_run(finished_run)
    run.poses_final = run.poses_true.clone()
    report = pose_accuracy(run)
    assert report["procrustes"]["final"]["rotation_deg_mean"] < 1e-4
    assert report["procrustes"]["final"]["translation_mean"] < 1e-5
    assert report["procrustes"]["final"]["rotation_deg_centre_floor_mean"] < 1e-4
    assert report["procrustes"]["final"]["reprojection_px_mean"] < 1e-4


def test_test_pose_refinement_brings_a_camera_four_degrees_off_back_exactly():
    """L-BFGS against the frozen Gaussians (`refine_poses`): two cameras, each turned about 4 deg about the object and
    shifted by 6% of its distance, return to the poses their targets were rendered from, to float precision (100
    Adam steps, as refinement was before, end 0.07-0.15 deg off), and a camera started there stays there."""
    import math

    from conftest import random_scene

    from warpbags.camera_optimizer import corrected_viewmats
    from warpbags.evaluation import refine_poses
    from warpbags.gaussians import render_gaussians
    from warpbags.lie import rotation_error_deg

    scene = random_scene(n=1500, cams=2, width=64, height=64, dtype=torch.float32, seed=0, sh_degree=0,
                         scale_range=(0.02, 0.08))
    params = dict(means=scene["means"], quats=scene["quats"], scales=scene["scales"].log(),
                  opacities=torch.logit(scene["opacities"]), sh0=scene["colors"])
    true, Ks = scene["viewmats"], scene["Ks"]
    with torch.no_grad():
        targets, _, _ = render_gaussians(params, true, Ks, 64, 64, sh_degree=0, backgrounds=torch.ones(2, 3))
    turn = [math.radians(a) for a in (3, -2, 2, -2, 3, -2)]
    deltas = torch.tensor([[*turn[:3], 0.02, -0.015, 0.03], [*turn[3:], -0.02, 0.01, -0.02]])
    start = corrected_viewmats("object", true, deltas, torch.zeros(2, 3))

    def degrees_off(viewmats):
        return rotation_error_deg(viewmats[:, :3, :3], true[:, :3, :3])

    assert (degrees_off(start) > 4).all()
    assert (degrees_off(refine_poses(params, start, Ks, targets, 64, 64, 0, iters=30)) < 0.01).all()
    assert (degrees_off(refine_poses(params, true, Ks, targets, 64, 64, 0, iters=30)) < 0.01).all()


def test_image_metrics_are_psnr_of_the_clamped_render_and_the_literatures_ssim():
    g = torch.Generator().manual_seed(0)
    target = torch.rand(2, 24, 20, 3, generator=g)
    image = target + 0.05 * torch.randn(2, 24, 20, 3, generator=g)  # renders may leave [0, 1]: scored clamped
    assert image.max() > 1 and image.min() < 0
    clamped = image.clamp(0, 1)
    metrics = image_metrics(image, target, LpipsMetric())
    mse = ((clamped.double() - target.double()) ** 2).mean(dim=(1, 2, 3))
    for view in range(2):
        assert metrics["per_view"][view]["psnr"] == pytest.approx(float(-10 * torch.log10(mse[view])), rel=1e-9)
        t, i = target[view].double().numpy(), clamped[view].double().numpy()
        assert metrics["per_view"][view]["ssim"] == pytest.approx(_gaussian_window_ssim(i, t), rel=1e-9)
    assert metrics["mean"]["psnr"] == pytest.approx(float((-10 * torch.log10(mse)).mean()), rel=1e-9)


def test_ssim_of_images_smaller_than_its_window_is_scored():
    """An image smaller than the 11 x 11 window is scored as 3DGS scores it (zero-padded), not refused."""
    from warpbags.evaluation import ssim

    target = np.random.default_rng(0).random((8, 9, 3))
    assert ssim(target, target) == pytest.approx(1.0)
    assert 0.0 < ssim(0.8 * target + 0.1, target) < 1.0
    assert ssim(target[:2], target[:2]) == pytest.approx(1.0)
    assert ssim(target[:8, :8], target[:8, :8]) == pytest.approx(_gaussian_window_ssim(target[:8, :8], target[:8, :8]))


def test_ssim_counts_the_border_as_gaussianobject_does():
    """GaussianObject scores with 3DGS's ssim, whose window is zero-padded at the border and averaged over every
    pixel; scikit-image's leaves the 5-pixel border out. On an object amid white background the two differ (the
    border is where the images agree), and eval reported scikit-image's while its docs said GaussianObject's."""
    from skimage.metrics import structural_similarity

    from warpbags.evaluation import ssim

    rng = np.random.default_rng(1)
    target = np.ones((40, 48, 3))
    target[12:28, 14:34] = rng.random((16, 20, 3))  # an object on white
    image = np.clip(target + 0.3 * rng.standard_normal(target.shape) * (target < 1), 0, 1)
    ours = ssim(image, target)
    assert ours == pytest.approx(_gaussian_window_ssim(image, target), rel=1e-12)
    # in float64 whatever the arrays' dtype (float32 statistics are off by about 1e-6)
    single = image.astype(np.float32), target.astype(np.float32)
    assert ssim(*single) == pytest.approx(_gaussian_window_ssim(*(a.astype(np.float64) for a in single)), rel=1e-12)
    cropped = structural_similarity(target, image, channel_axis=-1, data_range=1.0, gaussian_weights=True, sigma=1.5,
                                    use_sample_covariance=False)
    assert ours > cropped + 0.01


def _gaussian_window_ssim(image: np.ndarray, target: np.ndarray) -> float:
    """3DGS's SSIM (utils/loss_utils.py), written out: an 11 x 11 Gaussian window of sigma 1.5 over the images
    zero-padded by 5 pixels, population statistics, C1 = 0.01^2, C2 = 0.03^2, averaged over every pixel and
    channel."""
    offsets = np.arange(11) - 5
    window = np.exp(-offsets ** 2 / (2 * 1.5 ** 2))
    window = np.outer(window, window) / np.outer(window, window).sum()

    def blurred(x):  # the window's weighted sum around every pixel, zeros beyond the border
        h, w = x.shape
        padded = np.pad(x, 5)
        return np.array([[(window * padded[r:r + 11, c:c + 11]).sum() for c in range(w)] for r in range(h)])

    maps = []
    for channel in range(3):
        x, y = image[..., channel], target[..., channel]
        mx, my = blurred(x), blurred(y)
        vx, vy, cxy = blurred(x * x) - mx ** 2, blurred(y * y) - my ** 2, blurred(x * y) - mx * my
        c1, c2 = 0.01 ** 2, 0.03 ** 2
        maps.append((2 * mx * my + c1) * (2 * cxy + c2) / ((mx ** 2 + my ** 2 + c1) * (vx + vy + c2)))
    return float(np.mean(maps))


class MeanAbsoluteDifference(torch.nn.Module):
    """Stands in for LPIPS-VGG: one distance per image pair, [B, 1, 1, 1], as `lpips.LPIPS` returns."""

    def forward(self, images, targets):
        return (images - targets).abs().mean(dim=(1, 2, 3), keepdim=True)


def test_image_metrics_report_the_lpips_network_distance(monkeypatch):
    package = types.ModuleType("lpips")
    package.LPIPS = lambda **options: MeanAbsoluteDifference()
    monkeypatch.setitem(sys.modules, "lpips", package)
    g = torch.Generator().manual_seed(1)
    target = torch.rand(2, 12, 10, 3, generator=g)
    image = (target + 0.1 * torch.randn(2, 12, 10, 3, generator=g)).clamp(0, 1)
    lpips_metric = LpipsMetric()
    assert lpips_metric.unavailable is None
    metrics = image_metrics(image, target, lpips_metric)
    # The images in [0, 1], as GaussianObject's evaluation gives them to LPIPS (the package documents [-1, 1]).
    expected = (image.double() - target.double()).abs().mean(dim=(1, 2, 3))
    for view in range(2):
        assert metrics["per_view"][view]["lpips"] == pytest.approx(expected[view].item(), rel=1e-5)
    assert metrics["mean"]["lpips"] == pytest.approx(expected.mean().item(), rel=1e-5)


class RecordingMeanAbsoluteDifference(MeanAbsoluteDifference):
    """`MeanAbsoluteDifference` that keeps the images it was given."""

    def __init__(self):
        super().__init__()
        self.inputs = []

    def forward(self, images, targets):
        self.inputs.append((images, targets))
        return super().forward(images, targets)


def test_lpips_metric_gives_the_network_the_images_in_zero_to_one(monkeypatch):
    """`LpipsMetric` feeds the network [1, 3, H, W] float32 images as they are, in [0, 1], as GaussianObject's
    render.py does for the numbers it publishes (the package documents [-1, 1]; the repair loss scales to that)."""
    network = RecordingMeanAbsoluteDifference()
    package = types.ModuleType("lpips")
    package.LPIPS = lambda **options: network
    monkeypatch.setitem(sys.modules, "lpips", package)
    rng = np.random.default_rng(2)
    image, target = rng.random((6, 5, 3)), rng.random((6, 5, 3))
    LpipsMetric()(image, target)
    (given_image, given_target), = network.inputs
    expected = lambda a: torch.from_numpy(a).permute(2, 0, 1)[None].float()  # noqa: E731
    torch.testing.assert_close(given_image, expected(image), rtol=0, atol=0)
    torch.testing.assert_close(given_target, expected(target), rtol=0, atol=0)


def test_flip_is_zero_for_the_same_image_and_grows_with_the_distortion():
    g = torch.Generator().manual_seed(3)
    target = torch.rand(1, 32, 40, 3, generator=g) * 0.6 + 0.2
    noise = torch.randn(1, 32, 40, 3, generator=g)
    assert FlipMetric()(target[0].numpy(), target[0].numpy()) == 0.0
    flips = [image_metrics((target + sigma * noise).clamp(0, 1), target, LpipsMetric())["mean"]["flip"]
             for sigma in (0.02, 0.1, 0.3)]
    assert 0.0 < flips[0] < flips[1] < flips[2] < 1.0


def test_flip_of_numpy_images_writes_and_prints_nothing(tmp_path, monkeypatch, capfd):
    monkeypatch.chdir(tmp_path)
    target = np.random.default_rng(4).random((16, 12, 3), dtype=np.float32)
    value = FlipMetric()(np.clip(target * 0.8, 0, 1), target)
    assert 0.0 < value < 1.0 and isinstance(value, float)
    assert capfd.readouterr() == ("", "") and list(tmp_path.iterdir()) == []


def test_flip_that_fails_to_import_is_unavailable_and_null(monkeypatch):
    monkeypatch.setitem(sys.modules, "flip_evaluator", None)  # `import flip_evaluator` raises ModuleNotFoundError
    flip_metric = FlipMetric()
    assert flip_metric.unavailable.startswith("ModuleNotFoundError")
    target = torch.rand(2, 8, 8, 3, generator=torch.Generator().manual_seed(5))
    metrics = image_metrics(target * 0.9, target, LpipsMetric(), flip_metric)
    assert metrics["mean"]["flip"] is None and all(view["flip"] is None for view in metrics["per_view"])
    assert metrics["mean"]["psnr"] > 0


def test_image_metrics_without_lpips_report_none(monkeypatch):
    monkeypatch.setitem(sys.modules, "lpips", None)
    lpips_metric = LpipsMetric()
    assert lpips_metric.unavailable.startswith("ModuleNotFoundError")
    target = torch.rand(2, 8, 8, 3, generator=torch.Generator().manual_seed(2))
    metrics = image_metrics(target * 0.9, target, lpips_metric)
    assert metrics["mean"]["lpips"] is None and all(view["lpips"] is None for view in metrics["per_view"])


def test_ply_round_trip(finished_run, tmp_path):
    params = read_ply(finished_run / "gaussians.ply")
    write_ply(tmp_path / "copy.ply", params)
    again = read_ply(tmp_path / "copy.ply")
    assert set(again) == set(params)
    for name in params:
        torch.testing.assert_close(again[name], params[name], rtol=0, atol=0)


def test_export_is_in_the_source_frame(finished_run, tmp_path):
    result = runner.invoke(app, ["export", str(finished_run), "--out", str(tmp_path / "export")])
    assert result.exit_code == 0, result.output
    info = json.loads((finished_run / "config.json").read_text())
    center, scale = np.array(info["normalization"]["center"]), info["normalization"]["scale"]
    normalized, exported = read_ply(finished_run / "gaussians.ply"), read_ply(tmp_path / "export" / "gaussians.ply")
    np.testing.assert_allclose(scale * (exported["means"].numpy() - center), normalized["means"].numpy(), atol=1e-4)
    np.testing.assert_allclose(exported["scales"].exp().numpy() * scale, normalized["scales"].exp().numpy(), rtol=1e-4)
    torch.testing.assert_close(exported["quats"], normalized["quats"])
    # The exported cameras see the exported Gaussians where the normalized cameras see the normalized ones.
    poses_norm = np.load(finished_run / "poses_final.npy")
    poses_src = np.load(tmp_path / "export" / "poses_final.npy")
    point_norm, point_src = normalized["means"][0].numpy(), exported["means"][0].numpy()
    cam_norm = poses_norm[1, :3, :3] @ point_norm + poses_norm[1, :3, 3]
    cam_src = poses_src[1, :3, :3] @ point_src + poses_src[1, :3, 3]
    np.testing.assert_allclose(cam_src * scale, cam_norm, atol=1e-4)


def _run_on_scene(finished_run, tmp_path, scene_root, **entries):
    """A copy of `finished_run` whose config.json names `scene_root` as its scene folder (and holds `entries`)."""
    run = tmp_path / "run"
    shutil.copytree(finished_run, run)
    info = json.loads((run / "config.json").read_text())
    (run / "config.json").write_text(json.dumps({**info, "scene_root": str(scene_root), **entries}))
    return run, info


def test_export_writes_the_training_cameras_with_the_inputs_calibration_as_a_colmap_model(finished_run, tmp_path):
    # A scene whose model calibrates full-size images of twice the size, with a radial distortion, and which holds
    # only the images downsampled by 2 (as maryrose ships only images_8/): the model must name the images that are
    # there, with the given calibration scaled to them and its distortion, not the run's undistorted intrinsics.
    info = json.loads((finished_run / "config.json").read_text())
    scene = tmp_path / "scene"
    shutil.copytree(info["scene_root"], scene)
    source = read_model(scene / "sparse" / "0")
    Ks = np.stack([camera.K for camera in source.cameras]) * np.array([2.0, 2.0, 1.0])[:, None]
    distortions = np.tile([0.01, -0.002, 0.0, 0.0], (len(Ks), 1))
    shutil.rmtree(scene / "sparse" / "0")
    write_model(scene / "sparse" / "0", source.image_names, source.viewmats, Ks, 128, 128, distortions=distortions)
    (scene / "images").rename(scene / "images_2")
    run, _ = _run_on_scene(finished_run, tmp_path, scene, resolution=2)
    # a base colour far above white and one far below black: the points' colours are clamped, not wrapped
    params = read_ply(run / "gaussians.ply")
    params["sh0"][:2] = torch.tensor([10.0, -10.0])[:, None, None]
    write_ply(run / "gaussians.ply", params)

    result = runner.invoke(app, ["export", str(run), "--out", str(tmp_path / "export")])
    assert result.exit_code == 0, result.output
    assert f"the model's images are in {scene / 'images_2'}" in " ".join(result.output.split())
    model = read_model(tmp_path / "export" / "sparse" / "0")
    names = info["image_names"]
    assert model.image_names == sorted(names) and len(names) == 4
    assert all((scene / "images_2" / name).is_file() for name in model.image_names)
    poses = np.load(tmp_path / "export" / "poses_final.npy")
    # poses_final.npy is float32: its rotations are orthonormal to ~1e-7, COLMAP stores quaternions
    np.testing.assert_allclose(model.viewmats, poses[[names.index(name) for name in model.image_names]], atol=1e-6)
    given = dict(zip(source.image_names, Ks))
    for name, camera in zip(model.image_names, model.cameras):
        np.testing.assert_allclose(camera.K, given[name] * np.array([0.5, 0.5, 1.0])[:, None], atol=1e-9)
        assert (camera.width, camera.height, camera.model) == (64, 64, "OPENCV")
        np.testing.assert_allclose(camera.distortion, [0.01, -0.002, 0.0, 0.0])
    gaussians = read_ply(tmp_path / "export" / "gaussians.ply")
    assert len(model.points) == len(gaussians["means"])
    means = gaussians["means"].numpy().astype(np.float64)
    # each point is a Gaussian's centre in its base colour: 255 * (0.5 + C0 * f_dc), clamped to [0, 255] and rounded
    by_position, by_centre = np.lexsort(model.points.T), np.lexsort(means.T)
    np.testing.assert_allclose(model.points[by_position], means[by_centre], atol=1e-5)
    C0 = 0.28209479177387814  # the SH basis of degree 0, 1 / (2 sqrt(pi))
    base = np.clip(0.5 + C0 * gaussians["sh0"][:, 0, :].numpy().astype(np.float64), 0.0, 1.0)
    np.testing.assert_array_equal(model.colors[by_position], np.round(255 * base[by_centre]).astype(np.uint8))
    assert {tuple(color) for color in base[:2]} == {(1.0, 1.0, 1.0), (0.0, 0.0, 0.0)}


def test_exported_image_names_with_spaces_are_kept_in_a_binary_model(finished_run, tmp_path):
    """COLMAP's text format splits an image name at a space: "view 000.png" was read back as "view" for every image.
    Such a model is written binary."""
    info = json.loads((finished_run / "config.json").read_text())
    scene = tmp_path / "scene"
    shutil.copytree(info["scene_root"], scene)
    source = read_model(scene / "sparse" / "0")
    spaced = {name: name.replace("_", " ") for name in source.image_names}
    for name, new_name in spaced.items():
        (scene / "images" / name).rename(scene / "images" / new_name)
    shutil.rmtree(scene / "sparse" / "0")
    write_model(scene / "sparse" / "0", [spaced[name] for name in source.image_names], source.viewmats,
                np.stack([camera.K for camera in source.cameras]), 64, 64)
    run, _ = _run_on_scene(finished_run, tmp_path, scene, image_names=[spaced[name] for name in info["image_names"]])
    result = runner.invoke(app, ["export", str(run), "--out", str(tmp_path / "export")])
    assert result.exit_code == 0, result.output
    written = {path.name for path in (tmp_path / "export" / "sparse" / "0").iterdir()}
    assert {"cameras.bin", "images.bin", "points3D.bin"} <= written and all(name.endswith(".bin") for name in written)
    names = read_model(tmp_path / "export" / "sparse" / "0").image_names
    assert names == sorted(spaced[name] for name in info["image_names"])
    result = runner.invoke(app, ["export", str(run), "--out", str(tmp_path / "export")])  # over the earlier export
    assert result.exit_code == 0, result.output


def _write_cut_short(monkeypatch, file_name: str, keep) -> None:
    """pycolmap writes its models with `file_name` cut to `keep(data)` bytes of its data: what a full disk or a
    file-size limit leaves, of which pycolmap's writers say nothing."""
    from warpbags.data.colmap import _pycolmap

    reconstruction_class = _pycolmap().Reconstruction
    for method in ("write_text", "write_binary"):
        def write_cut_short(reconstruction, folder, real_write=getattr(reconstruction_class, method)):
            real_write(reconstruction, folder)
            written = Path(folder) / file_name
            if written.is_file():
                data = written.read_bytes()
                written.write_bytes(data[:keep(data)])

        monkeypatch.setattr(reconstruction_class, method, write_cut_short)


def _last_line_start(data: bytes) -> int:
    return data.rindex(b"\n", 0, len(data) - 1) + 1


@pytest.mark.parametrize("keep, found", [(lambda data: _last_line_start(data) + 6, "is damaged"),
                                         (_last_line_start, "is incomplete")], ids=["within-a-line", "at-a-line-end"])
def test_a_colmap_model_cut_short_is_one_line_and_leaves_the_earlier_export(finished_run, tmp_path, monkeypatch,
                                                                            keep, found):
    """pycolmap's writers ignore I/O errors: under a file-size limit, `export` said it wrote sparse/0 and the model cut
    short replaced the earlier export's."""
    out = tmp_path / "export"
    assert runner.invoke(app, ["export", str(finished_run), "--out", str(out)]).exit_code == 0
    earlier = {path: path.read_bytes() for path in out.rglob("*") if path.is_file()}
    _write_cut_short(monkeypatch, "points3D.txt", keep)
    result = runner.invoke(app, ["export", str(finished_run), "--out", str(out)])
    lines = _lines(result)
    assert result.exit_code == 2 and len(lines) == 1, result.output
    assert f"the COLMAP model written to {out / 'sparse' / '0.partial'} {found}" in lines[0]
    assert {path: path.read_bytes() for path in out.rglob("*") if path.is_file()} == earlier  # the staging gone too
    result = runner.invoke(app, ["export", str(finished_run), "--out", str(tmp_path / "fresh")])
    assert result.exit_code == 2 and not (tmp_path / "fresh").exists()  # a new folder: nothing of it is left


@pytest.mark.parametrize("file_name, cut", [("points3D.bin", 3), ("points3D.bin", 20), ("images.bin", 30),
                                             ("frames.bin", 1)])
def test_a_binary_colmap_model_cut_short_is_named(tmp_path, monkeypatch, file_name, cut):
    """pycolmap reads past a binary file's end: points3D.bin 3 bytes short took it 85 s to fail, 20 bytes short it
    read back as complete (the missing bytes as garbage)."""
    _write_cut_short(monkeypatch, file_name, lambda data: len(data) - cut)
    with pytest.raises(WarpbagsError) as error:
        write_model(tmp_path, ["a.png"], np.eye(4)[None], np.eye(3)[None], 8, 8, np.zeros((2, 3)), binary=True)
    assert str(error.value).startswith(f"the COLMAP model written to {tmp_path} is damaged (a full disk or a file-size "
                                       f"limit?): COLMAP model file {tmp_path / file_name} is cut short"), error.value


def test_exported_image_names_are_relative_to_one_image_folder_for_a_transforms_json_scene(finished_run, tmp_path):
    from warpbags.export import training_calibration

    info = json.loads((finished_run / "config.json").read_text())
    source = read_model(Path(info["scene_root"]) / "sparse" / "0")
    camera_to_world = np.linalg.inv(source.viewmats) @ np.diag([1.0, -1.0, -1.0, 1.0])
    K, (width, height) = source.cameras[0].K, (source.cameras[0].width, source.cameras[0].height)
    frames = [{"file_path": f"pictures/{name}", "transform_matrix": matrix.tolist()}
              for name, matrix in zip(source.image_names, camera_to_world)]
    scene = tmp_path / "scene"
    shutil.copytree(Path(info["scene_root"]) / "images", scene / "pictures")
    (scene / "transforms.json").write_text(json.dumps({"fl_x": K[0, 0], "fl_y": K[1, 1], "cx": K[0, 2], "cy": K[1, 2],
                                                       "w": width, "h": height, "frames": frames}))
    names = [f"pictures/{name}" for name in info["image_names"]]
    run = types.SimpleNamespace(path=finished_run, info={"scene_root": str(scene), "image_names": names,
                                                         "resolution": 1})
    calibration = training_calibration(run)
    assert calibration.image_folder == "pictures" and calibration.image_names == info["image_names"]
    np.testing.assert_allclose(calibration.Ks, np.tile(K, (len(names), 1, 1)), atol=1e-9)


def test_export_without_its_scene_folder_writes_nothing_unless_told_to_skip_the_cameras(finished_run, tmp_path):
    run, _ = _run_on_scene(finished_run, tmp_path, tmp_path / "moved-away")
    result = runner.invoke(app, ["export", str(run), "--out", str(tmp_path / "export")])
    assert result.exit_code == 2 and "moved-away is gone" in result.output and "--no-colmap" in result.output
    assert "Traceback" not in result.output and not (tmp_path / "export").exists()
    (tmp_path / "a-file").write_text("")
    result = runner.invoke(app, ["export", str(run), "--out", str(tmp_path / "a-file"), "--no-colmap"])
    assert result.exit_code == 2 and "a-file is a file, not a folder to export into" in result.output
    result = runner.invoke(app, ["export", str(run), "--out", str(tmp_path / "export"), "--no-colmap"])
    assert result.exit_code == 0, result.output
    assert sorted(path.name for path in (tmp_path / "export").iterdir()) == ["gaussians.ply", "poses_final.npy"]
    (tmp_path / "export" / "sparse" / "0").mkdir(parents=True)  # an earlier export's model, of other poses
    (tmp_path / "export" / "sparse" / "0" / "images.txt").write_text("")
    result = runner.invoke(app, ["export", str(run), "--out", str(tmp_path / "export"), "--no-colmap"])
    assert result.exit_code == 0, result.output
    assert sorted(path.name for path in (tmp_path / "export").iterdir()) == ["gaussians.ply", "poses_final.npy"]


def test_turntable_frames_and_video(finished_run):
    result = runner.invoke(app, ["render", str(finished_run), "--frames", "6"])
    assert result.exit_code == 0, result.output
    frames = sorted((finished_run / "turntable").glob("frame_*.png"))
    assert len(frames) == 6 and (finished_run / "turntable.mp4").stat().st_size > 1000
    import cv2

    first = cv2.imread(str(frames[0]))
    assert first.shape[:2] == (64, 64) and first.min() < 200  # the object is in view, not just white background
    # around it, the run's background: white, the default (a black one is the test below)
    assert json.loads((finished_run / "config.json").read_text())["config"]["background"] == "white"
    assert (first[0, 0] == 255).all(), first[0, 0]
    capture = cv2.VideoCapture(str(finished_run / "turntable.mp4"))
    assert int(capture.get(cv2.CAP_PROP_FRAME_COUNT)) == 6
    # a shorter render afterwards leaves no frame (nor the video) of the longer one behind
    assert runner.invoke(app, ["render", str(finished_run), "--frames", "3", "--no-video"]).exit_code == 0
    assert len(list((finished_run / "turntable").glob("frame_*.png"))) == 3
    assert not (finished_run / "turntable.mp4").exists()


def test_a_turntable_render_stopped_partway_leaves_the_earlier_one_and_frames_are_bounded(finished_run, tmp_path,
                                                                                          monkeypatch):
    """The earlier frames were removed before anything was rendered, so Ctrl-C or a failure left none (and the
    earlier video beside them); every frame was rendered in one batch, so a large --frames took the machine's memory."""
    import warpbags.export

    run = _copy_of(finished_run, tmp_path / "run")
    assert runner.invoke(app, ["render", str(run), "--frames", "3"]).exit_code == 0
    before = {path.name: path.read_bytes() for path in (run / "turntable").iterdir()}
    video = (run / "turntable.mp4").read_bytes()
    real_render, batches = warpbags.export.render_gaussians, []

    def render_then_stop(params, viewmats, *args, **kwargs):
        batches.append(len(viewmats))
        if len(batches) == 2:
            raise KeyboardInterrupt
        return real_render(params, viewmats, *args, **kwargs)

    monkeypatch.setattr(warpbags.export, "render_gaussians", render_then_stop)
    result = runner.invoke(app, ["render", str(run), "--frames", "20"])
    assert result.exit_code == 130 and batches == [warpbags.export.TURNTABLE_BATCH] * 2, result.output
    assert {path.name: path.read_bytes() for path in (run / "turntable").iterdir()} == before  # staging gone too
    assert (run / "turntable.mp4").read_bytes() == video and not list(run.glob("*.tmp*"))
    for frames in ("0", str(warpbags.export.MAX_TURNTABLE_FRAMES + 1)):
        result = runner.invoke(app, ["render", str(run), "--frames", frames])
        lines = [line for line in result.output.splitlines() if line.strip()]
        assert result.exit_code == 2 and len(lines) == 1 and "--frames must be in [1, 3600]" in lines[0], result.output


def test_a_turntable_render_stopped_by_sigterm_leaves_the_earlier_one(finished_run, tmp_path):
    """`kill` (SIGTERM) ended `warpbags render` at once, silently, leaving turntable.tmp.mp4 and the staged frames;
    it stops as Ctrl-C does: one line, exit 143, the earlier turntable kept."""
    run = _copy_of(finished_run, tmp_path / "run")
    assert runner.invoke(app, ["render", str(run), "--frames", "3"]).exit_code == 0
    before = {path.name: path.read_bytes() for path in (run / "turntable").iterdir()}
    video = (run / "turntable.mp4").read_bytes()
    code, output = stopped_by_sigterm(["render", str(run), "--frames", "3600"],
                                      lambda: any(run.glob("turntable/.partial/frame_*.png")))
    assert code == 143 and "stopped by SIGTERM" in output, output
    assert {path.name: path.read_bytes() for path in (run / "turntable").iterdir()} == before
    assert (run / "turntable.mp4").read_bytes() == video and not list(run.glob("*.tmp*"))


@pytest.mark.parametrize("height", [47, 48])
def test_a_turntable_of_an_odd_size_keeps_every_pixel_in_its_video(finished_run, tmp_path, height):
    """mp4v holds even sizes only: OpenCV wrote a 63 x 47 run's video at 62 x 46, its last column and row gone. The
    video is padded to 64 x 48 instead, the frames stay 63 x 47; of 63 x 48 only the width is padded (the rows and
    columns padded the other way round make frames the writer drops)."""
    import cv2

    run = _copy_of(finished_run, tmp_path / "run")
    info = json.loads((run / "config.json").read_text())
    (run / "config.json").write_text(json.dumps({**info, "width": 63, "height": height}))
    result = runner.invoke(app, ["render", str(run), "--frames", "2"])
    assert result.exit_code == 0, result.output
    assert cv2.imread(str(run / "turntable" / "frame_0000.png")).shape[:2] == (height, 63)
    capture = cv2.VideoCapture(str(run / "turntable.mp4"))
    assert (capture.get(cv2.CAP_PROP_FRAME_WIDTH), capture.get(cv2.CAP_PROP_FRAME_HEIGHT)) == (64, 48)


def test_a_damaged_turntable_frame_is_left_out_of_the_report_by_name(finished_run, tmp_path):
    import cv2

    run = _copy_of(finished_run, tmp_path / "run")
    assert runner.invoke(app, ["render", str(run), "--frames", "6", "--no-video"]).exit_code == 0
    (run / "turntable" / "frame_0000.png").write_bytes(b"not a png")
    result = runner.invoke(app, ["eval", str(run), "--refine-iters", "0"])
    assert result.exit_code == 0, result.output
    report = (run / "report.md").read_text()
    assert "Not readable as images, left out: `turntable/frame_0000.png`" in report
    assert "![turntable](turntable_strip.png)" in report
    strip = cv2.imread(str(run / "turntable_strip.png"))
    frame = cv2.imread(str(run / "turntable" / "frame_0001.png"))
    assert strip.shape[1] == 5 * round(frame.shape[1] * 128 / frame.shape[0])  # the five readable frames


def test_turntable_is_rendered_on_the_runs_background_and_names_what_it_lacks(finished_run, tmp_path):
    import cv2

    black = tmp_path / "black"
    shutil.copytree(finished_run, black, ignore=shutil.ignore_patterns("turntable*", "checkpoints"))
    info = json.loads((black / "config.json").read_text())
    info["config"]["background"] = "black"
    (black / "config.json").write_text(json.dumps(info))
    result = runner.invoke(app, ["render", str(black), "--frames", "2", "--no-video"])
    assert result.exit_code == 0, result.output
    frame = cv2.imread(str(black / "turntable" / "frame_0000.png"))
    assert frame[0, 0].max() == 0 and frame.max() > 50  # black around the object, as in training and the viewer
    del info["width"]
    (black / "config.json").write_text(json.dumps(info))
    result = runner.invoke(app, ["render", str(black), "--frames", "2", "--no-video"])
    lines = [line for line in result.output.splitlines() if line.strip()]
    assert result.exit_code == 2 and len(lines) == 1 and "config.json has no 'width'" in lines[0], result.output


def test_turntable_video_that_opencv_cannot_open_is_one_line_and_no_file(finished_run, tmp_path, monkeypatch):
    import cv2

    class Unopened:
        def __init__(self, *args):
            pass

        def isOpened(self):  # noqa: N802 - OpenCV's name
            return False

    run = tmp_path / "run"
    shutil.copytree(finished_run, run, ignore=shutil.ignore_patterns("turntable*", "checkpoints"))
    monkeypatch.setattr(cv2, "VideoWriter", Unopened)
    result = runner.invoke(app, ["render", str(run), "--frames", "2"])
    lines = [line for line in result.output.splitlines() if line.strip()]
    assert result.exit_code == 2 and len(lines) == 1 and "pass --no-video" in lines[0], result.output
    assert not list(run.glob("turntable*.mp4"))


@pytest.mark.parametrize("damage", ["cut-short", "frames-lost"])
def test_a_turntable_video_that_fails_to_write_is_one_line_and_the_earlier_render_stays(finished_run, tmp_path,
                                                                                        monkeypatch, damage):
    """OpenCV's video writer reports no write error: under a file-size limit, `render` replaced a good video with one
    no player opens, and said it wrote it."""
    import cv2

    run = _copy_of(finished_run, tmp_path / "run")
    assert runner.invoke(app, ["render", str(run), "--frames", "3"]).exit_code == 0
    earlier = {path: path.read_bytes() for path in [run / "turntable.mp4", *(run / "turntable").iterdir()]}
    real_writer = cv2.VideoWriter

    class FailingWriter:
        """OpenCV's writer, whose video is cut short when released or which loses every second frame."""

        def __init__(self, path, *args):
            self.path, self.writer, self.frames = Path(path), real_writer(path, *args), 0

        def isOpened(self):  # noqa: N802 - OpenCV's name
            return self.writer.isOpened()

        def write(self, image):
            self.frames += 1
            if damage == "cut-short" or self.frames % 2:
                self.writer.write(image)

        def release(self):
            self.writer.release()
            if damage == "cut-short" and self.path.is_file():
                self.path.write_bytes(self.path.read_bytes()[:1000])

    monkeypatch.setattr(cv2, "VideoWriter", FailingWriter)
    result = runner.invoke(app, ["render", str(run), "--frames", "4"])
    lines = _lines(result)
    assert result.exit_code == 2 and len(lines) == 1, result.output
    found = "does not open as a video" if damage == "cut-short" else "holds 2 of its 4 frames"
    assert f"could not write the turntable video {run / 'turntable.mp4'}: the video written {found}" in lines[0]
    assert {path: path.read_bytes() for path in [run / "turntable.mp4", *(run / "turntable").iterdir()]} == earlier
    assert not list(run.glob("*.tmp*"))


def test_a_turntable_frame_that_fails_to_write_is_one_line_and_the_earlier_render_stays(finished_run, tmp_path):
    """OpenCV's imwrite reports no write error: under a file-size limit, `render --no-video` put frames cut short in
    place of the earlier render's and said it wrote them."""
    import resource
    import signal

    run = _copy_of(finished_run, tmp_path / "run")
    assert runner.invoke(app, ["render", str(run), "--frames", "3", "--no-video"]).exit_code == 0
    earlier = {path: path.read_bytes() for path in (run / "turntable").iterdir()}
    soft, hard = resource.getrlimit(resource.RLIMIT_FSIZE)
    ignored = signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # a write past the limit fails, not the process
    resource.setrlimit(resource.RLIMIT_FSIZE, (min(len(data) for data in earlier.values()) - 1, hard))
    try:
        result = runner.invoke(app, ["render", str(run), "--frames", "3", "--no-video"])
    finally:
        resource.setrlimit(resource.RLIMIT_FSIZE, (soft, hard))
        signal.signal(signal.SIGXFSZ, ignored)
    lines = _lines(result)
    assert result.exit_code == 2 and len(lines) == 1, result.output
    assert f"could not write the turntable frame {run / 'turntable' / 'frame_0000.png'}: File too large" in lines[0]
    assert {path: path.read_bytes() for path in (run / "turntable").iterdir()} == earlier


@pytest.mark.parametrize("name", ["picture.png", "picture.jpg"])
def test_an_image_write_past_a_file_size_limit_raises(tmp_path, name):
    """`files.write_image`, which the turntable frames, eval's pictures and `warpbags synth` write with: a write that a
    full disk or a file-size limit cuts short raises OSError. OpenCV's imwrite returned True over this 16 px PNG cut
    to 100 bytes (it reports some failed writes and not others)."""
    import resource
    import signal

    import cv2

    from warpbags.files import write_image

    pixels = np.random.default_rng(0).integers(0, 256, (16, 16, 3), dtype=np.uint8)  # noise: no format shrinks it
    soft, hard = resource.getrlimit(resource.RLIMIT_FSIZE)
    ignored = signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # a write past the limit fails, not the process
    resource.setrlimit(resource.RLIMIT_FSIZE, (100, hard))
    try:
        with pytest.raises(OSError):
            write_image(tmp_path / name, pixels)
    finally:
        resource.setrlimit(resource.RLIMIT_FSIZE, (soft, hard))
        signal.signal(signal.SIGXFSZ, ignored)
    write_image(tmp_path / name, pixels)
    read = cv2.imread(str(tmp_path / name))
    assert read.shape == pixels.shape and (np.array_equal(read, pixels) or name.endswith(".jpg"))
    with pytest.raises(WarpbagsError, match=r"OpenCV could not encode .*picture\.xyz"):  # OpenCV raised cv2.error
        write_image(tmp_path / "picture.xyz", pixels)


def test_turntable_frame_names_sort_in_frame_order():
    from warpbags.export import MAX_TURNTABLE_FRAMES, turntable_frame_name

    names = [turntable_frame_name(index) for index in range(MAX_TURNTABLE_FRAMES)]
    assert names[:2] == ["frame_0000.png", "frame_0001.png"] and sorted(names) == names  # frame_1000 after frame_999


def test_a_render_removes_the_3_digit_frames_of_an_earlier_warpbags(finished_run, tmp_path):
    run = _copy_of(finished_run, tmp_path / "run")
    (run / "turntable").mkdir()
    for name in ("frame_000.png", "frame_001.png", "frame_002.png", "notes.txt"):
        (run / "turntable" / name).write_bytes(b"an earlier render")
    assert runner.invoke(app, ["render", str(run), "--frames", "2", "--no-video"]).exit_code == 0
    assert sorted(path.name for path in (run / "turntable").iterdir()) == ["frame_0000.png", "frame_0001.png",
                                                                           "notes.txt"]


def test_the_report_takes_the_frames_of_an_earlier_warpbags_in_frame_order(finished_run, tmp_path):
    """An earlier warpbags named frames with 3 digits: frame_1000.png sorts before frame_999.png by name. The report's
    frames are named here in the order it picks them, as it names those it cannot read."""
    run = _copy_of(finished_run, tmp_path / "run")
    (run / "turntable").mkdir()
    names = [f"frame_{index:03d}.png" for index in range(996, 1002)]
    for name in names:
        (run / "turntable" / name).write_bytes(b"not a png")
    assert runner.invoke(app, ["eval", str(run), "--refine-iters", "0"]).exit_code == 0
    listed = ", ".join(f"`turntable/{name}`" for name in names)
    assert f"Not readable as images, left out: {listed}" in (run / "report.md").read_text()


def test_turntable_orbits_about_the_up_axis():
    from warpbags.camera_paths import turntable_viewmats
    from warpbags.cameras import camera_centers
    from conftest import look_at

    eye = torch.tensor([4.0, 0.0, 1.0], dtype=torch.float64)
    # training cameras around the object at one height: their tilts cancel and the mean up is world z
    eyes = [eye, torch.tensor([0.0, 4.0, 1.0]), torch.tensor([-4.0, 0.0, 1.0]), torch.tensor([0.0, -4.0, 1.0])]
    viewmats = torch.stack([look_at(e.double(), torch.zeros(3, dtype=torch.float64)) for e in eyes])
    orbit = turntable_viewmats(viewmats, 4)
    centers = camera_centers(orbit)
    torch.testing.assert_close(centers[0], eye)
    torch.testing.assert_close(centers.norm(dim=1), torch.full((4,), eye.norm().item(), dtype=torch.float64))
    torch.testing.assert_close(centers[:, 2], torch.full((4,), 1.0, dtype=torch.float64))  # same height (z up)
    torch.testing.assert_close(centers[2, :2], -eye[:2])  # half a turn later: the opposite side


def test_the_turntable_turns_about_the_gaussians_wherever_the_run_put_them(finished_run, tmp_path):
    """The turntable turned about the world origin, while a run trained from noisy poses puts its Gaussians off it
    (0.4 units on maryrose from 15 deg / 0.3): the object swung across the frame and out of it. It turns about the
    Gaussians' opacity-weighted centre, where the viewer looks, so the same run in another gauge (moved by a 40 deg,
    x1.7 similarity, its Gaussians 1.9 units off the origin) renders the same frames."""
    import cv2

    from warpbags.gaussians import opacity_weighted_center

    frames = {}
    for name in ("as_trained", "moved"):
        run = _copy_of(finished_run, tmp_path / name)
        if name == "moved":
            _moved_by_a_similarity(run, angle_deg=40.0, scale=1.7)
            assert opacity_weighted_center(read_ply(run / "gaussians.ply")).norm() > 1.5
        assert runner.invoke(app, ["render", str(run), "--frames", "6", "--no-video"]).exit_code == 0
        frames[name] = np.stack([cv2.imread(str(path)) for path in sorted((run / "turntable").glob("frame_*.png"))])
    difference = np.abs(frames["moved"].astype(int) - frames["as_trained"])
    assert difference.max() <= 2, difference.reshape(6, -1).max(axis=1)  # 1 measured: float32 rounding


def test_eval_of_a_folder_that_is_not_a_run_is_one_line(tmp_path):
    result = runner.invoke(app, ["eval", str(tmp_path)])
    assert result.exit_code == 2
    assert len(result.output.strip().splitlines()) == 1 and "not a training run" in result.output


def test_info_of_a_training_run_folder_names_the_scene_folder_it_trained_on(finished_run, tmp_path):
    """`info` takes scenes: of a run folder, it said "no cameras in RUN: expected sparse/0/cameras.bin ...". A scene
    folder that holds a config.json of its own (a capture app's) keeps its own error."""
    scene_root = json.loads((finished_run / "config.json").read_text())["scene_root"]
    result = runner.invoke(app, ["info", str(finished_run)])
    lines = _lines(result)
    assert result.exit_code == 2 and len(lines) == 1, result.output
    assert (f"{finished_run} is a training run folder, not a scene: info takes a scene; the run's scene folder is "
            f"{scene_root}") in " ".join(result.output.split())
    capture = tmp_path / "capture"
    shutil.copytree(scene_root, capture)
    (capture / "config.json").write_text('{"note": "capture settings"}')
    (capture / "masks" / "view_003.png").unlink()
    result = runner.invoke(app, ["info", str(capture)])
    assert result.exit_code == 2 and "mask for image view_003.png is missing" in " ".join(result.output.split()), \
        result.output


@pytest.mark.parametrize("device, message", [("tpu", "--device must be cpu or cuda, got 'tpu'"),
                                             ("cuda", "--device cuda: no CUDA device is available")])
def test_eval_on_a_device_it_cannot_use_is_one_line_and_writes_nothing(finished_run, tmp_path, device, message):
    if device == "cuda" and torch.cuda.is_available():
        pytest.skip("this machine has a CUDA device")
    run = tmp_path / "run"
    shutil.copytree(finished_run, run)
    for earlier in ("eval.json", "report.md"):
        (run / earlier).unlink(missing_ok=True)
    shutil.rmtree(run / "eval", ignore_errors=True)
    result = runner.invoke(app, ["eval", str(run), "--device", device])
    assert result.exit_code == 2
    assert result.output.strip().splitlines() == [f"error: {message}"]
    assert not (run / "eval.json").exists() and not (run / "eval").exists()


def test_eval_of_an_unfinished_run_names_the_missing_file(finished_run, tmp_path):
    partial = tmp_path / "partial"
    partial.mkdir()
    (partial / "config.json").write_text((finished_run / "config.json").read_text())
    result = runner.invoke(app, ["eval", str(partial)])
    assert result.exit_code == 2 and "gaussians.ply is missing" in result.output


def _two_camera_copy(finished_run, folder):
    """The finished run with only its first two training cameras (too few for procrustes alignment)."""
    shutil.copytree(finished_run, folder)
    for name in ("poses_true", "poses_init", "poses_start", "poses_final", "intrinsics"):
        np.save(folder / f"{name}.npy", np.load(finished_run / f"{name}.npy")[:2])
    info = json.loads((folder / "config.json").read_text())
    (folder / "config.json").write_text(json.dumps({**info, "image_names": info["image_names"][:2]}))
    return folder


def test_load_run_names_intrinsics_that_do_not_match_the_poses(finished_run, tmp_path):
    folder = _two_camera_copy(finished_run, tmp_path / "mismatch")
    assert len(load_run(folder).intrinsics) == 2
    np.save(folder / "intrinsics.npy", np.load(finished_run / "intrinsics.npy"))  # four cameras' against two poses
    with pytest.raises(WarpbagsError, match="intrinsics.npy holds 4 cameras, the run's poses 2"):
        load_run(folder)


def test_pose_accuracy_leaves_out_the_alignment_two_cameras_cannot_fit(finished_run, tmp_path):
    run = load_run(_two_camera_copy(finished_run, tmp_path / "two"))
    lines = []
    report = pose_accuracy(run, log=lines.append)
    assert list(report) == ["pairwise"] and len(report["pairwise"]["final"]["rotation_deg"]) == 2
    assert len(lines) == 1 and "procrustes left out" in lines[0] and "at least 3" in lines[0], lines


def test_pose_accuracy_says_where_procrustes_fixes_its_turn_weakly(finished_run, tmp_path):
    """Reference cameras on a short arc: Procrustes' errors follow the centres' noise (`procrustes_weak`), said once
    in the log, and in eval.json and report.md beside the Procrustes rows."""
    run = load_run(finished_run)
    lines = []
    pose_accuracy(run, log=lines.append)
    assert not any("across their main line" in line for line in lines), lines  # cameras around the object
    folder = tmp_path / "arc"
    shutil.copytree(finished_run, folder)
    truth = np.load(finished_run / "poses_true.npy")
    angles = np.linspace(0, np.radians(30), len(truth))
    centres = 4 * np.stack([np.cos(angles), np.sin(angles), np.zeros_like(angles)], axis=1)
    truth[:, :3, 3] = -np.einsum("cij,cj->ci", truth[:, :3, :3], centres)
    np.save(folder / "poses_true.npy", truth)
    lines = []
    pose_accuracy(load_run(folder), log=lines.append)
    weak = [line for line in lines if "across their main line" in line]
    assert len(weak) == 1 and weak[0].startswith("pose errors: the camera centres spread 0.0"), lines
    assert weak[0].endswith("the pairwise errors do not depend on it")
    result = runner.invoke(app, ["eval", str(folder), "--refine-iters", "0"])  # and beside the numbers it is about
    assert result.exit_code == 0, result.output
    poses = json.loads((folder / "eval.json").read_text())["poses"]
    assert poses["procrustes"]["weakly_fixed"].startswith("the camera centres spread 0.0")
    assert "weakly_fixed" not in poses["pairwise"]
    assert "\nProcrustes: the camera centres spread 0.0" in (folder / "report.md").read_text()


def test_eval_of_two_cameras_falls_back_to_the_pairwise_alignment(finished_run, tmp_path):
    """Procrustes needs three camera centres: a two-view run is evaluated with the pairwise alignment, as the
    trainer's own pose errors are, and eval.json says which alignment it used."""
    two = _two_camera_copy(finished_run, tmp_path / "two")
    result = runner.invoke(app, ["eval", str(two), "--procrustes", "--refine-iters", "0"])
    assert result.exit_code == 0, result.output
    assert "pairwise alignment: 2 cameras: Procrustes needs at least 3 camera centres" in " ".join(result.output.split())
    assert json.loads((two / "eval.json").read_text())["alignment"] == "pairwise"


def test_eval_pairwise_maps_the_held_out_cameras_by_the_pairwise_alignment(finished_run, tmp_path):
    """`eval --pairwise` reaches the evaluation: the held-out cameras are mapped into the model's frame by SPARF's
    pairwise sim(3), not Procrustes' (the default), so every held-out view is rendered from another pose and scores
    other metrics (0.1-0.4 dB apart on the fixture's run), the same as `evaluate_run(alignment="pairwise")`'s. The
    training-pose rows report both alignments whatever the flag: only the held-out views can tell."""
    reports = {}
    for alignment, flags in (("procrustes", []), ("pairwise", ["--pairwise"])):
        run = _copy_of(finished_run, tmp_path / alignment)  # eval writes into the run folder
        result = runner.invoke(app, ["eval", str(run), *flags, "--refine-iters", "0"], env={"COLUMNS": "200"})
        assert result.exit_code == 0, result.output
        reports[alignment] = json.loads((run / "eval.json").read_text())
        assert reports[alignment]["alignment"] == alignment
        assert f"held-out views ({reports[alignment]['test_views']}, {alignment} alignment)" in result.output
        assert f"test cameras aligned by {alignment})" in (run / "report.md").read_text()
    for procrustes, pairwise in zip(reports["procrustes"]["images"]["per_view"],
                                    reports["pairwise"]["images"]["per_view"]):
        assert abs(procrustes["psnr"] - pairwise["psnr"]) > 0.01 and procrustes["ssim"] != pairwise["ssim"]
    expected = evaluate_run(_copy_of(finished_run, tmp_path / "direct"), alignment="pairwise", refine_iters=0,
                            log=lambda message: None)
    for got, wanted in zip(reports["pairwise"]["images"]["per_view"], expected["images"]["per_view"]):
        for metric in ("psnr", "ssim", "flip"):  # LPIPS is null where its network does not load
            assert got[metric] == pytest.approx(wanted[metric], rel=1e-6), metric


def test_eval_without_a_run_folder_evaluates_the_run_under_runs_that_finished_last(finished_run, tmp_path,
                                                                                  monkeypatch):
    """`warpbags eval` with no RUN_DIR takes the run under ./runs/ that finished last (`latest_run`: its
    gaussians.ply, written with the result, is newest). Not the folder modified last (eval itself writes into the run
    it evaluates), nor the last or first by name, nor a newer folder that is not a run, nor a run started later and
    still training (it took that one, and stopped on its missing gaussians.ply)."""
    runs = tmp_path / "runs"
    for name, result_time, folder_time in (("a-middle", 2e8, 3e8), ("b-newest", 3e8, 1e8), ("c-oldest", 1e8, 2e8)):
        run = _copy_of(finished_run, runs / name)
        os.utime(run / "gaussians.ply", (result_time, result_time))
        os.utime(run, (folder_time, folder_time))
    training = _copy_of(finished_run, runs / "d-training")
    (training / "gaussians.ply").unlink()
    os.utime(training / "config.json", (5e8, 5e8))
    (runs / "notes").mkdir()
    (runs / "notes" / "todo.txt").write_text("")
    os.utime(runs / "notes", (4e8, 4e8))
    monkeypatch.chdir(tmp_path)
    result = runner.invoke(app, ["eval", "--refine-iters", "0"], env={"COLUMNS": "200"})
    assert result.exit_code == 0, result.output
    assert sorted(path.parent.name for path in runs.glob("*/eval.json")) == ["b-newest"]
    assert json.loads((runs / "b-newest" / "eval.json").read_text())["run"] == str(Path("runs") / "b-newest")
    assert f"wrote {Path('runs') / 'b-newest' / 'eval.json'}" in result.output
    for name in ("a-middle", "b-newest", "c-oldest"):
        (runs / name / "gaussians.ply").unlink()
    result = runner.invoke(app, ["eval"], env={"COLUMNS": "200"})
    assert result.exit_code == 2 and result.output.strip() == (
        f"error: no finished training run under {runs.resolve()} (4 unfinished); pass RUN_DIR or train first")


def test_sweep_runs_every_combination_once_and_skips_finished_runs(finished_run, tmp_path):
    from warpbags.sweep import SweepSpec, run_sweep

    info = json.loads((finished_run / "config.json").read_text())
    spec = SweepSpec(scene=info["scene_root"], out=tmp_path / "sweep", rot_noises=(0, 5), views=(4,), seeds=(0,),
                     refine_iters=2, overrides=(("iters", 4),))
    messages = []
    rows = run_sweep(spec, log=messages.append)
    assert len(rows) == 4 and {r["method"] for r in rows} == {"bags", "baseline"}
    assert sum(m.startswith("train ") for m in messages) == 4
    noisy = [r for r in rows if r["rot_noise_deg"] == 5]
    assert all(r["rot_err_initial"] > 0.5 for r in noisy)
    assert all(0.0 < r["flip"] < 1.0 for r in rows)
    assert all(r["rot_err_final"] == pytest.approx(r["rot_err_initial"]) for r in noisy if r["method"] == "baseline")
    for name in ("sweep.csv", "sweep.json", "psnr_vs_noise.png", "pose_error_vs_noise.png", "curves.png"):
        assert (spec.out / name).stat().st_size > 100, name
    assert (spec.out / "bags-4v-rot5-seed0" / "report.md").is_file()
    messages.clear()
    again = run_sweep(spec, log=messages.append)
    assert messages == [f"skip {r['run']} (done)" for r in rows] and again == rows
    # a run killed (SIGKILL) before its first checkpoint: its setup files, a log line cut short and an atomic write's
    # temporary stay; the next sweep trains it again, and leaves a folder holding anything else alone
    killed = spec.out / "bags-4v-rot0-seed0"
    kept = ("config.json", "poses_true.npy", "poses_init.npy", "poses_start.npy", "intrinsics.npy")
    for entry in killed.iterdir():
        if entry.name not in kept:
            shutil.rmtree(entry) if entry.is_dir() else entry.unlink()
    (killed / "log.jsonl").write_text('{"iter": 1, "lo')
    (killed / "poses_history.tmp.npz").write_bytes(b"cut")
    (killed / "checkpoints").mkdir()
    messages.clear()
    assert len(run_sweep(spec, log=messages.append)) == 4
    assert sum(m == "train bags-4v-rot0-seed0" for m in messages) == 1 and (killed / "eval.json").is_file()
    other = spec.out / "bags-4v-rot5-seed0"
    for name in ("eval.json", "gaussians.ply"):  # no checkpoints and no eval.json, but results: not a killed start
        (other / name).unlink()
    shutil.rmtree(other / "checkpoints")
    with pytest.raises(WarpbagsError, match="not empty"):
        run_sweep(spec, log=messages.append)
    assert (other / "poses_final.npy").is_file()


def test_a_sweep_run_keeps_every_stage_to_its_threads(finished_run, tmp_path, monkeypatch):
    """A Ray task renders with the CPUs it declared (`render_threads`); the run's other CPU stages (the coherence
    solve at construction, projection, the loss, evaluation) keep to them too."""
    import warpbags.sweep as sweep
    import warpbags.threads as threads
    from warpbags.threads import host_threads

    monkeypatch.setattr(threads, "usable_cores", lambda: 8)  # more cores than the run's share, on any machine
    seen = []

    class Stop(Exception):
        """Raised where the trainer would be built: the thread limit there is what this test reads."""

    def start_or_resume(*args, **kwargs):
        seen.append(host_threads())
        raise Stop

    monkeypatch.setattr(sweep, "start_or_resume", start_or_resume)
    info = json.loads((finished_run / "config.json").read_text())
    spec = sweep.SweepSpec(scene=info["scene_root"], out=tmp_path / "sweep", rot_noises=(0,), views=(4,), seeds=(0,))
    with pytest.raises(Stop):
        sweep.run_combination(spec, sweep.sweep_runs(spec)[0], sweep.open_scene(spec.scene), render_threads=1)
    assert seen == [1] and host_threads() == 8  # and the limit ends with the run


def test_report_has_the_metrics_and_pictures(finished_run):
    assert runner.invoke(app, ["eval", str(finished_run), "--refine-iters", "0"]).exit_code == 0
    report = (finished_run / "report.md").read_text()
    assert "| procrustes | final |" in report and "PSNR" in report
    assert "| centre floor (deg) |" in report
    assert "| test poses | PSNR | SSIM | FLIP | LPIPS |" in report
    flip = json.loads((finished_run / "eval.json").read_text())["images"]["mean"]["flip"]
    assert f"| {flip:.4f} |" in report
    assert "![loss and pose error](curves.png)" in report and (finished_run / "curves.png").stat().st_size > 1000
    # the quick preset's search over turns in round 2 (8 iterations: rounds of 2, 3 and 3, round 2 from iteration 2)
    assert "| from iteration | camera | best turn | its loss | unturned loss | kept |" in report
    assert "| 2 |" in report
    assert "eval/" in report
    assert "## Held-out views: truth | render | 4x error" in report


def test_the_refinement_rows_show_the_refined_metrics_and_the_pictures_say_they_are_refined(finished_run, tmp_path):
    """Nothing checked the refinement row's numbers: a terminal row or report.md row that showed the aligned metrics
    passed; and the pictures, the refined render, were labelled "render" next to the aligned row."""
    run = _copy_of(finished_run, tmp_path / "run")
    result = runner.invoke(app, ["eval", str(run), "--refine-iters", "3"])
    assert result.exit_code == 0, result.output
    saved = json.loads((run / "eval.json").read_text())
    report = (run / "report.md").read_text()
    for label, terminal, key in (("aligned", "aligned", "images"),
                                 ("+ 3 refinement iterations", "+ 3 refinement its", "images_after_test_pose_refinement")):
        mean = saved[key]["mean"]
        assert f"| {label} | {mean['psnr']:.2f} | {mean['ssim']:.4f} | {mean['flip']:.4f} |" in report, report
        row = next(line for line in result.output.splitlines() if terminal in line)
        assert f"{mean['psnr']:.2f}" in row and f"{mean['ssim']:.4f}" in row and f"{mean['flip']:.4f}" in row, row
    assert saved["images"]["mean"]["psnr"] != saved["images_after_test_pose_refinement"]["mean"]["psnr"]
    assert "## Held-out views: truth | render after 3 refinement iterations | 4x error" in report


def test_sweep_bad_values_one_line(tmp_path):
    result = runner.invoke(app, ["sweep", str(tmp_path), "--rot-noises", "a,b"])
    assert result.exit_code == 2 and "--rot-noises 'a,b': 'a' is not a number" in result.output
    result = runner.invoke(app, ["sweep", "maryrose", "--views", "4,1", "--out", str(tmp_path / "s")])
    assert result.exit_code == 2 and "--views '4,1': 1 is below 2" in result.output
    result = runner.invoke(app, ["sweep", "maryrose", "--rot-noises=0,-5", "--out", str(tmp_path / "s")])
    assert result.exit_code == 2 and "--rot-noises '0,-5': -5 is below 0" in result.output  # the sweep's option
    result = runner.invoke(app, ["sweep", "maryrose", "--rot-noises", "10,200", "--out", str(tmp_path / "s")])
    assert result.exit_code == 2 and "--rot-noises '10,200': 200 is above 180" in result.output
    result = runner.invoke(app, ["sweep", "maryrose", "--rot-noises", "nan", "--out", str(tmp_path / "s")])
    assert result.exit_code == 2 and "--rot-noises 'nan': 'nan' is not a finite number" in result.output
    result = runner.invoke(app, ["sweep", "maryrose", "--refine-iters", "-1", "--out", str(tmp_path / "s")])
    assert result.exit_code == 2 and "--refine-iters must be >= 0, got -1" in result.output
    (tmp_path / "a-file").write_text("")
    result = runner.invoke(app, ["sweep", "maryrose", "--out", str(tmp_path / "a-file")])
    message = " ".join(result.output.split())
    assert result.exit_code == 2 and "a-file is a file, not a folder to hold the sweep" in message
    result = runner.invoke(app, ["sweep", "maryrose", "--views", ",", "--out", str(tmp_path / "s")])
    assert result.exit_code == 2 and "--views ',': expected comma-separated numbers, got none" in result.output
    # a combination that cannot run is named before the first one trains (maryrose has 69 images)
    result = runner.invoke(app, ["sweep", "maryrose", "--views", "4,80", "--rot-noises", "5",
                                 "--out", str(tmp_path / "s")])
    lines = [line for line in result.output.splitlines() if line.strip()]
    assert result.exit_code == 2 and len(lines) == 1, result.output
    assert "sweep run " in lines[0] and "fewer than --views 80" in lines[0] and not (tmp_path / "s").exists()


def test_a_sweep_with_two_views_reports_their_pairwise_errors(finished_run, tmp_path):
    from warpbags.sweep import SweepSpec, run_sweep

    info = json.loads((finished_run / "config.json").read_text())
    spec = SweepSpec(scene=info["scene_root"], out=tmp_path / "sweep", rot_noises=(5,), views=(2,), seeds=(0,),
                     refine_iters=0, overrides=(("iters", 4),))
    rows = run_sweep(spec, log=lambda message: None)
    for row in rows:
        report = json.loads((spec.out / row["run"] / "eval.json").read_text())
        assert report["alignment"] == "pairwise"
        assert row["rot_err_initial"] == report["poses"]["pairwise"]["initial"]["rotation_deg_mean"] > 0.5
    # `warpbags eval` asked for procrustes titles its held-out table with the alignment it used
    result = runner.invoke(app, ["eval", str(spec.out / rows[0]["run"]), "--refine-iters", "0"],
                           env={"COLUMNS": "200"})
    assert result.exit_code == 0 and "held-out views (" in result.output, result.output
    assert "pairwise alignment)" in result.output and "procrustes alignment)" not in result.output, result.output


def test_json_outputs_write_a_non_finite_number_as_null():
    from warpbags.files import finite_json

    text = finite_json({"psnr": float("inf"), "views": [1.5, float("nan")], "nested": ({"flip": -float("inf")},)})
    assert json.loads(text) == {"psnr": None, "views": [1.5, None], "nested": [{"flip": None}]}
    assert "Infinity" not in text and "NaN" not in text


def test_atomic_output_replaces_only_on_success(tmp_path):
    from warpbags.files import atomic_output

    target = tmp_path / "table.json"
    target.write_text("old")
    with pytest.raises(RuntimeError):
        with atomic_output(target) as temporary:
            temporary.write_text("half")
            raise RuntimeError("writer failed")
    assert target.read_text() == "old" and sorted(p.name for p in tmp_path.iterdir()) == ["table.json"]
    with atomic_output(target) as temporary:
        assert temporary.suffix == ".json"
        temporary.write_text("new")
    assert target.read_text() == "new" and sorted(p.name for p in tmp_path.iterdir()) == ["table.json"]


def test_writable_folder_names_the_file_or_the_folder_that_cannot_be_written(tmp_path):
    from warpbags.files import writable_folder

    (tmp_path / "a-file").write_text("")
    expected = f"{tmp_path / 'a-file'} is a file, not a folder to train into"
    for path in (tmp_path / "a-file", tmp_path / "a-file" / "run" / "deeper"):
        with pytest.raises(WarpbagsError, match="^" + re.escape(expected) + "$"):
            writable_folder(path, "to train into")
    fresh = tmp_path / "new" / "run"
    assert writable_folder(fresh, "to train into") == fresh and not fresh.parent.exists()  # checked, not made
    # `runs` linked to a disk that is not mounted: a FileExistsError traceback once the run made its folder
    (tmp_path / "runs").symlink_to(tmp_path / "unmounted" / "scratch")
    with pytest.raises(WarpbagsError, match=f"^{re.escape(str(tmp_path / 'runs'))} is a link to .*unmounted/scratch, "
                                            "which does not exist: no folder to train into$"):
        writable_folder(tmp_path / "runs" / "mary", "to train into")
    if os.geteuid() == 0:
        return  # root writes anywhere: a folder without write permission cannot be tested
    locked = tmp_path / "locked"
    locked.mkdir(mode=0o555)
    expected = f"{locked} is not writable, so {locked / 'run'} cannot be made"
    with pytest.raises(WarpbagsError, match="^" + re.escape(expected)):
        writable_folder(locked / "run", "to train into")


def test_comparison_file_names_never_collide():
    assert comparison_file_names(["images/r_0.png", "images/r_10.png"]) == ["r_0.png", "r_10.png"]
    assert comparison_file_names(["a/x.png", "b/x.png", "y.jpg"]) == ["000_x.png", "001_x.png", "002_y.png"]
    assert comparison_file_names(["x.jpg", "x.png"]) == ["000_x.png", "001_x.png"]


def test_eval_of_views_without_masks_renders_on_the_runs_background(finished_run, tmp_path, monkeypatch):
    """Without masks the held-out views are compared as they are, their background and all, which a run learns in
    front of its own background (as `render` and `view` show it): eval rendered them, and refined their poses, on
    white whatever the run's, so a run trained on black lost every uncovered pixel (a maskless synthetic scene: PSNR
    6.66 instead of 10.44). Here the scene is photographed on black without masks: on the run's black its views score
    17.8 dB, on white 2.1. Views with masks stay on white (GaussianObject's protocol, every README number) whatever
    the run's background, their metrics unchanged."""
    import cv2

    import warpbags.evaluation

    scene_root = Path(json.loads((finished_run / "config.json").read_text())["scene_root"])
    on_black = tmp_path / "scene_on_black"
    shutil.copytree(scene_root, on_black, ignore=shutil.ignore_patterns("masks"))
    for image_path in sorted((on_black / "images").glob("*.png")):
        mask = cv2.imread(str(scene_root / "masks" / image_path.name), cv2.IMREAD_GRAYSCALE)
        image = cv2.imread(str(image_path), cv2.IMREAD_COLOR)
        image[mask < 128] = 0
        assert cv2.imwrite(str(image_path), image)
    maskless = load_scene(on_black)
    assert maskless.masks is None
    real_render, backgrounds_seen = warpbags.evaluation.render_gaussians, []

    def recording_render(*args, backgrounds: torch.Tensor, **kwargs):
        backgrounds_seen.append(backgrounds.cpu())
        return real_render(*args, backgrounds=backgrounds, **kwargs)

    monkeypatch.setattr(warpbags.evaluation, "render_gaussians", recording_render)
    reports = {}
    for scene, background, expected in ((on_black, "black", 0.0), (on_black, "white", 1.0),
                                        (scene_root, "black", 1.0), (scene_root, "white", 1.0)):
        run = _copy_of(finished_run, tmp_path / f"{scene.name}_{background}")
        info = json.loads((run / "config.json").read_text())
        if scene == on_black:  # without masks the scene is normalized otherwise: the run's true poses follow it
            np.save(run / "poses_true.npy", maskless.viewmats[[maskless.image_names.index(name)
                                                                for name in info["image_names"]]].double().numpy())
            info["normalization"] = maskless.normalization.to_dict()
        info.update(scene_root=str(scene), config={**info["config"], "background": background})
        (run / "config.json").write_text(json.dumps(info))
        backgrounds_seen.clear()
        reports[scene, background] = evaluate_run(run, refine_iters=1, log=lambda message: None)
        # every render, those of the test-pose refinement too
        assert backgrounds_seen and all((seen == expected).all() for seen in backgrounds_seen), (scene, background)
    psnr = {key: report["images"]["mean"]["psnr"] for key, report in reports.items()}
    assert psnr[on_black, "white"] < psnr[on_black, "black"] - 10.0, psnr  # 2.1 and 17.8 dB measured
    for key in ("images", "images_after_test_pose_refinement"):
        assert reports[scene_root, "black"][key] == reports[scene_root, "white"][key]


# ------------------------------------------------------------------------------------------------ damaged runs
def _copy_of(finished_run, folder):
    """The finished run without its evaluation, renders, exports and checkpoints."""
    shutil.copytree(finished_run, folder, ignore=shutil.ignore_patterns(
        "eval*", "report.md", "curves.png", "turntable*", "export", "checkpoints"))
    return folder


def _lines(result) -> list[str]:
    return [line for line in result.output.splitlines() if line.strip()]


def test_a_ply_of_no_gaussians_is_one_line_and_no_command_writes_anything(finished_run, tmp_path):
    run = _copy_of(finished_run, tmp_path / "run")
    header = (run / "gaussians.ply").read_bytes().split(b"end_header\n")[0]
    (run / "gaussians.ply").write_bytes(re.sub(rb"element vertex \d+", b"element vertex 0", header) + b"end_header\n")
    with pytest.raises(WarpbagsError, match=re.escape(f"{run / 'gaussians.ply'}: the PLY holds no Gaussians")):
        read_ply(run / "gaussians.ply")
    before = sorted(path.name for path in run.iterdir())
    for command in (["eval", str(run)], ["render", str(run), "--frames", "2"],
                    ["export", str(run), "--out", str(tmp_path / "export")]):
        result = runner.invoke(app, command)
        assert result.exit_code == 2 and len(_lines(result)) == 1, result.output
        assert "gaussians.ply: the PLY holds no Gaussians" in result.output
    assert sorted(path.name for path in run.iterdir()) == before and not (tmp_path / "export").exists()


@pytest.mark.parametrize("change, message", [
    (lambda info: info.pop("scene"), "has no 'scene': written by an older warpbags"),
    (lambda info: info.update(scene_root=5), "'scene_root' must be a folder (text), got 5"),
    (lambda info: info.update(resolution="8"), "'resolution' must be 1, 2, 4 or 8, got '8'"),
    (lambda info: info.update(image_names="IMG_0.png"), "'image_names' must be a list of image names"),
])
def test_a_config_json_with_a_damaged_scene_field_is_one_line_naming_it(finished_run, tmp_path, change, message):
    """A config.json without "scene" was a KeyError traceback out of eval, a scene_root of 5 a TypeError, and a
    resolution of "8" said "resolution must be 1, 2, 4 or 8, got 8" without naming the file."""
    run = _copy_of(finished_run, tmp_path / "run")
    info = json.loads((run / "config.json").read_text())
    change(info)
    (run / "config.json").write_text(json.dumps(info))
    result = runner.invoke(app, ["eval", str(run), "--refine-iters", "0"])
    assert result.exit_code == 2 and len(_lines(result)) == 1, result.output
    assert str(run / "config.json") in result.output.replace("\n", "") and message in " ".join(result.output.split())
    assert not (run / "eval.json").exists()


def test_paths_with_brackets_are_printed_as_they_are(finished_run, tmp_path):
    """Rich read `[s0]` in a run's path as markup: `warpbags eval "m[s0]"` said it wrote m/eval.json."""
    run = _copy_of(finished_run, tmp_path / "m[s0]")
    result = runner.invoke(app, ["eval", str(run), "--refine-iters", "0"])
    assert result.exit_code == 0, result.output
    assert f"wrote {run / 'eval.json'}" in " ".join(result.output.split()), result.output


def test_a_run_without_its_result_is_told_to_resume_only_when_it_has_a_checkpoint(finished_run, tmp_path):
    """A run killed before its first checkpoint (SIGKILL, power) was told to continue with --resume, which refuses
    it ("no checkpoint")."""
    killed = _copy_of(finished_run, tmp_path / "killed")  # no checkpoints
    (killed / "gaussians.ply").unlink()
    stopped = tmp_path / "stopped"
    shutil.copytree(finished_run, stopped, ignore=shutil.ignore_patterns("eval*", "report.md", "gaussians.ply"))
    for run, message in ((killed, "the run stopped before its first checkpoint, so it cannot be resumed"),
                         (stopped, "the run has not finished (continue it with --resume)")):
        result = runner.invoke(app, ["eval", str(run), "--refine-iters", "0"])
        assert result.exit_code == 2 and len(_lines(result)) == 1, result.output
        assert message in " ".join(result.output.split()), result.output


def test_a_ply_header_claiming_more_gaussians_than_the_file_holds_is_a_truncated_ply(finished_run, tmp_path):
    """`element vertex 1000000000` in a small file was read as that many bytes: a MemoryError traceback from
    eval, render, export and view."""
    run = _copy_of(finished_run, tmp_path / "run")
    data = (run / "gaussians.ply").read_bytes()
    (run / "gaussians.ply").write_bytes(re.sub(rb"element vertex \d+", b"element vertex 1000000000000", data))
    with pytest.raises(WarpbagsError, match=re.escape(f"{run / 'gaussians.ply'}: truncated PLY (")):
        read_ply(run / "gaussians.ply")
    result = runner.invoke(app, ["eval", str(run), "--refine-iters", "0"])
    assert result.exit_code == 2 and len(_lines(result)) == 1 and "truncated PLY" in result.output, result.output


def test_a_log_cut_short_is_named_by_line_and_eval_writes_nothing(finished_run, tmp_path):
    from warpbags.run_folder import RunFolder

    run = _copy_of(finished_run, tmp_path / "run")
    text = (run / "log.jsonl").read_text()
    count = len(text.splitlines())
    (run / "log.jsonl").write_text(text[:-20])  # the last record cut short, as a crash leaves it
    with pytest.raises(WarpbagsError, match=re.escape(f"{run / 'log.jsonl'}:{count}: not a log record")):
        RunFolder(run).read_log()
    result = runner.invoke(app, ["eval", str(run), "--refine-iters", "0"])
    assert result.exit_code == 2 and len(_lines(result)) == 1, result.output
    assert f"log.jsonl:{count}: not a log record" in result.output
    for output in ("eval", "eval.json", "report.md", "curves.png"):
        assert not (run / output).exists(), output


@pytest.mark.parametrize("change, message", [
    (lambda record: record.pop("loss"), 'no number "loss"'),
    (lambda record: record.update(rot_err_deg="3"), 'no number "rot_err_deg"'),
    (lambda record: record.update(iter=-1), 'no iteration count "iter"'),
])
def test_a_log_record_without_what_the_report_plots_is_named_by_line(finished_run, tmp_path, change, message):
    run = _copy_of(finished_run, tmp_path / "run")
    lines = (run / "log.jsonl").read_text().splitlines()
    record = json.loads(lines[1])
    change(record)
    lines[1] = json.dumps(record)
    (run / "log.jsonl").write_text("\n".join(lines) + "\n")
    result = runner.invoke(app, ["eval", str(run), "--refine-iters", "0"])
    assert result.exit_code == 2 and len(_lines(result)) == 1, result.output
    assert f"log.jsonl:2: not a log record ({message})" in result.output
    for output in ("eval", "eval.json", "report.md", "curves.png"):
        assert not (run / output).exists(), output


def _zero_poses(poses):
    return np.zeros_like(poses)


def _mirrored(poses):
    poses = poses.copy()
    poses[1, 0, :3] *= -1  # camera 1's rotation part a reflection (determinant -1)
    return poses


def _not_finite(poses):
    poses = poses.copy()
    poses[2, 0, 3] = np.nan
    return poses


@pytest.mark.parametrize("name, damage, message", [
    ("intrinsics", lambda K: np.zeros((4, 2)), "intrinsics.npy: expected [C,3,3] intrinsics, got an array of shape "
                                               "[4, 2]"),
    ("poses_final", lambda P: P[:, :3, :3], "poses_final.npy: expected [C,4,4] world-to-camera poses, got an array of "
                                            "shape [4, 3, 3]"),
    ("poses_final", lambda P: np.zeros(16), "poses_final.npy: expected [C,4,4] world-to-camera poses, got an array of "
                                            "shape [16]"),
    ("poses_final", _zero_poses, "poses_final.npy: camera 0 is not a world-to-camera pose"),
    ("poses_init", _mirrored, "poses_init.npy: camera 1 is not a world-to-camera pose (its 3x3 part has determinant -1"),
    ("poses_start", _not_finite, "poses_start.npy: camera 2 holds a value that is not finite"),
    # a focal length of 0 rendered a white picture
    ("intrinsics", lambda K: K * np.array([1.0, 0.0, 1.0])[:, None], "intrinsics.npy: camera 0 has focal lengths"),
    ("poses_true", lambda P: P[0], "poses_true.npy: expected [C,4,4] world-to-camera poses, got an array of shape "
                                   "[4, 4]"),
    ("poses_true", lambda P: P[:3], "poses_true.npy holds 3 cameras, the run's poses 4 (poses_final.npy)"),
    ("poses_final", lambda P: P[:0], "poses_final.npy: expected [C,4,4] world-to-camera poses, got an array of shape "
                                     "[0, 4, 4]"),
])
def test_malformed_camera_files_are_named_by_every_command_that_reads_them(finished_run, tmp_path, name, damage,
                                                                           message):
    """Every reader of a run's camera files (load_run: eval, agree, render, export; the viewer) checks them in one
    place: [C,4,4] rigid poses and [C,3,3] intrinsics, finite, one C, the offending file named."""
    from warpbags.viewer.content import load_viewer_content

    run = _copy_of(finished_run, tmp_path / "run")
    np.save(run / f"{name}.npy", damage(np.load(finished_run / f"{name}.npy")))
    with pytest.raises(WarpbagsError, match="^" + re.escape(f"{run / name}")):
        load_run(run)
    with pytest.raises(WarpbagsError, match=re.escape(message)):
        load_viewer_content(run, log=lambda line: None)
    result = runner.invoke(app, ["agree", str(finished_run), str(run)])  # all-zero poses were a 180 deg table
    assert result.exit_code == 2 and len(_lines(result)) == 1, result.output
    assert message in " ".join(result.output.split())


def test_a_config_json_naming_other_than_the_runs_cameras_is_one_line_from_every_command(finished_run, tmp_path):
    """config.json's image_names go with the cameras by position: 3 names for 4 cameras were an IndexError traceback
    out of `warpbags view`, a COLMAP model of 3 images from `export` and an evaluation from `eval`."""
    from warpbags.viewer.content import load_viewer_content

    run = _copy_of(finished_run, tmp_path / "run")
    info = json.loads((run / "config.json").read_text())
    assert len(info["image_names"]) == 4
    for names in (info["image_names"][:3], [*info["image_names"], "view_999.png"]):
        (run / "config.json").write_text(json.dumps({**info, "image_names": names}))
        message = (f"{run / 'config.json'}: 'image_names' lists {len(names)} training views, the run's poses 4 "
                   "(poses_final.npy)")
        with pytest.raises(WarpbagsError, match="^" + re.escape(message)):
            load_run(run)
        with pytest.raises(WarpbagsError, match="^" + re.escape(message)):
            load_viewer_content(run, log=lambda line: None)
        for command in (["eval", str(run), "--refine-iters", "0"], ["export", str(run), "--out", str(tmp_path / "e")],
                        ["render", str(run), "--frames", "2"], ["view", str(run), "--port", "0"]):
            result = runner.invoke(app, command)
            assert result.exit_code == 2 and len(_lines(result)) == 1, result.output
            assert message in " ".join(result.output.split())
    assert not (tmp_path / "e").exists() and not (run / "eval.json").exists() and not (run / "turntable").exists()


def test_gaussians_that_are_not_finite_are_named_and_render_nothing(finished_run, tmp_path):
    """A gaussians.ply with NaN centres rendered white frames and exited 0."""
    run = _copy_of(finished_run, tmp_path / "run")
    params = read_ply(run / "gaussians.ply")
    params["means"][5, 0] = float("nan")
    write_ply(run / "gaussians.ply", params)
    result = runner.invoke(app, ["render", str(run), "--frames", "2"])
    assert result.exit_code == 2 and len(_lines(result)) == 1, result.output
    assert "gaussians.ply: x of Gaussian 5 is nan (1 of" in " ".join(result.output.split())
    assert not (run / "turntable").exists()


def test_run_files_named_wrongly_or_missing_from_a_finished_run_say_so(finished_run, tmp_path):
    """A run's config.json given for the run said "not a training run (no config.json)"; a finished run missing a pose
    file said it had not finished and to --resume it. Without poses_final.npy (what a kill between the results'
    writes left, when an earlier warpbags wrote gaussians.ply first) every command that reads the run says so in one
    line, not a TypeError traceback from the camera files' reader."""
    result = runner.invoke(app, ["eval", str(finished_run / "config.json"), "--refine-iters", "0"])
    assert result.exit_code == 2 and "config.json is a file: name the run's folder" in " ".join(result.output.split())
    for name in ("poses_true.npy", "poses_final.npy"):
        run = _copy_of(finished_run, tmp_path / f"without-{name}")
        (run / name).unlink()
        for command in (["eval", str(run), "--refine-iters", "0"], ["export", str(run)], ["render", str(run)]):
            result = runner.invoke(app, command)
            assert result.exit_code == 2 and len(_lines(result)) == 1, result.output
            assert f"{name} is missing from the finished run" in " ".join(result.output.split())


def test_a_config_json_that_is_no_runs_says_so(finished_run, tmp_path):
    """A config.json of {} was "unreadable ('config')", a KeyError's text; a 'config' that is a list of pairs was
    read as one."""
    run = _copy_of(finished_run, tmp_path / "run")
    (run / "config.json").write_text("{}")
    result = runner.invoke(app, ["eval", str(run), "--refine-iters", "0"])
    assert result.exit_code == 2 and len(_lines(result)) == 1, result.output
    assert "config.json holds no 'config' (not a run's config.json)" in " ".join(result.output.split())
    # a 'config' of [name, value] pairs read as a config (dict() takes them) and then failed the sweep's readers
    info = json.loads((finished_run / "config.json").read_text())
    (run / "config.json").write_text(json.dumps({**info, "config": [list(item) for item in info["config"].items()]}))
    result = runner.invoke(app, ["eval", str(run), "--refine-iters", "0"])
    assert result.exit_code == 2 and len(_lines(result)) == 1, result.output
    assert "config.json: 'config' must be a JSON object, got list" in " ".join(result.output.split())


def test_a_malformed_saved_config_names_config_json(finished_run, tmp_path):
    run, info = _run_on_scene(_copy_of(finished_run, tmp_path / "source"), tmp_path,
                              json.loads((finished_run / "config.json").read_text())["scene_root"],
                              normalization={"scale": "x"})
    for command in (["eval", str(run), "--refine-iters", "0"], ["export", str(run), "--out", str(tmp_path / "e")]):
        result = runner.invoke(app, command)
        assert result.exit_code == 2 and len(_lines(result)) == 1, result.output
        assert f"{run / 'config.json'}: normalization must be" in " ".join(result.output.split())
    assert not (tmp_path / "e").exists() and not (run / "eval.json").exists()
    (run / "config.json").write_text(json.dumps({**info, "config": {**info["config"], "iters": "abc"}}))
    with pytest.raises(WarpbagsError, match="^" + re.escape(f"{run / 'config.json'}: iters must be like 5000, got "
                                                            "'abc'")):
        load_run(run)
    (run / "config.json").write_text(json.dumps({**info, "config": {**info["config"], "iters": 0}}))
    with pytest.raises(WarpbagsError, match="^" + re.escape(f"{run / 'config.json'}: --iters must be")):
        load_run(run)  # out of range: refused by name, not a modulo by zero in the schedule


def test_export_refuses_the_run_its_scene_and_other_folders_and_checks_its_targets_first(finished_run, tmp_path):
    scene = tmp_path / "scene"
    shutil.copytree(json.loads((finished_run / "config.json").read_text())["scene_root"], scene)
    run, _ = _run_on_scene(_copy_of(finished_run, tmp_path / "source"), tmp_path, scene)

    def contents(folder):
        return {path.relative_to(folder): path.read_bytes() for path in sorted(folder.rglob("*")) if path.is_file()}

    kept = {folder: contents(folder) for folder in (run, scene)}
    (tmp_path / "notes").mkdir()
    (tmp_path / "notes" / "todo.txt").write_text("mine")
    other = _copy_of(finished_run, tmp_path / "other")  # another run: its export/ would take this run's model
    kept[other] = contents(other)
    for out, message in [(run, "is the run folder"), (scene, "is the run's scene folder"),
                         (tmp_path, "is a folder that holds the run folder"),
                         (tmp_path / "notes", "is not empty and not an earlier export (it holds todo.txt)"),
                         (other / "export", f"is inside the run folder {other.resolve()}, another run than")]:
        result = runner.invoke(app, ["export", str(run), "--out", str(out)])
        assert result.exit_code == 2 and len(_lines(result)) == 1, result.output
        assert message in " ".join(result.output.split())
    assert {folder: contents(folder) for folder in (run, scene, other)} == kept
    assert (tmp_path / "notes" / "todo.txt").read_text() == "mine"
    # an earlier export is replaced
    export = tmp_path / "export"
    assert runner.invoke(app, ["export", str(run), "--out", str(export)]).exit_code == 0
    result = runner.invoke(app, ["export", str(run), "--out", str(export)])
    assert result.exit_code == 0, result.output
    # entries of the wrong kind: refused before anything is written
    for name, make, message in [("gaussians.ply", Path.mkdir, "gaussians.ply is a folder, where an export writes a "
                                 "file"),
                                ("sparse", Path.touch, "sparse is a file, where an export writes a folder")]:
        wrong = tmp_path / f"wrong-{name}"
        wrong.mkdir()
        make(wrong / name)
        result = runner.invoke(app, ["export", str(run), "--out", str(wrong)])
        assert result.exit_code == 2 and len(_lines(result)) == 1, result.output
        assert message in " ".join(result.output.split())
        assert [path.name for path in wrong.iterdir()] == [name]


@pytest.mark.parametrize("command, make, message", [
    (["eval", "--refine-iters", "0"], lambda run: (run / "eval").write_text(""), "eval is a file, not a folder"),
    (["eval", "--refine-iters", "0"], lambda run: (run / "eval.json").mkdir(), "eval.json is a folder, not a file"),
    (["eval", "--refine-iters", "0"], lambda run: (run / "report.md").mkdir(), "report.md is a folder, not a file"),
    (["render", "--frames", "2"], lambda run: (run / "turntable").write_text(""), "turntable is a file, not a folder"),
    (["render", "--frames", "2"], lambda run: (run / "turntable.mp4").mkdir(), "turntable.mp4 is a folder, not a file"),
])
def test_outputs_of_the_wrong_kind_are_one_line_before_anything_is_written(finished_run, tmp_path, command, make,
                                                                          message):
    run = _copy_of(finished_run, tmp_path / "run")
    make(run)
    before = sorted(path.name for path in run.iterdir())
    result = runner.invoke(app, [command[0], str(run), *command[1:]])
    assert result.exit_code == 2 and len(_lines(result)) == 1, result.output
    assert message in " ".join(result.output.split())
    assert sorted(path.name for path in run.iterdir()) == before


def test_a_capture_of_few_views_is_evaluated_on_every_8th_view_it_did_not_train_on(finished_run, tmp_path, caplog):
    """Without sparse_test.txt every 8th view that no split takes is held out, the same views for every view
    count. A capture of few views may have none left so: its runs are then evaluated on every 8th view
    they did not train on, and one that trained on all of those is one line, without the loader's warning about
    the missing file before it."""
    from warpbags.data import load_scene
    from warpbags.evaluation import held_out_views

    scene = tmp_path / "scene"
    shutil.copytree(json.loads((finished_run / "config.json").read_text())["scene_root"], scene)
    (scene / "sparse_test.txt").unlink()
    for size, views in ((4, "0 4 12 14"), (6, "0 2 4 6 12 14"), (9, "0 2 3 4 5 6 12 13 14")):  # no view 8
        (scene / f"sparse_{size}.txt").write_text(views.replace(" ", "\n") + "\n")
    names = load_scene(scene).image_names
    run, _ = _run_on_scene(_copy_of(finished_run, tmp_path / "source"), tmp_path, scene,
                           image_names=[names[i] for i in (0, 4, 12, 14)])
    caplog.clear()  # the load_scene above said the same: the warning must come from held_out_views
    with caplog.at_level("WARNING", logger="warpbags.data"):
        assert held_out_views(load_run(run)).image_names == [names[8]]
    assert "sparse_test.txt missing, test views [8]" in caplog.text

    (scene / "sparse_2.txt").write_text("0\n8\n")  # view 8 in a split: the scene's rule holds out no view
    assert held_out_views(load_run(run)).image_names == [names[8]]  # the run did not train on it
    info = json.loads((run / "config.json").read_text())
    (run / "config.json").write_text(json.dumps({**info, "image_names": [names[i] for i in (0, 4, 8, 12)]}))
    caplog.clear()
    with caplog.at_level("WARNING", logger="warpbags.data"):
        result = runner.invoke(app, ["eval", str(run), "--refine-iters", "0"])
    assert result.exit_code == 2 and len(_lines(result)) == 1, result.output
    assert "has no test split" in result.output and "every 8th view" in " ".join(result.output.split())
    assert "sparse_test.txt missing" not in caplog.text and not (run / "eval.json").exists()


def test_a_test_split_that_holds_a_training_view_of_the_run_is_one_error(finished_run, tmp_path):
    """A sparse_test.txt written after training that names one of the run's training views would score the run on
    an image it was fitted to: eval refuses, naming the view, before it writes anything."""
    from warpbags.data import load_scene

    scene = tmp_path / "scene"
    shutil.copytree(json.loads((finished_run / "config.json").read_text())["scene_root"], scene)
    names = load_scene(scene).image_names
    test = [int(line) for line in (scene / "sparse_test.txt").read_text().split()]
    run, _ = _run_on_scene(_copy_of(finished_run, tmp_path / "source"), tmp_path, scene,
                           image_names=[names[test[0]]] + [name for name in names if name != names[test[0]]][:3])
    result = runner.invoke(app, ["eval", str(run), "--refine-iters", "0"])
    assert result.exit_code == 2 and len(_lines(result)) == 1, result.output
    assert "holds views the run trained on" in result.output and names[test[0]] in result.output
    assert not (run / "eval.json").exists()


def test_eval_json_is_written_last(finished_run, tmp_path, monkeypatch):
    """A sweep takes eval.json as "evaluated": an evaluation stopped before its report (a kill, a full disk) must
    leave none, or the sweep would skip the run without its report from then on."""
    run = _copy_of(finished_run, tmp_path / "run")
    (run / "eval.json").unlink(missing_ok=True)

    def fail(*args, **kwargs):
        raise OSError("disk full")

    monkeypatch.setattr("warpbags.evaluation.write_run_report", fail)
    with pytest.raises(OSError, match="disk full"):
        evaluate_run(run, refine_iters=0, log=lambda message: None)
    assert not (run / "eval.json").exists()


def test_a_file_a_command_cannot_write_is_one_line(finished_run, tmp_path, monkeypatch):
    """A full disk or a file-size limit under `warpbags export` (or agree --json) was an OSError traceback."""
    def full_disk(path, params):
        raise OSError(27, "File too large", str(path))

    monkeypatch.setattr("warpbags.export.write_ply", full_disk)
    result = runner.invoke(app, ["export", str(finished_run), "--out", str(tmp_path / "made" / "export")])
    assert result.exit_code == 2 and len(_lines(result)) == 1, result.output
    assert "OSError: [Errno 27] File too large" in " ".join(result.output.split())
    assert not (tmp_path / "made").exists()  # the folders it made, and what it wrote there, are gone


def test_an_npz_cut_short_under_an_npy_name_is_one_line(tmp_path):
    """np.load reads a file starting with a zip's magic as an archive: one cut short was a BadZipFile traceback out
    of `warpbags info` and everything that reads poses_bounds.npy or the depth maps."""
    from warpbags.files import read_array

    np.savez(tmp_path / "poses.npz", poses=np.zeros((3, 17)))
    (tmp_path / "poses_bounds.npy").write_bytes((tmp_path / "poses.npz").read_bytes()[:60])
    with pytest.raises(WarpbagsError, match="poses_bounds.npy is not a NumPy array file"):
        read_array(tmp_path / "poses_bounds.npy", "poses")


# ------------------------------------------------------------------------------------- frame and background of eval
def _hamilton(p: torch.Tensor, q: torch.Tensor) -> torch.Tensor:
    """Quaternion product p q, (w, x, y, z) first to last: the rotation q, then p."""
    w1, x1, y1, z1 = p.unbind(-1)
    w2, x2, y2, z2 = q.unbind(-1)
    return torch.stack([w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2, w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
                        w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2, w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2], dim=-1)


def _moved_by_a_similarity(run: Path, angle_deg: float, scale: float, seed: int = 0) -> None:
    """Move the run's model frame by x -> scale R x + shift (R: `angle_deg` about a random axis, a random shift),
    written out here without warpbags' pose maths: its Gaussians (means, orientations, log-scales; SH degree 0, so
    colours need no turning) and the poses it estimated (initial, start, final), which are in the model's frame. The
    true poses and the scene stay: the run is the same run, trained in another gauge."""
    from random_poses import generator, skew_reference, unit_vectors

    gen = generator(seed)
    axis = unit_vectors(1, gen)[0]
    shift = torch.randn(3, generator=gen, dtype=torch.float64)
    angle = math.radians(angle_deg)
    rotation = torch.linalg.matrix_exp(skew_reference(angle * axis))
    turn = torch.cat([torch.tensor([math.cos(angle / 2)], dtype=torch.float64), math.sin(angle / 2) * axis])
    params = read_ply(run / "gaussians.ply")
    assert "shN" not in params  # view-dependent colour would have to turn with the frame
    params["means"] = (scale * params["means"].double() @ rotation.T + shift).float()
    params["quats"] = _hamilton(turn.expand(len(params["quats"]), 4), params["quats"].double()).float()
    params["scales"] = params["scales"] + math.log(scale)
    write_ply(run / "gaussians.ply", params)
    for name in ("poses_init", "poses_start", "poses_final"):
        # camera coordinates R_c x + t_c of a point x are those of x' = s R x + shift divided by s: the world-to-camera
        # [R_c R^T | s t_c - R_c R^T shift] sees the moved world as [R_c | t_c] saw the old one, scaled by s
        poses = np.load(run / f"{name}.npy")
        viewmats = torch.from_numpy(poses).double()
        turned = viewmats[:, :3, :3] @ rotation.T
        moved = viewmats.clone()
        moved[:, :3, :3] = turned
        moved[:, :3, 3] = scale * viewmats[:, :3, 3] - turned @ shift
        np.save(run / f"{name}.npy", moved.numpy().astype(poses.dtype))


def _numbers(tree, prefix: str = "") -> dict[str, np.ndarray]:
    """The numeric leaves of a nested dict, by their dotted key."""
    leaves = {}
    for key, value in tree.items():
        if isinstance(value, dict):
            leaves.update(_numbers(value, f"{prefix}{key}."))
        elif value is not None:
            leaves[f"{prefix}{key}"] = np.asarray(value, dtype=np.float64)
    return leaves


def test_eval_of_a_run_trained_in_another_frame_gives_the_same_metrics_and_pose_errors(finished_run, tmp_path):
    """The Gaussians live in the frame of the run's estimated poses, which training fixes only up to a similarity:
    the held-out true cameras are mapped into it through the inverse of the sim(3) that aligns the estimated
    cameras onto the true ones. The fixture's run is trained in nearly the true frame (that sim(3) is nearly the
    identity), so mapping the test cameras through the sim(3) itself instead of its inverse (a wrong direction in
    `test_cameras_in_model_frame`) went unseen: here the same run moved by a 40 deg, x1.7 similarity must score
    the same PSNR, SSIM and FLIP on the held-out views, and the same pose errors, as the run as trained (measured:
    within 1e-6 dB and 1e-5 deg; the wrong direction costs 4-8 dB)."""
    as_trained = _copy_of(finished_run, tmp_path / "as_trained")
    moved = _copy_of(finished_run, tmp_path / "moved")
    _moved_by_a_similarity(moved, angle_deg=40.0, scale=1.7)
    assert not np.allclose(np.load(moved / "poses_final.npy"), np.load(as_trained / "poses_final.npy"), atol=0.1)

    expected = evaluate_run(as_trained, refine_iters=0, log=lambda message: None)
    got = evaluate_run(moved, refine_iters=0, log=lambda message: None)
    assert got["test_views"] == expected["test_views"] >= 2
    for view_got, view_expected in zip(got["images"]["per_view"], expected["images"]["per_view"]):
        assert view_got["psnr"] == pytest.approx(view_expected["psnr"], abs=1e-3)
        assert view_got["ssim"] == pytest.approx(view_expected["ssim"], abs=1e-4)
        assert view_got["flip"] == pytest.approx(view_expected["flip"], abs=1e-4)
    poses_got, poses_expected = _numbers(got["poses"]), _numbers(expected["poses"])
    assert set(poses_got) == set(poses_expected) and any("reprojection_px" in key for key in poses_got)
    for key, value in poses_expected.items():
        np.testing.assert_allclose(poses_got[key], value, rtol=1e-5, atol=1e-4, err_msg=key)


def test_eval_scores_the_held_out_views_masked_onto_white_whatever_their_background(finished_run, tmp_path):
    """GaussianObject's protocol: the renders (on white) are compared with the ground truth masked onto white, not
    with the images as they are. The synthetic scene's background is white already (but for the object's
    anti-aliased edge), so comparing with the raw images (`targets = test.images`) went unseen: here the same run
    is evaluated on a copy of its scene whose images are green outside their masks, and must score exactly as on
    the white scene, with the truth in its comparison pictures white outside the masks."""
    import cv2

    from warpbags.evaluation import held_out_views

    scene_root = json.loads((finished_run / "config.json").read_text())["scene_root"]
    green = tmp_path / "green_scene"
    shutil.copytree(scene_root, green)
    for image_path in sorted((green / "images").glob("*.png")):
        image = cv2.imread(str(image_path), cv2.IMREAD_COLOR)
        mask = cv2.imread(str(green / "masks" / image_path.name), cv2.IMREAD_GRAYSCALE)
        image[mask < 128] = (40, 160, 30)  # BGR
        assert cv2.imwrite(str(image_path), image)
    on_white = _copy_of(finished_run, tmp_path / "white")
    on_green, _ = _run_on_scene(on_white, tmp_path / "green", green)
    test = held_out_views(load_run(on_green))
    targets = test.on_background(1.0)
    assert (test.images - targets).abs().amax(dim=(1, 2, 3)).min() > 0.5  # every held-out view's background is green

    expected = evaluate_run(on_white, refine_iters=0, log=lambda message: None)
    got = evaluate_run(on_green, refine_iters=0, log=lambda message: None)
    assert len(got["images"]["per_view"]) == len(test.image_names) >= 2
    for view_got, view_expected in zip(got["images"]["per_view"], expected["images"]["per_view"]):
        for metric in ("psnr", "ssim", "flip"):
            assert view_got[metric] == pytest.approx(view_expected[metric], rel=1e-6, abs=1e-6), metric
    for file_name, target in zip(comparison_file_names(test.image_names), targets):
        picture = cv2.cvtColor(cv2.imread(str(on_green / "eval" / file_name)), cv2.COLOR_BGR2RGB)
        truth = torch.from_numpy(picture[:, :test.width]).float() / 255  # truth | render | error
        assert (truth - target).abs().max() <= 1 / 255 + 1e-6


def test_a_run_whose_config_holds_settings_of_an_earlier_version_is_read_not_continued(finished_run, tmp_path):
    """config.json keeps every field, and reverted experiments' fields (camera.restarts, depth_patch, ...) made every
    command after training refuse such a run as holding "unknown training option(s)". It is read as this version has
    those settings, not at all; only continuing it is refused, by name: it would train otherwise than it started."""
    run = tmp_path / "old"
    shutil.copytree(finished_run, run, ignore=shutil.ignore_patterns("turntable*", "eval*", "report.md"))
    info = json.loads((run / "config.json").read_text())
    info["config"]["camera"]["restarts"] = 3
    info["config"]["depth_patch"] = 0.125
    (run / "config.json").write_text(json.dumps(info))
    result = runner.invoke(app, ["export", str(run), "--out", str(tmp_path / "export"), "--no-colmap"])
    assert result.exit_code == 0, result.output
    assert runner.invoke(app, ["eval", str(run), "--refine-iters", "0"]).exit_code == 0
    assert load_run(run).config.to_dict() == load_run(finished_run).config.to_dict()
    result = runner.invoke(app, ["train", "--resume", "--out", str(run)])
    assert result.exit_code == 2 and _lines(result) == [
        f"error: {run / 'config.json'} holds camera.restarts, depth_patch, settings of an earlier warpbags that this "
        "one has no more: the run cannot be continued (eval, export, render and view still read it)"], result.output


# ------------------------------------------------------------------------------------- export and eval, more cases
def test_a_colmap_workspace_or_a_model_beside_other_files_is_not_an_earlier_export(finished_run, tmp_path):
    """An export replaces only what an earlier export wrote: sparse/0/ of *.txt or *.bin files beside its
    gaussians.ply. COLMAP's own workspace (the model, no gaussians.ply) and a model folder holding a user's other file
    are refused in one line, their files kept: replaced, the user's reconstruction would be gone."""
    workspace = tmp_path / "workspace"
    (workspace / "sparse" / "0").mkdir(parents=True)
    for name in ("cameras.bin", "images.bin", "points3D.bin"):
        (workspace / "sparse" / "0" / name).write_bytes(b"mine")
    export = tmp_path / "export"
    assert runner.invoke(app, ["export", str(finished_run), "--out", str(export)]).exit_code == 0
    (export / "sparse" / "0" / "database.db").write_bytes(b"mine")
    for out, message in [(workspace, "is not empty and not an earlier export (no gaussians.ply)"),
                         (export, "holds more than the COLMAP model sparse/0/ an export writes")]:
        before = {path: path.read_bytes() for path in out.rglob("*") if path.is_file()}
        result = runner.invoke(app, ["export", str(finished_run), "--out", str(out)])
        assert result.exit_code == 2 and len(_lines(result)) == 1, result.output
        assert message in " ".join(result.output.split())
        assert {path: path.read_bytes() for path in out.rglob("*") if path.is_file()} == before


def test_a_model_staged_by_a_killed_export_is_not_taken_into_the_next(finished_run, tmp_path):
    """The model is staged in sparse/0.partial/ and renamed to sparse/0/ once read back: one that a killed export
    left (here a binary file of a model of names with spaces) must not end up beside the next export's text model."""
    out = tmp_path / "export"
    assert runner.invoke(app, ["export", str(finished_run), "--out", str(out)]).exit_code == 0
    staging = out / "sparse" / "0.partial"
    staging.mkdir()
    (staging / "images.bin").write_bytes(b"cut")
    result = runner.invoke(app, ["export", str(finished_run), "--out", str(out)])
    assert result.exit_code == 0, result.output
    assert sorted(path.name for path in (out / "sparse").iterdir()) == ["0"]
    written = {path.name for path in (out / "sparse" / "0").iterdir()}
    assert "images.txt" in written and all(name.endswith(".txt") for name in written), written


def test_the_colmap_model_names_the_full_size_images_where_the_scene_holds_them(finished_run, tmp_path):
    """A run at --resolution 2 of a scene holding images/ and images_2/: the model names the full-size images with
    the calibration as given, which COLMAP-reading trainers downsample themselves; images_2/ only where images/ is
    missing (the test above)."""
    import cv2

    info = json.loads((finished_run / "config.json").read_text())
    scene = tmp_path / "scene"
    shutil.copytree(info["scene_root"], scene)
    (scene / "images_2").mkdir()
    for image_path in (scene / "images").glob("*.png"):
        half = cv2.resize(cv2.imread(str(image_path)), (32, 32), interpolation=cv2.INTER_AREA)
        assert cv2.imwrite(str(scene / "images_2" / image_path.name), half)
    run, _ = _run_on_scene(finished_run, tmp_path, scene, resolution=2)
    result = runner.invoke(app, ["export", str(run), "--out", str(tmp_path / "export")])
    assert result.exit_code == 0, result.output
    said = "".join(result.output.split())  # Rich wraps a long path anywhere, even inside a name
    assert said.endswith("".join(f"the model's images are in {scene / 'images'}".split())), result.output
    source = read_model(scene / "sparse" / "0")
    given = dict(zip(source.image_names, source.cameras))
    model = read_model(tmp_path / "export" / "sparse" / "0")
    for name, camera in zip(model.image_names, model.cameras):
        assert (camera.width, camera.height) == (64, 64)
        np.testing.assert_allclose(camera.K, given[name].K, atol=1e-9)


def test_the_mean_metrics_are_the_means_of_the_views(monkeypatch):
    """The table's PSNR, SSIM and FLIP are means over the held-out views (the field's protocol), not medians: three
    views of very different noise, whose mean and median differ by dBs."""
    generator = torch.Generator().manual_seed(0)
    targets = torch.rand(3, 16, 16, 3, generator=generator)
    noise = torch.tensor([0.01, 0.1, 0.3])[:, None, None, None]
    images = targets + noise * torch.randn(3, 16, 16, 3, generator=generator)
    metrics = image_metrics(images, targets, lambda image, target: None)
    psnrs = [view["psnr"] for view in metrics["per_view"]]
    assert abs(np.mean(psnrs) - np.median(psnrs)) > 1.0
    for key in ("psnr", "ssim", "flip"):
        assert metrics["mean"][key] == pytest.approx(np.mean([view[key] for view in metrics["per_view"]]), rel=1e-12)
    assert metrics["mean"]["lpips"] is None


def _turned_about_z(viewmat: torch.Tensor, degrees: float) -> torch.Tensor:
    """`viewmat` with its camera turned by `degrees` about its viewing axis."""
    angle = math.radians(degrees)
    turn = torch.eye(4, dtype=viewmat.dtype)
    turn[:2, :2] = torch.tensor([[math.cos(angle), -math.sin(angle)], [math.sin(angle), math.cos(angle)]])
    return turn @ viewmat


def test_the_pose_table_holds_medians_the_orbit_percent_and_each_stages_own_object_motion(finished_run):
    """Given the true poses, and final poses with one camera turned 5 deg and another moved: the medians are the
    per-camera errors' medians (not their means), the translation is in percent of the orbit radius (x100, not a
    fraction), and the initial stage's object motion is measured under the initial stage's own sim(3): the true poses
    move the object by nothing, where the final stage's alignment moved it by a pixel in every view."""
    run = load_run(finished_run)
    run.poses_init = run.poses_true.clone()
    final = run.poses_true.clone()
    final[0] = _turned_about_z(final[0], 5.0)
    final[1, :3, 3] += torch.tensor([0.2, -0.1, 0.05], dtype=final.dtype)
    run.poses_final = final
    report = pose_accuracy(run, log=lambda message: None)
    assert set(report) == {"procrustes", "pairwise"}
    for name, entry in report.items():
        for stage in ("initial", "final"):
            errors = entry[stage]
            assert errors["rotation_deg_median"] == pytest.approx(np.median(errors["rotation_deg"]), abs=1e-9)
            assert errors["translation_median"] == pytest.approx(np.median(errors["translation"]), abs=1e-9)
            assert errors["translation_percent_of_orbit"] == pytest.approx(
                100 * errors["translation_mean"] / ORBIT_RADIUS)
        final_errors = entry["final"]
        assert abs(final_errors["rotation_deg_median"] - final_errors["rotation_deg_mean"]) > 0.3, name
        assert final_errors["translation_mean"] > 0.01 and final_errors["reprojection_px_mean"] > 0.1, name
        assert max(entry["initial"]["reprojection_px"]) < 1e-3, (name, entry["initial"]["reprojection_px"])


def test_an_earlier_evaluations_pictures_do_not_stay(finished_run, tmp_path):
    """eval/ holds this evaluation's comparisons only: one of an earlier evaluation on another split (or of a view
    since renamed) would stand in the report beside them as a held-out view."""
    import cv2

    run = _copy_of(finished_run, tmp_path / "run")
    (run / "eval").mkdir()
    assert cv2.imwrite(str(run / "eval" / "view_of_another_split.png"), np.zeros((4, 4, 3), np.uint8))
    result = evaluate_run(run, refine_iters=0, log=lambda message: None)
    pictures = sorted(path.name for path in (run / "eval").iterdir())
    assert len(pictures) == result["test_views"] >= 2 and "view_of_another_split.png" not in pictures
    assert "view_of_another_split" not in (run / "report.md").read_text()


def test_eval_of_a_scene_normalized_otherwise_than_the_run_is_one_line(finished_run, tmp_path):
    """The held-out cameras are put in the run's normalized frame by the normalization the scene gives now: a scene
    whose cameras or points changed since training (another centre) would score the run on cameras off by as much."""
    run = _copy_of(finished_run, tmp_path / "run")
    info = json.loads((run / "config.json").read_text())
    info["normalization"]["center"] = [value + 0.5 for value in info["normalization"]["center"]]
    (run / "config.json").write_text(json.dumps(info))
    result = runner.invoke(app, ["eval", str(run), "--refine-iters", "0"])
    assert result.exit_code == 2 and len(_lines(result)) == 1, result.output
    assert "no longer matches the run's normalization: was the scene changed?" in " ".join(result.output.split())
    assert not (run / "eval.json").exists() and not (run / "eval").exists()


def test_eval_with_negative_refinement_iterations_is_one_line(finished_run, tmp_path):
    """--refine-iters -1 evaluated without refinement and reported it as done; refused before anything is read."""
    run = _copy_of(finished_run, tmp_path / "run")
    result = runner.invoke(app, ["eval", str(run), "--refine-iters", "-1"])
    assert result.exit_code == 2 and len(_lines(result)) == 1, result.output
    assert "--refine-iters must be >= 0, got -1" in result.output
    assert not (run / "eval.json").exists() and not (run / "eval").exists()


def test_the_training_curves_are_labelled_with_the_alignment_training_logged_its_errors_after(finished_run, tmp_path,
                                                                                               monkeypatch):
    """The curves plot the pose errors training logged, after the run's `pose_alignment`: an evaluation aligning
    its test cameras otherwise (`warpbags eval --pairwise`) must not relabel them."""
    import warpbags.report

    run = _copy_of(finished_run, tmp_path / "run")
    labels = []
    monkeypatch.setattr(warpbags.report, "plot_training_curves",
                        lambda records, path, alignment: labels.append(alignment))
    result = evaluate_run(run, alignment="pairwise", refine_iters=0, log=lambda message: None)
    assert result["alignment"] == "pairwise" and load_run(run).config.pose_alignment == "procrustes"
    assert labels == ["procrustes"]

"""Evaluation of a training run: novel-view image metrics and camera-pose accuracy, measured as the field does.

Image metrics (GaussianObject's protocol): held-out views (`sparse_test` split) rendered on a white background and
compared with the ground truth masked onto white (views without masks: rendered on the run's background, as training,
`warpbags render` and `warpbags view` render the Gaussians, and compared with the images as they are): PSNR, SSIM
(3DGS's, which GaussianObject scores with), FLIP (NVIDIA's LDR-FLIP through the `flip-evaluator` package: a
perceptual error in [0, 1], lower is better, no learned weights, so it works offline) and LPIPS-VGG (the `lpips`
package, on images in [0, 1] as GaussianObject's evaluation) when it and its weights are available offline. A metric
that cannot be had (LPIPS without its weights, FLIP if its package fails to import) is reported as null with the
reason, never guessed.

The held-out poses are true poses, while the Gaussians live in the frame of the optimized training poses. The
test cameras are therefore mapped through the sim(3) that aligns the optimized training cameras to the true ones
(BARF's protocol), and optionally refined photometrically with the Gaussians frozen (BARF: 100 iterations),
since a residual alignment error of a fraction of a degree already costs dBs.

Pose accuracy: rotation error (geodesic, degrees) and camera-centre error (scene units, and % of the orbit radius)
after sim(3) Procrustes (Umeyama on camera centres, BARF) and after SPARF's pairwise alignment, which does not
overfit with 4-9 cameras; both are reported and labelled.
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import torch
from skimage.metrics import peak_signal_noise_ratio

from warpbags.alignment import (align_viewmats, alignment_for, centre_floor_errors, pose_errors, procrustes_unfit,
                                procrustes_weak, reprojection_errors)
from warpbags.camera_optimizer import CameraOptimizer, CameraOptimizerSettings
from warpbags.configs.train import ALIGNMENTS, BACKGROUNDS
from warpbags.data import ORBIT_RADIUS, Scene, load_scene
from warpbags.data.splits import evaluation_views
from warpbags.devices import torch_device
from warpbags.errors import WarpbagsError, one_line
from warpbags.files import atomic_output, finite_json, writable_file, writable_folder
from warpbags.gaussians import object_points, opacity_weighted_center, render_gaussians, sh_degree_of
from warpbags.losses import load_lpips, photometric_loss
from warpbags.losses import ssim as loss_ssim
from warpbags.report import REPORT_FILES, write_image_grid, write_run_report
from warpbags.run_folder import RunFolder, TrainingRun, load_run, require_info, run_normalization
from warpbags.threads import torch_threads


@contextlib.contextmanager
def _held_back_warnings(logger_name: str) -> Iterator[list[logging.LogRecord]]:
    """Hold back what `logger_name` logs in the block: passed on when the block ends normally, dropped when it
    raises (the error says what went wrong in one line; a warning that led to it would be a second line)."""
    logger = logging.getLogger(logger_name)
    held: list[logging.LogRecord] = []

    class Holder(logging.Handler):
        def emit(self, record: logging.LogRecord) -> None:
            held.append(record)

    holder, propagate = Holder(), logger.propagate
    logger.addHandler(holder)
    logger.propagate = False
    try:
        yield held
    finally:
        logger.removeHandler(holder)
        logger.propagate = propagate
    if propagate and logger.parent is not None:  # on to where they would have gone (the logger's own handlers,
        for record in held:                       # which still took them in the block, are not given them twice)
            logger.parent.handle(record)


def held_out_views(run: TrainingRun) -> Scene:
    """The run's scene restricted to its test split, in the run's normalized frame and training resolution.

    The scene's notes on splits it lacks (`warpbags.data.splits`) are logged only when the views are returned: a
    missing test split is this function's error alone.

    Raises:
        WarpbagsError: the scene folder is gone, has no test split (`warpbags.data.splits.evaluation_views`), or no
            longer matches the run's frame.
    """
    require_info(run, "scene", "scene_root", "resolution", "normalization", "image_names")
    info, config = run.info, run.config
    stored = run_normalization(run)
    with _held_back_warnings("warpbags.data"):
        scene = load_scene(info["scene_root"], resolution=info["resolution"], name=info["scene"])
        if not np.allclose(scene.normalization.matrix(), stored.matrix(), atol=1e-5):
            raise WarpbagsError(f"{info['scene_root']} no longer matches the run's normalization: was the scene "
                                "changed?")
        test = evaluation_views(scene, info["image_names"])
    return scene.subset(test).downscaled(config.max_image_size)


def _check_outputs(run: TrainingRun, comparisons: list[str]) -> None:
    """Check, before anything is computed or written, that every output of `evaluate_run` can be written: eval/
    (and its comparison PNGs), eval.json and the report's files.

    Raises:
        WarpbagsError: one of them is of the wrong kind (eval a file, eval.json a folder) or cannot be written.
    """
    purpose = "to write the evaluation to"
    folder = writable_folder(run.path / "eval", "for the evaluation's comparison pictures")
    for name in comparisons + [path.name for path in folder.glob("*.png")]:  # written, or removed as stale
        writable_file(folder / name, purpose)
    for name in ("eval.json", *REPORT_FILES):
        writable_file(run.path / name, purpose)


def test_cameras_in_model_frame(run: TrainingRun, test: Scene, alignment: str) -> torch.Tensor:
    """[T,4,4] the held-out cameras of `test` mapped into the model's frame, through the sim(3) (`alignment`) that
    maps the run's final training cameras onto their true poses (BARF's protocol).

    Raises:
        WarpbagsError: the alignment cannot be fitted to the run's cameras.
    """
    try:
        sim3 = pose_errors(run.poses_final, run.poses_true, alignment=alignment)["sim3"]
    except ValueError as error:
        raise WarpbagsError(f"{run.path}: cannot map the test cameras into the model's frame: {error}") from None
    return align_viewmats(test.viewmats.double(), sim3.inverse()).float()


def pose_accuracy(run: TrainingRun, log=print) -> dict:
    """Initial and final pose errors of the training cameras under each alignment the cameras allow: rotation,
    centre distance, the pixels the object moves by in each image (`reprojection_errors`: the trained Gaussians'
    opaque centres, at the training resolution; runs that saved their intrinsics) and, after Procrustes, the
    rotation error the centres alone force.

    An alignment that cannot be fitted (procrustes with fewer than 3 or collinear camera centres, pairwise with
    one camera) is left out of the report, with a logged line saying why.
    """
    report = {}
    points = object_points(run.params).double()  # where the final poses put the object
    for alignment in ALIGNMENTS:
        poses_by_stage = {"initial": run.poses_init, "final": run.poses_final}
        if alignment == "procrustes" and (reason := procrustes_unfit(run.poses_true)):
            log(f"pose errors: procrustes left out: {reason}")
            continue
        weak = procrustes_weak(run.poses_true) if alignment == "procrustes" else None
        if weak:
            log(f"pose errors: {weak}; the pairwise errors do not depend on it")
        try:
            errors_by_stage = {stage: pose_errors(poses, run.poses_true, alignment=alignment)
                               for stage, poses in poses_by_stage.items()}
        except ValueError as error:
            log(f"pose errors: {alignment} left out: {error}")
            continue
        entry = {}
        object_reference = errors_by_stage["final"]["sim3"].apply(points)  # where the final alignment puts the object
        for stage, errors in errors_by_stage.items():
            entry[stage] = {
                "rotation_deg": errors["rotation_errors_deg"].tolist(),
                "translation": errors["translation_errors"].tolist(),
                "rotation_deg_mean": errors["rotation_error_deg_mean"],
                "rotation_deg_median": errors["rotation_error_deg_median"],
                "translation_mean": errors["translation_error_mean"],
                "translation_median": errors["translation_error_median"],
                "translation_percent_of_orbit": 100 * errors["translation_error_mean"] / ORBIT_RADIUS,
            }
            if run.intrinsics is not None:
                pixels = reprojection_errors(poses_by_stage[stage], run.poses_true, run.intrinsics,
                                             object_reference, errors["sim3"])
                entry[stage]["reprojection_px"] = pixels.tolist()
                entry[stage]["reprojection_px_mean"] = pixels.mean().item()
            if alignment == "procrustes":  # the normalized scene is centred on the object
                floor = centre_floor_errors(poses_by_stage[stage], run.poses_true, torch.zeros(3, dtype=torch.float64))
                entry[stage]["rotation_deg_centre_floor"] = floor.tolist()
                entry[stage]["rotation_deg_centre_floor_mean"] = floor.mean().item()
        if weak:  # eval.json and report.md say it beside the numbers it is about
            entry["weakly_fixed"] = weak
        report[alignment] = entry
    return report


def refine_poses(params, viewmats, Ks, targets, width, height, sh_degree, iters: int,
                 settings: CameraOptimizerSettings | None = None,
                 background: tuple[float, float, float] = BACKGROUNDS["white"]):
    """Photometric pose refinement of each view with the Gaussians frozen (BARF's test-time optimization), through
    the same camera optimizer as training (`settings`: its parameterization; default object-centric, preconditioned),
    by `iters` L-BFGS iterations per view (`CameraOptimizer.refine`: Adam wanders against a frozen model), the
    Gaussians rendered on `background` (RGB in [0, 1], that of the targets).

    Returns:
        [C,4,4] refined world-to-camera matrices.
    """
    frozen = {name: value.detach() for name, value in params.items()}
    settings = dataclasses.replace(settings or CameraOptimizerSettings(), fix_first_camera=False)
    cameras = CameraOptimizer(viewmats, settings, opacity_weighted_center(frozen), Ks, width, height, frozen["means"])
    backgrounds = torch.tensor(background, device=viewmats.device)[None]

    def loss_of_view(view: int):
        def loss(corrected: torch.Tensor) -> torch.Tensor:
            images, _, _ = render_gaussians(frozen, corrected[view:view + 1], Ks[view:view + 1], width, height,
                                            sh_degree=sh_degree, backgrounds=backgrounds)
            return photometric_loss(images, targets[view:view + 1])[0]
        return loss

    for view in range(len(viewmats)):  # one solve per view: each has its own curvature and line search
        cameras.refine(loss_of_view(view), iters)
    return cameras.viewmats()


class LpipsMetric:
    """LPIPS-VGG through the `lpips` package, or a reason why it is unavailable (no package, no weights offline).

    Images go in as they are, in [0, 1], as GaussianObject's render.py gives them for the numbers it publishes,
    though the package documents [-1, 1]: LPIPS values compare with GaussianObject's and BAGS's tables.
    """

    def __init__(self) -> None:
        self.model, self.unavailable = load_lpips()

    def __call__(self, image: np.ndarray, target: np.ndarray) -> float | None:
        if self.model is None:
            return None
        to_tensor = lambda a: torch.from_numpy(a).permute(2, 0, 1)[None].float()  # noqa: E731
        with torch.no_grad():
            return float(self.model(to_tensor(image), to_tensor(target)))


class FlipMetric:
    """Mean LDR-FLIP error (Andersson et al. 2020) of an image against its reference through NVIDIA's
    `flip-evaluator` package, at its default viewing condition (67 pixels per degree), inputs taken as sRGB in
    [0, 1]; or a reason why it is unavailable (the package, a regular dependency, fails to import)."""

    def __init__(self) -> None:
        try:
            import flip_evaluator  # noqa: PLC0415 - imported here so a broken install is one reason, not a crash
        except ImportError as error:
            self.flip = None
            self.unavailable = one_line(error)
        else:
            self.flip, self.unavailable = flip_evaluator, None

    def __call__(self, image: np.ndarray, target: np.ndarray) -> float | None:
        if self.flip is None:
            return None
        as_input = lambda a: np.ascontiguousarray(np.clip(a, 0, 1), dtype=np.float32)  # noqa: E731
        _, mean, _ = self.flip.evaluate(as_input(target), as_input(image), "LDR", applyMagma=False)
        return float(mean)


METRICS = ("psnr", "ssim", "flip", "lpips")


def psnr(image: np.ndarray, target: np.ndarray) -> float:
    """PSNR (dB) of an [H,W,3] image in [0, 1] against its target (scikit-image's, data range 1)."""
    return float(peak_signal_noise_ratio(target, image, data_range=1.0))


def ssim(image: np.ndarray, target: np.ndarray) -> float:
    """SSIM of an [H,W,3] image in [0, 1] against its target as GaussianObject reports it: 3DGS's `ssim`
    (utils/loss_utils.py, which GaussianObject's render.py scores with). Wang et al.'s statistics in an 11 x 11
    Gaussian window of sigma 1.5 (population statistics, C1 = 0.01^2, C2 = 0.03^2), the images zero-padded where
    the window passes the border, averaged over every pixel and channel; in float64. scikit-image's (as torchmetrics'
    and nerfstudio's) leaves the 5-pixel border out instead, and reads lower where the border is background (at 128
    px about 0.02-0.07 on maryrose). The training loss's D-SSIM is the same SSIM (`warpbags.losses.ssim`)."""
    image, target = (torch.from_numpy(np.ascontiguousarray(array, dtype=np.float64))[None] for array in (image, target))
    return float(loss_ssim(image, target))


def image_metrics(images: torch.Tensor, targets: torch.Tensor, lpips_metric: LpipsMetric,
                  flip_metric: FlipMetric | None = None) -> dict:
    """Per-view and mean PSNR, SSIM, FLIP, LPIPS of [C,H,W,3] renders against targets (both on the same
    background); a metric that is unavailable is None. `flip_metric` defaults to a new `FlipMetric`."""
    flip_metric = FlipMetric() if flip_metric is None else flip_metric
    per_view = []
    for image, target in zip(images.clamp(0, 1).double().numpy(), targets.double().numpy()):
        per_view.append({
            "psnr": psnr(image, target),
            "ssim": ssim(image, target),
            "flip": flip_metric(image, target),
            "lpips": lpips_metric(image, target),
        })
    mean = {key: (None if per_view[0][key] is None else float(np.mean([v[key] for v in per_view])))
            for key in METRICS}
    return {"mean": mean, "per_view": per_view}


def comparison_file_names(image_names: list[str]) -> list[str]:
    """One PNG name per test image: its stem, or, where two images share a stem (a/x.png and b/x.png, x.jpg and
    x.png), its position and stem for all of them, so that no comparison overwrites another."""
    stems = [Path(name).stem for name in image_names]
    if len(set(stems)) == len(stems):
        return [f"{stem}.png" for stem in stems]
    return [f"{index:03d}_{stem}.png" for index, stem in enumerate(stems)]


def _save_comparison(path: Path, target: torch.Tensor, image: torch.Tensor) -> None:
    """truth | render | 4x absolute error, side by side, as PNG."""
    write_image_grid(path, [[target, image, (image - target).abs() * 4]])


@torch_threads(1)  # Warp's host threads render; torch's OpenMP workers would fight them
def evaluate_run(path: str | Path, *, alignment: str = "procrustes", refine_iters: int = 100, device: str = "cpu",
                 log=print) -> dict:
    """Evaluate a run folder; writes eval.json, eval/<view>.png (truth | render | error) and report.md into it.

    Args:
        path: the run folder.
        alignment: how test cameras are mapped into the model's frame: "procrustes" or "pairwise".
        refine_iters: test-time pose refinement iterations per held-out view (0 = none).
        device: where the held-out views are rendered and their poses refined: "cpu" or "cuda" (the metrics are
            computed on the CPU).

    Returns:
        The eval.json content.
    """
    if alignment not in ALIGNMENTS:
        raise WarpbagsError(f"alignment must be one of {', '.join(ALIGNMENTS)}, got {alignment!r}")
    if refine_iters < 0:
        raise WarpbagsError(f"--refine-iters must be >= 0, got {refine_iters}")
    on = torch_device(device)
    run = load_run(path)
    test = held_out_views(run)
    # everything read and every output checked before the first file is written: a bad log line or an eval.json that
    # is a folder is one line, not a traceback after half the outputs
    records = RunFolder(run.path).read_log()
    _check_outputs(run, comparison_file_names(test.image_names))
    if alignment_for(run.poses_true, alignment) != alignment:  # as the trainer's pose errors do
        log(f"pairwise alignment: {procrustes_unfit(run.poses_true)}")
        alignment = "pairwise"
    test_viewmats = test_cameras_in_model_frame(run, test, alignment)
    poses = pose_accuracy(run, log)
    # The object masked onto white, as GaussianObject evaluates. Views without masks are compared as they are, their
    # background and all, which the Gaussians learned in front of the run's background: rendered on white, a black
    # run's every uncovered pixel counted as an error (a maskless synthetic scene: PSNR 6.66, 10.44 on its black).
    background = BACKGROUNDS["white"] if test.masks is not None else run.config.background_rgb
    targets = test.on_background(background)
    sh_degree = sh_degree_of(run.params)
    lpips_metric = LpipsMetric()
    if lpips_metric.unavailable:
        log(f"LPIPS unavailable ({lpips_metric.unavailable}); reported as null")
    flip_metric = FlipMetric()
    if flip_metric.unavailable:
        log(f"FLIP unavailable ({flip_metric.unavailable}); reported as null")

    params, Ks = {name: value.to(on) for name, value in run.params.items()}, test.Ks.to(on)
    backgrounds = torch.tensor(background, device=on).expand(len(test.image_names), 3).contiguous()

    def render(viewmats):
        with torch.no_grad():
            images, _, _ = render_gaussians(params, viewmats.to(on), Ks, test.width, test.height,
                                            sh_degree=sh_degree, backgrounds=backgrounds)
        return images.cpu()

    images = render(test_viewmats)
    result = {
        "run": str(run.path),
        "scene": run.info["scene"],
        "views": run.config.views,
        # False: training started from the scene's own poses, so the final pose rows measure the corrections
        "pose_noise_injected": run.config.injects_pose_noise,
        "test_views": len(test.image_names),
        "image_size": [test.width, test.height],
        "alignment": alignment,
        "lpips_unavailable": lpips_metric.unavailable,
        "flip_unavailable": flip_metric.unavailable,
        "poses": poses,
        "images": image_metrics(images, targets, lpips_metric, flip_metric),
    }
    if refine_iters > 0:
        settings = CameraOptimizerSettings.from_config(run.config.camera)
        refined = refine_poses(params, test_viewmats.to(on), Ks, targets.to(on), test.width, test.height, sh_degree,
                               refine_iters, settings=settings, background=background)
        images = render(refined)
        result["images_after_test_pose_refinement"] = {"iters": refine_iters,
                                                        **image_metrics(images, targets, lpips_metric, flip_metric)}
    out = run.path / "eval"
    out.mkdir(exist_ok=True)
    for stale in out.glob("*.png"):  # comparisons of an earlier evaluation (another split) must not stay
        stale.unlink()
    for file_name, target, image in zip(comparison_file_names(test.image_names), targets, images):
        _save_comparison(out / file_name, target, image)
    write_run_report(run.path, result, alignment_for(run.poses_true, run.config.pose_alignment), records)
    # last: a sweep takes eval.json as "evaluated", so a kill before it leaves the run to be evaluated again
    with atomic_output(run.path / "eval.json") as temporary:
        temporary.write_text(finite_json(result))
    return result


"""Training: losses, densification bookkeeping, the Trainer (loss, pose recovery, resume, NaN) and `warpbags train`."""

from __future__ import annotations

import dataclasses
import json
import math
import os
import re
import shutil
import signal
import subprocess
import sys
import types
from pathlib import Path

import numpy as np
import pytest
import torch
from typer.testing import CliRunner
from warpbags.cameras import camera_centers, mean_viewmats
from warpbags.cli.main import app
from warpbags.configs.train import TrainConfig, load_preset, parse_settings

from warpbags.data import SyntheticOptions, ensure_synthetic_scene, load_scene
from warpbags.errors import WarpbagsError
from warpbags import camera_setup, run_folder
from warpbags import trainer as trainer_module
from warpbags.losses import depth_loss, ssim
from warpbags.pose_history import read_pose_history
from warpbags.strategy import replace_rows
from warpbags.schedule import Schedule, exponential_lr
from warpbags.trainer import Trainer, saved_run_config, start_or_resume, training_scene

TINY = SyntheticOptions(views=16, width=96, height=96)


@pytest.fixture(scope="module")
def scene_dir(tmp_path_factory):
    return ensure_synthetic_scene(TINY, cache_dir=tmp_path_factory.mktemp("cache"))


def tiny_config(**overrides) -> TrainConfig:
    """The quick preset, small; without the search over turns of the worst-fit camera unless `camera` asks for it
    (it retrains a whole round per turn; its own test is below)."""
    base = dict(iters=40, rounds=1, pose_opt_start=10, pose_round_window=(0.0, 1.0), depth_until=10,
                checkpoint_every=10, init_points=800, hull_resolution=32, render_threads=1)
    base.update(overrides)
    base["camera"] = {"hypotheses_round": 0, **overrides.get("camera", {})}
    return load_preset("quick", **base)


def make_trainer(scene_dir, out, **overrides) -> Trainer:
    config = tiny_config(**overrides)
    scene = training_scene(load_scene(scene_dir, name="tiny"), config)
    return Trainer(scene, config, out, log=lambda message: None)


# ------------------------------------------------------------------------------------------------ losses
def test_ssim_identical_is_one_and_differentiable():
    images = torch.rand(2, 20, 24, 3, dtype=torch.float64, requires_grad=True)
    assert ssim(images, images.detach()).item() == pytest.approx(1.0, abs=1e-9)
    targets = torch.rand(2, 20, 24, 3, dtype=torch.float64)
    assert ssim(images, targets).item() < 0.5
    small = targets[:1, :12, :12]
    torch.autograd.gradcheck(lambda x: ssim(x, small), (images[:1, :12, :12].detach().requires_grad_(),))


@pytest.mark.parametrize("mode", ["mad", "pearson"])
def test_depth_loss_is_scale_and_shift_invariant_in_disparity(mode):
    depth = 1.0 + torch.rand(1, 16, 16)
    alphas = torch.ones(1, 16, 16)
    target = 1.0 / (3.0 / depth + 0.5)  # disparity scaled by 3 and shifted by 0.5
    assert depth_loss(depth, alphas, target, None, mode=mode).item() == pytest.approx(0.0, abs=1e-5)
    assert depth_loss(depth, alphas, 1.0 + torch.rand(1, 16, 16), None, mode=mode).item() > 0.1
    assert depth_loss(depth, torch.zeros(1, 16, 16), target, None, mode=mode) is None


def test_replace_rows_carries_adam_state():
    params = {"a": torch.nn.Parameter(torch.arange(4.0)[:, None])}
    optimizer = torch.optim.Adam([{"params": [params["a"]], "name": "a"}], lr=0.1)
    params["a"].sum().backward()
    optimizer.step()
    moments = optimizer.state[params["a"]]["exp_avg"].clone()
    replace_rows(params, optimizer, torch.tensor([True, False, True, True]), {"a": torch.full((2, 1), 9.0)})
    state = optimizer.state[params["a"]]
    assert params["a"].shape == (5, 1) and optimizer.param_groups[0]["params"][0] is params["a"]
    assert torch.equal(state["exp_avg"][:3], moments[[0, 2, 3]]) and torch.all(state["exp_avg"][3:] == 0)


def test_floater_removal_drops_an_isolated_gaussian():
    from warpbags.configs.train import DensifyConfig
    from warpbags.strategy import DensifyStrategy

    g = torch.Generator().manual_seed(0)
    means = torch.randn(400, 3, generator=g) * 0.2
    means[7] = torch.tensor([5.0, 5.0, 5.0])  # far from everything
    params = {"means": torch.nn.Parameter(means), "opacities": torch.nn.Parameter(torch.zeros(400))}
    optimizer = torch.optim.Adam([{"params": [p], "name": n} for n, p in params.items()])
    strategy = DensifyStrategy(DensifyConfig(floater_every=10, opacity_reset_every=0), scene_extent=1.0)
    report = strategy.step(10, params, optimizer, g)
    assert report["floaters"] >= 1 and len(params["means"]) == 400 - report["floaters"]
    assert not torch.any((params["means"] == torch.tensor([5.0, 5.0, 5.0])).all(1))
    assert report["floaters"] <= 4  # a Gaussian cloud is not eroded


@pytest.mark.parametrize("background", ["white", "black"])
def test_the_densification_knows_the_background(scene_dir, tmp_path, background):
    """On a white background 3DGS and GaussianObject reset opacities and remove floaters once more at `start`."""
    strategy = make_trainer(scene_dir, tmp_path, background=background).model.strategy
    assert strategy.white_background == (background == "white")


# ------------------------------------------------------------------------------------------------ trainer
def test_short_run_lowers_loss_and_writes_files(scene_dir, tmp_path):
    trainer = make_trainer(scene_dir, tmp_path / "run")
    trainer.write_run_files()
    trainer.train()
    log = [json.loads(line) for line in (tmp_path / "run" / "log.jsonl").read_text().splitlines()]
    assert len(log) == 40
    assert np.mean([r["loss"] for r in log[-5:]]) < 0.7 * np.mean([r["loss"] for r in log[:5]])
    for name in ("config.json", "poses_true.npy", "poses_init.npy", "gaussians.ply", "poses_final.npy"):
        assert (tmp_path / "run" / name).is_file(), name
    header = (tmp_path / "run" / "gaussians.ply").read_bytes().split(b"end_header")[0].decode()
    assert "property float f_dc_0" in header and "property float rot_3" in header and "property float opacity" in header


@pytest.mark.parametrize("fix_first_camera", [True, False])
def test_pose_optimizer_is_created_once_and_keeps_state(scene_dir, tmp_path, fix_first_camera):
    trainer = make_trainer(scene_dir, tmp_path, pose_opt_start=2, camera={"fix_first_camera": fix_first_camera})
    cameras = trainer.cameras
    optimizer, rotations = cameras.optimizer, cameras.rotations
    trainer.train(stop_at=4)
    assert trainer.cameras is cameras and cameras.optimizer is optimizer and cameras.rotations is rotations
    steps = int(optimizer.state[rotations]["step"])
    assert steps == 2  # iterations 2 and 3
    trainer.train(stop_at=6)
    assert cameras.optimizer is optimizer and int(optimizer.state[rotations]["step"]) == steps + 2
    params = cameras.params()
    moved = params.abs().amax(dim=1) > 0
    assert moved.tolist() == [not fix_first_camera] + [True] * (len(params) - 1)  # the gauge camera stays put
    rates = {group["name"]: group["lr"] for group in optimizer.param_groups}
    assert rates["translation"] == pytest.approx(trainer.config.lr.pose_translation_scale * rates["rotation"])


def test_a_gauge_camera_stays_at_its_given_pose_from_the_start(scene_dir, tmp_path):
    """`--fix-first-camera` holds camera 0 at its given pose: the mask-centroid start turned it with the others, and
    the gauge then held it there, an error nothing could correct."""
    trainer = make_trainer(scene_dir, tmp_path, rot_noise_deg=10.0, trans_noise=0.2, camera={"fix_first_camera": True})
    given = trainer.scene.viewmats[0]  # the gauge is given exactly (`camera_setup.given_viewmats`)
    assert torch.allclose(trainer.current_viewmats()[0], given, atol=1e-6)
    trainer.train(stop_at=20)
    assert torch.allclose(trainer.current_viewmats()[0], given, atol=1e-6)
    assert not torch.allclose(trainer.current_viewmats()[1:], trainer.scene.viewmats[1:], atol=1e-3)


def test_one_view_per_step_moves_only_the_rendered_camera(scene_dir, tmp_path):
    trainer = make_trainer(scene_dir, tmp_path, pose_opt_start=0, views_per_step=1, rot_noise_deg=5.0)
    everyone = set()
    for step in range(1, 5):
        before = trainer.current_viewmats()
        trainer.train(stop_at=step)
        moved = ((trainer.current_viewmats() - before).abs().amax(dim=(1, 2)) > 0).nonzero().flatten().tolist()
        assert len(moved) == 1, moved  # Adam's momentum must not move the cameras that were not rendered
        everyone.update(moved)
    assert len(everyone) > 1  # the rendered camera changes from step to step


def test_rounds_restart_gaussians_and_keep_poses(scene_dir, tmp_path):
    trainer = make_trainer(scene_dir, tmp_path, iters=20, rounds=2, pose_opt_start=0, rot_noise_deg=5.0)
    trainer.train(stop_at=10)
    means_round_one = trainer.params["means"]
    cameras = trainer.cameras
    before = trainer.current_viewmats()
    with torch.no_grad():  # corrections well beyond one step, so that losing them could not pass for a step
        cameras.rotations.add_(10 * trainer.config.lr.pose)
    poses_round_one = trainer.current_viewmats()
    added = (poses_round_one - before).abs().max().item()
    trainer.train(stop_at=11)
    assert trainer.params["means"] is not means_round_one  # fresh Gaussians from the re-carved hull
    assert trainer.cameras is cameras
    # The corrections were folded into the base poses: the latents restart at zero and took one Adam step (at most
    # the learning rate per coordinate), and the poses went on from where round one ended.
    latent = torch.cat([cameras.rotations, cameras.translations], 1).detach()
    assert 0 < latent.abs().max().item() <= 1.001 * trainer.config.lr.pose
    assert torch.allclose(cameras.base_viewmats, poses_round_one, atol=1e-6)
    assert (trainer.current_viewmats() - poses_round_one).abs().max().item() < added / 3


def test_round_anchor_holds_later_rounds_near_their_start(scene_dir, tmp_path):
    """From the second round on, camera.round_anchor pulls the corrections back towards the round's start: a strong
    anchor leaves the cameras much closer to where the round began than no anchor does."""
    moved = {}
    for anchor in (0.0, 1e4):
        trainer = make_trainer(scene_dir, tmp_path / str(anchor), iters=40, rounds=2, pose_opt_start=0,
                               rot_noise_deg=5.0, camera={"round_anchor": anchor})
        trainer.train(stop_at=20)
        start = trainer.current_viewmats()
        trainer.train(stop_at=40)
        moved[anchor] = (trainer.current_viewmats() - start).abs().max().item()
    assert moved[0.0] > 0
    assert moved[1e4] < 0.2 * moved[0.0]


def test_a_scene_without_depth_maps_is_said_unless_the_depth_term_is_off(scene_dir, tmp_path):
    for overrides, said in (({}, True), ({"lambda_depth": 0.0}, False), ({"depth_until": 0}, False)):
        notes = []
        config = tiny_config(**overrides)
        scene = dataclasses.replace(training_scene(load_scene(scene_dir, name="tiny"), config), depths=None)
        Trainer(scene, config, tmp_path / str(len(overrides)) / str(said), log=notes.append)
        assert any("no depth maps in this scene: depth term skipped" in note for note in notes) == said, notes


def test_the_repair_stage_anchors_at_the_coarse_stages_final_poses(scene_dir, tmp_path):
    """Without an average (`camera.average_share` 0) the coarse stage's end still folds the corrections into the
    base poses: with one round the repair stage's anchor pulled towards the round's start, the noisy given poses."""
    trainer = make_trainer(scene_dir, tmp_path, iters=20, pose_opt_start=0, rot_noise_deg=5.0,
                           camera={"average_share": 0.0, "round_anchor": 1.0})
    given = trainer.current_viewmats()
    trainer.train(stop_at=20)
    cameras = trainer.cameras
    assert (cameras.base_viewmats - given).abs().max().item() > 1e-3  # the poses moved, and the base with them
    assert cameras.params().abs().max().item() == 0.0


def test_the_chamfer_computed_beside_the_render_is_the_steps_own(scene_dir, tmp_path):
    # GaussianModel.loss computes the silhouette chamfer on a side thread while it renders: the term must be the
    # chamfer of the step's poses and Gaussians, with its gradient in the poses.
    trainer = make_trainer(scene_dir, tmp_path / "run", lambda_chamfer=1.0)
    model, views = trainer.model, torch.tensor([1])
    settings = trainer.schedule.at(trainer.config.pose_opt_start)
    assert settings.silhouette and settings.pose_active
    viewmats = trainer.cameras(views)
    loss, terms, _ = model.loss(views, viewmats, settings)
    data = model.training_views
    inline = data.silhouettes.chamfer_loss(model.params["means"], torch.sigmoid(model.params["opacities"]), viewmats,
                                           data.Ks[views], views)
    assert terms["chamfer"] == inline.item() > 0
    loss.backward()
    with_chamfer = trainer.cameras.rotations.grad.clone()
    trainer.cameras.zero_grad()
    model.config = dataclasses.replace(model.config, lambda_chamfer=0.0)
    model.loss(views, trainer.cameras(views), settings)[0].backward()
    assert not torch.equal(trainer.cameras.rotations.grad, with_chamfer)


def test_the_training_loss_is_the_weighted_sum_of_its_terms(scene_dir, tmp_path):
    """While the depth term is on, loss = (1 - lambda_depth) photometric + lambda_mask mask + lambda_chamfer chamfer
    + lambda_mask_distance mask distance + lambda_depth depth (`TrainConfig`: the photometric weight is 1 -
    lambda_depth), photometric =
    (1 - lambda_dssim) L1 + lambda_dssim (1 - SSIM). Nothing checked the sum: dropping `- lambda_depth *
    photometric` (reviewer's mutant MF) passed every test. Each weight is set to a value of its own; with the depth
    term off the photometric weight is 1."""
    weights = dict(lambda_dssim=0.3, lambda_mask=0.07, lambda_chamfer=0.6, lambda_depth=0.4, lambda_mask_distance=0.25)
    trainer = make_trainer(scene_dir, tmp_path, **weights, silhouette_until=20, camera={"coherence_iters": 0})
    views, viewmats = torch.arange(trainer.num_cameras), trainer.current_viewmats()
    # the silhouette terms (chamfer, mask distance) for a round's first `silhouette_until` iterations; the mask's BCE
    # throughout
    depth_until = trainer.config.depth_until
    for iteration, depth, silhouette in ((0, True, True), (depth_until, False, True), (20, False, False)):
        settings = trainer.schedule.at(iteration)
        assert settings.depth is depth and settings.silhouette is silhouette
        loss, terms, _ = trainer.model.loss(views, viewmats, settings)
        shapes = ["chamfer", "mask_distance"] if silhouette else []
        assert set(terms) == {"l1", "ssim", "mask", *shapes, *(["depth"] if depth else [])}, terms
        assert min(terms["l1"], 1 - terms["ssim"], terms["mask"], *(terms[name] for name in shapes),
                   terms.get("depth", 1)) > 1e-3
        photometric = (1 - weights["lambda_dssim"]) * terms["l1"] + weights["lambda_dssim"] * (1 - terms["ssim"])
        silhouettes = weights["lambda_mask"] * terms["mask"] + (
            weights["lambda_chamfer"] * terms["chamfer"] + weights["lambda_mask_distance"] * terms["mask_distance"]
            if silhouette else 0.0)
        expected = silhouettes + ((1 - weights["lambda_depth"]) * photometric + weights["lambda_depth"] * terms["depth"]
                                  if depth else photometric)
        assert loss.item() == pytest.approx(expected, rel=1e-5, abs=1e-7), (iteration, terms)


@pytest.mark.parametrize("init, note", [("sfm", "SfM points: 500 of "), ("random", "random points (500)"),
                                        ("hull", "visual hull: ")])
def test_initializations(scene_dir, tmp_path, init, note):
    """Each initialization is the one asked for, not its fallback to random points (whose notes also name it)."""
    notes = []
    config = tiny_config(init=init, init_points=500)
    scene = training_scene(load_scene(scene_dir, name="tiny"), config)
    trainer = Trainer(scene, config, tmp_path, log=notes.append)
    assert any(line.startswith(f"initialization: {note}") for line in notes), notes
    if init == "sfm":  # the Gaussians sit on the scene's SfM points
        distances = torch.cdist(trainer.params["means"].detach().double(), scene.points.double()).min(dim=1).values
        assert distances.max() < 1e-5


def test_two_cameras_say_that_the_logged_pose_error_is_pairwise(scene_dir, tmp_path):
    notes = []
    config = tiny_config(views=2, rot_noise_deg=5.0)
    trainer = Trainer(training_scene(load_scene(scene_dir, name="tiny"), config), config, tmp_path, log=notes.append)
    assert sum("pose error uses pairwise alignment" in line for line in notes) == 1, notes
    assert trainer.pose_error()["rot_err_deg"] > 0.5  # pairwise fits two cameras; procrustes would raise
    notes.clear()
    Trainer(training_scene(load_scene(scene_dir, name="tiny"), tiny_config()), tiny_config(), tmp_path / "four",
            log=notes.append)
    assert not any("pairwise" in line for line in notes), notes


def test_no_pose_opt_keeps_poses_and_trains_one_round(scene_dir, tmp_path):
    trainer = make_trainer(scene_dir, tmp_path, pose_opt=False, iters=12, rounds=3, rot_noise_deg=5.0)
    trainer.train()
    assert torch.all(trainer.cameras.params() == 0)
    torch.testing.assert_close(trainer.current_viewmats(), trainer.viewmats_init, rtol=0, atol=0)
    assert trainer.schedule.rounds == 1  # one round: no re-initialization throws the trained Gaussians away


@pytest.mark.parametrize("rounds", [1, 2])
def test_resume_equals_uninterrupted(scene_dir, tmp_path, rounds):
    overrides = dict(iters=24, rounds=rounds, checkpoint_every=8, pose_opt_start=4, rot_noise_deg=3.0,
                     densify={"start": 6, "stop": 20, "every": 6, "grad_threshold": 1e-5, "max_gaussians": 1200})
    full = make_trainer(scene_dir, tmp_path / "full", **overrides)
    full.train()
    interrupted = make_trainer(scene_dir, tmp_path / "part", **overrides)
    interrupted.train(stop_at=16)
    resumed = make_trainer(scene_dir, tmp_path / "part", **overrides)
    assert resumed.resume() and resumed.iteration == 16
    resumed.train()
    assert len(full.params["means"]) == len(resumed.params["means"])
    for name in full.params:
        torch.testing.assert_close(resumed.params[name], full.params[name], rtol=0, atol=0)
    torch.testing.assert_close(resumed.cameras.params(), full.cameras.params(), rtol=0, atol=0)
    # the final poses are the average of the last round's estimates, half of which came before the checkpoint
    torch.testing.assert_close(resumed.current_viewmats(), full.current_viewmats(), rtol=0, atol=1e-6)
    log = (tmp_path / "part" / "log.jsonl").read_text().splitlines()
    assert [json.loads(line)["iter"] for line in log] == list(range(1, 25))
    # The pose history (every 10 iterations) follows the resumed trajectory, and records where it was resumed.
    full_history, resumed_history = read_pose_history(tmp_path / "full"), read_pose_history(tmp_path / "part")
    assert full_history.iterations.tolist() == [10, 20] and resumed_history.iterations.tolist() == [10, 16, 20]
    np.testing.assert_allclose(resumed_history.viewmats[[0, 2]], full_history.viewmats, rtol=0, atol=1e-6)


@pytest.mark.parametrize("views, continued", [(4, False), (6, True)])
def test_the_coherence_solve_continues_the_masks_beyond_the_frame_from_six_views_on(scene_dir, tmp_path, views,
                                                                                     continued, monkeypatch):
    config = tiny_config(views=views, camera={"coherence_iters": 2})
    lines, margins = [], []
    solve = trainer_module.coherent_start

    def recording_solve(cameras, targets, *args):  # what the solve is given, not only what the log says
        margins.append(targets.margin)
        return solve(cameras, targets, *args)

    monkeypatch.setattr(trainer_module, "coherent_start", recording_solve)
    Trainer(training_scene(load_scene(scene_dir, name="tiny"), config), config, tmp_path, log=lines.append)
    solve = [line for line in lines if "silhouette coherence of the starting poses" in line]
    assert len(solve) == 1 and ("masks continued beyond the image border" in solve[0]) == continued
    assert len(margins) == 1 and (margins[0] > 0) == continued


def test_feature_matches_are_found_for_a_run_that_uses_them_at_the_images_resolution(scene_dir):
    """Found on the views as read (96 px here) and scaled with them to the training size; a run without the
    epipolar term does not look for them."""
    scene = load_scene(scene_dir, name="tiny")
    assert training_scene(scene, tiny_config(views=6)).matches is None
    wanted = dict(views=6, lambda_epipolar=0.01, matches_min_inliers=8)
    half, full = (training_scene(scene, tiny_config(**wanted, max_image_size=size)) for size in (48, 96))
    assert len(full.matches) > 0 and full.matches.size == (96, 96) and half.matches.size == (48, 48)
    assert torch.equal(half.matches.pixels_a * 2, full.matches.pixels_a)
    assert training_scene(scene, tiny_config(**wanted, pose_opt=False)).matches is None


def test_the_epipolar_term_joins_the_loss_while_the_poses_move_and_the_solve_uses_it(scene_dir, tmp_path,
                                                                                       monkeypatch):
    solves = []
    original = camera_setup.epipolar_loss
    monkeypatch.setattr(camera_setup, "epipolar_loss", lambda *args: solves.append(1) or original(*args))
    trainer = make_trainer(scene_dir, tmp_path, iters=6, pose_opt_start=3, views=6, lambda_epipolar=0.01,
                           matches_min_inliers=8, camera={"coherence_iters": 2, "coherence_epipolar": 1e-3})
    assert solves  # the coherence solve's loss has the term
    records = [trainer.train_step() for _ in range(6)]
    assert [("epipolar" in record) for record in records] == [False, False, False, True, True, True]
    assert all(record["epipolar"] > 0 for record in records[3:])


def test_the_coherence_solve_adds_the_epipolar_residual_with_its_weight_to_its_loss(scene_dir, monkeypatch):
    """`camera.coherence_epipolar` weighs the matches' epipolar residual in the loss the coherence solve minimizes;
    the test above only sees `epipolar_loss` called, so the term subtracted or weighted 0 passed. The solve's loss,
    at poses a few degrees off the truth (where the residual is large), is the coherence loss plus weight times the
    residual: for weight 0 the coherence loss alone, for 1e-3 and 0.5 the weighted residual added."""
    from warpbags.camera_optimizer import CameraOptimizer, CameraOptimizerSettings
    from warpbags.correspondences import epipolar_loss
    from warpbags.data.noise import perturb_viewmats
    from warpbags.silhouette import SilhouetteTargets

    scene = training_scene(load_scene(scene_dir, name="tiny"),
                           tiny_config(views=6, lambda_epipolar=0.01, matches_min_inliers=8))
    truth, Ks, center = scene.viewmats.double(), scene.Ks.double(), torch.zeros(3, dtype=torch.float64)
    targets = SilhouetteTargets(scene.masks)
    radius = targets.object_radius(truth, Ks, center)  # the solve's, from the poses it starts at
    objectives, refine = [], CameraOptimizer.refine
    monkeypatch.setattr(CameraOptimizer, "refine",
                        lambda cameras, loss_of, iterations: objectives.append(loss_of) or refine(cameras, loss_of, 0))
    weights = (0.0, 1e-3, 0.5)
    for weight in weights:
        cameras = CameraOptimizer(truth, CameraOptimizerSettings(precondition=False), center)
        camera_setup.coherent_start(cameras, targets, Ks, center, 0, scene.matches, weight)
    assert len(objectives) == len(weights)
    off = perturb_viewmats(truth, 3.0, 0.0, seed=2)
    coherence = targets.coherence_loss(off, Ks, center, radius)
    residual = epipolar_loss(off, Ks, scene.matches)
    # measured 3.85 and 1.25e-2: weighted by 1e-3 the residual is a third of the coherence loss, by 0.5 most of it
    assert residual > 1.0 and coherence > 1e-3, (residual, coherence)
    for weight, loss_of in zip(weights, objectives):
        with torch.no_grad():
            torch.testing.assert_close(loss_of(off), coherence + weight * residual, rtol=1e-9, atol=0)


def test_a_resumed_run_does_not_solve_its_starting_poses_again(scene_dir, tmp_path):
    """The checkpoint holds the solved starting poses: resuming neither repeats the silhouette-coherence solve nor
    changes the poses it restores."""
    config = tiny_config(iters=8, checkpoint_every=4)
    scene = training_scene(load_scene(scene_dir, name="tiny"), config)
    lines = []
    first = start_or_resume(scene, config, tmp_path, log=lines.append)
    assert sum("silhouette coherence of the starting poses" in line for line in lines) == 1
    first.train(stop_at=4)
    lines.clear()
    resumed = start_or_resume(scene, config, tmp_path, resume=True, log=lines.append)
    assert resumed.iteration == 4 and not any("silhouette coherence" in line for line in lines), lines
    torch.testing.assert_close(resumed.viewmats_start, first.viewmats_start, rtol=0, atol=0)
    torch.testing.assert_close(resumed.current_viewmats(), first.current_viewmats(), rtol=0, atol=0)


def test_resuming_with_other_views_or_another_image_size_is_refused(scene_dir, tmp_path):
    """The checkpoint's poses and Gaussians belong to the run's training views at its image size: the run's scene
    folder with another split or at another size is refused, naming the run folder and what differs."""
    config = tiny_config(iters=4, checkpoint_every=2, max_image_size=32)
    scene = load_scene(scene_dir, name="tiny")
    start_or_resume(training_scene(scene, config), config, tmp_path, log=lambda message: None).train(stop_at=2)
    for other, difference in [(config.replaced(views=6), "the scene's views .* are not the run's"),
                              (config.replaced(max_image_size=48), "the images are 48x48 px, the run's 32x32")]:
        with pytest.raises(WarpbagsError, match=f"^--resume: {re.escape(str(tmp_path))} holds a run of other "
                                                f"training views or image size than the scene's "
                                                f"\\(.*{difference}.*\\); give the scene as the run opened it"):
            start_or_resume(training_scene(scene, other), config, tmp_path, resume=True, log=lambda message: None)
    assert start_or_resume(training_scene(scene, config), config, tmp_path, resume=True,
                           log=lambda message: None).iteration == 2


def test_cli_resume_of_a_folder_named_as_a_preset_is_refused_at_the_presets_resolution(scene_dir, tmp_path,
                                                                                        monkeypatch):
    """A run of a scene folder named kitchen (a preset's name) in the data root: `--resume` without the scene
    reopens it as the preset, which reads it at the preset's 1/4 resolution. The images are then of another size
    than the run's, and the resume is refused in one line instead of going on with them."""
    data = tmp_path / "data"
    shutil.copytree(scene_dir, data / "kitchen")
    monkeypatch.setenv("WARPBAGS_DATA", str(data))
    out = tmp_path / "run"
    started = runner.invoke(app, ["train", str(data / "kitchen"), "--iters", "4", "--max-image-size", "32",
                                  "--set", "init_points=300", "--set", "checkpoint_every=2", "--out", str(out)])
    assert started.exit_code == 0, started.output
    result = runner.invoke(app, ["train", "--resume", "--out", str(out)])
    lines = [line for line in result.output.splitlines() if line.strip()]
    message = " ".join(result.output.split())
    assert result.exit_code == 2 and len(lines) == 1, result.output
    assert f"{out} holds a run of other training views" in message and "the images are 24x24 px, the run's 32x32" \
        in message, result.output


def test_cli_resume_of_a_users_folder_named_as_a_preset_reopens_that_folder(scene_dir, tmp_path):
    """A run of the user's own folder `caps/maryrose`: the hint after Ctrl-C (`--resume --out RUN`, no scene)
    reopened the packaged maryrose preset and refused ("a run of the scene in caps/maryrose, not of ...assets")."""
    folder = tmp_path / "caps" / "maryrose"
    shutil.copytree(scene_dir, folder)
    out = tmp_path / "run"
    started = runner.invoke(app, ["train", str(folder), "--iters", "4", "--max-image-size", "32",
                                  "--set", "init_points=300", "--set", "checkpoint_every=2", "--out", str(out)])
    assert started.exit_code == 0, started.output
    result = runner.invoke(app, ["train", "--resume", "--out", str(out)])
    assert result.exit_code == 0, result.output


def test_a_checkpoint_at_a_rounds_start_resumes_at_the_last_rounds_resolution(scene_dir, tmp_path):
    """With a pyramid over the rounds, the Gaussians saved at a round's start were trained at the round before's
    level: a resumed trainer holds them with those training views until the next step starts the round (which is
    what the search over turns renders them with), as the uninterrupted trainer does. Three rounds over three
    levels: a new trainer starts at the first round's quarter resolution, the checkpoint at the third round's
    start holds Gaussians of the second round's half resolution."""
    overrides = dict(iters=9, rounds=3, pyramid_levels=3, checkpoint_every=100)
    interrupted = make_trainer(scene_dir, tmp_path, **overrides)
    interrupted.write_run_files()
    interrupted.train(stop_at=6)
    resumed = make_trainer(scene_dir, tmp_path, **overrides)
    assert resumed.model.training_views.targets.shape[2] == interrupted.full_scene.width // 4  # before resuming
    assert resumed.resume() and resumed.iteration == 6
    width = interrupted.model.training_views.targets.shape[2]
    assert resumed.model.training_views.targets.shape[2] == width == interrupted.full_scene.width // 2


def test_nan_is_caught_and_last_checkpoint_kept(scene_dir, tmp_path):
    trainer = make_trainer(scene_dir, tmp_path, iters=30, checkpoint_every=5)
    trainer.train(stop_at=10)
    good = trainer.latest_checkpoint()
    with torch.no_grad():
        trainer.params["means"][0, 0] = float("nan")
    with pytest.raises(WarpbagsError, match="diverged at iteration 10.*checkpoint_000010"):
        trainer.train()
    assert trainer.latest_checkpoint() == good
    assert torch.load(good, weights_only=False)["iteration"] == 10


def test_a_step_that_diverges_on_a_checkpoint_iteration_is_not_checkpointed(scene_dir, tmp_path):
    """The finiteness check before a step cannot see what the step itself does: a step that leaves NaN on an
    iteration that checkpoints is caught at the checkpoint, which is not written."""
    trainer = make_trainer(scene_dir, tmp_path, iters=30, checkpoint_every=5)
    trainer.train(stop_at=5)
    step = trainer.model.optimizer.step

    def diverging_step(*args, **kwargs):
        result = step(*args, **kwargs)
        if trainer.iteration == 9:  # the step that makes iteration 10, a checkpoint iteration
            with torch.no_grad():
                trainer.params["means"][0, 0] = float("nan")
        return result

    trainer.model.optimizer.step = diverging_step
    with pytest.raises(WarpbagsError, match="diverged at iteration 10: parameter means .*checkpoint_000005"):
        trainer.train()
    assert trainer.latest_checkpoint().name == "checkpoint_000005.pt"


def test_a_last_step_that_leaves_the_cameras_non_finite_is_reported_not_averaged(scene_dir, tmp_path):
    """The coarse stage's last step is followed by the average of the estimates (`camera.average_share`), which
    would turn NaN cameras into an SVD failure or NaN base poses with zero corrections: it is Diverged instead."""
    trainer = make_trainer(scene_dir, tmp_path, iters=12, checkpoint_every=5, pose_opt_start=0,
                           camera={"average_share": 1.0})
    trainer.train(stop_at=10)
    step = trainer.cameras.step

    def diverging_step(*args, **kwargs):
        step(*args, **kwargs)
        if trainer.iteration == 11:  # the last step
            with torch.no_grad():
                trainer.cameras.rotations[0, 0] = float("nan")

    trainer.cameras.step = diverging_step
    with pytest.raises(WarpbagsError, match="diverged at iteration 12: parameter camera parameters has NaN.*checkpoint_000010"):
        trainer.train()


def test_poses_thrown_out_of_any_alignment_are_a_divergence_and_a_late_pose_start_is_said(scene_dir, tmp_path):
    """`--set lr.pose=1000` threw the cameras to ~1e30 and the step's logged pose error raised umeyama's ValueError
    as a traceback; a pose start after the run's last iteration (the paper preset cut short) left the poses frozen
    without a word."""
    with pytest.raises(WarpbagsError, match="diverged at iteration [0-9]+: the poses cannot be aligned"):
        make_trainer(scene_dir, tmp_path / "thrown", iters=12, pose_opt_start=0, rot_noise_deg=3.0,
                     lr={"pose": 1e6, "pose_warmup": 0}).train()
    notes = []
    config = tiny_config(iters=8, pose_opt_start=10)
    Trainer(training_scene(load_scene(scene_dir, name="tiny"), config), config, tmp_path / "late", log=notes.append)
    assert any("pose optimization starts at iteration 10, after the run's 8" in note for note in notes), notes
    # a pose window that rounds to no iteration of its round: said too (rounds of 10 iterations, window 31-34%)
    notes = []
    config = tiny_config(iters=20, rounds=2, pose_opt_start=0, pose_round_windows=((0.0, 1.0), (0.31, 0.34)))
    Trainer(training_scene(load_scene(scene_dir, name="tiny"), config), config, tmp_path / "narrow", log=notes.append)
    assert any("pose window of round(s) 1 (0-based) holds no iteration" in note for note in notes), notes
    assert not any(Schedule(config).poses_move(i) for i in range(10, 20))
    assert Schedule(tiny_config(iters=20, rounds=2, pose_opt_start=0)).rounds_without_pose_window() == []


def test_a_pose_start_after_the_coarse_stage_says_the_poses_move_in_the_repair_stage_only(scene_dir, tmp_path):
    """With a repair stage, a `pose_opt_start` past the coarse iterations but before the run's end was said to leave
    the poses "where the start procedures put them" (compared with `iters`, not `total_iters`), though they move
    through the rest of the repair stage; at or past the run's last iteration they do stay."""
    scene = load_scene(scene_dir, name="tiny")
    for pose_opt_start, moves in ((10, True), (13, False), (20, False)):
        notes = []
        config = tiny_config(iters=8, pose_opt_start=pose_opt_start, repair={"iters": 5},
                             camera={"coherence_iters": 0})
        assert config.total_iters == 13
        Trainer(training_scene(scene, config), config, tmp_path / str(pose_opt_start), log=notes.append)
        said = [note for note in notes if note.startswith("pose optimization starts at")]
        assert len(said) == 1, notes
        if moves:
            assert (f"pose optimization starts at iteration {pose_opt_start}, after the coarse stage's 8: the poses "
                    "move in the repair stage only") in said[0]
            assert any(Schedule(config).poses_move(i) for i in range(8, 13))
        else:
            assert (f"pose optimization starts at iteration {pose_opt_start}, after the run's 13: the poses stay "
                    "where the start procedures put them") in said[0]
            assert not any(Schedule(config).poses_move(i) for i in range(13))


def test_a_log_record_describes_the_step_it_logs(scene_dir, tmp_path):
    """Record "iter" n is the n-th step (index n - 1): its pose flag and SH degree are that step's schedule's."""
    trainer = make_trainer(scene_dir, tmp_path, iters=6, pose_opt_start=3, sh_degree=1, sh_degree_every=2)
    records = [trainer.train_step() for _ in range(6)]
    assert [record["iter"] for record in records] == [1, 2, 3, 4, 5, 6]
    assert [record["pose_opt"] for record in records] == [False, False, False, True, True, True]
    assert [record["sh_degree"] for record in records] == [0, 0, 1, 1, 1, 1]


def test_ctrl_c_stops_one_call_of_train_not_the_next(scene_dir, tmp_path):
    """Ctrl-C (SIGINT) finishes the iteration, checkpoints and raises; a later `train()` of the same trainer goes on
    to the end instead of stopping again after one iteration."""
    trainer = make_trainer(scene_dir, tmp_path, iters=6, checkpoint_every=100)
    trainer.write_run_files()
    with pytest.raises(KeyboardInterrupt):  # the signal handler's effect, as a Ctrl-C during iteration 1 has
        trainer.train(callback=lambda record: trainer._request_stop(signal.SIGINT, None))
    assert trainer.iteration == 1 and trainer.latest_checkpoint().name == "checkpoint_000001.pt"
    trainer.train()
    assert trainer.iteration == 6


def test_sigterm_stops_training_with_a_checkpoint_as_ctrl_c_does(scene_dir, tmp_path):
    """A job scheduler's or `kill`'s SIGTERM: the iteration finishes, a checkpoint is saved, KeyboardInterrupt (in a
    process of its own: without the trainer's handler, SIGTERM ends the process)."""
    code = (f"import os, signal, sys\n"
            f"sys.path.insert(0, {str(Path(__file__).parent)!r})\n"
            f"from test_training import make_trainer\n"
            f"from pathlib import Path\n"
            f"trainer = make_trainer(Path({str(scene_dir)!r}), Path({str(tmp_path / 'run')!r}), iters=6,\n"
            f"                       checkpoint_every=100)\n"
            f"trainer.write_run_files()\n"
            f"try:\n"
            f"    trainer.train(callback=lambda record: os.kill(os.getpid(), signal.SIGTERM))\n"
            f"except KeyboardInterrupt:\n"
            f"    print('stopped at', trainer.iteration, trainer.latest_checkpoint().name)\n"
            f"print('SIGTERM handler after train:', signal.getsignal(signal.SIGTERM) == signal.SIG_DFL)\n")
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, result.stderr[-2000:]
    assert result.stdout.splitlines()[-2:] == ["stopped at 1 checkpoint_000001.pt", "SIGTERM handler after train: True"]


def test_sigterm_is_left_to_a_handler_the_process_already_has(scene_dir, tmp_path):
    """A Ray worker's SIGTERM handler exits so that Ray retries the task (which resumes from the last checkpoint):
    training does not take SIGTERM from it."""
    received = []
    previous = signal.signal(signal.SIGTERM, lambda signum, frame: received.append(signum))
    try:
        trainer = make_trainer(scene_dir, tmp_path, iters=3, checkpoint_every=100)
        trainer.write_run_files()
        trainer.train(callback=lambda record: os.kill(os.getpid(), signal.SIGTERM))
        assert trainer.iteration == 3 and received == [signal.SIGTERM] * 3
    finally:
        signal.signal(signal.SIGTERM, previous)


def test_a_stop_by_signal_crosses_process_boundaries():
    """Ray and multiprocessing pickle a task's exception: Stopped is rebuilt from its signal number (its args hold
    the name, which `signal.Signals` does not take)."""
    import pickle

    from warpbags.errors import Stopped

    stopped = pickle.loads(pickle.dumps(Stopped(signal.SIGTERM)))
    assert isinstance(stopped, KeyboardInterrupt) and stopped.signum == signal.SIGTERM


def test_train_stopped_by_sigterm_exits_143_and_keeps_its_checkpoint(scene_dir, tmp_path):
    """`warpbags train` stopped by SIGTERM exits with the shell's 128 + 15, which job schedulers read, not Ctrl-C's
    130, and says so; the checkpoint it saved is there to resume from."""
    out = tmp_path / "run"
    command = [sys.executable, "-m", "warpbags.cli.main", "train", str(scene_dir), "--views", "4", "--out", str(out),
               "--log-every", "1", "--set", "iters=400", "--set", "rounds=1", "--set", "init_points=800",
               "--set", "hull_resolution=32", "--set", "checkpoint_every=1000", "--set", "camera.hypotheses_round=0"]
    process = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    for line in process.stdout:
        if line.startswith("iter "):
            process.send_signal(signal.SIGTERM)
            break
    stdout, stderr = process.communicate(timeout=600)
    assert process.returncode == 128 + signal.SIGTERM, stderr[-2000:]
    assert "stopped by SIGTERM" in stderr and "checkpoint saved, continue with --resume" in " ".join(stdout.split())
    assert list((out / "checkpoints").glob("checkpoint_*.pt"))


def test_a_new_run_that_fails_before_its_first_checkpoint_leaves_nothing_behind(scene_dir, tmp_path):
    """A run of `start_or_resume` that cannot be resumed (no checkpoint yet) removes what it wrote when it fails,
    whatever the failure, and the folder if it made it; from its first checkpoint on it is kept for --resume."""
    config = tiny_config(iters=6, checkpoint_every=3)
    scene = training_scene(load_scene(scene_dir, name="tiny"), config)
    made = tmp_path / "made" / "run"
    trainer = start_or_resume(scene, config, made, log=lambda message: None)
    assert (made / "config.json").is_file() and (made / "poses_true.npy").is_file()
    with torch.no_grad():
        trainer.params["means"][0, 0] = float("nan")
    with pytest.raises(WarpbagsError, match="diverged at iteration 0: .*no checkpoint was written yet"):
        trainer.train()
    assert not made.parent.exists()  # with the folder it made to hold it
    empty = tmp_path / "empty"
    empty.mkdir()
    trainer = start_or_resume(scene, config, empty, log=lambda message: None)

    def interrupt(record):  # an interrupt the SIGINT handler did not turn into a checkpoint (another thread's)
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        trainer.train(callback=interrupt)
    assert empty.is_dir() and list(empty.iterdir()) == []  # the folder it found is left, empty
    trainer = start_or_resume(scene, config, empty, log=lambda message: None)
    trainer.train(stop_at=3)
    with torch.no_grad():
        trainer.params["means"][0, 0] = float("nan")
    with pytest.raises(WarpbagsError, match="diverged at iteration 3: .*checkpoint_000003"):
        trainer.train()
    assert len((empty / "log.jsonl").read_text().splitlines()) == 3 and (empty / "config.json").is_file()
    assert start_or_resume(scene, config, empty, resume=True, log=lambda message: None).iteration == 3


def test_a_second_run_started_into_a_folder_while_the_first_starts_stops(scene_dir, tmp_path, monkeypatch):
    """The folder was checked before the start procedures and made only after them: a second run started into the
    same --out meanwhile (a resubmitted job) found it empty too, and both trained into it, one log for two runs.
    The first now claims the folder before its start procedures; the second stops, writing nothing."""
    config = tiny_config(iters=3)
    scene = training_scene(load_scene(scene_dir, name="tiny"), config)
    out = tmp_path / "made" / "same"
    starting_poses = trainer_module.starting_poses
    second = []

    def second_run_starts(*args, **kwargs):  # during the first run's start procedures
        with pytest.raises(WarpbagsError, match="another run is starting in .*same"):
            start_or_resume(scene, config, out, log=lambda message: None)
        second.append(sorted(path.name for path in out.iterdir()))
        return starting_poses(*args, **kwargs)

    monkeypatch.setattr(trainer_module, "starting_poses", second_run_starts)
    start_or_resume(scene, config, out, log=lambda message: None).train()
    assert second == [[run_folder.STARTING_FILE]]
    assert not (out / run_folder.STARTING_FILE).exists() and (out / "gaussians.ply").is_file()
    # two that both found it empty: the second claim stops
    both = run_folder.RunFolder(tmp_path / "both")
    both.claim_new()
    with pytest.raises(WarpbagsError, match="another run is starting"):
        run_folder.RunFolder(tmp_path / "both").claim_new()
    # a start that fails before its setup files leaves no folder it made, and no claim

    def failing_start(*args, **kwargs):
        raise WarpbagsError("the start failed")

    monkeypatch.setattr(trainer_module, "starting_poses", failing_start)
    with pytest.raises(WarpbagsError, match="the start failed"):
        start_or_resume(scene, config, tmp_path / "failed" / "run", log=lambda message: None)
    assert not (tmp_path / "failed").exists()


def test_resuming_a_finished_run_trains_nothing(scene_dir, tmp_path):
    finished = make_trainer(scene_dir, tmp_path, iters=4)
    finished.write_run_files()
    finished.train()
    resumed = make_trainer(scene_dir, tmp_path, iters=4)
    assert resumed.resume() and resumed.iteration == 4
    resumed.train()
    assert len((tmp_path / "log.jsonl").read_text().splitlines()) == 4  # no iteration ran again


def test_resume_cuts_log_and_pose_history_back_to_the_checkpoint(scene_dir, tmp_path, monkeypatch):
    monkeypatch.setattr(run_folder, "RECORD_EVERY", 1)
    trainer = make_trainer(scene_dir, tmp_path, iters=6, checkpoint_every=2)
    trainer.train(stop_at=5)  # checkpoints at 2, 4 and 5
    (tmp_path / "checkpoints" / "checkpoint_000005.pt").unlink()  # the run goes on past its last checkpoint,
    with open(tmp_path / "log.jsonl", "a") as log:
        log.write('{"iter": 6, "stage": "coa')  # and stops in the middle of a line
    assert read_pose_history(tmp_path).iterations.tolist() == [1, 2, 3, 4, 5]
    resumed = make_trainer(scene_dir, tmp_path, iters=6)
    assert resumed.resume() and resumed.iteration == 4
    assert [json.loads(line)["iter"] for line in (tmp_path / "log.jsonl").read_text().splitlines()] == [1, 2, 3, 4]
    history = read_pose_history(tmp_path)
    assert history.iterations.tolist() == [1, 2, 3, 4]
    np.testing.assert_array_equal(history.viewmats[-1], resumed.current_viewmats().numpy())


def test_a_config_json_changed_after_the_run_started_is_refused_on_resume(scene_dir, tmp_path):
    """config.json alone decided how a checkpoint was resumed: edited (an object-centric run's corrections read as
    camera-centred ones, 30 iterations cut to 12), the run went on silently. The checkpoint's own config is compared;
    how often it saves and its render threads may differ."""
    trainer = make_trainer(scene_dir, tmp_path, iters=4, checkpoint_every=2)
    trainer.write_run_files()
    trainer.train(stop_at=2)
    info = json.loads((tmp_path / "config.json").read_text())
    info["config"]["camera"]["parameterization"] = "camera"
    (tmp_path / "config.json").write_text(json.dumps(info))
    result = runner.invoke(app, ["train", "--resume", "--out", str(tmp_path)])
    message = " ".join(result.output.split())
    errors = [line for line in result.output.splitlines() if line.startswith("error:")]
    assert result.exit_code == 2 and len(errors) == 1 and "Traceback" not in result.output, result.output
    assert "checkpoint_000002.pt was saved with camera.parameterization = 'object', the config resumed with" in message
    assert make_trainer(scene_dir, tmp_path, iters=4, checkpoint_every=3, render_threads=2).resume()


def test_a_run_saved_with_a_value_its_config_now_mends_resumes_where_it_would_have_ended(scene_dir, tmp_path):
    """A run started before `validate` refused --blur-px without --blur-until saved blur_sigma_px 4.0 with
    blur_until 0 (a blur never applied) in config.json and in its checkpoints. `TrainConfig.from_dict` mends
    config.json's value to 0.0, and the checkpoint's unmended 4.0 was then taken for an edit of config.json: "was
    saved with blur_sigma_px = 4.0 ... restore it", so the run could never be resumed. It resumes, and ends as the
    run did uninterrupted."""
    out = tmp_path / "run"
    trainer = make_trainer(scene_dir, out, iters=4, checkpoint_every=2, pose_opt_start=0, rot_noise_deg=3.0)
    trainer.write_run_files()
    trainer.train()
    checkpoints = out / "checkpoints"
    uninterrupted = torch.load(checkpoints / "checkpoint_000004.pt", weights_only=False)
    info = json.loads((out / "config.json").read_text())
    assert info["config"]["blur_sigma_px"] == 0.0 and info["config"]["blur_until"] == 0
    info["config"]["blur_sigma_px"] = 4.0
    (out / "config.json").write_text(json.dumps(info))
    state = torch.load(checkpoints / "checkpoint_000002.pt", weights_only=False)
    state["config"]["blur_sigma_px"] = 4.0
    torch.save(state, checkpoints / "checkpoint_000002.pt")
    (checkpoints / "checkpoint_000004.pt").unlink()  # the run stopped after its checkpoint at 2
    result = runner.invoke(app, ["train", "--resume", "--out", str(out)])
    assert result.exit_code == 0, result.output
    assert "restore it" not in result.output
    assert [json.loads(line)["iter"] for line in (out / "log.jsonl").read_text().splitlines()] == [1, 2, 3, 4]
    resumed = torch.load(checkpoints / "checkpoint_000004.pt", weights_only=False)
    for name, value in uninterrupted["params"].items():
        torch.testing.assert_close(resumed["params"][name], value, rtol=0, atol=0)
    for name, value in uninterrupted["cameras"]["module"].items():
        torch.testing.assert_close(resumed["cameras"]["module"][name], value, rtol=0, atol=0)
    # a checkpoint whose config cannot be read is named (the error said "unknown training option(s)" alone)
    resumed["config"]["old_field"] = 1
    torch.save(resumed, checkpoints / "checkpoint_000004.pt")
    with pytest.raises(WarpbagsError, match=re.escape(f"{checkpoints / 'checkpoint_000004.pt'}: its config: unknown")):
        trainer.load_checkpoint(checkpoints / "checkpoint_000004.pt")


def test_a_full_disk_while_training_is_one_line_naming_the_checkpoint_kept(scene_dir, tmp_path, monkeypatch):
    """A checkpoint torch could not write (its RuntimeError "unexpected pos" at a file-size limit) or a result file
    numpy could not (OSError: no space left) was a traceback."""
    trainer = make_trainer(scene_dir, tmp_path, iters=4, checkpoint_every=2)
    trainer.write_run_files()
    save = torch.save

    def full_disk(*args, **kwargs):
        raise RuntimeError("[enforce fail at inline_container.cc:672] . unexpected pos 368768 vs 368656")

    monkeypatch.setattr(torch, "save", full_disk)
    with pytest.raises(WarpbagsError, match=f"^cannot write into {re.escape(str(tmp_path))}: torch.save failed "
                                            r"\(\[enforce fail .*unexpected pos"):
        trainer.train()
    assert not list((tmp_path / "checkpoints").glob("*"))  # nor a temporary left
    monkeypatch.setattr(torch, "save", save)
    trainer = make_trainer(scene_dir, tmp_path, iters=4, checkpoint_every=2)

    def no_space(path, array):
        raise OSError(28, "No space left on device", str(path))

    monkeypatch.setattr(run_folder.np, "save", no_space)
    with pytest.raises(WarpbagsError, match="No space left on device.*checkpoint_000004.pt is kept: --resume "
                                            "continues from it once there is room"):
        trainer.train()


def test_an_old_or_damaged_checkpoint_is_one_line(scene_dir, tmp_path):
    trainer = make_trainer(scene_dir, tmp_path, iters=2)
    trainer.write_run_files()
    trainer.train()
    path = trainer.latest_checkpoint()
    state = torch.load(path, weights_only=False)
    del state["cameras"]  # as written before the camera optimizer had a state of its own
    torch.save(state, path)
    with pytest.raises(WarpbagsError, match="older warpbags \\(no cameras\\); it cannot be resumed"):
        make_trainer(scene_dir, tmp_path, iters=2).resume()
    path.write_bytes(path.read_bytes()[:200])  # cut short
    result = runner.invoke(app, ["train", str(scene_dir), "--resume", "--out", str(tmp_path)])
    errors = [line for line in result.output.splitlines() if line.startswith("error:")]
    assert result.exit_code == 2 and "Traceback" not in result.output, result.output
    assert len(errors) == 1 and "unreadable checkpoint" in errors[0], result.output


@pytest.fixture(scope="module")
def pose_run(scene_dir, tmp_path_factory):
    trainer = make_trainer(scene_dir, tmp_path_factory.mktemp("pose"), **POSE_TEST)
    before = trainer.pose_error(trainer.viewmats_init)
    trainer.train()
    return before, trainer.pose_error()


def test_fifteen_degree_noise_on_every_camera_is_cut_to_a_quarter(pose_run):
    before, after = pose_run
    assert before["rot_err_deg"] > 12.0
    # Measured 14.17 -> 0.89 deg and 0.357 -> 0.014 (1.06 / 0.022 before the silhouette-coherence solve of the
    # starting poses) with the depth term in the first half of each round (60 iterations, an older version: 3.56 /
    # 0.109; rounding-level changes have moved a single seed's result by 2 deg, docs/pose-recovery.md). Without the
    # scene's depth maps an older version ended at 12.95 deg. So this bounds what the method must always do (frozen
    # noisy poses stay at 14.17), not how well.
    assert after["rot_err_deg"] <= before["rot_err_deg"] / 4, (before, after)
    assert after["trans_err"] <= 0.25 * before["trans_err"], (before, after)


def test_the_search_never_turns_a_gauge_camera(scene_dir, tmp_path):
    """With camera 0 held as the gauge (`camera.fix_first_camera`), the worst fit is chosen among the others, even
    when camera 0 fits worst: a turn of the gauge camera could never be corrected."""
    trainer = make_trainer(scene_dir, tmp_path, iters=4, camera={"fix_first_camera": True})
    trainer.train()
    fits = {0: 9.0, 1: 1.0, 2: 3.0, 3: 2.0}  # camera 0 fits worst, camera 2 next
    trainer.model.loss = lambda views, viewmats, settings: (torch.tensor(fits[int(views[0])]), {}, {})
    assert trainer._worst_fit_view() == 2
    trainer.cameras.gauge[0] = 1.0  # a free gauge: every camera may be chosen
    assert trainer._worst_fit_view() == 0


# The quick preset as shipped (free gauge, 3 rounds of 200 iterations, its pose window), on both cores, but without
# the search over turns of the worst-fit camera (`tiny_config`; its own test is below).
POSE_TEST = dict(iters=600, rounds=3, rot_noise_deg=15.0, trans_noise=0.3, pose_opt_start=0,
                 pose_round_window=(0.25, 1.0), depth_until=100, init_points=3000, hull_resolution=48, render_threads=0)


def test_a_camera_left_rolled_off_is_turned_back_by_the_hypotheses(scene_dir, tmp_path):
    """camera.hypotheses_round: without depth maps, a camera started 25 deg off in roll (which the mask-centroid
    start does not fix) is still 19.4 deg off after two rounds of 100 iterations with the search off (measured). With
    it, the camera is the worst fit after round 1 (22.5 deg off), a turn back by 20 deg about its line of sight wins
    round 2 by 14% of the loss, and the camera ends 0.1 deg off (measured). Started 20 deg off, it is 16.6 deg off
    after round 1 and the best turn (10 deg) wins by 3%, under the 5% margin (6.7% before the distance outside a mask
    at the image border was corrected): on this 96 px scene the loss tells turns apart only from about 20 deg."""
    from warpbags.alignment import pose_errors
    from warpbags.camera_optimizer import corrected_viewmats

    config = tiny_config(**{**POSE_TEST, "iters": 200, "rounds": 2, "depth_until": 50, "rot_noise_deg": 0.0,
                            "trans_noise": 0.0, "checkpoint_every": 1000,
                            # the coherence solve would first spread the roll over all cameras (its own tests)
                            "camera": {"hypotheses_round": 1, "hypothesis_angles": (10.0, 20.0),
                                       "coherence_iters": 0}})
    scene = dataclasses.replace(training_scene(load_scene(scene_dir, name="tiny"), config), depths=None)
    viewmats = scene.viewmats.clone().float()
    roll = torch.tensor([[0.0, 0.0, math.radians(25.0), 0.0, 0.0, 0.0]])
    viewmats[2] = corrected_viewmats("object", viewmats[2:3], roll, torch.zeros(1, 3))[0]
    messages = []
    trainer = Trainer(scene, config, tmp_path, viewmats_init=viewmats, log=messages.append)
    trainer.train(stop_at=150)
    assert trainer.iteration == 100  # the search trains its round as a whole: a stop inside it stops at its start,
    assert trainer.latest_checkpoint().name == "checkpoint_000100.pt"  # and checkpoints there
    trainer.train()
    assert trainer.iteration == 200
    search = [message for message in messages if "the worst fit" in message]
    assert len(search) == 1 and search[0].startswith("round 1: camera 2, the worst fit, turned -"), messages
    assert search[0].endswith(": kept") and "about z" in search[0], search
    errors = pose_errors(trainer.current_viewmats().double(), trainer.viewmats_true.double())["rotation_errors_deg"]
    assert errors[2] < 5.0, errors
    # The kept trial's iterations are logged once each, in order, with its poses.
    log = [json.loads(line) for line in (tmp_path / "log.jsonl").read_text().splitlines()]
    assert [record["iter"] for record in log] == list(range(1, 201))
    decisions = [record["view_hypotheses"] for record in log if "view_hypotheses" in record]
    assert len(decisions) == 1 and log[100]["view_hypotheses"]["kept"] and log[100]["view_hypotheses"]["camera"] == 2
    assert read_pose_history(tmp_path).iterations.tolist() == list(range(10, 201, 10))


def test_a_turn_that_does_not_beat_the_margin_is_not_kept_and_the_run_ends_as_without_the_search(scene_dir, tmp_path):
    """camera.hypothesis_margin: a turn is kept only when it beats the unturned trial by the margin; at 99% none
    does, and the search goes back to its unturned trial, which trained from the same model, poses and random
    stream as the run without the search. Its log record says so, and the two runs end at the same poses bit for
    bit (a search that kept its best turn regardless ends elsewhere)."""
    def final_poses(name, camera):
        trainer = make_trainer(scene_dir, tmp_path / name, iters=8, rounds=2, pose_opt_start=0, checkpoint_every=1000,
                               camera=camera)
        trainer.train()
        assert trainer.iteration == 8
        log = [json.loads(line) for line in (tmp_path / name / "log.jsonl").read_text().splitlines()]
        assert [record["iter"] for record in log] == list(range(1, 9))
        return np.load(tmp_path / name / "poses_final.npy"), [record.get("view_hypotheses") for record in log]

    searched, log = final_poses("search", {"hypotheses_round": 1, "hypothesis_angles": (10.0, 20.0),
                                           "hypothesis_margin": 0.99})
    decisions = [decision for decision in log if decision is not None]
    assert len(decisions) == 1 and log[4] is decisions[0]  # in round 1's first record (iteration 5)
    assert decisions[0]["kept"] is False and decisions[0]["best_loss"] > 0.01 * decisions[0]["unturned_loss"]
    unsearched, log = final_poses("off", {"hypotheses_round": 0})
    assert not any(log)
    assert np.array_equal(searched, unsearched)


def test_a_search_in_the_last_round_trains_to_the_end(scene_dir, tmp_path):
    """8 iterations in 3 rounds: rounds of 2, 3 and 3 (the longer ones last); the search in the last round trains
    its 3 iterations per trial and the run ends at iteration 8 with its results written."""
    trainer = make_trainer(scene_dir, tmp_path, iters=8, rounds=3, pose_opt_start=0,
                           camera={"hypotheses_round": 2, "hypothesis_angles": (10.0, 20.0)})
    trainer.train()
    assert trainer.iteration == 8 and (tmp_path / "gaussians.ply").is_file()
    log = [json.loads(line)["iter"] for line in (tmp_path / "log.jsonl").read_text().splitlines()]
    assert log == list(range(1, 9))


# ------------------------------------------------------------------------------------------------ CLI
runner = CliRunner()


def test_cli_smoke_writes_run_files(scene_dir, tmp_path):
    out = tmp_path / "run"
    result = runner.invoke(app, ["train", str(scene_dir), "--iters", "6", "--pose-opt-start", "2", "--rot-noise-deg", "5",
                                 "--out", str(out), "--max-image-size", "48"])
    assert result.exit_code == 0, result.output
    for name in ("config.json", "poses_true.npy", "poses_init.npy", "log.jsonl", "gaussians.ply", "poses_final.npy"):
        assert (out / name).is_file(), name
    assert len((out / "log.jsonl").read_text().splitlines()) == 6
    assert np.load(out / "poses_final.npy").shape == (4, 4, 4)
    config = json.loads((out / "config.json").read_text())["config"]
    assert config["iters"] == 6 and config["rot_noise_deg"] == 5.0
    # noise injected: the scene's poses are the truth, and the distance from them is an error
    assert "initial pose error" in result.output and "cameras moved" not in result.output
    # A fresh run into the same folder is refused (resuming one: test_resuming_a_finished_run_trains_nothing).
    again = runner.invoke(app, ["train", str(scene_dir), "--iters", "6", "--out", str(out)])
    assert again.exit_code == 2 and "--resume" in again.output


def test_cli_resume_goes_on_with_the_runs_config(scene_dir, tmp_path):
    out = tmp_path / "run"
    command = ["train", str(scene_dir), "--iters", "4", "--max-image-size", "32", "--set", "init_points=300",
               "--out", str(out)]
    assert runner.invoke(app, command).exit_code == 0
    # the command line that started the run, given again: accepted (the run is finished, nothing trains)
    again = runner.invoke(app, [*command, "--resume"])
    assert again.exit_code == 0, again.output
    assert "already finished its 4 iterations" in again.output and "nan" not in again.output
    assert len((out / "log.jsonl").read_text().splitlines()) == 4
    # the scene left out, as the message after Ctrl-C suggests: the run's own
    bare = runner.invoke(app, ["train", "--resume", "--out", str(out)])
    assert bare.exit_code == 0 and "already finished its 4 iterations" in bare.output, bare.output
    missing = runner.invoke(app, ["train", "--out", str(tmp_path / "fresh")])
    assert missing.exit_code == 2 and "give the scene to train" in missing.output
    # the run left the resolution factor to the scene, which read it at 1: naming that factor opens the same images
    assert json.loads((out / "config.json").read_text())["resolution"] == 1
    named = runner.invoke(app, [*command, "--resume", "-r", "1"])
    assert named.exit_code == 0 and "already finished its 4 iterations" in named.output, named.output
    # anything that would change the run half-way is refused, before the scene is loaded at another size
    for extra, message in [(["--views", "5"], "trained with views=4, not 5"),
                           (["--preset", "paper"], "trained with --preset quick, not paper"),
                           (["--max-image-size", "64"], "trained with max_image_size=32, not 64"),
                           (["-r", "2"], "read its images at the scene's resolution factor 1, not 2"),
                           (["--set", "init_points=500"], "trained with init_points=300, not 500")]:
        result = runner.invoke(app, [*command, "--resume", *extra])
        lines = [line for line in result.output.splitlines() if line.strip()]
        assert result.exit_code == 2 and len(lines) == 1 and message in lines[0], result.output
    # another scene folder (a copy of the run's): refused, by the CLI and by the Python API alike
    other = tmp_path / "other-scene"
    shutil.copytree(scene_dir, other)
    result = runner.invoke(app, [*command[:1], str(other), *command[2:], "--resume"])
    lines = [line for line in result.output.splitlines() if line.strip()]
    assert result.exit_code == 2 and len(lines) == 1 and "holds a run of the scene in" in lines[0], result.output
    with pytest.raises(WarpbagsError, match="holds a run of the scene in"):
        config = saved_run_config(out)
        start_or_resume(training_scene(load_scene(other), config), config, out, resume=True)


@pytest.mark.parametrize(
    "arguments, message",
    [
        (["--views", "1"], "--views must be >= 2"),
        (["--views", "17"], "fewer than --views 17"),
        (["--iters", "0"], "--iters must be >= 1"),
        (["--rot-noise-deg", "-1"], "--rot-noise-deg must be >= 0"),
        (["--preset", "fast"], "--preset must be one of"),
        (["--init", "mesh"], "--init must be hull, sfm or random"),
        (["--depth-loss", "l2"], "--depth-loss must be mad or pearson"),
        (["--blur-px", "-2"], "--blur-px must be >= 0"),
        (["--rounds", "0"], "--rounds must be in [1, iters]"),
        (["--device", "tpu"], "--device must be cpu or cuda"),
        (["--resume"], "--resume: no checkpoint"),
    ],
)
def test_cli_bad_values_one_line(scene_dir, tmp_path, arguments, message):
    result = runner.invoke(app, ["train", str(scene_dir), "--out", str(tmp_path / "r"), *arguments])
    assert result.exit_code == 2
    lines = [line for line in result.output.splitlines() if line.strip()]
    assert len(lines) == 1 and message in lines[0], result.output


@pytest.mark.parametrize("below", ["", "run"])
def test_cli_out_that_is_a_file_is_one_line_before_training(scene_dir, tmp_path, below, monkeypatch):
    """`--out` naming a file, or a folder inside one, is refused before the scene is read (a minute for a folder of
    photographs, then the start procedures), not by a traceback when the run's first file is written."""
    (tmp_path / "a-file").write_text("")

    def not_reached(*args, **kwargs):
        raise AssertionError("the scene was read")

    monkeypatch.setattr("warpbags.cli.train.training_scene", not_reached)
    result = runner.invoke(app, ["train", str(scene_dir), "--out", str(tmp_path / "a-file" / below)])
    lines = [line for line in result.output.splitlines() if line.strip()]
    assert result.exit_code == 2 and len(lines) == 1, result.output
    assert "a-file is a file, not a folder to train into" in " ".join(result.output.split())


def test_cli_new_run_into_a_folder_that_is_not_empty_is_one_line_before_training(scene_dir, tmp_path, monkeypatch):
    """A new run overwrites nothing and appends to no other log: a folder that holds anything (the scene itself, what
    a failed run of an older warpbags left) is refused before the scene is read, naming what it holds; the Python
    entry point refuses it too."""
    def not_reached(*args, **kwargs):
        raise AssertionError("the scene was read")

    monkeypatch.setattr("warpbags.cli.train.training_scene", not_reached)
    before = sorted(path.name for path in scene_dir.iterdir())
    result = runner.invoke(app, ["train", str(scene_dir), "--out", str(scene_dir)])
    lines = [line for line in result.output.splitlines() if line.strip()]
    message = " ".join(result.output.split())
    assert result.exit_code == 2 and len(lines) == 1, result.output
    assert f"{scene_dir} is not empty (" in message and "sparse_4.txt" in message and "another --out" in message
    assert sorted(path.name for path in scene_dir.iterdir()) == before
    left = tmp_path / "left"
    left.mkdir()
    (left / "log.jsonl").write_text('{"iter": 1}\n')
    with pytest.raises(WarpbagsError, match=re.escape(f"{left} holds a run stopped before its first checkpoint")):
        start_or_resume(None, tiny_config(), left)
    assert (left / "log.jsonl").read_text() == '{"iter": 1}\n'


def test_cli_unknown_scene_one_line(tmp_path):
    result = runner.invoke(app, ["train", str(tmp_path / "nope")])
    assert result.exit_code == 2 and len(result.output.strip().splitlines()) == 1
    assert result.output.startswith("error: scene ") and "nope" in result.output and "no preset" in result.output


def test_cli_any_view_count_through_the_farthest_point_split(scene_dir, tmp_path):
    out = tmp_path / "five"
    result = runner.invoke(app, ["train", str(scene_dir), "--views", "5", "--iters", "3", "--out", str(out),
                                 "--max-image-size", "32", "--set", "init_points=300", "--set", "hull_resolution=16"])
    assert result.exit_code == 0, result.output
    assert "no sparse_5.txt" in result.output and "farthest-point" in result.output
    assert np.load(out / "poses_final.npy").shape == (5, 4, 4)
    # no noise injected: training starts from the scene's own poses, which a user's capture does not vouch for, so
    # the distance from them is reported as how far the cameras moved, not as an error
    output = " ".join(result.output.split())
    assert "no noise injected" in output and "cameras moved" in output and "pose error" not in output


def test_training_leaves_the_callers_torch_threads_alone(scene_dir, tmp_path):
    previous = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        trainer = make_trainer(scene_dir, tmp_path, iters=2)
        trainer.train()
        assert torch.get_num_threads() == 2
    finally:
        torch.set_num_threads(previous)


def test_pyramid_levels_train_early_rounds_at_lower_resolution(scene_dir, tmp_path):
    trainer = make_trainer(scene_dir, tmp_path, iters=6, rounds=3, pyramid_levels=2, pose_opt_start=0,
                           rot_noise_deg=5.0)
    full = trainer.full_scene.width
    sizes = []
    trainer.train(callback=lambda record: sizes.append(trainer.scene.width))
    assert sizes == [full // 2] * 4 + [full] * 2  # rounds 1-2 at the coarse level, the last at full resolution
    views = torch.arange(2)
    assert trainer.model.render(views, trainer.cameras.viewmats()[views], 0)[0].shape[1:3] == (full, full)
    trainer.write_run_files()
    assert np.load(tmp_path / "intrinsics.npy")[0, 0, 2] == pytest.approx(trainer.full_scene.Ks[0, 0, 2].item())


def test_every_configured_round_runs_and_their_lengths_differ_by_at_most_one():
    """Rounds that do not divide the iterations are balanced, the longer ones last: a ceil-length split ran 5 rounds
    of 10 iterations asked for 6, and left the last round (whose Gaussians are the result) 1 iteration of 4."""
    for iters, rounds, lengths in [(10, 6, [1, 1, 2, 2, 2, 2]), (10, 4, [2, 2, 3, 3]), (20, 8, [2, 2, 2, 2, 3, 3, 3, 3]),
                                   (600, 3, [200, 200, 200]), (8, 3, [2, 3, 3])]:
        schedule = Schedule(load_preset("quick", iters=iters, rounds=rounds))
        starts = [i for i in range(iters) if i == 0 or schedule.starts_round(i)]
        assert schedule.rounds == rounds and [schedule.round_end(start) - start for start in starts] == lengths
        assert [schedule.round_length(k) for k in range(rounds)] == lengths
        assert [schedule.round_index(start) for start in starts] == list(range(rounds))


def test_the_gaussians_adam_takes_each_groups_rate_and_the_position_rate_scaled_by_the_extent():
    """`--set lr.NAME=...` reaches the Gaussians' Adam: each group its own rate, the position rate times the scene
    extent and decaying from means_init to means_final (no test read the optimizer's rates)."""
    from warpbags.model import GaussianModel

    rates = dict(means_init=1e-3, means_final=1e-5, scales=2e-3, quats=3e-3, opacities=4e-3, sh_dc=5e-3, sh_rest=6e-3)
    config = load_preset("quick", lr=rates)
    params = {name: torch.nn.Parameter(torch.zeros(3, 3)) for name in ("means", "scales", "quats", "opacities",
                                                                       "sh0", "shN")}
    model = GaussianModel(config, None, params, 2.5, torch.Generator())
    groups = {group["name"]: group for group in model.optimizer.param_groups}
    expected = {"means": 2.5e-3, "scales": 2e-3, "quats": 3e-3, "opacities": 4e-3, "sh0": 5e-3, "shN": 6e-3}
    assert {name: group["lr"] for name, group in groups.items()} == pytest.approx(expected, rel=1e-12)
    for fraction, position in ((0.0, 1e-3), (0.5, 1e-4), (1.0, 1e-5)):
        model.set_learning_rate(fraction)
        assert groups["means"]["lr"] == pytest.approx(2.5 * position, rel=1e-12)
        assert groups["scales"]["lr"] == 2e-3


def test_the_position_lr_ends_every_round_at_its_final_value():
    """The Gaussians' position lr decays over each round's own length: rounds of unequal length (11 iterations in
    rounds of 2, 3, 3, 3) each reach the final value at their last iteration."""
    schedule = Schedule(load_preset("quick", iters=11, rounds=4))
    fractions = [schedule.at(i).gaussian_lr_fraction for i in range(11)]
    assert fractions == [0.0, 1.0, 0.0, 0.5, 1.0, 0.0, 0.5, 1.0, 0.0, 0.5, 1.0]


def test_rounds_of_unequal_length_have_their_pose_windows_as_shares_of_their_own_length():
    """10 iterations in rounds of 3, 3 and 4 with poses in each round's second half move them at 2, 5 and 8-9."""
    schedule = Schedule(load_preset("quick", iters=10, rounds=3, pose_round_window=(0.5, 1.0)))
    assert [i for i in range(10) if schedule.at(i).pose_active] == [2, 5, 8, 9]


def test_rounds_take_their_own_pose_windows():
    config = load_preset("quick", iters=40, rounds=4, pose_round_window=(0.0, 1.0),
                         pose_round_windows=[[0.25, 1.0], [0.25, 1], [0.5, 1]])
    assert config.pose_round_windows == ((0.25, 1.0), (0.25, 1), (0.5, 1))
    schedule = Schedule(config)
    # rounds 0-1 from a quarter in, round 2 and the rounds after it (the last entry) from half-way
    assert [i for i in range(40) if schedule.at(i).pose_active] == [
        *range(3, 10), *range(13, 20), *range(25, 30), *range(35, 40)]
    # the lr decays over each round's own window (and ramps up over its first lr.pose_warmup steps)
    assert schedule.at(25).pose_lr == pytest.approx(config.lr.pose / config.lr.pose_warmup)
    # empty: pose_round_window in every round
    assert [i for i in range(20) if Schedule(load_preset("quick", iters=40, rounds=4)).at(i).pose_active] == [
        *range(3, 10), *range(13, 20)]
    given = parse_settings(["pose_round_windows=[[0.25, 1], [0.5, 1]]"])  # `warpbags train --set ...`
    assert load_preset("quick", **given).pose_round_windows == ((0.25, 1), (0.5, 1))
    for bad in ([[0.5, 0.5]], [[0.2]], [3], [["a", "b"]], [[True, 1]]):
        with pytest.raises(WarpbagsError, match="pose_round_windows must be"):
            load_preset("quick", pose_round_windows=bad)


def test_the_poses_are_averaged_over_the_last_share_of_the_last_rounds_window():
    """Rounds of 20 with poses from a quarter in: the last round's window is 25-39; its last half (8 of 15 steps)
    with average_share 0.5, all of it with 1, none with 0, and none without pose optimization."""
    def averaged(**overrides):
        schedule = Schedule(load_preset("quick", iters=40, rounds=2, **overrides))
        return [i for i in range(40) if schedule.at(i).pose_average]

    assert averaged(camera={"average_share": 1.0}) == list(range(25, 40))
    assert averaged(camera={"average_share": 0.5}) == list(range(32, 40))
    assert averaged(camera={"average_share": 0.0}) == [] and averaged(pose_opt=False) == []
    assert load_preset("quick").camera.average_share == 1.0 and load_preset("paper").camera.average_share == 0.0
    with pytest.raises(WarpbagsError, match="camera.average_share must be in"):
        load_preset("quick", camera={"average_share": 1.5})


def test_a_run_ends_with_the_mean_of_its_last_rounds_estimates(scene_dir, tmp_path):
    """The training is the same with or without the average (the same Gaussians, to the bit); only the final poses
    differ: the mean of the estimates after each step of the averaged window (steps 9, 10 and 11 of rounds of 6 with
    poses in their second half), which poses_final holds."""
    overrides = dict(iters=12, rounds=2, pose_opt_start=0, pose_round_window=(0.5, 1.0), rot_noise_deg=3.0)
    estimates = {}
    averaged = make_trainer(scene_dir, tmp_path / "averaged", **overrides, camera={"average_share": 1.0})
    averaged.train(callback=lambda record: estimates.setdefault(record["iter"], averaged.current_viewmats().double()))
    last = make_trainer(scene_dir, tmp_path / "last", **overrides, camera={"average_share": 0.0})
    last.train()
    for name in last.params:
        assert torch.equal(averaged.params[name], last.params[name]), name
    assert [i for i in range(12) if averaged.schedule.at(i).pose_average] == [9, 10, 11]
    window = [estimates[10], estimates[11], last.current_viewmats().double()]  # after steps 9, 10 and 11
    expected = mean_viewmats(sum(e[:, :3, :3] for e in window), sum(camera_centers(e) for e in window), 3)
    final = torch.from_numpy(np.load(tmp_path / "averaged" / "poses_final.npy")).double()
    torch.testing.assert_close(final, expected, rtol=0, atol=1e-6)
    torch.testing.assert_close(estimates[12], final, rtol=0, atol=1e-6)  # the last record's poses are the mean
    assert (final - last.current_viewmats().double()).abs().max() > 1e-5


def test_the_pose_lr_warms_up_at_the_start_of_every_rounds_pose_window():
    config = load_preset("quick", iters=80, rounds=2, lr={"pose_warmup": 4})
    schedule, plain = Schedule(config), Schedule(load_preset("quick", iters=80, rounds=2, lr={"pose_warmup": 0}))
    for window_start in (10, 50):  # a quarter into each round of 40
        ramp = [schedule.at(window_start + k).pose_lr / plain.at(window_start + k).pose_lr for k in range(6)]
        assert ramp == pytest.approx([0.25, 0.5, 0.75, 1.0, 1.0, 1.0])
    with pytest.raises(WarpbagsError, match="lr.pose_warmup must be >= 0"):
        load_preset("quick", lr={"pose_warmup": -1})


def test_the_repair_stage_keeps_the_coarse_stages_real_view_loss_and_warms_its_pose_lr_up():
    """The repair stage's poses keep moving from the real views: it dropped the silhouette terms that hold them (a
    tiny run's cameras drifted 2.9 -> 5.5 deg in 20 repair iterations) and took full pose-lr steps from Adam's
    reset moments. Now its real-view loss is the coarse stage's last (silhouettes as they ended, depth off) and the
    pose lr ramps up over its first `lr.pose_warmup` steps, as at every round's window."""
    repair = {"iters": 10}
    config = load_preset("quick", iters=80, rounds=2, lr={"pose_warmup": 4}, repair=repair)
    schedule = Schedule(config)
    plain = Schedule(load_preset("quick", iters=80, rounds=2, lr={"pose_warmup": 0}, repair=repair))
    last_coarse, first_repair = schedule.at(79), schedule.at(80)
    assert first_repair.silhouette and last_coarse.silhouette and not first_repair.depth
    ramp = [schedule.at(80 + k).pose_lr / plain.at(80 + k).pose_lr for k in range(6)]
    assert ramp == pytest.approx([0.25, 0.5, 0.75, 1.0, 1.0, 1.0])
    # silhouette terms switched off within each round stay off in the repair stage, on where they lasted the round
    for until, expected in ((10, False), (40, True)):
        assert Schedule(load_preset("quick", iters=80, rounds=2, silhouette_until=until, repair=repair)
                        ).at(85).silhouette is expected


def test_the_pose_lr_decays_exponentially_to_its_final_value_over_each_rounds_window():
    """`lr.pose_final` is documented as the lr at the end of each round's pose window, reached by an exponential
    decay restarted every round. Nothing checked the decay's end or its shape: measured over window length instead of
    length - 1 the last step stopped short of `pose_final` (reviewer's mutant MA), and without the decay every step
    took `lr.pose` (MB). Rounds of 36 with windows of 27 iterations: 9-35 (a quarter in) and 36-62 (the first three
    quarters); the warm-up (4 steps) is over at the checked iterations."""
    config = load_preset("quick", iters=72, rounds=2, pose_round_windows=((0.25, 1.0), (0.0, 0.75)),
                         lr={"pose": 1e-2, "pose_final": 4e-4, "pose_warmup": 4})
    schedule = Schedule(config)
    assert [schedule.pose_window(i) for i in (9, 36)] == [(9, 36), (36, 63)]
    for start, end in ((9, 36), (36, 63)):
        assert schedule.at(start).pose_lr == pytest.approx(config.lr.pose / 4, rel=1e-12)  # the ramp's first step
        assert schedule.at(end - 1).pose_lr == pytest.approx(config.lr.pose_final, rel=1e-12)
        halfway = start + (end - start - 1) // 2
        assert schedule.at(halfway).pose_lr == pytest.approx(math.sqrt(config.lr.pose * config.lr.pose_final),
                                                             rel=1e-12)
        lrs = [schedule.at(i).pose_lr for i in range(start + 4, end)]  # after the ramp: a falling geometric series
        assert all(later < earlier for earlier, later in zip(lrs, lrs[1:]))
        assert [later / earlier for earlier, later in zip(lrs, lrs[1:])] == pytest.approx(
            [(config.lr.pose_final / config.lr.pose) ** (1 / (end - start - 1))] * (len(lrs) - 1), rel=1e-9)


def test_the_sh_degree_restarts_at_every_rounds_start_and_climbs_within_it():
    """Each round's fresh Gaussians start at SH degree 0 and gain a degree every `sh_degree_every` iterations of the
    round. Counted from the start of training (reviewer's mutant MH), a later round's fresh Gaussians started at a
    high degree; the existing checks (a one-round run, the last round's final degree) passed."""
    config = load_preset("quick", iters=60, rounds=3, sh_degree=3, sh_degree_every=4)
    schedule = Schedule(config)
    for round_start in (0, 20, 40):
        degrees = [schedule.at(round_start + k).sh_degree for k in range(20)]
        assert degrees == [min(3, k // 4) for k in range(20)], (round_start, degrees)
        assert schedule.at(round_start).round_iteration == 0
    repaired = Schedule(load_preset("quick", iters=60, rounds=3, sh_degree=3, sh_degree_every=4, repair={"iters": 5}))
    assert [repaired.at(i).sh_degree for i in (40, 60, 64)] == [0, 3, 3]  # the repair stage trains the full degree


def test_shares_of_a_round_count_the_iterations_their_decimal_value_says():
    """A share times a length is rounded up to whole iterations; the float product overshoots (0.55 * 100 is
    55.00000000000001) and the plain `math.ceil` of it took one iteration too many: a (0.55, 1.0) window of a
    100-iteration round started at 56, (0.28, 0.56) of 200 was (57, 113), and `camera.average_share` 0.07 of a
    100-step window averaged 8 estimates."""
    def window(iters, share):
        return Schedule(load_preset("quick", iters=iters, rounds=1, pose_opt_start=0, pose_round_window=share)
                        ).pose_window(0)

    assert window(100, (0.55, 1.0)) == (55, 100)
    assert window(200, (0.28, 0.56)) == (56, 112)
    assert window(100, (0.25, 0.5)) == (25, 50) and window(10, (0.31, 0.34)) == (4, 4)  # shares still round up
    schedule = Schedule(load_preset("quick", iters=100, rounds=1, pose_opt_start=0, pose_round_window=(0.0, 1.0),
                                    camera={"average_share": 0.07}))
    assert [i for i in range(100) if schedule.at(i).pose_average] == list(range(93, 100))


def test_the_pose_lr_warms_up_from_pose_opt_start_where_it_falls_inside_a_window():
    """The warm-up ramps the pose lr over the first `lr.pose_warmup` steps the poses take. With `pose_opt_start`
    inside the repair stage (poses still at the coarse stage's end), the ramp was counted from the repair stage's
    first iteration, so the first step the poses took was already at the full lr (6/4 of the ramp, clamped to 1).
    Inside a coarse round's window the ramp starts at `pose_opt_start` too (the window itself starts there)."""
    config = load_preset("quick", iters=80, rounds=2, pose_opt_start=20, lr={"pose_warmup": 4})
    schedule = Schedule(config)  # round 0's window (a quarter in: 10) starts at pose_opt_start
    assert [i for i in range(40) if schedule.poses_move(i)][0] == 20
    assert [schedule.at(20 + k).pose_lr / exponential_lr(config.lr.pose, config.lr.pose_final, k / 19)
            for k in range(6)] == pytest.approx([0.25, 0.5, 0.75, 1.0, 1.0, 1.0])
    # pose_opt_start in the repair stage (coarse stage 40, repair stage 40-59): the poses move from 45
    config = load_preset("quick", iters=40, rounds=2, pose_opt_start=45, lr={"pose_warmup": 4}, repair={"iters": 20})
    schedule = Schedule(config)
    assert [i for i in range(60) if schedule.poses_move(i)] == list(range(45, 60))
    assert [schedule.at(45 + k).pose_lr / config.lr.pose_final for k in range(6)] == pytest.approx(
        [0.25, 0.5, 0.75, 1.0, 1.0, 1.0])


def test_lbfgs_rounds_solve_the_poses_every_few_iterations_instead_of_adam_steps():
    schedule = Schedule(load_preset("quick", iters=40, rounds=2, camera={"lbfgs_from_round": 1, "lbfgs_every": 4}))
    steps = [schedule.at(i) for i in range(40)]
    assert [i for i, s in enumerate(steps) if s.pose_active] == list(range(5, 20))  # Adam in round 0's window
    assert [i for i, s in enumerate(steps) if s.pose_solve] == [27, 31, 35, 39]  # solves in round 1's window
    assert not any(s.pose_solve for s in steps[:20]) and not any(s.pose_active for s in steps[20:])
    assert not any(s.pose_solve for s in map(Schedule(load_preset("quick", iters=40, rounds=2)).at, range(40)))
    # a window shorter than lbfgs_every still ends with a solve (round 1's window: iterations 25-39)
    longer = Schedule(load_preset("quick", iters=40, rounds=2, camera={"lbfgs_from_round": 1, "lbfgs_every": 100}))
    assert [i for i in range(40) if longer.at(i).pose_solve] == [39]
    with pytest.raises(WarpbagsError, match="camera.lbfgs_every"):
        load_preset("quick", camera={"lbfgs_every": 0})


def test_a_pose_solve_moves_every_camera_and_no_adam_step_does(scene_dir, tmp_path):
    """With L-BFGS rounds the cameras keep their poses between solves (no Adam step, no moments) and a solve lowers
    the loss of every view against the Gaussians it holds still."""
    trainer = make_trainer(scene_dir, tmp_path, iters=20, rounds=1, pose_opt_start=0, rot_noise_deg=5.0,
                           trans_noise=0.1, camera={"lbfgs_from_round": 0, "lbfgs_every": 10, "lbfgs_iters": 5})
    views = torch.arange(trainer.num_cameras)
    trainer.train(stop_at=9)
    before = trainer.current_viewmats()
    assert not trainer.cameras.optimizer.state  # no Adam step was taken
    trainer.train(stop_at=10)  # iteration 9: a step of the Gaussians, then a solve against them
    after = trainer.current_viewmats()
    moved = (after - before).abs().amax(dim=(1, 2))
    assert (moved > 1e-4).all(), moved
    settings = trainer.schedule.at(9)
    assert trainer.model.loss(views, after, settings)[0].item() < trainer.model.loss(views, before, settings)[0].item()
    trainer.train(stop_at=15)
    assert torch.equal(trainer.current_viewmats(), after)


def test_the_orbit_is_held_until_its_round():
    config = load_preset("quick", iters=30, rounds=3, camera={"orbit_from_round": 2}, repair={"iters": 5})
    schedule = Schedule(config)
    assert [schedule.at(i).orbit_free for i in (0, 9, 10, 19, 20, 29, 30, 34)] == [False] * 4 + [True] * 4
    assert all(Schedule(load_preset("quick")).at(i).orbit_free for i in range(0, 600, 50))
    with pytest.raises(WarpbagsError, match="object parameterization"):
        load_preset("quick", camera={"parameterization": "camera", "orbit_from_round": 1})
    with pytest.raises(WarpbagsError, match="orbit_from_round must be >= 0"):
        load_preset("quick", camera={"orbit_from_round": -1})


def test_a_run_holds_the_orbit_until_its_round_and_resumes_with_its_start(scene_dir, tmp_path):
    trainer = make_trainer(scene_dir, tmp_path, iters=4, rounds=2, pose_opt_start=0, rot_noise_deg=5.0,
                           camera={"orbit_from_round": 1})
    trainer.train(stop_at=2)
    assert not trainer.cameras.orbit_free and torch.all(trainer.cameras.params()[:, :2] == 0)
    trainer.train()
    assert trainer.cameras.orbit_free
    resumed = make_trainer(scene_dir, tmp_path, iters=4, rounds=2, pose_opt_start=0, rot_noise_deg=5.0,
                           camera={"orbit_from_round": 1})
    resumed.resume()
    torch.testing.assert_close(resumed.viewmats_start, trainer.viewmats_start, rtol=0, atol=0)
    torch.testing.assert_close(resumed.current_viewmats(), trainer.current_viewmats(), rtol=0, atol=0)


def test_cli_without_a_terminal_prints_compact_lines_and_no_warp_driver_warning(scene_dir, tmp_path):
    import subprocess
    import sys

    out = tmp_path / "run"
    command = [sys.executable, "-c", "from warpbags.cli.main import app; app()", "train", str(scene_dir), "--iters",
               "4", "--log-every", "2", "--max-image-size", "32", "--out", str(out), "--set", "init_points=300",
               "--set", "hull_resolution=16", "--rounds", "1"]
    result = subprocess.run(command, capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, result.stderr
    lines = [line for line in result.stdout.splitlines() if line.startswith("iter ")]
    assert [line.split()[1] for line in lines] == ["2/4", "4/4"], result.stdout
    assert all("loss" in line and "rot" in line and "s/step" in line and "eta" in line for line in lines)
    assert "CUDA driver" not in result.stderr + result.stdout and "Warp 1." not in result.stdout
    assert "Module " not in result.stdout + result.stderr  # no module-load lines either (devices.init_warp_quietly)
    again = [str(tmp_path / "verbose") if argument == str(out) else argument for argument in command[3:]]
    verbose = subprocess.run([*command[:3], "--verbose", *again], capture_output=True, text=True, timeout=600)
    assert verbose.returncode == 0 and "Module " in verbose.stdout + verbose.stderr, verbose.stderr


def test_configs_of_older_runs_still_load():
    # Runs written before the camera group held the gauge at the top level.
    assert TrainConfig.from_dict({"fix_first_camera": True, "iters": 7}).camera.fix_first_camera is True
    assert TrainConfig.from_dict({"iters": 7}).camera.fix_first_camera is False


def test_the_round_anchor_leaves_the_first_round_free():
    config = load_preset("quick", iters=30, rounds=3, camera={"round_anchor": 0.5}, repair={"iters": 5})
    schedule = Schedule(config)
    assert [schedule.at(i).pose_anchor for i in (0, 9, 10, 29, 30, 34)] == [0.0, 0.0, 0.5, 0.5, 0.5, 0.5]
    assert all(Schedule(load_preset("quick")).at(i).pose_anchor == 0.0 for i in range(0, 600, 50))
    with pytest.raises(WarpbagsError, match="round_anchor must be >= 0"):
        load_preset("quick", camera={"round_anchor": -1.0})


def test_continue_from_takes_the_other_models_extent_for_its_densification_too():
    """The extent sets the position lr (the model's) and the densification thresholds (its strategy's): a model
    that goes on from another takes both, or a leave-one-out fit would densify by its own scene's size."""
    from warpbags.init import initial_gaussians
    from warpbags.model import GaussianModel

    def params():
        points = torch.rand(20, 3, generator=torch.Generator().manual_seed(0))
        return {name: torch.nn.Parameter(value) for name, value in initial_gaussians(points, points, 0).items()}

    config, views = load_preset("quick"), types.SimpleNamespace(device=torch.device("cpu"))  # all it reads of them
    model = GaussianModel(config, views, params(), 1.0, torch.Generator())
    model.continue_from(GaussianModel(config, views, params(), 3.0, torch.Generator()))
    assert model.scene_extent == model.strategy.scene_extent == 3.0


def test_a_runs_results_end_with_gaussians_ply_which_marks_it_finished(tmp_path, monkeypatch):
    """`latest_run` takes a run holding gaussians.ply for a finished one: written before poses_final.npy, a failure
    between the two (a full disk, a kill) left a run that eval and export took and refused."""
    from warpbags.run_folder import RunFolder

    folder = RunFolder(tmp_path / "run")
    folder.path.mkdir()

    def full_disk(*args, **kwargs):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(run_folder.np, "save", full_disk)
    params = {"means": torch.zeros(2, 3), "quats": torch.tensor([[1.0, 0, 0, 0]] * 2), "scales": torch.zeros(2, 3),
              "opacities": torch.zeros(2), "sh0": torch.zeros(2, 1, 3)}
    with pytest.raises(OSError):
        folder.write_results(params, torch.eye(4).repeat(2, 1, 1))
    assert not (folder.path / "gaussians.ply").exists()


def test_a_checkpoint_write_cut_short_is_not_the_latest_checkpoint(tmp_path):
    """A SIGKILL during `atomic_output` leaves checkpoint_N.tmp.pt, which sorts after checkpoint_N.pt: resuming from
    it would fail, and a new run would take the folder for a run to --resume."""
    from warpbags.run_folder import RunFolder

    folder = RunFolder(tmp_path / "run")
    folder.checkpoints.mkdir(parents=True)
    assert not folder.has_checkpoint()
    (folder.checkpoints / "checkpoint_000500.tmp.pt").write_bytes(b"cut")
    assert not folder.has_checkpoint()
    (folder.checkpoints / "notes.txt").write_text("")
    assert folder.holds_unfinished_start() is False  # a file it does not know
    (folder.checkpoints / "notes.txt").unlink()
    (folder.checkpoints / "checkpoint_000500.tmp.pt").unlink()
    (folder.path / "config.json").write_text("{}")
    (folder.path / "config.tmp.json").write_text("{")
    assert folder.holds_unfinished_start()
    with pytest.raises(WarpbagsError, match="stopped before its first checkpoint"):
        folder.require_new()
    (folder.checkpoints / "checkpoint_000100.pt").write_bytes(b"")
    (folder.checkpoints / "checkpoint_000200.tmp.pt").write_bytes(b"cut")
    assert folder.latest_checkpoint().name == "checkpoint_000100.pt" and not folder.holds_unfinished_start()


def test_a_run_killed_while_writing_its_first_checkpoint_is_an_unfinished_start(tmp_path):
    """A SIGKILL during the first checkpoint's write leaves the setup files, the log and checkpoint_N.tmp.pt: a run
    stopped before its first checkpoint, which a new run names as such and `remove_unfinished` (a failed start, the
    sweep) clears with the folders made for it."""
    from warpbags.files import missing_folders
    from warpbags.run_folder import RunFolder

    folder = RunFolder(tmp_path / "made" / "run")
    made = missing_folders(folder.path)
    folder.checkpoints.mkdir(parents=True)
    for name in ("config.json", "poses_true.npy", "log.jsonl"):
        (folder.path / name).write_text("")
    (folder.checkpoints / "checkpoint_000100.tmp.pt").write_bytes(b"cut")
    assert folder.holds_unfinished_start()
    with pytest.raises(WarpbagsError, match="stopped before its first checkpoint"):
        folder.require_new()
    folder.remove_unfinished(made)
    assert not (tmp_path / "made").exists()


def test_a_checkpoint_write_cut_short_is_not_kept_in_place_of_a_checkpoint(tmp_path):
    """Saving keeps the newest `CHECKPOINTS_KEPT` checkpoints written in full; the temporary of an earlier write
    cut short (it sorts after the checkpoints) is removed, not counted among them."""
    from warpbags.run_folder import CHECKPOINT_KEYS, CHECKPOINTS_KEPT, RunFolder

    folder = RunFolder(tmp_path)
    folder.checkpoints.mkdir()
    (folder.checkpoints / "checkpoint_000900.tmp.pt").write_bytes(b"cut")
    for iteration in range(1, CHECKPOINTS_KEPT + 2):
        folder.save_checkpoint({**dict.fromkeys(CHECKPOINT_KEYS), "iteration": iteration, "repair": None})
    assert sorted(path.name for path in folder.checkpoints.iterdir()) == [
        f"checkpoint_{iteration:06d}.pt" for iteration in range(2, CHECKPOINTS_KEPT + 2)]


def test_checkpoints_past_a_million_iterations_are_kept_and_resumed_by_iteration(tmp_path):
    """Checkpoint names are zero-padded to six digits, so from iteration 1000000 on they no longer sort as text in
    the order of their iterations: saving 999998-1000001 deleted checkpoint_1000000 (it sorted first) and named
    checkpoint_999999 the latest, from which a resume would train 2 iterations again. A stray file named like a
    checkpoint (checkpoint_notes.pt) is no checkpoint of an iteration and breaks nothing."""
    from warpbags.run_folder import CHECKPOINT_KEYS, CHECKPOINTS_KEPT, RunFolder

    folder = RunFolder(tmp_path)
    saved = [folder.save_checkpoint({**dict.fromkeys(CHECKPOINT_KEYS), "iteration": iteration, "repair": None})
             for iteration in (999998, 999999, 1000000, 1000001)]
    assert [path.name for path in saved] == ["checkpoint_999998.pt", "checkpoint_999999.pt", "checkpoint_1000000.pt",
                                             "checkpoint_1000001.pt"]
    assert CHECKPOINTS_KEPT == 3
    assert sorted(path.name for path in folder.checkpoints.iterdir()) == [
        "checkpoint_1000000.pt", "checkpoint_1000001.pt", "checkpoint_999999.pt"]
    assert folder.latest_checkpoint().name == "checkpoint_1000001.pt"
    assert folder.load_checkpoint(folder.latest_checkpoint(), "cpu")["iteration"] == 1000001
    (folder.checkpoints / "checkpoint_notes.pt").write_text("not a checkpoint")
    assert folder.has_checkpoint() and folder.latest_checkpoint().name == "checkpoint_1000001.pt"
    folder.save_checkpoint({**dict.fromkeys(CHECKPOINT_KEYS), "iteration": 1000002, "repair": None})
    assert sorted(path.name for path in folder.checkpoints.glob("checkpoint_1*.pt")) == [
        "checkpoint_1000000.pt", "checkpoint_1000001.pt", "checkpoint_1000002.pt"]
    assert folder.latest_checkpoint().name == "checkpoint_1000002.pt"
    assert (folder.checkpoints / "checkpoint_notes.pt").read_text() == "not a checkpoint"  # a user's file is kept


def test_cutting_back_a_log_that_is_not_text_is_one_line(tmp_path):
    from warpbags.run_folder import LOG_FILE, RunFolder

    (tmp_path / LOG_FILE).write_bytes(b'{"iter": 1}\n\xff\xfe\n')
    with pytest.raises(WarpbagsError, match=f"^{re.escape(str(tmp_path / LOG_FILE))}: unreadable \\("):
        RunFolder(tmp_path).truncate(1, torch.eye(4)[None])


def test_no_coarse_round_densifies_at_its_last_iteration(scene_dir, tmp_path):
    """The quick preset densifies every 50 steps of a round up to its 200th, the round's last: the saved model held
    clones and split children that no step had trained (held-out PSNR 20.01 -> 19.58 on the 64 px synthetic scene),
    and the turn search picked its worst-fit camera from an earlier round's model that held them."""
    trainer = make_trainer(scene_dir, tmp_path, iters=40, rounds=2,
                           densify={"start": 10, "stop": 21, "every": 10, "grad_threshold": 1e-9})
    records, counts = [], []
    for _ in range(40):
        counts.append(len(trainer.model.params["means"]))
        records.append(trainer.train_step())
    assert [record["iter"] for record in records if record.get("cloned", 0) + record.get("split", 0)] == [10, 30]
    assert len(trainer.model.params["means"]) == counts[-1]  # the last step changed no row
    assert [i for i in range(40) if not trainer.schedule.at(i).densify] == [19, 39]


def test_the_blur_shrinks_over_each_round_and_reaches_the_loss_as_does_the_depth_mode(scene_dir, tmp_path):
    """Nothing checked that --blur-px / --blur-until blur anything or that --depth-loss pearson reaches the loss
    (the schedule's blur returning 0, or the depth term called without its mode, passed)."""
    schedule = Schedule(tiny_config(iters=40, rounds=2, blur_sigma_px=2.0, blur_until=10))
    assert [schedule.at(i).blur_sigma for i in (0, 5, 10, 19, 20, 25, 39)] == pytest.approx([2, 1, 0, 0, 2, 1, 0])
    trainers = {mode: make_trainer(scene_dir, tmp_path / mode, depth_loss=mode) for mode in ("mad", "pearson")}
    views = torch.arange(trainers["mad"].num_cameras)
    settings = trainers["mad"].schedule.at(0)
    assert settings.depth and settings.blur_sigma == 0
    terms = {mode: trainer.model.loss(views, trainer.current_viewmats(), settings)[1]
             for mode, trainer in trainers.items()}
    assert terms["mad"]["depth"] != pytest.approx(terms["pearson"]["depth"], rel=1e-3)
    blurred = trainers["mad"].model.loss(views, trainers["mad"].current_viewmats(),
                                         dataclasses.replace(settings, blur_sigma=2.0))[1]
    assert blurred["l1"] < 0.95 * terms["mad"]["l1"]  # blurred renders and targets differ less


def test_an_sh_degree_no_round_reaches_is_said(scene_dir, tmp_path):
    """--set sh_degree=2 on the quick preset (rounds of 200, a degree every 1000 iterations of a round) trained
    degree 0 only, its higher coefficients saved as zeros, without a word."""
    scene = load_scene(scene_dir, name="tiny")
    for every, said in ((1000, True), (5, False)):
        notes = []
        config = tiny_config(iters=40, rounds=2, sh_degree=2, sh_degree_every=every)
        Trainer(training_scene(scene, config), config, tmp_path / str(every), log=notes.append)
        assert Schedule(config).final_sh_degree() == (0 if said else 2)
        assert any("sh_degree 2 is reached after" in note and "up to degree 0" in note for note in notes) is said


def test_a_sigterm_while_a_new_run_starts_removes_its_folder(scene_dir, tmp_path, monkeypatch):
    """SIGTERM (kill, a job scheduler) during the start procedures ended the process at once: the claim on the
    folder stayed, and the same --out was refused as "another run is starting". It now stops the start as Ctrl-C
    does (exit 143), and the folder the run made is removed."""
    def killed_while_starting(*args, **kwargs):
        os.kill(os.getpid(), signal.SIGTERM)
        raise AssertionError("SIGTERM did not stop the start")

    monkeypatch.setattr(trainer_module, "starting_poses", killed_while_starting)
    out = tmp_path / "made" / "run"
    # as in a fresh process: a handler an earlier test left (Ray's) would take the signal instead
    previous = signal.signal(signal.SIGTERM, signal.SIG_DFL)
    try:
        result = runner.invoke(app, ["train", str(scene_dir), "--iters", "4", "--set", "init_points=300",
                                     "--set", "hull_resolution=24", "--out", str(out)])
        assert signal.getsignal(signal.SIGTERM) == signal.SIG_DFL  # the handler was the start's only
    finally:
        signal.signal(signal.SIGTERM, previous)
    assert result.exit_code == 143 and "stopped by SIGTERM" in result.output, result.output
    assert not (tmp_path / "made").exists()


def test_the_steps_left_count_the_turn_searchs_trial_rounds_until_it_is_done(scene_dir, tmp_path):
    """The progress bar and the log lines' ETA counted iterations only, while the turn search trains its round once
    per turn more: at its start the ETA said seconds were left of minutes (the quick preset: 600 iterations, 1400
    steps)."""
    trainer = make_trainer(scene_dir, tmp_path, iters=12, rounds=3, pose_opt_start=0,
                           camera={"hypotheses_round": 1, "hypothesis_angles": (10.0, 20.0)})
    turns = 4  # +-10 and +-20 deg about the line of sight
    assert trainer.steps_left() == 12 + turns * 4
    trainer.train(stop_at=2)
    assert trainer.steps_left() == 10 + turns * 4
    trainer.train(stop_at=8)  # past the searched round (iterations 4-7)
    assert trainer.steps_left() == 4
    assert make_trainer(scene_dir, tmp_path / "frozen", iters=12, rounds=3, pose_opt=False,
                        camera={"hypotheses_round": 1}).steps_left() == 12


def test_the_turn_searchs_trial_steps_move_the_progress_display(scene_dir, tmp_path):
    """The turn search reported nothing until it ended (1000 of the quick preset's 1400 steps), so the progress bar
    and the log lines stood still through it: its trial steps are now counted out as they train, in the steps that
    `steps_left` counts, and a run without a terminal prints a line every --log-every of them."""
    trainer = make_trainer(scene_dir, tmp_path / "api", iters=12, rounds=3, pose_opt_start=0,
                           camera={"hypotheses_round": 1, "hypothesis_angles": (10.0, 20.0)})
    done = []
    trainer.train(stop_at=8, on_trial_step=done.append)
    assert done == list(range(5, 4 + 5 * 4 + 1))  # round 1 (iterations 4-7) trained unturned and with 4 turns
    assert 12 + 4 * 4 - trainer.steps_left() == done[-1]  # where the bar goes on from after the search

    result = runner.invoke(app, ["train", str(scene_dir), "--iters", "12", "--rounds", "3", "--log-every", "5",
                                 "--max-image-size", "32", "--set", "init_points=300", "--set", "hull_resolution=16",
                                 "--set", "camera.hypotheses_round=1", "--out", str(tmp_path / "cli")])
    assert result.exit_code == 0, result.output
    trial_lines = [line.split()[3] for line in result.output.splitlines() if line.startswith("turn search: step")]
    assert trial_lines == ["5/28", "10/28", "15/28", "20/28"], result.output


def test_resuming_with_the_runs_views_in_another_order_is_refused(tmp_path):
    """The checkpoint's poses and per-camera state go with the views by position: the run's own views listed in
    another order (a split file rewritten) would resume every camera with another's pose."""
    from warpbags.run_folder import RunFolder

    info = {"image_names": ["a.png", "b.png", "c.png"], "width": 8, "height": 8}
    scene = types.SimpleNamespace(image_names=["a.png", "b.png", "c.png"], width=8, height=8)
    assert RunFolder(tmp_path).view_differences(scene, info) == []
    scene.image_names = ["b.png", "a.png", "c.png"]
    assert RunFolder(tmp_path).view_differences(scene, info) == ["the views are the run's in another order"]


def test_a_run_killed_between_its_coarse_result_and_its_first_checkpoint_is_an_unfinished_start(tmp_path):
    """With a repair stage and --checkpoint-every above --iters, the coarse stage's end writes coarse/ (its setup
    files and results) just before the first checkpoint. A SIGKILL between the two left a folder that a new run
    called "not empty" and a resumed sweep refused, rather than a run stopped before its first checkpoint, which the
    sweep trains again; `remove_unfinished` (a failed start, the sweep) clears coarse/ with the rest."""
    from warpbags.files import missing_folders
    from warpbags.run_folder import SETUP_FILES, RunFolder

    folder = RunFolder(tmp_path / "made" / "run")
    made = missing_folders(folder.path)
    (folder.path / "coarse").mkdir(parents=True)
    for name in (*SETUP_FILES, "log.jsonl"):
        (folder.path / name).write_text("")
    for name in (*SETUP_FILES, "poses_final.npy", "gaussians.tmp.ply"):  # killed while it wrote gaussians.ply
        (folder.path / "coarse" / name).write_text("")
    assert folder.holds_unfinished_start()
    with pytest.raises(WarpbagsError, match="stopped before its first checkpoint"):
        folder.require_new()
    (folder.path / "coarse" / "notes.txt").write_text("mine")
    assert not folder.holds_unfinished_start()  # a file no run writes there
    (folder.path / "coarse" / "notes.txt").unlink()
    folder.remove_unfinished(made)
    assert not (tmp_path / "made").exists()

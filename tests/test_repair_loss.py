"""Repair stage numbers: the pseudo-view loss against the repaired renders, and the 3D-noise statistics."""

from __future__ import annotations

import math
from types import SimpleNamespace

import pytest
import torch

from warpbags.camera_paths import turntable_viewmats
from warpbags.configs.train import load_preset
from warpbags.repair.pairs import NOISY_PARAMETERS, noise_statistics
from warpbags.repair.stage import RepairStage

# As tests/test_repair.py's TINY_REPAIR; the stage here never builds pairs nor fits (its repairer is given).
TINY_REPAIR = dict(iters=16, loo_iters=24, loo_snapshot=16, loo_samples=2, noise_renders=2, fit_steps=30, fit_crop=32,
                   pseudo_views=4, refresh_every=5, samples_kept=2)


def tiny_config(**repair):
    return load_preset("quick", iters=30, rounds=1, pose_opt_start=0, depth_until=10, checkpoint_every=10,
                       init_points=600, hull_resolution=32, render_threads=1, rot_noise_deg=3.0,
                       repair={**TINY_REPAIR, **repair})


class AddingRepairer:
    """A fitted repairer (the `Repairer` protocol) whose repair adds `offset` to every pixel."""

    def __init__(self, offset: float):
        self.offset = offset

    def fit(self, pairs, log) -> dict:
        raise AssertionError("a given repairer is used as it is, not fitted")

    def repair(self, images: torch.Tensor) -> torch.Tensor:
        return images + self.offset

    def state_dict(self) -> dict:
        return {"offset": self.offset}

    def load_state_dict(self, state: dict) -> None:
        self.offset = state["offset"]


def test_the_pseudo_view_loss_is_the_weighted_distance_of_the_render_to_its_repaired_render(tmp_path):
    """RepairStage.loss: GaussianObject's pseudo-view loss is the view's distance weight x (w1 L1 + w2 L2) of the
    render against the repaired render of the last refresh. A model that renders the same image everywhere and a
    repairer that adds 0.25 make it w x (w1 0.25 + w2 0.0625) exactly; one pseudo view makes the pick known, and
    8 training cameras 45 deg apart put it well inside the reach where the weight is below 1."""
    generator = torch.Generator().manual_seed(0)
    image = 0.7 * torch.rand(12, 16, 3, generator=generator)
    base = torch.eye(4)
    base[2, 3] = 4.0
    viewmats = turntable_viewmats(base[None].double(), 8).float()
    model = SimpleNamespace(training_views=SimpleNamespace(device="cpu"),
                            params={"means": 0.3 * torch.randn(50, 3, generator=generator),
                                    "opacities": torch.randn(50, generator=generator)},
                            render_views=lambda cameras: image.expand(len(cameras), -1, -1, -1).clone())
    config = tiny_config(pseudo_views=1, weight_l1=0.7, weight_l2=2.0, weight_lpips=0.0)
    stage = RepairStage(config, tmp_path, model, viewmats, torch.Generator().manual_seed(3),
                        log=lambda message: None, repairer=AddingRepairer(0.25))
    loss, terms = stage.loss(model, viewmats, iteration=config.iters)  # the repair stage's first: a refresh
    torch.testing.assert_close(stage.targets, image[None] + 0.25)  # the repaired renders are the targets
    weight = stage.weights[0].item()
    assert 0.05 < weight < 0.9, weight
    assert terms == pytest.approx({"pseudo_l1": 0.25, "pseudo_l2": 0.0625})
    assert loss.item() == pytest.approx(weight * (0.7 * 0.25 + 2.0 * 0.0625), rel=1e-5)


def test_the_noise_statistics_are_the_per_channel_mean_and_std_of_unseen_minus_seen_averaged_over_models():
    """noise_statistics: the 3D noise follows how a leave-one-out model's Gaussians differ from those of a copy that
    saw the view, unseen - seen, per channel over the Gaussians of each model (the std unbiased, as torch's), then
    averaged over the models: an unseen copy that sits +1 further along x on average gives noise of mean +1 in x.
    Two models of 2 and 3 Gaussians whose differences are known."""
    generator = torch.Generator().manual_seed(0)
    differences = [
        {"means": torch.tensor([[1.0, 0.0, -2.0], [3.0, 0.0, -4.0]]), "opacities": torch.tensor([0.5, 1.5])},
        {"means": torch.tensor([[0.0, 1.0, -1.0], [0.0, 3.0, -1.0], [0.0, 5.0, -1.0]]),
         "opacities": torch.tensor([-1.0, -1.0, 2.0])}]
    models = []
    for difference in differences:
        difference["scales"] = -difference["means"]
        difference["quats"] = torch.cat([difference["means"], torch.ones(len(difference["means"]), 1)], dim=1)
        seen = {name: torch.randn(value.shape, generator=generator) for name, value in difference.items()}
        models.append(({name: seen[name] + difference[name] for name in seen}, seen))
    noise = noise_statistics([{name: unseen[name] - seen[name] for name in NOISY_PARAMETERS}
                              for unseen, seen in models])  # as `leave_one_out` returns them
    root2 = math.sqrt(2.0)
    expected_mean = {"means": [1.0, 1.5, -2.0], "scales": [-1.0, -1.5, 2.0], "quats": [1.0, 1.5, -2.0, 1.0],
                     "opacities": 0.5}
    expected_std = {"means": [root2 / 2, 1.0, root2 / 2], "scales": [root2 / 2, 1.0, root2 / 2],
                    "quats": [root2 / 2, 1.0, root2 / 2, 0.0], "opacities": (math.sqrt(0.5) + math.sqrt(3.0)) / 2}
    assert sorted(noise.mean) == sorted(noise.std) == sorted(NOISY_PARAMETERS)
    for name in NOISY_PARAMETERS:
        torch.testing.assert_close(noise.mean[name], torch.tensor(expected_mean[name]), atol=1e-5, rtol=0)
        torch.testing.assert_close(noise.std[name], torch.tensor(expected_std[name]), atol=1e-5, rtol=0)

"""Repair stage: the repair network, 3D noise, pseudo cameras and their loss, the plug-in point, and the stage end to
end."""

from __future__ import annotations

import json
import math
import re
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from typer.testing import CliRunner

from warpbags.cli.main import app
from warpbags.configs.train import RepairConfig, load_preset
from warpbags.data import SyntheticOptions, ensure_synthetic_scene, load_scene
from warpbags.errors import WarpbagsError
from warpbags.evaluation import evaluate_run, held_out_views
from warpbags.run_folder import load_run
from warpbags.gaussians import render_gaussians, sh_degree_of
from warpbags.blur import gaussian_blur
from warpbags.camera_paths import turntable_viewmats
from warpbags.cameras import camera_centers
from warpbags.repair import RepairPairs, UNetRepairer, make_repairer
from warpbags.repair import pairs as pairs_module
from warpbags.repair.network import PluginRepairer, repairer_factory
from warpbags.repair.pairs import (LEAVE_ONE_OUT, NOISE, NOISY_PARAMETERS, LeaveOneOutFit, NoiseStatistics,
                                   build_pairs, leave_one_out, leave_one_out_config, noise_statistics,
                                   perturbed_gaussians)
from warpbags.repair.stage import RepairStage, distance_weights, pseudo_ratio
from warpbags.model import GaussianModel, TrainingViews
from warpbags.trainer import Trainer, training_scene

TINY = SyntheticOptions(views=16, width=96, height=96)
# A repair stage small enough for a test: 4 leave-one-out models of 24 iterations, 30 fitting steps, 16 repair
# iterations with a refresh every 5.
TINY_REPAIR = dict(iters=16, loo_iters=24, loo_snapshot=16, loo_samples=2, noise_renders=2, fit_steps=30, fit_crop=32,
                   pseudo_views=4, refresh_every=5, samples_kept=2)


@pytest.fixture(scope="module")
def scene_dir(tmp_path_factory):
    return ensure_synthetic_scene(TINY, cache_dir=tmp_path_factory.mktemp("cache"))


def tiny_config(**repair):
    return load_preset("quick", iters=30, rounds=1, pose_opt_start=0, depth_until=10, checkpoint_every=10,
                       init_points=600, hull_resolution=32, render_threads=1, rot_noise_deg=3.0,
                       repair={**TINY_REPAIR, **repair})


def object_images(scene_dir, count=4) -> torch.Tensor:
    scene = load_scene(scene_dir, name="tiny").subset(list(range(count)))
    masks = scene.masks[..., None]
    return scene.images * masks + (1 - masks)


# ------------------------------------------------------------------------------------------------ network
def test_unfitted_repair_network_is_the_identity(scene_dir):
    images = object_images(scene_dir, 2)
    repairer = UNetRepairer(RepairConfig())
    torch.testing.assert_close(repairer.repair(images), images, rtol=0, atol=1e-6)
    odd = images[:, :90, :93]  # sides that are not multiples of 4 are padded and cropped back, in place
    torch.testing.assert_close(repairer.repair(odd), odd, rtol=0, atol=1e-6)


def test_repair_network_learns_to_undo_a_blur(scene_dir):
    targets = object_images(scene_dir)
    corrupted = gaussian_blur(targets, 1.5).clamp(0, 1)
    half = len(targets) // 2
    pairs = RepairPairs(corrupted, targets, [LEAVE_ONE_OUT] * half + [NOISE] * (len(targets) - half),
                        list(range(len(targets))), NoiseStatistics({}, {}))
    repairer = UNetRepairer(RepairConfig(fit_steps=150, fit_crop=48, fit_batch=4), seed=0)
    stats = repairer.fit(pairs, log=lambda message: None)
    # The blur is the same everywhere, so undoing it carries over to the held-out view: the fit keeps going.
    assert stats["steps"] >= 100
    assert min(error for _, error in stats["validation_mse"]) < 0.8 * stats["validation_mse_identity"]
    for kind in (LEAVE_ONE_OUT, NOISE):
        assert stats["l1_repaired"][kind] < 0.8 * stats["l1_identity"][kind], stats


def test_repair_network_fit_stops_where_the_held_out_view_gets_worse(scene_dir):
    # The fitted views are brightened, the held-out (last) view darkened: what the network learns (darken) makes
    # the held-out view worse, so no check beats leaving it alone and the final network stays the identity.
    targets = object_images(scene_dir)
    corrupted = (targets + 0.3).clamp(0, 1)
    corrupted[-1] = (targets[-1] - 0.3).clamp(0, 1)
    pairs = RepairPairs(corrupted, targets, [LEAVE_ONE_OUT] * len(targets), list(range(len(targets))),
                        NoiseStatistics({}, {}))
    repairer = UNetRepairer(RepairConfig(fit_steps=60, fit_crop=48, fit_batch=4), seed=0)
    stats = repairer.fit(pairs, log=lambda message: None)
    assert stats["steps"] == 0
    torch.testing.assert_close(repairer.repair(targets), targets, rtol=0, atol=1e-6)


def test_make_repairer_loads_a_plugin_and_rejects_bad_ones(tmp_path, monkeypatch):
    (tmp_path / "my_repairers.py").write_text(
        "class Passthrough:\n"
        "    def __init__(self, config, seed, device): self.seed = seed\n"
        "    def fit(self, pairs, log): return {}\n"
        "    def repair(self, images): return images\n"
        "    def state_dict(self): return {}\n"
        "    def load_state_dict(self, state): pass\n"
        "def not_a_repairer(config, seed, device): return object()\n"
        "class TakesConfigOnly:\n"
        "    def __init__(self, config): pass\n"
        "def failing(config, seed, device): raise FileNotFoundError('weights.safetensors')\n")
    (tmp_path / "broken_repairers.py").write_text("raise RuntimeError('no GPU: diffusers needs CUDA')\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    assert make_repairer(RepairConfig(repairer="my_repairers:Passthrough"), seed=3).repairer.seed == 3
    assert isinstance(make_repairer(RepairConfig()), UNetRepairer)
    for spec, message in [("my_repairers:not_a_repairer", "lacks"), ("my_repairers:missing", "cannot load"),
                          ("no_such_module:factory", "cannot load"), ("diffusion", "package.module:factory"),
                          ("my_repairers:TakesConfigOnly", r"cannot be called as factory\(config, seed, device\)"),
                          ("my_repairers:failing", r"building it failed \(FileNotFoundError: weights.safetensors\)"),
                          ("broken_repairers:factory", r"cannot load it \(RuntimeError: no GPU: diffusers needs CUDA; "
                                                       r"the module must be installed or on PYTHONPATH\)")]:
        with pytest.raises(WarpbagsError, match=message) as error:
            make_repairer(RepairConfig(repairer=spec))
        assert "\n" not in str(error.value)
    # the signature is checked where a run starts (`repairer_factory`), not after its coarse stage
    with pytest.raises(WarpbagsError, match="cannot be called as factory"):
        repairer_factory("my_repairers:TakesConfigOnly")


@pytest.mark.parametrize("body, message", [
    ("def fit(self, pairs, log): raise RuntimeError('CUDA out of memory in my LoRA')",
     "its fit failed (RuntimeError: CUDA out of memory in my LoRA)"),
    ("def fit(self, pairs, log): return torch.zeros(2)", "its fit returned Tensor, not a dict of statistics"),
    ("def fit(self, pairs, log): return {'loss': torch.zeros(2)}",
     "its fit returned statistics fit.json cannot hold (TypeError: Object of type Tensor is not JSON serializable)"),
    ("def repair(self, images): raise ValueError('bad tile size')", "its repair failed (ValueError: bad tile size)"),
    ("def repair(self, images): return images[:, ::2]",
     "its repair of (2, 8, 8, 3) images on cpu returned (2, 4, 8, 3) torch.float32 on cpu"),
    ("def state_dict(self): raise KeyError('lora')", "its state_dict failed (KeyError: 'lora')"),
])
def test_a_plugin_repairers_failure_is_one_line_naming_it(tmp_path, monkeypatch, body, message):
    """A plug-in's fit, repair or state_dict that raises, or returns what the stage cannot use, came after the coarse
    stage and the leave-one-out pairs as a traceback."""
    methods = {"fit": "def fit(self, pairs, log): return {}", "repair": "def repair(self, images): return images",
               "state_dict": "def state_dict(self): return {}"}
    methods[body.split("(")[0].removeprefix("def ")] = body
    module = tmp_path.name  # one per case: Python imports a module once
    (tmp_path / f"{module}.py").write_text(
        "import torch\nclass Plugin:\n    def __init__(self, config, seed, device): pass\n"
        + "".join(f"    {method}\n" for method in methods.values())
        + "    def load_state_dict(self, state): pass\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    repairer = make_repairer(RepairConfig(repairer=f"{module}:Plugin"))
    images = torch.rand(2, 8, 8, 3)
    pairs = SimpleNamespace()  # these plug-ins do not read it
    with pytest.raises(WarpbagsError) as error:
        repairer.fit(pairs, print)
        repairer.repair(images)
        repairer.state_dict()
    assert str(error.value) == f"--repairer {module}:Plugin: {message}"


@pytest.mark.parametrize("left_out", [0, 2])
def test_a_leave_one_out_model_never_trains_on_the_view_it_leaves_out(scene_dir, monkeypatch, left_out):
    """The leave-one-out pairs show the repairer what a model that never saw a view renders there: the first render
    of the view, and the "unseen" copy whose parameters give the 3D-noise statistics, must come from Gaussians
    initialized and fitted without it; only the "seen" copy takes it back. Fitting the "unseen" model to every
    training view (`others = list(range(views.num_views))` in `leave_one_out`) left the pairs without their
    failures and went unseen: each model's Gaussians are followed here through their initialization, every step's
    sampled views and `continue_from`, and the views each render of the left-out view was fitted to are checked."""
    config = tiny_config(loo_iters=12, loo_snapshot=4, loo_samples=2)  # samples at iterations 4 (pure) and 5 (seen)
    scene = training_scene(load_scene(scene_dir, name="tiny"), config)
    names = scene.image_names
    models, renders = [], []  # every model made; (image names its Gaussians were fitted to, rendered view's name)
    initialized, sample_views = GaussianModel.initialized.__func__, GaussianModel.sample_views
    continue_from, render_views = GaussianModel.continue_from, GaussianModel.render_views

    def initialized_from(cls, config, training_views, *args, **kwargs):
        model = initialized(cls, config, training_views, *args, **kwargs)
        model.fitted_to, model.steps = set(training_views.scene.image_names), 0  # the hull is carved from them
        models.append(model)
        return model

    def sampled(self):
        views = sample_views(self)
        self.fitted_to |= {self.training_views.scene.image_names[view] for view in views.tolist()}
        self.steps += 1
        return views

    def continued(self, other):
        continue_from(self, other)
        self.fitted_to, self.steps = set(other.fitted_to), other.steps  # other's Gaussians, and what made them

    def rendered(self, viewmats, Ks=None, *args, **kwargs):
        (view,) = [i for i, pose in enumerate(scene.viewmats) if torch.allclose(pose.float(), viewmats[0].float(),
                                                                               atol=1e-5)]
        renders.append((set(self.fitted_to), names[view]))
        return render_views(self, viewmats, Ks, *args, **kwargs)

    monkeypatch.setattr(GaussianModel, "initialized", classmethod(initialized_from))
    monkeypatch.setattr(GaussianModel, "sample_views", sampled)
    monkeypatch.setattr(GaussianModel, "continue_from", continued)
    monkeypatch.setattr(GaussianModel, "render_views", rendered)

    coarse = SimpleNamespace(training_views=TrainingViews.of(scene, config, torch.device("cpu")))
    samples, differences = leave_one_out(coarse, scene.viewmats, config, left_out)

    others = set(names) - {names[left_out]}
    assert len(samples) == len(renders) == 2 and all(name == names[left_out] for _, name in renders)
    assert renders[0][0] == others  # the first render: Gaussians fitted to the other views alone
    assert renders[1][0] == set(names)  # the seen copy took the view back (the recording sees it)
    unseen = [model for model in models if model.steps == config.repair.loo_iters and names[left_out] not in
              model.fitted_to]
    assert len(unseen) == 1 and unseen[0].fitted_to == others  # the model the noise statistics compare with
    assert set(differences) and all(torch.isfinite(value).all() for value in differences.values())


# ------------------------------------------------------------------------------------------------ 3D noise
def test_perturbed_gaussians_follow_the_noise_statistics():
    count = 20000
    params = {"means": torch.zeros(count, 3), "scales": torch.zeros(count, 3), "quats": torch.zeros(count, 4),
              "opacities": torch.zeros(count), "sh0": torch.zeros(count, 1, 3)}
    mean = {name: torch.full(params[name].shape[1:], 0.1) for name in NOISY_PARAMETERS}
    std = {name: torch.full(params[name].shape[1:], 0.5) for name in NOISY_PARAMETERS}
    noise = NoiseStatistics(mean, std)
    generator = torch.Generator().manual_seed(0)
    full = perturbed_gaussians(params, noise, clamp_std=0.7, dropout=0.0, generator=generator)
    assert full["means"].mean().item() == pytest.approx(0.1, abs=0.01)
    assert full["means"].std().item() == pytest.approx(0.5, abs=0.01)
    for name in NOISY_PARAMETERS[1:]:  # the others clamped to mean +- 0.7 std, and every one of them perturbed
        assert full[name].mean().item() == pytest.approx(0.1, abs=0.01), name
        assert full[name].min().item() >= 0.1 - 0.35 - 1e-6 and full[name].max().item() <= 0.1 + 0.35 + 1e-6, name
        assert full[name].std().item() > 0.2, name
    assert torch.equal(full["sh0"], params["sh0"])  # colours get no noise
    sparse = perturbed_gaussians(params, noise, clamp_std=0.7, dropout=0.75, generator=generator)
    assert (sparse["means"] != 0).float().mean().item() == pytest.approx(0.25, abs=0.01)
    none = perturbed_gaussians(params, noise, clamp_std=0.7, dropout=1.0, generator=generator)
    assert all(torch.equal(none[name], params[name]) for name in params)


def test_distance_weights_favour_views_away_from_the_training_cameras():
    base = torch.eye(4, dtype=torch.float64)
    base[2, 3] = 4.0
    orbit = turntable_viewmats(base[None], 16)
    train = orbit[::4]  # 4 cameras, 90 degrees apart
    weights = distance_weights(orbit[[0, 1, 2]], train)
    assert weights[0].item() == pytest.approx(0.0, abs=1e-6)  # on a training camera
    assert 0 < weights[1] < weights[2] <= 1  # half-way between two is farthest
    # Unevenly spaced: d_max is 1.2 x the largest distance from a training camera to its second-nearest other.
    train = orbit[[0, 2, 3, 9]]
    centres, pseudo = camera_centers(train), camera_centers(orbit[[1, 5, 6]])
    second_nearest = max(sorted((centres[i] - centres[j]).norm().item() for j in range(4) if j != i)[1]
                         for i in range(4))
    nearest = [min((p - c).norm().item() for c in centres) for p in pseudo]
    expected = [min(1.0, 2 * d / (1.2 * second_nearest)) for d in nearest]
    torch.testing.assert_close(distance_weights(orbit[[1, 5, 6]], train), torch.tensor(expected, dtype=torch.float64))
    assert 0 < min(expected) and max(expected) < 1



def test_the_repair_stage_draws_its_pseudo_cameras_about_the_gaussians(tmp_path):
    """Gaussians and training cameras moved together move the pseudo cameras with them: they are drawn about the
    Gaussians' opacity-weighted centre, which noisy poses leave away from the origin, not about the origin."""
    from conftest import look_at

    generator = torch.Generator().manual_seed(0)
    means = 0.3 * torch.randn(200, 3, generator=generator)
    eyes = [torch.tensor([4 * np.cos(a), 4 * np.sin(a), 1.5], dtype=torch.float32) for a in (0.3, 1.9, 3.6, 5.0)]
    viewmats = torch.stack([look_at(eye, torch.zeros(3)) for eye in eyes])
    shift = torch.tensor([0.5, -0.6, 0.4])
    moved = torch.eye(4)
    moved[:3, 3] = -shift  # the camera of world point x + shift is the camera of x moved by shift

    def pseudo_viewmats(means, viewmats, folder):
        params = {"means": means, "opacities": torch.randn(len(means), generator=torch.Generator().manual_seed(1))}
        model = SimpleNamespace(training_views=SimpleNamespace(device="cpu"), params=params,
                                render_views=lambda cameras: torch.full((len(cameras), 16, 16, 3), 0.5))
        stage = RepairStage(tiny_config(weight_lpips=0.0), folder, model, viewmats, torch.Generator().manual_seed(2),
                            log=lambda message: None, repairer=UNetRepairer(RepairConfig()))
        stage.refresh(model, viewmats, iteration=0)
        return stage.viewmats

    at_origin = pseudo_viewmats(means, viewmats, tmp_path / "a")
    torch.testing.assert_close(pseudo_viewmats(means + shift, viewmats @ moved, tmp_path / "b"), at_origin @ moved,
                               rtol=0, atol=1e-5)
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


# ------------------------------------------------------------------------------------------------ end to end
def make_trainer(scene_dir, out, **repair) -> Trainer:
    config = tiny_config(**repair)
    return Trainer(training_scene(load_scene(scene_dir, name="tiny"), config), config, out, log=lambda message: None)


def test_repair_stage_runs_end_to_end_and_writes_its_samples(scene_dir, tmp_path):
    trainer = make_trainer(scene_dir, tmp_path)
    trainer.write_run_files()
    trainer.train()
    config = trainer.config
    assert trainer.iteration == config.iters + config.repair.iters
    records = [json.loads(line) for line in (tmp_path / "log.jsonl").read_text().splitlines()]
    repair_records = [r for r in records if r["stage"] == "repair"]
    assert len(repair_records) == config.repair.iters
    assert repair_records[0]["pseudo_ratio"] == 1.0 and "pseudo_l1" in repair_records[0]
    assert repair_records[-1]["pseudo_ratio"] == 0.0  # the last 30% train on the real views alone
    assert all(np.isfinite(r["loss"]) for r in repair_records)

    # The leave-one-out fits are models without a run folder: repair/ holds the stage's own files only.
    assert sorted(path.name for path in (tmp_path / "repair").iterdir()) == ["fit.json", "pairs.pt", "repairer.pt",
                                                                             "samples"]
    fit = json.loads((tmp_path / "repair" / "fit.json").read_text())
    assert fit["pairs"] == {LEAVE_ONE_OUT: 4 * 2, NOISE: 4 * 2}
    pairs = RepairPairs.load(tmp_path / "repair" / "pairs.pt")
    assert pairs.corrupted.shape == pairs.targets.shape == (16, 96, 96, 3)
    # A leave-one-out render of a view is worse than the coarse model's render of it, which saw the view.
    loo = [i for i, kind in enumerate(pairs.kinds) if kind == LEAVE_ONE_OUT]
    views = [pairs.views[i] for i in loo]
    coarse = load_run(tmp_path / "coarse")
    trained = trainer.model.training_views
    coarse_renders, _, _ = render_gaussians(coarse.params, coarse.poses_final[views].float(), trained.Ks[views],
                                            trainer.scene.width, trainer.scene.height,
                                            sh_degree=sh_degree_of(coarse.params), backgrounds=torch.ones(len(views), 3))
    loo_errors = (pairs.corrupted[loo] - pairs.targets[loo]).abs().mean(dim=(1, 2, 3))
    coarse_errors = (coarse_renders.clamp(0, 1) - pairs.targets[loo]).abs().mean(dim=(1, 2, 3))
    assert (loo_errors > coarse_errors).all(), (loo_errors, coarse_errors)
    assert (tmp_path / "repair" / "samples" / "pairs.png").is_file()
    pseudo_samples = sorted((tmp_path / "repair" / "samples").glob("pseudo_*.png"))
    assert [p.name for p in pseudo_samples] == ["pseudo_000035.png", "pseudo_000040.png"]  # refreshes, newest 2 kept

    for folder in (tmp_path / "coarse", tmp_path):  # both results evaluate as runs, and show the object
        assert (folder / "gaussians.ply").is_file() and (folder / "poses_final.npy").is_file()
        report = evaluate_run(folder, refine_iters=0, log=lambda message: None)
        test = held_out_views(load_run(folder))
        masks = test.masks[..., None]
        blank_psnr = (-10 * torch.log10((1 - (test.images * masks + 1 - masks)).square().mean(dim=(1, 2, 3)))).mean()
        assert len(report["images"]["per_view"]) == report["test_views"] == len(test.image_names)
        assert report["images"]["mean"]["psnr"] > blank_psnr.item() + 1.0  # better than a blank white render
    coarse_poses, final_poses = np.load(tmp_path / "coarse" / "poses_final.npy"), np.load(tmp_path / "poses_final.npy")
    assert not np.allclose(coarse_poses, final_poses)  # the poses kept optimizing through the repair stage


def test_resumed_repair_stage_names_an_unreadable_saved_file(tmp_path):
    """A resumed run reads repair/pairs.pt and repair/repairer.pt back with torch.load: a file cut short, of another
    kind or of another layout was a RuntimeError, UnpicklingError or TypeError traceback. It is one line naming the
    file, as an unreadable checkpoint is. The stage keeps the RepairConfig as `repair` (`config` was the name of the
    TrainConfig its constructor takes)."""
    config = tiny_config()
    folder = tmp_path / "repair"
    folder.mkdir()
    pairs = RepairPairs(torch.zeros(2, 8, 8, 3), torch.ones(2, 8, 8, 3), [LEAVE_ONE_OUT, NOISE], [0, 1],
                        NoiseStatistics({}, {}))
    state = make_repairer(config.repair).state_dict()
    coarse = SimpleNamespace(training_views=torch.zeros(0))  # a resumed stage reads only where it trains
    messages = []

    def resume() -> RepairStage:
        return RepairStage(config, folder, coarse, torch.eye(4)[None], torch.Generator(), log=messages.append)

    pairs.save(folder / "pairs.pt")
    torch.save(state, folder / "repairer.pt")
    stage = resume()
    assert messages[:2] == [f"repair: loaded 2 pairs from {folder}",
                            f"repair: loaded the fitted repairer from {folder}"]
    assert stage.repair == config.repair and not hasattr(stage, "config")

    saved = (folder / "repairer.pt").read_bytes()
    (folder / "repairer.pt").write_bytes(saved[:len(saved) // 2])  # cut short
    with pytest.raises(WarpbagsError, match=f"^{re.escape(str(folder / 'repairer.pt'))}: unreadable \\(") as error:
        resume()
    torch.save({"weights": torch.zeros(1)}, folder / "repairer.pt")  # a torch file of another layout
    with pytest.raises(WarpbagsError, match=f"^{re.escape(str(folder / 'repairer.pt'))}: unreadable \\("):
        resume()
    (folder / "repairer.pt").write_bytes(saved)
    for content in (b"not a torch file", None):  # bytes of another kind; a torch file of another layout
        if content is None:
            torch.save({"images": torch.zeros(1)}, folder / "pairs.pt")
        else:
            (folder / "pairs.pt").write_bytes(content)
        with pytest.raises(WarpbagsError, match=f"^{re.escape(str(folder / 'pairs.pt'))}: unreadable \\(") as error:
            resume()
        assert "\n" not in str(error.value)


def test_a_stop_during_the_repairer_fit_stops_it_and_the_saved_pairs_are_reused(tmp_path):
    """Ctrl-C and SIGTERM were only flagged during the repairer's fit (minutes at its 400 steps), and a run stopped
    there had pairs.pt but no repairer.pt, so its resume built the leave-one-out pairs again."""
    config = tiny_config()
    folder = tmp_path / "repair"
    folder.mkdir()
    g = torch.Generator().manual_seed(0)
    pairs = RepairPairs(torch.rand(4, 16, 16, 3, generator=g), torch.rand(4, 16, 16, 3, generator=g),
                        [LEAVE_ONE_OUT, NOISE, LEAVE_ONE_OUT, NOISE], [0, 0, 1, 1], NoiseStatistics({}, {}))
    pairs.save(folder / "pairs.pt")
    coarse = SimpleNamespace(training_views=torch.zeros(0))  # no model: building pairs would fail
    messages, checks = [], []

    def should_stop() -> bool:
        checks.append(True)
        return len(checks) > 3

    with pytest.raises(KeyboardInterrupt):
        RepairStage(config, folder, coarse, torch.eye(4)[None], torch.Generator(), log=messages.append,
                    should_stop=should_stop)
    assert messages == [f"repair: loaded 4 pairs from {folder}"] and len(checks) == 4
    assert not (folder / "repairer.pt").exists()


def test_the_fitted_repairer_is_saved_last_so_a_resume_finishes_what_a_failed_fit_left(tmp_path):
    """repairer.pt, which a resumed run takes for a finished fit, was written before fit.json and samples/pairs.png:
    a run whose fit.json could not be written resumed without ever writing either."""
    config = tiny_config(fit_steps=2)
    folder = tmp_path / "repair"
    folder.mkdir()
    g = torch.Generator().manual_seed(0)
    RepairPairs(torch.rand(4, 16, 16, 3, generator=g), torch.rand(4, 16, 16, 3, generator=g),
                [LEAVE_ONE_OUT, NOISE, LEAVE_ONE_OUT, NOISE], [0, 0, 1, 1],
                NoiseStatistics({}, {})).save(folder / "pairs.pt")
    (folder / "fit.json").mkdir()  # fit.json cannot be written (as on a full disk)
    coarse = SimpleNamespace(training_views=torch.zeros(0))

    def start() -> RepairStage:
        return RepairStage(config, folder, coarse, torch.eye(4)[None], torch.Generator(), log=lambda message: None)

    with pytest.raises(OSError):
        start()
    assert not (folder / "repairer.pt").exists()
    (folder / "fit.json").rmdir()
    start()
    assert all((folder / name).is_file() for name in ("fit.json", "samples/pairs.png", "repairer.pt"))


def test_repair_stage_resumes_to_the_same_result(scene_dir, tmp_path):
    straight = make_trainer(scene_dir, tmp_path / "straight")
    straight.train()
    interrupted = make_trainer(scene_dir, tmp_path / "resumed")
    interrupted.train(stop_at=interrupted.config.iters + 7)
    messages = []
    resumed = Trainer(interrupted.scene, interrupted.config, tmp_path / "resumed", log=messages.append)
    assert resumed.resume()
    resumed.train()
    assert any("loaded" in message for message in messages)  # pairs and repairer were not rebuilt
    for name in straight.params:
        torch.testing.assert_close(resumed.params[name], straight.params[name], rtol=0, atol=0)
    torch.testing.assert_close(resumed.current_viewmats(), straight.current_viewmats(), rtol=0, atol=0)


def test_cli_trains_with_repair_and_rejects_contradictions(scene_dir, tmp_path):
    runner = CliRunner()
    out = tmp_path / "run"
    settings = [f"--set=repair.{key}={json.dumps(value)}" for key, value in TINY_REPAIR.items() if key != "iters"]
    common = [str(scene_dir), "--iters", "20", "--rounds", "1", "--set", "init_points=500", "--set",
              "hull_resolution=32", "--set", "render_threads=1", *settings]
    result = runner.invoke(app, ["train", *common, "--repair-iters", "6", "--out", str(out)])
    assert result.exit_code == 0, result.output
    assert "20 + 6 repair iterations" in result.output
    saved = json.loads((out / "config.json").read_text())["config"]
    assert saved["repair"]["iters"] == 6 and saved["repair"]["loo_iters"] == TINY_REPAIR["loo_iters"]
    assert (out / "repair" / "samples" / "pairs.png").is_file() and (out / "coarse" / "gaussians.ply").is_file()

    for extra, message in [(["--no-repair", "--repair-iters", "5"], "and --no-repair both set repair.iters"),
                           (["--set", "repair.fit_steps=many"], "repair.fit_steps must be like"),
                           (["--views", "4", "--set", "views=6"], "--views 4 and --set views=6 both set views"),
                           (["--set", "repair.nope=1"], "unknown training option"),
                           (["--set", "repair.iters=5", "--no-repair"], "--no-repair and --set repair.iters=5 both set"),
                           (["--set", "repair.loo_samples=0"], "repair.loo_samples must be in [1, (loo_iters - loo_snapshot) // 4 = 2]"),
                           (["--set", "repair.noise_dropout=[0.9,0.2]"], "repair.noise_dropout must be (low, high)"),
                           (["--set", "background=black", "--repair-iters", "2"], "white background"),
                           (["--set", "repair"], "expected name=value"),
                           (["--repairer", "nowhere:factory", "--repair-iters", "2"], "cannot load"),
                           (["--no-repair", "--repairer", "unet"], "--repairer unet would be unused: the repair stage "
                                                                      "is off")]:
        result = runner.invoke(app, ["train", *common, *extra, "--out", str(tmp_path / "bad")])
        assert result.exit_code == 2 and message in result.output, (extra, result.output)
        assert "Traceback" not in result.output


def test_no_repair_writes_no_repair_files(scene_dir, tmp_path):
    runner = CliRunner()
    result = runner.invoke(app, ["train", str(scene_dir), "--iters", "10", "--rounds", "1", "--no-repair",
                                 "--set", "init_points=400", "--set", "hull_resolution=24", "--out", str(tmp_path)])
    assert result.exit_code == 0, result.output
    assert json.loads((tmp_path / "config.json").read_text())["config"]["repair"]["iters"] == 0
    assert not (tmp_path / "repair").exists() and not (tmp_path / "coarse").exists()
    assert (tmp_path / "gaussians.ply").is_file()


def test_the_pseudo_view_ratio_ramps_linearly_then_stops():
    """r goes linearly from pseudo_ratio_start to pseudo_ratio_end over the first pseudo_until of the repair
    iterations, then 0 (the end-to-end test checks only the first and last value: r held at its start passed)."""
    config = RepairConfig(iters=10, pseudo_until=0.5, pseudo_ratio_start=1.0, pseudo_ratio_end=0.5)
    assert [pseudo_ratio(config, i) for i in range(10)] == pytest.approx([1.0, 0.875, 0.75, 0.625, 0.5, 0, 0, 0, 0, 0])
    # 0.55 of 100 iterations is 55 (its float product, 55.00000000000001, rounded up to 56)
    config = RepairConfig(iters=100, pseudo_until=0.55, pseudo_ratio_start=1.0, pseudo_ratio_end=0.5)
    assert pseudo_ratio(config, 54) == pytest.approx(0.5) and pseudo_ratio(config, 55) == 0


# ------------------------------------------------------------------ what the stage's mutation review found unguarded
def test_leave_one_out_fits_stop_densifying_at_the_snapshot():
    """The noise statistics take unseen - seen per Gaussian, so both copies must keep the one Gaussian set they share
    at the snapshot: their densification must stop there even where the preset's densify.stop comes later."""
    for repair in ({}, {"loo_iters": 300, "loo_snapshot": 120}):  # the quick preset's densify.stop is 201
        config = load_preset("quick", repair={"iters": 5, **repair})
        assert config.densify.stop > config.repair.loo_snapshot  # the case the cap is there for
        assert leave_one_out_config(config).densify.stop <= config.repair.loo_snapshot


def test_leave_one_out_samples_its_first_quarter_and_returns_unseen_minus_seen(scene_dir, monkeypatch):
    """leave_one_out renders its samples at the snapshot and the iterations after it, within the first quarter of
    the span to loo_iters, and returns the unseen copy's parameters minus the seen copy's (the sign the noise's mean
    takes), checked on the two fits it made rather than on differences built by hand."""
    config = tiny_config(loo_iters=24, loo_snapshot=16, loo_samples=2)  # span (24 - 16) // 4 = 2: renders at 16, 17
    scene = training_scene(load_scene(scene_dir, name="tiny"), config)
    fits, rendered_at = [], []
    init, render = LeaveOneOutFit.__init__, LeaveOneOutFit.render

    def recording_init(self, *args, **kwargs):
        init(self, *args, **kwargs)
        fits.append(self)

    def recording_render(self, view):
        rendered_at.append(self.iteration)
        return render(self, view)

    monkeypatch.setattr(LeaveOneOutFit, "__init__", recording_init)
    monkeypatch.setattr(LeaveOneOutFit, "render", recording_render)
    coarse = SimpleNamespace(training_views=TrainingViews.of(scene, config, torch.device("cpu")))
    _, differences = leave_one_out(coarse, scene.viewmats, config, left_out=1)
    assert rendered_at == [16, 17]
    (unseen,) = [fit for fit in fits if fit.model.training_views.num_views == scene.num_views - 1]
    (seen,) = [fit for fit in fits if fit.model.training_views.num_views == scene.num_views]
    for name in NOISY_PARAMETERS:
        expected = unseen.model.params[name].detach().cpu() - seen.model.params[name].detach().cpu()
        assert expected.abs().max() > 0
        torch.testing.assert_close(differences[name], expected, rtol=0, atol=0)


def test_build_pairs_draws_noise_from_its_ranges_and_pairs_each_render_with_its_own_views_image(monkeypatch):
    """build_pairs: every pair, leave-one-out or noise, is the render of the view it is labelled with against that
    view's real image; each noise render uses perturbed parameters, with a clamp and a dropout drawn across
    noise_clamp_std and noise_dropout (each within its own range, not the other's or one end). A fake coarse model
    renders view v as the flat value (v + 1) / 10, so a render shows which view it is of."""
    count, size, gaussians = 3, 8, 5
    generator = torch.Generator().manual_seed(0)
    targets = torch.rand(count, size, size, 3, generator=generator)
    params = {"means": torch.zeros(gaussians, 3), "scales": torch.zeros(gaussians, 3),
              "quats": torch.zeros(gaussians, 4), "opacities": torch.zeros(gaussians)}
    viewmats = torch.eye(4).repeat(count, 1, 1)
    viewmats[:, 2, 3] = torch.arange(count) + 1.0
    given_params = []

    def render_views(cameras, Ks=None, params=None, sh_degree=None):
        given_params.append(params)
        return torch.stack([torch.full((size, size, 3), camera[2, 3].item() / 10) for camera in cameras])

    coarse = SimpleNamespace(training_views=SimpleNamespace(targets=targets, Ks=torch.eye(3).repeat(count, 1, 1)),
                             params=params, render_views=render_views)

    def fake_leave_one_out(coarse, viewmats, config, left_out, should_stop):
        samples = torch.full((2, size, size, 3), (left_out + 1) / 10)
        return samples, {name: torch.randn(gaussians, *value.shape[1:]) for name, value in params.items()}

    draws = []  # (clamp_std, dropout) of every noise render
    perturbed = pairs_module.perturbed_gaussians

    def recording_perturbed(params, noise, clamp_std, dropout, generator):
        draws.append((clamp_std, dropout))
        return perturbed(params, noise, clamp_std, dropout, generator)

    monkeypatch.setattr(pairs_module, "leave_one_out", fake_leave_one_out)
    monkeypatch.setattr(pairs_module, "perturbed_gaussians", recording_perturbed)
    config = tiny_config(noise_renders=8, noise_clamp_std=(0.1, 0.2), noise_dropout=(0.5, 0.9))
    pairs = build_pairs(coarse, viewmats, config, log=lambda message: None)
    assert pairs.kinds.count(LEAVE_ONE_OUT) == 2 * count and pairs.kinds.count(NOISE) == 8 * count
    for corrupted, target, view in zip(pairs.corrupted, pairs.targets, pairs.views):
        assert torch.all(corrupted == (view + 1) / 10)  # the render of the view the pair is labelled with
        assert torch.equal(target, targets[view])  # ... against that view's real image
    clamps, dropouts = torch.tensor([draw[0] for draw in draws]), torch.tensor([draw[1] for draw in draws])
    assert len(draws) == 8 * count
    assert 0.1 <= clamps.min() and clamps.max() <= 0.2 and clamps.max() - clamps.min() > 0.05
    assert 0.5 <= dropouts.min() and dropouts.max() <= 0.9 and dropouts.max() - dropouts.min() > 0.2
    noisy = [given for given in given_params if given is not None]
    assert len(noisy) == 8 * count and all(not torch.equal(given["means"], params["means"]) for given in noisy)


def random_pairs(views, kinds, size=16, seed=0) -> RepairPairs:
    generator = torch.Generator().manual_seed(seed)
    count = len(views)
    return RepairPairs(torch.rand(count, size, size, 3, generator=generator),
                       torch.rand(count, size, size, 3, generator=generator), list(kinds), list(views),
                       NoiseStatistics({}, {}))


def test_the_repairer_fit_validates_on_the_held_out_views_noise_pairs():
    """The fit's validation set is the held-out (last) view's noise pairs, not its leave-one-out ones: its identity
    error is that of pair 3 alone."""
    pairs = random_pairs([0, 0, 1, 1], [LEAVE_ONE_OUT, NOISE, LEAVE_ONE_OUT, NOISE])
    repairer = UNetRepairer(RepairConfig(fit_steps=2, fit_crop=8, fit_batch=2))
    stats = repairer.fit(pairs, log=lambda message: None)
    expected = ((pairs.corrupted[3] - pairs.targets[3]) ** 2).mean().item()
    assert stats["validation_view"] == 1
    assert stats["validation_mse_identity"] == pytest.approx(expected, rel=1e-6)


def test_the_repairer_final_fit_takes_the_best_checks_step_count():
    """After the validated run, the final fit trains for the step count of the best check (20 here), not fit_steps."""
    pairs = random_pairs([0, 1], [NOISE, NOISE])
    pairs.corrupted.zero_()
    pairs.targets.fill_(1.0)  # identity MSE 1: every check below beats it
    repairer = UNetRepairer(RepairConfig(fit_steps=30, fit_crop=8, fit_batch=2))
    final_steps = []

    def fake_train(pairs, steps, size, should_stop, validation=None, check_every=0):
        if validation is not None:
            return [], [(10, 0.5), (20, 0.1), (30, 0.3)]
        final_steps.append(steps)
        return [0.0] * steps, []

    repairer._train = fake_train
    stats = repairer.fit(pairs, log=lambda message: None)
    assert stats["steps"] == 20 and final_steps == [20]


def test_a_flipped_training_crop_flips_its_target_too():
    """Crops are flipped for augmentation: with targets equal to the inputs, every crop's target must still equal
    its input, which a flip of the input alone breaks."""
    pairs = random_pairs([0, 1, 2, 3], [NOISE] * 4)
    pairs = RepairPairs(pairs.corrupted, pairs.corrupted.clone(), pairs.kinds, pairs.views, pairs.noise)
    repairer = UNetRepairer(RepairConfig(fit_batch=16, fit_crop=8))
    for _ in range(3):
        inputs, targets = repairer._crops(pairs, 8)
        assert torch.equal(inputs, targets)


def test_training_crops_find_object_pixels_missing_from_the_render():
    """A part of the object the render lacks (white there, dark in the real image) is what the repair must paint:
    crops centre on pixels that are object in either image, so every crop here holds the corner only the real image
    shows."""
    corrupted = torch.ones(2, 32, 32, 3)
    targets = torch.ones(2, 32, 32, 3)
    targets[:, :4, :4] = 0.2
    pairs = RepairPairs(corrupted, targets, [NOISE, NOISE], [0, 1], NoiseStatistics({}, {}))
    repairer = UNetRepairer(RepairConfig(fit_batch=8, fit_crop=8))
    _, crop_targets = repairer._crops(pairs, 8)
    assert all((crop < 0.99).any() for crop in crop_targets)


def test_repaired_images_stay_in_the_unit_range():
    """A network whose output overshoots (a bias of 0.5 on a 0.9 image) still gives images in [0, 1]."""
    repairer = UNetRepairer(RepairConfig())
    with torch.no_grad():
        repairer.network.output.bias.fill_(0.5)
    repaired = repairer.repair(torch.full((1, 8, 8, 3), 0.9))
    assert repaired.max() <= 1.0


class RecordingPlugin:
    """A plug-in repairer whose fit takes should_stop and records it, and whose repair moves images to `device`."""

    def __init__(self, device=None):
        self.device, self.should_stop = device, None

    def fit(self, pairs, log, should_stop):
        self.should_stop = should_stop
        return {}

    def repair(self, images):
        return images.to(self.device) if self.device else images

    def state_dict(self):
        return {}

    def load_state_dict(self, state):
        pass


def test_a_plugin_whose_fit_takes_should_stop_is_given_it():
    """A plug-in that can stop its own (long) fit on Ctrl-C gets the stage's should_stop."""
    plugin = RecordingPlugin()
    stop = lambda: False  # noqa: E731
    PluginRepairer(plugin, "mine:Plugin").fit(SimpleNamespace(), print, should_stop=stop)
    assert plugin.should_stop is stop


def test_a_plugin_repair_returned_on_another_device_is_one_line():
    """Images a plug-in returns on another device than it was given fail as one line naming it, not later in the
    loss as a device mismatch."""
    with pytest.raises(WarpbagsError, match="returned .* on meta"):
        PluginRepairer(RecordingPlugin("meta"), "mine:Plugin").repair(torch.rand(2, 8, 8, 3))


def ring_stage(folder, views=4, **repair):
    """A repair stage over `views` training cameras evenly around a ring, a model rendering flat grey that records
    the cameras it is given, and a repairer that changes nothing; the coarse stage ends at iteration 30."""
    base = torch.eye(4)
    base[2, 3] = 4.0
    viewmats = turntable_viewmats(base[None].double(), views).float()
    calls = []

    def render_views(cameras):
        calls.append(cameras.clone())
        return torch.full((len(cameras), 8, 8, 3), 0.5)

    model = SimpleNamespace(training_views=SimpleNamespace(device="cpu"),
                            params={"means": torch.zeros(10, 3), "opacities": torch.zeros(10)},
                            render_views=render_views)
    stage = RepairStage(tiny_config(weight_lpips=0.0, **repair), folder, model, viewmats,
                        torch.Generator().manual_seed(0), log=lambda message: None, repairer=AddingRepairer(0.0))
    return stage, model, viewmats, calls


def test_pseudo_cameras_sit_30_to_70_percent_along_every_gap(tmp_path):
    """Pseudo cameras are drawn 30-70% of the way along a gap between neighbouring training cameras, over every gap
    including the one that closes the ring, and the stage's weights are their distance_weights."""
    stage, model, viewmats, _ = ring_stage(tmp_path, pseudo_views=400)
    stage.refresh(model, viewmats, iteration=30)
    pseudo, train = camera_centers(stage.viewmats.double()), camera_centers(viewmats.double())
    cosines = (pseudo / pseudo.norm(dim=1, keepdim=True)) @ (train / train.norm(dim=1, keepdim=True)).T
    angles = torch.rad2deg(torch.arccos(cosines.clamp(-1, 1)))  # [K, C] degrees; the gaps are 90 degrees
    nearest_two = angles.topk(2, dim=1, largest=False)
    assert nearest_two.values[:, 0].min() >= 0.3 * 90 - 0.5  # none closer than 30% of a gap to a training camera
    gaps = {tuple(sorted(pair)) for pair in nearest_two.indices.tolist()}
    assert gaps == {(0, 1), (1, 2), (2, 3), (0, 3)}
    torch.testing.assert_close(stage.weights, distance_weights(stage.viewmats, viewmats))


def test_the_pseudo_loss_draws_a_random_pseudo_view_each_iteration(tmp_path):
    """Each repair iteration's pseudo loss renders one pseudo view drawn at random, so 20 iterations between
    refreshes use more than one of the 4."""
    stage, model, viewmats, calls = ring_stage(tmp_path, pseudo_views=4, refresh_every=50)
    for iteration in range(30, 50):
        stage.loss(model, viewmats, iteration)
    used = {tuple(call[0].flatten().tolist()) for call in calls if len(call) == 1}  # the single-view renders
    assert len(used) > 1


def test_pseudo_view_refreshes_count_from_the_repair_stages_start(tmp_path, monkeypatch):
    """Refreshes come every refresh_every repair iterations from the stage's first (iteration 30 here), not at
    multiples of refresh_every of the whole run's count: 7 does not divide 30, so the two differ."""
    stage, model, viewmats, _ = ring_stage(tmp_path, refresh_every=7)
    refreshed = []
    refresh = stage.refresh

    def recording_refresh(model, viewmats, iteration):
        refreshed.append(iteration)
        refresh(model, viewmats, iteration)

    monkeypatch.setattr(stage, "refresh", recording_refresh)
    for iteration in range(30, 47):
        stage.loss(model, viewmats, iteration)
    assert refreshed == [30, 37, 44]


def test_a_repair_step_mixes_real_and_pseudo_losses_by_the_ratio(scene_dir, tmp_path, monkeypatch):
    """Inside the ratio's ramp a repair step's loss is (1 - r) real + r pseudo: a real loss of 1 and a pseudo loss
    of 3 make it exactly that."""
    config = tiny_config(pseudo_until=1.0, pseudo_ratio_start=0.8, pseudo_ratio_end=0.2)
    trainer = Trainer(training_scene(load_scene(scene_dir, name="tiny"), config), config, tmp_path,
                      log=lambda message: None)
    trainer.iteration = config.iters + 5
    means = trainer.model.params["means"]
    monkeypatch.setattr(trainer.model, "loss", lambda views, viewmats, settings: (means.sum() * 0 + 1.0, {}, None))
    trainer.repair_stage = SimpleNamespace(loss=lambda model, viewmats, iteration: (means.sum() * 0 + 3.0, {}))
    ratio = pseudo_ratio(config.repair, 5)
    assert 0 < ratio < 1
    record = trainer.train_step()
    assert record["pseudo_ratio"] == pytest.approx(ratio)
    assert record["loss"] == pytest.approx((1 - ratio) * 1.0 + ratio * 3.0)

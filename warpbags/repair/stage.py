"""`RepairStage`: the pseudo-view half of GaussianObject's repair optimization.

After the coarse stage the trainer (`warpbags.trainer`) builds one RepairStage, which
1. builds the repairer's training pairs (`warpbags.repair.pairs`) and fits the repairer, or loads both from the
   run folder when a resumed run already made them;
2. every `refresh_every` iterations draws `pseudo_views` novel cameras in the gaps between the training cameras,
   renders them and repairs the renders: the pseudo ground truth;
3. each iteration returns the loss of one pseudo view against its repaired image.
The trainer mixes it with the real-view loss (`RepairConfig` gives the schedule) and keeps optimizing the poses
from the real views.

Files (under the run folder's repair/):
    pairs.pt            the training pairs and 3D-noise statistics
    repairer.pt         the fitted repairer's state
    fit.json            fitting statistics (L1 to the real images per pair kind, before and after repair)
    samples/pairs.png   rows of corrupted | repaired | real image, leave-one-out pairs first
    samples/pseudo_XXXXXX.png   rows of render | repaired image of pseudo views at a refresh (newest kept)
"""

from __future__ import annotations

import pickle
from pathlib import Path
from typing import Callable

import torch

from warpbags.camera_paths import interpolated_viewmats
from warpbags.cameras import camera_centers
from warpbags.configs.train import RepairConfig, TrainConfig
from warpbags.errors import WarpbagsError, one_line
from warpbags.files import atomic_output, finite_json
from warpbags.gaussians import opacity_weighted_center
from warpbags.losses import load_lpips, repair_loss
from warpbags.model import GaussianModel
from warpbags.repair.network import Repairer, make_repairer
from warpbags.repair.pairs import LEAVE_ONE_OUT, NOISE, RepairPairs, build_pairs
from warpbags.report import write_image_grid
from warpbags.schedule import share_of

SAMPLE_ROWS = 4  # pictures per kind in a sample sheet


def distance_weights(pseudo_viewmats: torch.Tensor, train_viewmats: torch.Tensor) -> torch.Tensor:
    """[K] GaussianObject's pseudo-view weights min(1, 2 d / d_max): d is the distance from a pseudo camera to the
    nearest training camera, d_max 1.2 x the largest distance from a training camera to its second-nearest other
    (so views next to a real one, whose renders need little repair, count less)."""
    pseudo, train = camera_centers(pseudo_viewmats), camera_centers(train_viewmats)
    nearest = torch.cdist(pseudo, train).min(dim=1).values
    between = torch.cdist(train, train).sort(dim=1).values
    reach = 1.2 * between[:, min(2, len(train) - 1)].max()
    return (2 * nearest / reach.clamp_min(1e-12)).clamp(max=1.0)


def pseudo_ratio(config: RepairConfig, repair_iteration: int) -> float:
    """r in loss = (1 - r) real + r pseudo at a repair iteration (0-based): linear from `pseudo_ratio_start` to
    `pseudo_ratio_end` over the first `pseudo_until` of the repair iterations, 0 after."""
    until = share_of(config.pseudo_until, config.iters)
    if repair_iteration >= until:
        return 0.0
    fraction = repair_iteration / max(until - 1, 1)
    return config.pseudo_ratio_start + (config.pseudo_ratio_end - config.pseudo_ratio_start) * fraction


def _load_saved(path: Path, load: Callable[[Path], object]) -> object:
    """`load(path)`: a file the repair stage saved (pairs.pt, repairer.pt), read for a resumed run.

    Raises:
        WarpbagsError: the file cannot be read (cut short, another file in its place, not the layout `load` reads),
            named in one line as `RunFolder.load_checkpoint` names a checkpoint.
    """
    try:
        return load(path)
    except (OSError, RuntimeError, EOFError, ValueError, pickle.UnpicklingError, KeyError, TypeError) as error:
        raise WarpbagsError(f"{path}: unreadable ({one_line(error, limit=1000)})") from None


class RepairStage:
    """Pseudo ground truth from a repairer, for a run whose coarse stage is finished.

    Args:
        config: the run's config (its `repair` group sets everything here).
        folder: where its files go (the run folder's repair/).
        coarse: the coarse model the pairs are built from.
        viewmats: [C,4,4] the coarse stage's poses.
        generator: the run's random stream (pseudo cameras and which one each iteration uses).
        log: receives one-line progress notices.
        should_stop: checked while the pairs are built (KeyboardInterrupt when it turns true).
        repairer: an already fitted repairer to use as it is (no pairs are built); default: the config's,
            fitted on this run's pairs.

    Attributes:
        repair: the run's `RepairConfig` (`config.repair`).

    Raises:
        WarpbagsError: a resumed run's pairs.pt or repairer.pt cannot be read.
    """

    def __init__(self, config: TrainConfig, folder: Path, coarse: GaussianModel, viewmats: torch.Tensor,
                 generator: torch.Generator, log: Callable[[str], None] = print,
                 should_stop: Callable[[], bool] = lambda: False, repairer: Repairer | None = None):
        self.repair, self.generator = config.repair, generator
        self.coarse_iters = config.iters  # repair iterations count from here
        self.folder = Path(folder)
        self.samples = self.folder / "samples"
        self.samples.mkdir(parents=True, exist_ok=True)
        self.log = log
        device = str(coarse.training_views.device)
        pairs_path, repairer_path = self.folder / "pairs.pt", self.folder / "repairer.pt"
        if repairer is not None:
            self.repairer = repairer
        else:
            fitted = pairs_path.is_file() and repairer_path.is_file()  # a resumed run whose repairer was fitted
            self.repairer = make_repairer(self.repair, config.seed, device)
            pairs = self._training_pairs(pairs_path, coarse, viewmats, config, should_stop)
            if fitted:
                # saved on whichever device the run used before
                _load_saved(repairer_path, lambda path: self.repairer.load_state_dict(
                    torch.load(path, map_location="cpu", weights_only=False)))
                log(f"repair: loaded the fitted repairer from {self.folder}")
            else:
                self._fit(pairs, should_stop)
        self.lpips, unavailable = load_lpips() if self.repair.weight_lpips > 0 else (None, None)
        if self.lpips is not None:
            self.lpips.to(device)
        if unavailable:
            log(f"repair: LPIPS unavailable ({unavailable}); the pseudo-view loss is L1 + L2 only")
        self.viewmats: torch.Tensor | None = None  # [K,4,4] current pseudo cameras
        self.targets: torch.Tensor | None = None  # [K,H,W,3] their repaired renders
        self.weights: torch.Tensor | None = None  # [K] their distance weights

    def _training_pairs(self, path: Path, coarse: GaussianModel, viewmats: torch.Tensor, config: TrainConfig,
                        should_stop: Callable[[], bool]) -> RepairPairs:
        """The repairer's training pairs: those an earlier start of this run saved at `path` (the costly part of the
        stage: a run stopped during the fit keeps them), else built from leave-one-out models of `coarse` at the
        [C,4,4] `viewmats` and saved there."""
        if path.is_file():
            pairs = _load_saved(path, RepairPairs.load)
            self.log(f"repair: loaded {len(pairs.kinds)} pairs from {self.folder}")
            return pairs
        self.log(f"repair: building training pairs ({len(viewmats)} leave-one-out models, "
                 f"{self.repair.loo_iters} iterations each)")
        pairs = build_pairs(coarse, viewmats, config, should_stop, self.log)
        pairs.save(path)
        return pairs

    def _fit(self, pairs: RepairPairs, should_stop: Callable[[], bool]) -> None:
        """Fit the repairer on `pairs` and save its fit statistics (fit.json), a sample sheet of the pairs and, last,
        the repairer itself: a resumed run takes repairer.pt as a finished fit and writes none of the others."""
        # `make_repairer`'s: the U-Net's fit takes should_stop, and a plug-in's wrapper hands it on where it takes it
        stats = self.repairer.fit(pairs, self.log, should_stop=should_stop)
        with atomic_output(self.folder / "fit.json") as temporary:
            temporary.write_text(finite_json({"pairs": {kind: pairs.kinds.count(kind) for kind in set(pairs.kinds)},
                                              **stats}, indent=2))
        self._save_pair_samples(pairs)
        with atomic_output(self.folder / "repairer.pt") as temporary:
            torch.save(self.repairer.state_dict(), temporary)

    def refresh(self, model: GaussianModel, viewmats: torch.Tensor, iteration: int) -> None:
        """Draw new pseudo cameras between the training cameras at [C,4,4] `viewmats`, render them with `model` and
        store their repaired renders as the pseudo ground truth (sample sheet named after `iteration`).

        The cameras use training camera 0's intrinsics (GaussianObject takes a real view's field of view too).
        """
        repair, generator = self.repair, self.generator
        gaps = torch.randint(len(viewmats), (repair.pseudo_views,), generator=generator)
        fractions = 0.3 + 0.4 * torch.rand(repair.pseudo_views, generator=generator)  # GaussianObject: 0.5 +- 0.2
        with torch.no_grad():  # about the object, which noisy poses leave away from the origin
            center = opacity_weighted_center(model.params).double()
        self.viewmats = interpolated_viewmats(viewmats.double(), gaps, fractions.double(), center).float()
        self.weights = distance_weights(self.viewmats, viewmats)
        with torch.no_grad():
            renders = model.render_views(self.viewmats).clamp(0, 1)
        self.targets = self.repairer.repair(renders)
        rows = [[render.cpu(), target.cpu()] for render, target in zip(renders[:SAMPLE_ROWS], self.targets)]
        write_image_grid(self.samples / f"pseudo_{iteration:06d}.png", rows)
        for old in sorted(self.samples.glob("pseudo_*.png"))[:-repair.samples_kept]:
            old.unlink()

    def loss(self, model: GaussianModel, viewmats: torch.Tensor, iteration: int) -> tuple[torch.Tensor, dict]:
        """The pseudo-view loss of `model` on one random pseudo view at run iteration `iteration` (refreshing the
        pseudo ground truth when due, around the training cameras at [C,4,4] `viewmats`)."""
        repair_iteration = iteration - self.coarse_iters
        if self.targets is None or repair_iteration % self.repair.refresh_every == 0:
            self.refresh(model, viewmats, iteration)
        pick = torch.randint(len(self.viewmats), (1,), generator=self.generator)
        images = model.render_views(self.viewmats[pick])
        repair = self.repair
        losses, terms = repair_loss(images, self.targets[pick], repair.weight_l1, repair.weight_l2, repair.weight_lpips,
                                    self.lpips)
        return (self.weights[pick] * losses).mean(), terms

    def _save_pair_samples(self, pairs: RepairPairs) -> None:
        rows = []
        for kind in (LEAVE_ONE_OUT, NOISE):
            index = [i for i, k in enumerate(pairs.kinds) if k == kind]
            index = index[:: max(len(index) // SAMPLE_ROWS, 1)][:SAMPLE_ROWS]  # spread over the views
            repaired = self.repairer.repair(pairs.corrupted[index])
            rows += [[pairs.corrupted[i], image, pairs.targets[i]] for i, image in zip(index, repaired)]
        write_image_grid(self.samples / "pairs.png", rows)

    def state_dict(self) -> dict:
        return {"viewmats": self.viewmats, "targets": self.targets, "weights": self.weights}

    def load_state_dict(self, state: dict) -> None:
        self.viewmats, self.targets, self.weights = state["viewmats"], state["targets"], state["weights"]

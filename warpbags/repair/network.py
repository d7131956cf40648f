"""Repairers: image-to-image models that turn renders of a sparse-view model into plausible images of the object.

GaussianObject's repairer is Stable Diffusion 1.5 + ControlNet-tile with a per-scene LoRA; its weights cannot be
downloaded here, so warpbags ships `UNetRepairer`, a compact U-Net fitted per scene on the same (corrupted
render, real image) pairs. Any object with the `Repairer` methods can take its place:

    warpbags train maryrose --repair-iters 3000 --repairer mypackage.diffusion:make_repairer

where ``make_repairer(config: RepairConfig, seed: int, device: str) -> Repairer`` (for instance a ControlNet +
LoRA model loaded from local weights, whose `fit` trains the LoRA on the pairs).
"""

from __future__ import annotations

import importlib
import inspect
import json
import math
from typing import Callable, Protocol, runtime_checkable

import torch
import torch.nn.functional as F
from torch import nn

from warpbags.configs.train import RepairConfig
from warpbags.errors import WarpbagsError, one_line
from warpbags.repair.pairs import NOISE, RepairPairs
from warpbags.threads import host_threads, torch_threads


@runtime_checkable
class Repairer(Protocol):
    """What the repair stage needs from a repairer. Images are [B, H, W, 3] float in [0, 1] on a white background;
    `repair` returns them on the device they came on."""

    def fit(self, pairs: RepairPairs, log: Callable[[str], None]) -> dict:
        """Learn to map `pairs.corrupted` to `pairs.targets`; returns statistics worth saving (JSON-able). A
        repairer whose `fit` also takes `should_stop` (a callable, `UNetRepairer.fit`) is given the stage's, to
        raise KeyboardInterrupt when it turns true: Ctrl-C and SIGTERM then stop a fit that takes minutes."""

    def repair(self, images: torch.Tensor) -> torch.Tensor:
        """Repaired versions of `images` (no gradient)."""

    def state_dict(self) -> dict:
        """Everything needed to restore the fitted repairer (saved as repair/repairer.pt)."""

    def load_state_dict(self, state: dict) -> None:
        """Restore from `state_dict()`."""


def _conv_block(channels_in: int, channels_out: int) -> nn.Sequential:
    return nn.Sequential(
        nn.Conv2d(channels_in, channels_out, 3, padding=1), nn.GroupNorm(4, channels_out), nn.SiLU(),
        nn.Conv2d(channels_out, channels_out, 3, padding=1), nn.GroupNorm(4, channels_out), nn.SiLU(),
    )


class RepairUNet(nn.Module):
    """A 3-level U-Net predicting a residual: ``repaired = image + net(image)``.

    The output convolution starts at zero, so an unfitted network is the identity (a repairer that has seen no
    data changes nothing). Input sides must be multiples of 4 (`UNetRepairer.repair` pads).
    """

    levels = 3

    def __init__(self, channels: int = 16):
        super().__init__()
        widths = [channels * 2**level for level in range(self.levels)]
        self.encoders = nn.ModuleList([_conv_block(3, widths[0])] + [
            _conv_block(widths[level - 1], widths[level]) for level in range(1, self.levels)])
        self.decoders = nn.ModuleList([
            _conv_block(widths[level + 1] + widths[level], widths[level]) for level in range(self.levels - 1)])
        self.output = nn.Conv2d(widths[0], 3, 1)
        nn.init.zeros_(self.output.weight)
        nn.init.zeros_(self.output.bias)

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        """[B, 3, H, W] -> [B, 3, H, W]."""
        skips, features = [], images * 2 - 1
        for level, encoder in enumerate(self.encoders):
            features = encoder(features if level == 0 else F.avg_pool2d(features, 2))
            skips.append(features)
        for level in reversed(range(self.levels - 1)):
            features = F.interpolate(features, scale_factor=2, mode="bilinear", align_corners=False)
            features = self.decoders[level](torch.cat([features, skips[level]], dim=1))
        return images + self.output(features)


class UNetRepairer:
    """`RepairUNet` fitted per scene with L1 on random crops (flipped at random) of the pairs, for a number of
    steps chosen on a held-out view (see `fit`).

    Crops are centred on object pixels (either image not white), where the repair has something to do.
    """

    def __init__(self, config: RepairConfig, seed: int = 0, device: str = "cpu"):
        self.config, self.device = config, torch.device(device)
        self.seed, self.generator = seed, torch.Generator().manual_seed(seed)
        self._fresh_network(seed)

    def _crops(self, pairs: RepairPairs, size: int) -> tuple[torch.Tensor, torch.Tensor]:
        count, height, width, _ = pairs.corrupted.shape
        picks = torch.randint(count, (self.config.fit_batch,), generator=self.generator)
        inputs, targets = [], []
        for pick in picks.tolist():
            corrupted, target = pairs.corrupted[pick], pairs.targets[pick]
            ys, xs = torch.nonzero(((corrupted < 0.99) | (target < 0.99)).any(-1), as_tuple=True)
            if len(ys) == 0:
                ys, xs = torch.tensor([height // 2]), torch.tensor([width // 2])
            choice = torch.randint(len(ys), (1,), generator=self.generator).item()
            top = min(max(int(ys[choice]) - size // 2, 0), height - size)
            left = min(max(int(xs[choice]) - size // 2, 0), width - size)
            rows, columns = slice(top, top + size), slice(left, left + size)
            corrupted, target = corrupted[rows, columns], target[rows, columns]
            if torch.rand(1, generator=self.generator).item() < 0.5:
                corrupted, target = corrupted.flip(1), target.flip(1)
            inputs.append(corrupted)
            targets.append(target)
        to_nchw = lambda images: torch.stack(images).permute(0, 3, 1, 2).contiguous().to(self.device)  # noqa: E731
        return to_nchw(inputs), to_nchw(targets)

    def _fresh_network(self, seed: int) -> None:
        with torch.random.fork_rng(devices=[]):  # seeds the initial weights without touching the caller's RNG
            torch.manual_seed(seed)
            self.network = RepairUNet(self.config.unet_channels).to(self.device)

    def _train(self, pairs: RepairPairs, steps: int, size: int, should_stop: Callable[[], bool],
               validation: RepairPairs | None = None,
               check_every: int = 0) -> tuple[list[float], list[tuple[int, float]]]:
        """`steps` Adam steps on L1 (cosine-decayed rate) from the current network; returns the crop losses and,
        with `validation`, its whole-image mean squared error every `check_every` steps.

        Raises:
            KeyboardInterrupt: `should_stop()` turned true (checked every step).
        """
        optimizer = torch.optim.Adam(self.network.parameters(), lr=self.config.fit_lr)
        schedule = torch.optim.lr_scheduler.LambdaLR(
            optimizer, lambda step: 0.1 + 0.9 * 0.5 * (1 + math.cos(math.pi * step / steps)))
        losses, checks = [], []
        for step in range(1, steps + 1):
            if should_stop():
                raise KeyboardInterrupt
            self.network.train()
            inputs, targets = self._crops(pairs, size)
            loss = (self.network(inputs) - targets).abs().mean()
            optimizer.zero_grad()
            loss.backward()
            optimizer.step()
            schedule.step()
            losses.append(loss.item())
            if validation is not None and step % check_every == 0:
                self.network.eval()
                checks.append((step, ((self.repair(validation.corrupted) - validation.targets) ** 2).mean().item()))
        self.network.eval()
        return losses, checks

    def fit(self, pairs: RepairPairs, log: Callable[[str], None] = print,
            should_stop: Callable[[], bool] = lambda: False) -> dict:
        """Fit with the number of steps chosen on a held-out view, then on all pairs (KeyboardInterrupt when
        `should_stop()` turns true).

        A network fitted on a few views soon starts painting those views' appearance into others, which makes
        novel views worse (measured on the 4-view synthetic scene: the coarse model's held-out renders go from
        PSNR 22.9 to 23.0 after 200 steps, to 19.2 after 400). So a first fit leaves out the pairs of the last
        training view and checks the mean squared error of its 3D-noise pairs (mildly corrupted renders, like
        novel views near the training cameras; its leave-one-out renders are far worse than those and kept
        improving while the held-out renders got worse) every tenth of `fit_steps`. The best step count (none,
        if no check beats leaving the images as they are) is used for the final fit on every pair.

        Returns:
            statistics: the chosen steps, the validation curve, and the L1 per pair kind before and after.
        """
        config = self.config
        height, width = pairs.corrupted.shape[1:3]
        size = min(config.fit_crop, height, width) // 4 * 4
        if size < 8:
            raise WarpbagsError(f"images of {width}x{height} are too small to fit the repair network")
        held_out_view = max(pairs.views)
        validation = pairs.select([view == held_out_view and kind == NOISE
                                   for view, kind in zip(pairs.views, pairs.kinds)])
        if not validation.kinds:  # no 3D-noise pairs (noise_renders = 0): all of the view's pairs
            validation = pairs.select([view == held_out_view for view in pairs.views])
        training = pairs.select([view != held_out_view for view in pairs.views])
        before = self.l1_by_kind(pairs, repaired=False)
        # Convolutions use every core the process may run on (or a sweep task's share); the renderer is idle.
        with torch_threads(host_threads()):
            check_every = max(config.fit_steps // 10, 1)
            _, checks = self._train(training, config.fit_steps, size, should_stop, validation, check_every)
            identity = ((validation.corrupted - validation.targets) ** 2).mean().item()
            best_steps, best_error = min(checks, key=lambda check: check[1])
            steps = best_steps if best_error < identity else 0
            self._fresh_network(self.seed)
            losses = self._train(pairs, steps, size, should_stop)[0] if steps else []
            after = self.l1_by_kind(pairs, repaired=True)
        stats = {"steps": steps, "crop": size, "validation_view": held_out_view, "validation_mse_identity": identity,
                 "validation_mse": checks, "final_crop_l1": losses[-1] if losses else None,
                 "l1_identity": before, "l1_repaired": after}
        log(f"repair network: {steps} of {config.fit_steps} steps (held-out view {held_out_view}: MSE "
            f"{identity:.5f} unrepaired, {best_error:.5f} best)")
        return stats

    def l1_by_kind(self, pairs: RepairPairs, repaired: bool) -> dict[str, float]:
        """Mean whole-image L1 to the targets per pair kind, of the repaired (or the raw) corrupted images."""
        result = {}
        for kind in sorted(set(pairs.kinds)):
            index = [i for i, k in enumerate(pairs.kinds) if k == kind]
            images = pairs.corrupted[index]
            if repaired:
                images = self.repair(images)
            result[kind] = (images.cpu() - pairs.targets[index]).abs().mean().item()
        return result

    @torch.no_grad()
    def repair(self, images: torch.Tensor) -> torch.Tensor:
        height, width = images.shape[1:3]
        pad_y, pad_x = -height % 4, -width % 4
        inputs = F.pad(images.permute(0, 3, 1, 2).to(self.device), (0, pad_x, 0, pad_y), mode="replicate")
        repaired = torch.cat([self.network(batch) for batch in inputs.split(8)])
        return repaired[:, :, :height, :width].permute(0, 2, 3, 1).clamp(0, 1).to(images.device)

    def state_dict(self) -> dict:
        return {"network": self.network.state_dict()}

    def load_state_dict(self, state: dict) -> None:
        self.network.load_state_dict(state["network"])
        self.network.eval()


def repairer_factory(spec: str) -> Callable[[RepairConfig, int, str], Repairer]:
    """The factory `spec` names: "unet" (`UNetRepairer`) or "package.module:factory", imported.

    Raises:
        WarpbagsError: a malformed spec, a factory that cannot be imported or not called as factory(config, seed,
            device).
    """
    if spec == "unet":
        return UNetRepairer
    module_name, _, attribute = spec.partition(":")
    if not module_name or not attribute:
        raise WarpbagsError(f"--repairer must be unet or package.module:factory, got {spec!r}")
    try:
        factory = getattr(importlib.import_module(module_name), attribute)
    except Exception as error:  # ImportError, AttributeError, or what the module raises as it is imported
        raise WarpbagsError(f"--repairer {spec}: cannot load it ({one_line(error)}; the module must be installed or "
                            "on PYTHONPATH)") from None
    try:  # checked where the run starts (Trainer), not where the repair stage does, after the coarse stage
        inspect.signature(factory).bind(RepairConfig(), 0, "cpu")
    except TypeError as error:
        raise WarpbagsError(f"--repairer {spec}: cannot be called as factory(config, seed, device) ({error})") from None
    except ValueError:
        pass  # a callable without an inspectable signature: the call itself will tell
    return factory


def make_repairer(config: RepairConfig, seed: int = 0, device: str = "cpu") -> Repairer:
    """The repairer `config.repairer` names, built as factory(config, seed, device).

    Raises:
        WarpbagsError: the factory cannot be imported or called, it raises, or what it returns lacks the `Repairer`
            methods.
    """
    factory = repairer_factory(config.repairer)
    try:
        repairer = factory(config, seed, device)
    except Exception as error:  # a plugin's own failure, named in one line as every CLI error is
        raise WarpbagsError(f"--repairer {config.repairer}: building it failed ({one_line(error)})") from None
    if not isinstance(repairer, Repairer):
        raise WarpbagsError(f"--repairer {config.repairer}: returned {type(repairer).__name__}, which lacks "
                            "fit/repair/state_dict/load_state_dict")
    return repairer if config.repairer == "unet" else PluginRepairer(repairer, config.repairer)


class PluginRepairer:
    """A plug-in repairer (`--repairer module:factory`) whose failures are one line naming it: its errors come
    after the coarse stage and the leave-one-out pairs, and were tracebacks. Checks what it returns: `fit` a dict
    that JSON can hold (fit.json), `repair` images of the shape and device it was given. A stop (KeyboardInterrupt)
    passes through."""

    def __init__(self, repairer: Repairer, spec: str):
        self.repairer, self.spec = repairer, spec

    def _call(self, what: str, call: Callable[[], object]) -> object:
        try:
            return call()
        except Exception as error:  # the plug-in's own failure
            raise WarpbagsError(f"--repairer {self.spec}: its {what} failed ({one_line(error)})") from None

    def fit(self, pairs: RepairPairs, log: Callable[[str], None], should_stop: Callable[[], bool] = lambda: False
            ) -> dict:
        stops = "should_stop" in inspect.signature(self.repairer.fit).parameters  # a plug-in's may not take it
        stats = self._call("fit", lambda: self.repairer.fit(pairs, log, should_stop=should_stop) if stops else
                           self.repairer.fit(pairs, log))
        if not isinstance(stats, dict):
            raise WarpbagsError(f"--repairer {self.spec}: its fit returned {type(stats).__name__}, not a dict of "
                                "statistics")
        try:
            json.dumps(stats)
        except (TypeError, ValueError) as error:
            raise WarpbagsError(f"--repairer {self.spec}: its fit returned statistics fit.json cannot hold "
                                f"({one_line(error)})") from None
        return stats

    def repair(self, images: torch.Tensor) -> torch.Tensor:
        repaired = self._call("repair", lambda: self.repairer.repair(images))
        if not (isinstance(repaired, torch.Tensor) and repaired.shape == images.shape
                and repaired.device == images.device and repaired.is_floating_point()):
            got = (f"{tuple(repaired.shape)} {repaired.dtype} on {repaired.device}"
                   if isinstance(repaired, torch.Tensor) else type(repaired).__name__)
            raise WarpbagsError(f"--repairer {self.spec}: its repair of {tuple(images.shape)} images on "
                                f"{images.device} returned {got}")
        return repaired

    def state_dict(self) -> dict:
        return self._call("state_dict", self.repairer.state_dict)

    def load_state_dict(self, state: dict) -> None:
        self._call("load_state_dict", lambda: self.repairer.load_state_dict(state))

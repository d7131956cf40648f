"""Training losses (GaussianObject): L1 + D-SSIM, mask BCE on alpha, scale-invariant depth, the repair-stage mix."""

from __future__ import annotations

import functools

import torch
import torch.nn.functional as F

from warpbags.errors import one_line
from warpbags.kernels.loss import SSIM_C1, SSIM_C2
from warpbags.wrapper import fused_photometric_loss, ssim_window


def ssim(images: torch.Tensor, targets: torch.Tensor) -> torch.Tensor:
    """Mean SSIM (Wang et al. 2004) with an 11 x 11 Gaussian window (sigma 1.5), zero-padded as 3DGS's `ssim`;
    differentiable. The torch reference of the fused passes (`warpbags.wrapper.fused_photometric_loss`), with their
    window and constants.

    Args:
        images, targets: [B, H, W, 3] in [0, 1].

    Returns:
        [] mean SSIM over pixels, channels and batch.
    """
    x, y = images.permute(0, 3, 1, 2), targets.permute(0, 3, 1, 2)
    channels = x.shape[1]
    taps = ssim_window(str(x.device), torch.float64)
    window = (taps[:, None] @ taps[None, :]).to(x.dtype).expand(channels, 1, -1, -1)
    blur = functools.partial(F.conv2d, weight=window, padding=taps.shape[0] // 2, groups=channels)
    mu_x, mu_y = blur(x), blur(y)
    sigma_x = blur(x * x) - mu_x**2
    sigma_y = blur(y * y) - mu_y**2
    sigma_xy = blur(x * y) - mu_x * mu_y
    c1, c2 = SSIM_C1, SSIM_C2
    ssim_map = ((2 * mu_x * mu_y + c1) * (2 * sigma_xy + c2)) / ((mu_x**2 + mu_y**2 + c1) * (sigma_x + sigma_y + c2))
    return ssim_map.mean()


def photometric_loss(images: torch.Tensor, targets: torch.Tensor,
                     lambda_dssim: float = 0.2) -> tuple[torch.Tensor, dict]:
    """``(1 - lambda_dssim) L1 + lambda_dssim (1 - SSIM)`` over [B, H, W, 3] images; returns (loss, terms).

    SSIM is `ssim`'s (11 x 11 Gaussian window, zero padding). The loss and its gradient in `images` come from the
    fused Warp passes of kernels/loss.py (host threads on the CPU); targets that need a gradient take the plain
    torch path.
    """
    if targets.requires_grad:
        l1 = (images - targets).abs().mean()
        ssim_value = ssim(images, targets)
        loss = (1 - lambda_dssim) * l1 + lambda_dssim * (1 - ssim_value)
    else:
        loss, l1, ssim_value = fused_photometric_loss(images, targets.detach(), lambda_dssim)
    return loss, {"l1": l1.item(), "ssim": ssim_value.item()}


def mask_loss(alphas: torch.Tensor, masks: torch.Tensor) -> torch.Tensor:
    """Binary cross-entropy between rendered opacity [B, H, W] and object masks [B, H, W] in {0, 1}."""
    return F.binary_cross_entropy(alphas.clamp(1e-6, 1 - 1e-6), masks)


def _normalized(values: torch.Tensor) -> torch.Tensor:
    """Shift by the median and divide by the mean absolute deviation from it (scale/shift invariance)."""
    median = values.median()
    return (values - median) / (values - median).abs().mean().clamp_min(1e-6)


def depth_loss(
    depths: torch.Tensor, alphas: torch.Tensor, target_depths: torch.Tensor, masks: torch.Tensor | None,
    mode: str = "mad",
) -> torch.Tensor | None:
    """GaussianObject's monocular-depth term on disparities, invariant to their scale and shift.

    mode "mad" (GaussianObject's default): L1 between median/MAD-normalized disparities; "pearson":
    1 - Pearson correlation of the disparities. Compared per view inside ``mask & alpha > 0.5 & target > 0``, so
    the target may be metric or relative (any positive scale and shift of disparity gives the same loss).

    Args:
        depths: [B, H, W] rendered expected depth. alphas: [B, H, W] rendered opacity.
        target_depths: [B, H, W] depth maps (0 = no value). masks: [B, H, W] object masks, or None.
        mode: "mad" or "pearson".

    Returns:
        [] mean over views with at least 16 valid pixels, or None when no view has enough.
    """
    if mode not in ("mad", "pearson"):
        raise ValueError(f"depth loss mode must be mad or pearson, got {mode!r}")
    losses = []
    for index in range(len(depths)):
        valid = (alphas[index] > 0.5) & (target_depths[index] > 0) & (depths[index] > 1e-6)
        if masks is not None:
            valid &= masks[index] > 0.5
        if int(valid.sum()) < 16:
            continue
        rendered, target = 1.0 / depths[index][valid], 1.0 / target_depths[index][valid]
        if mode == "mad":
            losses.append((_normalized(rendered) - _normalized(target)).abs().mean())
        else:
            rendered, target = rendered - rendered.mean(), target - target.mean()
            correlation = (rendered * target).sum() / (rendered.norm() * target.norm()).clamp_min(1e-12)
            losses.append(1.0 - correlation)
    return torch.stack(losses).mean() if losses else None


def load_lpips() -> tuple[torch.nn.Module | None, str | None]:
    """LPIPS-VGG from the `lpips` package (GaussianObject's metric and repair loss): (network, None), or
    (None, why it is unavailable) when the package or its weights cannot be had offline.

    Only a missing package (ImportError) or weights that cannot be read or downloaded (OSError, which covers
    urllib's URLError) mean "unavailable"; any other exception is a real failure and propagates.
    """
    try:
        import lpips  # noqa: PLC0415 - optional dependency (it pulls torchvision and downloads weights)

        network = lpips.LPIPS(net="vgg", verbose=False)
    except (ImportError, OSError) as error:
        return None, one_line(error)
    for parameter in network.parameters():
        parameter.requires_grad_(False)
    return network, None


def repair_loss(images: torch.Tensor, targets: torch.Tensor, weight_l1: float, weight_l2: float, weight_lpips: float,
                lpips_network: torch.nn.Module | None = None) -> tuple[torch.Tensor, dict]:
    """GaussianObject's pseudo-view loss ``w1 L1 + w2 MSE + w3 LPIPS`` over [B, H, W, 3] images, per image.

    Returns:
        ([B] losses, terms) where terms holds the batch means; the LPIPS term is skipped without a network.
    """
    l1 = (images - targets).abs().mean(dim=(1, 2, 3))
    l2 = ((images - targets) ** 2).mean(dim=(1, 2, 3))
    losses = weight_l1 * l1 + weight_l2 * l2
    terms = {"pseudo_l1": l1.mean().item(), "pseudo_l2": l2.mean().item()}
    if lpips_network is not None and weight_lpips > 0:
        # [B,3,H,W] in [-1, 1], the range the lpips package's networks were trained on. GaussianObject's repair
        # loss feeds [0, 1] (torchmetrics' LPIPS, normalize=False); eval does too (`evaluation.LpipsMetric`), only
        # so that its numbers compare with GaussianObject's tables: a loss has no table to match.
        to_lpips = lambda x: x.permute(0, 3, 1, 2) * 2 - 1  # noqa: E731
        perceptual = lpips_network(to_lpips(images), to_lpips(targets)).reshape(-1)
        losses = losses + weight_lpips * perceptual
        terms["pseudo_lpips"] = perceptual.mean().item()
    return losses, terms

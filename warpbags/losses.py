"""Training losses (GaussianObject): L1 + D-SSIM, mask BCE on alpha, scale-invariant depth, the repair-stage mix."""

from __future__ import annotations

import functools

import torch
import torch.nn.functional as F
import warp as wp

from warpbags.kernels.loss import (
    RUN,
    WINDOW_RADIUS,
    photometric_grad_kernel,
    ssim_column_pass_kernel,
    ssim_grad_row_pass_kernel,
    ssim_row_pass_kernel,
)
from warpbags.wrapper import _default_cpu_threads, _launcher, _run_ranges, _to_warp


@functools.lru_cache(maxsize=8)
def _gaussian_window(size: int, sigma: float, device: str, dtype: torch.dtype) -> torch.Tensor:
    coords = torch.arange(size, dtype=torch.float64) - (size - 1) / 2
    g = torch.exp(-(coords**2) / (2 * sigma**2))
    g = g / g.sum()
    return (g[:, None] @ g[None, :]).to(device=device, dtype=dtype)


def ssim(images: torch.Tensor, targets: torch.Tensor, window_size: int = 11, sigma: float = 1.5) -> torch.Tensor:
    """Mean SSIM (Wang et al. 2004) with a Gaussian window, zero-padded as 3DGS's `ssim`; differentiable.

    Args:
        images, targets: [B, H, W, 3] in [0, 1].
        window_size, sigma: the Gaussian window (11 x 11, sigma 1.5).

    Returns:
        [] mean SSIM over pixels, channels and batch.
    """
    x, y = images.permute(0, 3, 1, 2), targets.permute(0, 3, 1, 2)
    channels = x.shape[1]
    window = _gaussian_window(window_size, sigma, str(x.device), x.dtype).expand(channels, 1, -1, -1)
    blur = functools.partial(F.conv2d, weight=window, padding=window_size // 2, groups=channels)
    mu_x, mu_y = blur(x), blur(y)
    sigma_x = blur(x * x) - mu_x**2
    sigma_y = blur(y * y) - mu_y**2
    sigma_xy = blur(x * y) - mu_x * mu_y
    c1, c2 = 0.01**2, 0.03**2
    ssim_map = ((2 * mu_x * mu_y + c1) * (2 * sigma_xy + c2)) / ((mu_x**2 + mu_y**2 + c1) * (sigma_x + sigma_y + c2))
    return ssim_map.mean()


def photometric_loss(images: torch.Tensor, targets: torch.Tensor, lambda_dssim: float = 0.2) -> tuple[torch.Tensor, dict]:
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
        loss, l1, ssim_value = _FusedPhotometricLoss.apply(images, targets.detach(), lambda_dssim)
    return loss, {"l1": l1.item(), "ssim": ssim_value.item()}


@functools.lru_cache(maxsize=8)
def _window_1d(device: str, dtype: torch.dtype, sigma: float = 1.5) -> torch.Tensor:
    coords = torch.arange(2 * WINDOW_RADIUS + 1, dtype=torch.float64) - WINDOW_RADIUS
    g = torch.exp(-(coords**2) / (2 * sigma**2))
    return (g / g.sum()).to(device=device, dtype=dtype)


def _row_passes(kernel, before: list, after: list, rows: int, runs: int, device: torch.device) -> None:
    """Launch a pass of kernels/loss.py (arguments `before`, the launch's first row, `after`) over `rows` image rows
    of `runs` runs each, split into row ranges across host threads on the CPU. The pass is complete when this
    returns: the next one reads neighbouring rows."""
    workers = 1 if device.type == "cuda" else min(_default_cpu_threads(), max(rows // 16, 1))
    bounds = torch.linspace(1, rows, 2 * workers + 1).round().long().tolist()
    ranges = [(0, 1)] + [(a, b) for a, b in zip(bounds[:-1], bounds[1:]) if b > a]

    launcher = _launcher(device)  # every launch names its device and stream: no process-wide default

    def work(_, first, stop):
        wp.launch(kernel, dim=(runs, stop - first), inputs=[*before, first, *after],
                  device=launcher.device, stream=launcher.stream)

    _run_ranges(work, ranges, workers)


def _runs(planes: torch.Tensor) -> wp.array:
    """Warp view of contiguous [..., RUN] planes as an array of RUN-vectors."""
    return _to_warp(planes.view(-1, RUN), f"vec{RUN}")


class _FusedPhotometricLoss(torch.autograd.Function):
    """(loss, L1, SSIM) of [B, H, W, 3] images against targets; only the loss is differentiable (in the images).
    The passes and their planes (per channel, rows padded to runs of RUN pixels): kernels/loss.py."""

    @staticmethod
    def forward(ctx, images, targets, lambda_dssim):
        batch, height, width, _ = images.shape
        images, targets = images.detach().contiguous(), targets.to(images.dtype).contiguous()
        rows, runs = batch * height, -(-width // RUN)
        window = _to_warp(_window_1d(str(images.device), images.dtype), "scalar")
        # x's and y's channel planes, each row with a zero run before and after it (the row blur's zero padding)
        planes = images.new_zeros(6, rows, runs + 2, RUN)
        planes.view(6, batch, height, -1)[:3, ..., RUN:RUN + width] = images.permute(3, 0, 1, 2)
        planes.view(6, batch, height, -1)[3:, ..., RUN:RUN + width] = targets.permute(3, 0, 1, 2)
        row_means = images.new_empty(15, rows, runs, RUN)
        _row_passes(ssim_row_pass_kernel, [_runs(planes), window, rows, runs], [_runs(row_means)], rows, runs,
                    images.device)
        ssim_sums = images.new_empty(rows * runs)
        l1_sums = torch.empty_like(ssim_sums)
        partials = images.new_empty(9, rows, runs + 2, RUN)  # dS/dmu_x, dS/dE[x^2], dS/dE[xy] per channel
        partials[:, :, [0, -1]] = 0  # the padding runs, for the backward's row blur
        _row_passes(ssim_column_pass_kernel, [_runs(planes), window, width, height, rows, runs],
                    [_runs(row_means), _to_warp(ssim_sums, "scalar"), _to_warp(l1_sums, "scalar"), _runs(partials)],
                    rows, runs, images.device)
        values = 3 * batch * height * width
        l1, ssim_value = l1_sums.sum() / values, ssim_sums.sum() / values
        loss = (1 - lambda_dssim) * l1 + lambda_dssim * (1 - ssim_value)
        ctx.save_for_backward(planes, partials)
        ctx.shape = images.shape
        ctx.lambda_dssim = lambda_dssim
        ctx.mark_non_differentiable(l1, ssim_value)
        return loss, l1, ssim_value

    @staticmethod
    def backward(ctx, v_loss, _v_l1, _v_ssim):
        planes, partials = ctx.saved_tensors
        batch, height, width, _ = ctx.shape
        rows, runs = batch * height, -(-width // RUN)
        window = _to_warp(_window_1d(str(planes.device), planes.dtype), "scalar")
        blurred = planes.new_empty(9, rows, runs, RUN)
        _row_passes(ssim_grad_row_pass_kernel, [window, rows, runs], [_runs(partials), _runs(blurred)], rows, runs,
                    planes.device)
        v_planes = planes.new_empty(3, rows, runs, RUN)
        scalar = {torch.float32: wp.float32, torch.float64: wp.float64}[planes.dtype]
        values = 3 * batch * height * width
        scales = [scalar(-ctx.lambda_dssim / values), scalar((1 - ctx.lambda_dssim) / values)]
        _row_passes(photometric_grad_kernel, [_runs(planes), window, height, rows, runs],
                    [_runs(blurred), *scales, _runs(v_planes)], rows, runs, planes.device)
        v_images = v_planes.view(3, batch, height, runs * RUN)[..., :width].permute(1, 2, 3, 0)
        return v_images * v_loss, None, None


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
        return None, f"{type(error).__name__}: {str(error).splitlines()[0] if str(error) else ''}"[:200]
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
        to_lpips = lambda x: x.permute(0, 3, 1, 2) * 2 - 1  # noqa: E731 - [B,3,H,W] in [-1, 1]
        perceptual = lpips_network(to_lpips(images), to_lpips(targets)).reshape(-1)
        losses = losses + weight_lpips * perceptual
        terms["pseudo_lpips"] = perceptual.mean().item()
    return losses, terms

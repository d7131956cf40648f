"""Gaussian weights and blur of image batches: the coarse-to-fine blur of renders and targets (`warpbags.model`), the
soft edges of monocular-like depth maps (`warpbags.data.noise`) and SSIM's window (`warpbags.wrapper`,
`warpbags.losses`)."""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F


def gaussian_taps(radius: int, sigma: float, dtype: torch.dtype = torch.float64,
                  device: torch.device | str = "cpu") -> torch.Tensor:
    """The 2 radius + 1 weights of a 1-D Gaussian centred on the middle tap, standard deviation `sigma` taps, summing
    to 1 (computed in float64, returned as `dtype`)."""
    coords = torch.arange(-radius, radius + 1, dtype=torch.float64)
    weights = torch.exp(-(coords**2) / (2 * sigma**2))
    return (weights / weights.sum()).to(device=device, dtype=dtype)


def gaussian_blur(images: torch.Tensor, sigma: float) -> torch.Tensor:
    """Separable Gaussian blur of [B, H, W, C] images (reflect-padded, 3 sigma radius); identity for sigma < 0.3."""
    if sigma < 0.3:
        return images
    radius = max(1, min(int(math.ceil(3 * sigma)), min(images.shape[1:3]) - 1))
    kernel = gaussian_taps(radius, sigma, images.dtype, images.device)
    x = images.permute(0, 3, 1, 2)
    channels = x.shape[1]
    x = F.pad(x, (radius, radius, radius, radius), mode="reflect")
    x = F.conv2d(x, kernel.view(1, 1, 1, -1).expand(channels, 1, 1, -1), groups=channels)
    x = F.conv2d(x, kernel.view(1, 1, -1, 1).expand(channels, 1, -1, 1), groups=channels)
    return x.permute(0, 2, 3, 1)

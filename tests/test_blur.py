"""warpbags.blur: the Gaussian blur of image batches against a float64 numpy reference (CPU)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from warpbags.blur import gaussian_blur


def _reference_blur(image: np.ndarray, sigma: float) -> np.ndarray:
    """[H, W] float64 image blurred by the 1-D Gaussian of radius ceil(3 sigma) along rows, then along columns, its
    border reflected without repeating the edge pixel (numpy's 'reflect', as torch's)."""
    radius = math.ceil(3 * sigma)
    taps = np.exp(-np.arange(-radius, radius + 1) ** 2 / (2 * sigma * sigma))
    taps /= taps.sum()
    padded = np.pad(image, radius, mode="reflect")
    rows = np.stack([np.convolve(row, taps, mode="valid") for row in padded])  # [H + 2 radius, W]
    return np.stack([np.convolve(column, taps, mode="valid") for column in rows.T]).T


@pytest.mark.parametrize("sigma", [0.8, 1.5])
def test_gaussian_blur_is_the_separable_three_sigma_gaussian_with_reflected_borders(sigma):
    """Only "blurred differs less" and SSIM's own taps were tested: a radius of 1 sigma, replicated borders and the
    rows padded r - 1 above and r + 1 below (the image moved down a pixel) all passed. Every pixel of every channel
    of a non-square batch matches the reference to float64 rounding."""
    images = torch.rand(2, 13, 17, 3, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    expected = np.stack([np.stack([_reference_blur(image[..., channel].numpy(), sigma) for channel in range(3)], -1)
                         for image in images])
    torch.testing.assert_close(gaussian_blur(images, sigma), torch.from_numpy(expected), rtol=0, atol=1e-12)

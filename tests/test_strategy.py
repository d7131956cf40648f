"""Densification statistics: what `DensifyStrategy.accumulate` needs and what it adds up."""

from __future__ import annotations

import pytest
import torch

from warpbags.configs.train import DensifyConfig
from warpbags.errors import WarpbagsError
from warpbags.strategy import DensifyStrategy


def _meta(width=8, height=6):
    means2d = torch.zeros(1, 3, 2, requires_grad=True)
    return {"means2d": means2d, "radii": torch.tensor([[2, 0, 1]], dtype=torch.int32), "width": width, "height": height}


def test_accumulate_adds_ndc_gradient_norms_of_visible_gaussians():
    strategy = DensifyStrategy(DensifyConfig(), scene_extent=1.0)
    meta = _meta()
    (meta["means2d"] * torch.tensor([[[1.0, 2.0], [5.0, 5.0], [0.0, -1.0]]])).sum().backward()
    strategy.accumulate(0, meta)
    # x by W/2 = 4, y by H/2 = 3; the second Gaussian has radius 0 (not visible) and adds nothing.
    torch.testing.assert_close(strategy.grad_sum, torch.tensor([(16.0 + 36.0) ** 0.5, 0.0, 3.0]))
    torch.testing.assert_close(strategy.grad_count, torch.tensor([1.0, 0.0, 1.0]))


def test_accumulate_without_the_means2d_gradient_is_an_error():
    strategy = DensifyStrategy(DensifyConfig(), scene_extent=1.0)
    with pytest.raises(WarpbagsError, match=r"retain_grad\(\)") as error:
        strategy.accumulate(0, _meta())
    assert "\n" not in str(error.value)


def test_accumulate_is_independent_of_the_views_per_step():
    """The same view rendered twice in a batch whose loss is the batch mean gives the one-view statistics."""
    weights = torch.tensor([[1.0, 2.0], [5.0, 5.0], [0.0, -1.0]])
    single, batched = DensifyStrategy(DensifyConfig(), 1.0), DensifyStrategy(DensifyConfig(), 1.0)
    meta = _meta()
    (meta["means2d"] * weights).sum().backward()
    single.accumulate(0, meta)
    means2d = torch.zeros(2, 3, 2, requires_grad=True)
    ((means2d * weights).sum((1, 2))).mean().backward()
    batch_meta = {"means2d": means2d, "radii": torch.tensor([[2, 0, 1]] * 2, dtype=torch.int32), "width": 8,
                  "height": 6}
    batched.accumulate(0, batch_meta)
    torch.testing.assert_close(batched.grad_sum / batched.grad_count.clamp_min(1),
                               single.grad_sum / single.grad_count.clamp_min(1))

"""Densification: what `DensifyStrategy.accumulate` needs and adds up, and what clone, split, prune, the
Gaussian budget and the opacity reset do to the parameters and their Adam moments."""

from __future__ import annotations

import dataclasses
import math

import pytest
import torch
from random_poses import skew_reference

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


def test_accumulate_restarts_statistics_of_another_length():
    """A checkpoint of an earlier version saved after a floater removal holds statistics of the length before it:
    they restart rather than fail to add up."""
    strategy = DensifyStrategy(DensifyConfig(), scene_extent=1.0)
    strategy.load_state_dict({"grad_sum": torch.ones(4), "grad_count": torch.ones(4)})
    meta = _meta()
    (meta["means2d"] * torch.tensor([[[1.0, 2.0], [5.0, 5.0], [0.0, -1.0]]])).sum().backward()
    strategy.accumulate(0, meta)
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


def _four_gaussians():
    """G0 small with a large gradient (cloned), G1 large with a large gradient (split; turned 90 deg about z, so its
    long axis lies along world y), G2 small gradient (kept), G3 nearly transparent (pruned); Adam holds moments for
    all after one step."""
    logit = lambda p: math.log(p / (1 - p))  # noqa: E731
    params = {
        "means": torch.tensor([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]),
        "scales": torch.log(torch.tensor([[0.005] * 3, [0.1, 0.05, 0.05], [0.05] * 3, [0.05] * 3])),
        "quats": torch.tensor([[1.0, 0.0, 0.0, 0.0], [math.sqrt(0.5), 0.0, 0.0, math.sqrt(0.5)],
                               [1.0, 0.0, 0.0, 0.0], [1.0, 0.0, 0.0, 0.0]]),
        "opacities": torch.tensor([logit(0.5), logit(0.6), logit(0.7), logit(0.01)]),
        "sh0": torch.arange(12.0).reshape(4, 1, 3),
    }
    params = {name: torch.nn.Parameter(value) for name, value in params.items()}
    optimizer = torch.optim.Adam([{"params": [value], "lr": 1e-3, "name": name} for name, value in params.items()])
    sum(value.sum() for value in params.values()).backward()
    optimizer.step()
    config = DensifyConfig(start=0, stop=100, every=1, grad_threshold=1e-3, percent_dense=0.01, prune_opacity=0.05,
                           prune_scale=0.5, opacity_reset_every=0, floater_every=0)
    strategy = DensifyStrategy(config, scene_extent=1.0)
    strategy.grad_sum, strategy.grad_count = torch.tensor([2.0, 1.0, 0.0, 0.0]), torch.ones(4)
    return params, optimizer, strategy


def test_clone_split_and_prune_change_the_rows_as_3dgs_does():
    params, optimizer, strategy = _four_gaussians()
    before = {name: value.detach().clone() for name, value in params.items()}
    moments = {(name, key): optimizer.state[value][key].clone() for name, value in params.items()
               for key in ("exp_avg", "exp_avg_sq")}
    report = strategy.step(1, params, optimizer, torch.Generator().manual_seed(0))
    assert report == {"cloned": 1, "split": 1, "pruned": 1}
    # rows: G0, G2 kept; G0's clone; G1's two children (G1 itself replaced, G3 pruned)
    assert len(params["means"]) == 5
    for name in params:
        torch.testing.assert_close(params[name][[0, 1, 2]].detach(), before[name][[0, 2, 0]])
    # the children are drawn from the parent's Gaussian: the draws scaled by its axes, turned by its rotation
    # (about 90 deg about z: Adam's step moved the quaternion a little), as the axis-angle of its quaternion
    draws = torch.randn(2, 3, generator=torch.Generator().manual_seed(0)) * before["scales"][1].exp()
    w, vector = before["quats"][1, 0], before["quats"][1, 1:]
    angle = 2 * torch.atan2(vector.norm(), w)
    rotation = torch.linalg.matrix_exp(skew_reference(vector / vector.norm() * angle))
    torch.testing.assert_close(params["means"][3:].detach(), before["means"][1] + draws @ rotation.T)
    torch.testing.assert_close(params["scales"][3:].detach(), (before["scales"][1].exp() / 1.6).log().expand(2, 3))
    torch.testing.assert_close(params["opacities"][3:].detach(), before["opacities"][1].expand(2))
    # Adam's moments (both) follow their rows; new rows start at zero
    for (name, key), moment in moments.items():
        state = optimizer.state[params[name]][key]
        assert state.shape == params[name].shape
        torch.testing.assert_close(state[[0, 1]], moment[[0, 2]])
        assert not state[2:].any()


def test_a_large_flat_gaussian_is_split_not_cloned():
    """Clone or split is decided by a Gaussian's largest axis: a flat one (0.1 long, 0.005 thin, against
    percent_dense 0.01) is large."""
    params, optimizer, strategy = _four_gaussians()
    with torch.no_grad():
        params["scales"][1] = torch.log(torch.tensor([0.1, 0.005, 0.005]))
    report = strategy.step(1, params, optimizer, torch.Generator().manual_seed(0))
    assert report == {"cloned": 1, "split": 1, "pruned": 1}  # G0 cloned, G1 split
    torch.testing.assert_close(params["scales"][3:].detach().exp(), torch.tensor([[0.1, 0.005, 0.005]]).expand(2, 3)
                               / 1.6)


def test_densification_restarts_the_gradient_statistics():
    """After a densification the statistics start again from zero, one per Gaussian of the new set."""
    params, optimizer, strategy = _four_gaussians()
    strategy.step(1, params, optimizer, torch.Generator().manual_seed(0))
    assert len(params["means"]) == 5
    torch.testing.assert_close(strategy.grad_sum, torch.zeros(5))
    torch.testing.assert_close(strategy.grad_count, torch.zeros(5))


@pytest.mark.parametrize(("iteration", "densifies"), [(1, True), (2, False)])
def test_densification_runs_before_stop_and_not_at_it(iteration, densifies):
    """The schedule is [start, stop): with stop = 2, iteration 1 densifies and iteration 2 changes nothing."""
    params, optimizer, strategy = _four_gaussians()
    strategy.config = dataclasses.replace(strategy.config, stop=2)
    report = strategy.step(iteration, params, optimizer, torch.Generator().manual_seed(0))
    assert (report == {"cloned": 1, "split": 1, "pruned": 1}) == densifies
    assert (len(params["means"]) == 4) != densifies


def test_oversized_gaussians_are_pruned():
    params, optimizer, strategy = _four_gaussians()
    strategy.grad_sum = torch.zeros(4)  # nothing densified
    strategy.config = dataclasses.replace(strategy.config, prune_scale=0.07)  # G1's 0.1 is above it, G2's 0.05 not
    before = params["means"].detach().clone()
    report = strategy.step(1, params, optimizer, torch.Generator().manual_seed(0))
    assert report == {"cloned": 0, "split": 0, "pruned": 2}  # G1 by its size, G3 by its opacity
    torch.testing.assert_close(params["means"].detach(), before[[0, 2]])


def test_a_short_budget_keeps_the_largest_gradients():
    params, optimizer, strategy = _four_gaussians()
    strategy.config = dataclasses.replace(strategy.config, max_gaussians=5)  # room for one more
    report = strategy.step(1, params, optimizer, torch.Generator().manual_seed(0))
    assert report == {"cloned": 1, "split": 0, "pruned": 1}  # G0's gradient (2.0) beats G1's (1.0)


def test_the_opacity_reset_caps_opacities_and_zeroes_their_moments():
    params, optimizer, strategy = _four_gaussians()
    with torch.no_grad():
        params["opacities"][3] = math.log(0.001 / 0.999)  # below the cap: kept as it is
    strategy.config = dataclasses.replace(strategy.config, start=50, opacity_reset_every=1)
    report = strategy.step(1, params, optimizer, torch.Generator().manual_seed(0))
    assert report == {"opacity_reset": 1}
    torch.testing.assert_close(torch.sigmoid(params["opacities"]).detach(), torch.tensor([0.01, 0.01, 0.01, 0.001]))
    state = optimizer.state[params["opacities"]]
    assert not state["exp_avg"].any() and not state["exp_avg_sq"].any()


def test_a_step_that_no_step_follows_neither_grows_nor_resets():
    """`grows=False` (the coarse stage's last iteration): no clone, split, prune or opacity reset is scheduled."""
    params, optimizer, strategy = _four_gaussians()
    strategy.config = dataclasses.replace(strategy.config, start=1, stop=10, every=1, grad_threshold=1e-12,
                                          opacity_reset_every=1)
    strategy.grad_sum, strategy.grad_count = torch.ones(4), torch.ones(4)
    before = {name: param.detach().clone() for name, param in params.items()}
    assert strategy.step(1, params, optimizer, torch.Generator().manual_seed(0), grows=False) == {}
    assert all(torch.equal(params[name].detach(), value) for name, value in before.items())
    assert {"cloned", "opacity_reset"} <= strategy.step(1, params, optimizer, torch.Generator().manual_seed(0)).keys()


def test_pruning_keeps_the_most_opaque_gaussian_of_all_transparent_ones_and_no_reset_comes_at_or_after_stop():
    """Two guards no test reached (each removed, the tests passed): a prune of every Gaussian keeps the most opaque
    one, and the opacity reset happens only before `stop`."""
    params, optimizer, strategy = _four_gaussians()
    with torch.no_grad():
        params["opacities"].copy_(torch.logit(torch.tensor([0.001, 0.003, 0.002, 0.0005])))
    strategy.grad_sum = torch.zeros(4)  # nothing cloned or split
    report = strategy.step(1, params, optimizer, torch.Generator().manual_seed(0))
    assert report["pruned"] == 3 and len(params["means"]) == 1
    torch.testing.assert_close(torch.sigmoid(params["opacities"]).detach(), torch.tensor([0.003]))
    params, optimizer, strategy = _four_gaussians()
    strategy.config = dataclasses.replace(strategy.config, start=1000, stop=20, opacity_reset_every=10)
    assert [("opacity_reset" in strategy.step(i, params, optimizer, torch.Generator())) for i in (10, 20, 30)] == [
        True, False, False]


def _cloud_with_a_floater(count, generator, distance=10.0):
    """`count` means around the origin (standard deviation 0.2), Gaussian 0 at (`distance`,) * 3; Adam over the
    means and opacities."""
    means = torch.randn(count, 3, generator=generator) * 0.2
    means[0] = distance
    params = {"means": torch.nn.Parameter(means), "opacities": torch.nn.Parameter(torch.zeros(count))}
    optimizer = torch.optim.Adam([{"params": [p], "name": n} for n, p in params.items()])
    return params, optimizer


@pytest.mark.parametrize("white_background", [False, True])
def test_floaters_and_resets_follow_gaussianobjects_schedule(white_background):
    """GaussianObject (as 3DGS) removes floaters and resets opacities only before `stop`, and on a white background
    once more at `start`; the floater removal ran to the end of the round, the saved model included."""
    config = DensifyConfig(start=30, stop=100, every=1000, opacity_reset_every=40, floater_every=20)
    strategy = DensifyStrategy(config, scene_extent=1.0, white_background=white_background)
    done = {}
    for iteration in range(1, 201):
        g = torch.Generator().manual_seed(iteration)
        params, optimizer = _cloud_with_a_floater(100, g)  # a floater at every step
        for key in strategy.step(iteration, params, optimizer, g):
            done.setdefault(key, []).append(iteration)
    extra = [30] if white_background else []
    assert done["floaters"] == sorted([20, 40, 60, 80, *extra])
    assert done["opacity_reset"] == sorted([40, 80, *extra])


def test_a_smaller_floater_std_ratio_removes_more():
    """`floater_std_ratio` is how many standard deviations above the average neighbour distance "far" begins."""
    removed = {}
    for ratio in (0.5, 3.0):
        generator = torch.Generator().manual_seed(0)
        # not so far that it alone makes the standard deviation, which would leave only it above any ratio
        params, optimizer = _cloud_with_a_floater(400, generator, distance=5.0)
        config = DensifyConfig(floater_every=10, opacity_reset_every=0, floater_std_ratio=ratio)
        removed[ratio] = DensifyStrategy(config, 1.0).step(10, params, optimizer, generator).get("floaters", 0)
    assert removed[0.5] > removed[3.0] >= 1, removed


def test_a_floater_removal_keeps_the_survivors_gradient_statistics():
    """Off the densification grid (`floater_every` not a multiple of `every`) the survivors' statistics of the
    interval so far stay: restarted, the next densification would judge on the steps after the removal only."""
    params, optimizer = _cloud_with_a_floater(100, torch.Generator().manual_seed(0))
    config = DensifyConfig(start=0, stop=1000, every=100, floater_every=30, opacity_reset_every=0)
    strategy = DensifyStrategy(config, scene_extent=1.0)
    strategy.grad_sum, strategy.grad_count = torch.arange(100.0), torch.full((100,), 29.0)
    assert strategy.step(30, params, optimizer, torch.Generator()) == {"floaters": 1}  # Gaussian 0
    torch.testing.assert_close(strategy.grad_sum, torch.arange(1.0, 100.0))
    # the next step adds to them
    means2d = torch.zeros(1, 99, 2, requires_grad=True)
    means2d.sum().backward()
    strategy.accumulate(30, {"means2d": means2d, "radii": torch.ones(1, 99, dtype=torch.int32), "width": 2,
                             "height": 2})
    torch.testing.assert_close(strategy.grad_count, torch.full((99,), 30.0))
    torch.testing.assert_close(strategy.grad_sum, torch.arange(1.0, 100.0) + 2 ** 0.5)

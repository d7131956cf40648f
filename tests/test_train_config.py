"""Training presets: `paper()` and `quick()` give exactly the configs they gave before `paper()` stopped restating the
dataclass defaults (values written down at b03b2db); the defaults are the paper schedule's coarse stage."""

from __future__ import annotations

import dataclasses

import pytest

from warpbags.configs.train import RepairConfig, TrainConfig, paper, quick
from warpbags.errors import WarpbagsError

PAPER = {
    "preset": "paper", "views": 4, "iters": 5000, "rounds": 1, "pose_opt": True, "pose_opt_start": 1000,
    "pose_round_window": (0.0, 1.0), "pose_round_windows": (), "depth_until": 1000,
    "rot_noise_deg": 0.0, "rot_noise_fixed": False, "trans_noise": 0.0, "noise_seed": 0,
    "seed": 0, "resolution": None, "max_image_size": 0, "pyramid_levels": 1, "views_per_step": 1, "background": "white",
    "sh_degree": 2, "sh_degree_every": 1000, "init": "hull", "init_points": 20000, "hull_resolution": 64,
    "hull_dilation_px": 0, "hull_missed_views": 1, "blur_sigma_px": 0.0, "blur_until": 0, "lambda_dssim": 0.2,
    "lambda_mask": 0.01, "lambda_depth": 0.05, "lambda_mask_distance": 0.0, "lambda_chamfer": 1.0,
    "silhouette_until": 0, "lambda_epipolar": 0.0, "matches_min_inliers": 40, "depth_loss": "mad",
    "checkpoint_every": 500, "pose_alignment": "procrustes",
    "render_threads": 0,
    "lr": {"means_init": 0.00016, "means_final": 1.6e-06, "sh_dc": 0.0025, "sh_rest": 0.000125, "opacities": 0.05,
           "scales": 0.005, "quats": 0.001, "adam_eps": 1e-15, "pose": 0.003, "pose_final": 0.0003,
           "pose_translation_scale": 1.0, "pose_warmup": 0},
    "camera": {"parameterization": "object", "precondition": True, "precondition_reg": 0.1, "centroid_start": True, "coherence_iters": 100,
               "coherence_continued_from_views": 6, "coherence_epipolar": 0.0,
               "fix_first_camera": False, "orbit_from_round": 0, "round_anchor": 0.0,
               "lbfgs_from_round": None, "lbfgs_every": 10, "lbfgs_iters": 10, "hypotheses_round": 0,
               "hypothesis_axes": "z", "hypothesis_angles": (15.0, 30.0), "hypothesis_margin": 0.05,
               "average_share": 0.0},
    "densify": {"start": 500, "stop": 3000, "every": 100, "grad_threshold": 0.0002, "percent_dense": 0.01,
                "prune_opacity": 0.005, "prune_scale": 0.1, "opacity_reset_every": 1000, "max_gaussians": 0,
                "floater_every": 500, "floater_std_ratio": 3.0},
    "repair": {"iters": 3000, "loo_iters": 5000, "loo_snapshot": 3000, "loo_samples": 8, "noise_renders": 8,
               "noise_clamp_std": (0.6, 0.8), "noise_dropout": (0.6, 0.8), "repairer": "unet", "unet_channels": 32,
               "fit_steps": 2000, "fit_lr": 0.002, "fit_batch": 8, "fit_crop": 128, "pseudo_views": 20,
               "refresh_every": 200, "pseudo_ratio_start": 1.0, "pseudo_ratio_end": 0.5, "pseudo_until": 0.7,
               "weight_l1": 0.5, "weight_l2": 0.5, "weight_lpips": 2.0, "samples_kept": 3},
}

QUICK = {
    "preset": "quick", "views": 4, "iters": 600, "rounds": 3, "pose_opt": True, "pose_opt_start": 0,
    "pose_round_window": (0.25, 1.0), "pose_round_windows": (), "depth_until": 100,
    "rot_noise_deg": 0.0, "rot_noise_fixed": False, "trans_noise": 0.0, "noise_seed": 0,
    "seed": 0, "resolution": None, "max_image_size": 128, "pyramid_levels": 1, "views_per_step": 0,
    "background": "white", "sh_degree": 0, "sh_degree_every": 1000, "init": "hull", "init_points": 3000,
    "hull_resolution": 48, "hull_dilation_px": 2, "hull_missed_views": 1, "blur_sigma_px": 0.0, "blur_until": 0,
    "lambda_dssim": 0.2, "lambda_mask": 0.01, "lambda_depth": 0.05, "lambda_mask_distance": 0.0,
    "lambda_chamfer": 1.0, "silhouette_until": 0, "lambda_epipolar": 0.0, "matches_min_inliers": 40,
    "depth_loss": "mad", "checkpoint_every": 100,
    "pose_alignment": "procrustes", "render_threads": 0,
    "lr": {"means_init": 0.0016, "means_final": 1.6e-05, "sh_dc": 0.0025, "sh_rest": 0.000125, "opacities": 0.05,
           "scales": 0.005, "quats": 0.001, "adam_eps": 1e-15, "pose": 0.01, "pose_final": 0.001,
           "pose_translation_scale": 0.1, "pose_warmup": 20},
    "camera": {"parameterization": "object", "precondition": True, "precondition_reg": 0.1, "centroid_start": True, "coherence_iters": 100,
               "coherence_continued_from_views": 6, "coherence_epipolar": 0.0,
               "fix_first_camera": False, "orbit_from_round": 0, "round_anchor": 0.0,
               "lbfgs_from_round": None, "lbfgs_every": 10, "lbfgs_iters": 10, "hypotheses_round": 1,
               "hypothesis_axes": "z", "hypothesis_angles": (15.0, 30.0), "hypothesis_margin": 0.05,
               "average_share": 1.0},
    "densify": {"start": 100, "stop": 201, "every": 50, "grad_threshold": 0.0008, "percent_dense": 0.01,
                "prune_opacity": 0.005, "prune_scale": 0.1, "opacity_reset_every": 0, "max_gaussians": 6000,
                "floater_every": 0, "floater_std_ratio": 3.0},
    "repair": {"iters": 0, "loo_iters": 300, "loo_snapshot": 200, "loo_samples": 4, "noise_renders": 8,
               "noise_clamp_std": (0.6, 0.8), "noise_dropout": (0.6, 0.8), "repairer": "unet", "unet_channels": 16,
               "fit_steps": 400, "fit_lr": 0.002, "fit_batch": 8, "fit_crop": 64, "pseudo_views": 8,
               "refresh_every": 50, "pseudo_ratio_start": 1.0, "pseudo_ratio_end": 0.5, "pseudo_until": 0.7,
               "weight_l1": 0.5, "weight_l2": 0.5, "weight_lpips": 2.0, "samples_kept": 3},
}


def test_presets_are_unchanged_by_the_refactor():
    """Exact equality, types included (1000 and 1000.0 compare equal, so the reprs are compared too)."""
    for make, expected in ((paper, PAPER), (quick, QUICK)):
        values = make().to_dict()
        assert values == expected, make.__name__
        assert repr(values) == repr(expected), make.__name__


def test_paper_is_the_defaults_with_its_repair_stage():
    assert dataclasses.replace(paper(), repair=RepairConfig()) == TrainConfig()
    assert paper().repair.iters > 0 and TrainConfig().repair.iters == 0


def test_a_field_declared_of_any_length_takes_a_list_of_any_length():
    """`camera.hypothesis_angles` is `tuple[float, ...]`: one angle or three, not only the default's two; a pair such
    as `pose_round_window` keeps its length."""
    from warpbags.configs.train import load_preset

    assert load_preset("quick", camera={"hypothesis_angles": [20]}).camera.hypothesis_angles == (20,)
    assert load_preset("quick", camera={"hypothesis_angles": [10, 20, 30]}).camera.hypothesis_angles == (10, 20, 30)
    with pytest.raises(WarpbagsError, match="hypothesis_angles must be different degrees"):
        load_preset("quick", camera={"hypothesis_angles": []})
    with pytest.raises(WarpbagsError, match="pose_round_window must be like"):
        load_preset("quick", pose_round_window=[0.25])


def test_values_that_would_break_training_later_are_refused_up_front():
    """A learning-rate schedule interpolates in log space and densification divides by its period: such values fail
    at load time with the field's name, not as a math error hundreds of iterations into a run."""
    from warpbags.configs.train import load_preset

    for overrides, message in [({"lr": {"pose_final": 0}}, "lr.pose_final must be > 0"),
                               ({"lr": {"means_init": -1e-4}}, "lr.means_init must be > 0"),
                               ({"lr": {"quats": -1}}, "lr.quats must be >= 0"),
                               ({"densify": {"every": 0}}, "densify.every must be >= 1"),
                               ({"camera": {"coherence_continued_from_views": -1}},
                                "camera.coherence_continued_from_views must be >= 0")]:
        with pytest.raises(WarpbagsError, match=message):
            load_preset("quick", **overrides)
    assert load_preset("quick", lr={"sh_rest": 0}).lr.sh_rest == 0  # a group held still is allowed


def test_parse_settings_refuses_a_field_of_a_group_set_to_a_value():
    """The benchmarks' `--set`: `repair=3` then `repair.iters=1` is one clear error, not a TypeError."""
    from warpbags.configs.train import parse_settings

    assert parse_settings(["repair.iters=1", "views=6"]) == {"repair": {"iters": 1}, "views": 6}
    with pytest.raises(WarpbagsError, match="--set 'repair.iters=1': repair was set to 3, not a group of fields"):
        parse_settings(["repair=3", "repair.iters=1"])


def _float_fields(config, prefix=""):
    """(dotted name, value) of every float field of a config dataclass and its groups, tuples of floats included."""
    for item in dataclasses.fields(config):
        value = getattr(config, item.name)
        if dataclasses.is_dataclass(value):
            yield from _float_fields(value, f"{prefix}{item.name}.")
        elif isinstance(value, float) or (isinstance(value, tuple) and value and isinstance(value[0], float)):
            yield prefix + item.name, value


def _override(path, value):
    """load_preset's keyword overrides setting the field at dotted `path`."""
    group, _, name = path.rpartition(".")
    return {group: {name: value}} if group else {name: value}


def test_every_float_field_must_be_finite():
    """NaN and inf pass `>= 0`-style checks (inf) or fail them with a misleading message (NaN): `--trans-noise inf`
    reached a LinAlgError in the preconditioner, `--set lambda_dssim=NaN` diverged at iteration 0. Every float field
    of the whole tree, a list's items too, is refused by one check that names it (its option where it has one)."""
    from warpbags.configs.train import FLOAT_OPTIONS, load_preset

    found = dict(_float_fields(quick()))
    assert {"trans_noise", "lr.sh_dc", "camera.hypothesis_angles", "densify.grad_threshold",
            "repair.noise_dropout"} <= set(found)  # the walk reaches every group
    for path, value in found.items():
        for bad in (float("nan"), float("inf"), float("-inf")):
            if isinstance(value, tuple):
                given, shown = [value[0], bad], rf"\[{value[0]}, {bad}\]"
                name = path
            else:
                given, shown, name = bad, str(bad), FLOAT_OPTIONS.get(path, path)
            with pytest.raises(WarpbagsError, match=rf"^{name} must be (a )?finite numbers?, got {shown}$"):
                load_preset("quick", **_override(path, given))
    with pytest.raises(WarpbagsError, match=r"^pose_round_windows must be finite numbers, got \[\(0.1, nan\)\]$"):
        load_preset("quick", pose_round_windows=[[0.1, float("nan")]])


def test_non_finite_values_are_named_by_their_train_option():
    """FLOAT_OPTIONS, the float fields' `warpbags train` options as validate names them, are TRAIN_OPTIONS's."""
    from warpbags.cli.train_options import TRAIN_OPTIONS, field_type
    from warpbags.configs.train import FLOAT_OPTIONS

    options = {option.path: option.flag for option in TRAIN_OPTIONS
               if option.sets is None and field_type(option.path) is float}
    assert FLOAT_OPTIONS == options


def test_range_checks_that_training_needed():
    """Each value refused here crashed or silently misbehaved later: a segfault in the renderer (render_threads -1),
    a ZeroDivisionError in carving (hull_resolution 0), a diverging run (max_image_size 1, --trans-noise 1e30), a
    TypeError (lr.pose null), a blur that is never applied (--blur-px with --blur-until 0, the presets' default). The
    seeds' and lr.adam_eps's ranges have tests of their own, below."""
    from warpbags.configs.train import load_preset

    for overrides, message in [
            ({"trans_noise": 1e30}, r"--trans-noise must be <= 4 \(a std in normalized scene units, where the "
                                    r"cameras orbit at radius 4\), got 1e\+30"),
            ({"render_threads": -1}, r"render_threads must be in \[0, 1024\]"),
            ({"render_threads": 100000}, r"render_threads must be in \[0, 1024\] \(0: all cores\), got 100000"),
            ({"hull_resolution": 0}, r"hull_resolution must be in \[2, 256\]"),
            ({"hull_resolution": 1000}, r"hull_resolution must be in \[2, 256\]"),
            ({"hull_missed_views": -1}, "hull_missed_views must be >= 0"),
            ({"hull_dilation_px": -1}, r"hull_dilation_px must be in \[0, 100\]"),
            # a traceback from OpenCV's allocator; numpy's for as many points
            ({"hull_dilation_px": 1000000}, r"hull_dilation_px must be in \[0, 100\], got 1000000"),
            ({"init_points": 10**13}, r"init_points must be in \[1, 5000000\]"),
            ({"repair": {"fit_batch": 10**8}}, r"repair.fit_batch must be in \[1, 256\]"),  # the machine's memory
            # a window of no iteration, where the Gaussians never densify
            ({"densify": {"start": 10, "stop": 2}}, "densify.start and densify.stop must be 0 <= start <= stop"),
            ({"densify": {"start": -100, "stop": -50}}, "densify.start and densify.stop must be 0 <= start <= stop"),
            # turns trained twice, or a turn that is the camera unturned: whole rounds wasted
            ({"camera": {"hypothesis_axes": "zz"}}, "camera.hypothesis_axes must be different letters of xyz"),
            ({"camera": {"hypothesis_angles": [15, 15]}}, r"camera.hypothesis_angles must be different degrees"),
            ({"camera": {"hypothesis_angles": [360]}}, r"degrees in \(0, 180\]"),
            ({"rot_noise_fixed": True}, "--rot-noise-fixed needs --rot-noise-deg > 0"),  # did nothing
            ({"sh_degree_every": 0}, "sh_degree_every must be >= 1"),
            ({"views_per_step": 5}, r"views_per_step must be in \[0, views = 4\] \(0 = all\), got 5"),
            ({"views_per_step": -1}, r"views_per_step must be in \[0, views = 4\]"),
            ({"lambda_dssim": 1.5}, r"lambda_dssim must be in \[0, 1\], got 1.5"),
            ({"lambda_dssim": -0.1}, r"lambda_dssim must be in \[0, 1\]"),
            ({"lambda_mask": -1}, "lambda_mask must be >= 0"),
            ({"max_image_size": 1}, r"--max-image-size must be 0 \(off\) or >= 16"),
            ({"max_image_size": -1}, r"--max-image-size must be 0 \(off\) or >= 16"),
            ({"depth_until": -1}, "depth_until must be >= 0"),
            ({"densify": {"max_gaussians": -1}}, "densify.max_gaussians must be >= 0"),
            ({"densify": {"grad_threshold": 0}}, "densify.grad_threshold must be > 0"),
            ({"densify": {"percent_dense": -0.01}}, "densify.percent_dense must be >= 0"),
            ({"densify": {"prune_opacity": 1}}, r"densify.prune_opacity must be in \[0, 1\)"),
            ({"densify": {"prune_scale": 0}}, "densify.prune_scale must be > 0"),
            ({"densify": {"floater_std_ratio": -1}}, "densify.floater_std_ratio must be >= 0"),
            ({"blur_sigma_px": 4.0}, r"--blur-px 4 needs --blur-until > 0 .*got --blur-until 0")]:
        with pytest.raises(WarpbagsError, match=message):
            load_preset("quick", **overrides)
    # the limits themselves pass
    for overrides in [{"trans_noise": 4}, {"render_threads": 1024}, {"hull_resolution": 2}, {"hull_missed_views": 0},
                      {"sh_degree_every": 1}, {"views_per_step": 4}, {"lambda_dssim": 1}, {"lambda_mask": 0},
                      {"max_image_size": 0}, {"max_image_size": 16},
                      {"densify": {"max_gaussians": 0, "prune_opacity": 0, "floater_std_ratio": 0}},
                      {"blur_sigma_px": 4.0, "blur_until": 1}, {"blur_sigma_px": 0.0, "blur_until": 0},
                      {"hull_dilation_px": 100}, {"init_points": 5_000_000}, {"repair": {"fit_batch": 256}},
                      {"densify": {"start": 5, "stop": 5}}, {"camera": {"hypothesis_angles": [180]}},
                      {"rot_noise_fixed": True, "rot_noise_deg": 10.0}]:
        load_preset("quick", **overrides)


def test_seeds_are_refused_where_torch_would_take_them_as_another_seed():
    """torch's CPU generator keeps a seed modulo 2^32 (a negative one too), so [-2^63, 2^63) passed seeds that
    train as others: 2^32 as 0 (a sweep's `--seeds 0,4294967296` reported one run twice), -1 as 2^32 - 1. The
    message says why and which seed it would have been; a seed past 64 bits (torch's OverflowError) is refused too."""
    from warpbags.configs.train import load_preset

    for field, option in (("seed", "--seed"), ("noise_seed", "--noise-seed")):
        for seed, same in [(2**32, 0), (-1, 2**32 - 1), (2**32 + 5, 5), (2**70, 0)]:
            with pytest.raises(WarpbagsError, match=rf"^{option} must be in \[0, 2\^32\), got {seed}: torch's CPU "
                                                    rf"generator keeps a seed modulo 2\^32, so it would act as seed "
                                                    rf"{same}$"):
                load_preset("quick", **{field: seed})
        for seed in (0, 2**32 - 1):  # the limits themselves pass
            assert getattr(load_preset("quick", **{field: seed}), field) == seed


def test_an_adam_eps_that_float32_cannot_hold_is_refused():
    """lr.adam_eps 1e-50 passed (only > 0 was checked) and is 0 in the Gaussians' float32 Adam, whose first step
    divided 0 by 0: "training diverged" at iteration 1. Below float32's smallest normal number it is refused, named;
    that number itself passes and trains finite steps where a gradient is 0."""
    import torch
    from warpbags.configs.train import load_preset

    tiny = torch.finfo(torch.float32).tiny
    for eps in (1e-50, tiny / 2, 0.0):
        with pytest.raises(WarpbagsError, match=rf"^lr.adam_eps must be >= {tiny}, the smallest normal float32 "):
            load_preset("quick", lr={"adam_eps": eps})
    assert load_preset("quick", lr={"adam_eps": tiny}).lr.adam_eps == tiny
    parameter = torch.nn.Parameter(torch.ones(2))
    optimizer = torch.optim.Adam([parameter], lr=0.1, eps=tiny, fused=True)  # as `gaussian_optimizer` builds it
    parameter.grad = torch.tensor([0.0, 1.0])
    optimizer.step()
    assert parameter.detach().tolist() == pytest.approx([1.0, 0.9])


def test_a_saved_config_from_before_a_bound_still_resumes():
    """A run saved a blur without blur_until (never applied), more render threads than MAX_RENDER_THREADS or a seed
    outside [0, 2^32) before `validate` refused them: its config reads back as what it trained with (torch kept the
    seed modulo 2^32), and resuming validates it."""
    from warpbags.configs.train import MAX_RENDER_THREADS, TrainConfig

    saved = TrainConfig.from_dict({"blur_sigma_px": 4.0, "blur_until": 0, "render_threads": 5000, "seed": -1,
                                   "noise_seed": 2**32 + 7})
    assert (saved.blur_sigma_px, saved.render_threads) == (0.0, MAX_RENDER_THREADS)
    assert (saved.seed, saved.noise_seed) == (2**32 - 1, 7)
    assert saved.replaced() == saved
    with pytest.raises(WarpbagsError, match="seed must be like 0, got True"):
        TrainConfig.from_dict({"seed": True})
    assert TrainConfig.from_dict({"blur_sigma_px": 4.0, "blur_until": 50}).blur_sigma_px == 4.0


def test_a_field_that_may_be_null_is_typed_by_its_declaration():
    """`resolution: int | None` and `camera.lbfgs_from_round` have the default None, which tells no type: 2.0 and true
    passed (2.0 == 2 and True == 1 pass `resolution in (None, 1, 2, 4, 8)`) and were saved so. A field that may not be
    null refuses null (it reached validate's comparisons as a TypeError), and a list of numbers refuses text."""
    from warpbags.configs.train import load_preset

    for overrides, message in [({"resolution": 2.0}, "resolution must be an integer or null, got 2.0"),
                               ({"resolution": True}, "resolution must be an integer or null, got True"),
                               ({"resolution": "2"}, "resolution must be an integer or null, got '2'"),
                               ({"camera": {"lbfgs_from_round": 1.0}},
                                "camera.lbfgs_from_round must be an integer or null, got 1.0"),
                               ({"camera": {"lbfgs_from_round": False}},
                                "camera.lbfgs_from_round must be an integer or null, got False"),
                               ({"lr": {"pose": None}}, "lr.pose must be like 0.01, got None"),
                               ({"camera": {"hypothesis_angles": ["a"]}},
                                r"camera.hypothesis_angles must be a list of numbers, got \['a'\]"),
                               ({"repair": {"noise_clamp_std": ["a", 1]}},
                                r"repair.noise_clamp_std must be like \(0.6, 0.8\), got \('a', 1\)")]:
        with pytest.raises(WarpbagsError, match=f"^{message}$"):
            load_preset("quick", **overrides)
    assert load_preset("quick", resolution=2).resolution == 2
    assert load_preset("quick", camera={"lbfgs_from_round": 0}).camera.lbfgs_from_round == 0
    assert load_preset("quick", camera={"lbfgs_from_round": None}).camera.lbfgs_from_round is None
    saved = load_preset("quick", resolution=4).to_dict()
    assert TrainConfig.from_dict(saved).resolution == 4 and TrainConfig.from_dict(quick().to_dict()) == quick()

"""Pose recovery benchmark: train with injected noise, print initial/final pose errors and seconds/iteration.

    python bench/train_poses.py SCENE [--views 4] [--rot 15] [--trans 0.1] [--preset quick] [key=value ...]

SCENE: a preset name (maryrose, synthetic) or `synthetic-small` (a 16-view 96 px synthetic scene in the cache).
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time

import torch
from warpbags.configs.train import load_preset

from warpbags.data import SyntheticOptions, ensure_synthetic_scene, load_scene
from warpbags.trainer import Trainer, training_scene


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("scene")
    parser.add_argument("--views", type=int, default=4)
    parser.add_argument("--rot", type=float, default=15.0)
    parser.add_argument("--trans", type=float, default=0.1)
    parser.add_argument("--preset", default="quick")
    parser.add_argument("overrides", nargs="*", help="TrainConfig fields as key=value (JSON values)")
    args = parser.parse_intermixed_args()
    overrides = {key: json.loads(value) for key, value in (item.split("=", 1) for item in args.overrides)}
    config = load_preset(args.preset, views=args.views, rot_noise_deg=args.rot, trans_noise=args.trans, **overrides)
    if args.scene == "synthetic-small":
        scene = load_scene(ensure_synthetic_scene(SyntheticOptions(views=16, width=96, height=96)), name="synthetic-small")
    else:
        scene = args.scene
    scene = training_scene(scene, config)
    with tempfile.TemporaryDirectory() as out:
        trainer = Trainer(scene, config, out)
        initial = trainer.pose_error()
        started = time.perf_counter()
        records = []
        trainer.train(callback=lambda r: (records.append(r), r["iter"] % 50 == 0 and print(
            f"{r['iter']:5d} loss {r['loss']:.4f} N {r['num_gaussians']} rot {r['rot_err_deg']:.3f} trans {r['trans_err']:.4f}", flush=True)))
        seconds = (time.perf_counter() - started) / len(records)
    final = records[-1]
    print(json.dumps({"scene": args.scene, "views": args.views, "size": [scene.width, scene.height], "rot_noise_deg": args.rot,
                      "trans_noise": args.trans, "initial_rot_err_deg": initial["rot_err_deg"], "initial_trans_err": initial["trans_err"],
                      "final_rot_err_deg": final["rot_err_deg"], "final_trans_err": final["trans_err"],
                      "final_loss": final["loss"], "num_gaussians": final["num_gaussians"], "seconds_per_iter": seconds,
                      "overrides": overrides}))


if __name__ == "__main__":
    torch.set_num_threads(1)
    main()

"""Do the training views share feature matches? SIFT between every pair, checked against the reference poses.

    python bench/view_matches.py SCENE [SCENE ...] [--views 4,6,9] [--features 4000] [--ratio 0.85]
        [--true-px 2] [--ransac-px 1.5] [--min-inliers 15] [--pairs] [--json PATH]

SCENE: as bench/pose_recovery.py (a preset, a folder, or one of its small synthetic scenes). For each scene and view
count, OpenCV SIFT finds features inside each training view's mask (eroded by 2 px, so the background's edge does
not count) at the resolution the scene is read at, and for every pair of views:

- the ratio test (Lowe) keeps a match whose nearest descriptor is closer than `--ratio` times the second nearest;
- a match is *true* when its Sampson distance to the epipolar geometry of the reference poses is under `--true-px`
  pixels: what a correspondence loss on the poses (SPARF's idea, without its network) would need;
- MAGSAC (OpenCV's USAC) fits a fundamental matrix to the matches (`--ransac-px`): what a method that does not know
  the poses would keep. A pair is *kept* with at least `--min-inliers` inliers, and *right* when most of its inliers
  are true.

The table gives, per scene and view count, the pairs, those with at least 10 true matches, those kept, how many of
the kept are right, and the true share of all kept inliers: where it is low, the matches that survive geometric
verification are mostly wrong, and a correspondence term would pull the poses towards them.
"""

from __future__ import annotations

import argparse
import itertools
import math
import time
from pathlib import Path

import torch

from common import check_json, check_options, check_view_counts, open_bench_scene, write_json
from warpbags.cli.common import clean_errors, parse_numbers
from warpbags.correspondences import (RANSAC_PX, RATIO, SIFT_FEATURES, fundamental_matrices, match_pair,
                                      sampson_distances, sift_detector, view_features)

TRUE_PAIR_MATCHES = 10


def pair_matches(features_a, features_b, F_reference: torch.Tensor, ratio: float, true_px: float, ransac_px: float
                 ) -> dict:
    """The ratio-test matches of two views, how many are true under `F_reference`, MAGSAC's inliers and their
    true ones."""
    matched_a, matched_b, inliers = match_pair(features_a, features_b, ratio, ransac_px)
    true = (sampson_distances(F_reference, torch.from_numpy(matched_a), torch.from_numpy(matched_b)) < true_px).numpy()
    return {"matches": len(matched_a), "true": int(true.sum()), "inliers": int(inliers.sum()),
            "true_inliers": int((inliers & true).sum())}


def view_matches(scene, views: int, features: int, ratio: float, true_px: float, ransac_px: float,
                 min_inliers: int) -> dict:
    """Every pair of the scene's `views` training views (as training picks them: its sparse_N split, else
    farthest-point views): matches and their checks (`pair_matches`)."""
    started = time.perf_counter()
    chosen = scene.train_views(views)
    sift = sift_detector(features)
    viewmats, Ks = scene.viewmats.double(), scene.Ks.double()
    features_of = {i: view_features(scene.images[i].numpy(), None if scene.masks is None else scene.masks[i].numpy(),
                                    sift) for i in chosen}
    pairs = []
    for a, b in itertools.combinations(chosen, 2):
        F = fundamental_matrices(viewmats[a], viewmats[b], Ks[a], Ks[b])
        axis_a, axis_b = viewmats[a, 2, :3], viewmats[b, 2, :3]  # optical axes in the world (rows of R)
        angle = math.degrees(math.acos(float((axis_a @ axis_b).clamp(-1.0, 1.0))))
        counts = pair_matches(features_of[a], features_of[b], F, ratio, true_px, ransac_px)
        kept = counts["inliers"] >= min_inliers
        pairs.append({"views": [a, b], "angle_deg": angle, **counts, "kept": kept,
                      "right": kept and 2 * counts["true_inliers"] > counts["inliers"]})
    kept_inliers = sum(p["inliers"] for p in pairs if p["kept"])
    return {
        "training_views": list(chosen), "size": [scene.width, scene.height],
        "features": [len(points) for points, _ in features_of.values()],
        "pairs": pairs,
        "with_true": sum(p["true"] >= TRUE_PAIR_MATCHES for p in pairs),
        "kept": sum(p["kept"] for p in pairs), "right": sum(p["right"] for p in pairs),
        "kept_true_share": sum(p["true_inliers"] for p in pairs if p["kept"]) / kept_inliers if kept_inliers else None,
        "minutes": (time.perf_counter() - started) / 60,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("scenes", nargs="+")
    parser.add_argument("--views", default="4,6,9",
                        help="training view counts, comma-separated (the views training would pick)")
    parser.add_argument("--features", type=int, default=SIFT_FEATURES, help="SIFT features per view at most")
    parser.add_argument("--ratio", type=float, default=RATIO, help="Lowe's ratio test")
    parser.add_argument("--true-px", type=float, default=2.0,
                        help="a match is true within this Sampson distance (px) of the reference epipolar geometry")
    parser.add_argument("--ransac-px", type=float, default=RANSAC_PX, help="MAGSAC's inlier threshold, px")
    parser.add_argument("--min-inliers", type=int, default=15, help="a pair is kept with this many inliers")
    parser.add_argument("--pairs", action="store_true", help="also print every pair with a true or kept match")
    parser.add_argument("--json", type=Path, help="also write every pair's numbers here")
    args = parser.parse_args()
    views = parse_numbers(args.views, "--views", int)
    check_options([(args.features > 0, f"--features must be positive, got {args.features}"),
                   (0 < args.ratio <= 1, f"--ratio must be in (0, 1], got {args.ratio}"),
                   (args.true_px > 0, f"--true-px must be positive, got {args.true_px}"),
                   (args.ransac_px > 0, f"--ransac-px must be positive, got {args.ransac_px}"),
                   (args.min_inliers >= 8, f"--min-inliers must be at least 8, got {args.min_inliers}"),
                   (min(views) >= 2, f"--views {args.views}: at least 2 views make a pair")])
    check_json(args.json)
    scenes = {name: open_bench_scene(name) for name in args.scenes}
    check_view_counts(scenes, views)
    header = (f"{'scene':<24} {'views':>5} {'px':>5} {'pairs':>5} {'with true':>9} {'kept':>5} {'right':>5} "
              f"{'true share of kept inliers':>26}")
    print(f"SIFT {args.features} features inside the masks, ratio {args.ratio}; true within {args.true_px} px of the "
          f"reference epipolar lines; MAGSAC {args.ransac_px} px, a pair kept with >= {args.min_inliers} inliers")
    print(header + "\n" + "-" * len(header), flush=True)
    rows = []
    for name, scene in scenes.items():
        for count in views:
            result = view_matches(scene, count, args.features, args.ratio, args.true_px, args.ransac_px,
                                  args.min_inliers)
            rows.append({"scene": name, "views": count, **result})
            share = result["kept_true_share"]
            print(f"{name:<24} {count:>5} {max(result['size']):>5} {len(result['pairs']):>5} {result['with_true']:>9} "
                  f"{result['kept']:>5} {result['right']:>5} {'-' if share is None else f'{share:.0%}':>26}"
                  f"  ({result['minutes'] * 60:.0f} s)", flush=True)
            if args.pairs:
                for pair in result["pairs"]:
                    if pair["true"] or pair["kept"]:
                        a, b = pair["views"]
                        print(f"    {a:>3}-{b:<3} {pair['angle_deg']:5.1f} deg apart: {pair['matches']:4d} matches, "
                              f"{pair['true']:4d} true, {pair['inliers']:4d} inliers of which {pair['true_inliers']} "
                              f"true{'' if pair['kept'] else ' (not kept)'}")
            if args.json:
                settings = {name: value for name, value in vars(args).items() if name != "json"}
                write_json(args.json, {"settings": settings, "rows": rows})
    print(f"pairs: of the training views; with true: at least {TRUE_PAIR_MATCHES} matches consistent with the reference "
          "poses; kept: pairs MAGSAC keeps; right: kept pairs most of whose inliers are true")


if __name__ == "__main__":
    clean_errors(main)()  # a bad scene name or option: one line and exit code 2, as the CLI

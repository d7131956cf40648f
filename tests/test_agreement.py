"""`warpbags agree`: how far runs of one capture agree on each camera's pose, without reference poses."""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
from random_poses import generator, random_sim3, random_viewmats, skew_reference
from typer.testing import CliRunner

from warpbags.agreement import pose_agreement
from warpbags.alignment import align_viewmats
from warpbags.cli.main import app
from warpbags.configs.train import load_preset
from warpbags.data import ORBIT_RADIUS, SyntheticOptions, ensure_synthetic_scene
from warpbags.errors import WarpbagsError
from warpbags.run_folder import TrainingRun

runner = CliRunner()


def turned_about_own_centre(viewmat: torch.Tensor, axis: list[float], degrees: float) -> torch.Tensor:
    """The camera turned by `degrees` about `axis` (camera frame) through its own centre: its centre stays."""
    omega = torch.tensor(axis, dtype=torch.float64)
    turn = torch.linalg.matrix_exp(skew_reference(omega / omega.norm() * math.radians(degrees)))
    turned = viewmat.clone()
    turned[:3, :] = turn @ viewmat[:3, :]
    return turned


def fake_run(name: str, poses: torch.Tensor, *, root: str = "/scenes/a", views: int = 4, start=None, truth=None,
             width: int = 128) -> TrainingRun:
    """A finished run's contents, as `load_run` returns them: final poses `poses` from `start` (default: the same),
    a model of points about the origin, intrinsics; with `truth`, a run that perturbed those poses before training."""
    points = torch.randn(500, 3, generator=generator(7), dtype=torch.float64) * 0.5
    params = {"means": points, "opacities": torch.full((500,), 3.0, dtype=torch.float64)}
    Ks = torch.tensor([[300.0, 0, 64], [0, 300, 64], [0, 0, 1]], dtype=torch.float64).repeat(len(poses), 1, 1)
    info = {"scene_root": root, "image_names": [f"view_{k}.png" for k in range(views)], "width": width, "height": 128}
    config = load_preset("quick", rot_noise_deg=15.0 if truth is not None else 0.0)
    return TrainingRun(path=Path(name), info=info, config=config, params=params,
                       poses_true=poses if truth is None else truth, poses_init=poses if start is None else start,
                       poses_final=poses, intrinsics=Ks)


def orbit_viewmats(count: int) -> torch.Tensor:
    """`count` cameras on a ring of the orbit radius, looking at the origin (where `fake_run`'s points are)."""
    viewmats = []
    for k in range(count):
        angle = 2 * math.pi * k / count
        centre = torch.tensor([ORBIT_RADIUS * math.cos(angle), ORBIT_RADIUS * math.sin(angle), 0.5], dtype=torch.float64)
        forward = -centre / centre.norm()
        right = torch.linalg.cross(forward, torch.tensor([0.0, 0, 1], dtype=torch.float64))
        right = right / right.norm()
        down = torch.linalg.cross(forward, right)
        rotation = torch.stack([right, down, forward])
        viewmat = torch.eye(4, dtype=torch.float64)
        viewmat[:3, :3], viewmat[:3, 3] = rotation, -rotation @ centre
        viewmats.append(viewmat)
    return torch.stack(viewmats)


def test_a_camera_one_run_turned_is_the_one_that_disagrees():
    """Two runs whose cameras are the same up to a similarity, but for camera 2 turned 2 deg about its own centre:
    the pair's alignment is exact, camera 2 disagrees by 2 deg and moves the object, the others by nothing."""
    poses = orbit_viewmats(4)
    other = align_viewmats(poses, random_sim3(generator(3)))  # another gauge: same relative poses
    other[2] = turned_about_own_centre(other[2], [0.3, 1.0, 0.2], 2.0)
    result = pose_agreement([fake_run("a", poses), fake_run("b", other)])
    assert result.alignment == "procrustes" and result.pairs == [(0, 1)] and result.error_deg is None
    np.testing.assert_allclose(result.rotation_deg[0], [0, 0, 2, 0], atol=1e-6)
    np.testing.assert_allclose(result.centre_percent[0], 0, atol=1e-6)
    # 2 deg about the camera's own centre shifts a distant object by about f * 2 deg (300 px focal: ~10 px)
    assert result.pixels[0, 2] == pytest.approx(300 * math.radians(2), rel=0.15)
    assert result.pixels[0, [0, 1, 3]].max() < 1e-6


def test_centre_distances_are_a_share_of_the_orbit_in_the_frame_they_are_measured_in():
    """Training leaves a run's scale a few % off the scene's. The same run in a frame twice as large (its cameras'
    centres and its object scaled about the origin) disagrees with another run by the same share of the orbit: it
    read twice as much when divided by the scene's radius of 4."""
    poses = orbit_viewmats(4)
    moved = poses.clone()
    moved[2, :3, 3] -= moved[2, :3, :3] @ (0.4 * moved[2, 0, :3])  # its centre 0.4 along its own x axis
    doubled = moved.clone()
    doubled[:, :3, 3] *= 2
    small, large = fake_run("b", moved), fake_run("b2", doubled)
    large.params = {**large.params, "means": 2 * large.params["means"]}
    near = pose_agreement([fake_run("a", poses), small]).centre_percent
    assert near[0, 2] > 2.0  # camera 2 moved 10% of the orbit sideways; Procrustes spreads part of it
    np.testing.assert_allclose(pose_agreement([fake_run("a", poses), large]).centre_percent, near, rtol=1e-6)


def test_the_central_run_is_the_one_the_others_agree_with():
    poses = orbit_viewmats(5)
    near = poses.clone()
    near[1] = turned_about_own_centre(near[1], [1.0, 0, 0], 0.5)
    far = poses.clone()
    far[1] = turned_about_own_centre(far[1], [-1.0, 0, 0], 6.0)
    far[3] = turned_about_own_centre(far[3], [0, 1.0, 0], 4.0)
    result = pose_agreement([fake_run("near", near), fake_run("far", far), fake_run("middle", poses)])
    assert result.pairs == [(0, 1), (0, 2), (1, 2)]
    assert result.central_run() == 2  # 0.5 deg from "near", 6 and 4 from "far": it has the least disagreement
    summary = result.to_json()
    assert summary["central_run"] == "middle" and len(summary["per_camera"]["rotation_deg_max"]) == 5
    assert summary["per_camera"]["rotation_deg_max"][1] == pytest.approx(6.5, abs=1e-3)  # "near" against "far"


def test_runs_that_perturbed_the_truth_report_their_errors_and_whether_they_started_alike():
    truth = orbit_viewmats(4)
    ended = truth.clone()
    ended[0] = turned_about_own_centre(ended[0], [0, 0, 1.0], 1.5)
    start, other_start = random_viewmats(4, generator(5)), random_viewmats(4, generator(6))
    alike = pose_agreement([fake_run("a", ended, start=start, truth=truth), fake_run("b", truth, start=start, truth=truth)])
    np.testing.assert_allclose(alike.error_deg, [[1.5, 0, 0, 0], [0, 0, 0, 0]], atol=1e-6)
    assert alike.same_start and alike.to_json()["error_deg"][0][0] == pytest.approx(1.5)
    moved = align_viewmats(ended, random_sim3(generator(9)))
    regauged = pose_agreement([fake_run("a", moved, start=start, truth=truth),
                               fake_run("b", truth, start=start, truth=truth)])
    np.testing.assert_allclose(regauged.error_deg, alike.error_deg, atol=1e-6)  # errors after alignment, in any gauge
    apart = pose_agreement([fake_run("a", ended, start=start), fake_run("b", truth, start=other_start)])
    assert not apart.same_start and apart.error_deg is None  # no noise injected: the scene's poses are no truth


def test_two_cameras_are_compared_after_the_pairwise_alignment():
    poses = orbit_viewmats(2)
    other = align_viewmats(poses, random_sim3(generator(4)))  # another gauge: the same relative pose
    result = pose_agreement([fake_run("a", poses, views=2), fake_run("b", other, views=2)])
    assert result.alignment == "pairwise"
    np.testing.assert_allclose(result.rotation_deg, 0, atol=1e-6)


@pytest.mark.parametrize("case, message", [
    ("one run", "at least two runs of one capture, got 1"),
    ("other scene", "b is a run of /scenes/other, a of /scenes/a: compare runs of one capture"),
    ("other views", "b was trained on other views than a"),
    ("other resolution", "b trained at 256x128 px, a at 128x128: compare runs of one resolution"),
    ("diverged", "poses_final.npy holds poses that are not finite"),
])
def test_runs_that_cannot_be_compared_are_named(case, message):
    poses = random_viewmats(4, generator(1))
    runs = {"one run": [fake_run("a", poses)],
            "other scene": [fake_run("a", poses), fake_run("b", poses, root="/scenes/other")],
            "other views": [fake_run("a", poses), fake_run("b", poses)],
            "other resolution": [fake_run("a", poses), fake_run("b", poses, width=256)],
            "diverged": [fake_run("a", poses), fake_run("b", torch.full_like(poses, float("nan")))]}[case]
    if case == "other views":
        runs[1].info["image_names"] = ["view_0.png", "view_1.png", "view_2.png", "view_9.png"]
    with pytest.raises(WarpbagsError, match=message):
        pose_agreement(runs)


@pytest.fixture(scope="module")
def two_runs(tmp_path_factory):
    """A tiny finished run, and a copy of it whose camera 1 ends 3 deg further turned about its own centre."""
    scene = ensure_synthetic_scene(SyntheticOptions(views=16, width=64, height=64),
                                   cache_dir=tmp_path_factory.mktemp("cache"))
    runs = tmp_path_factory.mktemp("runs")
    result = runner.invoke(app, ["train", str(scene), "--iters", "6", "--rot-noise-deg", "4", "--trans-noise", "0.05",
                                 "--repair-iters", "0", "--out", str(runs / "a")])
    assert result.exit_code == 0, result.output
    shutil.copytree(runs / "a", runs / "b")
    poses = torch.from_numpy(np.load(runs / "b" / "poses_final.npy")).double()
    poses[1] = turned_about_own_centre(poses[1], [0, 1.0, 0], 3.0)
    np.save(runs / "b" / "poses_final.npy", poses.float().numpy())
    return runs / "a", runs / "b"


def test_agree_prints_and_writes_each_cameras_disagreement(two_runs, tmp_path):
    out = tmp_path / "new folder" / "agreement.json"  # its folder is made
    result = runner.invoke(app, ["agree", str(two_runs[0]), str(two_runs[1]), "--json", str(out)])
    assert result.exit_code == 0, result.output
    text = " ".join(result.output.split())
    assert "pose agreement of 2 runs (4 views, procrustes alignment" in text
    assert "runs disagree by 0.75 deg" in text  # 3 deg on one camera of four
    saved = json.loads(out.read_text())
    np.testing.assert_allclose(saved["rotation_deg"][0], [0, 3, 0, 0], atol=2e-3)  # float32 poses on disk
    assert saved["runs"] == [str(two_runs[0]), str(two_runs[1])] and saved["pixels"][0][1] > 1.0
    # the runs perturbed the scene's poses (4 deg): their errors against them are shown and saved
    assert "| error" in result.output.replace("┃", "|") and len(saved["error_deg"]) == 2 and saved["same_start"]
    # two runs disagree with each other alike: naming the first "closest to the others" said nothing of them
    assert "closest to the others" not in text and saved["central_run"] is None
    # each camera's row: median and largest rotation, largest centre and pixel distance, mean error of the runs
    rows = {cells[0]: cells for cells in ([cell.strip() for cell in line.split("│")[1:-1]]
                                          for line in result.output.splitlines() if line.count("│") == 8)}
    per_camera = saved["per_camera"]
    for camera in range(4):
        expected = [f"{per_camera[key][camera]:.2f}" for key in
                    ("rotation_deg_median", "rotation_deg_max", "centre_percent_of_orbit_max", "pixels_max")]
        assert rows[str(camera)][2:6] == expected, rows[str(camera)]
        assert rows[str(camera)][6] == f"{np.mean(np.array(saved['error_deg'])[:, camera]):.2f}"
    assert rows["1"][2:4] == ["3.00", "3.00"] and rows["0"][2:4] == ["0.00", "0.00"]
    assert len({row[6] for row in rows.values()}) > 1 and float(rows["1"][5]) > 1.0
    # three runs, camera 1 turned by 0, 3 and 1 deg about one axis: pairs 3, 1 and 2 deg, median 2, largest 3
    third = tmp_path / "c"
    shutil.copytree(two_runs[0], third)
    poses = torch.from_numpy(np.load(third / "poses_final.npy")).double()
    poses[1] = turned_about_own_centre(poses[1], [0, 1.0, 0], 1.0)
    np.save(third / "poses_final.npy", poses.float().numpy())
    result = runner.invoke(app, ["agree", str(two_runs[0]), str(two_runs[1]), str(third)])
    assert result.exit_code == 0, result.output
    row = next([cell.strip() for cell in line.split("│")[1:-1]] for line in result.output.splitlines()
               if line.count("│") == 8 and line.split("│")[1].strip() == "1")
    assert row[2:4] == ["2.00", "3.00"], row


@pytest.mark.parametrize("arguments, message", [
    (["A"], "agreement needs at least two runs of one capture, got 1"),
    (["A", "B", "A"], "is given twice: compare different runs of one capture"),
    (["A", "NOT_A_RUN"], "is not a training run (no config.json)"),
    (["A", "MISSING"], "nothere: no such run folder"),
    (["A", "B", "--json", "FOLDER"], "is a folder: name the file to write"),
    (["A", "B", "--json", "INSIDE_A_FILE"], "is a file, not a folder to write --json into"),
])
def test_agree_bad_input_is_one_line(two_runs, tmp_path, arguments, message):
    (tmp_path / "a-file").write_text("")
    names = {"A": str(two_runs[0]), "B": str(two_runs[1]), "NOT_A_RUN": str(tmp_path), "FOLDER": str(tmp_path),
             "MISSING": str(tmp_path / "nothere"),
             "INSIDE_A_FILE": str(tmp_path / "a-file" / "agreement.json")}
    result = runner.invoke(app, ["agree", *(names.get(argument, argument) for argument in arguments)])
    lines = [line for line in result.output.splitlines() if line.strip()]
    assert result.exit_code == 2 and len(lines) == 1 and message in " ".join(result.output.split()), result.output


@pytest.mark.parametrize("inside", ["config.json", "sub/agreement.json", "../a/eval.json"])
def test_agree_never_writes_into_a_run_it_compares(two_runs, inside):
    """--json naming a file in one of the run folders (its config.json above all) is refused before anything is
    read or written."""
    before = {path: path.read_bytes() for run in two_runs for path in run.iterdir() if path.is_file()}
    target = f"{two_runs[1]}/{inside}"
    result = runner.invoke(app, ["agree", str(two_runs[0]), str(two_runs[1]), "--json", target])
    lines = [line for line in result.output.splitlines() if line.strip()]
    assert result.exit_code == 2 and len(lines) == 1, result.output
    assert "is inside the run folder" in " ".join(result.output.split())
    assert {path: path.read_bytes() for run in two_runs for path in run.iterdir() if path.is_file()} == before
    assert not (two_runs[1] / "sub").exists()


def test_agree_pairwise_anchors_each_pair_on_a_camera_the_runs_agree_on(two_runs, tmp_path):
    """`agree --pairwise` reaches the comparison, not only its title: the second run's camera 1 also ends 0.4 (10% of
    the orbit) along its own x axis. Procrustes fits the four centres at once and spreads that move over every
    camera, which then disagree by turns neither run made; SPARF's pairwise alignment anchors the pair on a camera
    they agree on, so camera 1 alone disagrees (3 deg, its centre 10% of the orbit)."""
    moved = tmp_path / "moved"
    shutil.copytree(two_runs[1], moved)
    poses = torch.from_numpy(np.load(moved / "poses_final.npy")).double()
    poses[1, :3, 3] -= poses[1, :3, :3] @ (0.4 * poses[1, 0, :3])  # its centre 0.4 along its own x axis
    np.save(moved / "poses_final.npy", poses.float().numpy())
    saved = {}
    for alignment, flags in (("procrustes", []), ("pairwise", ["--pairwise"])):  # procrustes: the default
        out = tmp_path / f"{alignment}.json"
        result = runner.invoke(app, ["agree", str(two_runs[0]), str(moved), *flags, "--json", str(out)])
        assert result.exit_code == 0, result.output
        assert f"pose agreement of 2 runs (4 views, {alignment} alignment" in " ".join(result.output.split())
        saved[alignment] = json.loads(out.read_text())
        assert saved[alignment]["alignment"] == alignment
    pairwise, procrustes = saved["pairwise"], saved["procrustes"]
    np.testing.assert_allclose(pairwise["rotation_deg"][0], [0, 3, 0, 0], atol=2e-3)  # float32 poses on disk
    np.testing.assert_allclose(np.array(pairwise["centre_percent_of_orbit"][0])[[0, 2, 3]], 0, atol=1e-3)
    assert pairwise["centre_percent_of_orbit"][0][1] == pytest.approx(10, rel=0.05)
    # Procrustes: every camera of the pair reads turned (2.2 deg measured), camera 1 less than the others
    assert min(np.array(procrustes["rotation_deg"][0])[[0, 2, 3]]) > 1.0, procrustes["rotation_deg"]

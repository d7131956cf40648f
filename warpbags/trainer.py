"""`Trainer`: the loop that fits 3D Gaussians and corrects the camera poses (BAGS), coarse then repair stage.

One class for every variant (pose optimization on/off, gauge choice, repair on/off, presets) chosen by
`TrainConfig`. The first `iters` iterations are the coarse stage, in rounds that each start from fresh Gaussians;
the `repair.iters` after them the repair stage (`warpbags.repair.RepairStage`: pseudo views supervised by repaired
renders, next to the real views). The parts it runs, each in its own module:

    warpbags.schedule          what each iteration does (rounds, pyramid level, SH degree, loss windows, pose window,
                               learning rates)
    warpbags.model             the Gaussians of a round: parameters, optimizer, densification, render, loss
    warpbags.camera_setup      the starting poses and the camera optimizer (`warpbags.camera_optimizer`)
    warpbags.run_folder        config, poses, log, checkpoints and results on disk (the layout is documented there)

The trainer adds the loop itself: rounds, the search of one round over turns of its worst-fit camera
(`camera.hypotheses_round`), the repair stage, checkpoint cadence, the log and Ctrl-C. The module also
holds the run's entry points that the command line, the benchmarks, the sweep and the tests import from here
(`training_scene`, `start_or_resume`, `default_run_dir`) and the attributes they read (`params`, `cameras`,
`scene`, `pose_error`).
"""

from __future__ import annotations

import contextlib
import copy
import dataclasses
import signal
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import torch

from warpbags.alignment import alignment_for, pose_errors, procrustes_unfit
from warpbags.camera_optimizer import hypothesis_turns
from warpbags.camera_setup import coherent_start, given_viewmats, starting_poses, training_cameras
from warpbags.configs.scenes import SCENES
from warpbags.configs.train import TrainConfig, differing_fields
from warpbags.correspondences import find_view_matches
from warpbags.data import open_scene, resolve_scene
from warpbags.data.scene import Scene
from warpbags.devices import torch_device
from warpbags.errors import Stopped, WarpbagsError, sigterm_unclaimed
from warpbags.files import missing_folders, writable_folder
from warpbags.model import Diverged, GaussianModel, TrainingViews, scene_extent
from warpbags.repair import RepairStage, Repairer, repairer_factory
from warpbags.repair.stage import pseudo_ratio
from warpbags.run_folder import RunFolder
from warpbags.schedule import Schedule, StepSettings
from warpbags.silhouette import SilhouetteTargets
from warpbags.threads import torch_threads

# What stops training with a checkpoint: Ctrl-C, and the SIGTERM a job scheduler or `kill` sends before it kills.
STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)


class Trainer:
    """Gaussians + pose corrections from the training views of one scene.

    Args:
        scene: the scene, already restricted to the training views (``Scene.subset``) and downscaled; its
            ``viewmats`` are the true poses.
        config: the training configuration.
        out_dir: run folder (created when first written).
        device: "cpu" or "cuda".
        viewmats_init: [C,4,4] starting poses; default: the true poses with the config's noise injected.
        log: callable receiving a one-line notice (e.g. "no depth maps: depth term skipped").
        resuming: the state comes from a checkpoint next (`resume`): the silhouette-coherence solve of the starting
            poses, whose result the checkpoint holds, is skipped.
    """

    def __init__(self, scene: Scene, config: TrainConfig, out_dir: str | Path, device: str = "cpu",
                 viewmats_init: torch.Tensor | None = None, log: Callable[[str], None] = print,
                 resuming: bool = False):
        self.device = torch_device(device)
        if config.repair.iters > 0:
            repairer_factory(config.repair.repairer)  # a bad --repairer fails now, not after the coarse stage
        self.config, self.log = config, log
        self.run_folder = RunFolder(out_dir)
        self.schedule = Schedule(config)
        # the turns of the worst-fit camera that round `camera.hypotheses_round` is trained once more with
        self.hypothesis_turns = hypothesis_turns(config.camera.hypothesis_axes, config.camera.hypothesis_angles)
        self.num_cameras = scene.num_views
        self.full_scene = scene
        self._levels: dict[int, TrainingViews] = {}  # the training views at each pyramid level used so far
        full = self._training_views(0)
        self.viewmats_true = scene.viewmats.to(self.device)
        viewmats_init = given_viewmats(scene, config) if viewmats_init is None else viewmats_init
        self.viewmats_init = viewmats_init.to(self.device).float()
        self.viewmats_start, self.object_center = starting_poses(self.viewmats_init, full.masks, full.Ks, config, log)
        self.scene_extent = scene_extent(self.viewmats_init)
        if full.depths is None and config.depth_until > 0 and config.lambda_depth > 0:
            # The depth term is what takes the synthetic scene's cameras in from 15 degrees of noise (README, "Pose
            # recovery"): without depth maps poses rest on the images and masks alone.
            self.log("no depth maps in this scene: depth term skipped" + (
                "; poses are corrected from the images and masks alone, which recovers far less from large pose "
                "noise (zoe_depth/*.png or depths/*.npy per image give the depth prior)" if config.pose_opt else ""))
        # the logged pose error's alignment: the configured one, pairwise where Procrustes cannot fit the reference
        # cameras (found once: the reference poses do not change)
        self.pose_alignment = alignment_for(self.viewmats_true.cpu(), config.pose_alignment)
        if self.pose_alignment != config.pose_alignment:
            self.log(f"the logged pose error uses pairwise alignment ({procrustes_unfit(self.viewmats_true.cpu())})")
        if config.pose_opt and config.pose_opt_start >= config.total_iters:  # e.g. the paper preset cut short
            self.log(f"pose optimization starts at iteration {config.pose_opt_start}, after the run's "
                     f"{config.total_iters}: the poses stay where the start procedures put them (--pose-opt-start to "
                     "move them)")
        elif config.pose_opt and config.pose_opt_start >= config.iters:
            self.log(f"pose optimization starts at iteration {config.pose_opt_start}, after the coarse stage's "
                     f"{config.iters}: the poses move in the repair stage only (--pose-opt-start to move them earlier)")
        if (reached := self.schedule.final_sh_degree()) < config.sh_degree:
            self.log(f"sh_degree {config.sh_degree} is reached after {config.sh_degree * config.sh_degree_every} "
                     f"iterations of a round; the last round trains up to degree {reached}, so the model's higher "
                     "coefficients stay zero (a smaller sh_degree_every, or longer rounds)")
        if empty_windows := self.schedule.rounds_without_pose_window():
            self.log(f"the pose window of round(s) {', '.join(str(k) for k in empty_windows)} (0-based) holds no "
                     "iteration of the round: poses hold still there (a wider pose_round_window(s) or fewer rounds)")
        self.generator = torch.Generator().manual_seed(config.seed)  # initialization, view sampling, densification
        self.iteration = 0
        self.model = self._fresh_model(self.viewmats_start)
        # The camera optimizer is created exactly once (resume loads state into it); its preconditioner comes from
        # the hull carved at the starting poses, before the coherence solve moves them (round 0 is carved again).
        views = self.model.training_views
        self.cameras = training_cameras(config, self.viewmats_start, self.object_center, views.Ks, views.scene.width,
                                        views.scene.height, self.model.params["means"].detach())
        if config.pose_opt and full.masks is not None and config.camera.coherence_iters > 0 and not resuming:
            # With enough views the silhouettes fix the poses without the frame's false border (`CameraConfig`).
            continued = self.num_cameras >= config.camera.coherence_continued_from_views
            targets = (full.silhouettes if full.silhouettes is not None and not continued
                       else SilhouetteTargets(full.masks, continued_beyond_frame=continued).to(self.device))
            before, after = coherent_start(self.cameras, targets, full.Ks, self.object_center,
                                           config.camera.coherence_iters, full.scene.matches,
                                           config.camera.coherence_epipolar)
            self.log(f"silhouette coherence of the starting poses: {before:.2e} -> {after:.2e}"
                     + (" (masks continued beyond the image border)" if continued else ""))
            self.viewmats_start = self.cameras.viewmats()
            self.model = self._fresh_model(self.viewmats_start)  # carved again, with the coherent poses
        self.repair_stage: RepairStage | None = None  # built when the repair stage first uses pseudo views
        self._repair_state: dict | None = None  # its checkpointed state, applied when it is built
        self._stop_signal: int | None = None  # the signal that asked training to stop (`_request_stop`)
        # Set by `start_or_resume` for a new run (the folders it makes: `files.missing_folders`): until the first
        # checkpoint, a failure removes what the run wrote (`RunFolder.remove_unfinished`). None: the caller's folder.
        self.new_run_folders: list[Path] | None = None

    def _training_views(self, level: int | None = None) -> TrainingViews:
        """The training views at pyramid level `level` (0 = the full training resolution, k = 1/2^k of it; None:
        the current iteration's level)."""
        level = self.schedule.pyramid_level(self.iteration) if level is None else level
        if level not in self._levels:
            full = self.full_scene
            scene = full if level == 0 else full.downscaled(max(8, max(full.width, full.height) >> level),
                                                            keep_objects=True)
            self._levels[level] = TrainingViews.of(scene, self.config, self.device)
        return self._levels[level]

    def _fresh_model(self, viewmats: torch.Tensor) -> GaussianModel:
        """The Gaussians of a new round, at its pyramid level, carved with [C,4,4] `viewmats`: the poses carry over
        from round to round, the Gaussians (which have partly absorbed the old pose errors) do not."""
        return GaussianModel.initialized(self.config, self._training_views(), viewmats, self.scene_extent,
                                         self.generator, self.log)

    # ----------------------------------------------------------------------------------------------- state
    @property
    def out_dir(self) -> Path:
        return self.run_folder.path

    @property
    def params(self) -> dict[str, torch.nn.Parameter]:
        """The current round's Gaussian parameters."""
        return self.model.params

    @property
    def scene(self) -> Scene:
        """The training views at the current round's resolution."""
        return self.model.training_views.scene

    @property
    def in_repair(self) -> bool:
        """True in the repair stage: the coarse iterations are done and repair iterations follow."""
        return self.schedule.in_repair(self.iteration)

    def current_viewmats(self) -> torch.Tensor:
        """[C,4,4] the poses as currently estimated."""
        return self.cameras.viewmats()

    def pose_error(self, viewmats: torch.Tensor | None = None) -> dict[str, float]:
        """Mean rotation (deg) and camera-centre errors of `viewmats` (default: current) against the truth."""
        viewmats = self.current_viewmats() if viewmats is None else viewmats
        errors = pose_errors(viewmats.double().cpu(), self.viewmats_true.double().cpu(), alignment=self.pose_alignment)
        return {"rot_err_deg": errors["rotation_error_deg_mean"], "trans_err": errors["translation_error_mean"]}

    # ----------------------------------------------------------------------------------------------- step
    def train_step(self) -> dict:
        """One iteration (coarse or repair stage); returns its log record."""
        if self.in_repair:
            return self._repair_step()
        started = time.perf_counter()
        if self.schedule.starts_round(self.iteration):
            self.model = self._fresh_model(self.current_viewmats())
            # The corrections so far are folded into the base poses, so that the round's anchor
            # (camera.round_anchor) pulls towards where it started; Adam's moments are cleared on purpose: the pose
            # lr restarts with the round, and second moments from the converged end of the last round would turn
            # its first steps into jumps.
            self.cameras.rebase()
        settings = self.schedule.at(self.iteration)
        self.cameras.set_learning_rate(settings.pose_lr)
        self.cameras.set_orbit_free(settings.orbit_free)
        with self._divergence_reported():
            loss, terms = self.model.fit_step(self.cameras, settings)
            if settings.pose_solve:
                self._solve_poses(settings)
        if settings.pose_average:
            self.cameras.accumulate_average()
        self.iteration += 1
        if self.iteration == self.config.iters:  # the coarse stage ends with the average of its last estimates
            with self._divergence_reported():
                self.model.check_finite_parameters(self.cameras)  # the last step's, before they are averaged away
                self.cameras.apply_average()
            # averaged or not, the repair stage starts from the coarse stage's final poses: its anchor
            # (camera.round_anchor) pulls towards them, not towards where the last round started (with one round, the
            # noisy given poses), and its pose lr warms up from zeroed Adam moments (a no-op after an average)
            self.cameras.rebase()
        return self._record("coarse", loss, terms, started)

    def _solve_poses(self, settings: StepSettings) -> None:
        """Every camera solved by L-BFGS against the current Gaussians, which hold still (`camera.lbfgs_from_round`):
        the loss of this iteration's terms over all training views."""
        views = torch.arange(self.num_cameras, device=self.device)
        self.cameras.refine(lambda viewmats: self.model.loss(views, viewmats, settings)[0],
                            self.config.camera.lbfgs_iters)
        self.model.optimizer.zero_grad(set_to_none=True)
        if not torch.isfinite(self.cameras.params()).all():
            raise Diverged("the L-BFGS pose solve left non-finite camera parameters")

    def _repair_step(self) -> dict:
        """A repair-stage iteration: (1 - r) real-view loss + r pseudo-view loss, no densification."""
        started = time.perf_counter()
        ratio = pseudo_ratio(self.config.repair, self.iteration - self.config.iters)
        if self.repair_stage is None and ratio > 0:  # built when first needed (no pairs for a real-only schedule)
            self.start_repair_stage()
        settings = self.schedule.at(self.iteration)
        self.model.set_learning_rate(settings.gaussian_lr_fraction)
        self.cameras.set_learning_rate(settings.pose_lr)
        self.cameras.set_orbit_free(settings.orbit_free)
        loss, terms, views = torch.zeros((), device=self.device), {"pseudo_ratio": ratio}, None
        if ratio < 1:
            views = self.model.sample_views()
            real, real_terms, _ = self.model.loss(views, self.cameras.poses(views, settings.pose_active),
                                                  settings)
            loss, terms = (1 - ratio) * real, {**terms, **real_terms}
        if ratio > 0:
            pseudo, pseudo_terms = self.repair_stage.loss(self.model, self.current_viewmats(), self.iteration)
            loss, terms = loss + ratio * pseudo, {**terms, **pseudo_terms}
        with self._divergence_reported():
            self.model.optimize(loss, self.cameras, views, settings)
        self.iteration += 1
        return self._record("repair", loss, terms, started)

    def start_repair_stage(self, repairer: Repairer | None = None) -> RepairStage:
        """Build the repair stage on the coarse result (pairs and a fitted repairer, or those of a resumed run), or
        use `repairer` as it is."""
        self.repair_stage = RepairStage(self.config, self.out_dir / "repair", self.model, self.current_viewmats(),
                                        self.generator, log=self.log, should_stop=lambda: self._stop_signal is not None,
                                        repairer=repairer)
        if self._repair_state is not None:
            self.repair_stage.load_state_dict(self._repair_state)
        return self.repair_stage

    @contextlib.contextmanager
    def _divergence_reported(self) -> Iterator[None]:
        try:
            yield
        except Diverged as error:
            last = self.latest_checkpoint()
            kept = f"last good checkpoint: {last}" if last else "no checkpoint was written yet"
            raise WarpbagsError(f"training diverged at iteration {self.iteration}: {error}; {kept}") from None

    def _record(self, stage: str, loss: torch.Tensor, terms: dict, started: float) -> dict:
        """The log record of the step just taken: "iter" counts the steps done, the schedule's entries are those of
        the step itself (index iter - 1)."""
        schedule, iteration = self.schedule, self.iteration
        with self._divergence_reported():
            try:
                pose_error = self.pose_error()
            except ValueError as error:  # poses a step too large for them (lr.pose) threw out of any alignment
                raise Diverged(f"the poses cannot be aligned to the reference any more ({error})") from None
        return {"iter": iteration, "stage": stage, "loss": loss.item(), **terms,
                "num_gaussians": self.model.num_gaussians, "sh_degree": schedule.sh_degree(iteration - 1),
                "pose_opt": schedule.poses_move(iteration - 1), **pose_error,
                "seconds": time.perf_counter() - started}

    # ----------------------------------------------------------------------------------------------- files
    def latest_checkpoint(self) -> Path | None:
        return self.run_folder.latest_checkpoint()

    def save_checkpoint(self) -> Path:
        """Checkpoint the current state (`RunFolder.save_checkpoint`).

        Raises:
            WarpbagsError: a parameter is not finite (the last step diverged): a checkpoint only ever holds a
                state training can go on from, and the error names the last one that does.
        """
        with self._divergence_reported():
            self.model.check_finite_parameters(self.cameras)
        return self.run_folder.save_checkpoint({
            "iteration": self.iteration, "config": self.config.to_dict(), **self.model.state_dict(),
            "cameras": self.cameras.state(), "generator": self.generator.get_state(),
            "viewmats_init": self.viewmats_init.cpu(), "viewmats_start": self.viewmats_start.cpu(),
            "repair": None if self.repair_stage is None else self.repair_stage.state_dict(),
        })

    def load_checkpoint(self, path: Path, changed_on_purpose: frozenset[str] = frozenset()) -> None:
        """Restore everything a checkpoint holds (into the existing camera optimizer).

        Args:
            changed_on_purpose: config fields (names as `differing_fields` takes them) that this trainer may set
                differently from the checkpoint's run: a benchmark's control continuing it with other settings.

        Raises:
            WarpbagsError: the checkpoint is unreadable or from an older warpbags, its config cannot be read, or its
                run's config differs from the one resumed with (config.json changed after the run started).
        """
        state = self.run_folder.load_checkpoint(path, self.device)
        # read as config.json was (`TrainConfig.from_dict` mends values saved before a check refused them)
        try:
            saved = TrainConfig.from_dict(state["config"]).to_dict()
        except WarpbagsError as error:
            raise WarpbagsError(f"{path}: its config: {error}") from None
        if differences := differing_fields(saved, self.config.to_dict(), RESUMABLE_CHANGES | changed_on_purpose):
            field, saved, given = differences[0]
            raise WarpbagsError(f"{path} was saved with {field} = {saved!r}, the config resumed with (config.json) "
                                f"says {given!r}: the run's config.json was changed after it started; restore it")
        self.iteration = state["iteration"]
        # the level the saved Gaussians were trained at (a checkpoint at a round's start holds the last round's)
        self.model.training_views = self._training_views(self.schedule.pyramid_level(max(self.iteration - 1, 0)))
        self.model.load_state_dict(state)
        self.cameras.load_state(state["cameras"])
        self.generator.set_state(state["generator"].cpu())  # the checkpoint was loaded onto the training device
        self.viewmats_init = state["viewmats_init"].to(self.device)
        self.viewmats_start = state["viewmats_start"].to(self.device)
        self.repair_stage, self._repair_state = None, state.get("repair")

    def resume(self) -> bool:
        """Load the newest checkpoint and cut log.jsonl and the pose history back to it; False when there is none."""
        path = self.latest_checkpoint()
        if path is None:
            return False
        self.load_checkpoint(path)
        self.run_folder.truncate(self.iteration, self.current_viewmats())
        self.log(f"resumed from {path} (iteration {self.iteration})")
        return True

    def write_run_files(self, folder: Path | None = None) -> None:
        """config.json, poses_true/init/start.npy, intrinsics.npy into `folder` (default: the run folder)."""
        run_folder = self.run_folder if folder is None else RunFolder(folder)
        # The full training resolution, whatever level a round trains at.
        run_folder.write_setup(self.config, self.full_scene, str(self.device), self.viewmats_true, self.viewmats_init,
                               self.viewmats_start)

    def write_results(self, folder: Path | None = None) -> None:
        """poses_final.npy, then gaussians.ply (`RunFolder.write_results`), into `folder` (default: the run folder)."""
        (self.run_folder if folder is None else RunFolder(folder)).write_results(self.params, self.current_viewmats())

    def remove_if_unfinished(self) -> None:
        """For a new run of `start_or_resume` without a checkpoint yet: remove the files it wrote (and the folders
        made for it), since it can neither be resumed nor evaluated. Anything else: nothing."""
        if self.new_run_folders is not None and not self.run_folder.has_checkpoint():
            self.run_folder.remove_unfinished(self.new_run_folders)

    # ----------------------------------------------------------------------------------------------- loop
    def _request_stop(self, signum, frame) -> None:
        self._stop_signal = signum

    def _worst_fit_view(self) -> int:
        """The training view with the highest loss under the current Gaussians and poses (last iteration's terms),
        among the cameras that may move (not a gauge camera held at its given pose)."""
        settings = self.schedule.at(self.iteration - 1)
        viewmats = self.current_viewmats()
        movable = self.cameras.movable_cameras()
        losses = {camera: self.model.loss(torch.tensor([camera], device=self.device), viewmats[[camera]],
                                          settings)[0].item() for camera in movable}
        return max(movable, key=losses.__getitem__)

    def _search_view_hypotheses(self, on_trial_step: Callable[[int], None] | None = None
                                ) -> list[tuple[dict, torch.Tensor]] | None:
        """`camera.hypotheses_round`: train the round that starts now once with the worst-fit camera as it is and
        once per turn of `self.hypothesis_turns`, and keep the trial of lowest mean loss over the round's last tenth if
        it beats the unturned camera's by more than `camera.hypothesis_margin` (relative). The trainer is left at
        the kept trial's end. Returns its (log record, poses) per iteration, or None on Ctrl-C (the trainer is then
        back at the round's start). `on_trial_step(done)` after each trial step: the run's training steps done so
        far, counted as `steps_left` counts them."""
        camera_config = self.config.camera
        camera = self._worst_fit_view()
        round_start, round_end = self.iteration, self.schedule.round_end(self.iteration)
        round_index, length = self.schedule.round_index(round_start), round_end - round_start
        scored = max(1, round(0.1 * length))
        # Each trial starts from the same state; copies, since Adam's state tensors are stepped in place.
        start_model, start_cameras = self.model, copy.deepcopy(self.cameras.state())
        start_generator = self.generator.get_state()

        def back_to_start() -> None:
            self.model, self.iteration = start_model, round_start
            self.cameras.load_state(copy.deepcopy(start_cameras))
            self.generator.set_state(start_generator)

        self.log(f"round {round_index} (0-based): camera {camera} fits worst; the round is trained unturned and with "
                 f"each of {len(self.hypothesis_turns)} turns of it about the object")
        unturned, best = None, None
        done = round_start  # training steps before the search: its trials count from there (`steps_left`)
        for label, rotation in [("not turned", None), *self.hypothesis_turns]:
            back_to_start()
            if rotation is not None:
                self.cameras.turn_about_object(camera, rotation.to(self.cameras.base_viewmats))
            steps = []
            for _ in range(length):
                steps.append((self.train_step(), self.current_viewmats()))
                done += 1
                if on_trial_step is not None:
                    on_trial_step(done)
                if self._stop_signal is not None:
                    back_to_start()
                    return None
            trial = dict(label=label, steps=steps, model=self.model, cameras=copy.deepcopy(self.cameras.state()),
                         generator=self.generator.get_state(),
                         score=sum(record["loss"] for record, _ in steps[-scored:]) / scored)
            if rotation is None:
                unturned = trial
            elif best is None or trial["score"] < best["score"]:
                best = trial
        kept = best if best["score"] < (1 - camera_config.hypothesis_margin) * unturned["score"] else unturned
        self.model, self.iteration = kept["model"], round_end
        self.cameras.load_state(kept["cameras"])
        self.generator.set_state(kept["generator"])
        # The decision goes into the round's first log record too (the report lists it).
        decision = {"camera": camera, "best_turn": best["label"], "best_loss": best["score"],
                    "unturned_loss": unturned["score"], "kept": kept is best}
        kept["steps"][0][0]["view_hypotheses"] = decision
        self.log(f"round {round_index}: camera {camera}, the worst fit, turned {best['label']}: loss "
                 f"{best['score']:.4f} against {unturned['score']:.4f} not turned: "
                 + ("kept" if kept is best else "not kept"))
        return kept["steps"]

    def steps_left(self) -> int:
        """Training steps still to take: the iterations left and, while the round searched for view hypotheses is
        ahead, its turned trials (each trains that round once more): what a progress estimate counts."""
        left = self.config.total_iters - self.iteration
        round_index = self.config.camera.hypotheses_round
        if self.config.pose_opt and 0 < round_index < self.schedule.rounds:
            if self.iteration <= self.schedule.round_starts[round_index]:
                left += len(self.hypothesis_turns) * self.schedule.round_length(round_index)
        return left

    def _hypotheses_due(self) -> bool:
        """True at the start of the coarse round `camera.hypotheses_round` (> 0) when poses are optimized."""
        round_index = self.config.camera.hypotheses_round
        return (round_index > 0 and self.config.pose_opt and self.schedule.starts_round(self.iteration)
                and self.schedule.round_index(self.iteration) == round_index)

    def _finish_iteration(self, record: dict, viewmats: torch.Tensor, write_log: Callable[[dict], None],
                          callback: Callable[[dict], None] | None, stop_at: int, can_checkpoint: bool = True) -> dict:
        """Log the iteration of `record` (`record["iter"]` iterations done; its poses `viewmats`), write the coarse
        result when it ends the coarse stage, checkpoint on the cadence (when `can_checkpoint`: the trainer's state
        is this iteration's) and stop on Ctrl-C. Returns the record."""
        iteration = record["iter"]
        write_log(record)
        self.run_folder.record_poses(iteration, viewmats)
        if callback is not None:
            callback(record)
        coarse_done = iteration == self.config.iters and self.config.repair.iters > 0
        if coarse_done:
            self.write_run_files(folder=self.out_dir / "coarse")
            self.write_results(self.out_dir / "coarse")
        if can_checkpoint and (iteration % self.config.checkpoint_every == 0 or iteration == stop_at or coarse_done):
            self.save_checkpoint()
        if self._stop_signal is not None and can_checkpoint:
            self.save_checkpoint()
            raise KeyboardInterrupt  # `train` says which signal (`Stopped`)
        return record

    def train(self, stop_at: int | None = None, callback: Callable[[dict], None] | None = None,
              on_trial_step: Callable[[int], None] | None = None) -> dict:
        """Train until `stop_at` (default: all coarse and repair iterations) are done; returns the last record.

        Logs every iteration and records the poses every `warpbags.pose_history.RECORD_EVERY` iterations.
        Checkpoints every `checkpoint_every` iterations, at the end of the coarse stage and at the end. With a repair
        stage, the coarse result is also written to coarse/ as a run folder of its own. Ctrl-C (SIGINT), or SIGTERM
        where no one else's handler takes it (`STOP_SIGNALS`, `sigterm_unclaimed`), finishes the current iteration,
        saves a checkpoint and raises KeyboardInterrupt. Divergence raises WarpbagsError. `callback(record)` is called
        after each iteration. The round searched for view hypotheses (`camera.hypotheses_round`) trains as a whole: a
        `stop_at` inside it stops at its start, Ctrl-C goes back to its start, only its end is checkpointed, and its
        iterations are logged (and passed to `callback`) after the search, the trainer then at the round's end;
        `on_trial_step(done)` is called after each of its trial steps, with the training steps done so far as
        `steps_left` counts them, so that a progress display moves through it. A new run of `start_or_resume` that fails
        (any exception, KeyboardInterrupt included) before its first checkpoint is written removes the files it wrote,
        and the folders made for it: nothing half-written stays.
        """
        total = self.config.total_iters
        stop_at = total if stop_at is None else min(stop_at, total)
        self._stop_signal = None  # a Ctrl-C that stopped an earlier call is not this one's
        previous_handlers = {}
        try:
            for stop_signal in STOP_SIGNALS:
                # SIGTERM only where no one else's handler takes it: a Ray worker's exits so that Ray retries the
                # task, which then resumes from the last checkpoint
                if stop_signal == signal.SIGINT or sigterm_unclaimed():
                    previous_handlers[stop_signal] = signal.signal(stop_signal, self._request_stop)
        except ValueError:  # not the main thread: Ctrl-C is handled by the caller
            pass
        record: dict = {}
        # On the CPU Warp runs its own host threads; torch's OpenMP workers would fight them.
        threads = torch_threads(1) if self.device.type == "cpu" else contextlib.nullcontext()
        try:
            with threads, self.run_folder.log_writer() as write_log:
                while self.iteration < stop_at:
                    if self._hypotheses_due():
                        if self.schedule.round_end(self.iteration) > stop_at:
                            self.save_checkpoint()  # the search trains its round as a whole: stop at its start
                            break
                        steps = self._search_view_hypotheses(on_trial_step)
                        if steps is None:  # Ctrl-C during the search: back at the round's start
                            self.save_checkpoint()
                            raise KeyboardInterrupt
                        # Only the kept round's state is left, so only its last iteration can be checkpointed.
                        for index, (record, viewmats) in enumerate(steps):
                            record = self._finish_iteration(record, viewmats, write_log, callback, stop_at,
                                                            can_checkpoint=index == len(steps) - 1)
                        continue
                    record = self._finish_iteration(self.train_step(), self.current_viewmats(), write_log, callback,
                                                    stop_at)
        except BaseException as error:
            self.remove_if_unfinished()
            # every stop a signal asked for (here, in the search over turns, in the repair stage's pair building)
            # leaves as one Stopped that names it; a Ctrl-C no handler of ours took stays as it came
            if isinstance(error, KeyboardInterrupt) and self._stop_signal is not None:
                raise Stopped(self._stop_signal) from None
            if isinstance(error, OSError):
                raise self._write_failure(error) from None
            raise
        finally:
            for stop_signal, handler in previous_handlers.items():
                if handler is not None:  # None: a handler not installed from Python, which Python cannot put back
                    signal.signal(stop_signal, handler)
        if self.iteration >= total:
            try:
                self.write_results()
            except OSError as error:
                raise self._write_failure(error) from None
        return record

    def _write_failure(self, error: OSError) -> WarpbagsError:
        """One line for a file of the run that could not be written (a full disk, a file-size limit), with the
        checkpoint a --resume would continue from."""
        latest = self.latest_checkpoint()
        kept = f"; {latest} is kept: --resume continues from it once there is room" if latest is not None else ""
        return WarpbagsError(f"cannot write into {self.run_folder.path}: {' '.join(str(error).split())}{kept}")


def training_scene(scene: Scene | str | Path, config: TrainConfig, data_root: str | Path | None = None,
                   log: Callable[[str], None] | None = None) -> Scene:
    """The training views of a scene (a loaded Scene, a preset name or a folder), downscaled per `config`.

    The views are the scene's `sparse_{views}.txt` split, or else a farthest-point choice (said through `log`). A
    config that uses the feature matches' epipolar term gets the views' matches found here, before downscaling.

    Raises:
        WarpbagsError: unknown scene, missing data, fewer images than `config.views`, or a view whose object vanishes
            at the training size.
    """
    if not isinstance(scene, Scene):
        scene = open_scene(scene, root=data_root, resolution=config.resolution)
    views = scene.train_views(config.views)
    if log is not None and str(config.views) not in scene.splits:
        log(f"{scene.name} has no sparse_{config.views}.txt: {config.views} training views chosen by farthest-point "
            "sampling of the camera centres")
    scene = scene.subset(views)
    if config.uses_matches:  # on the images as read: a training image of 128 px holds few features
        scene = dataclasses.replace(scene, matches=find_view_matches(scene.images, scene.masks,
                                                                     config.matches_min_inliers))
        if log is not None:
            log(f"feature matches between the training views: {len(scene.matches)} in "
                f"{len(scene.matches.pairs)} of {len(views) * (len(views) - 1) // 2} pairs")
    return scene.downscaled(config.max_image_size, keep_objects=True)


def default_run_dir(scene_name: str, views: int, root: str | Path = "runs") -> Path:
    """`runs/<scene>-<views>v-<YYYYmmdd-HHMMSS>`."""
    return Path(root) / f"{scene_name}-{views}v-{time.strftime('%Y%m%d-%H%M%S')}"


# Fields a run may be resumed with at other values: how often it saves and on how many threads it renders change
# neither what a checkpoint holds nor the schedule that goes on from it.
RESUMABLE_CHANGES = frozenset({"checkpoint_every", "render_threads"})


def saved_run_config(out_dir: str | Path) -> TrainConfig:
    """The config of the run in `out_dir`, which a resumed run continues with.

    Raises:
        WarpbagsError: no checkpoint in `out_dir`, or no readable config.json.
    """
    run_folder = RunFolder(out_dir)
    if not run_folder.has_checkpoint():
        raise WarpbagsError(f"--resume: no checkpoint in {run_folder.checkpoints}")
    return run_folder.resumable_config()


def saved_run_scene(out_dir: str | Path, data_root: str | Path | None = None) -> str:
    """The scene the run in `out_dir` trained on, as `training_scene` takes it: its preset name if it was one and
    the preset (with `data_root`) is still that folder (the preset also fixes the resolution and published splits),
    else its folder (a folder of the user's named like a preset, a data-root preset whose root is not given now).

    Raises:
        WarpbagsError: no readable config.json in `out_dir`, or one without the scene.
    """
    info = RunFolder(out_dir).read_info()
    if not isinstance(info.get("scene_root"), str):
        raise WarpbagsError(f"{Path(out_dir) / 'config.json'} names no scene folder: give the scene")
    name = info.get("scene")
    if name in SCENES:
        try:
            if str(resolve_scene(name, data_root)[0].resolve()) == info["scene_root"]:
                return name
        except WarpbagsError:  # a data-root preset without its data root: the folder the run recorded
            pass
    return info["scene_root"]


def start_or_resume(scene: Scene, config: TrainConfig, out_dir: str | Path, device: str = "cpu", resume: bool = False,
                    log: Callable[[str], None] = print) -> Trainer:
    """A Trainer for `out_dir`: fresh (run files written) or, with `resume`, continued from its last checkpoint
    (with the config saved in the run folder).

    A fresh run needs a new or empty `out_dir` (`RunFolder.require_new`); until its first checkpoint, a failure of
    `Trainer.train` (or of writing its first files here) removes what it wrote, and the folders made for `out_dir`.

    Raises:
        WarpbagsError: `resume` without a checkpoint in `out_dir`, with another scene folder than the run's or with
            other training views or another image size than the run's (`RunFolder.view_differences`), or a fresh
            run into a folder that is not empty (one with a run named as such), or an `out_dir` that is a file or
            cannot be written.
    """
    run_folder = RunFolder(writable_folder(out_dir, "to train into"))
    if resume:
        config = saved_run_config(out_dir)
        info = run_folder.read_info()
        if not run_folder.trained_on(scene, info):
            raise WarpbagsError(f"--resume: {out_dir} holds a run of the scene in {info.get('scene_root')}, not of "
                                f"{Path(scene.root).resolve()}")
        # The same folder opened another way (as a preset or a folder, at another --resolution, another split)
        # gives other views or another size, which the checkpoint's poses and Gaussians do not fit.
        differences = run_folder.view_differences(scene, info)
        if differences:
            raise WarpbagsError(f"--resume: {out_dir} holds a run of other training views or image size than the "
                                f"scene's ({'; '.join(differences)}); give the scene as the run opened it (its "
                                f"folder {info.get('scene_root')}, or its preset name, with the same --resolution)")
    else:
        run_folder.require_new()
    made_folders = missing_folders(run_folder.path)
    if not resume:  # claimed before the start procedures (seconds to minutes), in which another run could start
        run_folder.claim_new()
    try:
        trainer = Trainer(scene, config, out_dir, device=device, log=log, resuming=resume)
    except BaseException:
        if not resume:
            run_folder.remove_unfinished(made_folders)
        raise
    if resume:
        trainer.resume()
        return trainer
    trainer.new_run_folders = made_folders
    try:
        trainer.write_run_files()
    except BaseException:
        trainer.remove_if_unfinished()
        raise
    run_folder.release_claim()
    return trainer

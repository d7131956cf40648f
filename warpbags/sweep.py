"""`warpbags sweep`: BAGS against the fixed-pose baseline over rotation noise, view counts and seeds.

Each combination is one run folder `<out>/<method>-<views>v-rot<noise>-seed<seed>/` (trained, then evaluated by
`run_combination`). A folder that already holds eval.json (of the sweep's evaluation settings) is skipped and one
with checkpoints is resumed, so an interrupted sweep continues where it stopped. An executor maps `run_combination`
over the combinations: `LocalExecutor` runs them one after another in this process, `RayExecutor` as Ray tasks on
this machine or on an existing cluster. Results: `<out>/sweep.json`, `<out>/sweep.csv` and the plots of
`warpbags.report`. A sweep locks its folder while it runs (`<out>/.sweep.lock`): a second sweep into it is refused.

It stays one module (about 550 lines) because the executors are the sweep's own map: both call
`run_combination` and `make_executor` picks between them, so moving them out would make an import cycle.
"""

from __future__ import annotations

import csv
import fcntl
import json
import math
import os
import signal
import socket
import threading
from contextlib import contextmanager
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Callable, Iterator, Protocol

from warpbags.alignment import procrustes_weak
from warpbags.configs.train import (DEFAULT_PRESET, MAX_RENDER_THREADS, TrainConfig, check_repairer_used,
                                     differing_fields, is_number, load_preset, retired_fields)
from warpbags.data import Scene, open_scene
from warpbags.data.catalog import check_data_root
from warpbags.data.splits import evaluation_views
from warpbags.devices import checked_device_name, torch_device
from warpbags.errors import WarpbagsError, raise_stopped, sigterm_unclaimed
from warpbags.evaluation import evaluate_run
from warpbags.files import atomic_output, finite_json, missing_folders, writable_file, writable_folder
from warpbags.report import SWEEP_FIGURES, plot_sweep
from warpbags.run_folder import RunFolder
from warpbags.schedule import Schedule
from warpbags.threads import limited_host_threads, usable_cores
from warpbags.trainer import start_or_resume, training_scene

METHODS = {"baseline": False, "bags": True}  # method -> pose optimization
EXECUTORS = ("local", "ray")
RAY_INSTALL = 'pip install -e ".[ray]" in the warpbags checkout (scripts/setup.sh installs it)'
Log = Callable[[str], None]


@dataclass(frozen=True)
class SweepSpec:
    """What to sweep. `overrides` are TrainConfig fields applied to every run (e.g. iters); `device` trains them."""

    scene: str
    out: Path
    rot_noises: tuple[float, ...] = (0, 5, 10, 15, 20, 30)
    views: tuple[int, ...] = (4, 6, 9)
    seeds: tuple[int, ...] = (0,)
    trans_noise: float = 0.0
    preset: str = DEFAULT_PRESET
    refine_iters: int = 50
    overrides: tuple[tuple[str, object], ...] = ()
    device: str = "cpu"


@dataclass(frozen=True)
class SweepRun:
    """One combination of a sweep; it is trained and evaluated into `<out>/<name>/`."""

    method: str
    views: int
    rot_noise_deg: float
    seed: int

    @property
    def name(self) -> str:
        return f"{self.method}-{self.views}v-rot{self.rot_noise_deg:g}-seed{self.seed}"


class Executor(Protocol):
    """Runs `run_combination` for each combination and returns their rows in the order given; both methods are
    required (`run_sweep` calls `check` first)."""

    def check(self, spec: SweepSpec) -> None:
        """Raise WarpbagsError for what would stop the runs before they start (called before the sweep reads its
        scene or writes anything)."""

    def map(self, spec: SweepSpec, runs: list[SweepRun], scene: Scene, log: Log) -> list[dict]: ...


def run_sweep(spec: SweepSpec, data_root: Path | None = None, log: Log = print,
              executor: Executor | None = None) -> list[dict]:
    """Train and evaluate every combination not done yet (with `executor`, default `LocalExecutor`); write the
    plots, then sweep.json and sweep.csv; returns one row per run. The sweep's folder is locked meanwhile."""
    checked_device_name(spec.device)  # whether CUDA is there is the executor's business: its runs' machines
    check_data_root(spec.scene, data_root)
    _check_iters(spec)
    executor = executor or LocalExecutor()
    executor.check(spec)
    writable_folder(spec.out, "to hold the sweep")
    for name in (*SWEEP_TABLES, *SWEEP_FIGURES):  # written after every run: a folder in the way is said now
        writable_file(spec.out / name, "for the sweep's tables and figures")
    writable_file(spec.out / LOCK_FILE, "to lock the sweep's folder")
    configs = {}
    for run in sweep_runs(spec):  # every run's settings checked before the first one trains
        with _naming(run):
            configs[run] = combination_config(spec, run)
            check_repairer_used(dict(spec.overrides), configs[run], option="--set repair.repairer")
            _check_poses_move(configs[run])
    with _sweep_lock(spec.out):  # from before its folder is read to the last output: no other sweep changes it
        # at the resolution the overrides give (`--set resolution=R`; None: the preset's), as `training_scene` opens
        # it for `warpbags train`: each run's config.json records that resolution
        scene = open_scene(spec.scene, root=data_root, resolution=next(iter(configs.values())).resolution)
        for run, config in configs.items():
            run_dir = spec.out / run.name
            with _naming(run):
                evaluation_views(scene, [scene.image_names[i] for i in scene.train_views(config.views)])  # eval's views
                _check_earlier_run(run_dir, config, scene)
                if _is_done(run_dir):  # what the tables and curves read of it: named now, not after the others train
                    _row(run_dir, run, spec.refine_iters)
                    RunFolder(run_dir).read_log()
        for views in spec.views:  # the runs' evaluation is quiet (`_quiet`): what it would say of the tables, said here
            if weak := procrustes_weak(scene.viewmats[scene.train_views(views)]):
                log(f"{views} views: {weak}; the tables' pose errors are Procrustes' (eval.json holds pairwise ones)")
        rows = executor.map(spec, list(configs), scene, log)
        plot_sweep(rows, spec.out)
        _write_tables(rows, spec.out)  # last, as evaluate_run writes eval.json: a failed plot leaves the earlier tables
    return rows


@contextmanager
def _naming(run: SweepRun) -> Iterator[None]:
    """A WarpbagsError in the block as one of `run`, named."""
    try:
        yield
    except WarpbagsError as error:
        raise WarpbagsError(f"sweep run {run.name}: {error}") from None


LOCK_FILE = ".sweep.lock"
"""What `run_sweep` locks in the sweep's folder while it runs; hidden, and removed when the sweep ends."""


@contextmanager
def _sweep_lock(out: Path) -> Iterator[None]:
    """Hold an exclusive lock on the sweep folder `out` (made if missing) for the block: two sweeps into one folder
    trained the same runs at once (one clearing the other's unfinished start, or both resuming one run into one log).
    On leaving, the lock file goes, and so do the folders made for it that stayed empty: a sweep refused before it
    wrote anything leaves no folder.

    Raises:
        WarpbagsError: another sweep holds the lock.
    """
    made = missing_folders(out)
    path = out / LOCK_FILE
    while True:
        out.mkdir(parents=True, exist_ok=True)
        try:
            handle = open(path, "a")
        except FileNotFoundError:  # a sweep ending removed the folder it had made, empty: make it again
            continue
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            handle.close()
            raise WarpbagsError(f"another sweep is running in {out}") from None
        try:  # a sweep ending removes the file it locked: one opened before that is no lock on the folder
            if os.path.samestat(os.fstat(handle.fileno()), os.stat(path)):
                break
        except FileNotFoundError:
            pass
        handle.close()
    try:
        yield
    finally:
        path.unlink(missing_ok=True)  # while locked, so that no sweep locks the file once it is gone
        handle.close()
        for folder in made:
            try:
                folder.rmdir()
            except OSError:  # not empty: the sweep's outputs
                pass


def _check_iters(spec: SweepSpec) -> None:
    """Iterations given for every run against the preset's rounds, which a sweep does not set: in the terms of the
    sweep's options (`TrainConfig.validate` would name --rounds, which `warpbags sweep` does not have).

    Raises:
        WarpbagsError: `iters` in the overrides, without `rounds`, below the preset's rounds; or an unknown preset.
    """
    overrides = dict(spec.overrides)
    iters = overrides.get("iters")
    if "rounds" in overrides or not isinstance(iters, int) or isinstance(iters, bool):
        return  # the preset's own iterations fit its rounds; a value of the wrong type is load_preset's to name
    rounds = load_preset(spec.preset).rounds
    if iters < rounds:
        raise WarpbagsError(f"--iters must be >= {rounds}: the {spec.preset} preset trains in {rounds} "
                            f"round{'s' if rounds != 1 else ''} of at least one iteration each, got {iters}")


def _check_poses_move(config: TrainConfig) -> None:
    """Refuse a run that optimizes poses but whose schedule moves them at no iteration (`Schedule.poses_move`, what
    training steps by): its row would be the baseline's under BAGS's name. `warpbags train` starts such a run with
    a warning (`Trainer`), which the sweep's quiet runs do not show (`_quiet`).

    Raises:
        WarpbagsError: no iteration moves a pose, naming the option to change.
    """
    schedule = Schedule(config)
    if not config.pose_opt or any(schedule.poses_move(iteration) for iteration in range(config.total_iters)):
        return
    # the trainer's two warnings: every round too short for its pose window, or pose_opt_start past them all
    if len(schedule.rounds_without_pose_window()) == schedule.rounds:
        window = config.pose_round_windows or config.pose_round_window
        raise WarpbagsError(f"the bags runs would never move a pose: {config.iters} iterations in {schedule.rounds} "
                            f"round(s) leave no iteration in any round's pose window {window} (shares of a round); "
                            "give more --iters")
    raise WarpbagsError(f"the bags runs would never move a pose: pose optimization starts at iteration "
                        f"{config.pose_opt_start} (pose_opt_start), after every iteration of their pose windows; give "
                        "more --iters, or a smaller --set pose_opt_start=N")


def sweep_runs(spec: SweepSpec) -> list[SweepRun]:
    """Every combination of `spec`, in the order of the tables: views, noise, seed, then method; a value given twice
    (or two noise levels that name the same folder) once, so that no two runs write one folder."""
    runs = [SweepRun(method, views, noise, seed) for views in spec.views for noise in spec.rot_noises
            for seed in spec.seeds for method in METHODS]
    unique: dict[str, SweepRun] = {}
    for run in runs:
        unique.setdefault(run.name, run)
    return list(unique.values())


def combination_config(spec: SweepSpec, run: SweepRun, render_threads: int | None = None) -> TrainConfig:
    """The training config of one combination: the spec's preset and overrides, the run's views, noise, seed and
    method.

    Raises:
        WarpbagsError: a setting the preset does not allow (`TrainConfig.validate`).
    """
    return load_preset(spec.preset, views=run.views, rot_noise_deg=float(run.rot_noise_deg),
                       trans_noise=spec.trans_noise, pose_opt=METHODS[run.method], seed=run.seed,
                       noise_seed=run.seed, **{"render_threads": render_threads, **dict(spec.overrides)})


def run_combination(spec: SweepSpec, run: SweepRun, scene: Scene, render_threads: int | None = None) -> dict:
    """Train and evaluate one combination into its folder, unless it holds eval.json already; a folder with
    checkpoints is resumed. Returns the run's row of sweep.json.

    Args:
        scene: the opened `spec.scene`.
        render_threads: host threads for CPU rendering of a fresh run (None: the preset's); a resumed run keeps
            the setting it was started with. Every other CPU stage of the run (the coherence solve, projection,
            the loss, evaluation) keeps to this many threads too.
    """
    run_dir = spec.out / run.name
    if not _is_done(run_dir):
        config = combination_config(spec, run, render_threads)
        folder = RunFolder(run_dir)
        resume = folder.has_checkpoint()
        if folder.holds_unfinished_start():  # a run killed (SIGKILL, power) before its first checkpoint: again
            folder.remove_unfinished([])
        with limited_host_threads(render_threads):
            trainer = start_or_resume(training_scene(scene, config), config, run_dir, device=spec.device,
                                      resume=resume, log=_quiet)
            trainer.train()
            evaluate_run(run_dir, refine_iters=spec.refine_iters, device=spec.device, log=_quiet)
    return _row(run_dir, run, spec.refine_iters)


def progress(spec: SweepSpec, run: SweepRun) -> str:
    """What `run_combination` is about to do with the run's folder, as the sweep logs it."""
    run_dir = spec.out / run.name
    if _is_done(run_dir):
        return f"skip {run.name} (done)"
    return f"{'resume' if RunFolder(run_dir).has_checkpoint() else 'train'} {run.name}"


class LocalExecutor:
    """The default: one run after another in this process, rendering on every core."""

    def check(self, spec: SweepSpec) -> None:
        torch_device(spec.device)  # --device cuda on a machine without CUDA

    def map(self, spec: SweepSpec, runs: list[SweepRun], scene: Scene, log: Log) -> list[dict]:
        rows = []
        for run in runs:
            log(progress(spec, run))
            rows.append(run_combination(spec, run, scene))
        return rows


@dataclass(frozen=True)
class RayExecutor:
    """Each run not done yet becomes a Ray task that declares `cpus_per_run` CPUs and `gpus_per_run` GPUs, so Ray
    runs as many at once as the cluster holds (one per GPU with the defaults of `--device cuda`).

    Tasks write into the run folders themselves: on a cluster `spec.out` must be on a filesystem that every node
    mounts at the same path, and every node needs warpbags installed. The scene travels through Ray's object store.
    A CPU task renders with `cpus_per_run` host threads; the renderer's thread count changes results at rounding
    level, so a sweep equals the local executor's when `cpus_per_run` is the local machine's core count.

    Attributes:
        address: an existing cluster, as ray.init takes it (HOST:6379, ray://HOST:10001, or auto for one started
            with `ray start` on this machine). None starts a local Ray instance for the sweep and stops it after.
            An already initialized Ray is used as it is.
        cpus_per_run: CPUs each task declares, and its CPU rendering threads.
        gpus_per_run: GPUs each task declares (a fraction lets runs share a GPU).
    """

    address: str | None = None
    cpus_per_run: int = 1
    gpus_per_run: float = 0.0

    def __post_init__(self) -> None:
        if not 1 <= self.cpus_per_run <= MAX_RENDER_THREADS:  # each task's render threads (`render_threads`)
            raise WarpbagsError(f"--cpus-per-run must be in [1, {MAX_RENDER_THREADS}], got {self.cpus_per_run}")
        if not 0 <= self.gpus_per_run < math.inf:  # NaN fails too (Ray failed on it after starting)
            raise WarpbagsError(f"--gpus-per-run must be a finite number >= 0, got {self.gpus_per_run:g}")

    def check(self, spec: SweepSpec) -> None:
        """Ray importable, a GPU declared for CUDA runs and a given cluster address answering."""
        if spec.device == "cuda" and self.gpus_per_run == 0:
            raise WarpbagsError("--device cuda with --gpus-per-run 0: a Ray task sees no GPU it did not declare")
        ray = _import_ray()
        if self.address not in (None, "auto") and not ray.is_initialized():  # an initialized Ray is used as it is
            _check_reachable(self.address)

    def map(self, spec: SweepSpec, runs: list[SweepRun], scene: Scene, log: Log) -> list[dict]:
        ray = _import_ray()
        started_here = not ray.is_initialized()
        previous = signal.getsignal(signal.SIGTERM)
        unclaimed = sigterm_unclaimed()  # a handler of the caller's stays the caller's
        if started_here:
            self._connect(ray)
        # Ray's core worker installs a native handler that prints a stack dump and exits 1 on SIGTERM: the sweep
        # stops as a local one does instead (its runs resume; Ray is shut down; exit 143)
        takes_sigterm = started_here and threading.current_thread() is threading.main_thread() and unclaimed
        if takes_sigterm:
            signal.signal(signal.SIGTERM, raise_stopped)
        try:
            self._check_node_resources(ray)
            # Workers may run in another folder than this process: give them absolute paths.
            return self._run_tasks(ray, replace(spec, out=spec.out.resolve()), runs, scene, log)
        finally:
            if started_here:
                ray.shutdown()
            if takes_sigterm and previous is not None:
                signal.signal(signal.SIGTERM, previous)

    def _connect(self, ray) -> None:
        if self.address is None:
            # A local instance for this sweep only: no dashboard, no usage report (starts fast and offline).
            os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")
            options = {"address": "local", "include_dashboard": False}
        else:
            options = {"address": self.address}  # answering: `check`
        try:
            # Workers' own output (Warp's banner, module loads) stays in Ray's logs, as the local runs are quiet.
            ray.init(log_to_driver=False, **options)
        except (ConnectionError, ValueError, RuntimeError) as error:
            if self.address is None:
                raise WarpbagsError(f"cannot start a local Ray instance: {error}") from None
            raise WarpbagsError(f"--address {self.address}: cannot connect to Ray: {error} (a cluster with token "
                                "authentication also needs RAY_AUTH_MODE=token and its token here)") from None

    def _check_node_resources(self, ray) -> None:
        """Fail now, rather than leave tasks pending forever, if no node can hold one run."""
        nodes = [node["Resources"] for node in ray.nodes() if node["Alive"]]
        for resource, need, option in (("CPU", self.cpus_per_run, "--cpus-per-run"),
                                       ("GPU", self.gpus_per_run, "--gpus-per-run")):
            largest = max((node.get(resource, 0) for node in nodes), default=0)
            if need > largest:
                raise WarpbagsError(f"{option} {need:g}: no node of the Ray cluster has that many {resource}s "
                                    f"(largest: {largest:g})")

    def _run_tasks(self, ray, spec: SweepSpec, runs: list[SweepRun], scene: Scene, log: Log) -> list[dict]:
        """The finished runs' rows read here, the others' from one task each."""
        rows, todo = {}, []
        for run in runs:
            log(progress(spec, run))
            if _is_done(spec.out / run.name):
                rows[run] = _row(spec.out / run.name, run, spec.refine_iters)
            else:
                todo.append(run)
        if todo:
            rows.update(self._gather(ray, spec, todo, scene, log))
        return [rows[run] for run in runs]

    def _gather(self, ray, spec: SweepSpec, runs: list[SweepRun], scene: Scene, log: Log) -> dict[SweepRun, dict]:
        """Submit one task per run and collect the rows as the tasks finish, in whatever order."""
        task = ray.remote(num_cpus=self.cpus_per_run, num_gpus=self.gpus_per_run)(run_combination)
        scene_ref = ray.put(scene)
        pending = {task.remote(spec, run, scene_ref, self.cpus_per_run): run for run in runs}
        rows = {}
        while pending:
            [ready], _ = ray.wait(list(pending), num_returns=1)
            run = pending.pop(ready)
            rows[run] = _task_result(ray, ready, run)
            log(f"finished {run.name}")
        return rows


def make_executor(name: str, *, address: str | None = None, cpus_per_run: int | None = None,
                  gpus_per_run: float | None = None, device: str = "cpu") -> Executor:
    """The executor named on the command line, with the Ray defaults for `device`: one CPU and one GPU per run with
    cuda, else no GPU and this machine's cores per run (like the local executor's runs).

    Raises:
        WarpbagsError: an unknown name, or Ray options with the local executor.
    """
    if name not in EXECUTORS:
        raise WarpbagsError(f"--executor must be one of {', '.join(EXECUTORS)}, got {name!r}")
    if name == "local":
        given = [option for option, value in (("--address", address), ("--cpus-per-run", cpus_per_run),
                                              ("--gpus-per-run", gpus_per_run)) if value is not None]
        if given:
            raise WarpbagsError(f"{', '.join(given)} {'needs' if len(given) == 1 else 'need'} --executor ray")
        return LocalExecutor()
    on_gpu = device == "cuda"
    return RayExecutor(address=address,
                       cpus_per_run=cpus_per_run if cpus_per_run is not None else 1 if on_gpu
                       else min(usable_cores(), MAX_RENDER_THREADS),
                       gpus_per_run=gpus_per_run if gpus_per_run is not None else 1.0 if on_gpu else 0.0)


def _import_ray():
    try:
        import ray  # noqa: PLC0415 - an optional extra, needed only by this executor
    except ImportError:
        raise WarpbagsError(f"--executor ray needs Ray: {RAY_INSTALL}") from None
    return ray


def _check_reachable(address: str) -> None:
    """A quick TCP check of HOST:PORT: ray.init retries an address nobody answers for minutes."""
    host, _, port = address.removeprefix("ray://").rpartition(":")
    if not host or not port.isdigit():
        raise WarpbagsError(f"--address must be HOST:PORT, ray://HOST:PORT or auto, got {address!r}")
    try:
        socket.create_connection((host, int(port)), timeout=10).close()
    except OSError as error:
        raise WarpbagsError(f"--address {address}: no Ray cluster answers there ({error}); "
                            "start one with `ray start --head` on that machine") from None


def _task_result(ray, ref, run: SweepRun) -> dict:
    """A task's row; a WarpbagsError inside the task stays one line, naming the run."""
    try:
        return ray.get(ref)
    except ray.exceptions.RayTaskError as error:
        if isinstance(error.cause, WarpbagsError):
            raise WarpbagsError(f"{run.name}: {error.cause}") from None
        raise


def _check_earlier_run(run_dir: Path, config: TrainConfig, scene: Scene) -> None:
    """Raise WarpbagsError when `run_dir` holds a run (finished or not) of another scene folder or other settings than
    `config`: a resumed sweep skips finished runs and continues the others with their saved config, so its table
    would mix settings. The render threads may differ (a machine's, not the run's). A folder that holds no run but
    other files is refused too."""
    folder = RunFolder(run_dir)
    if not (_is_done(run_dir) or folder.has_checkpoint() or folder.holds_unfinished_start()):
        folder.require_new()  # what its training asks when its turn comes: a folder holding something else
    if not (run_dir / "config.json").is_file():
        return
    info = folder.read_info()
    if not folder.trained_on(scene, info):
        raise WarpbagsError(f"{run_dir} holds a run of the scene in {info.get('scene_root')}: choose another --out")
    saved = folder.saved_config(info)
    if retired := retired_fields(info["config"]):  # dropped from `saved`: finished, its row would mix settings too
        raise WarpbagsError(f"{run_dir} holds a run with {', '.join(retired)}, settings of an earlier warpbags that "
                            "this one has no more: choose another --out (or remove that run)")
    differing = differing_fields(saved.to_dict(), config.to_dict(), frozenset({"render_threads"}))
    if differing:
        name, value, asked = differing[0]
        raise WarpbagsError(f"{run_dir} holds a run with {name}={value!r}, not {asked!r}: choose another --out (or "
                            "remove that run)")


def _is_done(run_dir: Path) -> bool:
    return (run_dir / "eval.json").is_file()


def _quiet(message: str) -> None:
    """Runs inside a sweep log nothing of their own: the sweep logs one line per run."""


# evaluate_run writes eval.json atomically, so a malformed one is no sweep's cut short but an older warpbags', another
# tool's or one edited by hand: the sweep does not overwrite it, it says how to replace it.
_EVALUATE_AGAIN = "remove it and run the sweep again to evaluate the run anew"


def _row(run_dir: Path, run: SweepRun, refine_iters: int) -> dict:
    """The run's row of sweep.json, read from its eval.json; a metric eval.json holds as null (`finite_json`'s
    NaN or infinity: the PSNR of an exact render, a metric that failed) is None, and so is psnr_refined of a sweep
    that does not refine the test poses (`refine_iters` 0).

    Raises:
        WarpbagsError: eval.json cannot be read, lacks a number of the row (an older warpbags' or another tool's
            file), or is of another evaluation than the sweep's (`warpbags eval` run on it with other refinement
            iterations than `refine_iters`, or with --pairwise), named with the file.
    """
    path = run_dir / "eval.json"
    try:
        report = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as error:
        raise WarpbagsError(f"{path}: unreadable ({error}); {_EVALUATE_AGAIN}") from None
    alignment = _lookup(report, path, "alignment")  # pairwise below 3 training views
    if not isinstance(alignment, str):
        raise WarpbagsError(f"{path}: alignment is {alignment!r}, not a name; {_EVALUATE_AGAIN}")
    # the sweep's evaluation refines for `refine_iters` (none at 0): a run evaluated otherwise is not comparable
    refined = "images_after_test_pose_refinement"
    iters = _lookup(report, path, refined, "iters") if refined in report else 0
    if iters != refine_iters:
        raise WarpbagsError(f"{path}: evaluated with {iters!r} test pose refinement iterations, not the sweep's "
                            f"{refine_iters} (an earlier sweep with another --refine-iters, or `warpbags eval`); "
                            f"{_EVALUATE_AGAIN}")
    images = _lookup(report, path, "images", "mean")

    def number(*keys: str) -> float | None:
        value = _lookup(report, path, *keys)
        if value is not None and not is_number(value):
            raise WarpbagsError(f"{path}: {'.'.join(keys)} is {value!r}, not a number; {_EVALUATE_AGAIN}")
        return value

    row = {
        "method": run.method, "views": run.views, "rot_noise_deg": run.rot_noise_deg, "seed": run.seed,
        "rot_err_initial": number("poses", alignment, "initial", "rotation_deg_mean"),
        "rot_err_final": number("poses", alignment, "final", "rotation_deg_mean"),
        "trans_err_initial": number("poses", alignment, "initial", "translation_mean"),
        "trans_err_final": number("poses", alignment, "final", "translation_mean"),
        "psnr": number("images", "mean", "psnr"), "ssim": number("images", "mean", "ssim"),
        "flip": number("images", "mean", "flip") if "flip" in images else None,  # none in those from before FLIP
        "psnr_refined": number(refined, "mean", "psnr") if refine_iters else None, "run": run_dir.name,
    }
    # the sweep's evaluation aligns by Procrustes wherever the cameras allow it, as their pose errors in eval.json say
    sweeps = "procrustes" if "procrustes" in report["poses"] else "pairwise"
    if alignment != sweeps:
        raise WarpbagsError(f"{path}: evaluated with the {alignment} alignment, not the sweep's {sweeps} (by `warpbags "
                            f"eval --{alignment}`?); {_EVALUATE_AGAIN}")
    return row


def _lookup(report: object, path: Path, *keys: str) -> object:
    """report[keys[0]][keys[1]]... of eval.json at `path`.

    Raises:
        WarpbagsError: a key that is missing (or a level that is no JSON object), named with `path`.
    """
    value = report
    for depth, key in enumerate(keys):
        if not isinstance(value, dict) or key not in value:
            raise WarpbagsError(f"{path}: no {'.'.join(keys[:depth + 1])} (not an evaluation of this warpbags); "
                                f"{_EVALUATE_AGAIN}")
        value = value[key]
    return value


SWEEP_TABLES = ("sweep.json", "sweep.csv")
"""The tables `run_sweep` writes into the sweep's folder, one row per run."""


def _write_tables(rows: list[dict], out: Path) -> None:
    with atomic_output(out / SWEEP_TABLES[0]) as temporary:
        temporary.write_text(finite_json(rows))
    with atomic_output(out / SWEEP_TABLES[1]) as temporary, open(temporary, "w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)

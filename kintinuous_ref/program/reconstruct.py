"""`kintinuous reconstruct`: a dataset in, a folder of results out.

The program around the algorithm box (kintinuous_ref.pipeline.run): it opens the dataset (a TUM
folder, a log, a bag, a downloaded sequence or a built-in scenario rendered into the cache),
checks everything it can before the first frame, shows progress, and however the run ends saves
what was done (every file written under a temporary name and renamed into place) and says how it
ended in report.json's "status": "completed", "interrupted" or "failed".
"""

from __future__ import annotations

import os
import sys
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Any

import numpy as np

from kintinuous_ref.backend import REFERENCE, Backend, load_backend
from kintinuous_ref.config import Config, PreprocessConfig
from kintinuous_ref.datasets.tum import Frame, FrameSequence
from kintinuous_ref.errors import (
    ConfigError,
    DatasetError,
    ImageSizeError,
    InternalError,
    KintinuousError,
)
from kintinuous_ref.loop_closure.closer import LoopCloser
from kintinuous_ref.pipeline import GROUNDTRUTH, check_run, error_reason, run
from kintinuous_ref.plausibility import ITERATION_KEYS, check_inputs
from kintinuous_ref.program.output_folder import locked, waiting_lock, write_text_atomic
from kintinuous_ref.program.read_ahead import ReadAhead, readers_for
from kintinuous_ref.program.results import prepare_output, save_interrupted_report, write_outputs
from kintinuous_ref.program.warmup import compile_estimate, kernels_to_compile, warm_up
from kintinuous_ref.signals import Interrupted

DEFAULT_DATASET = "desk"
SCENARIO_FRAMES = 300  # length of a built-in scenario generated into the cache


def cache_folder() -> Path:
    """Where generated scenarios are kept: $KINTINUOUS_CACHE, else ~/.cache/kintinuous. A
    variable naming a file (or a path through one) is refused here, naming the variable, since
    the error of the first write below it would name neither."""
    root = os.environ.get("KINTINUOUS_CACHE")
    if not root:
        return Path.home() / ".cache" / "kintinuous"
    path = Path(root)
    for folder in (path, *path.parents):
        if folder.exists():
            if not folder.is_dir():
                raise ConfigError(
                    f"$KINTINUOUS_CACHE={root}: {folder} is a file, not a folder; point "
                    "KINTINUOUS_CACHE at a folder (made when missing), or unset it for "
                    "~/.cache/kintinuous"
                )
            break
    return path


def open_dataset(
    dataset: str | None,
    intrinsics: str | None = None,
    progress: bool = False,
    *,
    size: tuple[int, int] | None = None,
    groundtruth: Path | None = None,
    topics: str | None = None,
    need_camera: bool = True,
    frames_needed: int | None = None,
) -> FrameSequence:
    """Any input the system reads (docs/datasets.md), `desk` when `dataset` is None:

    - a `.klg` log (Kintinuous / ElasticFusion): `size` (default 640x480) and `intrinsics`
      (fx,fy,cx,cy or a JSON file) say what the log does not; without a camera (only when
      `need_camera` is False, for conversion) frames can still be read;
    - a ROS1 `.bag` or ROS2 bag folder: topics `rgb,depth,info` (default TUM's, then
      RealSense's), camera from its CameraInfo unless `intrinsics` is given;
    - a TUM RGB-D folder;
    - a sequence fetched with `kintinuous download` (fr1/desk, ...), from the cache;
    - a built-in synthetic scenario by name (rendered into the cache on first use, its first
      `frames_needed` frames only when that is given).

    `groundtruth` (a TUM trajectory file) gives a log or a bag its ground truth.
    """
    from kintinuous_ref.camera import intrinsics_from_option
    from kintinuous_ref.datasets import bag, download, klg, synthetic, tum

    dataset = dataset or DEFAULT_DATASET
    path = Path(dataset)
    width, height = size or klg.DEFAULT_SIZE
    camera = intrinsics_from_option(intrinsics, width, height) if intrinsics else None
    if path.suffix == ".klg":
        if camera is None and need_camera:
            raise ConfigError(
                f"{path}: a .klg log holds no camera: pass --intrinsics fx,fy,cx,cy "
                "(and --size WxH unless 640x480)"
            )
        if camera is not None and size is None:  # a JSON camera gives the size
            width, height = camera.width, camera.height
        return klg.open_log(path, (width, height), camera, groundtruth)
    if size is not None and intrinsics is None:
        raise ConfigError("--size is the image size of a .klg log, or of --intrinsics fx,fy,cx,cy")
    if bag.is_bag(path):
        chosen = bag.parse_topics(topics) if topics else None
        return bag.open_bag(path, chosen, camera, groundtruth)
    for option, value in (("--groundtruth", groundtruth), ("--topics", topics)):
        if value is not None:
            raise ConfigError(f"{option} applies to .klg logs and bags, not to {dataset}")
    if path.is_dir():
        return tum.open_sequence(path, intrinsics)
    downloaded = download.cached(dataset, cache_folder() / "tum")
    if downloaded is not None:
        return tum.open_sequence(downloaded, intrinsics)
    if dataset in download.SEQUENCES:
        raise DatasetError(
            f"{dataset}: not downloaded yet: run `kintinuous download {dataset}` first"
        )
    scenarios = synthetic.list_scenarios()
    if dataset not in scenarios:
        raise DatasetError(
            f"{dataset}: neither a dataset folder nor a scenario ({', '.join(scenarios)}), "
            "nor a .klg log, a bag or a downloaded sequence"
        )
    folder = cache_folder() / dataset
    # A scenario is rendered only as far as a run needs it (`frames_needed`, all by default),
    # and extended when a later run needs more.
    needed = (
        SCENARIO_FRAMES if frames_needed is None else min(max(frames_needed, 1), SCENARIO_FRAMES)
    )
    # Runs started together render it once: the others wait, then find it rendered.
    with waiting_lock(folder.with_name(f".{folder.name}.lock")):
        rendered = rendered_frames(folder)
        # a cache that lists its frames but lacks its true surface (a render stopped while it
        # made it) is completed, its frames kept and still listed
        if rendered < needed or not (folder / "scene.ply").is_file():
            synthetic.write_scenario(
                dataset,
                folder,
                frames=SCENARIO_FRAMES,
                progress=progress,
                render=max(needed, rendered),
            )
    return tum.open_sequence(folder, intrinsics)


def rendered_frames(folder: Path) -> int:
    """Frames a scenario folder in the cache holds (its associations.txt is written last)."""
    listing = folder / "associations.txt"
    if not listing.is_file():
        return 0
    return sum(1 for line in listing.read_text().splitlines() if line and line[0] != "#")


def check_start(start: int, sequence: FrameSequence) -> None:
    """Refuse a first frame outside the sequence (ConfigError naming --start and its range)."""
    if not 0 <= start < len(sequence):
        raise ConfigError(f"--start {start} outside the sequence's frames 0..{len(sequence) - 1}")


def check_pyramid(config: Config, width: int, height: int, odometry: str = GROUNDTRUTH) -> None:
    """Refuse (ConfigError) a preprocess.pyramid_levels no run can use: none, or more than
    halving a `width` x `height` image leaves a pixel for (the coarsest level would be empty, and
    the reference ends in an internal error at the first frame); or fewer than the tracker of
    `odometry` runs iterations on (check_tracker_levels)."""
    levels = config.preprocess.pyramid_levels
    most = max(min(width, height).bit_length(), 1)  # levels whose short side keeps a pixel
    if not 1 <= levels <= most:
        raise ConfigError(
            f"preprocess.pyramid_levels {levels}: a {width}x{height} image has levels 1..{most} "
            f"(each half the size of the one before); choose one in that range (the default "
            f"is {PreprocessConfig.pyramid_levels})"
        )
    check_tracker_levels(config, odometry)


def check_tracker_levels(config: Config, odometry: str) -> None:
    """Refuse (ConfigError) iterations for more pyramid levels than preprocessing builds: the
    dense tracker of `odometry` (a FOVIS switch's too) needs one level per count, and without
    them fails on every frame, which the run would only report after its work."""
    key = ITERATION_KEYS.get(odometry.removeprefix("fovis/"))
    if key is None:
        return  # ground truth, or FOVIS alone: no dense levels
    section, name = key.split(".")
    iterations = list(getattr(getattr(config, section), name))
    levels = config.preprocess.pyramid_levels
    if len(iterations) > levels:
        raise ConfigError(
            f"{key} {iterations}: counts for {len(iterations)} pyramid levels, but "
            f"preprocess.pyramid_levels is {levels}, so --odometry {odometry} would fail on "
            f"every frame; give {key} at most {levels} counts or preprocess.pyramid_levels at "
            f"least {len(iterations)}"
        )


def _warn(warnings: list[str]) -> None:
    for warning in warnings:
        print(f"kintinuous: warning: {warning}", file=sys.stderr, flush=True)


def _camera_source(sequence: FrameSequence) -> str:
    """Where a sequence's camera came from, for messages: its intrinsics.json, else the
    sequence."""
    listed = Path(sequence.path) / "intrinsics.json"
    return str(listed) if listed.is_file() else str(sequence.path)


def _first_depth(
    sequence: FrameSequence, start: int, skip_bad_frames: bool, camera_source: str
) -> np.ndarray | None:
    """The depth (metres) of the run's first frame, read before the work so that a frame no run
    can use is refused before an output folder exists: an image whose size is not the camera's
    (every frame would differ alike), or a frame that cannot be read. With `skip_bad_frames` an
    unreadable first frame is None, and the run leaves it out."""
    try:
        return sequence[start].depth
    except ImageSizeError as err:
        raise ImageSizeError(f"frame {start}: {err} (the camera of {camera_source})") from None
    except DatasetError as err:
        if skip_bad_frames:
            return None
        raise DatasetError(f"frame {start}: {err}") from None


def _bad_frames_checked(
    items: Iterable[tuple[int, Frame | None, BaseException | None]],
    skip: bool,
    skipped: list[str],
) -> Iterator[Frame]:
    """The frames of ReadAhead's items; an unreadable one (corrupt, wrong size) is a
    DatasetError naming the frame and its file, or with `skip` left out and listed in
    `skipped`, when the run reaches it."""
    for index, frame, error in items:
        if error is None:
            yield frame
            continue
        if not isinstance(error, DatasetError):
            raise error
        message = f"frame {index}: {error}"
        if not skip:
            raise DatasetError(message) from None
        skipped.append(message)


# (backend, odometry) pairs whose kernels this process has compiled or loaded already
_PREPARED: set[tuple[str, str]] = set()


def prepare_kernels(backend: Backend, config: Config, odometry: str) -> None:
    """Compile (or load from numba's cache) the kernels the run will call, before its progress
    bar starts, so that the bar's rate and time left count frames only. A compile is one line
    on stderr: announced with how long it will take (compile_estimate) where numba's cache lacks
    the kernels, and ended with how long it took; loading from the cache takes about a second
    and says nothing."""
    if backend.name == REFERENCE or (backend.name, odometry) in _PREPARED:
        return
    part = kernels_to_compile(backend, tracking=odometry != GROUNDTRUTH)
    if part is not None:
        print(
            f"compiling the {backend.name} kernels for {part}, not yet in numba's cache "
            f"({compile_estimate(backend, part)}; later runs load them in seconds)...",
            end="",
            file=sys.stderr,
            flush=True,
        )
    try:
        report = warm_up(backend, config, odometry)
    except BaseException:
        if part is not None:  # the error on a line of its own
            print(file=sys.stderr, flush=True)
        raise
    _PREPARED.add((backend.name, odometry))
    if part is not None:
        print(f" done in {report.seconds:.0f} s", file=sys.stderr, flush=True)
    elif report.kernel_seconds:  # compiled in this process alone (cuda), or a stale record
        count = len(report.kernel_seconds)
        print(f"compiled {count} kernels in {report.seconds:.0f} s", file=sys.stderr, flush=True)


def reconstruct(
    sequence: FrameSequence,
    out: Path,
    config: Config,
    odometry: str = GROUNDTRUTH,
    start: int = 0,
    count: int | None = None,
    backend_name: str = "ref",
    show_progress: bool = True,
    predict_model: bool | None = None,
    overwrite: bool = False,
    skip_bad_frames: bool = False,
    loop_closure: bool = False,
    plausibility_checks: bool = True,
    camera_source: str | None = None,
) -> dict[str, Any]:
    """Run the pipeline over frames start.. of a sequence and write the outputs into `out`.

    Everything that can be checked is checked before the first frame is read; `out` must not
    hold an earlier result unless `overwrite` (which removes it first), and is held by this run
    (output_folder.locked): a second run into it is refused while this one lives. However the
    run ends,
    what was done is saved (write_outputs) with its status; then an interrupted run raises
    Interrupted, a failed one a one-line KintinuousError (InternalError for a bug, whose
    traceback goes to crash.log in `out`). An unreadable frame ends the run, or with
    `skip_bad_frames` is left out and counted in the report's "skipped_frames". `loop_closure`
    closes loops and deforms the map (docs/loop_closure.md). `plausibility_checks` refuses
    valid but absurd input before the work (plausibility.check_inputs; `camera_source` names
    where the camera came from, the dataset's by default); what they and the run find
    suspicious is written to stderr and report.json's "warnings".
    """
    backend = load_backend(backend_name)  # ConfigError when it cannot run here
    check_start(start, sequence)
    if count is not None and count <= 0:
        raise ConfigError(f"--frames must be positive, got {count}")
    warnings: list[str] = []
    groundtruth = None
    if sequence.groundtruth is not None:
        try:
            groundtruth = sequence.groundtruth_for_frames()
        except DatasetError as err:
            if odometry == GROUNDTRUTH:
                raise
            # optional for a tracker: the run goes on from the identity, and says so
            warnings.append(f"{err}: ground truth not used; the run starts at the identity")
    check_run(config, odometry, groundtruth, backend, loop_closure, dataset=str(sequence.path))
    check_pyramid(config, sequence.camera.width, sequence.camera.height, odometry)
    camera_source = camera_source or _camera_source(sequence)
    depth = _first_depth(sequence, start, skip_bad_frames, camera_source)
    if plausibility_checks:
        first_pose = np.eye(4) if groundtruth is None else groundtruth.poses[start]
        warnings += check_inputs(config, sequence.camera, camera_source, depth, first_pose, start)
    _warn(warnings)
    with locked(out):  # a second run into `out` is refused until this one ends
        out = prepare_output(out, overwrite)
        total = (len(sequence) - start) if count is None else min(count, len(sequence) - start)
        bar = None
        if show_progress:
            from tqdm import tqdm

            prepare_kernels(backend, config, odometry)

            bar = tqdm(total=total, unit="frame", desc="reconstruct")
        skipped: list[str] = []
        readers = readers_for() if sequence.parallel_reads else 1
        frames = range(start, start + total)
        reader = ReadAhead(
            sequence.__getitem__, frames, goes_on_after=DatasetError, readers=readers
        )
        try:
            result = run(
                _bad_frames_checked(reader, skip_bad_frames, skipped),
                sequence.camera,
                config,
                odometry,
                groundtruth,
                progress=(lambda _: bar.update(1)) if bar is not None else None,
                predict_model=predict_model,
                slices=out / "slices",
                backend=backend,
                capture_errors=True,
                loop_closer=LoopCloser(config, sequence.camera) if loop_closure else None,
            )
        except BaseException:
            if bar is not None:
                bar.close()
            raise
        finally:
            reader.close()  # the sequence is this thread's again
        info = {
            "dataset": str(sequence.path),
            "odometry": odometry,
            "backend": backend.name,
            "start": start,
            "skipped_frames": len(skipped),
            "skipped_reasons": skipped[:50],
            "warnings": warnings,
        }
        saved: list[str] = []
        try:
            if bar is not None:
                bar.close()  # the one-line messages below start on a line of their own
            print(
                f"writing the results of {result.frames} frames (trajectory, mesh, report)...",
                file=sys.stderr,
                flush=True,
            )
            expected = KintinuousError | OSError | MemoryError  # one line, no crash.log
            if result.error is not None and not isinstance(result.error, expected):
                write_text_atomic(out / "crash.log", result.error_traceback)
                saved.append("crash.log")
            report = write_outputs(result, out, info, saved=saved, groundtruth=groundtruth)
        except KeyboardInterrupt as again:
            name = getattr(again, "signal_name", "SIGINT")
            names = ["trajectory.txt", "mesh.ply", "preview.png", "report.json"]
            if result.moving is not None:
                names.insert(2, "volume_origins.txt")
            if "report.json" not in saved:  # how the run ended, written in milliseconds
                save_interrupted_report(out, info, result, saved, names, name)
            missing = [n for n in names if n not in saved]
            raise Interrupted(
                name,
                f"{name} during the save: saved {', '.join(saved) or 'nothing'} in {out}; "
                f"NOT saved: {', '.join(missing)}",
            ) from None
        except OSError as err:
            raise KintinuousError(
                f"{out}: cannot save the run ({error_reason(err)}); saved: "
                f"{', '.join(saved) or 'nothing'}"
            ) from None
        _warn(report["warnings"][len(warnings) :])  # the run's own
        kept = f"the {result.frames} frames done are saved in {out}"
        if report["not_saved"]:
            problems = "; ".join(f"{k}: {v}" for k, v in report["not_saved"].items())
            kept = f"saved {', '.join(report['saved'])} in {out} but NOT {problems}"
        if result.interrupted:
            raise Interrupted(
                result.signal_name,
                f"{result.reason} after frame {result.last_frame}: {kept}",
            )
        if result.error is not None:
            if "crash.log" in saved:
                raise InternalError(f"{result.reason}; traceback in {out / 'crash.log'}; {kept}")
            raise KintinuousError(f"{result.reason}; {kept}")
        if report["not_saved"]:
            raise KintinuousError(kept)
        return report

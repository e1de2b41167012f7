"""The `kintinuous` command: reconstruct, synth, evaluate, table, benchmark, warmup, convert,
download and info.

Heavy modules are imported inside the handlers so that `kintinuous --help` stays instant.
Errors meant for people (KintinuousError, and argparse's usage errors) become one line on stderr
and exit status 2; an OSError (a full disk, a folder that cannot be written) one line and 2;
SIGINT, SIGTERM and SIGHUP one line and 128 + the signal's number. Any other exception is a bug:
one line that says so, exit status 70, and the traceback in a crash log (reconstruct's in its
output folder, with the run's work kept). A command that did not do all that was asked (a
`table` with a failed run) exits with status 1.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path
from typing import Any, NoReturn

from kintinuous_ref import __version__
from kintinuous_ref.errors import ConfigError, InternalError, KintinuousError
from kintinuous_ref.strict_json import dumps as strict_dumps

# The algorithms multiply many small matrices (6xN systems, 3x3 rotations), for which a threaded
# BLAS costs more in wake-ups than it gains: measured 25 ms instead of 0.15 ms per product on a
# busy 2-core machine. Must be set before NumPy is first imported (the handlers import it lazily).
for _variable in ("OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):  # OpenMP users keep their threads
    os.environ.setdefault(_variable, "1")

# The names of kintinuous_ref.odometry.METHODS, spelled out so that --help needs no NumPy import
# (tests/test_trackers.py checks that the two agree).
ODOMETRY_CHOICES = (
    "groundtruth",
    "icp",
    "rgbd",
    "fovis",
    "fovis/icp",
    "fovis/rgbd",
    "icp+rgbd",
    "fovis/icp+rgbd",
)
DEFAULT_ODOMETRY = "icp+rgbd"  # kintinuous_ref.odometry.DEFAULT_METHOD, the paper's tracker


# The help of --fast-odometry on reconstruct and benchmark. Its speed and accuracy are measured
# in docs/benchmarks.md, not quoted here, so that the help never outlives its numbers.
FAST_ODOMETRY_HELP = (
    "dense trackers skip the finest pyramid level (the original code's CPU option) and the "
    "model is raycast only for the quarter of the pixels they read: faster tracking and "
    "raycasting for some frame-to-frame accuracy (docs/benchmarks.md measures both)"
)


def _finite_float(text: str) -> float:
    """An option's number: finite (no inf or nan)."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, found {text!r}") from None
    if value != value or value in (float("inf"), float("-inf")):
        raise argparse.ArgumentTypeError(f"expected a finite number, found {text!r}")
    return value


class _Parser(argparse.ArgumentParser):
    """argparse with its errors as one line, like every other error of the command."""

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"kintinuous: error: {message} (see {self.prog} --help)\n")


def _add_synth(commands: argparse._SubParsersAction) -> None:
    parser = commands.add_parser(
        "synth",
        help="render a synthetic RGB-D sequence with exact ground truth (TUM folder layout)",
    )
    parser.add_argument("scenario", nargs="?", help="scenario name (see --list)")
    parser.add_argument("--list", action="store_true", help="list the scenarios and exit")
    parser.add_argument("--out", type=Path, help="output folder")
    parser.add_argument("--frames", type=int, default=300)
    parser.add_argument("--width", type=int, default=640)
    parser.add_argument("--height", type=int, default=480)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--no-noise", action="store_true", help="exact depth and colour")
    parser.add_argument(
        "--workers", type=int, default=2, help="processes rendering frames (default 2)"
    )
    parser.add_argument(
        "--mesh-spacing",
        type=_finite_float,
        default=0.05,
        help="edge length of the ground-truth mesh scene.ply in metres (default 0.05)",
    )
    parser.set_defaults(handler=_run_synth)


def _run_synth(args: argparse.Namespace) -> None:
    from kintinuous_ref.datasets import synthetic

    if args.list:
        for name, summary in synthetic.list_scenarios().items():
            print(f"{name:10s} {summary}")
        return
    if not args.scenario or not args.out:
        raise KintinuousError("synth needs a SCENARIO and --out DIR (or --list)")
    synthetic.write_scenario(
        args.scenario,
        args.out,
        frames=args.frames,
        width=args.width,
        height=args.height,
        seed=args.seed,
        noise=not args.no_noise,
        progress=True,
        workers=max(1, args.workers),
        mesh_spacing=args.mesh_spacing,
    )
    print(f"wrote {args.frames} frames of '{args.scenario}' to {args.out}")


def _add_evaluate(commands: argparse._SubParsersAction) -> None:
    parser = commands.add_parser(
        "evaluate", help="ATE, frame-to-frame error and drift of a trajectory against ground truth"
    )
    parser.add_argument("estimate", type=Path, help="estimated trajectory (TUM format)")
    parser.add_argument("groundtruth", type=Path, help="ground-truth trajectory (TUM format)")
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    parser.set_defaults(handler=_run_evaluate)


def _run_evaluate(args: argparse.Namespace) -> None:
    from kintinuous_ref import metrics
    from kintinuous_ref.datasets import tum

    errors = metrics.evaluate(
        tum.read_trajectory(args.estimate), tum.read_trajectory(args.groundtruth)
    )
    if args.json:
        print(strict_dumps(errors.as_dict()))
    else:
        print(errors.summary())


def _add_run_options(parser: argparse.ArgumentParser) -> None:
    """The options every command that runs the pipeline shares: volume, backend, configuration."""
    parser.add_argument("--volume-size", type=_finite_float, default=3.0, help="cube side, metres")
    parser.add_argument("--resolution", type=int, default=256, help="voxels per side")
    parser.add_argument(
        "--backend",
        choices=["ref", "cpu", "cuda", "auto"],
        default="auto",
        help="ref (NumPy), cpu (numba), cuda; auto: cuda where a GPU works, else cpu "
        "(kintinuous info)",
    )
    parser.add_argument(
        "--config",
        type=Path,
        help='JSON file of configuration values, nested ({"icp": {...}}) or dotted keys',
    )
    parser.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="override one configuration value, e.g. --set combined.rgbd_weight=0.2 "
        "(value parsed as JSON when it can be; repeatable; applied after --config)",
    )


def _add_reconstruct(commands: argparse._SubParsersAction) -> None:
    parser = commands.add_parser(
        "reconstruct",
        help="fuse an RGB-D sequence into a coloured mesh (mesh.ply, trajectory.txt, report.json)",
    )
    parser.add_argument(
        "dataset",
        nargs="?",
        help="TUM folder, .klg log, ROS bag, downloaded sequence (fr1/desk, ...) or synthetic "
        "scenario name (default: desk, generated and cached); docs/datasets.md",
    )
    parser.add_argument(
        "--out",
        required=True,
        help="output folder (new, empty, or holding an earlier result with --overwrite)",
    )
    parser.add_argument(
        "--overwrite",
        action="store_true",
        help="replace the earlier result in --out (removed before the run starts)",
    )
    parser.add_argument(
        "--skip-bad-frames",
        action="store_true",
        help="leave out an unreadable frame (corrupt or wrong size) and count it in the report, "
        "instead of stopping there (the work before it is kept either way)",
    )
    parser.add_argument(
        "--odometry",
        default=DEFAULT_ODOMETRY,
        choices=ODOMETRY_CHOICES,
        help=f"a tracker (docs/odometry.md) or groundtruth (known poses); default "
        f"{DEFAULT_ODOMETRY}, the paper's",
    )
    parser.add_argument("--frames", type=int, help="number of frames (default: all)")
    parser.add_argument("--start", type=int, default=0, help="first frame")
    _add_run_options(parser)
    parser.add_argument(
        "--shift-threshold",
        type=int,
        default=14,
        metavar="V",
        help="moving volume: shift when the camera is V voxels from the volume's basis "
        "(1..16, default 14; docs/moving_volume.md)",
    )
    parser.add_argument(
        "--fixed-volume",
        action="store_true",
        help="keep the volume where it starts (KinectFusion) instead of moving it (Kintinuous)",
    )
    parser.add_argument(
        "--loop-closure",
        action="store_true",
        help="recognise revisited places, correct the trajectory through a pose graph and "
        "deform the map (docs/loop_closure.md); writes trajectory_uncorrected.txt and "
        "trajectory_loops.png too",
    )
    parser.add_argument(
        "--intrinsics",
        help="fx,fy,cx,cy or a JSON file (overrides the dataset's camera; a .klg log needs it)",
    )
    _add_input_options(parser)
    parser.add_argument(
        "--no-colour-weighting",
        action="store_true",
        help="fuse colour without the angle weight and discontinuity check (paper VI-B)",
    )
    parser.add_argument(
        "--fast-odometry",
        action="store_true",
        help=FAST_ODOMETRY_HELP,
    )
    parser.add_argument(
        "--raycast",
        action="store_true",
        help="predict the model every frame even when no tracker needs it (for timings)",
    )
    parser.set_defaults(handler=_run_reconstruct)


def _run_reconstruct(args: argparse.Namespace) -> None:
    from kintinuous_ref.backend import load_backend
    from kintinuous_ref.config import ColourConfig, Config, VolumeConfig, fast_odometry
    from kintinuous_ref.pipeline import check_settings
    from kintinuous_ref.program import reconstruct

    config = Config(
        volume=VolumeConfig(
            resolution=args.resolution,
            size=args.volume_size,
            shift_threshold=args.shift_threshold,
            moving=not args.fixed_volume,
        ),
        colour=ColourConfig(
            angle_weighting=not args.no_colour_weighting,
            discontinuity_check=not args.no_colour_weighting,
        ),
    )
    config = _configured(config, args.config, args.set)
    if args.fast_odometry:
        config = fast_odometry(config)
    # before generating or reading anything: the settings, the volume against the memory that
    # will hold it among them
    check_settings(config, args.odometry, load_backend(args.backend), args.loop_closure)
    out = reconstruct.check_output(args.out, args.overwrite)
    sequence = reconstruct.open_dataset(
        args.dataset,
        args.intrinsics,
        progress=True,
        size=_parse_size(args.size),
        groundtruth=args.groundtruth,
        topics=args.topics,
        frames_needed=args.start + args.frames if args.frames else None,
    )
    report = reconstruct.reconstruct(
        sequence,
        out,
        config,
        odometry=args.odometry,
        start=args.start,
        count=args.frames,
        backend_name=args.backend,
        predict_model=True if args.raycast else None,
        overwrite=args.overwrite,
        skip_bad_frames=args.skip_bad_frames,
        loop_closure=args.loop_closure,
    )
    total = report["timing_ms"]["total"]["mean"]
    skipped = f", skipped {report['skipped_frames']} bad" if report["skipped_frames"] else ""
    print(
        f"fused {report['fused_frames']} of {report['frames']} frames{skipped} "
        f"({total:.0f} ms per frame); wrote {out}/mesh.ply with "
        f"{report['mesh']['vertices']} vertices ({report['shifts']} volume shifts, "
        f"{report['slices']} slices)"
    )
    if "loop_closures" in report:
        loops = report["loop_closures"]
        print(
            f"loop closure: {loops['keyframes']} keyframes, {loops['candidates']} candidates "
            f"verified, {len(loops['closures'])} loops closed (docs/loop_closure.md)"
        )


def _add_input_options(parser: argparse.ArgumentParser) -> None:
    """The options that say what a .klg log or a bag does not (reconstruct and convert)."""
    parser.add_argument(
        "--size",
        metavar="WxH",
        help="image size of a .klg log, or of the images --intrinsics fx,fy,cx,cy describes "
        "(default 640x480)",
    )
    parser.add_argument(
        "--groundtruth",
        type=Path,
        metavar="FILE",
        help="ground-truth trajectory (TUM format) of a .klg log or a bag",
    )
    parser.add_argument(
        "--topics",
        metavar="RGB,DEPTH,INFO",
        help="a bag's colour, depth and camera-info topics (default: TUM's "
        "/camera/rgb/image_color,/camera/depth/image,/camera/rgb/camera_info, else the "
        "RealSense driver's /camera/color/image_raw,/camera/aligned_depth_to_color/image_raw,"
        "/camera/color/camera_info)",
    )


def _parse_size(text: str | None) -> tuple[int, int] | None:
    """--size WIDTHxHEIGHT as (width, height); None when not given."""
    if not text:
        return None
    width, _, height = text.lower().partition("x")
    if not (width.isdigit() and height.isdigit() and int(width) > 0 and int(height) > 0):
        raise KintinuousError(f"--size expects WIDTHxHEIGHT such as 320x240, got {text!r}")
    return int(width), int(height)


def _add_convert(commands: argparse._SubParsersAction) -> None:
    parser = commands.add_parser(
        "convert",
        help="convert a sequence: to a .klg log (OUT ending in .klg) or to a TUM folder",
        description="Write any input reconstruct reads (TUM folder, .klg log, bag, downloaded "
        "sequence or scenario) as a Kintinuous/ElasticFusion .klg log when OUT ends in .klg "
        "(zlib millimetre depth, JPEG colour), else as a new TUM folder (PNG images; "
        "intrinsics.json and groundtruth.txt when known).",
    )
    parser.add_argument("source", help="input sequence")
    parser.add_argument("out", type=Path, help="OUT.klg or a new folder")
    parser.add_argument("--intrinsics", help="fx,fy,cx,cy or a JSON file (the source's camera)")
    _add_input_options(parser)
    parser.set_defaults(handler=_run_convert)


def _run_convert(args: argparse.Namespace) -> None:
    from kintinuous_ref.datasets import klg, tum
    from kintinuous_ref.program import reconstruct

    sequence = reconstruct.open_dataset(
        args.source,
        args.intrinsics,
        progress=True,
        size=_parse_size(args.size),
        groundtruth=args.groundtruth,
        topics=args.topics,
        need_camera=False,
    )
    frames = sequence.frames()
    if args.out.suffix == ".klg":
        if args.out.exists():
            raise KintinuousError(f"{args.out}: already exists; choose a new output file")
        count = klg.write_log(args.out, frames)
        camera = sequence.camera
        print(f"wrote {count} frames to {args.out}")
        if camera is not None:
            print(
                f"read it with: --intrinsics {camera.fx:g},{camera.fy:g},{camera.cx:g},"
                f"{camera.cy:g} --size {camera.width}x{camera.height}"
            )
    else:
        truth = sequence.groundtruth
        count = tum.write_sequence(args.out, frames, sequence.camera, truth)
        print(f"wrote {count} frames to {args.out}")


# The names of kintinuous_ref.datasets.download.SEQUENCES, spelled out so that --help needs no
# NumPy import (tests/test_download.py checks that they agree).
PAPER_SEQUENCES = ("fr1/desk", "fr2/desk", "fr1/room", "fr2/large_no_loop")
OTHER_SEQUENCES = ("fr1/xyz", "fr1/360", "fr2/xyz", "fr3/long_office_household")
TUM_BASE_URL = "https://cvg.cit.tum.de/rgbd/dataset/"
MIRROR_VARIABLE = "KINTINUOUS_MIRROR"


def _add_download(commands: argparse._SubParsersAction) -> None:
    paper, others = ", ".join(PAPER_SEQUENCES), ", ".join(OTHER_SEQUENCES)
    parser = commands.add_parser(
        "download",
        help=f"fetch a TUM RGB-D sequence by name ({paper}, ...) or an archive URL",
        description=f"Fetch and unpack TUM RGB-D sequences into the cache "
        f"($KINTINUOUS_CACHE or ~/.cache/kintinuous, under tum/), after which reconstruct and "
        f"table take the name (kintinuous reconstruct fr1/desk). The paper's Table I "
        f"sequences: {paper}. Also known: {others}. Their sha256 checksums are not pinned "
        f"(each download prints the one it got; --sha256 pins it).",
    )
    parser.add_argument(
        "targets", nargs="+", metavar="NAME|URL", help="sequence name(s) or a TUM-layout .tgz URL"
    )
    parser.add_argument(
        "--dest", type=Path, help="folder to unpack into (default: the cache's tum/ folder)"
    )
    parser.add_argument("--sha256", metavar="HEX", help="expected sha256 of the archive")
    parser.add_argument(
        "--mirror",
        metavar="URL",
        help=f"base URL that replaces {TUM_BASE_URL} for named sequences (default: "
        f"${MIRROR_VARIABLE} when set)",
    )
    parser.set_defaults(handler=_run_download)


def _run_download(args: argparse.Namespace) -> None:
    from kintinuous_ref.datasets.download import download
    from kintinuous_ref.program import reconstruct

    if args.sha256 and len(args.targets) > 1:
        raise KintinuousError("--sha256 checks one archive: give one NAME or URL with it")
    root = args.dest or reconstruct.cache_folder() / "tum"
    mirror = args.mirror or os.environ.get(MIRROR_VARIABLE) or None
    for target in args.targets:
        folder, digest = download(target, root, args.sha256, mirror)
        if digest:
            print(f"{target}: unpacked into {folder} (archive sha256 {digest})")
        else:
            print(f"{target}: already in {folder}")


def _configured(config: Any, path: Path | None, settings: list[str]) -> Any:
    """`config` with the values of a JSON file (nested or dotted keys) and then of KEY=VALUE
    strings, each checked against its field's type where it is read: a bad value is one
    ConfigError naming the file or --set, the key, what was expected and what was found."""
    from kintinuous_ref.config import with_overrides

    if path is not None:
        values = _flatten(_read_config_file(Path(path)))
        try:
            config = with_overrides(config, values)
        except ConfigError as err:
            raise ConfigError(f"{path}: {err}") from None
    for setting in settings:
        key, equals, text = setting.partition("=")
        if not equals or not key.strip():
            raise ConfigError(f"--set expects KEY=VALUE, got {setting!r}")
        try:
            value = json.loads(text)
        except (json.JSONDecodeError, RecursionError):
            value = text  # a bare word such as original-code
        try:
            config = with_overrides(config, {key.strip(): value})
        except ConfigError as err:
            raise ConfigError(f"--set: {err}") from None
    return config.validate()


def _read_config_file(path: Path) -> dict:
    """The JSON object of a --config file, or a one-line ConfigError saying why not."""
    if path.is_dir():
        raise ConfigError(f"{path}: is a folder; --config takes a JSON file")
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        raise ConfigError(f"{path}: configuration file not found") from None
    except OSError as err:
        raise ConfigError(f"{path}: cannot read the configuration file ({err.strerror})") from None
    try:
        values = json.loads(data.decode("utf-8"))
    except UnicodeDecodeError:
        raise ConfigError(f"{path}: not a text file; --config takes a JSON file") from None
    except json.JSONDecodeError as err:
        raise ConfigError(f"{path}: not valid JSON ({err})") from None
    except RecursionError:
        raise ConfigError(f"{path}: not valid JSON (nested too deeply)") from None
    if not isinstance(values, dict):
        raise ConfigError(
            f"{path}: expected one JSON object of configuration values, found "
            f"{type(values).__name__}"
        )
    return values


def _flatten(values: dict, prefix: str = "") -> dict:
    """{"icp": {"iterations": [..]}} as {"icp.iterations": [..]} (values checked later)."""
    flat: dict = {}
    for key, value in values.items():
        if isinstance(value, dict) and value:
            flat.update(_flatten(value, f"{prefix}{key}."))
        else:
            flat[f"{prefix}{key}"] = value
    return flat


def _add_table(commands: argparse._SubParsersAction) -> None:
    parser = commands.add_parser(
        "table",
        help="the paper's Tables I-VI and Figs. 4-7: every odometry method on every dataset",
    )
    parser.add_argument(
        "datasets", nargs="+", metavar="DATASET", help="TUM folders or synthetic scenario names"
    )
    parser.add_argument(
        "--methods",
        nargs="+",
        choices=ODOMETRY_CHOICES[1:],
        metavar="METHOD",
        help=f"odometry methods: {', '.join(ODOMETRY_CHOICES[1:])} (default: all seven)",
    )
    parser.add_argument("--out", type=Path, default=Path("evaluation"), help="output folder")
    parser.add_argument("--jobs", type=int, default=1, help="runs in parallel (processes)")
    parser.add_argument(
        "--scheduler",
        metavar="ADDRESS",
        help="send the runs to this dask.distributed scheduler instead (pip install "
        "'kintinuous[dask]'; workers must see the datasets and --out)",
    )
    parser.add_argument("--frames", type=int, help="frames per run (default: all)")
    parser.add_argument("--start", type=int, default=0, help="first frame")
    parser.add_argument("--size", help="WIDTHxHEIGHT: resize the images (e.g. 320x240)")
    _add_run_options(parser)
    parser.add_argument("--mesh", action="store_true", help="also write each run's mesh.ply")
    parser.set_defaults(handler=_run_table)


def _run_table(args: argparse.Namespace) -> int:
    from kintinuous_ref.config import Config, VolumeConfig
    from kintinuous_ref.program.evaluation import evaluate_methods, method_title

    size = _parse_size(args.size)
    if args.scheduler:
        from kintinuous_ref.program.evaluation.runs import dask_client

        dask_client(args.scheduler).close()  # fail early: dask missing or scheduler unreachable
    config = Config(volume=VolumeConfig(resolution=args.resolution, size=args.volume_size))
    config = _configured(config, args.config, args.set)

    def done(outcome, finished: int, total: int) -> None:  # noqa: ANN001
        if outcome.status == "ok":
            errors = outcome.errors
            what = (
                f"ATE median {errors['ate_median']:.4f} m, {outcome.tracking_failures} "
                f"tracking failures, {outcome.seconds:.0f} s"
            )
        else:
            what = f"FAILED: {outcome.reason}"
        print(f"[{finished}/{total}] {outcome.dataset} {method_title(outcome.method)}: {what}")
        sys.stdout.flush()

    header = ["# Kintinuous odometry evaluation (paper section VII)", ""]
    header += [f"Command: `{_table_command(args)}`", ""]
    evaluation = evaluate_methods(
        args.datasets,
        args.out,
        methods=args.methods,
        config=config,
        start=args.start,
        frames=args.frames,
        size=size,
        backend=args.backend,
        jobs=args.jobs,
        scheduler=args.scheduler,
        mesh=args.mesh,
        on_done=done,
        header=header,
    )
    print()
    print(evaluation.markdown)
    print(f"wrote {', '.join(str(path) for path in evaluation.files)}", flush=True)
    if evaluation.failed:
        print(
            f"kintinuous: {len(evaluation.failed)} of {len(evaluation.outcomes)} runs failed "
            "(reasons in table.md)",
            file=sys.stderr,
        )
        return 1
    return 0


def _table_command(args: argparse.Namespace) -> str:
    """The command line that reproduces a table (for table.md)."""
    import shlex

    words = ["kintinuous", "table", *args.datasets]
    if args.methods:
        words += ["--methods", *args.methods]
    for option in ("out", "jobs", "scheduler", "frames", "start", "size", "volume_size"):
        if getattr(args, option) is not None:
            words += [f"--{option.replace('_', '-')}", str(getattr(args, option))]
    words += ["--resolution", str(args.resolution), "--backend", args.backend]
    words += ["--mesh"] if args.mesh else []
    words += ["--config", str(args.config)] if args.config else []
    for setting in args.set:
        words += ["--set", setting]
    return shlex.join(words)


def _add_benchmark(commands: argparse._SubParsersAction) -> None:
    parser = commands.add_parser(
        "benchmark", help="per-stage milliseconds and frames/s of the pipeline on one backend"
    )
    parser.add_argument(
        "dataset", nargs="?", help="TUM folder or synthetic scenario name (default: desk)"
    )
    parser.add_argument("--odometry", default=DEFAULT_ODOMETRY, choices=ODOMETRY_CHOICES)
    parser.add_argument("--frames", type=int, default=30, help="frames (the first is a warm-up)")
    parser.add_argument("--start", type=int, default=0, help="first frame")
    _add_run_options(parser)
    parser.add_argument(
        "--fast-odometry",
        action="store_true",
        help=FAST_ODOMETRY_HELP,
    )
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    parser.set_defaults(handler=_run_benchmark)


def _run_benchmark(args: argparse.Namespace) -> None:
    from kintinuous_ref.config import Config, VolumeConfig, fast_odometry
    from kintinuous_ref.program.benchmark import benchmark, format_table

    config = Config(volume=VolumeConfig(resolution=args.resolution, size=args.volume_size))
    config = _configured(config, args.config, args.set)
    if args.fast_odometry:
        config = fast_odometry(config)
    report = benchmark(
        args.dataset, args.backend, args.odometry, args.frames, config, start=args.start
    )
    print(strict_dumps(report) if args.json else format_table(report))


def _add_warmup(commands: argparse._SubParsersAction) -> None:
    parser = commands.add_parser(
        "warmup",
        help="compile a backend's kernels now (numba does it once per installation) and say "
        "how long each took",
    )
    parser.add_argument(
        "--backend", choices=["ref", "cpu", "cuda", "auto"], default="auto", help="default auto"
    )
    parser.add_argument(
        "--odometry",
        default="all",
        choices=("all", *ODOMETRY_CHOICES),
        help="the trackers to compile (default all)",
    )
    parser.add_argument(
        "--empty-cache",
        action="store_true",
        help="measure what a fresh installation pays: compile into an empty temporary cache "
        "in a child process (this installation's cache is left as it is)",
    )
    parser.add_argument(
        "--serial",
        action="store_true",
        help="compile in this process only (by default a cold cpu cache is filled by two "
        "processes at once)",
    )
    parser.add_argument("--kernels", type=int, default=10, help="slowest kernels to list")
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    parser.set_defaults(handler=_run_warmup)


def _run_warmup(args: argparse.Namespace) -> None:
    from kintinuous_ref.backend import load_backend
    from kintinuous_ref.program import warmup

    backend = load_backend(args.backend)  # a one-line error before any work
    if args.empty_cache:
        report = warmup.warm_up_from_empty_cache(backend.name, args.odometry, args.serial)
    else:
        from tqdm import tqdm

        from kintinuous_ref.config import Config

        methods = warmup.methods_for(args.odometry)
        with tqdm(total=len(methods), unit="tracker", desc="warmup", disable=args.json) as bar:
            report = warmup.warm_up(
                backend,
                Config(),
                args.odometry,
                progress=lambda _: bar.update(1),
                parallel=not args.serial,
            ).as_dict()
    print(strict_dumps(report) if args.json else warmup.format_report(report, args.kernels))


def _add_info(commands: argparse._SubParsersAction) -> None:
    parser = commands.add_parser("info", help="which compute backends work on this machine")
    parser.set_defaults(handler=_run_info)


def _run_info(args: argparse.Namespace) -> None:
    from kintinuous_ref.backend import backend_status, load_backend

    notes = {"ref": "NumPy reference", "cpu": "numba parallel CPU loops", "cuda": "numba.cuda"}
    print(f"kintinuous {__version__}")
    for name, reason in backend_status().items():
        if reason:
            print(f"{name:5s} no    {reason}")
            continue
        note = load_backend(name).note
        print(f"{name:5s} yes   {notes.get(name, 'a plugin')}" + (f" ({note})" if note else ""))
    print(f"auto -> {load_backend('auto').name}")


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(
        prog="kintinuous",
        description="Dense RGB-D mapping with robust visual odometry (Whelan et al., ICRA 2013).",
    )
    parser.add_argument("--version", action="version", version=f"kintinuous {__version__}")
    commands = parser.add_subparsers(title="commands", metavar="COMMAND")
    for add in (
        _add_synth,
        _add_evaluate,
        _add_reconstruct,
        _add_table,
        _add_info,
        _add_benchmark,
        _add_warmup,
        _add_convert,
        _add_download,
    ):
        add(commands)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)  # SystemExit: --help, --version or a one-line usage error
    if not hasattr(args, "handler"):
        parser.print_help()
        return 1
    from kintinuous_ref.signals import Interrupted, handle_signals

    try:
        with handle_signals():
            status = args.handler(args)
    except InternalError as err:
        print(f"kintinuous: {err}", file=sys.stderr)  # it says that it is a bug
        return 70
    except KintinuousError as err:
        print(f"kintinuous: error: {err}", file=sys.stderr)
        return 2
    except Interrupted as stop:
        print(
            f"kintinuous: {stop.message or f'interrupted by {stop.signal_name}'}", file=sys.stderr
        )
        return stop.exit_status
    except KeyboardInterrupt:
        print("kintinuous: interrupted", file=sys.stderr)
        return 130
    except MemoryError:
        print(
            "kintinuous: error: out of memory (ask for fewer or smaller frames, or a smaller "
            "volume)",
            file=sys.stderr,
        )
        return 2
    except OSError as err:
        where = f"{err.filename}: " if err.filename else ""
        print(f"kintinuous: error: {where}{err.strerror or err}", file=sys.stderr)
        return 2
    except Exception as err:
        log = _crash_log()
        print(
            f"kintinuous: internal error (a bug, please report it): {type(err).__name__}: "
            f"{err}; traceback in {log}",
            file=sys.stderr,
        )
        return 70
    return status if isinstance(status, int) else 0


def _crash_log() -> str:
    """The current exception's traceback in a new file in the temporary folder; its path."""
    import tempfile
    import traceback

    try:
        handle, path = tempfile.mkstemp(prefix="kintinuous-crash-", suffix=".log")
        with os.fdopen(handle, "w") as log:
            log.write(traceback.format_exc())
        return path
    except OSError:
        return "nowhere (the temporary folder cannot be written)"


if __name__ == "__main__":
    sys.exit(main())

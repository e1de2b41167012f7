"""The arguments of each `kintinuous` command: one function per command adds its parser and
returns it (cli.build_parser gives it the command's body, commands.py).

Nothing here imports NumPy or the algorithms, so that `kintinuous --help` stays instant: the
choice lists come from kintinuous_ref.vocabulary, which imports nothing.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from kintinuous_ref.vocabulary import (
    BACKEND_CHOICES,
    DEFAULT_METHOD,
    ODOMETRY_CHOICES,
    OTHER_SEQUENCES,
    PAPER_SEQUENCES,
)

DEFAULT_ODOMETRY = DEFAULT_METHOD  # the paper's tracker


# The help of --fast-odometry on reconstruct and benchmark. Its speed and accuracy are measured
# in docs/benchmarks.md, not quoted here, so that the help never outlives its numbers.
FAST_ODOMETRY_HELP = (
    "dense trackers skip the finest pyramid level (the original code's CPU option) and the "
    "model is raycast only for the quarter of the pixels they read: faster tracking and "
    "raycasting for some frame-to-frame accuracy (docs/benchmarks.md measures both)"
)


# kintinuous_ref.datasets.download's, spelled out so that --help needs no NumPy import
# (tests/test_download.py checks that they agree).
TUM_BASE_URL = "https://cvg.cit.tum.de/rgbd/dataset/"
MIRROR_VARIABLE = "KINTINUOUS_MIRROR"


def finite_float(text: str) -> float:
    """An option's number: finite (no inf or nan)."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, found {text!r}") from None
    if value != value or value in (float("inf"), float("-inf")):
        raise argparse.ArgumentTypeError(f"expected a finite number, found {text!r}")
    return value


def positive_int(text: str) -> int:
    """An option's count: a whole number of at least 1."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a whole number, found {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected at least 1, found {value}")
    return value


def add_run_options(parser: argparse.ArgumentParser) -> None:
    """The options every command that runs the pipeline shares: volume, backend, configuration."""
    parser.add_argument("--volume-size", type=finite_float, default=3.0, help="cube side, metres")
    parser.add_argument("--resolution", type=int, default=256, help="voxels per side")
    parser.add_argument(
        "--backend",
        choices=BACKEND_CHOICES,
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


def add_input_options(parser: argparse.ArgumentParser) -> None:
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


def add_synth(commands: argparse._SubParsersAction) -> argparse.ArgumentParser:
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
        type=finite_float,
        default=0.05,
        help="edge length of the ground-truth mesh scene.ply in metres (default 0.05)",
    )
    return parser


def add_evaluate(commands: argparse._SubParsersAction) -> argparse.ArgumentParser:
    parser = commands.add_parser(
        "evaluate", help="ATE, frame-to-frame error and drift of a trajectory against ground truth"
    )
    parser.add_argument("estimate", type=Path, help="estimated trajectory (TUM format)")
    parser.add_argument("groundtruth", type=Path, help="ground-truth trajectory (TUM format)")
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    return parser


def add_reconstruct(commands: argparse._SubParsersAction) -> argparse.ArgumentParser:
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
        "--no-plausibility-checks",
        action="store_true",
        help="run input that is valid but implausible (a principal point outside the image, a "
        "field of view outside 20..160 degrees, a depth scale that puts the first frame's "
        "median depth outside 0.5..10 m, a volume with voxels over 0.1 m or that misses the "
        "first frame's surface), which is otherwise refused (docs/reliability.md)",
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
    add_run_options(parser)
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
    add_input_options(parser)
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
    return parser


def add_convert(commands: argparse._SubParsersAction) -> argparse.ArgumentParser:
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
    add_input_options(parser)
    return parser


def add_download(commands: argparse._SubParsersAction) -> argparse.ArgumentParser:
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
    return parser


def add_table(commands: argparse._SubParsersAction) -> argparse.ArgumentParser:
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
    parser.add_argument(
        "--out",
        type=Path,
        default=Path("evaluation"),
        help="output folder (new, empty, or holding an earlier table with --overwrite)",
    )
    parser.add_argument(
        "--overwrite",
        action="store_true",
        help="replace the earlier table in --out, its runs included (removed before the runs)",
    )
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
    add_run_options(parser)
    parser.add_argument("--mesh", action="store_true", help="also write each run's mesh.ply")
    return parser


def add_benchmark(commands: argparse._SubParsersAction) -> argparse.ArgumentParser:
    parser = commands.add_parser(
        "benchmark", help="per-stage milliseconds and frames/s of the pipeline on one backend"
    )
    parser.add_argument(
        "dataset", nargs="?", help="TUM folder or synthetic scenario name (default: desk)"
    )
    parser.add_argument("--odometry", default=DEFAULT_ODOMETRY, choices=ODOMETRY_CHOICES)
    parser.add_argument("--frames", type=int, default=30, help="frames (the first is a warm-up)")
    parser.add_argument("--start", type=int, default=0, help="first frame")
    add_run_options(parser)
    parser.add_argument(
        "--fast-odometry",
        action="store_true",
        help=FAST_ODOMETRY_HELP,
    )
    parser.add_argument(
        "--sync-stages",
        action="store_true",
        help="wait for the GPU at the end of each stage, so that each stage's time includes its "
        "device work (without it a GPU's stage times are the host's; frames/s is right either way)",
    )
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    return parser


def add_warmup(commands: argparse._SubParsersAction) -> argparse.ArgumentParser:
    parser = commands.add_parser(
        "warmup",
        help="compile a backend's kernels now (numba does it once per installation) and say "
        "how long each took",
    )
    parser.add_argument("--backend", choices=BACKEND_CHOICES, default="auto", help="default auto")
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
    return parser


def add_course(commands: argparse._SubParsersAction) -> argparse.ArgumentParser:
    parser = commands.add_parser(
        "course",
        help="the lessons of notebooks/ as executed notebooks (.ipynb) and HTML pages with "
        "their figures",
    )
    parser.add_argument("out", type=Path, metavar="DIR", help="folder to write the lessons into")
    parser.add_argument(
        "--lessons",
        type=lambda text: [key.strip() for key in text.split(",") if key.strip()],
        help="comma-separated lesson numbers or names, e.g. 01,03 (default: all)",
    )
    parser.add_argument("--no-html", action="store_true", help="write the .ipynb files only")
    parser.add_argument(
        "--jobs",
        type=positive_int,
        metavar="N",
        help="lessons run at a time (default: one per core, at most 4); the speed appendix "
        "always runs by itself",
    )
    parser.add_argument(
        "--notebooks",
        type=Path,
        metavar="FOLDER",
        help="the lessons' folder (default: notebooks/ of the source checkout)",
    )
    return parser


def add_info(commands: argparse._SubParsersAction) -> argparse.ArgumentParser:
    parser = commands.add_parser("info", help="which compute backends work on this machine")
    return parser

"""The bodies of the `kintinuous` commands: each takes the parsed arguments (arguments.py) and
does the work, importing the modules it needs when it runs, so that `kintinuous --help` stays
instant. A body that did not do all that was asked returns 1 (a `table` with a failed run);
errors are raised as one-line KintinuousErrors, which cli.main prints.
"""

from __future__ import annotations

import argparse
import os
import sys
from typing import TYPE_CHECKING

from kintinuous_ref import __version__
from kintinuous_ref.errors import KintinuousError
from kintinuous_ref.program.arguments import MIRROR_VARIABLE
from kintinuous_ref.program.config_options import configured, volume_from_options
from kintinuous_ref.program.output_folder import claimed, locked
from kintinuous_ref.strict_json import dumps as strict_dumps

if TYPE_CHECKING:
    from kintinuous_ref.datasets.tum import FrameSequence


def run_synth(args: argparse.Namespace) -> None:
    from kintinuous_ref.datasets import synthetic

    if args.list:
        for name, summary in synthetic.list_scenarios().items():
            print(f"{name:10s} {summary}")
        return
    if not args.scenario or not args.out:
        raise KintinuousError("synth needs a SCENARIO and --out DIR (or --list)")
    if args.frames < 1:
        raise KintinuousError(f"--frames must be at least 1 (frames to render), got {args.frames}")
    counts: list[int] = []
    with locked(args.out) as out:
        synthetic.write_scenario(
            args.scenario,
            out,
            frames=args.frames,
            width=args.width,
            height=args.height,
            seed=args.seed,
            noise=not args.no_noise,
            progress=True,
            workers=max(1, args.workers),
            mesh_spacing=args.mesh_spacing,
            on_rendering=counts.append,
        )
    print(synth_summary(args.scenario, args.out, args.frames, counts[0]))


def synth_summary(scenario: str, out: str, frames: int, rendered: int) -> str:
    """What `synth` did: the frames it rendered, and those the folder already held."""

    def counted(count: int) -> str:
        return f"{count} frame{'' if count == 1 else 's'}"

    if rendered == frames:
        return f"wrote {counted(frames)} of '{scenario}' to {out}"
    if rendered == 0:
        return f"{out} already holds the {counted(frames)} of '{scenario}': none rendered"
    already = frames - rendered
    return f"wrote {counted(rendered)} of '{scenario}' to {out} ({already} already there)"


def run_evaluate(args: argparse.Namespace) -> None:
    from kintinuous_ref import metrics
    from kintinuous_ref.datasets import tum

    errors = metrics.evaluate(
        tum.read_trajectory(args.estimate), tum.read_trajectory(args.groundtruth)
    )
    if args.json:
        print(strict_dumps(errors.as_dict()))
    else:
        print(errors.summary())


def run_reconstruct(args: argparse.Namespace) -> None:
    from kintinuous_ref.backend import load_backend
    from kintinuous_ref.config import ColourConfig, Config, fast_odometry
    from kintinuous_ref.pipeline import check_settings
    from kintinuous_ref.program import reconstruct, results

    config = Config(
        volume=volume_from_options(
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
    config = configured(config, args.config, args.set)
    if args.fast_odometry:
        config = fast_odometry(config)
    # before generating or reading anything: the settings, the volume against the memory that
    # will hold it among them
    check_settings(config, args.odometry, load_backend(args.backend), args.loop_closure)
    # held from before the dataset is read: a second run into the folder is refused at once
    with locked(args.out) as out:
        results.check_output(out, args.overwrite)
        frames_needed = args.start + args.frames if args.frames else None
        sequence = open_from_options(args.dataset, args, frames_needed=frames_needed)
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
            plausibility_checks=not args.no_plausibility_checks,
            camera_source=f"--intrinsics {args.intrinsics}" if args.intrinsics else None,
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


def parse_size(text: str | None) -> tuple[int, int] | None:
    """--size WIDTHxHEIGHT as (width, height); None when not given."""
    if not text:
        return None
    width, _, height = text.lower().partition("x")
    if not (width.isdigit() and height.isdigit() and int(width) > 0 and int(height) > 0):
        raise KintinuousError(f"--size expects WIDTHxHEIGHT such as 320x240, got {text!r}")
    return int(width), int(height)


def open_from_options(
    dataset: str | None, args: argparse.Namespace, **options: object
) -> FrameSequence:
    """The sequence `dataset` read with the input options reconstruct and convert share
    (--intrinsics, --size, --groundtruth, --topics), with a progress bar; `options` go on to
    reconstruct.open_dataset."""
    from kintinuous_ref.program import reconstruct

    return reconstruct.open_dataset(
        dataset,
        args.intrinsics,
        progress=True,
        size=parse_size(args.size),
        groundtruth=args.groundtruth,
        topics=args.topics,
        **options,
    )


def run_convert(args: argparse.Namespace) -> None:
    with claimed(args.out):  # a second convert into the same output is refused while it lives
        _convert(args)


def _convert(args: argparse.Namespace) -> None:
    from kintinuous_ref.datasets import klg, tum

    sequence = open_from_options(args.source, args, need_camera=False)
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


def run_download(args: argparse.Namespace) -> None:
    from kintinuous_ref.datasets.download import check_mirror, download
    from kintinuous_ref.program import reconstruct

    if args.sha256 and len(args.targets) > 1:
        raise KintinuousError("--sha256 checks one archive: give one NAME or URL with it")
    root = args.dest or reconstruct.cache_folder() / "tum"
    mirror = args.mirror or os.environ.get(MIRROR_VARIABLE) or None
    if mirror:
        check_mirror(mirror, "--mirror" if args.mirror else f"${MIRROR_VARIABLE}")
    for target in args.targets:
        folder, digest = download(target, root, args.sha256, mirror)
        if digest:
            print(f"{target}: unpacked into {folder} (archive sha256 {digest})")
        else:
            print(f"{target}: already in {folder}")


def run_table(args: argparse.Namespace) -> int:
    from kintinuous_ref.config import Config
    from kintinuous_ref.program.evaluation import evaluate_methods, method_title

    size = parse_size(args.size)
    if args.scheduler:
        from kintinuous_ref.program.evaluation.runs import dask_client

        dask_client(args.scheduler).close()  # fail early: dask missing or scheduler unreachable
    config = Config(volume=volume_from_options(resolution=args.resolution, size=args.volume_size))
    config = configured(config, args.config, args.set)

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
    header += [f"Command: `{table_command(args)}`", ""]
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
        overwrite=args.overwrite,
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


def table_command(args: argparse.Namespace) -> str:
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
    words += ["--overwrite"] if args.overwrite else []
    words += ["--config", str(args.config)] if args.config else []
    for setting in args.set:
        words += ["--set", setting]
    return shlex.join(words)


def run_benchmark(args: argparse.Namespace) -> None:
    from kintinuous_ref.config import Config, fast_odometry
    from kintinuous_ref.program.benchmark import benchmark, format_table

    config = Config(volume=volume_from_options(resolution=args.resolution, size=args.volume_size))
    config = configured(config, args.config, args.set)
    if args.fast_odometry:
        config = fast_odometry(config)
    report = benchmark(
        args.dataset,
        args.backend,
        args.odometry,
        args.frames,
        config,
        start=args.start,
        synchronize_stages=args.sync_stages,
    )
    print(strict_dumps(report) if args.json else format_table(report))


def run_warmup(args: argparse.Namespace) -> None:
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


def run_course(args: argparse.Namespace) -> int:
    from kintinuous_ref.program import course

    return course.run(args.out, args.lessons, args.notebooks, html=not args.no_html, jobs=args.jobs)


def run_info(args: argparse.Namespace) -> None:
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
    from kintinuous_ref.mesh import rendering_status

    reason = rendering_status()
    rendering = "VTK off-screen" if not reason else f"matplotlib plan views only: {reason}"
    print(f"previews: {rendering}")

"""The paper's results section (VII) as one call: every odometry method on every sequence.

    evaluation = evaluate_methods(["desk", "/data/rgbd_dataset_freiburg1_room"], out=Path("eval"))

runs each method of kintinuous_ref.vocabulary.METHODS through the full pipeline on each sequence
(runs.run_one, in parallel processes or on a Dask cluster), measures its trajectory against the
ground truth (metrics.evaluate) and writes to `out`:

- table.md: Tables I-VI laid out like the paper's (tables.py), best in bold, second in italics;
- table.json: every number, keyed by method and dataset;
- fig4_ranking_median.png, fig5_ranking_max.png: the ranking scores (eq. 16) as bar charts;
- trajectories.png: every trajectory against the ground truth, seen from above (figures.py);
- runs/DATASET/METHOD/: each run's trajectory.txt and report.json ('/' in a method's name
  becomes '_': runs/desk/fovis_icp+rgbd).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from kintinuous_ref.backend import load_backend
from kintinuous_ref.config import Config
from kintinuous_ref.datasets.tum import Trajectory
from kintinuous_ref.errors import ConfigError, DatasetError, KintinuousError
from kintinuous_ref.program.evaluation.runs import (
    FAILED,
    OK,
    RunOutcome,
    RunSpec,
    check_jobs,
    execute,
    run_folder_name,
    run_one,
    timing_statistics,
    write_failure,
)
from kintinuous_ref.program.evaluation.tables import (
    build_table,
    marks,
    method_title,
    render_markdown,
)
from kintinuous_ref.program.output_folder import (
    LOCK_NAME,
    atomic,
    is_temporary,
    locked,
    refuse_earlier,
    remove,
    write_text_atomic,
)
from kintinuous_ref.strict_json import dumps as strict_dumps
from kintinuous_ref.vocabulary import METHODS

__all__ = [
    "FAILED",
    "OK",
    "Dataset",
    "Evaluation",
    "RunOutcome",
    "RunSpec",
    "build_table",
    "evaluate_methods",
    "execute",
    "marks",
    "method_title",
    "open_datasets",
    "prepare_table_folder",
    "render_markdown",
    "run_one",
    "timing_statistics",
]


@dataclass
class Dataset:
    """A sequence of the evaluation as the parent process sees it."""

    label: str  # its name in the tables
    given: str  # what the user typed
    path: str | None = None  # TUM folder; None when it could not be opened
    reason: str = ""  # why it could not be opened
    frames: int = 0  # frames in the sequence
    groundtruth: Trajectory | None = None  # of the frames evaluated, for the trajectory figure

    def facts(self) -> dict[str, Any]:
        return {"given": self.given, "path": self.path, "frames": self.frames, "error": self.reason}


@dataclass
class Evaluation:
    table: dict[str, Any]  # what table.json holds
    markdown: str  # what table.md holds
    outcomes: list[RunOutcome]
    files: list[Path] = field(default_factory=list)

    @property
    def failed(self) -> list[RunOutcome]:
        return [o for o in self.outcomes if o.status != OK]


def open_datasets(
    names: list[str], start: int = 0, frames: int | None = None, progress: bool = False
) -> list[Dataset]:
    """Open each TUM folder or synthetic scenario (rendered into the cache here, once, so that
    parallel runs never race to write it). One that cannot be opened is kept with its reason: its
    runs are reported as failed."""
    from kintinuous_ref.program.reconstruct import open_dataset

    datasets: list[Dataset] = []
    for name in names:
        label = Path(name).name or name
        try:
            sequence = open_dataset(name, progress=progress)
        except KintinuousError as err:
            datasets.append(Dataset(_unique(label, datasets), name, reason=str(err)))
            continue
        if not Path(name).is_dir():  # a scenario: named as given, not after the cache folder
            label = name
        dataset = Dataset(_unique(label, datasets), name, str(sequence.path), frames=len(sequence))
        try:
            stop = None if frames is None else start + frames
            truth = sequence.groundtruth_for_frames()
            dataset.groundtruth = Trajectory(truth.timestamps[start:stop], truth.poses[start:stop])
        except KintinuousError:
            pass  # no usable ground truth: every run of it reports that itself
        datasets.append(dataset)
    return datasets


def check_some_dataset_exists(names: list[str]) -> None:
    """Refuse (DatasetError, one line) a table none of whose datasets exists: every run would
    fail, and the table would hold nothing but failures. A table that names some datasets that
    exist goes ahead, its missing ones reported as failed runs. Nothing is rendered here: an
    existing path or a scenario's name is enough."""
    from kintinuous_ref.datasets import synthetic
    from kintinuous_ref.program.reconstruct import open_dataset

    reasons = []
    for name in names:
        if Path(name).exists() or name in synthetic.list_scenarios():
            return
        try:
            open_dataset(name, need_camera=False)  # a downloaded sequence opens; others fail
        except KintinuousError as err:
            reasons.append(str(err))
            continue
        return
    if len(reasons) == 1:
        raise DatasetError(reasons[0])
    raise DatasetError(f"none of the {len(reasons)} datasets exists: {'; '.join(reasons)}")


def _unique(label: str, datasets: list[Dataset]) -> str:
    taken = {d.label for d in datasets}
    candidate, n = label, 2
    while candidate in taken:
        candidate, n = f"{label}-{n}", n + 1
    return candidate


def evaluate_methods(
    datasets: list[str],
    out: Path,
    methods: list[str] | None = None,
    config: Config | None = None,
    start: int = 0,
    frames: int | None = None,
    size: tuple[int, int] | None = None,
    backend: str = "ref",
    jobs: int = 1,
    scheduler: str | None = None,
    mesh: bool = False,
    on_done: Callable[[RunOutcome, int, int], None] | None = None,
    header: list[str] | None = None,
    overwrite: bool = False,
) -> Evaluation:
    """Run every method on every dataset and write table.md, table.json, the figures and the run
    folders into `out` (see the module docstring). Failed runs are reported, never raised. `out`
    is held for the whole evaluation (a second command into it is refused) and must be new or
    empty unless `overwrite`, which removes the earlier table and its runs first."""
    methods = list(methods or METHODS)
    unknown = [m for m in methods if m not in METHODS]
    if unknown:
        raise ConfigError(f"unknown method(s) {unknown}; choose from {', '.join(METHODS)}")
    if len(set(methods)) != len(methods):
        raise ConfigError(f"a method is named twice in {methods}")
    if not datasets:
        raise ConfigError("name at least one dataset")
    check_jobs(jobs)
    if start < 0 or (frames is not None and frames < 2):
        raise ConfigError(f"--start must be >= 0 and --frames >= 2, got {start} and {frames}")
    load_backend(backend)  # a clear error before any run
    config = config or Config()
    config.validate()
    check_some_dataset_exists(datasets)
    with locked(out) as folder:
        prepare_table_folder(folder, overwrite)
        return _evaluate_into(
            folder,
            datasets,
            methods,
            config,
            start,
            frames,
            size,
            backend,
            jobs,
            scheduler,
            mesh,
            on_done,
            header,
        )


def _evaluate_into(
    out: Path,
    datasets: list[str],
    methods: list[str],
    config: Config,
    start: int,
    frames: int | None,
    size: tuple[int, int] | None,
    backend: str,
    jobs: int,
    scheduler: str | None,
    mesh: bool,
    on_done: Callable[[RunOutcome, int, int], None] | None,
    header: list[str] | None,
) -> Evaluation:
    """evaluate_methods' work, its arguments checked and `out` held and prepared."""
    opened = open_datasets(datasets, start, frames)
    specs, failed = [], []
    for dataset in opened:
        for method in methods:
            folder = out / "runs" / dataset.label / run_folder_name(method)
            spec = RunSpec(
                dataset.label,
                dataset.path or dataset.given,
                method,
                str(folder),
                config,
                start,
                frames,
                size,
                backend,
                mesh,
            )
            if dataset.path is None:  # could not be opened: failed without running
                outcome = RunOutcome(dataset.label, method, FAILED, dataset.reason, out=str(folder))
                write_failure(spec, outcome)
                failed.append(outcome)
            else:
                specs.append(spec)
    for count, outcome in enumerate(failed, start=1):
        if on_done is not None:
            on_done(outcome, count, len(failed) + len(specs))

    def report(outcome: RunOutcome, finished: int, total: int) -> None:
        if on_done is not None:
            on_done(outcome, len(failed) + finished, len(failed) + total)

    outcomes = failed + execute(specs, jobs, scheduler, report)

    table = build_table(outcomes, methods, {d.label: d.facts() for d in opened})
    table["settings"] = {
        "start": start,
        "frames": frames,
        "size": list(size) if size else None,
        "backend": backend,
        "volume": {"resolution": config.volume.resolution, "size_m": config.volume.size},
    }
    markdown = render_markdown(table, header)
    groundtruths = {d.label: d.groundtruth for d in opened}
    files = _write_table(out, table, markdown, outcomes, groundtruths, methods)
    return Evaluation(table, markdown, outcomes, files)


def _write_table(
    out: Path,
    table: dict[str, Any],
    markdown: str,
    outcomes: list[RunOutcome],
    groundtruths: dict[str, Trajectory | None],
    methods: list[str],
) -> list[Path]:
    """table.md, table.json and the figures in `out`, each written whole (under a temporary
    name, then renamed) so that a reader never finds half a table; their paths."""
    from kintinuous_ref.program.evaluation.figures import ranking_figure, trajectory_figure

    write_text_atomic(out / "table.md", markdown)
    write_text_atomic(out / "table.json", strict_dumps(table, indent=1) + "\n")
    figures = {
        "fig4_ranking_median.png": lambda path: ranking_figure(table, "Median", path),
        "fig5_ranking_max.png": lambda path: ranking_figure(table, "Max", path),
        "trajectories.png": lambda path: trajectory_figure(outcomes, groundtruths, methods, path),
    }
    for name, draw in figures.items():
        with atomic(out / name) as temporary:
            draw(temporary)
    return [out / "table.md", out / "table.json", *(out / name for name in figures)]


# What a table writes into its folder (the module docstring): an earlier table is these.
TABLE_NAMES = (
    "table.md",
    "table.json",
    "fig4_ranking_median.png",
    "fig5_ranking_max.png",
    "trajectories.png",
    "runs",
)


def prepare_table_folder(out: Path, overwrite: bool = False) -> None:
    """Refuse (ConfigError) a folder holding an earlier table or other files unless `overwrite`,
    which removes the earlier table, its runs included: no old run mixes with the new ones.
    Called under `locked(out)`, so that no live table owns what it removes."""
    found = [
        entry.name
        for entry in sorted(out.iterdir())
        if entry.name != LOCK_NAME and not is_temporary(entry.name)
    ]
    if found and not overwrite:
        earlier = [name for name in TABLE_NAMES if name in found]
        if earlier:
            raise refuse_earlier(out, earlier)
        raise ConfigError(
            f"{out}: is not empty ({', '.join(found[:5])}); pass --overwrite to write the table "
            "among its files, or choose another --out"
        )
    try:
        remove(out, TABLE_NAMES)
    except OSError as err:
        raise ConfigError(
            f"{out}: cannot clear the earlier table ({err.strerror or err})"
        ) from None

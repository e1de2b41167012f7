"""Keeping numba's on-disk cache true to the sources, and knowing when it is warm.

numba keys each cached kernel to the modification time and size of the file that defines it,
not to the files of the functions it calls or inlines. The cpu loops (`<stage>/cpu.py`) compile
in the shared maths of `<stage>/ops.py` and `tsdf/voxel.py`, so after an edit to one of those the
unchanged loops would still load machine code built from the old maths, and a test or benchmark
would run code that is not in the files. A stamp of every source file of this package (path,
size, modification time) is kept in each cache folder; where it differs, the package's cached
kernels are dropped there and compile again on first use.

Each stage registers the cpu kernel that takes it longest to compile (`register_slowest`); that
kernel's cache folder, as numba reports it (`Dispatcher.stats.cache_path`: beside the sources,
under NUMBA_CACHE_DIR, or in the user's cache), is the stage's. A completed warm-up leaves a
record of the sources and numba it compiled in each folder of the stages it ran
(`record_warm_up`), which is how a later process knows those kernels are cached
(`warmed_up`).
"""

from __future__ import annotations

import contextlib
import hashlib
import importlib
import json
import math
import os
import sys
import tempfile
from collections.abc import Callable
from pathlib import Path
from types import SimpleNamespace
from typing import Any, TypeVar

PACKAGE = Path(__file__).resolve().parents[1]
STAMP_NAME = "kintinuous_fast_sources.stamp"
WARM_NAME = "kintinuous_fast_warm.stamp"
# The stage packages, by the name of their folder; each one's cpu module registers its slowest
# kernel when imported.
STAGES = ("preprocess", "tsdf", "raycast", "colour", "odometry")
MAPPING_STAGES = ("preprocess", "tsdf", "colour")  # what a run with known poses calls

Kernel = TypeVar("Kernel")
_SLOWEST: dict[str, Any] = {}


def register_slowest(stage: str) -> Callable[[Kernel], Kernel]:
    """A decorator for `stage`'s cpu kernel that takes longest to compile (applied above the
    numba decorator, it returns the kernel as it is): the kernel stands for the stage's cache."""
    if stage not in STAGES:
        raise ValueError(f"unknown stage {stage!r}; the stages are {', '.join(STAGES)}")

    def register(kernel: Kernel) -> Kernel:
        _SLOWEST[stage] = kernel
        return kernel

    return register


def slowest_kernels() -> dict[str, Any]:
    """Per stage, its registered kernel (every stage's cpu module imported first)."""
    for stage in STAGES:
        importlib.import_module(f"kintinuous_fast.{stage}.cpu")
        if stage not in _SLOWEST:
            raise LookupError(f"kintinuous_fast.{stage}.cpu registers no kernel (register_slowest)")
    return {stage: _SLOWEST[stage] for stage in STAGES}


def _cache_path(kernel: Any) -> str | None:
    """Where numba keeps `kernel`'s cache: None for anything but a kernel of this package
    compiled with cache=True."""
    function = getattr(kernel, "py_func", None)
    if not getattr(function, "__module__", "").startswith("kintinuous_fast."):
        return None
    try:
        return kernel.stats.cache_path
    except AttributeError:
        return None


def sources_stamp(root: Path = PACKAGE) -> str:
    """A digest of the path, size and modification time of every .py file below `root`."""
    digest = hashlib.sha256()
    for path in sorted(root.rglob("*.py")):
        info = path.stat()
        line = f"{path.relative_to(root).as_posix()} {info.st_size} {info.st_mtime_ns}\n"
        digest.update(line.encode())
    return digest.hexdigest()


def stage_folders(stages: tuple[str, ...] = STAGES) -> dict[str, Path]:
    """The folder numba keeps each stage's cpu kernels in."""
    kernels = slowest_kernels()
    return {stage: Path(kernels[stage].stats.cache_path) for stage in stages}


def cache_folders() -> list[Path]:
    """The folders numba keeps this package's cpu kernels in: each stage's, and those of any
    other cached kernel its loaded modules hold (a stage's subpackages, the targets' helpers),
    at module level or in a namespace of ops."""
    folders = set(stage_folders().values())
    for name, module in list(sys.modules.items()):
        if not name.startswith("kintinuous_fast.") or module is None:
            continue
        for value in list(vars(module).values()):
            held = vars(value).values() if isinstance(value, SimpleNamespace) else (value,)
            folders.update(Path(path) for path in map(_cache_path, held) if path)
    return sorted(folders)


def _warm_record(stamp: str) -> str:
    """What a warm-up records: the sources and the numba and Python that compiled them."""
    import numba

    python = ".".join(str(part) for part in sys.version_info[:2])
    return f"{stamp}\nnumba {numba.__version__}\npython {python}\n"


def record_warm_up(stages: tuple[str, ...]) -> None:
    """Note in each of `stages`' cache folders that a warm-up compiled their kernels from these
    sources (a folder that cannot be written is left as it is: the next run warms up again)."""
    record = _warm_record(sources_stamp())
    for folder in set(stage_folders(stages).values()):
        try:
            (folder / WARM_NAME).write_text(record)
        except OSError:
            continue


def warmed_up(stages: tuple[str, ...]) -> bool:
    """Whether a warm-up from these sources, with this numba, recorded each of `stages`."""
    record = _warm_record(sources_stamp())
    for folder in set(stage_folders(stages).values()):
        try:
            if (folder / WARM_NAME).read_text() != record:
                return False
        except OSError:
            return False
    return True


def drop_stale_kernels(folders: list[Path] | None = None, stamp: str | None = None) -> int:
    """Delete the cached kernels (.nbi, .nbc) and the warm-up record in each of `folders`
    (default: cache_folders()) whose stamp is not `stamp` (default: sources_stamp()), then stamp
    it; how many kernel files went. A folder that cannot be written is left as it is: numba then
    compiles afresh anyway."""
    folders = cache_folders() if folders is None else folders
    stamp = sources_stamp() if stamp is None else stamp
    dropped = 0
    for folder in folders:
        record = folder / STAMP_NAME
        try:
            if record.exists() and record.read_text() == stamp:
                continue
            folder.mkdir(parents=True, exist_ok=True)
            for path in [*folder.glob("*.nbi"), *folder.glob("*.nbc")]:
                path.unlink(missing_ok=True)
                dropped += 1
            (folder / WARM_NAME).unlink(missing_ok=True)
            record.write_text(stamp)
        except OSError:
            continue
    return dropped


# How long compiling took on this machine, per part of the kernels (kintinuous_ref.program.warmup
# names the parts), kept as a small JSON object {"<part>": seconds} in the folder of the stage
# every run calls. numba's cache files are dropped when the sources change, this file is not: it
# says how long the next compile will take after an update, a wiped cache or a new installation
# into the same cache folder.
ESTIMATE_NAME = "kintinuous_compile_seconds.json"
ESTIMATE_STAGE = "preprocess"


def estimate_file(folder: Path | None = None) -> Path:
    """The compile-time record: in `folder`, by default the cache folder of ESTIMATE_STAGE."""
    if folder is None:
        folder = stage_folders((ESTIMATE_STAGE,))[ESTIMATE_STAGE]
    return folder / ESTIMATE_NAME


def measured_compile_seconds(part: str, folder: Path | None = None) -> float | None:
    """The seconds the last measured compile of `part` took here; None where none was measured
    or the record cannot be read (missing, corrupt, another layout): then nothing is known."""
    try:
        record = json.loads(estimate_file(folder).read_text())
        seconds = float(record[part])
    except (OSError, ValueError, TypeError, KeyError, LookupError):
        return None
    return seconds if math.isfinite(seconds) and seconds > 0 else None


def record_compile_seconds(part: str, seconds: float, folder: Path | None = None) -> None:
    """Keep `seconds` as the compile time of `part`, beside the other parts' times. The record
    is replaced whole, so that a reader never sees half of it; a folder that cannot be written
    is left as it is (the next compile is then announced by the known range)."""
    path = estimate_file(folder)
    record: dict[str, float] = {}
    with contextlib.suppress(OSError, ValueError):
        loaded = json.loads(path.read_text())
        if isinstance(loaded, dict):
            record = {key: value for key, value in loaded.items() if _is_seconds(value)}
    record[part] = round(float(seconds), 1)
    with contextlib.suppress(OSError):
        path.parent.mkdir(parents=True, exist_ok=True)
        _replace_atomically(path, json.dumps(record, sort_keys=True) + "\n")


def _is_seconds(value: object) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def _replace_atomically(path: Path, text: str) -> None:
    """Write `text` to a temporary file beside `path` (mode 0644, as the cache's other files),
    then rename it over `path`: one step on a POSIX file system."""
    descriptor, temporary = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.")
    try:
        with os.fdopen(descriptor, "w") as stream:
            stream.write(text)
        os.chmod(temporary, 0o644)
        os.replace(temporary, path)
    except BaseException:
        Path(temporary).unlink(missing_ok=True)
        raise

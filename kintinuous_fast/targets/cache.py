"""Keeping numba's on-disk cache true to the sources.

numba keys each cached kernel to the modification time and size of the file that defines it,
not to the files of the functions it calls or inlines. The cpu loops (`<stage>/cpu.py`) compile
in the shared maths of `<stage>/ops.py` and `tsdf/voxel.py`, so after an edit to one of those the
unchanged loops would still load machine code built from the old maths, and a test or benchmark
would run code that is no longer in the files. A stamp of every source file of this package (path,
size, modification time) is kept in each cache folder; where it differs, the package's cached
kernels are dropped there and compile again on first use.
"""

from __future__ import annotations

import hashlib
from pathlib import Path
from typing import Any

PACKAGE = Path(__file__).resolve().parents[1]
STAMP_NAME = "kintinuous_fast_sources.stamp"


def sources_stamp(root: Path = PACKAGE) -> str:
    """A digest of the path, size and modification time of every .py file below `root`."""
    digest = hashlib.sha256()
    for path in sorted(root.rglob("*.py")):
        info = path.stat()
        line = f"{path.relative_to(root).as_posix()} {info.st_size} {info.st_mtime_ns}\n"
        digest.update(line.encode())
    return digest.hexdigest()


def slowest_kernels() -> dict[str, Any]:
    """Per stage package, the cpu kernel that takes longest to compile: where one is cached, a
    warm-up compiled that stage, and its cache folder is the stage's."""
    from kintinuous_fast.colour.cpu import _weights_loop
    from kintinuous_fast.odometry.cpu import _icp_loop
    from kintinuous_fast.preprocess.cpu import _bilateral_rows
    from kintinuous_fast.raycast.cpu import _raycast_loop
    from kintinuous_fast.tsdf.cpu import _integrate_loop

    return {
        "preprocess": _bilateral_rows,
        "tsdf": _integrate_loop,
        "colour": _weights_loop,
        "odometry": _icp_loop,
        "raycast": _raycast_loop,
    }


def cache_folders() -> list[Path]:
    """The folders numba keeps this package's cpu kernels in: one per stage package (beside the
    sources, or under NUMBA_CACHE_DIR or the user's cache where numba puts them instead)."""
    return sorted({Path(kernel._cache._cache_path) for kernel in slowest_kernels().values()})


def drop_stale_kernels(folders: list[Path] | None = None, stamp: str | None = None) -> int:
    """Delete the cached kernels (.nbi, .nbc) in each of `folders` (default: cache_folders())
    whose stamp is not `stamp` (default: sources_stamp()), then stamp it; how many files went.
    A folder that cannot be written is left as it is: numba then compiles afresh anyway."""
    try:
        folders = cache_folders() if folders is None else folders
    except AttributeError:  # another numba's cache layout: nothing known to drop
        return 0
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
            record.write_text(stamp)
        except OSError:
            continue
    return dropped

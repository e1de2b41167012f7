"""Reading and writing RGB-D sequences: TUM folders (tum) and generated scenes (synthetic).

Real datasets (7-Scenes' redkitchen, ...) are not part of the repository. `real_dataset(name)`
finds one in the folder named by the environment variable KINTINUOUS_DATA, else in
`../shared/data` beside the repository, and returns None when it is absent, so that notebooks,
tests and benchmarks can skip their real-data parts cleanly.
"""

from __future__ import annotations

import os
from pathlib import Path

DATA_VARIABLE = "KINTINUOUS_DATA"
# The repository's parent holds shared/data on the development machines.
DEFAULT_DATA_FOLDER = Path(__file__).resolve().parents[2].parent / "shared" / "data"


def data_folder() -> Path:
    """The folder holding real datasets: $KINTINUOUS_DATA, else ../shared/data beside the
    repository (it may not exist)."""
    value = os.environ.get(DATA_VARIABLE, "")
    return Path(value).expanduser() if value else DEFAULT_DATA_FOLDER


def real_dataset(name: str) -> Path | None:
    """The folder of the real dataset `name` (e.g. "redkitchen") in data_folder(), or None when
    it is not there."""
    folder = data_folder() / name
    return folder if folder.is_dir() else None

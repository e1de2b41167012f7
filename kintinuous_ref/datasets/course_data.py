"""The real frames the course's lessons end on, found in one place.

Every lesson of notebooks/ ends on real RGB-D frames with ground truth. `load_course_data()`
picks them, in this order:

1. the TUM RGB-D folder named by $KINTINUOUS_COURSE_DATA (the user's explicit choice, so it
   wins; a variable naming no usable folder is an error, not a silent fallback);
2. the shared 7-Scenes redkitchen frames (`real_dataset("redkitchen")`);
3. a TUM sequence fetched by `kintinuous download` into $KINTINUOUS_CACHE/tum (default
   ~/.cache/kintinuous/tum), the known names in download.SEQUENCES' order;
4. none: it returns None and the lessons print `skip_line()` instead of their real-data cells.

The lessons index frames 0..299 (frame pairs five apart, every tenth frame of ten seconds), so a
sequence lends the course its first run of COURSE_FRAMES consecutive frames that each have a
ground-truth pose within 0.02 s; course frame i is the i-th of them, and its pose is
`groundtruth.poses[i]` (the index `pipeline.run` looks poses up by). The lessons assert exact
numbers only on redkitchen (`is_redkitchen`); on any other sequence they check what holds for
every sequence (shapes, finite errors, a loose bound).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from kintinuous_ref.camera import Intrinsics
from kintinuous_ref.datasets import data_folder, download, real_dataset
from kintinuous_ref.datasets.tum import (
    Frame,
    FrameSequence,
    Trajectory,
    nearest_indices,
    open_sequence,
)
from kintinuous_ref.errors import DatasetError

COURSE_VARIABLE = "KINTINUOUS_COURSE_DATA"
CACHE_VARIABLE = "KINTINUOUS_CACHE"  # where `kintinuous download` unpacks, under tum/
REDKITCHEN = "redkitchen"
COURSE_FRAMES = 300  # ten seconds at 30 Hz: the most any lesson reads


@dataclass(frozen=True)
class CourseData:
    """A sequence's first `len(self)` consecutive frames that have ground truth.

    `name`: "redkitchen", a known TUM name ("fr1/desk") or the folder's name; `source`: where it
    was found, for the line a lesson prints; `first`: the sequence index of course frame 0."""

    name: str
    source: str
    sequence: FrameSequence
    first: int
    groundtruth: Trajectory

    def __len__(self) -> int:
        return len(self.groundtruth)

    @property
    def camera(self) -> Intrinsics:
        """The camera at the images' own size."""
        return self.sequence.camera

    @property
    def is_redkitchen(self) -> bool:
        """Whether the lessons' exact expected numbers (measured on redkitchen) apply."""
        return self.name == REDKITCHEN

    def camera_at(self, width: int, height: int) -> Intrinsics:
        """The camera for the frames downsized to width x height."""
        return self.camera.resized(width, height)

    def frame(self, index: int, width: int | None = None, height: int | None = None) -> Frame:
        """Course frame `index`, downsized to width x height when given: colour by area
        averaging, depth by nearest neighbour (averaging would invent depths between surfaces)."""
        if not 0 <= index < len(self):
            raise IndexError(f"{self.name}: course frame {index} out of range (0..{len(self) - 1})")
        image = self.sequence[self.first + index]
        colour, depth = image.colour, image.depth
        if width is not None and height is not None:
            colour = cv2.resize(colour, (width, height), interpolation=cv2.INTER_AREA)
            depth = cv2.resize(depth, (width, height), interpolation=cv2.INTER_NEAREST)
        return Frame(index=index, timestamp=image.timestamp, colour=colour, depth=depth)

    def __getitem__(self, index: int) -> Frame:
        """Course frame `index` at full size (so that CourseData serves where a sequence does)."""
        return self.frame(index)

    def frames(
        self, indices: range | list[int], width: int | None = None, height: int | None = None
    ) -> list[Frame]:
        """Course frames `indices`, downsized as `frame` does."""
        return [self.frame(index, width, height) for index in indices]

    def describe(self) -> str:
        """One line: which frames the lessons run on, and where they come from."""
        return (
            f"real data: {self.name} ({self.source}), frames {self.first}-"
            f"{self.first + len(self) - 1} of {len(self.sequence)}"
        )


def downloads_folder() -> Path:
    """Where `kintinuous download` unpacks TUM sequences: $KINTINUOUS_CACHE/tum, else
    ~/.cache/kintinuous/tum (the same rule as the command's cache folder)."""
    root = os.environ.get(CACHE_VARIABLE, "")
    return (Path(root) if root else Path.home() / ".cache" / "kintinuous") / "tum"


def first_tracked_run(sequence: FrameSequence, frames: int) -> tuple[int, Trajectory] | None:
    """(start, ground truth) of the first `frames` consecutive frames of `sequence` that each
    have a ground-truth pose within 0.02 s, or None when the sequence has no such run."""
    if sequence.groundtruth is None or len(sequence) < frames:
        return None
    nearest = nearest_indices(sequence.timestamps, sequence.groundtruth.timestamps)
    has_pose = np.concatenate([[0], (nearest >= 0).astype(np.int64)])
    # counts[k]: how many of the first k frames have a pose, so frames s..s+frames-1 all have
    # one where counts[s + frames] - counts[s] == frames.
    counts = np.cumsum(has_pose)
    full = np.flatnonzero(counts[frames:] - counts[:-frames] == frames)
    if len(full) == 0:
        return None
    start = int(full[0])
    chosen = slice(start, start + frames)
    return start, Trajectory(
        sequence.timestamps[chosen].copy(), sequence.groundtruth.poses[nearest[chosen]]
    )


def course_data_from(
    folder: Path, name: str, source: str, frames: int = COURSE_FRAMES
) -> CourseData:
    """The course's frames from the TUM folder `folder`; a DatasetError says in one line why a
    folder cannot serve (no ground truth, too short)."""
    sequence = open_sequence(folder)
    if sequence.groundtruth is None:
        raise DatasetError(
            f"{folder}: no groundtruth.txt; the course compares every estimate with the ground "
            "truth, so it needs a sequence that has one"
        )
    run = first_tracked_run(sequence, frames)
    if run is None:
        raise DatasetError(
            f"{folder}: no {frames} consecutive frames with a ground-truth pose within 0.02 s "
            f"({len(sequence)} frames in all); the lessons read {frames}"
        )
    start, groundtruth = run
    return CourseData(name, source, sequence, start, groundtruth)


def _chosen_by_variable(frames: int) -> CourseData | None:
    value = os.environ.get(COURSE_VARIABLE, "")
    if not value:
        return None
    folder = Path(value).expanduser()
    if not folder.is_dir():
        raise DatasetError(
            f"${COURSE_VARIABLE}={value}: not a folder; point it at a TUM RGB-D sequence "
            "(rgb.txt, depth.txt, groundtruth.txt), or unset it"
        )
    return course_data_from(folder, folder.resolve().name, f"${COURSE_VARIABLE}", frames)


def _downloaded(frames: int) -> CourseData | None:
    root = downloads_folder()
    for name in download.SEQUENCES:
        folder = download.cached(name, root)
        if folder is not None:
            return course_data_from(folder, name, f"downloaded into {root}", frames)
    return None


def load_course_data(frames: int = COURSE_FRAMES) -> CourseData | None:
    """The real frames the lessons end on (the module's order), or None when there are none."""
    chosen = _chosen_by_variable(frames)
    if chosen is not None:
        return chosen
    kitchen = real_dataset(REDKITCHEN)
    if kitchen is not None:
        return course_data_from(
            kitchen, REDKITCHEN, f"the shared frames in {kitchen.parent}", frames
        )
    return _downloaded(frames)


def skip_line() -> str:
    """The one line a lesson prints in place of its real-data cells when there are none."""
    return (
        f"no real data (no redkitchen in {data_folder()}, no TUM sequence in "
        f"${COURSE_VARIABLE} or {downloads_folder()}): skipping the real-data example; "
        "`kintinuous download fr1/desk` fetches one"
    )

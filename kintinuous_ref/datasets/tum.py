"""TUM RGB-D folders and trajectories.

A trajectory file has one pose per line, `timestamp tx ty tz qx qy qz qw`, camera-to-world;
lines starting with '#' are comments (Sturm et al., IROS 2012).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from kintinuous_ref import se3
from kintinuous_ref.errors import DatasetError


@dataclass
class Trajectory:
    """Timestamped camera-to-world poses: timestamps (N,) seconds, poses (N, 4, 4)."""

    timestamps: np.ndarray
    poses: np.ndarray

    def __post_init__(self) -> None:
        self.timestamps = np.asarray(self.timestamps, dtype=np.float64).reshape(-1)
        self.poses = np.asarray(self.poses, dtype=np.float64).reshape(-1, 4, 4)
        if len(self.timestamps) != len(self.poses):
            raise DatasetError(
                f"trajectory has {len(self.timestamps)} timestamps but {len(self.poses)} poses"
            )

    def __len__(self) -> int:
        return len(self.timestamps)

    @property
    def positions(self) -> np.ndarray:
        return self.poses[:, :3, 3]


def write_trajectory(path: Path, trajectory: Trajectory) -> None:
    """Write a trajectory in TUM format (timestamps to 1e-6 s, poses to 1e-9)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    lines = ["# timestamp tx ty tz qx qy qz qw"]
    for timestamp, pose in zip(trajectory.timestamps, trajectory.poses, strict=True):
        values = " ".join(f"{v:.9f}" for v in se3.to_tum(pose))
        lines.append(f"{timestamp:.6f} {values}")
    path.write_text("\n".join(lines) + "\n")


def read_trajectory(path: Path) -> Trajectory:
    """Read a TUM trajectory; a malformed line is reported with its file and line number."""
    path = Path(path)
    if not path.is_file():
        raise DatasetError(f"{path}: trajectory file not found")
    timestamps, poses = [], []
    for number, line in enumerate(path.read_text().splitlines(), start=1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        parts = line.replace(",", " ").split()
        try:
            values = [float(p) for p in parts]
            if len(values) != 8:
                raise ValueError(f"expected 8 numbers, found {len(values)}")
            pose = se3.from_tum(np.array(values[1:]))
        except (ValueError, se3.PoseError) as err:
            raise DatasetError(f"{path}:{number}: cannot parse pose line ({err})") from None
        timestamps.append(values[0])
        poses.append(pose)
    if not timestamps:
        raise DatasetError(f"{path}: trajectory has no poses")
    return Trajectory(np.array(timestamps), np.array(poses))

"""The repository's tiny TUM folder (data/tiny_desk) read raw, independently of the project's
readers: the truth that the log and bag readers are checked against."""

from pathlib import Path

import cv2
import numpy as np

TINY = Path(__file__).resolve().parents[1] / "data" / "tiny_desk"


def tum_frames() -> list[tuple[float, np.ndarray, np.ndarray]]:
    """(timestamp, raw uint16 depth in 1/5000 m, RGB colour) of each tiny_desk frame."""
    frames = []
    for line in (TINY / "associations.txt").read_text().splitlines():
        stamp, colour, _, depth = line.split()
        raw = cv2.imread(str(TINY / depth), cv2.IMREAD_UNCHANGED)
        rgb = cv2.imread(str(TINY / colour), cv2.IMREAD_COLOR)[..., ::-1]
        frames.append((float(stamp), raw, np.ascontiguousarray(rgb)))
    return frames

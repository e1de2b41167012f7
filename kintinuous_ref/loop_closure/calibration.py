"""Calibrating loop verification on real revisits: every check's statistic for candidates whose
truth is known.

A candidate is a pair of keyframes (a query and an older match) made from frames of a recording
with a ground truth, each at its true pose. `place_recognition.verify(..., every_check=True)`
measures every statistic (match count, RANSAC inliers and their share, the dense alignment's
RMSE and paired shares, the photometric share) however the checks decide, and the ground truth
says whether the two views show the same surface: the share of the query's points that land,
at the true relative pose, within `TRUE_PAIRING` metres of the match's surface (`true_overlap`).
Pairs above `SAME_PLACE` are true revisits, pairs below `DIFFERENT_PLACE` false ones; those in
between are measured and left unlabelled.

Three kinds of candidate (benchmarks/loop_calibration.py builds them all on redkitchen):

- **there and back** at a stride: the recording played forward on every stride-th frame and
  back on the frames between (`there_and_back_order`), keyframes taken by the run's own rule at
  the true poses, each keyframe of the way back against the older keyframes that the run would
  verify (`ranked_candidates`, outside the recent window);
- **offset**: a frame against an earlier one that the camera left at least `min_apart_m` and
  `min_apart_deg` before (a return that does not retrace the way out);
- **apart**: pairs whose views share no surface, those with the most ORB matches first (the
  ones that reach the later checks).

The offset and apart pairs are also measured with the dense alignment started from a drifted
odometry estimate (`drifted`: the true relative pose moved and turned by a given drift) rather
than from RANSAC's motion, as a tracked run starts it where the sparse stage finds too few
inliers (`LoopClosureConfig.dense_from_odometry`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Protocol

import cv2
import numpy as np

from kintinuous_ref import se3
from kintinuous_ref.camera import Intrinsics
from kintinuous_ref.config import Config, LoopClosureConfig
from kintinuous_ref.loop_closure.keyframes import Keyframe, is_new_keyframe, make_keyframe
from kintinuous_ref.loop_closure.place_recognition import (
    Verdict,
    match_descriptors,
    overlap,
    ranked_candidates,
    verify,
)
from kintinuous_ref.preprocess import preprocess_frame

TRUE_PAIRING = 0.05  # metres: the ground truth (KinectFusion's) is good to about a centimetre
SAME_PLACE = 0.3  # true overlap at and above which a pair is a true revisit
DIFFERENT_PLACE = 0.05  # and below which it is a false one
# metres: a dense alignment this close to the true relative pose is right (from the true pose
# itself it settles 1-7 cm away on redkitchen's offset views: the ground truth's own error over
# a few seconds); a loop with a wrong pose is as false as one between different places
RIGHT_POSE = 0.1


class FrameSource(Protocol):
    """What the keyframes are made from: a TUM sequence's frames (tum.Sequence)."""

    camera: Intrinsics

    def __len__(self) -> int: ...
    def __getitem__(self, index: int):  # noqa: ANN204 - a tum.Frame (colour, depth)
        ...


def there_and_back_order(count: int, stride: int = 2) -> list[int]:
    """Indices of a `count`-frame recording: every `stride`-th from 0 forward, then those
    stride // 2 after each of them back (stride 2: the even frames forward, the odd back)."""
    forward = list(range(0, count, stride))
    back = [index + stride // 2 for index in forward if index + stride // 2 < count]
    return forward + back[::-1]


def views_apart(first: np.ndarray, second: np.ndarray) -> tuple[float, float]:
    """(metres, degrees) between two camera poses."""
    relative = se3.inverse(first) @ second
    angle = np.degrees(se3.rotation_angle(relative[:3, :3]))
    return float(np.linalg.norm(relative[:3, 3])), float(angle)


def path_lengths(poses: np.ndarray) -> np.ndarray:
    """(N,) metres travelled up to each pose along the sequence."""
    steps = np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1)
    return np.concatenate([[0.0], np.cumsum(steps)])


@dataclass
class KeyframeMaker:
    """Keyframes of a recording's frames at their true poses, scaled to `width` x `height`
    (the pipeline's pyramid at that size), each made once."""

    frames: FrameSource
    truth: np.ndarray  # (N, 4, 4) camera-to-world per frame
    width: int
    height: int
    settings: LoopClosureConfig = field(default_factory=LoopClosureConfig)
    _made: dict[int, Keyframe] = field(default_factory=dict)

    def __call__(self, frame: int, node: int = 0, travelled: float = 0.0) -> Keyframe:
        if frame not in self._made:
            image = self.frames[frame]
            colour, depth = image.colour, image.depth
            camera = self.frames.camera
            if (camera.width, camera.height) != (self.width, self.height):
                size = (self.width, self.height)
                colour = cv2.resize(colour, size, interpolation=cv2.INTER_AREA)
                depth = cv2.resize(depth, size, interpolation=cv2.INTER_NEAREST)
                camera = camera.resized(self.width, self.height)
            preprocessed = preprocess_frame(colour, depth, camera, Config().preprocess)
            self._made[frame] = make_keyframe(
                0, frame, self.truth[frame], 0.0, preprocessed, self.settings
            )
        keyframe = self._made[frame]
        return Keyframe(**{**keyframe.__dict__, "node": node, "travelled": travelled})


def true_overlap(query: Keyframe, match: Keyframe) -> float:
    """The share of the query's points on the match's surface at their true relative pose."""
    truth = se3.inverse(match.pose) @ query.pose
    return overlap(query, match, truth, TRUE_PAIRING).paired_share


@dataclass
class Candidate:
    kind: str  # "there and back, stride S", "offset", "apart", ...
    query_frame: int
    match_frame: int
    apart_m: float  # the true distance between the two views
    apart_deg: float
    true_overlap: float
    verdict: Verdict
    pose_error_m: float | None  # the dense alignment's translation against the truth
    true_relative: np.ndarray  # (4, 4) the query in the match's camera frame, from the truth

    @property
    def label(self) -> bool | None:
        """True for a revisit, False for different places, None in between."""
        if self.true_overlap >= SAME_PLACE:
            return True
        if self.true_overlap < DIFFERENT_PLACE:
            return False
        return None

    @property
    def group(self) -> str:
        """ "right" (a revisit aligned right: to accept), "wrong" (a revisit aligned wrong, or
        different places: to refuse) or "unlabelled"."""
        if self.label is None:
            return "unlabelled"
        right = self.pose_error_m is not None and self.pose_error_m < RIGHT_POSE
        return "right" if self.label and right else "wrong"

    @property
    def information_chi2(self) -> float | None:
        """r^T H r for the dense pose's error r against the truth, in the pose graph's residual,
        H the alignment's own per-pair information (`alignment_information`)."""
        found, information = self.verdict.dense_pose, self.verdict.information
        if found is None or information is None:
            return None
        residual = pose_residual(found, self.true_relative)
        return float(residual @ information @ residual)

    def as_dict(self) -> dict:
        return {
            "group": self.group,
            "information_chi2": self.information_chi2,
            "kind": self.kind,
            "query_frame": self.query_frame,
            "match_frame": self.match_frame,
            "apart_m": self.apart_m,
            "apart_deg": self.apart_deg,
            "true_overlap": self.true_overlap,
            "label": self.label,
            "pose_error_m": self.pose_error_m,
            "dense_angle_deg": self.verdict.dense_angle_deg,
            **self.verdict.as_dict(),
        }


def drifted(pose: np.ndarray, drift: tuple[float, float], rng: np.random.Generator) -> np.ndarray:
    """`pose` moved `drift[0]` metres along a random direction and turned `drift[1]` degrees
    about a random axis: an odometry estimate of it with that much drift."""
    direction, axis = rng.normal(size=3), rng.normal(size=3)
    direction, axis = direction / np.linalg.norm(direction), axis / np.linalg.norm(axis)
    error = se3.exp(np.concatenate([axis * np.radians(drift[1]), np.zeros(3)]))
    error[:3, 3] = direction * drift[0]
    return pose @ error


def measure(  # noqa: PLR0913
    kind: str,
    query: Keyframe,
    match: Keyframe,
    settings: LoopClosureConfig,
    rng: np.random.Generator,
    drift: tuple[float, float] | None = None,
) -> Candidate:
    """Every check's statistic for one pair of keyframes (at their true poses). With `drift`
    (metres, degrees) the dense alignment starts from the true relative pose that far off, as a
    tracked run's odometry would give it (`verify`'s `prior`), instead of from RANSAC's motion."""
    truth = se3.inverse(match.pose) @ query.pose
    prior = drifted(truth, drift, rng) if drift is not None else None
    verdict = verify(
        query, match, settings, rng, every_check=True, prior=prior, from_prior=prior is not None
    )
    error = None
    if verdict.icp_rmse is not None and np.isfinite(verdict.icp_rmse):
        found = verdict.dense_pose
        if found is not None:
            error = float(np.linalg.norm(found[:3, 3] - truth[:3, 3]))
    apart = views_apart(match.pose, query.pose)
    return Candidate(
        kind, query.frame, match.frame, *apart, true_overlap(query, match), verdict, error, truth
    )


def pose_residual(measured: np.ndarray, true: np.ndarray) -> np.ndarray:
    """The pose graph's residual [log R(E), t(E)] of E = measured^-1 true (pose_graph.py)."""
    error = se3.inverse(measured) @ true
    return np.concatenate([se3.rotation_log(error[:3, :3]), error[:3, 3]])


def effective_pairs(candidates: list[Candidate]) -> float:
    """n with n H the information that states the right candidates' errors against the
    ground truth: the maximum likelihood scale of a Gaussian covariance, 6 / mean(r^T H r)
    (`Candidate.information_chi2`), so that r^T (n H) r averages 6, its six degrees of freedom."""
    # each pair once: from RANSAC's motion, as the calibrated runs measure it
    values = [
        c.information_chi2
        for c in candidates
        if c.group == "right" and c.verdict.dense_start == "ransac"
    ]
    values = [v for v in values if v is not None and np.isfinite(v)]
    return 6.0 / float(np.mean(values)) if values else float("nan")


def there_and_back_candidates(
    make: KeyframeMaker, stride: int, settings: LoopClosureConfig, rng: np.random.Generator
) -> list[Candidate]:
    """The candidates a run over redkitchen played there and back at `stride` verifies, with
    its keyframes at their true poses: each keyframe of the way back against the older
    keyframes with the most ORB matches outside the recent window."""
    order = there_and_back_order(len(make.truth), stride)
    travelled = path_lengths(make.truth[order])
    taken: list[Keyframe] = []
    out: list[Candidate] = []
    way_back = len(range(0, len(make.truth), stride))
    for position, frame in enumerate(order):
        last = taken[-1].pose if taken else None
        if not is_new_keyframe(last, make.truth[frame], settings):
            continue
        keyframe = make(frame, len(taken), float(travelled[position]))
        if position >= way_back:
            for match, _ in ranked_candidates(keyframe, taken, settings):
                out.append(measure(f"there and back, stride {stride}", keyframe, match,
                                   settings, rng))  # fmt: skip
        taken.append(keyframe)
    return out


def offset_pairs(
    truth: np.ndarray,
    min_apart_m: float,
    min_apart_deg: float,
    min_gap: int,
    step: int,
) -> list[tuple[int, int]]:
    """(query, match) frame pairs, match earlier by at least `min_gap` frames, whose true views
    are at least `min_apart_m` and `min_apart_deg` apart, on every `step`-th frame; for each
    query only the nearest such match in distance (the place it comes back to)."""
    pairs = []
    for query in range(min_gap, len(truth), step):
        best = None
        for match in range(0, query - min_gap + 1, step):
            metres, degrees = views_apart(truth[match], truth[query])
            if metres >= min_apart_m and degrees >= min_apart_deg:
                if best is None or metres < best[0]:
                    best = (metres, match)
        if best is not None:
            pairs.append((query, best[1]))
    return pairs


def measure_pairs(  # noqa: PLR0913
    kind: str,
    make: KeyframeMaker,
    pairs: list[tuple[int, int]],
    settings: LoopClosureConfig,
    rng: np.random.Generator,
    drift: tuple[float, float] | None = None,
) -> list[Candidate]:
    travelled = path_lengths(make.truth).tolist()
    return [
        measure(kind, make(q, 1, travelled[q]), make(m, 0, travelled[m]), settings, rng, drift)
        for q, m in pairs
    ]


def apart_pairs(
    make: KeyframeMaker, frames: list[int], count: int, settings: LoopClosureConfig
) -> list[tuple[int, int]]:
    """Up to `count` pairs of `frames` whose views share no surface (true overlap below
    DIFFERENT_PLACE both ways), the ones with the most ORB matches first."""
    scored = []
    for i, query in enumerate(frames):
        for match in frames[:i]:
            q, m = make(query), make(match)
            if max(true_overlap(q, m), true_overlap(m, q)) >= DIFFERENT_PLACE:
                continue
            matches = len(match_descriptors(q.descriptors, m.descriptors, settings.match_ratio)[0])
            scored.append((matches, query, match))
    scored.sort(reverse=True)
    return [(query, match) for _, query, match in scored[:count]]


def summary(candidates: list[Candidate]) -> dict:
    """Per kind: candidates in each group (Candidate.group) and how many of each were accepted."""
    out: dict = {}
    for c in candidates:
        entry = out.setdefault(c.kind, {})
        entry[c.group] = entry.get(c.group, 0) + 1
        if c.verdict.accepted:
            entry[f"{c.group}_accepted"] = entry.get(f"{c.group}_accepted", 0) + 1
    return out


# The statistics drawn by `draw_distributions`: (Verdict field, axis label, the threshold's
# LoopClosureConfig field and whether it is a lower bound).
STATISTICS = (
    ("matches", "ratio-test ORB matches", "min_matches", True),
    ("ransac_inliers", "RANSAC inliers", "min_ransac_inliers", True),
    ("ransac_share", "RANSAC inliers per match", "min_ransac_share", True),
    ("icp_rmse", "dense RMSE (m)", "max_icp_rmse", False),
    ("icp_inlier_share", "paired per point (absolute)", None, True),
    ("icp_overlap_share", "paired per visible point", "min_icp_overlap_share", True),
)
COLOURS = {"right": "tab:green", "wrong": "tab:red", "twins": "tab:purple"}
ROWS = {"right": 0, "wrong": 1, "twins": 2}


def _row(candidate: Candidate) -> str:
    """The figure's row: right, wrong (real) or the synthetic twins (wrong too)."""
    if candidate.group == "wrong" and candidate.kind.startswith("twins"):
        return "twins"
    return candidate.group


def draw_distributions(candidates: list[Candidate], settings: LoopClosureConfig):  # noqa: ANN201
    """A matplotlib figure: each check's statistic for right candidates, wrong real ones and the
    twins (strips, jittered), the threshold as a dashed line; last, the photometric share
    against the angle between the views at the found pose, with the share asked for."""
    import matplotlib.pyplot as plt

    labelled = [c for c in candidates if c.group != "unlabelled"]
    figure, grid = plt.subplots(2, 4, figsize=(13, 5.5))
    axes = grid.ravel()
    jitter = np.random.default_rng(0)
    for ax, (name, title, threshold, _) in zip(axes, STATISTICS, strict=False):
        for row, number in ROWS.items():
            values = [getattr(c.verdict, name) for c in labelled if _row(c) == row]
            values = np.array([v for v in values if v is not None and np.isfinite(v)], float)
            ax.plot(values, number + jitter.uniform(-0.25, 0.25, len(values)), ".",
                    color=COLOURS[row], alpha=0.6)  # fmt: skip
        if threshold is not None:
            ax.axvline(getattr(settings, threshold), color="k", linestyle="--")
        ax.set_yticks(list(ROWS.values()), list(ROWS))
        ax.set_xlabel(title)
    ax = axes[len(STATISTICS)]
    for row in ROWS:
        points = [(c.verdict.dense_angle_deg, c.verdict.photometric_share) for c in labelled
                  if _row(c) == row and c.verdict.photometric_share is not None]  # fmt: skip
        if points:
            ax.plot(*np.array(points).T, ".", color=COLOURS[row], alpha=0.6, label=row)
    degrees = np.linspace(0, 40, 81)
    required = np.maximum(settings.photometric_share_floor, settings.min_photometric_share
                          - settings.photometric_share_per_degree * degrees)  # fmt: skip
    ax.plot(degrees, required, "k--", label="asked for")
    ax.set_xlim(0, 40)
    ax.set_xlabel("degrees between the views (found pose)")
    ax.set_ylabel("photometric share")
    ax.legend(fontsize=7)
    axes[-1].axis("off")
    figure.tight_layout()
    return figure


def twins_candidates(
    settings: LoopClosureConfig, rng: np.random.Generator, width: int = 320, height: int = 240
) -> list[Candidate]:
    """The synthetic `twins` walk (two identical bays 5 m apart, a path that never comes back)
    with keyframes at its true poses: every candidate the run would verify, each with every
    statistic. None is a true revisit; the bays are the hardest false one."""
    from kintinuous_ref.datasets import synthetic

    scenario = synthetic.make_scenario("twins", frames=480, width=width, height=height)
    poses = scenario.trajectory.poses
    travelled = path_lengths(poses)
    taken: list[Keyframe] = []
    out: list[Candidate] = []
    for frame in range(0, len(scenario), 6):
        if taken and not is_new_keyframe(taken[-1].pose, poses[frame], settings):
            continue
        colour, depth = scenario.render(frame)
        preprocessed = preprocess_frame(colour, depth, scenario.camera, Config().preprocess)
        keyframe = make_keyframe(
            len(taken), frame, poses[frame], float(travelled[frame]), preprocessed, settings
        )
        for match, _ in ranked_candidates(keyframe, taken, settings):
            out.append(measure("twins (synthetic)", keyframe, match, settings, rng))
        taken.append(keyframe)
    return out

"""The course's one loader of real frames: which sequence it picks, the frames and poses it lends
the lessons, and the clean skip. The sequences are TUM folders written here from a synthetic
scenario, whose exact poses are the truth the loaded ground truth is compared with."""

from pathlib import Path

import numpy as np
import pytest

from kintinuous_ref.datasets import course_data
from kintinuous_ref.datasets.course_data import (
    COURSE_VARIABLE,
    first_tracked_run,
    load_course_data,
    skip_line,
)
from kintinuous_ref.datasets.synthetic import make_scenario
from kintinuous_ref.datasets.tum import Frame, Trajectory, open_sequence, write_sequence
from kintinuous_ref.errors import DatasetError

WIDTH, HEIGHT = 32, 24
FRAMES = 8  # the course length the tests ask for (the lessons ask for 300)


@pytest.fixture(scope="module")
def scenario():
    return make_scenario("desk", frames=12, width=WIDTH, height=HEIGHT, noise=False)


def write_tum(folder: Path, scenario, frames: int = 12, posed: list[int] | None = None) -> Path:
    """The scenario's first `frames` frames as a TUM folder; only the frames in `posed` (all
    when None) get a line in groundtruth.txt (TUM's ground truth may start late or have gaps)."""
    posed = list(range(len(scenario))) if posed is None else posed
    images = (
        Frame(i, t, *scenario.render(i))
        for i, t in enumerate(scenario.trajectory.timestamps[:frames])
    )
    truth = Trajectory(scenario.trajectory.timestamps[posed], scenario.trajectory.poses[posed])
    write_sequence(folder, images, scenario.camera, truth)
    return folder


@pytest.fixture
def places(tmp_path, monkeypatch):
    """Empty data folder, cache and variable: nothing to find until a test writes it."""
    data, cache = tmp_path / "data", tmp_path / "cache"
    data.mkdir()
    monkeypatch.setenv("KINTINUOUS_DATA", str(data))
    monkeypatch.setenv("KINTINUOUS_CACHE", str(cache))
    monkeypatch.delenv(COURSE_VARIABLE, raising=False)
    return data, cache / "tum"


def test_nothing_found_is_none_and_one_line_says_where_it_looked(places):
    data, downloads = places
    assert load_course_data(FRAMES) is None
    line = skip_line()
    assert "\n" not in line and "skipping" in line
    assert str(data) in line and str(downloads) in line and f"${COURSE_VARIABLE}" in line


def test_the_choice_order_variable_then_redkitchen_then_downloads(
    places, scenario, tmp_path, monkeypatch
):
    data, downloads = places
    write_tum(downloads / "fr1" / "xyz", scenario)
    write_tum(downloads / "fr1" / "desk", scenario)
    chosen = load_course_data(FRAMES)
    assert chosen.name == "fr1/desk"  # download.SEQUENCES' order: the paper's fr1/desk first
    assert not chosen.is_redkitchen and "downloaded" in chosen.source

    write_tum(data / "redkitchen", scenario)
    chosen = load_course_data(FRAMES)
    assert chosen.name == "redkitchen" and chosen.is_redkitchen
    assert chosen.sequence.path == data / "redkitchen"

    write_tum(tmp_path / "my_sequence", scenario)
    monkeypatch.setenv(COURSE_VARIABLE, str(tmp_path / "my_sequence"))
    chosen = load_course_data(FRAMES)
    assert chosen.name == "my_sequence" and not chosen.is_redkitchen
    assert chosen.source == f"${COURSE_VARIABLE}"
    assert "my_sequence" in chosen.describe()


def test_frames_and_poses_are_the_sequences_own(places, scenario, tmp_path, monkeypatch):
    monkeypatch.setenv(COURSE_VARIABLE, str(write_tum(tmp_path / "seq", scenario)))
    chosen = load_course_data(FRAMES)
    assert len(chosen) == FRAMES and chosen.first == 0
    np.testing.assert_allclose(
        chosen.groundtruth.poses, scenario.trajectory.poses[:FRAMES], atol=1e-8
    )
    full = chosen.frame(5)
    colour, depth = scenario.render(5)
    np.testing.assert_array_equal(full.colour, colour)  # PNG is lossless
    np.testing.assert_allclose(full.depth, depth, atol=0.5 / 5000)  # TUM's 1/5000 m steps
    assert full.index == 5 and full.timestamp == pytest.approx(scenario.trajectory.timestamps[5])

    small = chosen.frame(5, WIDTH // 2, HEIGHT // 2)
    assert small.colour.shape == (HEIGHT // 2, WIDTH // 2, 3)
    assert small.depth.shape == (HEIGHT // 2, WIDTH // 2)
    # nearest neighbour invents no depth between surfaces: every value is one of the frame's
    assert set(np.unique(small.depth)) <= set(np.unique(full.depth))
    camera = chosen.camera_at(WIDTH // 2, HEIGHT // 2)
    assert camera.fx == pytest.approx(scenario.camera.fx / 2)
    assert (camera.width, camera.height) == (WIDTH // 2, HEIGHT // 2)
    assert [frame.index for frame in chosen.frames(range(0, FRAMES, 3))] == [0, 3, 6]
    with pytest.raises(IndexError):
        chosen.frame(FRAMES)


def test_the_course_starts_where_the_ground_truth_covers_enough_frames(places, scenario, tmp_path):
    # frame 3 has no pose: frames 0-2 are too few, frames 4-11 are the first eight in a row
    folder = write_tum(tmp_path / "gap", scenario, posed=[0, 1, 2, *range(4, 12)])
    chosen = course_data.course_data_from(folder, "gap", "test", frames=FRAMES)
    assert chosen.first == 4 and len(chosen) == FRAMES
    np.testing.assert_allclose(chosen.groundtruth.poses, scenario.trajectory.poses[4:12], atol=1e-8)
    np.testing.assert_allclose(
        chosen.groundtruth.timestamps, scenario.trajectory.timestamps[4:12], atol=1e-6
    )
    np.testing.assert_array_equal(chosen.frame(0).depth, chosen.sequence[4].depth)
    # course frame i's pose is groundtruth.poses[i], as pipeline.run looks it up by frame.index
    assert chosen.frame(3).index == 3

    sequence = open_sequence(folder)
    assert first_tracked_run(sequence, 9) is None  # eight posed frames in a row at most


def test_a_sequence_that_cannot_serve_says_why(places, scenario, tmp_path, monkeypatch):
    short = write_tum(tmp_path / "short", scenario, frames=5)
    with pytest.raises(DatasetError, match=f"no {FRAMES} consecutive frames"):
        course_data.course_data_from(short, "short", "test", frames=FRAMES)
    bare = tmp_path / "bare"
    images = (Frame(i, float(i), *scenario.render(i)) for i in range(FRAMES))
    write_sequence(bare, images, scenario.camera)
    with pytest.raises(DatasetError, match="no groundtruth.txt"):
        course_data.course_data_from(bare, "bare", "test", frames=FRAMES)
    # a variable naming no folder is the user's mistake, not a reason to fall back quietly
    monkeypatch.setenv(COURSE_VARIABLE, str(tmp_path / "missing"))
    with pytest.raises(DatasetError, match=f"\\${COURSE_VARIABLE}=.*not a folder"):
        load_course_data(FRAMES)


def test_downloads_folder_follows_the_cache_variable(monkeypatch, tmp_path):
    monkeypatch.setenv("KINTINUOUS_CACHE", str(tmp_path))
    assert course_data.downloads_folder() == tmp_path / "tum"
    monkeypatch.delenv("KINTINUOUS_CACHE")
    assert course_data.downloads_folder() == Path.home() / ".cache" / "kintinuous" / "tum"

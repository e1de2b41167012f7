"""Property-based tests (hypothesis) of the readers: the TUM files (associations.txt,
rgb.txt/depth.txt, groundtruth.txt, intrinsics.json), .klg logs and bags given random bytes, or a
valid file with random edits (lines dropped, duplicated or swapped, fields replaced by random
words or numbers, bytes overwritten, the file cut), never raise anything but the project's
one-line errors (KintinuousError subclasses)."""

import shutil
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from kintinuous_ref.camera import load_intrinsics_json
from kintinuous_ref.datasets import tum
from kintinuous_ref.errors import KintinuousError

TINY = Path(__file__).resolve().parent.parent / "data" / "tiny_desk"
SETTINGS = settings(
    max_examples=80,
    deadline=None,
    suppress_health_check=[HealthCheck.function_scoped_fixture],
)
WORDS = (
    st.sampled_from(
        [
            "nan",
            "inf",
            "-inf",
            "1e400",
            "-1",
            "0",
            "",
            "#",
            "rgb/x.png",
            "depth/",
            "\x00",
            "é",
            "1,2",
        ]
    )
    | st.text(max_size=6)
    | st.floats().map(repr)
)


@pytest.fixture(scope="module")
def copy(tmp_path_factory):
    folder = tmp_path_factory.mktemp("readers") / "seq"
    shutil.copytree(TINY, folder)
    return folder


@st.composite
def edited(draw, text: str) -> bytes:
    """`text` with a few random line and field edits."""
    lines = text.splitlines()
    for _ in range(draw(st.integers(1, 4))):
        if not lines:
            break
        at = draw(st.integers(0, len(lines) - 1))
        action = draw(st.sampled_from(["drop", "duplicate", "swap", "field", "append"]))
        if action == "drop":
            del lines[at]
        elif action == "duplicate":
            lines.insert(at, lines[at])
        elif action == "swap":
            other = draw(st.integers(0, len(lines) - 1))
            lines[at], lines[other] = lines[other], lines[at]
        elif action == "field":
            fields = lines[at].split() or [""]
            fields[draw(st.integers(0, len(fields) - 1))] = draw(WORDS)
            lines[at] = " ".join(fields)
        else:
            lines[at] += " " + draw(WORDS)
    return ("\n".join(lines) + "\n").encode("utf-8", "surrogatepass")


def _only_project_errors(action) -> None:
    try:
        action()
    except KintinuousError as err:
        assert "\n" not in str(err)


def _open_and_read(folder: Path) -> None:
    """Open, read frame 0 and the per-frame ground truth; what was read is finite."""
    sequence = tum.open_sequence(folder)
    sequence[0]
    assert np.isfinite(sequence.timestamps).all()
    if sequence.groundtruth is not None:
        assert np.isfinite(sequence.groundtruth.poses).all()
        assert np.isfinite(sequence.groundtruth.timestamps).all()
        sequence.groundtruth_for_frames()


def _restore(folder: Path, name: str) -> None:
    shutil.copy(TINY / name, folder / name)


@SETTINGS
@given(data=st.binary(max_size=300))
def test_random_bytes_as_a_trajectory(copy, data):
    (copy / "groundtruth.txt").write_bytes(data)
    _only_project_errors(lambda: tum.read_trajectory(copy / "groundtruth.txt"))
    _restore(copy, "groundtruth.txt")


@SETTINGS
@given(data=edited((TINY / "groundtruth.txt").read_text()))
def test_random_edits_of_a_trajectory(copy, data):
    (copy / "groundtruth.txt").write_bytes(data)
    _only_project_errors(lambda: _open_and_read(copy))
    _restore(copy, "groundtruth.txt")


@SETTINGS
@given(name=st.sampled_from(["associations.txt", "intrinsics.json"]), data=st.binary(max_size=300))
def test_random_bytes_as_a_list_or_intrinsics_file(copy, name, data):
    (copy / name).write_bytes(data)
    _only_project_errors(lambda: _open_and_read(copy))
    _restore(copy, name)


@SETTINGS
@given(data=edited((TINY / "associations.txt").read_text()))
def test_random_edits_of_associations(copy, data):
    (copy / "associations.txt").write_bytes(data)
    _only_project_errors(lambda: _open_and_read(copy))
    _restore(copy, "associations.txt")


@SETTINGS
@given(
    name=st.sampled_from(["rgb.txt", "depth.txt"]),
    data=st.binary(max_size=200) | edited((TINY / "rgb.txt").read_text()),
)
def test_random_rgb_and_depth_lists(copy, name, data):
    # Without associations.txt the two lists are associated by timestamp.
    (copy / "associations.txt").unlink()
    (copy / name).write_bytes(data)
    _only_project_errors(lambda: _open_and_read(copy))
    _restore(copy, name)
    _restore(copy, "associations.txt")


@SETTINGS
@given(data=edited((TINY / "intrinsics.json").read_text().replace(",", " , ")))
def test_random_edits_of_intrinsics(copy, data):
    (copy / "intrinsics.json").write_bytes(data)
    _only_project_errors(lambda: load_intrinsics_json(copy / "intrinsics.json"))
    _restore(copy, "intrinsics.json")


def test_a_folder_as_a_trajectory_or_intrinsics(copy):
    for read in (tum.read_trajectory, load_intrinsics_json):
        with pytest.raises(KintinuousError):
            read(copy / "rgb")


@pytest.fixture(scope="module")
def valid_log(tmp_path_factory):
    """tiny_desk as a .klg log, written by the project's writer (its reader is under test)."""
    from kintinuous_ref.datasets import klg

    path = tmp_path_factory.mktemp("klg") / "desk.klg"
    klg.write_log(path, tum.open_sequence(TINY).frames(0, 3))
    read_every_frame_of_log(path)  # undamaged, it reads
    return path.read_bytes()


def read_every_frame_of_log(path: Path) -> None:
    from kintinuous_ref.datasets import klg

    sequence = klg.open_log(path, size=(160, 120))
    for frame in sequence.frames():
        assert frame.depth.shape == (120, 160) and np.isfinite(frame.depth).all()


@SETTINGS
@given(data=st.binary(max_size=4096))
def test_random_bytes_as_a_klg_log(tmp_path, data):
    path = tmp_path / "random.klg"
    path.write_bytes(data)
    try:
        read_every_frame_of_log(path)
    except KintinuousError:
        pass


@SETTINGS
@given(data=st.data())
def test_random_damage_to_a_klg_log(tmp_path, valid_log, data):
    # bytes overwritten at random places, and the log cut at a random length
    damaged = bytearray(valid_log)
    for _ in range(data.draw(st.integers(1, 8))):
        at = data.draw(st.integers(0, len(damaged) - 1))
        damaged[at] = data.draw(st.integers(0, 255))
    cut = data.draw(st.integers(0, len(damaged)))
    path = tmp_path / "damaged.klg"
    path.write_bytes(bytes(damaged[:cut]))
    try:
        read_every_frame_of_log(path)
    except KintinuousError:
        pass


@SETTINGS
@given(data=st.binary(max_size=2048))
def test_random_bytes_as_a_bag(tmp_path, data):
    from kintinuous_ref.datasets import bag

    path = tmp_path / "random.bag"
    path.write_bytes(data)
    try:
        bag.open_bag(path)
    except KintinuousError:
        pass

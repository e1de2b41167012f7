"""Intrinsics: projection against back-projection, pyramid scaling, known cameras, JSON."""

import json

import numpy as np
import pytest

from kintinuous_ref.camera import (
    TUM_CAMERAS,
    Intrinsics,
    camera_from_folder_name,
    load_intrinsics_json,
    parse_intrinsics,
)
from kintinuous_ref.errors import ConfigError, DatasetError

CAMERA = Intrinsics(525.0, 520.0, 319.5, 239.5, 640, 480)


def test_backproject_then_project_returns_pixel_grid():
    depth = np.random.default_rng(1).uniform(0.5, 4.0, size=(480, 640))
    pixels = CAMERA.project(CAMERA.backproject(depth))
    v, u = np.mgrid[0:480, 0:640]
    np.testing.assert_allclose(pixels[..., 0], u, atol=1e-9)
    np.testing.assert_allclose(pixels[..., 1], v, atol=1e-9)


def test_principal_point_backprojects_onto_the_axis():
    depth = np.full((480, 640), 2.0)
    vertex = Intrinsics(500, 500, 320, 240, 640, 480).backproject(depth)[240, 320]
    np.testing.assert_allclose(vertex, [0, 0, 2.0])


def test_pyramid_level_keeps_pixel_correspondence():
    # Pixel (u, v) at level 2 is pixel (4u, 4v) at level 0: the same ray.
    level2 = CAMERA.at_level(2)
    assert (level2.width, level2.height) == (160, 120)
    point = np.array([0.3, -0.2, 1.7])
    np.testing.assert_allclose(CAMERA.project(point), 4 * level2.project(point))


def test_known_tum_cameras_and_folder_names(tmp_path):
    assert TUM_CAMERAS["freiburg1"].fx == 517.3
    assert TUM_CAMERAS["freiburg3"].cy == 247.6
    folder = tmp_path / "rgbd_dataset_freiburg2_desk"
    folder.mkdir()
    assert camera_from_folder_name(folder) == TUM_CAMERAS["freiburg2"]
    assert camera_from_folder_name(tmp_path) is None


def test_intrinsics_json_round_trip(tmp_path):
    path = tmp_path / "intrinsics.json"
    path.write_text(json.dumps(CAMERA.to_json()))
    assert load_intrinsics_json(path) == CAMERA


def test_bad_intrinsics_are_reported(tmp_path):
    path = tmp_path / "intrinsics.json"
    path.write_text('{"fx": 1}')
    with pytest.raises(DatasetError, match="intrinsics.json"):
        load_intrinsics_json(path)
    with pytest.raises(ConfigError, match="four numbers"):
        parse_intrinsics("1,2,3")
    with pytest.raises(ConfigError, match="positive"):
        Intrinsics(-1, 1, 0, 0, 10, 10)
    assert parse_intrinsics("525,525,319.5,239.5").fx == 525


FIELDS = "fx, fy, cx, cy, width, height and optionally depth_scale"
WHOLE = {"fx": 131.25, "fy": 131.25, "cx": 79.5, "cy": 59.5, "width": 160, "height": 120}


@pytest.mark.parametrize(
    ("content", "what"),
    [
        ("{}", f"no fx, fy, cx, cy, width, height (expected {FIELDS})"),
        ("[]", f"a JSON list, expected an object with {FIELDS}"),
        ('"fx"', f"a JSON string, expected an object with {FIELDS}"),
        (json.dumps({**WHOLE, "cx": None}), "cx null is not a number"),
        (json.dumps({k: v for k, v in WHOLE.items() if k != "cy"}), f"no cy (expected {FIELDS})"),
        (json.dumps({**WHOLE, "fx": "wide"}), 'fx "wide" is not a number'),
        (json.dumps({**WHOLE, "fy": True}), "fy true is not a number"),
        (
            json.dumps({**WHOLE, "width": 160.5}),
            "width 160.5 is not a whole number of pixels of at least 1",
        ),
        (
            json.dumps({**WHOLE, "height": 0}),
            "height 0 is not a whole number of pixels of at least 1",
        ),
        (
            json.dumps({**WHOLE, "height": -120}),
            "height -120 is not a whole number of pixels of at least 1",
        ),
        (json.dumps({**WHOLE, "depth_scale": [5000]}), "depth_scale [5000] is not a number"),
    ],
)
def test_an_intrinsics_file_names_the_field_missing_or_invalid(tmp_path, content, what):
    # `{}` said "not a valid intrinsics file ('fx')", `[]` "list indices must be integers...",
    # and a width of 160.5 was read as 160
    path = tmp_path / "intrinsics.json"
    path.write_text(content)
    with pytest.raises(DatasetError) as caught:
        load_intrinsics_json(path)
    assert str(caught.value) == f"{path}: not a valid intrinsics file: {what}"


def test_a_whole_size_written_as_a_float_is_read(tmp_path):
    path = tmp_path / "intrinsics.json"
    path.write_text(json.dumps({**WHOLE, "width": 160.0}))
    camera = load_intrinsics_json(path)
    assert (camera.width, camera.height) == (160, 120) and isinstance(camera.width, int)

"""Configuration values enter in one place: --set, --config and the numeric options are checked
against the dataclass field types of kintinuous_ref/config.py before any work starts, and a bad
value is one line naming the key (or file), what was expected and what was found. The loader is
also fed random bytes and random edits of a valid file (hypothesis): nothing but ConfigError."""

import json
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from kintinuous_ref.config import Config, check_values, with_overrides
from kintinuous_ref.errors import ConfigError, KintinuousError
from kintinuous_ref.program import cli
from kintinuous_ref.program.cli import main

TINY = Path(__file__).resolve().parent.parent / "data" / "tiny_desk"


def _one_line_error(capsys, argv: list[str]) -> str:
    try:
        status = main(argv)
    except SystemExit as done:  # argparse's usage errors, one line too
        status = done.code
    err = capsys.readouterr().err.strip()
    assert status == 2, err
    assert len(err.splitlines()) == 1 and "Traceback" not in err, err
    return err


@pytest.mark.parametrize(
    ("setting", "message"),
    [
        ("tracking.min_correspondences=abc", "tracking.min_correspondences: expected an integer"),
        ("volume.size=[1,2]", "volume.size: expected a number >= 0, found list [1, 2]"),
        ("volume.size=NaN", "volume.size: expected a finite number, found nan"),
        ("volume.size=Infinity", "volume.size: expected a finite number, found inf"),
        ("icp=3", "icp: expected a section of keys (iterations,"),
        ("icp.iterations=5", "icp.iterations: expected a list of integers"),
        ("icp.iterations=[10,2.5]", "icp.iterations[1]: expected an integer >= 0, found float"),
        ("icp.iterations=[]", "icp.iterations: expected a list of integers"),
        ('rgbd.min_gradient=[1,"a"]', "rgbd.min_gradient[1]: expected a number >= 0"),
        ("volume.moving=1", "volume.moving: expected true or false, found int 1"),
        ("combined.weighting=magic", "combined.weighting: expected one of paper,"),
        ("tracking.fallback=7", "tracking.fallback: expected one of constant-velocity"),
        ("volume.truncation_distance=-1", "expected a number >= 0, found -1.0"),
        ("icp.iterations.x=1", "'icp.iterations' has no sub-keys"),
        ("nonsense=1", "unknown configuration key 'nonsense'"),
        ("=1", "--set expects KEY=VALUE"),
    ],
)
def test_a_bad_set_value_is_one_line_before_any_work(capsys, tmp_path, setting, message):
    out = tmp_path / "out"
    err = _one_line_error(
        capsys, ["reconstruct", str(TINY), "--out", str(out), "--set", setting, "--backend", "ref"]
    )
    assert message in err
    assert not out.exists()  # refused before the output folder was made


@pytest.mark.parametrize(
    ("content", "message"),
    [
        (b"\x00\xff\xfe\x89PNG", "not a text file"),
        (b'{"icp": 3}', "icp: expected a section of keys"),
        (b'{"volume": {"size": NaN}}', "volume.size: expected a finite number, found nan"),
        (b'{"volume": {"resolution": "big"}}', "volume.resolution: expected an integer"),
        (b'{"rgbd": {"iterations": 7}}', "rgbd.iterations: expected a list of integers"),
        (b"[1, 2]", "expected one JSON object of configuration values, found list"),
        (b"{", "not valid JSON"),
        (b"[" * 100_000, "not valid JSON"),
    ],
)
def test_a_bad_config_file_is_one_line_naming_it(capsys, tmp_path, content, message):
    path = tmp_path / "config.json"
    path.write_bytes(content)
    for argv in (
        ["reconstruct", str(TINY), "--out", str(tmp_path / "o"), "--config", str(path)],
        ["benchmark", str(TINY), "--config", str(path)],
    ):
        err = _one_line_error(capsys, argv)
        assert f"{path}: " in err and message in err


def test_a_folder_or_a_missing_file_as_config(capsys, tmp_path):
    for path, message in ((tmp_path, "is a folder"), (tmp_path / "no.json", "not found")):
        err = _one_line_error(
            capsys, ["reconstruct", str(TINY), "--out", str(tmp_path / "o"), "--config", str(path)]
        )
        assert f"{path}: " in err and message in err


@pytest.mark.parametrize("option", ["--volume-size", "--frames", "--resolution"])
@pytest.mark.parametrize("value", ["inf", "-inf", "nan", "abc"])
def test_non_finite_or_non_numeric_options(capsys, tmp_path, option, value):
    err = _one_line_error(
        capsys, ["reconstruct", str(TINY), "--out", str(tmp_path / "o"), f"{option}={value}"]
    )
    assert f"argument {option}:" in err and repr(value) in err


def test_table_and_benchmark_refuse_non_finite_volume_sizes(capsys, tmp_path):
    for argv in (
        ["table", str(TINY), "--out", str(tmp_path / "t"), "--volume-size", "inf"],
        ["benchmark", str(TINY), "--volume-size", "nan"],
    ):
        assert "expected a finite number" in _one_line_error(capsys, argv)


def test_good_values_are_converted_to_the_field_types(tmp_path):
    path = tmp_path / "config.json"
    path.write_text('{"icp": {"iterations": [5, 3, 2]}, "volume": {"resolution": 64.0}}')
    config = cli.configured(Config(), path, ["volume.truncation_distance=null", "rgbd={}"])
    assert config.icp.iterations == (5, 3, 2) and config.volume.resolution == 64
    assert isinstance(config.volume.resolution, int)
    assert config.volume.truncation_distance is None
    check_values(config)


# --- property-based: random bytes and random edits of a valid configuration file -------------

VALID = {
    "volume": {"size": 2.0, "resolution": 64, "moving": True, "placement": "ahead"},
    "icp": {"iterations": [10, 5, 4], "distance_threshold": 0.1},
    "tracking.fallback": "previous",
    "combined": {"rgbd_weight": 1.0},
}
JSON_VALUES = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=8),
    lambda children: (
        st.lists(children, max_size=4) | st.dictionaries(st.text(max_size=8), children, max_size=4)
    ),
    max_leaves=10,
)
KEYS = st.sampled_from(
    [
        "volume",
        "volume.size",
        "icp.iterations",
        "icp",
        "tracking.fallback",
        "colour.max_weight",
        "rgbd.min_gradient",
        "volume.truncation_distance",
        "fovis.min_inliers",
        "x.y",
        "",
    ]
)


def _load(tmp_path: Path, data: bytes) -> None:
    path = tmp_path / "config.json"
    path.write_bytes(data)
    try:
        cli.configured(Config(), path, [])
    except KintinuousError as err:
        assert "\n" not in str(err)


@settings(
    max_examples=150, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(data=st.binary(max_size=200))
def test_random_bytes_as_config(tmp_path, data):
    _load(tmp_path, data)


@settings(
    max_examples=150, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(edits=st.lists(st.tuples(KEYS, JSON_VALUES), max_size=4))
def test_random_edits_of_a_valid_config(tmp_path, edits):
    values = json.loads(json.dumps(VALID))
    for key, value in edits:
        values[key] = value
    _load(tmp_path, json.dumps(values).encode())


@settings(
    max_examples=100, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(text=st.text(max_size=40))
def test_random_set_strings(text):
    try:
        config = cli.configured(Config(), None, [text])
    except ConfigError as err:
        assert "\n" not in str(err)
    else:
        check_values(config)


def test_with_overrides_checks_what_a_program_passes():
    with pytest.raises(ConfigError, match="volume.size: expected a finite number"):
        with_overrides(Config(), {"volume.size": float("inf")})

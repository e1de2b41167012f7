"""The configuration tree: a volume config is checked once, when it is made, and keys that moved
are refused with the name of their replacement."""

import json
from pathlib import Path

import pytest

from kintinuous_ref.config import Config, RgbdConfig, VolumeConfig, with_overrides
from kintinuous_ref.errors import ConfigError
from kintinuous_ref.program.cli import main

TINY_DESK = Path(__file__).resolve().parents[1] / "data" / "tiny_desk"


def test_a_volume_config_is_refused_where_it_is_made():
    cases = [
        ({"size": 0.0}, "size must be positive"),
        ({"resolution": 2000}, "resolution must be in 8..1024"),
        ({"shift_threshold": 17}, "shift threshold"),
        ({"placement": "behind"}, "placement.*(ahead.*centred)"),
    ]
    for fields, message in cases:
        with pytest.raises(ConfigError, match=message):
            VolumeConfig(**fields)
        with pytest.raises(ConfigError, match=message):
            with_overrides(Config(), {f"volume.{key}": value for key, value in fields.items()})


def test_the_volume_config_is_checked_once_per_reconstruct(tmp_path, monkeypatch):
    calls = []
    check = VolumeConfig.validate

    def counted(self: VolumeConfig) -> None:
        calls.append(self)
        check(self)

    monkeypatch.setattr(VolumeConfig, "validate", counted)
    out = tmp_path / "out"
    arguments = ["reconstruct", str(TINY_DESK), "--backend", "ref", "--frames", "2"]
    status = main([*arguments, "--resolution", "32", "--out", str(out)])
    assert status == 0 and (out / "report.json").exists()
    assert len(calls) == 1  # when the CLI makes it; not again in the pipeline or make_volume


def test_the_translation_limit_lives_in_tracking_only(tmp_path, capsys):
    assert not hasattr(RgbdConfig(), "max_translation_jump")
    message = "'rgbd.max_translation_jump' is now 'tracking.max_translation_jump'"
    with pytest.raises(ConfigError, match=message):
        with_overrides(Config(), {"rgbd.max_translation_jump": 0.2})
    # An old configuration file gets one line naming the replacement.
    old = tmp_path / "old.json"
    old.write_text(json.dumps({"rgbd": {"max_translation_jump": 0.2}}))
    status = main(["reconstruct", str(TINY_DESK), "--config", str(old), "--out", str(tmp_path)])
    err = capsys.readouterr().err.strip()
    assert status == 2 and len(err.splitlines()) == 1, err
    assert "tracking.max_translation_jump" in err

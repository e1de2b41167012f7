"""The configuration a command runs with: the values of a --config JSON file (nested or dotted
keys) and then of each --set KEY=VALUE, over the command's own defaults. Every value is checked
against its field's type where it is read (kintinuous_ref.config.with_overrides), so a bad one is
one line naming the file or --set, the key, what was expected and what was found.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from kintinuous_ref.errors import ConfigError

# The volume's command-line options: the start of VolumeConfig's message for the field each sets,
# and what it becomes, so that a refused value names the option the user typed (a --set of the
# same key keeps VolumeConfig's own words, after "--set: ")
VOLUME_OPTIONS = (
    ("shift threshold ", "--shift-threshold (volume.shift_threshold) "),
    ("volume resolution ", "--resolution (volume.resolution) "),
    ("volume size ", "--volume-size (volume.size): volume size "),
)


def volume_from_options(**fields: Any) -> Any:
    """A VolumeConfig of the command line's --resolution, --volume-size, --shift-threshold (and
    other `fields`): a value out of its range is a ConfigError naming the option and its key."""
    from kintinuous_ref.config import VolumeConfig

    try:
        return VolumeConfig(**fields)
    except ConfigError as err:
        message = str(err)
        for start, option in VOLUME_OPTIONS:
            if message.startswith(start):
                raise ConfigError(option + message.removeprefix(start)) from None
        raise


def configured(config: Any, path: Path | None, settings: list[str]) -> Any:
    """`config` with the values of a JSON file (nested or dotted keys) and then of KEY=VALUE
    strings, each checked against its field's type where it is read: a bad value is one
    ConfigError naming the file or --set, the key, what was expected and what was found."""
    from kintinuous_ref.config import with_overrides

    if path is not None:
        values = flatten(read_config_file(Path(path)))
        try:
            config = with_overrides(config, values)
        except ConfigError as err:
            raise ConfigError(f"{path}: {err}") from None
    for setting in settings:
        key, equals, text = setting.partition("=")
        if not equals or not key.strip():
            raise ConfigError(f"--set expects KEY=VALUE, got {setting!r}")
        try:
            value = json.loads(text)
        except (json.JSONDecodeError, RecursionError):
            value = text  # a bare word such as original-code
        try:
            config = with_overrides(config, {key.strip(): value})
        except ConfigError as err:
            raise ConfigError(f"--set: {err}") from None
    return config.validate()


def read_config_file(path: Path) -> dict:
    """The JSON object of a --config file, or a one-line ConfigError saying why not."""
    if path.is_dir():
        raise ConfigError(f"{path}: is a folder; --config takes a JSON file")
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        raise ConfigError(f"{path}: configuration file not found") from None
    except OSError as err:
        raise ConfigError(f"{path}: cannot read the configuration file ({err.strerror})") from None
    try:
        values = json.loads(data.decode("utf-8"))
    except UnicodeDecodeError:
        raise ConfigError(f"{path}: not a text file; --config takes a JSON file") from None
    except json.JSONDecodeError as err:
        raise ConfigError(f"{path}: not valid JSON ({err})") from None
    except RecursionError:
        raise ConfigError(f"{path}: not valid JSON (nested too deeply)") from None
    if not isinstance(values, dict):
        raise ConfigError(
            f"{path}: expected one JSON object of configuration values, found "
            f"{type(values).__name__}"
        )
    return values


def flatten(values: dict, prefix: str = "") -> dict:
    """{"icp": {"iterations": [..]}} as {"icp.iterations": [..]} (values checked later)."""
    flat: dict = {}
    for key, value in values.items():
        if isinstance(value, dict) and value:
            flat.update(flatten(value, f"{prefix}{key}."))
        else:
            flat[f"{prefix}{key}"] = value
    return flat

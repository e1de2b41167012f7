"""Every JSON the project writes is strict (no NaN or Infinity), and `evaluate` reports a
non-finite or unreadable trajectory as one line naming the file (and line)."""

import json
import math

import numpy as np

from kintinuous_ref.program.cli import main
from kintinuous_ref.strict_json import dumps


def _strict(text: str):
    def refuse(constant: str):
        raise AssertionError(f"non-standard JSON constant {constant}")

    return json.loads(text, parse_constant=refuse)


def test_non_finite_numbers_become_null():
    value = {
        "nan": math.nan,
        "inf": [1.0, math.inf, -math.inf],
        "numpy": np.array([np.nan, 2.0], dtype=np.float32),
        "scalar": np.float64(np.inf),
        "tuple": (np.int64(3), np.bool_(True)),
    }
    assert _strict(dumps(value)) == {
        "nan": None,
        "inf": [1.0, None, None],
        "numpy": [None, 2.0],
        "scalar": None,
        "tuple": [3, True],
    }


def test_evaluate_refuses_non_finite_poses_and_images_in_one_line(tmp_path, capsys):
    truth = tmp_path / "truth.txt"
    truth.write_text("1.0 0 0 0 0 0 0 1\n2.0 0.1 0 0 0 0 0 1\n")
    cases = {
        "nan.txt": (b"1.0 0 0 0 0 0 0 1\n2.0 nan 0 0 0 0 0 1\n", "nan.txt:2: cannot parse pose"),
        "inf.txt": (b"1.0 0 0 inf 0 0 0 1\n", "inf.txt:1: cannot parse pose line"),
        "image.png": (b"\x89PNG\r\n\x1a\n\x00\x00\xff\xfe", "image.png: not a text file"),
    }
    for name, (content, message) in cases.items():
        (tmp_path / name).write_bytes(content)
        status = main(["evaluate", str(tmp_path / name), str(truth), "--json"])
        err = capsys.readouterr().err.strip()
        assert status == 2 and message in err and len(err.splitlines()) == 1, err

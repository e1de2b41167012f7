"""Strict JSON for every file and line the project writes: NaN and infinity, which
`json.dumps` would write as the non-standard NaN and Infinity, become null; NumPy numbers and
arrays become plain numbers and lists."""

from __future__ import annotations

import json
import math
from typing import Any


def finite(value: Any) -> Any:
    """`value` with every non-finite float replaced by None (recursively), NumPy scalars and
    arrays as Python numbers and lists, tuples as lists."""
    if isinstance(value, dict):
        return {key: finite(item) for key, item in value.items()}
    if isinstance(value, list | tuple):
        return [finite(item) for item in value]
    if hasattr(value, "tolist") and not isinstance(value, str | bytes):  # NumPy scalar or array
        return finite(value.tolist())
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def dumps(value: Any, **options: Any) -> str:
    """json.dumps of `finite(value)` with allow_nan=False: always valid JSON."""
    return json.dumps(finite(value), allow_nan=False, **options)

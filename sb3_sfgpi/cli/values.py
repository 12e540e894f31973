"""Reading option values: ``KEY=VALUE`` lists and preference weights."""

from __future__ import annotations

import json
from collections.abc import Sequence
from typing import Any

from sb3_sfgpi.cli.errors import UsageError
from sb3_sfgpi.common.weights import validate_weights


def key_values(items: Sequence[str], option: str) -> dict[str, Any]:
    """``KEY=VALUE`` strings as a dict; a VALUE that is valid JSON is read as JSON, else kept as a string."""
    parsed = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or not key:
            raise UsageError(f"{option} expects KEY=VALUE, got {item!r}")
        try:
            parsed[key] = json.loads(value)
        except json.JSONDecodeError:
            parsed[key] = value
    return parsed


def check_weights(values: Sequence[float], name: str) -> list[float]:
    """Weights of unknown length (checked against the domain later): non-negative, finite, summing to 1."""
    return validate_weights(values, len(values), name).tolist()

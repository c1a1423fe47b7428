"""Settings files: TOML or JSON into the typed config dataclasses (partial, nested, unknown keys refused)."""

from __future__ import annotations

import dataclasses
import json
import tomllib
from pathlib import Path
from typing import Any


def read_settings(path: str | Path) -> dict[str, Any]:
    """A TOML (.toml) or JSON settings file as a dict; errors name the file."""
    kind = "JSON" if str(path).endswith(".json") else "TOML"
    try:
        text = Path(path).read_text(encoding="utf-8")
        return json.loads(text) if kind == "JSON" else tomllib.loads(text)
    except (tomllib.TOMLDecodeError, json.JSONDecodeError, UnicodeDecodeError) as e:
        raise ValueError(f"{path}: not valid {kind}: {e}") from None


def from_dict(cls, data: dict[str, Any]):
    """A dataclass from a (partial, nested) dict; lists become tuples where the default is one; unknown
    keys raise ValueError."""
    known = {f.name for f in dataclasses.fields(cls)}
    unknown = set(data) - known
    if unknown:
        raise ValueError(f"unknown {cls.__name__} settings: {', '.join(sorted(unknown))}")
    values = {}
    for name, value in data.items():
        default = getattr(cls(), name)
        if dataclasses.is_dataclass(default) and isinstance(value, dict):
            value = from_dict(type(default), value)
        elif isinstance(default, tuple) and isinstance(value, list):
            value = tuple(value)
        values[name] = value
    return cls(**values)

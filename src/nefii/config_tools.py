"""Nested dataclass configs: built from (partial) dicts, and ``--set key=value`` overrides applied to them.

Shared by the fit's and the geometry stage's configs, so both accept the same override syntax
(dotted keys into nested sections, ``on``/``off`` for booleans) and reject unknown fields alike.
"""
from __future__ import annotations

import dataclasses
from typing import Any, TypeVar

T = TypeVar("T")


def dataclass_from_dict(cls: type[T], values: dict[str, Any], where: str = "") -> T:
    """``cls`` built from a (possibly partial, nested) dict; unknown keys raise ``KeyError``."""
    fields = {f.name: f for f in dataclasses.fields(cls)}  # type: ignore[arg-type]
    kwargs: dict[str, Any] = {}
    for key, value in values.items():
        if key not in fields:
            raise KeyError(f"unknown config field {where}{key}")
        sub = fields[key].default_factory if fields[key].default_factory is not dataclasses.MISSING else None
        if sub is not None and dataclasses.is_dataclass(sub):
            kwargs[key] = dataclass_from_dict(sub, value, f"{where}{key}.")  # type: ignore[arg-type]
        else:
            kwargs[key] = value
    return cls(**kwargs)


def parse_value(text: str, current: Any) -> Any:
    """``text`` read as the type of the field's ``current`` value (bool: on/off, true/false, 1/0)."""
    if isinstance(current, bool):
        if text.lower() in ("1", "true", "on", "yes"):
            return True
        if text.lower() in ("0", "false", "off", "no"):
            return False
        raise ValueError(f"expected on/off, got {text!r}")
    if isinstance(current, int):
        return int(text)
    if isinstance(current, float):
        return float(text)
    return text


def apply_overrides(values: dict[str, Any], overrides: list[str]) -> None:
    """Set each ``key=value`` (dotted keys into nested dicts) in ``values``, in place.

    Raises ``ValueError`` for an item without ``=`` or a value of the wrong type, ``KeyError`` for an
    unknown field (or a section given a value)."""
    for item in overrides:
        if "=" not in item:
            raise ValueError(f"--set wants key=value, got {item!r}")
        key, text = item.split("=", 1)
        node = values
        parts = key.split(".")
        for p in parts[:-1]:
            if not isinstance(node.get(p), dict):
                raise KeyError(f"unknown config field {key}")
            node = node[p]
        if parts[-1] not in node or isinstance(node[parts[-1]], dict):
            raise KeyError(f"unknown config field {key}")
        node[parts[-1]] = parse_value(text, node[parts[-1]])

"""Nested dataclass configs: built from (partial) dicts, ``--set key=value`` overrides applied to them, and
every value checked against its declared type before any work starts.

Shared by the fit's and the geometry stage's configs and by eval's and relight's settings, so all accept the
same override syntax (dotted keys into nested sections, ``on``/``off`` for booleans) and reject bad values
alike: a choice is a ``Literal`` (a wrong name gets the nearest valid one), a number an
``Annotated[int, Range(lo, hi)]``, checked by :func:`validate`.
"""
from __future__ import annotations

import dataclasses
import difflib
import math
import typing
from dataclasses import dataclass
from typing import Any, Literal, TypeVar

T = TypeVar("T")


@dataclass(frozen=True)
class Range:
    """Bounds of a number: ``lo <= x <= hi`` (``lo < x`` when ``lo_open``); None: unbounded. Non-finite
    floats are always refused."""

    lo: float | None = None
    hi: float | None = None
    lo_open: bool = False

    def problem(self, x: float) -> str | None:
        if isinstance(x, float) and not math.isfinite(x):
            return f"{x} is not a finite number"
        if self.lo is not None and (x <= self.lo if self.lo_open else x < self.lo):
            return f"{x:g} is {'not above' if self.lo_open else 'below'} {self.lo:g}" + self._span()
        if self.hi is not None and x > self.hi:
            return f"{x:g} is above {self.hi:g}" + self._span()
        return None

    def _span(self) -> str:
        lo = "" if self.lo is None else f"{self.lo:g} {'<' if self.lo_open else '<='} "
        hi = "" if self.hi is None else f" <= {self.hi:g}"
        return f" (wants {lo}x{hi})"


def host_memory_bytes() -> int:
    """This machine's physical memory."""
    import os
    return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")


def machine_memory_bytes() -> int:
    """The larger of this machine's physical memory and its largest CUDA device's (where work may run)."""
    host = host_memory_bytes()
    try:
        import torch
        gpus = [torch.cuda.get_device_properties(i).total_memory for i in range(torch.cuda.device_count())]
    except Exception:  # no CUDA build, no driver
        gpus = []
    return max([host, *gpus])


def check_memory(nbytes: float, what: str, sizes: str, have: int | None = None) -> None:
    """Refuse work whose estimated memory, ``nbytes``, exceeds what this machine holds (``have``, default
    :func:`machine_memory_bytes`); ``sizes`` names the settings that set it."""
    have = machine_memory_bytes() if have is None else have
    if nbytes > have:
        raise ValueError(f"{what} would need about {nbytes / 2**30:.0f} GiB of memory, more than this machine's "
                         f"{have / 2**30:.0f} GiB: lower {sizes}")


def _closest(word: str, options: typing.Iterable[str]) -> str | None:
    """The option nearest ``word`` (difflib's ratio >= 0.6), or None."""
    close = difflib.get_close_matches(word, list(options), n=1, cutoff=0.6)
    return close[0] if close else None


def nearest(word: str, options: typing.Iterable[str]) -> str:
    """``; did you mean 'X'?`` for the closest of ``options``, or nothing."""
    close = _closest(word, options)
    return f"; did you mean '{close}'?" if close else ""


def _problem(value: Any, hint: Any) -> str | None:
    """Why ``value`` does not fit the type ``hint`` (None: it does)."""
    rng = None
    if typing.get_origin(hint) is typing.Annotated:
        hint, *extras = typing.get_args(hint)
        rng = next((e for e in extras if isinstance(e, Range)), None)
    origin = typing.get_origin(hint)
    if origin is Literal:
        options = typing.get_args(hint)
        if value not in options:
            return f"{value!r} is not one of {', '.join(map(str, options))}" + nearest(str(value), map(str, options))
        return None
    if hint is bool:
        return None if isinstance(value, bool) else f"expected on/off, got {value!r}"
    if hint is int:
        if isinstance(value, bool) or not isinstance(value, int):
            return f"expected a whole number, got {value!r}"
    elif hint is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            return f"expected a number, got {value!r}"
    elif hint is str:
        return None if isinstance(value, str) else f"expected text, got {value!r}"
    return None if rng is None else rng.problem(value)


def validate(obj: Any, where: str = "") -> None:
    """Check every field of the dataclass ``obj`` (and its nested ones) against its annotation: ``Literal``
    choices, ``Annotated[..., Range]`` bounds, plain types. Raises ``ValueError("where.field: problem")``."""
    hints = typing.get_type_hints(type(obj), include_extras=True)
    for f in dataclasses.fields(obj):
        value = getattr(obj, f.name)
        if dataclasses.is_dataclass(value):
            validate(value, f"{where}{f.name}.")
            continue
        problem = _problem(value, hints[f.name])
        if problem is not None:
            raise ValueError(f"{where}{f.name}: {problem}")


def dataclass_from_dict(cls: type[T], values: dict[str, Any], where: str = "") -> T:
    """``cls`` built from a (possibly partial, nested) dict; unknown keys raise ``KeyError``, and a nested
    section's own checks (its ``__post_init__``) raise ``ValueError`` prefixed with the section's path."""
    fields = {f.name: f for f in dataclasses.fields(cls)}  # type: ignore[arg-type]
    kwargs: dict[str, Any] = {}
    for key, value in values.items():
        if key not in fields:
            raise KeyError(f"unknown config field {where}{key}{nearest(key, fields)}")
        sub = fields[key].default_factory if fields[key].default_factory is not dataclasses.MISSING else None
        if sub is not None and dataclasses.is_dataclass(sub):
            kwargs[key] = dataclass_from_dict(sub, value, f"{where}{key}.")  # type: ignore[arg-type]
        else:
            kwargs[key] = value
    try:
        return cls(**kwargs)
    except ValueError as e:
        if not where:
            raise
        raise ValueError(f"{where}{e}") from None


def parse_value(text: str, current: Any) -> Any:
    """``text`` read as the type of the field's ``current`` value (bool: on/off, true/false, 1/0)."""
    if isinstance(current, bool):
        if text.lower() in ("1", "true", "on", "yes"):
            return True
        if text.lower() in ("0", "false", "off", "no"):
            return False
        raise ValueError(f"expected on/off, got {text!r}")
    try:
        if isinstance(current, int):
            return int(text)
        if isinstance(current, float):
            return float(text)
    except ValueError:
        raise ValueError(f"expected {'a whole number' if isinstance(current, int) else 'a number'}, "
                         f"got {text!r}") from None
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
        for i, p in enumerate(parts[:-1]):
            if not isinstance(node.get(p), dict):
                sections = [k for k, v in node.items() if isinstance(v, dict)]
                raise KeyError(f"unknown config field {key}{_suggest(parts, i, p, sections)}")
            node = node[p]
        if parts[-1] not in node or isinstance(node[parts[-1]], dict):
            leaves = [k for k, v in node.items() if not isinstance(v, dict)]
            raise KeyError(f"unknown config field {key}{_suggest(parts, len(parts) - 1, parts[-1], leaves)}")
        try:
            node[parts[-1]] = parse_value(text, node[parts[-1]])
        except ValueError as e:
            raise ValueError(f"{key}: {e}") from None


def _suggest(parts: list[str], i: int, word: str, options: list[str]) -> str:
    """``; did you mean 'a.b.c'?`` with part ``i`` of the dotted key replaced by the nearest option."""
    close = _closest(word, options)
    return f"; did you mean '{'.'.join(parts[:i] + [close] + parts[i + 1:])}'?" if close else ""

"""Frozen configuration dataclasses to and from JSON-like dictionaries.

A run writes its whole configuration to ``config.json`` (``dataclasses.asdict``); :func:`from_dict`
reads such a dictionary back into the dataclass, recursively, so that a saved run can be repeated
(``run --config FILE``). Keys that are missing keep their defaults (a file written by an older
version still loads); unknown keys are an error that names them (a typo must not be ignored).
"""

from __future__ import annotations

import dataclasses
import types
import typing
from typing import Any, TypeVar

from vggt_slam_pp.errors import InputError

T = TypeVar("T")


def _dataclass_in(hint) -> type | None:
    """The dataclass type in a field's type hint (``X`` or ``X | None``), or None."""
    if dataclasses.is_dataclass(hint):
        return hint
    if typing.get_origin(hint) in (typing.Union, types.UnionType):
        found = [a for a in typing.get_args(hint) if dataclasses.is_dataclass(a)]
        return found[0] if len(found) == 1 else None
    return None


def _fits(value, hint) -> bool:
    """Whether ``value`` (from JSON) fits a field's type hint; hints other than plain types pass."""
    if typing.get_origin(hint) in (typing.Union, types.UnionType):
        return any(_fits(value, a) for a in typing.get_args(hint))
    if hint is type(None):
        return value is None
    if hint is bool:
        return isinstance(value, bool)
    if hint is int:
        return isinstance(value, int) and not isinstance(value, bool)
    if hint is float:
        return isinstance(value, (int, float)) and not isinstance(value, bool)
    if hint is str:
        return isinstance(value, str)
    if typing.get_origin(hint) is tuple or hint is tuple:
        return isinstance(value, (list, tuple))
    if dataclasses.is_dataclass(hint):
        return isinstance(value, dict)
    return True


def from_dict(cls: type[T], data: dict[str, Any], where: str = "config") -> T:
    """``cls`` built from ``data`` (nested dictionaries for nested dataclasses; lists become tuples where
    the field is a tuple).

    Raises:
        InputError: ``data`` is not a dictionary, has keys that ``cls`` does not know, or values the
            dataclass refuses.
    """
    if not isinstance(data, dict):
        raise InputError(f"{where}: expected an object, got {type(data).__name__}")
    fields = {f.name: f for f in dataclasses.fields(cls)}
    unknown = sorted(set(data) - set(fields))
    if unknown:
        raise InputError(f"{where}: unknown key(s) {', '.join(unknown)}; known: {', '.join(fields)}")
    hints = typing.get_type_hints(cls)
    kwargs = {}
    for name, value in data.items():
        if not _fits(value, hints[name]):
            raise InputError(f"{where}.{name}: {value!r} is not a {_name(hints[name])}")
        sub = _dataclass_in(hints[name])
        if sub is not None and isinstance(value, dict):
            value = from_dict(sub, value, f"{where}.{name}")
        elif isinstance(value, list) and typing.get_origin(hints[name]) is tuple:
            value = tuple(value)
        kwargs[name] = value
    try:
        return cls(**kwargs)
    except (TypeError, ValueError) as exc:
        raise InputError(f"{where}: {exc}") from None


def _name(hint) -> str:
    if dataclasses.is_dataclass(hint):
        return "section (an object)"
    return getattr(hint, "__name__", None) or str(hint)


def merged(base: dict[str, Any], overrides: dict[str, Any]) -> dict[str, Any]:
    """``base`` with ``overrides`` applied, nested dictionaries merged key by key."""
    out = dict(base)
    for key, value in overrides.items():
        out[key] = merged(out[key], value) if isinstance(value, dict) and isinstance(out.get(key), dict) else value
    return out


# Named starting points for ``run --preset``: (what it suits, overrides of ``RunConfig()``). Each comes
# from a measured setting (docs/benchmarks.md); flags given with it still override it.
PRESETS: dict[str, tuple[str, dict]] = {
    "vggt": ("the paper's system: VGGT-1B submaps of 32 keyframes (a GPU is advised)",
             {"backbone": {"name": "vggt"}}),
    "synthetic": ("synthetic sequences from `synth` / `demo`: simulated backbone, submaps of 8 keyframes",
                  {"backbone": {"name": "simulated"},
                   "frontend": {"keyframes": {"tau_disparity": 20.0}, "submap_size": 8}}),
    "video-cpu": ("dense video without a GPU (EuRoC in bench frontend): COLMAP submaps of 32 keyframes",
                  {"backbone": {"name": "colmap"}, "frontend": {"submap_size": 32}}),
    "photos": ("photo walks and sparse keyframes (castle in bench frontend): COLMAP submaps of 8 photos",
               {"backbone": {"name": "colmap"}, "frontend": {"submap_size": 8}}),
}

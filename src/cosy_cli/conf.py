"""Stage configurations: named presets, user dicts and command-line overrides merged in one way."""

from __future__ import annotations

from typing import Mapping

from .errors import CosyError


def merge_conf(named: Mapping[str, dict], conf: str | Mapping | None, overrides: Mapping, *, default: str,
               what: str) -> dict:
    """A stage's settings: the preset ``conf`` names (or the ``default`` preset updated by the
    dict ``conf``), then the ``overrides`` that are not None. Keys the default preset lacks are a
    :class:`CosyError`; checking values stays with each stage."""
    if conf is None:
        conf = default
    if isinstance(conf, str):
        if conf not in named:
            raise CosyError(f"unknown {what} configuration {conf!r} (known: {', '.join(named)})")
        base = dict(named[conf])
    else:
        base = {**named[default], **dict(conf)}
    base.update({k: v for k, v in overrides.items() if v is not None})
    unknown = sorted(set(base) - set(named[default]))
    if unknown:
        raise CosyError(f"unknown {what} setting(s) {', '.join(unknown)} (known: {', '.join(named[default])})")
    return base


_TRUE = ("true", "yes", "on", "1")
_FALSE = ("false", "no", "off", "0")


def as_bool(value, key: str, what: str) -> bool:
    """A yes/no setting from a bool, 0 / 1, or a word (``true/false``, ``yes/no``, ``on/off``, any
    case), as ``--set stage.KEY=VALUE`` and settings files give it; anything else is a
    :class:`CosyError` naming the setting (``bool("false")`` would be True)."""
    if isinstance(value, bool):
        return value
    if isinstance(value, (int, float)) and value in (0, 1):
        return bool(value)
    if isinstance(value, str) and value.strip().lower() in _TRUE + _FALSE:
        return value.strip().lower() in _TRUE
    raise CosyError(f"{what} setting {key} = {value!r} is not a yes/no value (true/false, yes/no, on/off, 1/0)")

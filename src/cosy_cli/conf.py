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

"""Models shipped with cosy (``src/cosy_cli/assets/``) and how a stage picks the model it runs."""

from __future__ import annotations

from pathlib import Path

from .errors import CosyError

ASSETS = Path(__file__).resolve().parent / "assets"


def shipped(name: str) -> Path:
    """The path of a shipped asset (it may not exist yet), e.g. ``shipped("detector.onnx")``."""
    return ASSETS / name


def model_path(given, shipped_path: Path, kind: str, needed: bool) -> Path | None:
    """The model a stage runs: ``given`` (must exist), else the shipped one when present, else
    None, or a :class:`CosyError` when ``needed``. ``kind`` names the model in messages and in
    the hint (``cosy train <kind>`` + ``cosy export``)."""
    if given is not None:
        p = Path(given)
        if not p.is_file():
            raise CosyError(f"{kind} model not found: train one with `cosy train {kind}` and export it with "
                            "`cosy export`, or leave the option out to use the shipped model", path=p)
        return p
    if shipped_path.is_file():
        return shipped_path
    if needed:
        raise CosyError(f"no {kind} model was given and none is shipped with cosy (expected {shipped_path}); train one "
                        f"with `cosy train {kind}` + `cosy export`, or choose another method")
    return None

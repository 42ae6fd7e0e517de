"""Image files: RGB/gray (png, jpg, tif), 16-bit depth (value x depth_scale = mm), masks."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from ..errors import CosyError
from .atomic import atomic_path

IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".tif", ".tiff")


def _imread(path: Path, flags: int) -> np.ndarray:
    if not path.is_file():
        raise CosyError("image not found", path=path)
    data = np.fromfile(str(path), dtype=np.uint8)
    img = cv2.imdecode(data, flags) if data.size else None
    if img is None:
        raise CosyError("unreadable image (not a valid png/jpg/tif)", path=path)
    return img


def read_rgb(path: str | Path) -> np.ndarray:
    """(H, W, 3) uint8 RGB. Gray images are replicated to three channels."""
    img = _imread(Path(path), cv2.IMREAD_COLOR)
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)


def read_depth(path: str | Path, depth_scale: float = 1.0) -> np.ndarray:
    """(H, W) float32 depth in mm (0 = no measurement): stored value x ``depth_scale``."""
    path = Path(path)
    img = _imread(path, cv2.IMREAD_ANYDEPTH | cv2.IMREAD_UNCHANGED)
    if img.ndim != 2:
        raise CosyError(f"depth image must have one channel, got shape {img.shape}", path=path)
    return img.astype(np.float32) * np.float32(depth_scale)


def read_mask(path: str | Path) -> np.ndarray:
    """(H, W) bool mask (non-zero pixels)."""
    img = _imread(Path(path), cv2.IMREAD_GRAYSCALE)
    return img > 0


def photo_files(folder: str | Path) -> list[Path]:
    """The image files of ``folder`` (png, jpg, tif; sorted by name; not its subfolders); a missing
    folder or one without images is an error naming it."""
    folder = Path(folder)
    if not folder.is_dir():
        raise CosyError("folder of photographs not found", path=folder)
    files = sorted(p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_EXTENSIONS)
    if not files:
        raise CosyError(f"no image ({', '.join(IMAGE_EXTENSIONS)}) in this folder", path=folder)
    return files


def read_photo_folder(folder: str | Path, max_side: int = 800) -> list[np.ndarray]:
    """Every image of ``folder`` (:func:`photo_files`) as (H, W, 3) uint8 RGB, shrunk so that its
    longer side is at most ``max_side`` px."""
    out = []
    for f in photo_files(folder):
        img = read_rgb(f)
        s = max_side / max(img.shape[:2])
        if s < 1:
            img = cv2.resize(img, (max(1, round(img.shape[1] * s)), max(1, round(img.shape[0] * s))),
                             interpolation=cv2.INTER_AREA)
        out.append(img)
    return out


def image_size(path: str | Path) -> tuple[int, int]:
    """(width, height) read from the file header when possible (png by hand, jpg/tif by PIL), else by decoding."""
    path = Path(path)
    if not path.is_file():
        raise CosyError("image not found", path=path)
    if path.suffix.lower() == ".png":
        with open(path, "rb") as f:
            head = f.read(24)
        if len(head) == 24 and head[:8] == b"\x89PNG\r\n\x1a\n":
            return int.from_bytes(head[16:20], "big"), int.from_bytes(head[20:24], "big")
    else:
        try:
            from PIL import Image

            with Image.open(path) as im:
                return int(im.size[0]), int(im.size[1])
        except Exception:  # PIL raises several types on bad or unknown files: decode instead
            pass
    img = _imread(path, cv2.IMREAD_UNCHANGED)
    return img.shape[1], img.shape[0]


def fmt_size(wh) -> str:
    """``640x480`` for (width, height)."""
    return f"{int(wh[0])}x{int(wh[1])}"


def _imwrite(path: Path, img: np.ndarray, params: list[int] | None = None) -> None:
    with atomic_path(path) as tmp:
        ok, buf = cv2.imencode(path.suffix, img, params or [])
        if not ok:
            raise CosyError("could not encode image", path=path)
        buf.tofile(str(tmp))


def _photo_params(path: Path, jpg_quality: int) -> list[int]:
    """Encoder settings of a photo by its file name: JPEG quality, else PNG compression 6."""
    if path.suffix.lower() in (".jpg", ".jpeg"):
        return [cv2.IMWRITE_JPEG_QUALITY, jpg_quality]
    return [cv2.IMWRITE_PNG_COMPRESSION, 6]


def write_rgb(path: str | Path, rgb: np.ndarray, jpg_quality: int = 95) -> None:
    path = Path(path)
    img = cv2.cvtColor(np.asarray(rgb, dtype=np.uint8), cv2.COLOR_RGB2BGR)
    _imwrite(path, img, _photo_params(path, jpg_quality))


def write_gray(path: str | Path, rgb: np.ndarray, jpg_quality: int = 95) -> None:
    """Write an (H, W, 3) RGB or (H, W) image as a one-channel grey image (BT.601 luma)."""
    path = Path(path)
    img = np.asarray(rgb, dtype=np.uint8)
    if img.ndim == 3:
        img = cv2.cvtColor(img, cv2.COLOR_RGB2GRAY)
    _imwrite(path, img, _photo_params(path, jpg_quality))


def is_gray_file(path: str | Path) -> bool:
    """Whether an image file has one channel (read by :func:`read_rgb` as three equal channels)."""
    img = _imread(Path(path), cv2.IMREAD_UNCHANGED)
    return img.ndim == 2 or img.shape[2] == 1


def write_depth(path: str | Path, depth_mm: np.ndarray, depth_scale: float = 1.0) -> None:
    """Write depth in mm as a 16-bit png holding ``round(depth_mm / depth_scale)``."""
    d = np.round(np.asarray(depth_mm, dtype=np.float64) / depth_scale)
    if d.max(initial=0) > 65535:
        raise CosyError(f"depth {d.max() * depth_scale:.0f} mm does not fit 16 bits at depth_scale {depth_scale}", path=path)
    _imwrite(Path(path), np.clip(d, 0, 65535).astype(np.uint16), [cv2.IMWRITE_PNG_COMPRESSION, 6])


def write_mask(path: str | Path, mask: np.ndarray) -> None:
    _imwrite(Path(path), (np.asarray(mask) > 0).astype(np.uint8) * 255, [cv2.IMWRITE_PNG_COMPRESSION, 9])

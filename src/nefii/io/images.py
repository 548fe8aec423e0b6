"""Image files. Internally images are linear float32 ``(H, W, C)``; PNG/JPG are sRGB."""
from __future__ import annotations

from pathlib import Path

import numpy as np
from PIL import Image

from .atomic import atomic_path


def srgb_to_linear(x: np.ndarray) -> np.ndarray:
    """IEC 61966-2-1 decoding of values in [0, 1]."""
    x = np.asarray(x, dtype=np.float32)
    return np.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4).astype(np.float32)


def linear_to_srgb(x: np.ndarray) -> np.ndarray:
    """IEC 61966-2-1 encoding; clips to [0, 1] first."""
    x = np.clip(np.asarray(x, dtype=np.float32), 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1.0 / 2.4) - 0.055).astype(np.float32)


def to_uint8(x: np.ndarray) -> np.ndarray:
    return (np.clip(x, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)


def write_png(path: str | Path, image: np.ndarray, *, srgb: bool = True) -> None:
    """Write ``(H, W)``, ``(H, W, 3)`` or ``(H, W, 4)`` float data atomically.

    With ``srgb`` the colour channels (not alpha) are sRGB-encoded; otherwise written as is.
    """
    img = np.asarray(image, dtype=np.float32)
    if img.ndim == 3 and srgb:
        rgb = linear_to_srgb(img[..., :3])
        img = np.concatenate([rgb, img[..., 3:]], -1) if img.shape[-1] == 4 else rgb
    elif img.ndim == 2 and srgb:
        img = linear_to_srgb(img)
    with atomic_path(path) as tmp:
        Image.fromarray(to_uint8(img)).save(tmp, format="PNG")

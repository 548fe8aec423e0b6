"""OpenEXR images through the ``OpenEXR`` 3.x package (never imageio: it silently writes TIFF).

Images are ``(H, W)``, ``(H, W, 3)`` or ``(H, W, 4)`` linear float arrays. RGBA EXR holds
premultiplied alpha, as OpenEXR defines it.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import InputError
from .atomic import atomic_path

_LAYOUTS = {3: "RGB", 4: "RGBA"}


def write_exr(path: str | Path, image: np.ndarray, *, half: bool = False) -> None:
    """Write atomically, ZIP-compressed; ``half`` stores float16 (values beyond 65504 become inf)."""
    import OpenEXR

    img = np.ascontiguousarray(np.asarray(image, dtype=np.float16 if half else np.float32))
    if img.ndim == 2:
        channels = {"Y": img}
    elif img.ndim == 3 and img.shape[-1] in _LAYOUTS:
        channels = {_LAYOUTS[img.shape[-1]]: img}
    else:
        raise ValueError(f"write_exr wants (H,W), (H,W,3) or (H,W,4); got {img.shape}")
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    with atomic_path(path) as tmp, OpenEXR.File(header, channels) as f:
        f.write(str(tmp))


def read_exr(path: str | Path) -> np.ndarray:
    """Read an EXR as float32: ``(H, W, 3|4)`` for RGB(A) files, ``(H, W)`` for a single channel.

    Raises :class:`InputError` naming the file if it is missing or not a readable EXR.
    """
    import OpenEXR

    path = Path(path)
    if not path.is_file():
        raise InputError(path, "file not found")
    try:
        with OpenEXR.File(str(path)) as f:
            chans = {name: np.asarray(c.pixels) for name, c in f.channels().items()}
    except Exception as e:  # OpenEXR raises plain exceptions with C++ messages
        raise InputError(path, f"not a readable OpenEXR image ({type(e).__name__}: {e})") from None
    for key in ("RGBA", "RGB"):
        if key in chans:
            return chans[key].astype(np.float32)
    if len(chans) == 1:
        return next(iter(chans.values())).astype(np.float32)
    names = sorted(chans)
    if all(c in chans for c in "RGB"):
        order = [c for c in "RGBA" if c in chans]
        return np.stack([chans[c] for c in order], -1).astype(np.float32)
    raise InputError(path, f"EXR channels {names} are not Y, RGB or RGBA")

"""Reading the files datasets are made of; every failure is an :class:`InputError` naming the file.

Images come back as numpy: colour ``(H, W, 3)`` linear float32 straight (not premultiplied)
colour, alpha ``(H, W)`` float32 or ``None``. PNG/JPG colour is sRGB-decoded, alpha and
masks are not. EXR is linear; RGBA EXR is premultiplied (as OpenEXR defines it) and is
un-premultiplied where alpha > 0. PNG/JPG pixels at the top code value in any channel are
reported as clipped: a camera's sensor or encoder saturated there, so the scene was at least
that bright and its true value is unknown.
"""
from __future__ import annotations

import json
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import InputError
from ..io.exr import read_exr
from ..io.images import srgb_to_linear

IMAGE_SUFFIXES = (".exr", ".png", ".jpg", ".jpeg")
"""image files nefii reads, in the order a suffix-less name is resolved"""


CLIP_CODES = 1
"""code values below the top counted as clipped (8-bit: >= 254/255; 16-bit: >= 65534/65535): JPEG's
rounding leaves saturated pixels a code or so below the top"""


@dataclass(frozen=True)
class Image:
    """One image file as nefii uses it."""

    rgb: np.ndarray
    """``(H, W, 3)`` linear float32 straight colour"""
    alpha: np.ndarray | None
    """``(H, W)`` float32, or ``None`` without an alpha channel"""
    clipped: np.ndarray | None
    """``(H, W)`` bool: some channel at the top of an integer format's range (PNG/JPG); ``None`` for EXR"""


def _read_ldr(path: Path) -> tuple[np.ndarray, np.ndarray | None, int]:
    """PNG/JPG through Pillow -> (values in [0, 1] with 1 or 3 channels, alpha or None, the format's top
    code value: 255 or 65535); no sRGB decoding."""
    from PIL import Image, UnidentifiedImageError

    if not path.is_file():
        raise InputError(path, "file not found")
    try:
        with Image.open(path) as im:
            im.load()
            mode = im.mode
            if mode in ("I;16", "I;16B", "I;16L", "I"):  # 16-bit greyscale
                return np.asarray(im, dtype=np.float32)[..., None] / 65535.0, None, 65535
            has_alpha = mode in ("RGBA", "LA", "PA") or "transparency" in im.info
            im = im.convert("RGBA" if has_alpha else "RGB")
            arr = np.asarray(im, dtype=np.float32) / 255.0
    except (UnidentifiedImageError, OSError, ValueError, SyntaxError) as e:
        raise InputError(path, f"not a readable image ({type(e).__name__}: {e})") from None
    return (arr[..., :3], arr[..., 3], 255) if has_alpha else (arr, None, 255)


EXIF_IFD = 0x8769
EXPOSURE_TIME, F_NUMBER, ISO = 0x829A, 0x829D, 0x8827
"""EXIF tags: ExposureTime (s), FNumber, ISOSpeedRatings (in the Exif sub-IFD)"""


def read_exposure(path: str | Path) -> float | None:
    """A JPEG/PNG's exposure from its EXIF, as the light it lets through relative to 1 s at f/1, ISO 1:
    ``t * ISO / N^2`` (a missing ISO or f-number counts as 1: a phone's aperture is fixed); ``None``
    without an exposure time (EXR, or no EXIF). A value no camera writes (zero, negative, NaN, a time
    over an hour, an f-number under 0.5, ISO over 10^7) is an :class:`InputError` naming the file."""
    from PIL import Image as PILImage, UnidentifiedImageError

    path = Path(path)
    if path.suffix.lower() not in (".jpg", ".jpeg", ".png") or not path.is_file():
        return None  # a missing file is reported where its pixels are read
    try:
        with PILImage.open(path) as im:
            if im.format == "PNG":
                im.load()  # a PNG's eXIf chunk may follow its pixels
            tags = im.getexif().get_ifd(EXIF_IFD)
    except (UnidentifiedImageError, OSError, ValueError, SyntaxError) as e:
        raise InputError(path, f"not a readable image ({type(e).__name__}: {e})") from None
    if EXPOSURE_TIME not in tags:
        return None

    def value(tag: int, name: str, lo: float, hi: float) -> float:
        raw = tags.get(tag, 1.0)
        try:
            v = float(raw[0] if isinstance(raw, (tuple, list)) else raw)
        except (TypeError, ValueError, ZeroDivisionError):
            raise InputError(path, f"EXIF {name} is not a number ({raw!r})") from None
        if not (np.isfinite(v) and lo < v <= hi):
            raise InputError(path, f"EXIF {name} {v:g} is absurd (expected over {lo:g} and at most {hi:g})")
        return v

    t = value(EXPOSURE_TIME, "ExposureTime", 0.0, 3600.0)
    n = value(F_NUMBER, "FNumber", 0.5, 1000.0) if F_NUMBER in tags else 1.0
    iso = value(ISO, "ISOSpeedRatings", 0.0, 1e7) if ISO in tags else 1.0
    return t * iso / (n * n)


def read_image(path: str | Path) -> Image:
    """An image file -> :class:`Image` (linear straight colour, alpha, clipped pixels).

    Single-channel images are repeated to three channels. Raises :class:`InputError` for a
    missing or unreadable file, an unknown suffix, or NaN/inf values.
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix == ".exr":
        img = read_exr(path)
        if img.ndim == 2:
            img = img[..., None]
        alpha = img[..., 3] if img.shape[-1] == 4 else None
        rgb = img[..., :3] if img.shape[-1] >= 3 else np.repeat(img[..., :1], 3, -1)
        bad = int((~np.isfinite(img)).any(-1).sum())
        if bad:
            raise InputError(path, f"{bad} pixel(s) with NaN or infinite values")
        if alpha is not None:  # premultiplied -> straight colour
            rgb = np.where(alpha[..., None] > 0, rgb / np.where(alpha > 0, alpha, 1.0)[..., None], rgb)
        return Image(np.ascontiguousarray(rgb, dtype=np.float32), alpha, None)
    if suffix in (".png", ".jpg", ".jpeg"):
        values, alpha, top = _read_ldr(path)
        if values.shape[-1] == 1:
            values = np.repeat(values, 3, -1)
        clipped = (values >= (top - CLIP_CODES - 0.5) / top).any(-1)
        return Image(srgb_to_linear(values), alpha, clipped)
    raise InputError(path, f"unsupported image type '{path.suffix}' (nefii reads {', '.join(IMAGE_SUFFIXES)})")


def read_data_map(path: str | Path, channels: int, *, srgb: bool = False) -> np.ndarray:
    """A ground-truth map -> ``(H, W, channels)`` float32 (``channels`` 1 or 3), alpha dropped.

    EXR values are taken as stored (RGBA: divided by alpha where alpha > 0, as OpenEXR's alpha
    is premultiplied); PNG values are divided by 255 (16-bit: 65535) and sRGB-decoded only when
    ``srgb`` (colours such as albedo, not data such as roughness).
    """
    path = Path(path)
    if path.suffix.lower() == ".exr":
        img = read_exr(path)
        if img.ndim == 3 and img.shape[-1] == 4:
            a = img[..., 3:]
            img = np.where(a > 0, img[..., :3] / np.where(a > 0, a, 1.0), img[..., :3])
    else:
        img, _, _ = _read_ldr(path)
        if srgb:
            img = srgb_to_linear(img)
    if img.ndim == 2:
        img = img[..., None]
    img = img[..., :3]
    if not np.isfinite(img).all():
        raise InputError(path, f"{int((~np.isfinite(img)).any(-1).sum())} pixel(s) with NaN or infinite values")
    if channels == 1:
        return np.ascontiguousarray(img[..., :1], dtype=np.float32)
    return np.ascontiguousarray(img if img.shape[-1] == 3 else np.repeat(img[..., :1], 3, -1), dtype=np.float32)


def read_mask(path: str | Path) -> np.ndarray:
    """A mask image -> bool ``(H, W)``: alpha > 0.5 if it has a non-opaque alpha, else mean colour > 0.5."""
    path = Path(path)
    if path.suffix.lower() == ".exr":
        img = read_exr(path)
        img = img[..., None] if img.ndim == 2 else img
        if not np.isfinite(img).all():
            raise InputError(path, "mask has NaN or infinite values")
        alpha = img[..., 3] if img.shape[-1] == 4 else None
        values = img[..., :3]
    else:
        values, alpha, _ = _read_ldr(path)
    if alpha is not None and (alpha < 1.0).any():
        return alpha > 0.5
    return values.mean(-1) > 0.5


def read_json(path: str | Path) -> dict[str, Any]:
    """A JSON object; missing, unreadable or malformed files raise :class:`InputError`."""
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "file not found")
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except json.JSONDecodeError as e:
        raise InputError(path, f"malformed JSON at line {e.lineno} column {e.colno}: {e.msg}") from None
    except (OSError, UnicodeDecodeError) as e:
        raise InputError(path, f"cannot read ({type(e).__name__}: {e})") from None
    if not isinstance(data, dict):
        raise InputError(path, f"expected a JSON object at the top level, found {type(data).__name__}")
    return data


def read_npz(path: str | Path) -> dict[str, np.ndarray]:
    """All arrays of an ``.npz`` archive (no pickles); a bad archive raises :class:`InputError`."""
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "file not found")
    try:
        z = np.load(path, allow_pickle=False)
        if not isinstance(z, np.lib.npyio.NpzFile):
            raise ValueError("a single .npy array, not an .npz archive")
        with z:
            return {k: np.asarray(z[k]) for k in z.files}
    except (zipfile.BadZipFile, ValueError, OSError, EOFError, KeyError) as e:
        raise InputError(path, f"not a readable .npz archive ({type(e).__name__}: {e})") from None


def matrix(value: Any, shapes: tuple[tuple[int, ...], ...], path: Path, where: str) -> np.ndarray:
    """``value`` as a float64 array of one of ``shapes`` (a flat list is reshaped), else :class:`InputError`."""
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError(path, f"{where}: not a numeric matrix") from None
    for shape in shapes:
        if arr.shape == shape:
            return arr
        if arr.ndim == 1 and arr.size == int(np.prod(shape)):
            return arr.reshape(shape)
    want = " or ".join("x".join(map(str, s)) for s in shapes)
    raise InputError(path, f"{where}: expected a {want} matrix, got shape {arr.shape}")


def list_images(folder: Path) -> list[Path]:
    """Image files directly in ``folder``, sorted by name (hidden files skipped)."""
    return sorted(p for p in folder.iterdir()
                  if p.is_file() and not p.name.startswith(".") and p.suffix.lower() in IMAGE_SUFFIXES)


def resolve_image(base: Path, prefer: tuple[str, ...] = IMAGE_SUFFIXES) -> Path:
    """The image file for a NeRF-style ``file_path`` (with or without a suffix).

    A known image suffix is stripped first, then ``stem + suffix`` is tried for each suffix
    in ``prefer`` order: so ``r_0``, ``r_0.png`` and ``r_0.exr`` all give ``r_0.exr`` when it
    exists. Raises :class:`InputError` naming what was tried.
    """
    stem = base.with_suffix("") if base.suffix.lower() in IMAGE_SUFFIXES else base
    for suffix in prefer:
        cand = stem.with_name(stem.name + suffix)
        if cand.is_file():
            return cand
    raise InputError(stem, f"image file not found (tried {', '.join(prefer)})")

"""Undistorting photographs once, with OpenCV, into a cache folder beside the data.

    <root>/nefii_undistorted/undistorted.json    the key, and per view its files and new intrinsics
    <root>/nefii_undistorted/images/NNNNN_<name>.png|.exr
    <root>/nefii_undistorted/masks/NNNNN_<name>.png

A lens is a pinhole ``K`` plus OpenCV distortion: ``OPENCV`` (``k1, k2, p1, p2, k3``, Brown-Conrady)
or ``OPENCV_FISHEYE`` (``k1..k4``, equidistant; a fisheye is never a pinhole, even with every ``k``
zero). Each image is resampled onto a pinhole camera of the same size whose ``K`` OpenCV chooses so
that every output pixel sees the photograph: ``cv2.getOptimalNewCameraMatrix`` with alpha 0, or
``cv2.fisheye.estimateNewCameraMatrixForUndistortRectify`` with balance 0. Images are interpolated
bilinearly (in their stored values: sRGB codes for PNG/JPG, linear premultiplied for EXR), masks by
nearest neighbour. Outputs keep the image's bit depth and channels; PNG and JPG become PNG
(lossless), EXR stays EXR.

Pixel centres: nefii (like COLMAP and nerfstudio) puts pixel ``(i, j)``'s centre at ``(j + 0.5, i + 0.5)``,
OpenCV at ``(j, i)``; ``K`` is shifted by half a pixel on the way into OpenCV and back.

The folder is written whole or not at all (``io.atomic.atomic_dir``) and is reused while its key, a
hash of the capture's camera file (nerfstudio's ``transforms.json``, COLMAP's ``cameras.bin|txt``) and of
every image and mask file it undistorts, is unchanged; otherwise
it is rebuilt as a whole and one line says so.
"""
from __future__ import annotations

import hashlib
import json
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Literal, Sequence

import numpy as np

from ..errors import InputError
from ..io.atomic import atomic_dir
from ..io.exr import read_exr, write_exr
from .assemble import View, relative_name
from .fingerprint import file_sha256

Model = Literal["PINHOLE", "OPENCV", "OPENCV_FISHEYE"]

COEFFS: dict[str, tuple[str, ...]] = {"PINHOLE": (), "OPENCV": ("k1", "k2", "p1", "p2", "k3"),
                                      "OPENCV_FISHEYE": ("k1", "k2", "k3", "k4")}
"""each camera model's distortion coefficients, in OpenCV's order"""

CACHE_DIR = "nefii_undistorted"
MANIFEST = "undistorted.json"
CACHE_VERSION = 1
"""bumped when what the cache holds changes, so older caches are rebuilt"""

PIXEL_CENTRE = np.array([[1.0, 0.0, 0.5], [0.0, 1.0, 0.5], [0.0, 0.0, 1.0]])
"""``K_nefii = PIXEL_CENTRE @ K_opencv``: pixel ``(i, j)``'s centre is ``(j + 0.5, i + 0.5)`` to nefii, ``(j, i)`` to OpenCV"""


@dataclass(frozen=True)
class Lens:
    """A camera's intrinsics as the capture states them."""

    model: Model
    """``PINHOLE``, ``OPENCV`` or ``OPENCV_FISHEYE``"""
    K: np.ndarray
    """(3, 3) pinhole part in nefii's pixel convention"""
    coeffs: tuple[float, ...]
    """distortion coefficients, ``COEFFS[model]`` in that order"""
    width: int
    """image width in pixels, as the capture states it"""
    height: int
    """image height in pixels"""

    @property
    def distorted(self) -> bool:
        """Whether images need resampling to be pinhole images."""
        return self.model == "OPENCV_FISHEYE" or any(c != 0.0 for c in self.coeffs)

    def opencv(self) -> tuple[np.ndarray, np.ndarray, tuple[int, int]]:
        """``K`` in OpenCV's pixel convention, the coefficients, and the ``(width, height)`` OpenCV takes."""
        return np.linalg.inv(PIXEL_CENTRE) @ self.K, np.array(self.coeffs), (self.width, self.height)

    def describe(self) -> str:
        """``OPENCV, k1=-0.10`` (non-zero coefficients only)."""
        values = [f"{n}={c:.3g}" for n, c in zip(COEFFS[self.model], self.coeffs) if c != 0.0]
        return ", ".join([self.model] + values)


def undistorted_K(lens: Lens) -> np.ndarray:
    """The pinhole ``K`` (nefii's convention) OpenCV picks for the undistorted image, every pixel valid."""
    import cv2

    K_cv, D, size = lens.opencv()
    if lens.model == "OPENCV_FISHEYE":
        K_new = cv2.fisheye.estimateNewCameraMatrixForUndistortRectify(K_cv, D, size, np.eye(3), balance=0.0)
    else:
        K_new, _ = cv2.getOptimalNewCameraMatrix(K_cv, D, size, 0.0, size)
    return PIXEL_CENTRE @ np.asarray(K_new, dtype=np.float64)


def rectify_maps(lens: Lens, K_new: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per output pixel, where to sample the photograph (OpenCV's float maps, x and y)."""
    import cv2

    K_cv, D, size = lens.opencv()
    K_new_cv = np.linalg.inv(PIXEL_CENTRE) @ K_new
    if lens.model == "OPENCV_FISHEYE":
        return cv2.fisheye.initUndistortRectifyMap(K_cv, D, np.eye(3), K_new_cv, size, cv2.CV_32FC1)
    return cv2.initUndistortRectifyMap(K_cv, D, None, K_new_cv, size, cv2.CV_32FC1)


def remap(image: np.ndarray, maps: tuple[np.ndarray, np.ndarray], *, nearest: bool = False) -> np.ndarray:
    """``image`` resampled through ``maps``: bilinear, or nearest for masks; borders replicated."""
    import cv2

    return cv2.remap(image, maps[0], maps[1], cv2.INTER_NEAREST if nearest else cv2.INTER_LINEAR,
                     borderMode=cv2.BORDER_REPLICATE)


# ---------------------------------------------------------------------------- one file

def _read(path: Path) -> np.ndarray:
    """The stored values, unconverted: uint8/uint16 (OpenCV's BGR order, kept as is) or EXR float32."""
    import cv2

    if path.suffix.lower() == ".exr":
        return read_exr(path)
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)  # no EXIF rotation, as Pillow in files.py
    if img is None:
        raise InputError(path, "not a readable image")
    return img


def _write(path: Path, image: np.ndarray) -> None:
    import cv2

    path.parent.mkdir(parents=True, exist_ok=True)
    if path.suffix == ".exr":
        write_exr(path, image)
    elif not cv2.imwrite(str(path), image):
        raise InputError(path, "could not write the undistorted image")


def _out_name(i: int, source: Path) -> str:
    return f"{i:05d}_{source.stem}{'.exr' if source.suffix.lower() == '.exr' else '.png'}"


def check_lens_size(shape: tuple[int, ...], path: Path, lens: Lens, what: str, json_path: Path) -> None:
    """``shape[:2]`` (H, W) of the ``what`` (image or mask) in ``path`` must be the lens's size that
    ``json_path`` gives."""
    h, w = shape[:2]
    if (w, h) != (lens.width, lens.height):
        raise InputError(path, f"{what} is {w}x{h} but {json_path.name} gives w={lens.width}, h={lens.height}")


# ---------------------------------------------------------------------------- the cache

def _key(json_path: Path, items: Sequence[tuple[View, Lens]]) -> str:
    h = hashlib.sha256(f"nefii-undistorted/{CACHE_VERSION}".encode())
    h.update(file_sha256(json_path).encode())
    for view, _ in items:
        for f in (view.image, view.mask):
            h.update(b"-" if f is None else file_sha256(f).encode())
    return h.hexdigest()


def _reuse(folder: Path, key: str, n: int) -> list[tuple[View, np.ndarray]] | None:
    """The cached views and intrinsics if ``folder`` holds this key's complete output, else ``None``."""
    try:
        manifest = json.loads((folder / MANIFEST).read_text(encoding="utf-8"))
        if manifest.get("version") != CACHE_VERSION or manifest.get("key") != key or len(manifest["views"]) != n:
            return None
        out = []
        for v in manifest["views"]:
            image, mask = folder / v["image"], None if v["mask"] is None else folder / v["mask"]
            if not image.is_file() or (mask is not None and not mask.is_file()):
                return None
            out.append((View(image=image, mask=mask), np.array(v["K"], dtype=np.float64).reshape(3, 3)))
        return out
    except (OSError, ValueError, KeyError, TypeError):  # missing or damaged: rebuild
        return None


def pinhole_views(root: Path, key_file: Path, views: Sequence[View], lenses: Sequence[Lens]
                  ) -> tuple[list[View], list[np.ndarray]]:
    """Each view as a pinhole image and its ``K``: distorted ones from the cache (:func:`undistort_cached`,
    keyed by ``key_file``), the others as they are."""
    sources, Ks = list(views), [lens.K for lens in lenses]
    distorted = [i for i, lens in enumerate(lenses) if lens.distorted]
    if distorted:
        done = undistort_cached(root, key_file, [(views[i], lenses[i]) for i in distorted])
        for i, (view, K) in zip(distorted, done):
            sources[i], Ks[i] = view, K
    return sources, Ks


def undistort_cached(root: Path, json_path: Path, items: Sequence[tuple[View, Lens]]) -> list[tuple[View, np.ndarray]]:
    """Each ``(view, lens)`` as an undistorted view in ``root/nefii_undistorted`` and its pinhole ``K``.

    Reuses the folder when its key matches; otherwise undistorts everything into it (atomically) and
    prints one line to stderr. A missing or unreadable file, or an image or mask whose size is not
    the lens's, raises :class:`InputError` naming it (and leaves the folder as it was).
    """
    folder = root / CACHE_DIR
    key = _key(json_path, items)
    cached = _reuse(folder, key, len(items))
    if cached is not None:
        return cached
    maps: dict[tuple, tuple[np.ndarray, tuple[np.ndarray, np.ndarray]]] = {}
    records, out = [], []
    try:
        with atomic_dir(folder) as tmp:
            for i, (view, lens) in enumerate(items):
                lens_key = (lens.model, lens.K.tobytes(), lens.coeffs, lens.width, lens.height)
                if lens_key not in maps:
                    K_new = undistorted_K(lens)
                    maps[lens_key] = (K_new, rectify_maps(lens, K_new))
                K_new, lens_maps = maps[lens_key]
                image = _read(view.image)
                check_lens_size(image.shape, view.image, lens, "image", json_path)
                name = f"images/{_out_name(i, view.image)}"
                _write(tmp / name, remap(image, lens_maps))
                mask_name = None
                if view.mask is not None:
                    mask = _read(view.mask)
                    check_lens_size(mask.shape, view.mask, lens, "mask", json_path)
                    mask_name = f"masks/{_out_name(i, view.mask)}"
                    _write(tmp / mask_name, remap(mask, lens_maps, nearest=True))
                records.append({"source": relative_name(view.image, root), "image": name,
                                "mask": mask_name, "model": lens.model, "coeffs": list(lens.coeffs),
                                "K_distorted": lens.K.tolist(), "K": K_new.tolist()})
                out.append((View(image=folder / name, mask=None if mask_name is None else folder / mask_name), K_new))
            (tmp / MANIFEST).write_text(json.dumps({"version": CACHE_VERSION, "key": key, "source": json_path.name,
                                                    "views": records}, indent=1), encoding="utf-8")
    except OSError as e:
        raise InputError(folder, f"cannot write the undistorted images ({type(e).__name__}: {e})") from None
    lenses = sorted({lens.describe() for _, lens in items})
    models = sorted({lens.model for _, lens in items})
    said = lenses[0] if len(lenses) == 1 else f"{len(lenses)} lenses: {', '.join(models)}"
    print(f"nefii: undistorted {len(items)} images ({said}) into {folder}", file=sys.stderr)
    return out

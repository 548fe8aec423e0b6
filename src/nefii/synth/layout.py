"""Writing a synthetic scene's output folder (the layout of docs/datasets.md).

The RGBA images (``r_K.exr``, ``relight/<env>/r_K.exr``) are what the camera sees of the
object: pixel means of radiance with the background counted as 0, i.e. RGB premultiplied by
the coverage in A, as OpenEXR defines it. The ground-truth maps (``_albedo``, ``_roughness``,
``_specular``, ``_diffuse``, ``_normal``, ``_depth``) are RGB or Y without alpha and
*straight*: pixel means divided by the coverage the same render measured, 0 off the object,
so ``_specular + _diffuse`` is the straight colour of ``r_K.exr`` (up to Monte Carlo noise).
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ..camera import OPENGL_TO_OPENCV
from ..io.atomic import write_text_atomic
from ..io.exr import write_exr
from ..io.images import write_png

HALF_MAX = 65504.0


def straight(values: np.ndarray, alpha: np.ndarray, min_alpha: float = 1e-4) -> np.ndarray:
    """Un-premultiply pixel means by coverage; 0 where the pixel (almost) never saw the object."""
    a = alpha[..., None] if values.ndim == alpha.ndim + 1 else alpha
    return np.where(a > min_alpha, values / np.maximum(a, min_alpha), 0.0).astype(np.float32)


def write_rgba(folder: Path, stem: str, rgba: np.ndarray, png: bool = True) -> int:
    """``stem.exr`` (float16 RGBA, premultiplied) and ``stem.png`` (sRGB, straight alpha).

    Returns how many values had to be clipped to float16's maximum (65504).
    """
    clipped = int((rgba[..., :3] > HALF_MAX).sum())
    write_exr(folder / f"{stem}.exr", np.minimum(rgba, HALF_MAX), half=True)
    if png:
        alpha = np.clip(rgba[..., 3], 0.0, 1.0)
        write_png(folder / f"{stem}.png", np.concatenate([straight(rgba[..., :3], alpha), alpha[..., None]], -1))
    return clipped


def write_test_maps(folder: Path, stem: str, layers: dict[str, np.ndarray], mask: np.ndarray,
                    c2w_gl: np.ndarray) -> None:
    """The ground-truth maps of one test view from :meth:`MitsubaRenderer.render_layers`."""
    a = layers["alpha"]
    write_exr(folder / f"{stem}_albedo.exr", straight(layers["albedo"], a))
    write_exr(folder / f"{stem}_roughness.exr", straight(layers["roughness"], a))
    write_exr(folder / f"{stem}_specular.exr", straight(layers["specular"], a))
    write_exr(folder / f"{stem}_diffuse.exr", straight(layers["full"] - layers["specular"], a))
    n = straight(layers["normal"], a)
    n = n / np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-12)
    write_exr(folder / f"{stem}_normal.exr", n.astype(np.float32))
    write_exr(folder / f"{stem}_depth.exr", z_depth(straight(layers["position"], a), a, c2w_gl))
    write_png(folder / f"{stem}_mask.png", np.clip(mask, 0.0, 1.0), srgb=False)


def z_depth(position: np.ndarray, alpha: np.ndarray, c2w_gl: np.ndarray) -> np.ndarray:
    """Distance along the optical axis (OpenCV camera z) of world points; 0 off the object."""
    c2w_cv = np.asarray(c2w_gl, dtype=np.float64) @ OPENGL_TO_OPENCV.numpy()
    z = (position - c2w_cv[:3, 3]) @ c2w_cv[:3, 2]
    return np.where(alpha > 1e-4, z, 0.0).astype(np.float32)


def write_json(path: Path, data: dict) -> None:
    write_text_atomic(path, json.dumps(data, indent=2) + "\n")

"""A new environment to relight with: an equirectangular HDR file, turned about world +Z and exposed.

Files: ``.exr`` (OpenEXR, through :mod:`nefii.io.exr`) and ``.hdr`` (Radiance RGBE, through
OpenCV, which reads RLE and flat scanlines; imageio is not used: it is silently wrong for HDR).
Both are read in the one mapping of :mod:`nefii.render.equirect` (row 0 is +Z, +X at the
image centre, ``u = 0.5 - phi / 2 pi``).

* ``rotate`` (degrees) turns the environment about world +Z, **counter-clockwise seen from
  above**: a light at azimuth ``phi = atan2(y, x)`` moves to ``phi + rotate``, i.e. the image
  content rolls left by ``rotate / 360`` of its width. It is applied exactly, to directions,
  not by resampling the image: ``E_rot(w) = E(R_z(-rotate) w)``.
* ``exposure`` (EV) scales radiance by ``2^EV`` in linear space.

What is refused (:class:`InputError` naming the file, one line, exit 2): a missing file, an
unknown suffix, an unreadable file, NaN or infinite values, a map that is black everywhere.
What is only warned about: negative values (set to 0) and a map that is not 2:1 (lat-long maps
are; any other size is still read in the same mapping, stretched).
"""
from __future__ import annotations

import math
import warnings
from pathlib import Path

import numpy as np
import torch
from jaxtyping import Float

from ..errors import InputError
from ..io.exr import read_exr
from ..render.envmap import Environment

ENVMAP_SUFFIXES = (".exr", ".hdr")


# --------------------------------------------------------------------------- reading files


MAX_TOTAL_RADIANCE = 1e30
"""the largest sum of a map's pixels accepted: sampling sums them, and paths multiply radiance by ratios of
pdfs; float32 ends at 3.4e38 (a map at 3e38 rendered a black object)"""


def _read_hdr(path: Path) -> np.ndarray:
    import cv2

    img = cv2.imread(str(path), cv2.IMREAD_ANYDEPTH | cv2.IMREAD_COLOR)
    if img is None or img.ndim != 3 or img.shape[-1] != 3:
        raise InputError(path, "not a readable Radiance HDR (RGBE) image")
    return np.ascontiguousarray(img[..., ::-1], dtype=np.float32)   # OpenCV gives BGR


def read_envmap(path: str | Path) -> Float[np.ndarray, "H W 3"]:
    """The file's linear RGB radiance ``(H, W, 3)`` float32, checked (see the module docstring)."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in ENVMAP_SUFFIXES:
        raise InputError(path, f"unsupported environment map format '{path.suffix}': use .exr or .hdr")
    if not path.is_file():
        raise InputError(path, "file not found")
    img = read_exr(path) if suffix == ".exr" else _read_hdr(path)
    if img.ndim == 2:
        img = np.repeat(img[..., None], 3, -1)
    img = img[..., :3]                                   # an alpha channel carries no light
    if img.shape[0] < 1 or img.shape[1] < 1:
        raise InputError(path, f"empty image ({img.shape[1]}x{img.shape[0]})")
    bad = int((~np.isfinite(img)).any(-1).sum())
    if bad:
        raise InputError(path, f"{bad} pixel(s) are NaN or infinite")
    if (img < 0).any():
        warnings.warn(f"{path}: {int((img < 0).any(-1).sum())} pixel(s) with negative radiance set to 0",
                      stacklevel=2)
        img = np.maximum(img, 0.0)
    if not img.any():
        raise InputError(path, "black everywhere: nothing to light with")
    h, w = img.shape[:2]
    if w != 2 * h:
        warnings.warn(f"{path}: {w}x{h} is not a 2:1 lat-long map; read in the same mapping (stretched)",
                      stacklevel=2)
    return np.ascontiguousarray(img, dtype=np.float32)


def load_environment(path: str | Path, rotate: float = 0.0, exposure: float = 0.0,
                     device: torch.device | str = "cpu", dtype: torch.dtype = torch.float32) -> Environment:
    """Read ``path`` (.exr or .hdr), scale by ``2^exposure``, turn by ``rotate`` degrees about +Z."""
    if not (math.isfinite(rotate) and math.isfinite(exposure)):
        raise InputError(None, f"--rotate {rotate} / --exposure {exposure}: must be finite numbers")
    return environment_from_radiance(torch.from_numpy(read_envmap(path)), path, rotate, exposure, device, dtype)


def environment_from_radiance(image: Float[torch.Tensor, "H W 3"], source: str | Path, rotate: float = 0.0,
                              exposure: float = 0.0, device: torch.device | str = "cpu",
                              dtype: torch.dtype = torch.float32) -> Environment:
    """A map already in memory (a file's, or a dataset's ``Relit`` map) as light: negative radiance set to 0,
    scaled by ``2^exposure``, turned by ``rotate`` degrees about +Z; ``source`` names it in errors (black
    everywhere, overflow)."""
    img = image.to(device=device, dtype=dtype).clamp_min(0.0) * (2.0 ** exposure)
    if not bool(torch.isfinite(img).all()):
        raise InputError(source, f"--exposure {exposure:g} makes the radiance overflow {dtype}")
    if not bool((img > 0).any()):
        raise InputError(source, "black everywhere: nothing to light with")
    total = float(img.double().sum())
    if total > MAX_TOTAL_RADIANCE:
        ev = math.ceil(math.log2(total / MAX_TOTAL_RADIANCE))
        raise InputError(source, f"radiance summing to {total:.3g} overflows the path tracer's float arithmetic "
                                 f"(at most {MAX_TOTAL_RADIANCE:g}); scale it down, e.g. --exposure {exposure - ev:g}")
    return Environment.from_image(img, rotate)

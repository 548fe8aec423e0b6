"""Deterministic tileable noise for procedural textures and skies.

A noise *tile* is white noise from numpy's PCG64 (fixed by a seed), shaped in the Fourier
domain to a power-law spectrum ``|k|^-exponent`` (fractal, like fBm; 3 gives cloud-like
fields), standardised and passed through the normal CDF so its values are spread evenly
over [0, 1]: thresholding at ``1 - c`` covers a fraction ``c``. Tiles are periodic, so
:func:`noise2` can look one up at any point of the plane by bilinear interpolation; that
costs a few gathers per point, whatever the detail, and the tile is made once per seed.
"""
from __future__ import annotations

import math
from functools import lru_cache

import numpy as np
import torch
from jaxtyping import Float
from torch import Tensor

TILE = 512
"""texels along each side of a noise tile"""


@lru_cache(maxsize=64)
def noise_tile(seed: int, exponent: float = 3.0, size: int = TILE) -> Tensor:
    """``(size, size)`` periodic fractal noise in [0, 1], the same on every machine for a seed."""
    rng = np.random.default_rng(np.random.SeedSequence([0x6E656669, seed]))
    white = rng.standard_normal((size, size))
    k = np.fft.fftfreq(size) * size
    kk = np.sqrt(k[:, None] ** 2 + k[None, :] ** 2)
    amplitude = np.where(kk > 0, np.maximum(kk, 1.0) ** (-exponent / 2.0), 0.0)
    field = np.fft.ifft2(np.fft.fft2(white) * amplitude).real
    z = torch.from_numpy((field - field.mean()) / field.std())
    return (0.5 * (1.0 + torch.erf(z / math.sqrt(2.0)))).to(torch.float32)


def noise2(xy: Float[Tensor, "*bs 2"], seed: int, exponent: float = 3.0) -> Float[Tensor, "*bs"]:
    """Bilinear lookup of :func:`noise_tile` at plane points ``xy``; one tile spans 1 x 1 units."""
    tile = noise_tile(seed, exponent)
    n = tile.shape[0]
    p = xy.to(torch.float32) * n - 0.5
    p0 = torch.floor(p)
    f = p - p0
    i = p0.to(torch.int64) % n
    x0, y0 = i[..., 0], i[..., 1]
    x1, y1 = (x0 + 1) % n, (y0 + 1) % n
    fx, fy = f[..., 0], f[..., 1]
    top = tile[y0, x0] * (1.0 - fx) + tile[y0, x1] * fx
    bottom = tile[y1, x0] * (1.0 - fx) + tile[y1, x1] * fx
    return top * (1.0 - fy) + bottom * fy


def smoothstep(e0: float, e1: float, x: Tensor) -> Tensor:
    """Hermite step from 0 at ``e0`` to 1 at ``e1``."""
    t = ((x - e0) / (e1 - e0)).clamp(0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)

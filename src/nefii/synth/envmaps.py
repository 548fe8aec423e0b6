"""Baking a procedural :class:`~nefii.synth.skies.Environment` onto a lat-long texel grid.

A :class:`Grid` says where its texels are: the direction of each texel centre, the texel a
direction falls in, and each row's solid angle. Baking takes the smooth background at the
texel centres and *splats* the sun disc: 65,536 directions spread evenly over the disc's
solid angle are dropped into the texels they fall in, so a texel gets the fraction of its
solid angle the sun covers and the sun's power is exact (to 1/65536) on any grid, even one
whose texels are larger than the sun. Two grids are used: nefii's equirect
(:func:`equirect_grid`, pixel centres of :mod:`nefii.render.equirect`, the files we write) and
the pole-to-pole grid Mitsuba's ``envmap`` reads (:func:`nefii.synth.mitsuba_backend.mitsuba_grid`).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

import numpy as np
import torch
from jaxtyping import Float
from torch import Tensor

from ..render.equirect import direction_to_pixel, direction_to_uv, pixel_directions, pixel_solid_angles
from ..render.frame import Frame
from .skies import Environment

ENVMAP_HEIGHT, ENVMAP_WIDTH = 1024, 2048
"""ground-truth map size: 0.18 deg texels, so a 1 deg sun spans about 5 texels"""
SUN_SAMPLES = 1 << 16
GOLDEN_ANGLE = math.pi * (3.0 - math.sqrt(5.0))


@dataclass(frozen=True)
class Grid:
    """Where the texels of an ``height x width`` lat-long image are."""

    height: int
    width: int
    centres: Callable[[], Tensor]
    """() -> (H, W, 3) float64 unit direction of every texel centre"""
    texel_of: Callable[[Tensor], tuple[Tensor, Tensor]]
    """(*bs, 3) directions -> (row, col) of the texel each falls in"""
    row_solid_angle: Callable[[], Tensor]
    """() -> (H,) float64 solid angle of one texel of each row"""


def equirect_grid(height: int, width: int) -> Grid:
    """nefii's mapping (:mod:`nefii.render.equirect`): pixel ``(i, j)`` covers its own cell."""
    return Grid(height, width, lambda: pixel_directions(height, width, dtype=torch.float64),
                lambda d: direction_to_pixel(d, height, width),
                lambda: pixel_solid_angles(height, width, dtype=torch.float64)[:, 0])


def bake(env: Environment, grid: Grid, *, rows_per_chunk: int = 64) -> np.ndarray:
    """``(H, W, 3)`` float32 texels: background at the centres, the sun disc splatted exactly."""
    dirs = grid.centres()
    out = torch.empty(grid.height, grid.width, 3, dtype=torch.float32)
    for i0 in range(0, grid.height, rows_per_chunk):
        out[i0:i0 + rows_per_chunk] = env.background(dirs[i0:i0 + rows_per_chunk].float())
    if env.sun is not None:
        _splat_sun(out, env, grid)
    return out.numpy()


def sun_directions(env: Environment, n: int = SUN_SAMPLES) -> Tensor:
    """``(n, 3)`` float64 directions evenly spread over the sun disc (a Fibonacci spiral on the cap)."""
    sun = env.sun
    k = torch.arange(n, dtype=torch.float64) + 0.5
    cos_a = 1.0 - (1.0 - sun.cos_radius) * k / n  # equal solid angle per sample
    sin_a = torch.sqrt((1.0 - cos_a * cos_a).clamp_min(0.0))
    phi = GOLDEN_ANGLE * k
    local = torch.stack([sin_a * torch.cos(phi), sin_a * torch.sin(phi), cos_a], -1)
    frame = Frame.from_normal(torch.tensor(sun.direction, dtype=torch.float64))
    return frame.to_world(local)


def _splat_sun(out: Tensor, env: Environment, grid: Grid) -> None:
    """Blend the sun into each texel by the fraction of the texel's solid angle it covers."""
    d = sun_directions(env)
    row, col = grid.texel_of(d)
    covered = torch.zeros(grid.height * grid.width, dtype=torch.float64)
    covered.index_add_(0, row * grid.width + col, torch.full((len(d),), env.sun.solid_angle() / len(d),
                                                             dtype=torch.float64))
    covered = covered.reshape(grid.height, grid.width)
    frac = (covered / grid.row_solid_angle()[:, None]).clamp(max=1.0).float().unsqueeze(-1)
    sun_rgb = torch.tensor(env.sun.radiance, dtype=torch.float32)
    out.mul_(1.0 - frac).add_(sun_rgb * frac)


def bake_equirect(env: Environment, height: int = ENVMAP_HEIGHT, width: int = ENVMAP_WIDTH) -> np.ndarray:
    """Ground-truth map in nefii's mapping: the background at
    :func:`nefii.render.equirect.pixel_directions`, the sun integrated over each pixel's cell."""
    return bake(env, equirect_grid(height, width))


def sample_equirect(image: np.ndarray, d: Float[Tensor, "*bs 3"]) -> Float[Tensor, "*bs C"]:
    """Bilinear lookup of a nefii equirect map at world directions (wraps in u, clamps in v)."""
    img = torch.as_tensor(image, dtype=torch.float32)
    H, W = img.shape[:2]
    u, v = direction_to_uv(d.to(torch.float64))
    x, y = u * W - 0.5, (v * H - 0.5).clamp(0.0, H - 1.0)
    x0, y0 = torch.floor(x), torch.floor(y).clamp(max=H - 2)
    fx, fy = (x - x0).float().unsqueeze(-1), (y - y0).float().unsqueeze(-1)
    x0, y0 = x0.long() % W, y0.long()
    x1 = (x0 + 1) % W
    top = img[y0, x0] * (1 - fx) + img[y0, x1] * fx
    bottom = img[y0 + 1, x0] * (1 - fx) + img[y0 + 1, x1] * fx
    return top * (1 - fy) + bottom * fy

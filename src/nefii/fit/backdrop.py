"""A backdrop is not the sky: background pixels of one constant colour are left out of the light's fit.

Datasets made for NeRF often ship their images composited over white or black (`white_bkgd`), with no alpha.
Their background pixels then say that the environment is that colour in every direction the views see past the
object, and Eq. 7's third term and the light's start believe it: on 2026-11-30 the corner composited over white
fitted to 18.6 dB albedo and roughness MSE 0.058, over black to 25.0 dB, against 29.6 dB and 0.016 from the same
renders with their alpha (docs/experiments.md). A real sky, room or capture is never one colour to within a few
percent over 95% of the pixels, so such a background is taken for a backdrop: its pixels are dropped (the fit
then learns the light from the object alone, as for a transparent render), and so are the object pixels the
silhouette crosses, since their colour mixes the object with the backdrop, not with the environment the fit
renders past the silhouette.
"""
from __future__ import annotations

import dataclasses

import torch
from jaxtyping import Float
from torch import Tensor

from .pixels import Pixels

SHARE = 0.95
"""the share of the background pixels that must lie within :data:`TOLERANCE` of their median colour"""
TOLERANCE = (0.01, 0.02)
"""(absolute, relative to the median) in linear colour, per channel"""
SAMPLE = 1 << 20
"""at most this many background pixels (every k-th) are read"""


def backdrop_colour(rgb: Float[Tensor, "Q 3"]) -> Float[Tensor, "3"] | None:
    """The colour of a constant backdrop, or None where the background pixels ``rgb`` are not one colour (or there
    are none)."""
    if len(rgb) == 0:
        return None
    seen = rgb[:: -(-len(rgb) // SAMPLE)].float()
    median = seen.median(0).values
    near = ((seen - median).abs() <= TOLERANCE[0] + TOLERANCE[1] * median.abs()).all(-1)
    return median if float(near.float().mean()) >= SHARE else None


def without_backdrop(pixels: Pixels) -> tuple[Pixels, Float[Tensor, "3"] | None]:
    """``pixels`` with their background pixels and their edge pixels dropped where the background is a constant
    backdrop, and its colour (None, and ``pixels`` as they are, otherwise)."""
    colour = backdrop_colour(pixels.bg_rgb)
    if colour is None:
        return pixels, None
    pixels = pixels.without_edges()
    return dataclasses.replace(pixels, bg_dirs=pixels.bg_dirs[:0], bg_rgb=pixels.bg_rgb[:0],
                               bg_view=pixels.bg_view[:0]), colour

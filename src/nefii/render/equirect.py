"""The one mapping between world directions and equirectangular (lat-long) pixels.

Convention (docs/design.md, identical to Blender's default world mapping):
world +Z is up; ``theta = acos(z)`` is the polar angle from +Z and
``phi = atan2(y, x)`` the azimuth. Texture coordinates ``u, v`` in [0, 1):

    u = 0.5 - phi / (2 pi)   (mod 1)     columns:  +X at u = 0.5, +Y at 0.25, -Y at 0.75, -X at the seam
    v = theta / pi                       rows:     row 0 is +Z (zenith), the last row is -Z

Pixel ``(row i, col j)`` of an ``H x W`` image covers ``[j, j+1) / W`` in ``u`` and
``[i, i+1) / H`` in ``v``; its centre is at ``((j + 0.5) / W, (i + 0.5) / H)``.
Every reader, writer, sampler and renderer of environment maps goes through these functions.
"""
from __future__ import annotations

import math

import torch
from jaxtyping import Float
from torch import Tensor

from .frame import normalize


def direction_to_uv(d: Float[Tensor, "*bs 3"]) -> tuple[Float[Tensor, "*bs"], Float[Tensor, "*bs"]]:
    """World direction (need not be unit) -> ``(u, v)`` in [0, 1)."""
    d = normalize(d)
    x, y, z = d.unbind(-1)
    phi = torch.atan2(y, x)
    u = torch.remainder(0.5 - phi / (2.0 * math.pi), 1.0)
    v = torch.atan2(torch.hypot(x, y), z) / math.pi  # = acos(z) / pi, precise near the poles
    return u, v


def uv_to_direction(u: Float[Tensor, "*bs"], v: Float[Tensor, "*bs"]) -> Float[Tensor, "*bs 3"]:
    """``(u, v)`` -> unit world direction; inverse of :func:`direction_to_uv`."""
    phi = 2.0 * math.pi * (0.5 - u)
    theta = math.pi * v
    st = torch.sin(theta)
    return torch.stack([st * torch.cos(phi), st * torch.sin(phi), torch.cos(theta)], -1)


def direction_to_pixel(d: Float[Tensor, "*bs 3"], height: int, width: int) -> tuple[Tensor, Tensor]:
    """World direction -> integer ``(row, col)`` of the pixel that contains it."""
    u, v = direction_to_uv(d)
    col = (u * width).long().clamp(0, width - 1)
    row = (v * height).long().clamp(0, height - 1)
    return row, col


def pixel_directions(height: int, width: int, *, device: torch.device | str | None = None,
                     dtype: torch.dtype = torch.float32) -> Float[Tensor, "H W 3"]:
    """Unit direction through the centre of every pixel."""
    v = (torch.arange(height, device=device, dtype=dtype) + 0.5) / height
    u = (torch.arange(width, device=device, dtype=dtype) + 0.5) / width
    vv, uu = torch.meshgrid(v, u, indexing="ij")
    return uv_to_direction(uu, vv)


def pixel_solid_angles(height: int, width: int, *, device: torch.device | str | None = None,
                       dtype: torch.dtype = torch.float32) -> Float[Tensor, "H 1"]:
    """Exact solid angle of each pixel row: ``(2 pi / W) (cos theta_top - cos theta_bottom)``."""
    edges = torch.arange(height + 1, device=device, dtype=dtype) * (math.pi / height)
    return ((2.0 * math.pi / width) * (torch.cos(edges[:-1]) - torch.cos(edges[1:]))).unsqueeze(-1)

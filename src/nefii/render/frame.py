"""Vectors and local shading frames.

Shapes: ``*bs`` is any batch shape; vectors have a trailing axis of 3.
A local frame has its z axis along the shading normal ``n``; directions in
local coordinates are written ``(x, y, z)`` with ``z = cos(theta)``.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
from jaxtyping import Float
from torch import Tensor


def dot(a: Float[Tensor, "*bs 3"], b: Float[Tensor, "*bs 3"]) -> Float[Tensor, "*bs"]:
    """Inner product over the last axis (broadcasting)."""
    return (a * b).sum(-1)


def normalize(v: Float[Tensor, "*bs 3"], eps: float = 1e-12) -> Float[Tensor, "*bs 3"]:
    """``v / |v|``, with ``eps`` guarding the zero vector."""
    return v / v.norm(dim=-1, keepdim=True).clamp_min(eps)


def reflect(v: Float[Tensor, "*bs 3"], h: Float[Tensor, "*bs 3"]) -> Float[Tensor, "*bs 3"]:
    """Mirror ``v`` about the unit vector ``h``: ``2 (v.h) h - v`` (both point away from the surface)."""
    return 2.0 * dot(v, h).unsqueeze(-1) * h - v


@dataclass(frozen=True)
class Frame:
    """Orthonormal basis ``(t, b, n)``; ``n`` is the local z axis."""

    t: Float[Tensor, "*bs 3"]
    b: Float[Tensor, "*bs 3"]
    n: Float[Tensor, "*bs 3"]

    @staticmethod
    def from_normal(n: Float[Tensor, "*bs 3"]) -> "Frame":
        """Branchless basis of Duff et al. 2017 (JCGT 6(1)), continuous except at ``n.z = 0`` sign flips."""
        x, y, z = n.unbind(-1)
        sign = torch.where(z >= 0, torch.ones_like(z), -torch.ones_like(z))
        a = -1.0 / (sign + z)
        k = x * y * a
        t = torch.stack([1.0 + sign * x * x * a, sign * k, -sign * x], -1)
        b = torch.stack([k, sign + y * y * a, -y], -1)
        return Frame(t, b, n)

    def unsqueeze(self, dim: int) -> "Frame":
        """Insert a broadcast axis into every basis vector (``dim`` as for the (*bs, 3) tensors, e.g. -2)."""
        return Frame(self.t.unsqueeze(dim), self.b.unsqueeze(dim), self.n.unsqueeze(dim))

    def to_local(self, v: Float[Tensor, "*bs 3"]) -> Float[Tensor, "*bs 3"]:
        return torch.stack([dot(v, self.t), dot(v, self.b), dot(v, self.n)], -1)

    def to_world(self, v: Float[Tensor, "*bs 3"]) -> Float[Tensor, "*bs 3"]:
        x, y, z = v.unbind(-1)
        return x.unsqueeze(-1) * self.t + y.unsqueeze(-1) * self.b + z.unsqueeze(-1) * self.n


def spherical_direction(cos_theta: Float[Tensor, "*bs"], phi: Float[Tensor, "*bs"],
                        sin_theta: Float[Tensor, "*bs"] | None = None) -> Float[Tensor, "*bs 3"]:
    """Unit vector with polar cosine ``cos_theta`` about +z and azimuth ``phi`` from +x."""
    if sin_theta is None:
        sin_theta = (1.0 - cos_theta * cos_theta).clamp_min(0.0).sqrt()
    return torch.stack([sin_theta * torch.cos(phi), sin_theta * torch.sin(phi), cos_theta], -1)

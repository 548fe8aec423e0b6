"""A dataset's ground-truth material (``material.npz`` beside ``mesh.ply``, written by ``nefii synth``),
looked up at any point of the mesh's surface: what the error budget substitutes for the learned field.

The textures follow Mitsuba's bitmap convention (``u`` along columns, ``v`` along rows downwards, texel
centres at ``(k + 0.5) / size``), read bilinearly with clamped borders, as the renderer read them.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from jaxtyping import Float, Int
from torch import Tensor

from ..errors import InputError
from ..raycast import MeshGeometry, Rays
from ..render.brdf import Material


@dataclass(frozen=True)
class TexturedMaterial:
    """Per-vertex texture coordinates of a mesh and its albedo and roughness bitmaps."""

    uv: Float[Tensor, "V 2"]
    base_color: Float[Tensor, "H W 3"]
    """linear RGB diffuse albedo"""
    roughness: Float[Tensor, "H W"]
    """perceptual roughness (GGX alpha = r^2)"""

    def lookup(self, uv: Float[Tensor, "B 2"]) -> Material:
        """Bilinear lookup at texture coordinates ``uv``."""
        H, W = self.roughness.shape
        maps = torch.cat([self.base_color, self.roughness.unsqueeze(-1)], -1).to(uv)
        x = (uv[:, 0] * W - 0.5).clamp(0, W - 1)
        y = (uv[:, 1] * H - 0.5).clamp(0, H - 1)
        x0, y0 = x.floor().long().clamp(max=W - 2), y.floor().long().clamp(max=H - 2)
        fx, fy = (x - x0).unsqueeze(-1), (y - y0).unsqueeze(-1)
        top = maps[y0, x0] * (1 - fx) + maps[y0, x0 + 1] * fx
        bottom = maps[y0 + 1, x0] * (1 - fx) + maps[y0 + 1, x0 + 1] * fx
        v = top * (1 - fy) + bottom * fy
        return Material(albedo=v[:, :3], roughness=v[:, 3])

    def at_hits(self, mesh: MeshGeometry, triangle: Int[Tensor, " B"], position: Float[Tensor, "B 3"]) -> Material:
        """The material at points ``position`` on triangles ``triangle`` of ``mesh`` (the mesh it belongs to)."""
        faces = torch.from_numpy(mesh.faces.astype(np.int64)).to(triangle.device)[triangle]     # (B, 3)
        p = torch.from_numpy(mesh.vertices).to(position)[faces]                               # (B, 3, 3)
        bary = barycentrics(p, position)
        uv = (self.uv.to(position)[faces] * bary.unsqueeze(-1)).sum(-2)
        return self.lookup(uv)


def barycentrics(corners: Float[Tensor, "B 3 3"], x: Float[Tensor, "B 3"]) -> Float[Tensor, "B 3"]:
    """Barycentric coordinates of ``x`` (projected onto the triangle's plane) in triangles ``corners``."""
    a, b, c = corners.unbind(-2)
    e0, e1, d = b - a, c - a, x - a
    d00, d01, d11 = (e0 * e0).sum(-1), (e0 * e1).sum(-1), (e1 * e1).sum(-1)
    d20, d21 = (d * e0).sum(-1), (d * e1).sum(-1)
    den = (d00 * d11 - d01 * d01).clamp_min(1e-30)
    v = (d11 * d20 - d01 * d21) / den
    w = (d00 * d21 - d01 * d20) / den
    return torch.stack([1 - v - w, v, w], -1)


def load_material(root: str | Path) -> TexturedMaterial:
    """``root/material.npz``; raises InputError naming the file if it is missing or malformed."""
    path = Path(root) / "material.npz"
    if not path.is_file():
        raise InputError(path, "not found: only scenes made by `nefii synth` carry their ground-truth material")
    try:
        with np.load(path) as z:
            uv, base, rough = z["uv"], z["base_color"], z["roughness"]
    except Exception as e:
        raise InputError(path, f"not a readable material file ({type(e).__name__}: {e})") from None
    if uv.ndim != 2 or uv.shape[1] != 2 or base.ndim != 3 or base.shape[2] != 3 or rough.shape != base.shape[:2]:
        raise InputError(path, f"unexpected shapes uv {uv.shape}, base_color {base.shape}, roughness {rough.shape}")
    return TexturedMaterial(torch.from_numpy(uv).float(), torch.from_numpy(base).float(),
                            torch.from_numpy(rough).float())


class MaterialOnMesh:
    """The textured material at arbitrary points of ``mesh``'s surface, given their outward normals: a short
    ray cast back onto the surface along ``-n`` finds the triangle (``(x, n) -> Material``)."""

    def __init__(self, material: TexturedMaterial, mesh: MeshGeometry) -> None:
        self.material, self.mesh = material, mesh

    def __call__(self, position: Float[Tensor, "B 3"], normal: Float[Tensor, "B 3"]) -> Material:
        eps = 1e-4 * self.mesh.scale
        n = normal / normal.norm(dim=-1, keepdim=True).clamp_min(1e-12)
        hit = self.mesh.intersect(Rays(position + eps * n, -n))
        tri = torch.where(hit.valid, hit.triangle_id, torch.zeros_like(hit.triangle_id))
        return self.material.at_hits(self.mesh, tri, torch.where(hit.valid.unsqueeze(-1), hit.position, position))

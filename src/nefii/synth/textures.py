"""Procedural bitmap textures: pattern functions over tile coordinates and the texture atlas.

A part's material is two functions of its texture coordinates ``(s, t)`` in [0, 1]:
linear RGB base colour and perceptual roughness. :func:`build_atlas` bakes every part's
material into one tile of a shared atlas (one base-colour and one roughness bitmap for the
whole scene) and remaps the part's texture coordinates into its tile. Tiles have a gutter
of clamped texels so bilinear lookups never bleed between parts.

Atlas texture coordinates follow Mitsuba's mesh/bitmap convention: ``u`` along columns,
``v`` along rows **downwards** (row = v * H), texel centres at ``(k + 0.5) / size``.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

import numpy as np
import torch
from torch import Tensor

from .meshes import TriMesh, merge
from .noise import noise2, smoothstep

Pattern = Callable[[Tensor, Tensor], Tensor]
"""``(s, t) -> values``: ``(*bs, 3)`` for colour, ``(*bs,)`` for roughness"""

ROUGHNESS_RANGE = (0.1, 0.95)
"""every roughness texel is clamped into this range (nefii's BRDF floor is 0.089)"""
ALBEDO_RANGE = (0.03, 0.9)


@dataclass(frozen=True)
class ProceduralMaterial:
    """Principled BSDF inputs of one part (specular 0.5, metallic 0 are fixed scene-wide)."""

    base_color: Pattern
    """linear RGB base colour (the diffuse albedo)"""
    roughness: Pattern
    """perceptual roughness r (GGX alpha = r^2)"""


# ---------------------------------------------------------------- pattern pieces

def rgb(*c: float) -> Tensor:
    return torch.tensor(c, dtype=torch.float32)


def mix(a: Tensor, b: Tensor, w: Tensor) -> Tensor:
    """Blend colours ``a`` -> ``b`` (``(3,)`` or ``(*bs, 3)``) by weight ``w`` ``(*bs,)``."""
    w = w.unsqueeze(-1)
    return a * (1.0 - w) + b * w


def noise(s: Tensor, t: Tensor, scale: float, seed: int, exponent: float = 3.0) -> Tensor:
    """Fractal noise in [0, 1]; ``scale`` noise tiles (largest features) per unit of ``s`` and ``t``."""
    return noise2(torch.stack([s * scale, t * scale], -1), seed, exponent)


def checker(s: Tensor, t: Tensor, ns: int, nt: int) -> Tensor:
    """1 on the 'odd' squares of an ``ns x nt`` checkerboard, else 0."""
    return ((torch.floor(s * ns) + torch.floor(t * nt)) % 2).float()


def stripes(x: Tensor, n: float, duty: float = 0.5, soft: float = 0.02) -> Tensor:
    """Soft-edged stripes along ``x``: ``n`` periods over [0, 1], fraction ``duty`` at 1."""
    f = torch.remainder(x * n, 1.0)
    return smoothstep(0.0, soft * n, f) * (1.0 - smoothstep(duty - soft * n, duty, f))


def dots(s: Tensor, t: Tensor, ns: int, nt: int, radius: float) -> Tensor:
    """Soft discs of ``radius`` (in cell units) centred in each of ``ns x nt`` cells."""
    ds = torch.remainder(s * ns, 1.0) - 0.5
    dt = torch.remainder(t * nt, 1.0) - 0.5
    return 1.0 - smoothstep(radius - 0.04, radius + 0.04, torch.sqrt(ds * ds + dt * dt))


def waves(s: Tensor, t: Tensor, n: float, amp: float, seed: int) -> Tensor:
    """Marble-like bands: ``0.5 + 0.5 sin(2 pi n (t + amp fbm))``."""
    return 0.5 + 0.5 * torch.sin(2.0 * math.pi * n * (t + amp * noise(s, t, 1.0, seed)))


# ---------------------------------------------------------------- atlas

@dataclass(frozen=True)
class Atlas:
    """A scene's merged mesh and its two texture bitmaps."""

    mesh: TriMesh
    """all parts, texture coordinates in atlas space"""
    base_color: np.ndarray
    """(H, W, 3) float32 linear RGB"""
    roughness: np.ndarray
    """(H, W) float32"""
    part_names: tuple[str, ...]
    part_faces: tuple[int, ...]
    """triangle count of each part, in order"""


def build_atlas(parts: list[tuple[str, TriMesh, ProceduralMaterial]], tile: int = 384,
                gutter: int = 4) -> Atlas:
    """Bake each part's material into a ``tile``-pixel square of a grid atlas."""
    n = math.ceil(math.sqrt(len(parts)))
    rows = math.ceil(len(parts) / n)
    H, W = rows * tile, n * tile
    base = np.zeros((H, W, 3), np.float32)
    rough = np.zeros((H, W), np.float32)
    inner = tile - 2 * gutter
    # texel centres of one tile, in the part's (s, t); gutter texels clamp to the border
    k = (torch.arange(tile, dtype=torch.float32) + 0.5 - gutter) / inner
    t, s = torch.meshgrid(k.clamp(0, 1), k.clamp(0, 1), indexing="ij")
    meshes = []
    for idx, (name, mesh, mat) in enumerate(parts):
        r, c = divmod(idx, n)
        y0, x0 = r * tile, c * tile
        with torch.no_grad():
            col = mat.base_color(s, t).clamp(*ALBEDO_RANGE)
            rgh = mat.roughness(s, t).clamp(*ROUGHNESS_RANGE)
        if col.shape != (tile, tile, 3) or rgh.shape != (tile, tile):
            raise ValueError(f"material of part {name!r} gave shapes {tuple(col.shape)}, {tuple(rgh.shape)}")
        base[y0:y0 + tile, x0:x0 + tile] = col.numpy()
        rough[y0:y0 + tile, x0:x0 + tile] = rgh.numpy()
        uv = np.stack([(x0 + gutter + mesh.uv[:, 0] * inner) / W, (y0 + gutter + mesh.uv[:, 1] * inner) / H], -1)
        meshes.append(mesh.with_uv(uv))
    return Atlas(merge(meshes), base, rough, tuple(p[0] for p in parts), tuple(len(p[1].faces) for p in parts))


def write_material(path, atlas: Atlas) -> None:
    """The ground-truth material as the renderer saw it, so it can be looked up at any surface point:
    ``uv`` (V, 2) per vertex of ``mesh.ply`` (atlas space, this module's convention), ``base_color``
    (H, W, 3) and ``roughness`` (H, W), float32, read bilinearly with clamped borders."""
    from ..io.atomic import atomic_path

    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            np.savez_compressed(f, uv=atlas.mesh.uv.astype(np.float32), base_color=atlas.base_color.astype(np.float32),
                                roughness=atlas.roughness.astype(np.float32))

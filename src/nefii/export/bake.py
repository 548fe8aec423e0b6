"""Bake the recovered material into textures over a UV atlas.

1. ``rasterise``: every texel whose centre lies within ``margin`` texels of a UV triangle gets
   the nearest point of the nearest such triangle (barycentric coordinates clamped to it), so
   the ring of texels just outside a chart holds the surface value at the chart's edge, which
   bilinear filtering at the seam reads.
2. The 3D point of each covered texel is the same barycentric combination of the triangle's
   corners; the material is decoded there by ``nefii.fit.model.decode_material`` (chunked, by
   ``material_at``), the decode the fit, eval and relight use, along the lookup normal interpolated as
   the ray caster interpolates it.
3. ``push_pull``: the empty texels between charts are filled from a pyramid of masked means, so
   mip levels and wide filters never pull in black.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np
import torch
from jaxtyping import Bool, Float, Int

from ..fit.model import NeFIIModel, material_at
from ..raycast.mesh import interpolate_normals
from .unwrap import UVAtlas

_CANDIDATES_PER_CHUNK = 1 << 21


@dataclass(frozen=True)
class TexelPoints:
    """The covered texels and the surface point each stands for."""

    rows: Int[np.ndarray, " N"]
    cols: Int[np.ndarray, " N"]
    triangle: Int[np.ndarray, " N"]
    bary: Float[np.ndarray, "N 3"]
    """barycentric coordinates in ``triangle`` (all >= 0, summing to 1)"""


@dataclass(frozen=True)
class BakedTextures:
    albedo: Float[np.ndarray, "S S 3"]
    """linear diffuse albedo in [0, 1]"""
    roughness: Float[np.ndarray, "S S"]
    """perceptual roughness (GGX alpha = roughness^2)"""
    covered: Bool[np.ndarray, "S S"]
    """texels decoded from the field; the rest are push-pull fill"""


# ---------------------------------------------------------------- rasterisation
def _closest_on_triangle(p: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray
                         ) -> tuple[np.ndarray, np.ndarray]:
    """Barycentrics ``(N, 3)`` of the point of triangle ``abc`` nearest to ``p`` (2D), and the distance."""
    e1, e2, q = b - a, c - a, p - a
    det = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]
    l1 = (q[:, 0] * e2[:, 1] - q[:, 1] * e2[:, 0]) / det
    l2 = (e1[:, 0] * q[:, 1] - e1[:, 1] * q[:, 0]) / det
    bary = np.stack([1.0 - l1 - l2, l1, l2], -1)
    dist = np.zeros(len(p))
    outside = (bary < 0).any(-1)
    if outside.any():
        po, corners = p[outside], (a[outside], b[outside], c[outside])
        best = np.full(len(po), np.inf)
        best_bary = np.zeros((len(po), 3))
        for i, j in ((0, 1), (1, 2), (2, 0)):  # nearest point of each edge segment
            s, e = corners[i], corners[j]
            d = e - s
            t = np.clip(((po - s) * d).sum(-1) / np.maximum((d * d).sum(-1), 1e-300), 0.0, 1.0)
            r = np.linalg.norm(po - (s + t[:, None] * d), axis=-1)
            take = r < best
            best = np.where(take, r, best)
            edge_bary = np.zeros((len(po), 3))
            edge_bary[:, i], edge_bary[:, j] = 1.0 - t, t
            best_bary[take] = edge_bary[take]
        bary[outside], dist[outside] = best_bary, best
    return bary, dist


def rasterise(uv: Float[np.ndarray, "V 2"], faces: Int[np.ndarray, "F 3"], size: int,
              margin: float = 1.5) -> TexelPoints:
    """Texels of a ``size``-square texture within ``margin`` texels of a triangle (see module doc).

    ``uv`` is in image convention (u right, v down, [0, 1]); texel ``(i, j)`` is centred at
    ``((j + 0.5) / size, (i + 0.5) / size)``. Each texel takes its nearest triangle (ties: the
    first); a texel inside a triangle is at distance 0 from it.
    """
    px = np.asarray(uv, dtype=np.float64) * size                              # texel units
    tri = px[faces]                                                            # (F, 3, 2)
    area2 = ((tri[:, 1, 0] - tri[:, 0, 0]) * (tri[:, 2, 1] - tri[:, 0, 1])
             - (tri[:, 1, 1] - tri[:, 0, 1]) * (tri[:, 2, 0] - tri[:, 0, 0]))
    keep = np.nonzero(np.abs(area2) > 1e-12)[0]                                # UV-degenerate triangles cover nothing
    lo = np.clip(np.ceil(tri[keep].min(1) - margin - 0.5), 0, size - 1).astype(np.int64)
    hi = np.clip(np.floor(tri[keep].max(1) + margin - 0.5), 0, size - 1).astype(np.int64)
    extent = np.maximum(hi - lo + 1, 0)                                        # (K, 2): columns, rows
    count = extent[:, 0] * extent[:, 1]
    best_dist = np.full(size * size, np.inf)
    best_tri = np.full(size * size, -1, dtype=np.int64)
    best_bary = np.zeros((size * size, 3))
    ends = np.cumsum(count)
    start = 0
    while start < len(keep):
        stop = int(np.searchsorted(ends, (ends[start - 1] if start else 0) + _CANDIDATES_PER_CHUNK, "right"))
        stop = max(stop, start + 1)
        k = np.arange(start, stop)
        rep = np.repeat(k, count[k])                                            # candidate -> kept triangle
        offset = np.arange(len(rep)) - np.repeat(np.cumsum(count[k]) - count[k], count[k])
        col = lo[rep, 0] + offset % extent[rep, 0]
        row = lo[rep, 1] + offset // extent[rep, 0]
        centre = np.stack([col + 0.5, row + 0.5], -1)
        t = tri[keep[rep]]
        bary, dist = _closest_on_triangle(centre, t[:, 0], t[:, 1], t[:, 2])
        near = dist <= margin
        texel = (row * size + col)[near]
        dist, bary, face = dist[near], bary[near], keep[rep][near]
        order = np.lexsort((dist, texel))                                       # per texel: nearest first
        texel, first = np.unique(texel[order], return_index=True)
        pick = order[first]
        better = dist[pick] < best_dist[texel]
        texel, pick = texel[better], pick[better]
        best_dist[texel], best_tri[texel], best_bary[texel] = dist[pick], face[pick], bary[pick]
        start = stop
    covered = np.nonzero(best_tri >= 0)[0]
    return TexelPoints(covered // size, covered % size, best_tri[covered], best_bary[covered])


# ---------------------------------------------------------------- dilation
def push_pull(image: Float[np.ndarray, "H W C"], mask: Bool[np.ndarray, "H W"]) -> Float[np.ndarray, "H W C"]:
    """Fill the texels outside ``mask`` from coarser masked means (pull), coarse to fine (push).

    Texels inside ``mask`` are returned unchanged; with no texel in ``mask`` the result is 0.
    """
    image = np.asarray(image, dtype=np.float64)
    weight = mask.astype(np.float64)
    if image.shape[0] <= 1 and image.shape[1] <= 1:
        return np.where(mask[..., None], image, 0.0)
    h, w = mask.shape
    ph, pw = h + h % 2, w + w % 2                                              # pad to even sides
    num = np.zeros((ph, pw, image.shape[-1]))
    den = np.zeros((ph, pw))
    num[:h, :w] = image * weight[..., None]
    den[:h, :w] = weight
    num = num.reshape(ph // 2, 2, pw // 2, 2, -1).sum((1, 3))
    den = den.reshape(ph // 2, 2, pw // 2, 2).sum((1, 3))
    coarse_mask = den > 0
    coarse = np.where(coarse_mask[..., None], num / np.maximum(den, 1e-300)[..., None], 0.0)
    coarse = push_pull(coarse, coarse_mask)
    return np.where(mask[..., None], image, _upsample2(coarse)[:h, :w])


def _upsample2(c: np.ndarray) -> np.ndarray:
    """Bilinear 2x upsampling (fine texel centres at coarse -0.25 / +0.25), clamped at the border."""
    for axis in (0, 1):
        p = np.concatenate([c.take([0], axis), c, c.take([-1], axis)], axis)
        n = c.shape[axis]
        mid, before, after = (p.take(np.arange(k, k + n), axis) for k in (1, 0, 2))
        c = np.stack([0.75 * mid + 0.25 * before, 0.75 * mid + 0.25 * after], axis + 1)
        shape = list(mid.shape)
        shape[axis] = 2 * n
        c = c.reshape(shape)
    return c


# ---------------------------------------------------------------- baking
def bake_textures(model: NeFIIModel, vertices: Float[np.ndarray, "V 3"], normals: Float[np.ndarray, "V 3"],
                  atlas: UVAtlas, progress: Callable[[int, int], None] | None = None) -> BakedTextures:
    """Albedo and roughness textures of ``model`` over ``atlas`` (``vertices`` and unit vertex ``normals``
    are the atlas's, in world space; ``normals`` are the material lookup's, the ray caster's
    ``lookup_normal``, and a texel's is interpolated as the ray caster interpolates them, by
    :func:`interpolate_normals`).

    ``progress(n, total)`` is told after each chunk of ``n`` of the ``total`` texels is decoded.
    """
    S = atlas.size
    texels = rasterise(atlas.uv, atlas.faces, S)
    tri = atlas.faces[texels.triangle]                                                 # (N, 3)
    corners = np.asarray(vertices, dtype=np.float64)[tri]                              # (N, 3, 3)
    points = torch.from_numpy((texels.bary[..., None] * corners).sum(1)).float()
    nrm = interpolate_normals(torch.from_numpy(np.asarray(normals, dtype=np.float64)[tri]),
                              torch.from_numpy(np.asarray(texels.bary, dtype=np.float64)))
    total = len(points)
    mat = material_at(model, points, nrm.float(),
                      progress=None if progress is None else (lambda n: progress(n, total)))
    values = torch.cat([mat.albedo, mat.roughness.unsqueeze(-1)], -1).cpu().double().numpy()
    image = np.zeros((S, S, 4))
    covered = np.zeros((S, S), dtype=bool)
    image[texels.rows, texels.cols] = values
    covered[texels.rows, texels.cols] = True
    filled = push_pull(image, covered).astype(np.float32)
    return BakedTextures(np.clip(filled[..., :3], 0.0, 1.0), np.clip(filled[..., 3], 0.0, 1.0), covered)

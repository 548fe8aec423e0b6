"""The geometry contract every backend (triangle mesh now, SDF later) fulfils.

A backend answers two queries for a batch of rays: the closest hit (:meth:`Geometry.intersect`)
and whether anything is hit at all (:meth:`Geometry.occluded`). Rays start at ``origins`` with
``t`` in ``[0, t_max)``; backends never self-offset, callers spawn secondary rays with
:func:`spawn_rays`. Results live on the device of the rays. An SDF backend returns its
geometric feature vector in ``SurfaceHit.features``.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import torch
from jaxtyping import Bool, Float, Int
from torch import Tensor

from ..render.frame import dot


@dataclass(frozen=True)
class Rays:
    origins: Float[Tensor, "*bs 3"]
    directions: Float[Tensor, "*bs 3"]
    """unit directions"""
    t_max: Float[Tensor, " *bs"] | None = None
    """ray extent; None means unbounded"""


@dataclass(frozen=True)
class SurfaceHit:
    """Closest hits; fields are meaningful where ``valid``."""

    valid: Bool[Tensor, " *bs"]
    t: Float[Tensor, " *bs"]
    """distance along the (unit) ray; +inf where nothing is hit"""
    position: Float[Tensor, "*bs 3"]
    normal: Float[Tensor, "*bs 3"]
    """unit shading normal (interpolated vertex normals for meshes), facing outwards"""
    geometric_normal: Float[Tensor, "*bs 3"]
    """unit face normal, facing outwards (winding order)"""
    lookup_normal: Float[Tensor, "*bs 3"]
    """unit normal along which the material field's lookup is offset (``MaterialField``'s ``normal_offset``):
    the shading normal, or a mesh's own smoother normals (``MeshGeometry.from_file``'s ``lookup_sigma``)"""
    triangle_id: Int[Tensor, " *bs"]
    """-1 where nothing is hit (and for backends without triangles)"""
    features: Float[Tensor, "*bs F"] | None = None
    """geometric feature vector f of an SDF backend; None for meshes"""


class Geometry(Protocol):
    """Frozen geometry that rays can be cast against."""

    scale: float
    """length of the bounding box diagonal: sets ray offsets"""

    def intersect(self, rays: Rays) -> SurfaceHit: ...

    def occluded(self, rays: Rays) -> Bool[Tensor, " *bs"]: ...


def spawn_rays(position: Float[Tensor, "*bs 3"], geometric_normal: Float[Tensor, "*bs 3"],
               directions: Float[Tensor, "*bs 3"], offset: float) -> Rays:
    """Secondary rays leaving a surface: the origin moves ``offset`` off the surface, to the
    side the direction goes (so rays into the surface, e.g. from shading-normal mismatch,
    still start on the correct side), which keeps rays from hitting their own triangle."""
    side = torch.where(dot(geometric_normal, directions) >= 0, 1.0, -1.0).unsqueeze(-1)
    return Rays(origins=position + side * offset * geometric_normal, directions=directions)


def visible_cosines(position: Float[Tensor, "P 3"], normal: Float[Tensor, "P 3"],
                    geometric_normal: Float[Tensor, "P 3"], geometry: Geometry, directions: Float[Tensor, "D 3"],
                    offset: float, max_rays: int = 1 << 20) -> Float[Tensor, "P D"]:
    """``V(x_p, d) max(n_p . d, 0)`` for every point and direction: visibility traced against ``geometry``
    (rays spawned ``offset`` world units off the surface, at most ``max_rays`` a call) for the pairs above the
    shading normal's horizon only, the others being 0 either way. A diffuse point's irradiance from a light of
    radiance ``L(d)`` on a lattice of cells ``dOmega`` is this matrix times ``L dOmega``."""
    cos = (normal @ directions.T).clamp_min(0.0)
    p_idx, d_idx = (cos > 0).nonzero(as_tuple=True)
    visible = torch.zeros_like(cos)
    for a in range(0, len(p_idx), max_rays):
        p, d = p_idx[a:a + max_rays], d_idx[a:a + max_rays]
        rays = spawn_rays(position[p], geometric_normal[p], directions[d], offset)
        visible[p, d] = (~geometry.occluded(rays)).to(cos.dtype)
    return visible * cos

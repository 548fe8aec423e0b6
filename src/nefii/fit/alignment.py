"""Does the given mesh agree with the images: do its triangles face the cameras, and does it sit where the
masks say the object is?

A mesh in another frame than the cameras (a glTF is Y-up, a Blender render's cameras Z-up), in other units or
off by a shift fits without complaint: :func:`nefii.fit.pixels.first_hits` keeps only the pixels where mask and
mesh agree, and the material and light are then fitted to the wrong pixels. With masks, the agreement is measured
away from the masks' edges (where a pixel's centre ray and its alpha may disagree by a sub-pixel) and a mesh that
disagrees is refused, naming a rotation about x that would make it agree when there is one.
"""
from __future__ import annotations

import math
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from ..data.scene import SceneData
from ..errors import InputError
from ..raycast import MeshGeometry, Rays
from ..raycast.base import Geometry
from .geometry_source import GeometrySource
from .path_trace import SurfacePoints
from .pixels import view_rays

AGREEMENT = (0.99, 0.6)
"""intersection over union of masks and mesh, away from the masks' edges, below which the mesh is reported:
a warning, an error. The built-in scenes' own meshes and the corner's reconstructions by `nefii geometry` score
0.9998-1.000; a mesh turned a quarter about x 0.40-0.53; the corner's mesh scaled by 1.05 about its centre 0.953,
shifted by 2% of its diagonal 0.980, and fitted on them the corner scores 20.9 and 17.7 dB albedo against 29.6
on its own mesh (docs/experiments.md, 2026-11-30)"""


@dataclass(frozen=True)
class Agreement:
    """Pixel counts over all views, masks' edge pixels left out."""

    inside: int
    """mask interior pixels (the mask and its 8 neighbours say object)"""
    inside_hit: int
    """... of which the mesh covers"""
    outside_hit: int
    """mask exterior pixels (the mask and its 8 neighbours say background) that the mesh covers"""

    @property
    def iou(self) -> float:
        union = self.inside + self.outside_hit
        return self.inside_hit / union if union else 1.0


def _interiors(mask: Tensor) -> tuple[Tensor, Tensor]:
    """``(H, W)`` bool -> where the 3 x 3 neighbourhood is all object, all background (borders count as both)."""
    m = mask.float()[None, None]
    obj = -F.max_pool2d(-m, 3, stride=1, padding=1)[0, 0] > 0.5
    bg = F.max_pool2d(m, 3, stride=1, padding=1)[0, 0] < 0.5
    return obj, bg


def mask_agreement(scene: SceneData, geometry: Geometry, inverted: bool = False) -> Agreement:
    """How well ``geometry``'s first hits cover ``scene``'s masks (which must be given; ``inverted``: their
    complements)."""
    assert scene.masks is not None
    inside = inside_hit = outside_hit = 0
    for v in range(len(scene)):
        o, d = view_rays(scene, v)
        hit = geometry.intersect(Rays(o.reshape(-1, 3), d.reshape(-1, 3))).valid
        hit = hit.reshape(scene.height, scene.width).cpu()
        obj, bg = _interiors(scene.masks[v] != inverted)
        inside += int(obj.sum())
        inside_hit += int((obj & hit).sum())
        outside_hit += int((bg & hit).sum())
    return Agreement(inside, inside_hit, outside_hit)


def _turned(mesh: MeshGeometry, degrees: int) -> MeshGeometry:
    """``mesh`` turned about the x axis (+90: a Y-up file's up onto +z)."""
    c, s = round(math.cos(math.radians(degrees))), round(math.sin(math.radians(degrees)))
    turn = np.array([[1, 0, 0], [0, c, -s], [0, s, c]], dtype=np.float64)
    return MeshGeometry(np.asarray(mesh.vertices, np.float64) @ turn.T, np.asarray(mesh.faces), threads=mesh.threads)


def check_alignment(scene: SceneData, geometry: Geometry, mesh_path: Path) -> Agreement | None:
    """Refuse (InputError naming ``mesh_path``) a mesh that the masks disagree with, warn where they partly do;
    None where the scene has no masks or the geometry is not a triangle mesh (an SDF from ``nefii geometry`` was
    made from these masks)."""
    if scene.masks is None or not isinstance(geometry, MeshGeometry):
        return None
    a = mask_agreement(scene, geometry)
    what = (f"the masks and the mesh agree on {a.iou:.1%} of the pixels (intersection over union away from the "
            f"masks' edges; {1 - a.inside_hit / max(a.inside, 1):.0%} of the masks' interior is missed)")
    if a.iou < AGREEMENT[1]:
        inverted = mask_agreement(scene, geometry, inverted=True).iou
        if inverted >= AGREEMENT[0]:
            raise InputError(scene.root, f"the masks and {mesh_path.name} agree on {a.iou:.1%} of the pixels, and on "
                                         f"{inverted:.1%} with the masks inverted: are the masks white on the "
                                         "background and black on the object?")
        turns = {deg: mask_agreement(scene, _turned(geometry, deg)).iou for deg in (90, -90, 180)}
        deg, best = max(turns.items(), key=lambda kv: kv[1])
        hint = "is it in the cameras' world and units?"
        if best >= AGREEMENT[0]:
            hint = (f"turned {deg:+d} degrees about x they agree on {best:.1%}"
                    + (" (a Y-up file, such as a glTF, into the cameras' Z-up world)" if deg == 90 else "")
                    + f": trimesh's `mesh.apply_transform(trimesh.transformations.rotation_matrix("
                      f"{math.radians(deg):.4f}, [1, 0, 0]))` turns it")
        raise InputError(mesh_path, f"{what}: the mesh is not where the images see the object; {hint}")
    if a.iou < AGREEMENT[0]:
        warnings.warn(f"{mesh_path}: {what}: is the mesh aligned with the cameras?", stacklevel=2)
    return a


BACK_FACING = (0.05, 0.5)
"""shares of the training pixels whose first hit sees the back of its triangle beyond which the mesh's winding
is reported: mixed (a warning), inverted (an error); the built-in meshes show 0"""


def check_winding(points: SurfacePoints, source: GeometrySource) -> None:
    """Refuse a mesh whose triangles face away from the cameras (normals pointing into the object): shading reads
    their backs, and the corner's mesh with its winding reversed fitted to 11.75 dB albedo and roughness MSE 0.245
    without a word (docs/experiments.md, 2026-11-30); warn where only part of it does."""
    if len(points) == 0:
        return
    back = float(((points.wo * points.geometric_normal).sum(-1) < 0).float().mean())
    hint = "normals must point out of the object, as counter-clockwise winding seen from outside makes them"
    if back > BACK_FACING[1]:
        raise InputError(source.mesh, f"{back:.0%} of the training pixels see the back of its triangles: its faces "
                                      f"wind the wrong way ({hint}; trimesh's `mesh.invert()` flips them)")
    if back > BACK_FACING[0]:
        warnings.warn(f"{source.mesh}: {back:.0%} of the training pixels see the back of its triangles: is its winding "
                      f"consistent? ({hint})", stacklevel=2)

"""The SDF's zero level set as a triangle mesh (marching cubes, scikit-image), in world coordinates."""
from __future__ import annotations

import numpy as np
import torch
import trimesh

from .networks import SDFNetwork
from .normalization import Normalization


@torch.no_grad()
def sdf_grid(sdf: SDFNetwork, resolution: int, chunk: int = 65536) -> np.ndarray:
    """SDF values on a ``resolution^3`` grid spanning ``[-1, 1]^3`` (index order x, y, z)."""
    g = torch.linspace(-1.0, 1.0, resolution)
    dev = next(sdf.parameters()).device
    out = np.empty(resolution**3, dtype=np.float32)
    pts = torch.stack(torch.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3)
    for s in range(0, len(pts), chunk):
        out[s:s + chunk] = sdf.sdf(pts[s:s + chunk].to(dev)).float().cpu().numpy()
    return out.reshape(resolution, resolution, resolution)


def extract_mesh(sdf: SDFNetwork, norm: Normalization, resolution: int, min_component: float = 0.01) -> trimesh.Trimesh:
    """Marching cubes of ``sdf = 0`` inside the unit sphere, faces wound outwards (towards ``sdf > 0``),
    components with fewer than ``min_component`` of the faces dropped, vertices in world coordinates."""
    from skimage.measure import marching_cubes

    vol = sdf_grid(sdf, resolution)
    g = np.linspace(-1.0, 1.0, resolution)
    xx, yy, zz = np.meshgrid(g, g, g, indexing="ij")
    vol = np.where(xx**2 + yy**2 + zz**2 > 1.0, np.maximum(vol, 1e-3), vol)   # nothing outside the sphere
    if not (vol.min() < 0 < vol.max()):
        raise ValueError("the SDF has no zero crossing inside the unit sphere: no surface to extract")
    step = 2.0 / (resolution - 1)
    verts, faces, _, _ = marching_cubes(vol, level=0.0, spacing=(step, step, step))
    verts = verts - 1.0
    mesh = trimesh.Trimesh(verts, faces, process=True)
    # orient: the face normals must point up the SDF gradient
    centers = torch.from_numpy(mesh.triangles_center.astype(np.float32))
    dev = next(sdf.parameters()).device
    _, grad, _ = sdf.with_gradient(centers.to(dev), create_graph=False)
    agree = (grad.cpu().numpy() * mesh.face_normals).sum(-1)
    if np.median(agree) < 0:
        mesh.invert()
    if min_component > 0 and len(mesh.faces):
        parts = mesh.split(only_watertight=False)
        keep = [p for p in parts if len(p.faces) >= min_component * len(mesh.faces)]
        if keep:
            mesh = trimesh.util.concatenate(keep)
    world = norm.to_world(torch.from_numpy(np.asarray(mesh.vertices, dtype=np.float64))).numpy()
    return trimesh.Trimesh(world, np.asarray(mesh.faces), process=False)

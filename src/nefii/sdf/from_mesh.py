"""Fit the SDF to a given mesh (the paper's route for synthetic evaluation: the same SDF machinery, with
the ground-truth shape), by L1 on signed distances at points near the surface and in the sphere."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
import trimesh
from jaxtyping import Float
from scipy.spatial import cKDTree
from torch import Tensor

from ..raycast.base import Rays
from ..raycast.mesh import MeshGeometry
from .config import GeometryConfig
from .losses import GeometryLoss
from .model import NeuSModel
from .normalization import Normalization
from .train import uniform_in_ball

_PARITY_DIRECTIONS = np.array([[0.267, 0.535, 0.802], [-0.577, 0.577, -0.577], [0.801, -0.534, 0.267]])


def inside_by_parity(geometry: MeshGeometry, points: np.ndarray, max_crossings: int = 64) -> np.ndarray:
    """Whether each point is inside a closed mesh: the parity of surface crossings along three rays,
    by majority (one ray grazing an edge cannot flip the answer)."""
    votes = np.zeros(len(points), dtype=np.int32)
    eps = 1e-6 * geometry.scale
    for d in _PARITY_DIRECTIONS:
        d = d / np.linalg.norm(d)
        o = torch.from_numpy(points.astype(np.float32))
        dirs = torch.from_numpy(np.broadcast_to(d, points.shape).astype(np.float32).copy())
        count = np.zeros(len(points), dtype=np.int32)
        active = np.ones(len(points), dtype=bool)
        for _ in range(max_crossings):
            idx = np.nonzero(active)[0]
            if len(idx) == 0:
                break
            hit = geometry.intersect(Rays(o[idx], dirs[idx]))
            v = hit.valid.numpy()
            count[idx[v]] += 1
            o[idx[v]] = hit.position[v] + dirs[idx[v]] * eps
            active[idx[~v]] = False
        votes += count % 2
    return votes >= 2


@dataclass(frozen=True)
class SignedDistances:
    points: Float[Tensor, "P 3"]
    """normalised coordinates"""
    sdf: Float[Tensor, " P"]
    """signed distance in normalised units (negative inside)"""


def mesh_signed_distances(mesh: trimesh.Trimesh, norm: Normalization, n: int, seed: int = 0,
                          surface_samples: int = 500_000) -> SignedDistances:
    """``n`` points (half near the surface at two noise scales, half uniform in the unit sphere) and their
    signed distances: magnitude by nearest neighbour among dense surface samples (error below half their
    spacing), sign by ray parity with Embree."""
    rng = np.random.default_rng(seed)
    surf, _ = trimesh.sample.sample_surface(mesh, surface_samples, seed=seed)
    surf_u = (surf - np.asarray(norm.center)) / norm.radius
    k = n // 4
    pick = surf_u[rng.integers(len(surf_u), size=2 * k)]
    near = pick + rng.normal(size=pick.shape) * np.repeat([[0.01], [0.05]], k, axis=0)
    g = torch.Generator().manual_seed(seed)
    uni = uniform_in_ball(n - 2 * k, g, torch.device("cpu")).double().numpy()
    pts = np.concatenate([near, uni])
    dist, _ = cKDTree(surf_u).query(pts, workers=-1)
    world = pts * norm.radius + np.asarray(norm.center)
    inside = inside_by_parity(MeshGeometry(np.asarray(mesh.vertices), np.asarray(mesh.faces)), world)
    sdf = np.where(inside, -dist, dist)
    return SignedDistances(torch.from_numpy(pts).float(), torch.from_numpy(sdf).float())


@dataclass
class MeshObjective:
    """L1 between the network's SDF and the mesh's at a batch of the precomputed points, plus eikonal."""

    cfg: GeometryConfig
    data: SignedDistances

    def loss(self, model: NeuSModel, step: int, generator: torch.Generator) -> GeometryLoss:
        dev = self.data.points.device
        i = torch.randint(len(self.data.points), (self.cfg.from_mesh_points,), generator=generator, device=dev)
        sdf, grad, _ = model.sdf.with_gradient(self.data.points[i], create_graph=True)
        l_sdf = (sdf - self.data.sdf[i]).abs().mean()
        l_eik = (grad.norm(dim=-1) - 1.0).square().mean()
        zero = l_sdf.new_zeros(())
        return GeometryLoss(l_sdf + self.cfg.eikonal_weight * l_eik, l_sdf, l_eik, zero)

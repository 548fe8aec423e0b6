"""Triangle meshes cast with Embree 4 (PyPI ``embreex``); no BVH of our own.

Embree takes float32 numpy arrays; rays are copied to the CPU and results back to the rays'
device. Large batches are split over threads (Embree releases the GIL), which is where most
of the speed on a few cores comes from.
"""
from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import torch
from jaxtyping import Bool, Float
from torch import Tensor

from ..errors import InputError
from ..render.frame import normalize
from .base import Rays, SurfaceHit

_MIN_RAYS_PER_THREAD = 16384


def vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area-weighted vertex normals (outwards for counter-clockwise winding)."""
    fn = np.cross(vertices[faces[:, 1]] - vertices[faces[:, 0]], vertices[faces[:, 2]] - vertices[faces[:, 0]])
    vn = np.zeros_like(vertices)
    for k in range(3):
        np.add.at(vn, faces[:, k], fn)
    return vn / np.maximum(np.linalg.norm(vn, axis=-1, keepdims=True), 1e-20)


def smooth_vertex_normals(vertices: np.ndarray, faces: np.ndarray, normals: np.ndarray, sigma: float) -> np.ndarray:
    """Unit vertex normals diffused over the mesh's edges to a lateral scale ``sigma`` (same units as the
    vertices): each round replaces a normal by the mean of itself and its 1-ring, and a random walk of
    ``k`` steps of mean edge length ``l`` spreads ``l sqrt(k / 2)`` per axis, so ``k = ceil(2 (sigma / l)^2)``.
    Along edges only: the two faces of a thin wall are not averaged together."""
    import scipy.sparse as sp

    if sigma <= 0:
        return normals
    i = np.concatenate([faces[:, 0], faces[:, 1], faces[:, 2], faces[:, 1], faces[:, 2], faces[:, 0]])
    j = np.concatenate([faces[:, 1], faces[:, 2], faces[:, 0], faces[:, 0], faces[:, 1], faces[:, 2]])
    n_v = len(vertices)
    adj = sp.coo_matrix((np.ones(len(i)), (i, j)), shape=(n_v, n_v)).tocsr()
    adj.data[:] = 1.0                                                  # each neighbour once
    walk = adj + sp.identity(n_v, format="csr")
    edge = float(np.linalg.norm(vertices[i] - vertices[j], axis=-1).mean())
    rounds = int(np.ceil(2.0 * (sigma / max(edge, 1e-12)) ** 2))
    n = normals.astype(np.float64)
    for _ in range(rounds):
        n = walk @ n
        n /= np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-20)
    return n.astype(normals.dtype)


def interpolate_normals(per_vertex: Float[Tensor, "*bs 3 3"], bary: Float[Tensor, "*bs 3"]) -> Float[Tensor, "*bs 3"]:
    """A point's unit normal from its triangle's three vertex normals and its barycentrics (interpolated,
    renormalised). The ray caster and the texture bake both interpolate through here."""
    return normalize((per_vertex * bary.unsqueeze(-1)).sum(-2))


def check_faces(faces: np.ndarray, num_vertices: int, path: str | Path) -> None:
    """Every face's vertex indices lie in ``[0, num_vertices)``."""
    bad = (faces < 0) | (faces >= num_vertices)
    if bad.any():
        f = int(np.argwhere(bad.any(-1))[0, 0])
        raise InputError(path, f"face {f} refers to vertex {int(faces[f][bad[f]][0])}, but the mesh has "
                               f"{num_vertices} vertices (indices 0..{num_vertices - 1})")


class MeshGeometry:
    """A frozen triangle mesh: ``intersect`` and ``occluded`` for batches of rays."""

    def __init__(self, vertices: np.ndarray, faces: np.ndarray, normals: np.ndarray | None = None,
                 threads: int | None = None, lookup_normals: np.ndarray | None = None) -> None:
        """``normals``: unit vertex (shading) normals, default area-weighted; ``lookup_normals``: unit vertex
        normals along which the material field's lookup is offset (:attr:`SurfaceHit.lookup_normal`), default
        the shading normals. ``threads``: Embree's threads, default every core this process may use (a GPU fit
        casts its rays on the host's cores)."""
        from embreex import rtcore_scene as rtcs
        from embreex.mesh_construction import TriangleMesh

        self.vertices = np.ascontiguousarray(vertices, dtype=np.float32)
        self.faces = np.ascontiguousarray(faces, dtype=np.int32)
        if self.vertices.ndim != 2 or self.vertices.shape[1] != 3 or self.faces.ndim != 2 or self.faces.shape[1] != 3:
            raise ValueError(f"MeshGeometry wants vertices (V,3) and faces (F,3); got {vertices.shape}, {faces.shape}")
        vn = vertex_normals(self.vertices.astype(np.float64), self.faces) if normals is None else normals
        self.vertex_normals = np.ascontiguousarray(vn, dtype=np.float32)
        if self.vertex_normals.shape != self.vertices.shape:
            raise ValueError(f"MeshGeometry wants one normal per vertex, (V,3) = {self.vertices.shape}; got "
                             f"{self.vertex_normals.shape}")
        fn = np.cross(self.vertices[self.faces[:, 1]] - self.vertices[self.faces[:, 0]],
                      self.vertices[self.faces[:, 2]] - self.vertices[self.faces[:, 0]])
        self.face_normals = (fn / np.maximum(np.linalg.norm(fn, axis=-1, keepdims=True), 1e-30)).astype(np.float32)
        lo, hi = self.vertices.min(0), self.vertices.max(0)
        self.bounds = (lo, hi)
        self.scale = float(np.linalg.norm(hi - lo))
        self.threads = threads or len(os.sched_getaffinity(0))
        self._scene = rtcs.EmbreeScene()
        TriangleMesh(self._scene, self.vertices, self.faces)
        self._vertices_t = torch.from_numpy(self.vertices)
        self._faces_t = torch.from_numpy(self.faces.astype(np.int64))
        self._normals_t = torch.from_numpy(self.vertex_normals)
        self.set_lookup_normals(lookup_normals)
        self._face_normals_t = torch.from_numpy(self.face_normals)
        self._pool = ThreadPoolExecutor(self.threads) if self.threads > 1 else None

    def set_lookup_normals(self, lookup_normals: np.ndarray | None) -> None:
        """Replace the material lookup's vertex normals ((V,3); None: the shading normals)."""
        lookup = self.vertex_normals if lookup_normals is None else np.ascontiguousarray(lookup_normals, np.float32)
        if lookup.shape != self.vertices.shape:
            raise ValueError(f"MeshGeometry wants one normal per vertex, (V,3) = {self.vertices.shape}; got lookup "
                             f"normals {lookup.shape}")
        self.lookup_normals = lookup
        self._lookup_t = self._normals_t if lookup is self.vertex_normals else torch.from_numpy(lookup)

    @staticmethod
    def from_file(path: str | Path, normal_sigma: float = 0.0, lookup_sigma: float = 0.0,
                  **kwargs) -> "MeshGeometry":
        """Load PLY/OBJ/GLB/... with trimesh; raises InputError naming the file on failure. ``normal_sigma`` > 0
        smooths the vertex normals to that lateral scale, a fraction of the bounding-box diagonal (see
        :func:`smooth_vertex_normals`); ``lookup_sigma`` > 0 gives the material lookup its own normals, the
        area-weighted ones smoothed to that scale (0: the shading normals)."""
        import trimesh

        path = Path(path)
        if not path.is_file():
            raise InputError(path, "mesh file not found")
        try:
            mesh = trimesh.load(path, force="mesh", process=False)
        except Exception as e:
            raise InputError(path, f"not a readable mesh ({type(e).__name__}: {e})") from None
        if len(mesh.faces) == 0:
            raise InputError(path, "mesh has no triangles")
        if not np.isfinite(mesh.vertices).all():
            raise InputError(path, "mesh has NaN/inf vertex coordinates")
        vertices, faces = np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces)
        check_faces(faces, len(vertices), path)
        return MeshGeometry.smoothed(vertices, faces, normal_sigma, lookup_sigma, **kwargs)

    @staticmethod
    def smoothed(vertices: np.ndarray, faces: np.ndarray, normal_sigma: float = 0.0, lookup_sigma: float = 0.0,
                 **kwargs) -> "MeshGeometry":
        """The mesh ``(V,3)`` vertices, ``(F,3)`` faces with its vertex normals smoothed as :meth:`from_file`
        says."""
        vertices = np.asarray(vertices, dtype=np.float64)
        if normal_sigma > 0 or lookup_sigma > 0:
            diagonal = float(np.linalg.norm(np.ptp(vertices, axis=0)))
            raw = vertex_normals(vertices, faces)
            kwargs["normals"] = smooth_vertex_normals(vertices, faces, raw, normal_sigma * diagonal)
            if lookup_sigma > 0:
                kwargs["lookup_normals"] = smooth_vertex_normals(vertices, faces, raw, lookup_sigma * diagonal)
        return MeshGeometry(vertices, faces, **kwargs)

    # ---- Embree calls, split over threads
    def _run(self, o: np.ndarray, d: np.ndarray, tmax: np.ndarray | None, query: str):
        def call(sl: slice):
            kw = {} if tmax is None else {"dists": np.ascontiguousarray(tmax[sl])}
            if query == "OCCLUDED":
                return self._scene.run(o[sl], d[sl], query="OCCLUDED", **kw)
            return self._scene.run(o[sl], d[sl], output=1, **kw)

        n = len(o)
        parts = min(self.threads, max(1, n // _MIN_RAYS_PER_THREAD))
        if parts == 1 or self._pool is None:
            return [call(slice(0, n))]
        edges = np.linspace(0, n, parts + 1).astype(int)
        return list(self._pool.map(call, [slice(a, b) for a, b in zip(edges[:-1], edges[1:])]))

    @staticmethod
    def _to_numpy(rays: Rays) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        o = np.ascontiguousarray(rays.origins.detach().reshape(-1, 3).cpu().numpy(), dtype=np.float32)
        d = np.ascontiguousarray(rays.directions.detach().reshape(-1, 3).cpu().numpy(), dtype=np.float32)
        t = None
        if rays.t_max is not None:
            t = np.ascontiguousarray(rays.t_max.detach().reshape(-1).cpu().numpy(), dtype=np.float32)
        return o, d, t

    def occluded(self, rays: Rays) -> Bool[Tensor, " *bs"]:
        o, d, t = self._to_numpy(rays)
        res = np.concatenate(self._run(o, d, t, "OCCLUDED")) if len(o) else np.zeros(0, np.int32)
        return torch.from_numpy(res != -1).to(rays.origins.device).reshape(rays.origins.shape[:-1])

    def intersect(self, rays: Rays) -> SurfaceHit:
        o, d, t = self._to_numpy(rays)
        bs, dev, dtype = tuple(rays.origins.shape[:-1]), rays.origins.device, rays.origins.dtype
        if len(o):
            parts = self._run(o, d, t, "INTERSECT")
            prim = np.concatenate([p["primID"] for p in parts]).astype(np.int64)
            u = np.concatenate([p["u"] for p in parts]).astype(np.float32)
            v = np.concatenate([p["v"] for p in parts]).astype(np.float32)
            tfar = np.concatenate([p["tfar"] for p in parts]).astype(np.float32)
        else:
            prim, u, v, tfar = np.zeros(0, np.int64), *(np.zeros(0, np.float32),) * 3
        # interpolate on the CPU in torch, for the hits only
        prim_t = torch.from_numpy(prim)
        valid = prim_t >= 0
        idx = valid.nonzero().squeeze(-1)
        tri = prim_t[idx]
        f = self._faces_t[tri]                                                 # (M, 3)
        uu, vv = torch.from_numpy(u)[idx], torch.from_numpy(v)[idx]
        w = torch.stack([1.0 - uu - vv, uu, vv], -1).unsqueeze(-1)             # barycentrics (M, 3, 1)
        n = len(prim)
        position = torch.zeros(n, 3)
        geo = torch.zeros(n, 3)
        position[idx] = (self._vertices_t[f] * w).sum(1)   # on the triangle: what ray offsets rely on

        normal = torch.zeros(n, 3)
        normal[idx] = interpolate_normals(self._normals_t[f], w.squeeze(-1))
        lookup = normal
        if self._lookup_t is not self._normals_t:
            lookup = torch.zeros(n, 3)
            lookup[idx] = interpolate_normals(self._lookup_t[f], w.squeeze(-1))
        geo[idx] = self._face_normals_t[tri]
        t_all = torch.where(valid, torch.from_numpy(tfar), torch.tensor(float("inf")))

        def out(a: Tensor, *tail: int) -> Tensor:
            return a.to(device=dev, dtype=dtype if a.is_floating_point() else a.dtype).reshape(*bs, *tail)

        return SurfaceHit(valid=out(valid), t=out(t_all), position=out(position, 3), normal=out(normal, 3),
                          geometric_normal=out(geo, 3), lookup_normal=out(lookup, 3),
                          triangle_id=out(torch.where(valid, prim_t, -1)))

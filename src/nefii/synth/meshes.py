"""Procedural triangle meshes in numpy: surfaces of revolution, tori, boxes; merging and PLY output.

Every builder returns a :class:`TriMesh` with smooth per-vertex normals where the surface is
smooth and split vertices at creases, triangles wound counter-clockwise seen from outside
(the geometric normal agrees with the shading normal), and local texture coordinates in
[0, 1]^2 that a scene later places into its texture atlas.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..io.atomic import atomic_path


@dataclass(frozen=True)
class TriMesh:
    """An indexed triangle mesh."""

    vertices: np.ndarray
    """(V, 3) float64 positions"""
    faces: np.ndarray
    """(F, 3) int64 vertex indices, counter-clockwise seen from outside"""
    normals: np.ndarray
    """(V, 3) float64 unit shading normals, pointing out"""
    uv: np.ndarray
    """(V, 2) float64 texture coordinates in [0, 1]"""

    def transformed(self, rotation: np.ndarray | None = None, translation=(0.0, 0.0, 0.0),
                    scale: float = 1.0) -> "TriMesh":
        """``x -> R (s x) + t``; normals rotate with ``R``."""
        R = np.eye(3) if rotation is None else np.asarray(rotation, dtype=np.float64)
        v = (scale * self.vertices) @ R.T + np.asarray(translation, dtype=np.float64)
        return TriMesh(v, self.faces, self.normals @ R.T, self.uv)

    def with_uv(self, uv: np.ndarray) -> "TriMesh":
        return TriMesh(self.vertices, self.faces, self.normals, uv)

    def face_normals(self) -> np.ndarray:
        """(F, 3) unit geometric normals from the winding."""
        a, b, c = (self.vertices[self.faces[:, k]] for k in range(3))
        n = np.cross(b - a, c - a)
        return n / np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-30)


def merge(meshes: list[TriMesh]) -> TriMesh:
    """Concatenate meshes into one (no welding)."""
    offsets = np.cumsum([0] + [len(m.vertices) for m in meshes[:-1]])
    return TriMesh(np.concatenate([m.vertices for m in meshes]),
                   np.concatenate([m.faces + o for m, o in zip(meshes, offsets)]),
                   np.concatenate([m.normals for m in meshes]),
                   np.concatenate([m.uv for m in meshes]))


def rotation(axis, angle: float) -> np.ndarray:
    """Rodrigues rotation matrix about ``axis`` by ``angle`` radians (right-handed)."""
    k = np.asarray(axis, dtype=np.float64)
    k = k / np.linalg.norm(k)
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * (K @ K)


# ---------------------------------------------------------------- grids

def grid_mesh(P: np.ndarray, N: np.ndarray, uv: np.ndarray | None = None) -> TriMesh:
    """Triangulate an ``(I, J)`` grid of points ``P`` with normals ``N`` (both ``(I, J, 3)``).

    Each quad becomes two triangles wound to agree with the averaged vertex normal;
    zero-area triangles (at poles) are dropped. ``uv`` defaults to ``(j/(J-1), i/(I-1))``.
    """
    I, J = P.shape[:2]
    if uv is None:
        s, t = np.meshgrid(np.linspace(0, 1, J), np.linspace(0, 1, I))
        uv = np.stack([s, t], -1)
    idx = np.arange(I * J).reshape(I, J)
    a, b = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel()
    c, d = idx[1:, :-1].ravel(), idx[1:, 1:].ravel()
    faces = np.concatenate([np.stack([a, b, d], -1), np.stack([a, d, c], -1)])
    V, Nv = P.reshape(-1, 3).astype(np.float64), N.reshape(-1, 3).astype(np.float64)
    Nv = Nv / np.maximum(np.linalg.norm(Nv, axis=-1, keepdims=True), 1e-30)
    p0, p1, p2 = V[faces[:, 0]], V[faces[:, 1]], V[faces[:, 2]]
    fn = np.cross(p1 - p0, p2 - p0)
    area2 = np.linalg.norm(fn, axis=-1)
    keep = area2 > 1e-12 * max(1.0, float(np.abs(V).max()) ** 2)
    flip = (fn * (Nv[faces[:, 0]] + Nv[faces[:, 1]] + Nv[faces[:, 2]])).sum(-1) < 0
    faces = np.where(flip[:, None], faces[:, [0, 2, 1]], faces)[keep]
    return TriMesh(V, faces.astype(np.int64), Nv, uv.reshape(-1, 2).astype(np.float64))


def profile_normals(r: np.ndarray, z: np.ndarray) -> np.ndarray:
    """Outward normals ``(n_r, n_z)`` of a smooth profile traversed with the solid on its left."""
    dr, dz = np.gradient(r), np.gradient(z)
    n = np.stack([dz, -dr], -1)
    return n / np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-30)


def revolve(segments: list[tuple[np.ndarray, np.ndarray]], n_around: int,
            sweep: tuple[float, float] = (0.0, 2.0 * np.pi)) -> TriMesh:
    """Surface of revolution about +Z of a profile given as smooth ``(r, z)`` segments.

    Segments meet at creases (their end points are duplicated with their own normals).
    ``sweep`` is the range of azimuth (a partial sweep leaves the ends open).
    Texture ``u`` runs along the sweep (0 to 1), ``v`` along the whole profile by arc length.
    """
    lengths = [np.sum(np.hypot(np.diff(r), np.diff(z))) for r, z in segments]
    total, start = float(sum(lengths)), 0.0
    phi = np.linspace(sweep[0], sweep[1], n_around + 1)
    cos, sin = np.cos(phi)[None, :], np.sin(phi)[None, :]
    parts = []
    for (r, z), length in zip(segments, lengths):
        nrz = profile_normals(r, z)
        s = start + np.concatenate([[0.0], np.cumsum(np.hypot(np.diff(r), np.diff(z)))])
        start += length
        P = np.stack([r[:, None] * cos, r[:, None] * sin, np.broadcast_to(z[:, None], (len(r), n_around + 1))], -1)
        N = np.stack([nrz[:, :1] * cos, nrz[:, :1] * sin,
                      np.broadcast_to(nrz[:, 1:], (len(r), n_around + 1))], -1)
        uu, vv = np.meshgrid((phi - sweep[0]) / (sweep[1] - sweep[0]), s / total)
        parts.append(grid_mesh(P, N, np.stack([uu, vv], -1)))
    return merge(parts)


def arc(center_r: float, center_z: float, radius: float, a0: float, a1: float, n: int):
    """Profile arc from angle ``a0`` to ``a1`` (radians, measured from +r towards +z)."""
    a = np.linspace(a0, a1, n)
    return center_r + radius * np.cos(a), center_z + radius * np.sin(a)


def line(p0, p1, n: int):
    """Straight profile segment from ``(r0, z0)`` to ``(r1, z1)``."""
    t = np.linspace(0.0, 1.0, n)
    return p0[0] + t * (p1[0] - p0[0]), p0[1] + t * (p1[1] - p0[1])


# ---------------------------------------------------------------- primitives

def sphere(radius: float, n_lat: int = 32, n_lon: int = 64) -> TriMesh:
    return revolve([arc(0.0, 0.0, radius, -np.pi / 2, np.pi / 2, n_lat + 1)], n_lon)


def torus(major: float, minor: float, n_major: int = 96, n_minor: int = 32,
          sweep: tuple[float, float] = (0.0, 2.0 * np.pi)) -> TriMesh:
    """Torus about +Z (or a section of one); texture ``u`` around the ring, ``v`` around the tube."""
    return revolve([arc(major, 0.0, minor, -np.pi, np.pi, n_minor + 1)], n_major, sweep)


def box(size, n: int = 8) -> TriMesh:
    """Axis-aligned box centred at the origin; faces laid out 3 x 2 in texture space."""
    half = np.asarray(size, dtype=np.float64) / 2.0
    t = np.linspace(-1.0, 1.0, n + 1)
    a, b = np.meshgrid(t, t)
    faces = []
    for k, (axis, sign) in enumerate([(0, 1), (0, -1), (1, 1), (1, -1), (2, 1), (2, -1)]):
        u_ax, v_ax = [i for i in range(3) if i != axis]
        P = np.zeros(a.shape + (3,))
        P[..., axis], P[..., u_ax], P[..., v_ax] = sign, a, b
        N = np.zeros_like(P)
        N[..., axis] = sign
        col, row = k % 3, k // 3
        uv = np.stack([(col + 0.5 * (a + 1)) / 3.0, (row + 0.5 * (b + 1)) / 2.0], -1)
        faces.append(grid_mesh(P * half, N, uv))
    return merge(faces)


def chain(*pieces) -> tuple[np.ndarray, np.ndarray]:
    """Join tangent-continuous profile pieces into one smooth segment (shared end points once)."""
    r = np.concatenate([pieces[0][0]] + [p[0][1:] for p in pieces[1:]])
    z = np.concatenate([pieces[0][1]] + [p[1][1:] for p in pieces[1:]])
    return r, z


def rounded_slab(radius: float, thickness: float, bevel: float, n_around: int = 96) -> TriMesh:
    """A round plinth centred at the origin: flat top and bottom, edges rounded with radius ``bevel``."""
    h, rb = thickness / 2.0, radius - bevel
    return revolve([chain(line((0.0, -h), (rb, -h), 8), arc(rb, -h + bevel, bevel, -np.pi / 2, 0.0, 6),
                          line((radius, -h + bevel), (radius, h - bevel), 3),
                          arc(rb, h - bevel, bevel, 0.0, np.pi / 2, 6), line((rb, h), (0.0, h), 8))], n_around)


# ---------------------------------------------------------------- output

def write_ply(path: str | Path, mesh: TriMesh) -> None:
    """Binary little-endian PLY with positions, normals and triangles (float32, int32)."""
    V = len(mesh.vertices)
    header = ("ply\nformat binary_little_endian 1.0\ncomment nefii synth ground-truth mesh, world coordinates\n"
              f"element vertex {V}\nproperty float x\nproperty float y\nproperty float z\n"
              "property float nx\nproperty float ny\nproperty float nz\n"
              f"element face {len(mesh.faces)}\nproperty list uchar int vertex_indices\nend_header\n")
    vert = np.concatenate([mesh.vertices, mesh.normals], -1).astype("<f4")
    face = np.empty(len(mesh.faces), dtype=[("n", "u1"), ("i", "<i4", (3,))])
    face["n"], face["i"] = 3, mesh.faces
    with atomic_path(path) as tmp:
        tmp.write_bytes(header.encode("ascii") + vert.tobytes() + face.tobytes())

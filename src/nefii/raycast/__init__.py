"""Frozen geometry: ray casting behind a small interface (see ``base.Geometry``)."""
from .base import Geometry, Rays, SurfaceHit, spawn_rays
from .mesh import MeshGeometry

__all__ = ["Geometry", "MeshGeometry", "Rays", "SurfaceHit", "spawn_rays"]

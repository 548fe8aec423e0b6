"""Where a run's frozen geometry comes from: a mesh, or the output folder of ``nefii geometry``
(its mesh, or its SDF sphere-traced with the feature vector f). One place for fit, eval and relight."""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path

from ..errors import InputError
from ..fields.features import FeatureField
from ..raycast import MeshGeometry
from ..raycast.base import Geometry
from .config import FitConfig

MODES = ("mesh", "sdf")


@dataclass(frozen=True)
class GeometrySource:
    mode: str
    """``mesh``: triangles ray-cast by Embree; ``sdf``: the SDF of ``folder`` sphere-traced"""
    mesh: Path
    """the triangle mesh (the one export and view use in either mode)"""
    folder: Path | None = None
    """the ``nefii geometry`` output, if the geometry came from one"""
    normal_sigma: float = 0.0
    """``mesh`` mode: the vertex normals are smoothed along the surface to this lateral scale, a fraction of
    the bounding-box diagonal (0: as computed from the triangles)"""
    lookup_sigma: float = 0.0
    """``mesh`` mode: the material lookup's normals (:attr:`SurfaceHit.lookup_normal`) smoothed to this scale
    (0: the shading normals)"""

    def to_dict(self) -> dict:
        return {"mode": self.mode, "mesh": str(self.mesh), "folder": None if self.folder is None else str(self.folder),
                "normal_sigma": self.normal_sigma, "lookup_sigma": self.lookup_sigma}

    @staticmethod
    def from_dict(d: dict) -> "GeometrySource":
        return GeometrySource(d["mode"], Path(d["mesh"]), None if d.get("folder") is None else Path(d["folder"]),
                              float(d.get("normal_sigma", 0.0)), float(d.get("lookup_sigma", 0.0)))

    def open(self) -> tuple[Geometry, FeatureField | None]:
        """The geometry to cast rays against and, in ``sdf`` mode, the feature field for the fields."""
        if self.mode == "sdf":
            from ..sdf.outputs import load_sdf
            from ..sdf.trace import SDFGeometry
            assert self.folder is not None
            loaded = load_sdf(self.folder)
            features = FeatureField(loaded.sdf, loaded.normalization.center, loaded.normalization.radius)
            return SDFGeometry(loaded.sdf, loaded.normalization), features
        return self.open_mesh(), None

    def open_mesh(self, threads: int | None = None) -> MeshGeometry:
        """The triangle mesh with the vertex normals the fit used (what ``mesh`` mode casts, and what export
        and view bake in either mode)."""
        return MeshGeometry.from_file(self.mesh, normal_sigma=self.normal_sigma, lookup_sigma=self.lookup_sigma,
                                      threads=threads)


def resolve_source(mesh: Path | None, geometry: Path | None, scene_mesh: Path | None, mode: str,
                   data: Path) -> GeometrySource:
    """``--mesh`` or ``--geometry`` (not both), else the scene's own mesh."""
    if mode not in MODES:
        raise InputError(None, f"geometry_mode must be one of {', '.join(MODES)}, got {mode!r}")
    if mesh is not None and geometry is not None:
        raise InputError(geometry, "give --mesh or --geometry, not both")
    if geometry is not None:
        if not (geometry / "sdf.pt").is_file() or not (geometry / "mesh.ply").is_file():
            raise InputError(geometry, "not a nefii geometry folder (needs sdf.pt and mesh.ply: run nefii geometry)")
        return GeometrySource(mode, (geometry / "mesh.ply").resolve(), geometry.resolve())
    if mode == "sdf":
        raise InputError(None, "geometry_mode=sdf needs --geometry GEO (the output of nefii geometry)")
    path = mesh or scene_mesh
    if path is None:
        raise InputError(data, "no geometry: the dataset has no mesh.ply; pass --mesh PATH or --geometry GEO "
                               "(run nefii geometry first)")
    return GeometrySource("mesh", Path(path).resolve())


def adapt_to_source(cfg: FitConfig, source: GeometrySource) -> tuple[FitConfig, GeometrySource]:
    """``cfg`` and ``source`` as they apply to this geometry: a reconstruction (the folder of ``nefii
    geometry``) takes ``material_offset_reconstructed`` as its material offset and, in ``mesh`` mode, its
    vertex normals smoothed by ``normal_smoothing_reconstructed``, the material lookup's by
    ``lookup_smoothing_reconstructed``; a given mesh keeps all as they are."""
    if source.folder is None:
        return cfg, source
    mesh_mode = source.mode == "mesh"
    return (dataclasses.replace(cfg, material_offset=cfg.material_offset_reconstructed),
            dataclasses.replace(source, normal_sigma=cfg.normal_smoothing_reconstructed if mesh_mode else 0.0,
                                lookup_sigma=cfg.lookup_smoothing_reconstructed if mesh_mode else 0.0))

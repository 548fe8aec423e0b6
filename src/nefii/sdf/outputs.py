"""What the geometry stage leaves in ``GEO/`` and how later stages read it back."""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path

import torch

from ..errors import InputError
from ..fit.build import make_encoding
from ..io.atomic import atomic_path
from ..io.safe_load import load_tensors
from .config import GeometryConfig, geometry_config_from_dict
from .networks import SDFNetwork
from .normalization import Normalization

SDF_FILE, MESH_FILE, NORMALIZATION_FILE = "sdf.pt", "mesh.ply", "normalization.json"


def save_sdf(folder: Path, cfg: GeometryConfig, sdf: SDFNetwork, norm: Normalization, source: str) -> None:
    with atomic_path(folder / SDF_FILE) as tmp:
        torch.save({"config": dataclasses.asdict(cfg), "sdf": sdf.state_dict(), "source": source,
                    "normalization": {"center": list(norm.center), "radius": norm.radius}}, tmp)
    norm.save(folder / NORMALIZATION_FILE)


@dataclass(frozen=True)
class LoadedSDF:
    sdf: SDFNetwork
    normalization: Normalization
    config: GeometryConfig
    mesh_path: Path


def load_sdf(folder: Path, device: torch.device | str = "cpu") -> LoadedSDF:
    """The frozen SDF network and normalisation of a ``nefii geometry`` output folder."""
    path = Path(folder) / SDF_FILE
    if not path.is_file():
        raise InputError(folder, f"no {SDF_FILE}: not a nefii geometry folder (run nefii geometry first)")
    state = load_tensors(path, device)
    try:
        cfg = geometry_config_from_dict(state["config"])
        net = SDFNetwork(make_encoding(cfg.sdf.encoding), cfg.sdf.hidden, cfg.sdf.layers, cfg.feature_dim,
                         cfg.init_radius)
        net.load_state_dict(state["sdf"])
        net.requires_grad_(False)                                  # frozen from here on (paper Sec. 3.1)
        n = state["normalization"]
        norm = Normalization(tuple(float(c) for c in n["center"]), float(n["radius"]))  # type: ignore[arg-type]
    except (OSError, RuntimeError, KeyError, TypeError, ValueError) as e:
        raise InputError(path, f"cannot read the SDF ({type(e).__name__}: {e})") from None
    return LoadedSDF(net.to(device).eval(), norm, cfg, Path(folder) / MESH_FILE)

"""What a fit leaves in its run folder, and how eval/relight/export read it back.

    RUN/config.json        the resolved FitConfig (read back through the same dataclasses)
    RUN/model.pt           fields' weights + config + scene box + data path + geometry source (and, in
                           sdf mode, the frozen SDF that supplies the feature vector f)
    RUN/envmap.exr         the recovered SGs as an equirectangular image (docs/design.md mapping)
    RUN/sg.npy             (K, 7) float32: axis xyz, sharpness, amplitude rgb (SG light only)
    RUN/checkpoints/       resumable training state (step_XXXXXXX.pt, atomic)

The recovered material is read back only through :func:`nefii.fit.model.decode_material`.
"""
from __future__ import annotations

import copy
import dataclasses
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from ..errors import InputError
from ..io.atomic import atomic_path, write_text_atomic
from ..fields.environment import SGEnvironment
from ..fields.features import FeatureField
from ..io.exr import write_exr
from ..io.safe_load import load_tensors
from ..render.sg import SGMixture
from .build import build_model, make_encoding
from .config import FitConfig, config_to_dict, saved_config_from_dict
from .geometry_source import GeometrySource
from .model import NeFIIModel
from .units import rescale_radiance

ENVMAP_SIZE = (256, 512)


@dataclass(frozen=True)
class FittedRun:
    folder: Path
    config: FitConfig
    model: NeFIIModel
    data: Path
    """the dataset the run was fitted on"""
    mesh: Path
    """the frozen geometry's triangle mesh"""
    geometry: GeometrySource
    """where the geometry came from (mesh or a nefii geometry folder, and how it is cast)"""
    box: tuple[torch.Tensor, torch.Tensor]
    """corners of the geometry's bounding box the fields were built over (CPU)"""

    def open_geometry(self):
        """The run's geometry for rays (sphere-traced SDF in ``sdf`` mode, else the mesh)."""
        return self.geometry.open()[0]


def sg_array(sg: SGMixture) -> np.ndarray:
    """``(K, 7)``: axis, sharpness, amplitude."""
    return torch.cat([sg.axis, sg.sharpness.unsqueeze(-1), sg.amplitude], -1).detach().cpu().float().numpy()


def write_config(folder: Path, cfg: FitConfig) -> None:
    write_text_atomic(folder / "config.json", json.dumps(config_to_dict(cfg), indent=2) + "\n")


def read_config(folder: Path) -> FitConfig:
    path = folder / "config.json"
    try:
        return saved_config_from_dict(json.loads(path.read_text()))
    except FileNotFoundError:
        raise InputError(path, "not found: is this a nefii run folder?") from None
    except (ValueError, KeyError, TypeError) as e:     # JSONDecodeError is a ValueError
        raise InputError(path, f"not a valid nefii config ({e.args[0] if e.args else type(e).__name__})") from None


def write_outputs(folder: Path, cfg: FitConfig, model: NeFIIModel, box: tuple[torch.Tensor, torch.Tensor],
                  data: Path, source: GeometrySource, radiance_unit: float) -> None:
    """model.pt, envmap.exr, sg.npy (each written atomically), in the images' units of radiance: ``model`` was
    trained in units of ``radiance_unit`` of them (:mod:`nefii.fit.units`) and is written scaled back (a copy;
    ``model`` is left as it is). model.pt is self-contained: with an SDF's feature field, the frozen SDF's
    weights and its configuration are in it too."""
    if radiance_unit != 1.0:
        model = copy.deepcopy(model)
        rescale_radiance(model, radiance_unit)
    feats = model.material.features
    sdf_blob = None if feats is None else {"config": dataclasses.asdict(source_config(source)),
                                           "center": feats.center.tolist(), "radius": feats.radius}
    with atomic_path(folder / "model.pt") as tmp:
        torch.save({"config": config_to_dict(cfg), "state": model.state_dict(), "box": [b.cpu() for b in box],
                    "data": str(data), "mesh": str(source.mesh), "geometry": source.to_dict(), "sdf": sdf_blob}, tmp)
    with torch.no_grad():
        write_exr(folder / "envmap.exr", model.env.to_equirect(*ENVMAP_SIZE).cpu().numpy())
        if isinstance(model.env, SGEnvironment):
            with atomic_path(folder / "sg.npy") as tmp:
                np.save(tmp, sg_array(model.env()))


def write_exposure(folder: Path, names: tuple[str, ...], gains: torch.Tensor) -> None:
    """``exposure.json``: each training view's learned RGB gain (``exposure = per_view``), by image file; their
    geometric mean is 1 per channel."""
    rows = {name: [round(float(x), 5) for x in g] for name, g in zip(names, gains.detach().cpu())}
    write_text_atomic(folder / "exposure.json", json.dumps({"gains": rows}, indent=2) + "\n")


def load_run(folder: str | Path, device: torch.device | str = "cpu") -> FittedRun:
    folder = Path(folder)
    path = folder / "model.pt"
    if not path.is_file():
        raise InputError(path, "not found: has `nefii fit` finished in this folder?")
    blob = load_tensors(path)
    try:
        cfg = saved_config_from_dict(blob["config"])
        features = None
        if blob.get("sdf") is not None:
            from ..sdf.config import geometry_config_from_dict
            from ..sdf.networks import SDFNetwork
            gcfg = geometry_config_from_dict(blob["sdf"]["config"])
            net = SDFNetwork(make_encoding(gcfg.sdf.encoding), gcfg.sdf.hidden, gcfg.sdf.layers, gcfg.feature_dim,
                             gcfg.init_radius)
            features = FeatureField(net, tuple(blob["sdf"]["center"]), blob["sdf"]["radius"])
        model = build_model(cfg, tuple(blob["box"]), features)
        model.load_state_dict(blob["state"])
        source = GeometrySource.from_dict(blob["geometry"]) if "geometry" in blob else \
            GeometrySource("mesh", Path(blob["mesh"]))
    except Exception as e:
        raise InputError(path, f"not a readable nefii model ({type(e).__name__}: {e})") from None
    return FittedRun(folder, cfg, model.to(device).eval(), Path(blob["data"]), Path(blob["mesh"]), source,
                     tuple(blob["box"]))


def source_config(source: GeometrySource):
    """The geometry stage's configuration of an ``sdf``-mode source."""
    from ..sdf.outputs import load_sdf
    assert source.folder is not None
    return load_sdf(source.folder).config

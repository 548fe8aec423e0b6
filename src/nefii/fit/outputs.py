"""What a fit leaves in its run folder, and how eval/relight/export read it back.

    RUN/config.json        the resolved FitConfig (read back through the same dataclasses)
    RUN/model.pt           fields' weights + config + scene box + data and mesh paths
    RUN/envmap.exr         the recovered SGs as an equirectangular image (docs/design.md mapping)
    RUN/sg.npy             (K, 7) float32: axis xyz, sharpness, amplitude rgb (SG light only)
    RUN/checkpoints/       resumable training state (step_XXXXXXX.pt, atomic)

``material_at`` is the one decode of the recovered material at given surface points, the same
``model.material`` call that ``path_trace`` makes (fit, eval, relight); export bakes it into
textures.
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from ..errors import InputError
from ..io.atomic import atomic_path, write_text_atomic
from ..io.exr import write_exr
from ..fields.environment import SGEnvironment
from ..render.brdf import Material
from ..render.sg import SGMixture
from .build import build_model
from .config import FitConfig, config_from_dict, config_to_dict
from .model import NeFIIModel

ENVMAP_SIZE = (256, 512)


@dataclass(frozen=True)
class FittedRun:
    folder: Path
    config: FitConfig
    model: NeFIIModel
    data: Path
    """the dataset the run was fitted on"""
    mesh: Path
    """the frozen geometry"""


def sg_array(sg: SGMixture) -> np.ndarray:
    """``(K, 7)``: axis, sharpness, amplitude."""
    return torch.cat([sg.axis, sg.sharpness.unsqueeze(-1), sg.amplitude], -1).detach().cpu().float().numpy()


def write_config(folder: Path, cfg: FitConfig) -> None:
    write_text_atomic(folder / "config.json", json.dumps(config_to_dict(cfg), indent=2) + "\n")


def read_config(folder: Path) -> FitConfig:
    path = folder / "config.json"
    try:
        return config_from_dict(json.loads(path.read_text()))
    except FileNotFoundError:
        raise InputError(path, "not found: is this a nefii run folder?") from None
    except (json.JSONDecodeError, KeyError, TypeError) as e:
        raise InputError(path, f"not a valid nefii config ({e})") from None


def write_outputs(folder: Path, cfg: FitConfig, model: NeFIIModel, box: tuple[torch.Tensor, torch.Tensor],
                  data: Path, mesh: Path) -> None:
    """model.pt, envmap.exr, sg.npy (each written atomically)."""
    with atomic_path(folder / "model.pt") as tmp:
        torch.save({"config": config_to_dict(cfg), "state": model.state_dict(),
                    "box": [b.cpu() for b in box], "data": str(data), "mesh": str(mesh)}, tmp)
    with torch.no_grad():
        write_exr(folder / "envmap.exr", model.env.to_equirect(*ENVMAP_SIZE).cpu().numpy())
        if isinstance(model.env, SGEnvironment):
            with atomic_path(folder / "sg.npy") as tmp:
                np.save(tmp, sg_array(model.env()))


def load_run(folder: str | Path, device: torch.device | str = "cpu") -> FittedRun:
    folder = Path(folder)
    path = folder / "model.pt"
    if not path.is_file():
        raise InputError(path, "not found: has `nefii fit` finished in this folder?")
    try:
        blob = torch.load(path, map_location="cpu", weights_only=False)
        cfg = config_from_dict(blob["config"])
        model = build_model(cfg, tuple(blob["box"]))
        model.load_state_dict(blob["state"])
    except Exception as e:
        raise InputError(path, f"not a readable nefii model ({type(e).__name__}: {e})") from None
    return FittedRun(folder, cfg, model.to(device).eval(), Path(blob["data"]), Path(blob["mesh"]))


@torch.no_grad()
def material_at(model: NeFIIModel, points: torch.Tensor, chunk: int = 65536,
                progress: Callable[[int], None] | None = None) -> Material:
    """The fitted material at world points ``(N, 3)``, decoded in chunks without gradient.

    Returns albedo ``(N, 3)`` (linear, [0, 1]) and roughness ``(N,)`` on the model's device;
    ``progress(n)`` is called with the number of points done after each chunk.
    """
    device = next(model.parameters()).device
    albedo, roughness = [], []
    for part in points.split(chunk):
        m = model.material(part.to(device=device, dtype=torch.float32))
        albedo.append(m.albedo)
        roughness.append(m.roughness)
        if progress is not None:
            progress(len(part))
    if not albedo:
        return Material(torch.zeros(0, 3, device=device), torch.zeros(0, device=device))
    return Material(torch.cat(albedo), torch.cat(roughness))

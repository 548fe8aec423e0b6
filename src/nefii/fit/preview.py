"""Preview images during a fit: one training view, path-traced with a few samples, beside its photo."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from ..data.scene import SceneData
from ..evaluate.render_views import render_view
from ..evaluate.outputs import tonemap_display
from ..raycast.base import Geometry
from ..io.images import linear_to_srgb, write_png
from .model import NeFIIModel
from .path_trace import Transport


@torch.no_grad()
def write_preview(path: Path, model: NeFIIModel, geometry: Geometry, scene: SceneData, view: int,
                  transport: Transport, num_samples: int = 4, seed: int = 0, radiance_unit: float = 1.0) -> None:
    """``path``: photo | path-traced | cache | albedo | roughness of training view ``view`` (PNG); ``model``'s
    radiance in units of ``radiance_unit`` of the photo's (:mod:`nefii.fit.units`)."""
    g = torch.Generator(device=next(model.parameters()).device).manual_seed(seed)
    was_training = model.training
    model.eval()
    pred = render_view(model, geometry, scene.cameras, view, num_samples, g, transport, filtered_layers=False)
    model.train(was_training)
    mask = pred.mask.cpu().numpy()[..., None]
    photo = scene.images[view].numpy()
    tiles = [tonemap_display(photo), tonemap_display(pred.rgb.cpu().numpy() * mask * radiance_unit),
             tonemap_display(pred.cache.cpu().numpy() * radiance_unit),
             linear_to_srgb(pred.albedo.cpu().numpy()), np.repeat(pred.roughness.cpu().numpy()[..., None], 3, -1)]
    write_png(path, np.concatenate(tiles, 1), srgb=False)

"""A camera view through the path tracer: ``spp`` paths per pixel, box-filtered, chunked for memory.

Each path starts at a uniformly jittered point of its pixel (a box filter, as the ground truth of
``nefii synth`` is rendered), so the fraction of paths that hit the object is the pixel's
coverage (the alpha of an RGBA EXR) and the mean over those paths its straight colour.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
from jaxtyping import Float
from torch import Tensor

from ..camera import jittered_pixel_rays
from ..raycast.base import Geometry, Rays
from ..render.envmap import Environment
from .pathtracer import MaterialFn, PathSettings, trace_paths

MAX_PATHS = 1 << 17
"""paths traced together (memory: a few hundred bytes each)"""


@dataclass(frozen=True)
class RelitImage:
    rgb: Float[Tensor, "H W 3"]
    """straight colour: the mean over the pixel's paths that hit the object; 0 where none did"""
    coverage: Float[Tensor, "H W"]
    """fraction of the pixel's paths that hit the object"""

    @property
    def premultiplied(self) -> Float[Tensor, "H W 3"]:
        """colour times coverage: the RGB of an RGBA EXR (background counted as 0)"""
        return self.rgb * self.coverage.unsqueeze(-1)


@torch.no_grad()
def render_relit(geometry: Geometry, material: MaterialFn, env: Environment, c2w: Float[Tensor, "4 4"],
                 K: Float[Tensor, "3 3"], height: int, width: int, spp: int, generator: torch.Generator | None,
                 settings: PathSettings = PathSettings(), max_paths: int = MAX_PATHS) -> RelitImage:
    """Path-trace one ``height x width`` view with ``spp`` jittered paths per pixel (on ``env``'s device).

    Rays are built in float64 from the float64 cameras and traced in float32.
    """
    dev = env.image.device
    n_px = height * width
    total = torch.zeros(n_px, 3, device=dev)
    hits = torch.zeros(n_px, device=dev)
    for start in range(0, n_px * spp, max_paths):
        path = torch.arange(start, min(start + max_paths, n_px * spp), device=dev)
        pixel = path // spp
        u = torch.rand(len(path), 2, generator=generator, device=dev, dtype=torch.float32)
        o, d = jittered_pixel_rays(c2w.to(dev), K.to(dev), width, pixel, u.double())
        out = trace_paths(Rays(o.float(), d.float()), geometry, material, env,
                          generator, settings)
        total.index_add_(0, pixel, out.radiance)
        hits.index_add_(0, pixel, out.hit.float())
    rgb = torch.where(hits.unsqueeze(-1) > 0, total / hits.clamp_min(1.0).unsqueeze(-1), torch.zeros_like(total))
    return RelitImage(rgb=rgb.reshape(height, width, 3), coverage=(hits / spp).reshape(height, width))

"""Render what a fitted model predicts for a camera: path-traced colour and its parts, the
material, the normal and the radiance cache's own colour (its "neural rendering")."""
from __future__ import annotations

from dataclasses import dataclass

import torch
from jaxtyping import Bool, Float
from torch import Tensor

from ..camera import pixel_rays
from ..data.scene import Cameras
from ..fit.model import NeFIIModel, decode_material
from ..fit.path_trace import SurfacePoints, Transport, path_trace
from ..raycast.base import Geometry, Rays


@dataclass(frozen=True)
class ViewPrediction:
    """One view; linear values; object quantities are 0 outside ``mask``."""

    rgb: Float[Tensor, "H W 3"]
    """path-traced colour (Eq. 2-4), the environment where the view ray escapes"""
    specular: Float[Tensor, "H W 3"]
    """the specular lobe's share of ``rgb`` on the object"""
    diffuse: Float[Tensor, "H W 3"]
    albedo: Float[Tensor, "H W 3"]
    roughness: Float[Tensor, "H W"]
    normal: Float[Tensor, "H W 3"]
    cache: Float[Tensor, "H W 3"]
    """the radiance cache's L(x, n, wo) at the first hit"""
    mask: Bool[Tensor, "H W"]
    """where the view ray hits the geometry"""


@torch.no_grad()
def render_view(model: NeFIIModel, geometry: Geometry, cameras: Cameras, view: int, num_samples: int,
                generator: torch.Generator | None, transport: Transport = Transport(), chunk: int = 2048
                ) -> ViewPrediction:
    H, W = cameras.height, cameras.width
    device = next(model.parameters()).device
    o, d = pixel_rays(cameras.c2w[view].cpu(), cameras.K[view].cpu(), H, W)
    o, d = o.reshape(-1, 3).float().to(device), d.reshape(-1, 3).float().to(device)
    hit = geometry.intersect(Rays(o, d))
    idx = hit.valid.nonzero().squeeze(-1)
    n_px = H * W
    rgb = model.env.radiance(d)
    out = {k: torch.zeros(n_px, 3, device=device) for k in ("specular", "diffuse", "albedo", "normal", "cache")}
    rough = torch.zeros(n_px, device=device)
    for c in idx.split(chunk):
        pts = SurfacePoints.from_hit(hit, c, -d[c])
        material = decode_material(model, pts.position, pts.lookup_normal)
        traced = path_trace(model, geometry, pts, material, num_samples, generator, transport)
        rgb[c] = traced.radiance.rgb
        out["specular"][c] = traced.radiance.specular
        out["diffuse"][c] = traced.radiance.diffuse
        out["albedo"][c] = material.albedo
        rough[c] = material.roughness
        out["normal"][c] = pts.normal
        out["cache"][c] = model.cache(pts.position, pts.normal, pts.wo)
    shape3 = (H, W, 3)
    return ViewPrediction(rgb=rgb.reshape(shape3), roughness=rough.reshape(H, W), mask=hit.valid.reshape(H, W),
                          **{k: v.reshape(shape3) for k, v in out.items()})

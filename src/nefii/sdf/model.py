"""The NeuS model (SDF, colour, sharpness, optional background) and the rendering of a batch of rays."""
from __future__ import annotations

from dataclasses import dataclass

import torch
from jaxtyping import Float
from torch import Tensor, nn

from ..fit.build import make_encoding
from ..fit.exposure import ViewGains
from .config import GeometryConfig
from .networks import Background, ColorNetwork, SDFNetwork, Sharpness
from .volume import composite_weights, neus_alpha, sphere_bounds, stratified_depths, upsample_depths


class NeuSModel(nn.Module):
    def __init__(self, cfg: GeometryConfig, background: bool, num_views: int | None = None) -> None:
        """``num_views``: the training views, which get a gain each with ``exposure = per_view`` (trained with
        the rest); None: no views (an SDF fitted to a mesh)."""
        super().__init__()
        torch.manual_seed(cfg.seed)
        self.sdf = SDFNetwork(make_encoding(cfg.sdf.encoding), cfg.sdf.hidden, cfg.sdf.layers, cfg.feature_dim,
                              cfg.init_radius)
        self.color = ColorNetwork(cfg.feature_dim, cfg.color.hidden, cfg.color.layers, cfg.view_freqs,
                                  make_encoding(cfg.color.encoding) if cfg.appearance_encoding else None)
        self.sharpness = Sharpness()
        self.background = Background() if background else None
        self.gains = ViewGains(num_views) if cfg.exposure == "per_view" and num_views is not None else None


@dataclass(frozen=True)
class RenderedRays:
    rgb: Float[Tensor, "R 3"]
    """object radiance plus, with a background model, what shows through"""
    opacity: Float[Tensor, " R"]
    """sum of the object's weights along each ray"""
    gradient: Float[Tensor, "R S 3"]
    """SDF gradient at the section midpoints (for the eikonal loss)"""
    inside: Float[Tensor, "R S"]
    """1 where a midpoint lies inside the unit sphere"""
    depth: Float[Tensor, " R"]
    """expected depth of the object part (weights normalised)"""


def render_rays(model: NeuSModel, o: Float[Tensor, "R 3"], d: Float[Tensor, "R 3"], cfg: GeometryConfig,
                generator: torch.Generator | None, train: bool, cos_anneal: float = 1.0) -> RenderedRays:
    """NeuS volume rendering of rays in normalised coordinates (unit directions)."""
    near, far, hit = sphere_bounds(o, d)
    far = torch.where(hit, far, near + 1e-3)
    z = stratified_depths(near, far, cfg.samples, generator, perturb=train)
    if cfg.importance > 0 and cfg.importance_rounds > 0:
        per_round = max(cfg.importance // cfg.importance_rounds, 1)
        with torch.no_grad():
            sdf = model.sdf.sdf(o.unsqueeze(1) + z.unsqueeze(-1) * d.unsqueeze(1))
            for i in range(cfg.importance_rounds):
                new = upsample_depths(z, sdf, per_round, 64.0 * 2**i)
                z, order = torch.sort(torch.cat([z, new], -1), -1)
                if i + 1 < cfg.importance_rounds:
                    sdf_new = model.sdf.sdf(o.unsqueeze(1) + new.unsqueeze(-1) * d.unsqueeze(1))
                    sdf = torch.cat([sdf, sdf_new], -1).gather(-1, order)
    mids = 0.5 * (z[:, 1:] + z[:, :-1])
    deltas = z[:, 1:] - z[:, :-1]
    pts = o.unsqueeze(1) + mids.unsqueeze(-1) * d.unsqueeze(1)                  # (R, S, 3)
    sdf, grad, feat = model.sdf.with_gradient(pts, create_graph=train)
    cos = (grad * d.unsqueeze(1)).sum(-1)
    alpha = neus_alpha(sdf, cos, deltas, model.sharpness(), cos_anneal)
    inside = (pts.norm(dim=-1) < 1.0).to(alpha.dtype)
    alpha = alpha * inside * hit.unsqueeze(-1).to(alpha.dtype)
    w = composite_weights(alpha)
    normal = grad / grad.norm(dim=-1, keepdim=True).clamp_min(1e-6)
    rgb_pts = model.color(pts, normal, d.unsqueeze(1).expand_as(pts), feat)
    opacity = w.sum(-1)
    rgb = (w.unsqueeze(-1) * rgb_pts).sum(1)
    if model.background is not None:
        rgb = rgb + (1.0 - opacity).clamp_min(0).unsqueeze(-1) * model.background(o, d, far, cfg.background_samples,
                                                                                  generator, perturb=train)
    depth = (w * mids).sum(-1) / opacity.clamp_min(1e-6)
    return RenderedRays(rgb, opacity, grad, inside, depth)

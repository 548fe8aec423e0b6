"""The geometry stage's losses: colour, eikonal and mask (NeuS Sec. 3.4)."""
from __future__ import annotations

from dataclasses import dataclass

import torch
from jaxtyping import Float
from torch import Tensor

from .model import RenderedRays
from .networks import SDFNetwork


@dataclass(frozen=True)
class GeometryLoss:
    total: Tensor
    color: Tensor
    """L1 of log(1 + radiance): HDR images, highlights kept from dominating"""
    eikonal: Tensor
    mask: Tensor


def geometry_loss(out: RenderedRays, rgb: Tensor, mask: Tensor | None, extra_gradients: Tensor,
                  eikonal_weight: float, mask_weight: float, ray_weights: Tensor | None = None) -> GeometryLoss:
    """``rgb`` (R, 3) target colours; ``mask`` (R,) bool or None; ``extra_gradients`` (M, 3): SDF
    gradients at points spread uniformly in the sphere (the eikonal term holds everywhere, not only
    along rays); ``ray_weights`` (R,): importance weights of the rays for the mask loss (rays drawn
    from a density other than uniform over the pixels), None: all equal. The colour loss is the
    mean over the masked rays either way (uniform over the masked pixels by construction)."""
    err = (torch.log1p(out.rgb.clamp_min(0)) - torch.log1p(rgb.clamp_min(0))).abs().sum(-1)
    if mask is not None:
        m = mask.to(err.dtype)
        l_color = (err * m).sum() / m.sum().clamp_min(1.0)
        o = out.opacity.clamp(1e-3, 1 - 1e-3)
        bce = torch.nn.functional.binary_cross_entropy(o, m, reduction="none")
        l_mask = bce.mean() if ray_weights is None else (bce * ray_weights).sum() / ray_weights.sum()
    else:
        l_color = err.mean()
        l_mask = err.new_zeros(())
    g = out.gradient.norm(dim=-1)
    inside = out.inside
    l_ray = ((g - 1.0).square() * inside).sum() / inside.sum().clamp_min(1.0)
    l_eik = 0.5 * (l_ray + (extra_gradients.norm(dim=-1) - 1.0).square().mean())
    total = l_color + eikonal_weight * l_eik + mask_weight * l_mask
    return GeometryLoss(total, l_color, l_eik, l_mask)


def level_set_area(sdf: Float[Tensor, " M"], tau: float) -> Tensor:
    """Mean of ``exp(-tau |f(u)|)`` over SDF values at points uniform in a region of volume ``V``: for
    an exact distance and large ``tau``, ``(2 / tau) A / V`` with ``A`` the area of the zero level set
    inside the region (the minimal-surface prior)."""
    return torch.exp(-tau * sdf.abs()).mean()


def normal_variation(sdf: SDFNetwork, x: Float[Tensor, "N 3"], radius: float, generator: torch.Generator) -> Tensor:
    """Mean ``|n(x) - n(x + t)|_1`` over the points, ``n`` the SDF's unit gradient and ``t`` a Gaussian
    step of std ``radius`` projected onto the tangent plane at ``x`` (so the prior smooths along the
    surface, not across thin walls); zero for no points."""
    if len(x) == 0:
        return x.new_zeros(())
    _, g, _ = sdf.with_gradient(x, create_graph=True)
    n = g / g.norm(dim=-1, keepdim=True).clamp_min(1e-6)
    nd = n.detach()
    t = torch.randn(x.shape, generator=generator, device=x.device, dtype=x.dtype) * radius
    t = t - (t * nd).sum(-1, keepdim=True) * nd
    _, g2, _ = sdf.with_gradient(x + t, create_graph=True)
    n2 = g2 / g2.norm(dim=-1, keepdim=True).clamp_min(1e-6)
    return (n - n2).abs().sum(-1).mean()

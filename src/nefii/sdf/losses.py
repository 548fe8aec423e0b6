"""The geometry stage's losses: colour, eikonal and mask (NeuS Sec. 3.4)."""
from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from .model import RenderedRays


@dataclass(frozen=True)
class GeometryLoss:
    total: Tensor
    color: Tensor
    """L1 of log(1 + radiance): HDR images, highlights kept from dominating"""
    eikonal: Tensor
    mask: Tensor


def geometry_loss(out: RenderedRays, rgb: Tensor, mask: Tensor | None, extra_gradients: Tensor,
                  eikonal_weight: float, mask_weight: float) -> GeometryLoss:
    """``rgb`` (R, 3) target colours; ``mask`` (R,) bool or None; ``extra_gradients`` (M, 3): SDF
    gradients at points spread uniformly in the sphere (the eikonal term holds everywhere, not only
    along rays)."""
    err = (torch.log1p(out.rgb.clamp_min(0)) - torch.log1p(rgb.clamp_min(0))).abs().sum(-1)
    if mask is not None:
        m = mask.to(err.dtype)
        l_color = (err * m).sum() / m.sum().clamp_min(1.0)
        o = out.opacity.clamp(1e-3, 1 - 1e-3)
        l_mask = torch.nn.functional.binary_cross_entropy(o, m)
    else:
        l_color = err.mean()
        l_mask = err.new_zeros(())
    g = out.gradient.norm(dim=-1)
    inside = out.inside
    l_ray = ((g - 1.0).square() * inside).sum() / inside.sum().clamp_min(1.0)
    l_eik = 0.5 * (l_ray + (extra_gradients.norm(dim=-1) - 1.0).square().mean())
    total = l_color + eikonal_weight * l_eik + mask_weight * l_mask
    return GeometryLoss(total, l_color, l_eik, l_mask)

"""Differentiable first hits of an SDF (the implicit-function-theorem gradient of IDR, Yariv et al. 2020)
and a silhouette loss from the SDF's minimum along a ray: what refining a surface through a renderer needs.

Pure functions of an :class:`~nefii.sdf.networks.SDFNetwork` in normalised (unit-sphere) coordinates.
"""
from __future__ import annotations

import torch
from jaxtyping import Bool, Float
from torch import Tensor

from .networks import SDFNetwork
from .volume import stratified_depths


@torch.no_grad()
def newton_along_ray(sdf: SDFNetwork, o: Float[Tensor, "R 3"], d: Float[Tensor, "R 3"], t: Float[Tensor, " R"],
                     iterations: int = 4) -> tuple[Float[Tensor, " R"], Float[Tensor, " R"]]:
    """``t`` moved to the SDF's zero along each unit ray by Newton steps ``t -= f / (grad f . d)`` from a
    nearby start (a hit on a slightly older mesh of the same SDF); returns the distances and ``|f|`` there.
    A step is skipped where the ray grazes the surface (``|grad f . d|`` below 0.05)."""
    for _ in range(iterations):
        f, grad, _ = sdf.with_gradient(o + t.unsqueeze(-1) * d, create_graph=False)
        slope = (grad * d).sum(-1)
        ok = slope.abs() > 0.05
        t = torch.where(ok, t - f / torch.where(ok, slope, torch.ones_like(slope)), t)
    return t, sdf.sdf(o + t.unsqueeze(-1) * d).abs()


def implicit_hit(sdf: SDFNetwork, o: Float[Tensor, "R 3"], d: Float[Tensor, "R 3"], t: Float[Tensor, " R"]
                 ) -> Float[Tensor, "R 3"]:
    """The hit point ``o + t d`` (``t`` a converged root, no gradient) as a function of the SDF's parameters:
    ``x(theta) = o + (t - f(x0; theta) / (grad f(x0) . d)) d``, the gradient of the hit by the implicit
    function theorem; its value is ``x0``'s (``f(x0) = 0``)."""
    x0 = (o + t.unsqueeze(-1) * d).detach()
    _, grad, _ = sdf.with_gradient(x0, create_graph=False)
    slope = (grad * d).sum(-1)
    slope = torch.where(slope.abs() < 0.05, torch.full_like(slope, -0.05), slope).detach()
    f = sdf.sdf(x0)
    return x0 - ((f - f.detach()) / slope).unsqueeze(-1) * d


def normal_at(sdf: SDFNetwork, x: Float[Tensor, "R 3"]) -> tuple[Float[Tensor, "R 3"], Float[Tensor, "R 3"]]:
    """The unit normal ``grad f / |grad f|`` at ``x`` and the raw gradient (for the eikonal term), both
    differentiable with respect to the SDF's parameters and to ``x`` (double backward)."""
    with torch.enable_grad():
        xg = x if x.requires_grad else x.detach().requires_grad_(True)
        (grad,) = torch.autograd.grad(sdf.sdf(xg).sum(), xg, create_graph=True)
    return grad / grad.norm(dim=-1, keepdim=True).clamp_min(1e-12), grad


def silhouette_loss(sdf: SDFNetwork, o: Float[Tensor, "R 3"], d: Float[Tensor, "R 3"], near: Float[Tensor, " R"],
                    far: Float[Tensor, " R"], mask: Bool[Tensor, " R"], samples: int, sharpness: float,
                    generator: torch.Generator | None = None) -> Tensor:
    """IDR's mask loss: ``BCE(sigmoid(-sharpness * min_t f(o + t d)), mask)`` with the minimum over
    ``samples`` stratified depths in ``[near, far]``: rays the mask says miss push the surface off them,
    rays it says hit pull it onto them. Mean over the rays, divided by ``sharpness`` as IDR does."""
    t = stratified_depths(near, far, samples, generator)                          # (R, S)
    f = sdf.sdf(o.unsqueeze(1) + t.unsqueeze(-1) * d.unsqueeze(1))                # (R, S)
    logit = -sharpness * f.min(-1).values
    return torch.nn.functional.binary_cross_entropy_with_logits(logit, mask.to(logit.dtype)) / sharpness
